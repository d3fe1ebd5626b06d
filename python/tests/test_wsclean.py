"""R2D2 as WSClean's deconvolver (`r2d2_imaging.wsclean`, WSClean's -python-deconvolution):
the Debian WSClean runs the engine's series, one network per major cycle, and its model is
`r2d2 image`'s on the same MS; a joined-channel run writes WSClean's products with R2D2
models."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import r2d2_imaging
from r2d2_imaging import wsclean as hook
from conftest import read_fits

SIZE = 128


def run(args, cwd, env=None):
    out = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True)
    assert out.returncode == 0, f"{args[0]} failed ({out.returncode}):\n{out.stdout[-4000:]}\n{out.stderr[-4000:]}"
    return out.stdout + out.stderr


@pytest.fixture(scope="module")
def ms(r2d2_bin, tmp_path_factory):
    """A VLA A+C track (6 h) at 128 x 128, as an MS; 4 channels over 20 %."""
    assert shutil.which("wsclean"), "WSClean is a test requirement (apt-get install wsclean; .ci/run installs it)"
    d = tmp_path_factory.mktemp("wsclean")
    run([r2d2_bin, "-q", "simulate", "--sky", "procedural:11", "--size", SIZE, "--hours", "5,1", "--integration-s", "120",
         "--nfreq", "4", "--freq-ratio", "1.2", "--no-rotation", "--seed", "11", "--out", "obs.parquet"], d)
    run([r2d2_bin, "-q", "convert", "obs.parquet", "obs.ms"], d)
    return d


def onnx_runtime() -> str:
    lib = r2d2_imaging._onnx_runtime()
    assert lib, "onnxruntime is a test requirement (tests/requirements.txt)"
    return lib


def wsclean(d, name, extra, env_words=""):
    env = dict(os.environ)
    env["R2D2_WSCLEAN"] = f"onnx_runtime={onnx_runtime()} {env_words}".strip()
    scale = f"{read_fits(d / 'r2d2-model.fits')[1]['CDELT2'] * 3600:.12f}asec"
    # The engine's grid and weighting (Briggs 0 on a weighting grid of twice the image),
    # gridded to 1e-6 at full size, as the other WSClean comparisons take them.
    args = ["wsclean", "-python-deconvolution", hook.HOOK, "-mgain", "0.8", "-niter", "1000000", "-nmiter", "200",
            "-size", SIZE, SIZE, "-scale", scale, "-weight", "briggs", "0", "-use-wgridder", "-wgridder-accuracy", "1e-6",
            "-padding", "2", "-no-small-inversion", "-j", "2", "-name", name, *extra, "obs.ms"]
    # The series `auto` takes at this size weighs on its trained field's grid, as `r2d2 image`
    # and the r2d2-wsclean command do (vla-r2d2-512 at 128: -super-weight 0.25).
    trained = hook.served_off_its_trained_size(int(SIZE))
    if trained:
        args[-1:-1] = ["-super-weight", f"{2 * int(SIZE) / (2 * trained):g}"]
    return run(args, d, env)


@pytest.fixture(scope="module")
def engine_run(ms, r2d2_bin):
    """`r2d2 image` on the MS's band, the series chosen for the size (vla-r2d2-512)."""
    env = dict(os.environ, ORT_DYLIB_PATH=onnx_runtime())
    log = run([r2d2_bin, "image", "obs.ms", "--size", SIZE, "--backend", "ort", "--name", "r2d2"], ms, env)
    return log


def test_the_hook_is_found_and_reads_wsclean_s_command_line():
    out = subprocess.run([sys.executable, "-m", "r2d2_imaging.wsclean"], capture_output=True, text=True, check=True)
    assert Path(out.stdout.strip()) == Path(hook.HOOK) and Path(hook.HOOK).is_file()
    job = hook.command_line_job(["-size", "128", "128", "-scale", "0.5asec", "-weight", "briggs", "-0.5", "-name", "x", "/"])
    assert job == {"scale_deg": 0.5 / 3600, "weighting": "briggs", "robust": -0.5, "ms": "/", "padding": 1.2, "super_weight": 1.0}
    job = hook.command_line_job(["-padding", "2", "-super-weight", "0.5", "-size", "64", "64"])
    assert (job["padding"], job["super_weight"]) == (2.0, 0.5)
    # WSClean weighs on padding x size / super-weight cells; the series on twice its field.
    assert hook.weighting_grid_problem(512, 2.0, 1.0, 512, "s") is None
    assert hook.weighting_grid_problem(1024, 2.0, 2.0, 512, "s") is None
    assert "-padding 2 -super-weight 1" in hook.weighting_grid_problem(512, 1.2, 1.0, 512, "s")
    assert "-padding 2 -super-weight 2" in hook.weighting_grid_problem(1024, 2.0, 1.0, 512, "s")
    assert hook.command_line_job(["-scale", "2amin", "-weight", "natural"])["scale_deg"] == pytest.approx(2 / 60)
    assert hook.command_line_job([])["weighting"] == "uniform", "WSClean's default weighting"
    with pytest.raises(ValueError, match="-scale"):
        hook.command_line_job(["-scale", "3parsec"])
    with pytest.raises(ValueError, match="R2D2_WSCLEAN"):
        hook._options("series")
    # The series' weighting grid (twice the image size: -padding 2) unless given.
    command = hook.wsclean_command(["-size", "512", "512", "obs.ms"])
    assert command[command.index("-padding") + 1] == "2" and "-use-wgridder" in command, command
    # Where auto's series runs off its trained size, WSClean weighs on its trained field: the
    # engine's own choice (vla-r2d2-512 serves 128 from its 512 field; at 32, which no series
    # serves, auto takes the nearest trained size, vla-r2d2-128's, off it).
    assert hook._native.auto_series(128) == ("vla-r2d2-512", 512)
    assert hook._native.auto_series(512) == ("vla-r2d2-512", None)
    assert hook._native.auto_series(32) == ("vla-r2d2-128", 128)
    assert hook.served_off_its_trained_size(128) == 512 and hook.served_off_its_trained_size(512) is None
    command = hook.wsclean_command(["-size", "32", "32", "obs.ms"])
    assert command[command.index("-super-weight") + 1] == "0.25", command
    command = hook.wsclean_command(["-size", "128", "128", "obs.ms"])
    assert command[command.index("-super-weight") + 1] == "0.25", command
    assert hook.weighting_grid_problem(128, 2.0, 0.25, 512, "s") is None
    assert "-super-weight" not in hook.wsclean_command(["-size", "512", "512", "obs.ms"])
    command = hook.wsclean_command(["-padding", "1.5", "-size", "512", "512", "obs.ms"])
    assert command.count("-padding") == 1 and command[command.index("-padding") + 1] == "1.5", command


def test_r2d2_wsclean_adds_super_weight_unless_a_series_is_named(monkeypatch):
    """`r2d2-wsclean` at 128 puts WSClean's weighting on the grid of `auto`'s series' trained
    field (vla-r2d2-512's), also for `series=auto`; not for a named series, and a command line
    it cannot read is left to WSClean to refuse."""
    monkeypatch.setenv("R2D2_WSCLEAN", "series=auto")
    assert "-super-weight" in hook.wsclean_command(["-size", "128", "128", "obs.ms"])
    monkeypatch.setenv("R2D2_WSCLEAN", "series=vla-r2d2-128")
    assert "-super-weight" not in hook.wsclean_command(["-size", "128", "128", "obs.ms"])
    monkeypatch.setenv("R2D2_WSCLEAN", "")
    command = hook.wsclean_command(["-size", "128", "128", "-padding", "two", "obs.ms"])
    assert "-super-weight" not in command and command[-1] == "obs.ms", command


def snr(truth, x):
    return 20 * np.log10(np.linalg.norm(truth) / np.linalg.norm(truth - x))


def test_wsclean_with_the_r2d2_deconvolver_gives_r2d2_image_s_model(ms, engine_run, r2d2_bin):
    truth, _ = read_fits(ms / "obs.sky.fits")
    # The series alone: WSClean's major cycles and the engine's residual update give the
    # same residual to the gridders' agreement, so each network sees the same input.
    env = dict(os.environ, ORT_DYLIB_PATH=onnx_runtime())
    run([r2d2_bin, "-q", "image", "obs.ms", "--size", SIZE, "--backend", "ort", "--no-final-clean", "--name", "r2d2-series"], ms, env)
    log = wsclean(ms, "ws-series", [], "final_clean=off")
    assert "r2d2: series vla-r2d2-512 (43 networks)" in log, log[-3000:]
    assert "43 networks, kept 43" in log, log[-3000:]
    ours, theirs = read_fits(ms / "r2d2-series-model.fits")[0], read_fits(ms / "ws-series-model.fits")[0]
    series_difference = np.linalg.norm(theirs - ours) / np.linalg.norm(ours)
    # With the final CLEAN: its minor cycles subtract the N x N PSF WSClean gives (the
    # engine's, the 2N x 2N one), so a component can land on a neighbouring pixel of a
    # near-tie; the fluxes and the precision are the same.
    log = wsclean(ms, "ws", [])
    assert "final CLEAN" in log, log[-3000:]
    ours, theirs = read_fits(ms / "r2d2-model.fits")[0], read_fits(ms / "ws-model.fits")[0]
    difference = np.linalg.norm(theirs - ours) / np.linalg.norm(ours)
    print(f"WSClean + R2D2 vs r2d2 image: the series' model {series_difference:.2e}, with the final CLEAN {difference:.2e} (relative L2); "
          f"SNR {snr(truth, theirs):.3f} dB vs {snr(truth, ours):.3f} dB; fluxes {theirs.sum():.5f} / {ours.sum():.5f} Jy")
    assert series_difference < 1e-5, f"the series' models differ by {series_difference:.2e}"
    assert difference < 5e-3, f"WSClean's R2D2 model differs from r2d2 image's by {difference:.2e}"
    assert abs(snr(truth, theirs) - snr(truth, ours)) < 0.05
    assert abs(theirs.sum() / ours.sum() - 1) < 1e-3


def test_a_joined_channel_run_writes_wsclean_s_products_with_r2d2_models(ms, engine_run):
    log = wsclean(ms, "wsj", ["-channels-out", "4", "-join-channels"])
    assert "4 channels joined" in log, log[-3000:]
    truth, _ = read_fits(ms / "obs.sky.fits")
    models = []
    for c in ["0000", "0001", "0002", "0003", "MFS"]:
        for product in ["model", "residual", "image"]:
            assert (ms / f"wsj-{c}-{product}.fits").is_file(), f"wsj-{c}-{product}.fits"
        models.append(read_fits(ms / f"wsj-{c}-model.fits")[0])
    # One series on the channels' weighted mean, its model each channel's (a flat spectrum,
    # as the simulated sky's): as precise as the whole band imaged as one channel.
    mfs = models[-1]
    single = read_fits(ms / "r2d2-model.fits")[0]
    spread = max(np.linalg.norm(m - mfs) / np.linalg.norm(mfs) for m in models[:-1])
    print(f"joined channels: MFS model SNR {snr(truth, mfs):.3f} dB (r2d2 image on the band: {snr(truth, single):.3f} dB); channel models within {spread:.1e} of it")
    assert spread < 1e-6
    assert abs(snr(truth, mfs) - snr(truth, single)) < 0.1


def test_what_the_deconvolver_cannot_do_is_said_on_wsclean_s_output(ms, engine_run):
    """WSClean 3.1 stops on a Python exception without printing it: the deconvolver says it."""
    env = dict(os.environ)
    for extra, words, expected in [
        (["-mgain", "1"], "", "give -mgain below 1"),
        ([], "series=no-such-series", "no-such-series: no model series of that name"),
        ([], "channels=some", "channels='some': expected joined or each"),
    ]:
        env["R2D2_WSCLEAN"] = words
        out = subprocess.run([sys.executable, "-m", "r2d2_imaging.wsclean", *extra, "-size", str(SIZE), str(SIZE), "-scale", "0.3asec", "-name", "bad", "obs.ms"],
                             cwd=ms, env=env, capture_output=True, text=True)
        assert out.returncode != 0, out.stdout[-2000:]
        assert f"r2d2: ERROR:" in out.stdout and expected in out.stdout, out.stdout[-3000:]


def test_a_series_the_guard_rejects_leaves_wsclean_the_model_of_clean_alone(ms, engine_run, r2d2_bin):
    """A series that diverges (the test models' Landweber at a gain far above 2 / ||D||) is
    rejected by the engine's guard inside WSClean as in `r2d2 image` (exit status 3 there):
    the final CLEAN then images the data from the empty model, so WSClean's model is
    `r2d2 image`'s, CLEAN alone's, not empty."""
    models = ms / "test-models"
    script = Path(__file__).resolve().parents[2] / "tests" / "make_test_models.py"
    run([sys.executable, script, models, "--gain", "1e4"], ms)
    series = models / "landweber"
    env = dict(os.environ, ORT_DYLIB_PATH=onnx_runtime())
    out = subprocess.run([str(r2d2_bin), "image", "obs.ms", "--size", str(SIZE), "--backend", "ort", "--step", str(series), "--name", "r2d2-rejected"],
                         cwd=ms, env=env, capture_output=True, text=True)
    assert out.returncode == 3, out.stderr[-3000:]
    assert "diverged" in out.stderr and "imaged the data from the empty model" in out.stderr, out.stderr[-3000:]
    # The test series was trained at 64 x 64: weights on its grid, as `r2d2 image` makes them.
    log = wsclean(ms, "ws-rejected", ["-super-weight", f"{SIZE / 64:g}"], f"series={series}")
    assert "diverged" in log and "final CLEAN images the data from the empty model" in log, log[-3000:]
    ours, theirs = read_fits(ms / "r2d2-rejected-model.fits")[0], read_fits(ms / "ws-rejected-model.fits")[0]
    assert np.count_nonzero(ours) > 0
    # CLEAN's components from the N x N PSF WSClean gives and from the engine's 2N x 2N one
    # land on neighbouring pixels of near-ties all over an extended sky: compared at about
    # the beam's resolution (a Gaussian of 2 pixels' sigma), with the fluxes.
    def smooth(image, sigma=2.0):
        f = np.fft.fftfreq(image.shape[0])
        kernel = np.exp(-2 * (np.pi * sigma) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
        return np.fft.ifft2(np.fft.fft2(image) * kernel).real
    difference = np.linalg.norm(smooth(theirs) - smooth(ours)) / np.linalg.norm(smooth(ours))
    print(f"a rejected series: WSClean + R2D2 vs r2d2 image, CLEAN alone's models within {difference:.2e} (relative L2, smoothed; "
          f"{np.linalg.norm(theirs - ours) / np.linalg.norm(ours):.2e} pixel by pixel), fluxes {theirs.sum():.5f} / {ours.sum():.5f} Jy")
    assert difference < 5e-3, f"WSClean's model differs from r2d2 image's by {difference:.2e}"
    assert abs(theirs.sum() / ours.sum() - 1) < 1e-3
