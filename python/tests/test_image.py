"""r2d2_imaging.image: one observation in this process, against `r2d2 image` on the same file."""

import json
import pickle
import subprocess
import threading
import time

import numpy as np
import pyarrow as pa
import pytest

import r2d2_imaging
from r2d2_imaging.dask import read_parquet
from conftest import read_fits

CLEAN = dict(size=128, step="clean", iterations=3, threads=1)


def cli_image(r2d2_bin, obs, prefix, *args):
    subprocess.run([str(r2d2_bin), "-q", "image", str(obs), "--name", str(prefix), *args], check=True)


@pytest.fixture(scope="module")
def clean_products(observations):
    return r2d2_imaging.image(observations[0], **CLEAN)


def test_arrays_header_and_metrics_are_the_cli_products(r2d2_bin, observations, clean_products, tmp_path):
    cli_image(r2d2_bin, observations[0], tmp_path / "cli/obs", "--size", "128", "--step", "clean", "--iterations", "3", "--threads", "1")
    p = clean_products
    assert p.id == observations[0].stem and p.size == 128
    for name in ["dirty", "psf", "model", "residual", "image"]:
        array = getattr(p, name)
        assert array.dtype == np.float32 and array.shape == (128, 128), name
        data, header = read_fits(tmp_path / f"cli/obs-{name}.fits")
        np.testing.assert_array_equal(array, data, err_msg=name)
    # The header's keywords are the FITS files' (astropy's reading of them).
    _, header = read_fits(tmp_path / "cli/obs-model.fits")
    for key, value in p.header.items():
        assert header[key] == pytest.approx(value) if isinstance(value, float) else header[key] == value, key
    for key in ["CTYPE1", "CRVAL1", "CDELT1", "CRPIX1", "CTYPE2", "CRVAL2", "CDELT2", "CRPIX2"]:
        assert key in p.header, key
    cli_metrics = json.loads((tmp_path / "cli/obs-metrics.json").read_text())
    assert [m["residual_ratio"] for m in p.metrics["iterations"]] == [m["residual_ratio"] for m in cli_metrics["iterations"]]
    assert p.metrics["image_size"] == 128 and len(p.metrics["iterations"]) == 3


def test_clean_controls_are_the_clis(r2d2_bin, observations, tmp_path):
    """WSClean's CLEAN controls reach the step as `r2d2 image`'s options do, and are refused
    with a network series."""
    controls = dict(niter=300, gain=0.1, mgain=0.8, auto_threshold=3.0)
    p = r2d2_imaging.image(observations[0], size=128, step="clean", threads=1, **controls)
    cli_image(r2d2_bin, observations[0], tmp_path / "cli/obs", "--size", "128", "--step", "clean", "--threads", "1",
              "--niter", "300", "--gain", "0.1", "--mgain", "0.8", "--auto-threshold", "3")
    data, _ = read_fits(tmp_path / "cli/obs-model.fits")
    np.testing.assert_array_equal(p.model, data)
    assert 0 < np.count_nonzero(p.model) <= 300
    with pytest.raises(r2d2_imaging.R2D2Error, match="invalid step: .* step clean"):
        r2d2_imaging.image(observations[0], size=128, threads=1, niter=300)
    # A series takes auto_threshold: its final CLEAN's depth, as the command line's.
    series = dict(size=128, threads=1, iterations=2, backend="tract")
    p = r2d2_imaging.image(observations[0], auto_threshold=1.0, **series)
    cli_image(r2d2_bin, observations[0], tmp_path / "cli/net", "--size", "128", "--threads", "1", "--iterations", "2",
              "--backend", "tract", "--auto-threshold", "1")
    data, _ = read_fits(tmp_path / "cli/net-model.fits")
    np.testing.assert_array_equal(p.model, data)
    default = r2d2_imaging.image(observations[0], **series)
    assert not np.array_equal(default.model, p.model)


def test_write_makes_exactly_the_cli_files(r2d2_bin, observations, clean_products, tmp_path):
    cli_image(r2d2_bin, observations[0], tmp_path / "cli/obs", "--size", "128", "--step", "clean", "--iterations", "3", "--threads", "1")
    clean_products.write(tmp_path / "py/obs")
    names = sorted(p.name for p in (tmp_path / "py").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "cli").iterdir())
    for name in names:
        if name.endswith(".fits"):
            a, ha = read_fits(tmp_path / "py" / name)
            b, hb = read_fits(tmp_path / "cli" / name)
            np.testing.assert_array_equal(a, b, err_msg=name)
            # HISTORY records the command line of a CLI run; the rest is the same.
            cards = lambda h: [(c.keyword, c.value, c.comment) for c in h.cards if c.keyword != "HISTORY"]
            assert cards(ha) == cards(hb), name
            assert any("r2d2-imaging" in str(h) for h in ha["HISTORY"]), name


def test_series_step_with_truth(r2d2_bin, observations, tmp_path):
    obs = observations[1]
    truth = obs.with_suffix(".sky.fits")
    p = r2d2_imaging.image(obs, size=128, truth=truth, threads=1)
    cli_image(r2d2_bin, obs, tmp_path / "obs", "--size", "128", "--truth", str(truth), "--threads", "1")
    # The restored image too (model at the fitted beam plus residual), as the CLI writes it.
    for name in ["dirty", "psf", "model", "residual", "image"]:
        np.testing.assert_array_equal(getattr(p, name), read_fits(tmp_path / f"obs-{name}.fits")[0], err_msg=name)
    snr = [m["snr"] for m in p.metrics["iterations"]]
    # One iteration per network (43: vla-r2d2-512 serves 128), then one per cycle of the final CLEAN on the residual, one
    # for its smoothed-residual steps and one where faint islands left its model.
    final_clean = p.metrics["settings"]["final_clean"]
    final_steps = final_clean["major_cycles"] + (final_clean["scale_steps"] > 0) + (final_clean["faint_islands"] > 0)
    assert p.metrics["settings"]["step"]["series"] == "vla-r2d2-512"
    assert len(snr) == 43 + final_steps and snr[-1] > snr[0] > 0, snr


def test_tables_in_memory_image_as_the_file(observations, clean_products):
    table = read_parquet(observations[0])
    for obs in [table, pa.RecordBatchReader.from_batches(table.schema, table.to_batches(max_chunksize=5000))]:
        p = r2d2_imaging.image(obs, id=observations[0].stem, **CLEAN)
        for name in ["dirty", "psf", "model", "residual", "image"]:
            np.testing.assert_array_equal(getattr(p, name), getattr(clean_products, name), err_msg=name)
    assert r2d2_imaging.image(table, **CLEAN).id == "table"


def test_products_pickle_whole(clean_products, tmp_path):
    copy = pickle.loads(pickle.dumps(clean_products))
    assert copy.id == clean_products.id and copy.header == clean_products.header and copy.metrics == clean_products.metrics
    for name in ["dirty", "psf", "model", "residual", "image"]:
        np.testing.assert_array_equal(getattr(copy, name), getattr(clean_products, name))
    copy.write(tmp_path / "a/obs")
    clean_products.write(tmp_path / "b/obs")
    for name in ["dirty", "model", "image"]:
        np.testing.assert_array_equal(read_fits(tmp_path / f"a/obs-{name}.fits")[0], read_fits(tmp_path / f"b/obs-{name}.fits")[0])


def test_every_option_of_r2d2_image_is_an_option_of_image(r2d2_bin, observations, tmp_path):
    """`image()` takes every option `r2d2 image --help` lists, by its name (a switch by what it
    turns: `final_clean=False` for `--no-final-clean`), parsed by the engine's one declaration:
    a bad value is refused naming the option as Python spells it."""
    import re
    help_text = subprocess.run([str(r2d2_bin), "image", "--help"], capture_output=True, text=True, check=True).stdout
    flags = set(re.findall(r"^\s+(?:-\w, )?--([a-z][a-z0-9-]*)", help_text, re.M)) - {"help", "verbose", "quiet"}
    assert len(flags) > 30, help_text
    names = set(r2d2_imaging.image_options())
    as_python = {flag.replace("-", "_").removeprefix("no_") for flag in flags}
    assert as_python == names, (as_python ^ names)
    with pytest.raises(r2d2_imaging.R2D2Error, match="invalid oversampling: invalid value 'lots' for 'oversampling'"):
        r2d2_imaging.image(observations[0], oversampling="lots", **CLEAN)
    with pytest.raises(r2d2_imaging.R2D2Error, match="invalid sise: .*size"):
        r2d2_imaging.image(observations[0], sise=64)
    with pytest.raises(r2d2_imaging.R2D2Error, match="invalid field: only a MeasurementSet"):
        r2d2_imaging.image(observations[0], field="0", **CLEAN)
    # The MS selection and the product prefix reach the engine (they were TypeErrors before).
    p = r2d2_imaging.image(observations[0], name=str(tmp_path / "named/obs"), final_clean=False, **CLEAN)
    assert (tmp_path / "named/obs-model.fits").is_file() and p.size == 128


def test_errors_are_r2d2_errors_with_the_engines_message(observations, tmp_path):
    with pytest.raises(r2d2_imaging.R2D2Error, match="missing.parquet"):
        r2d2_imaging.image(tmp_path / "missing.parquet", **CLEAN)
    with pytest.raises(r2d2_imaging.R2D2Error, match="weighting"):
        r2d2_imaging.image(observations[0], **{**CLEAN, "weighting": "brigs"})
    table = read_parquet(observations[0]).replace_schema_metadata({})
    with pytest.raises(r2d2_imaging.R2D2Error, match="phase_centre_ra_deg"):
        r2d2_imaging.image(table, **CLEAN)
    with pytest.raises(TypeError, match="Arrow table"):
        r2d2_imaging.image(42, **CLEAN)


def test_the_gil_is_released_while_the_engine_works(observations):
    """Python code runs in another thread while the engine images: with the GIL held it could
    not advance at all until the call returned."""
    done = threading.Event()
    ticks_during = []

    def count():
        n = 0
        while not done.is_set():
            n += 1
            time.sleep(0.001)
        ticks_during.append(n)

    counter = threading.Thread(target=count)
    counter.start()
    start = time.perf_counter()
    r2d2_imaging.image(observations[2], size=128, threads=1)
    seconds = time.perf_counter() - start
    done.set()
    counter.join()
    # At most one tick per millisecond; at least a quarter of them happened.
    assert ticks_during[0] > 0.25 * seconds * 1000 * 0.5, (ticks_during, seconds)


def test_engine_warnings_reach_pythons_warnings(observations):
    """A job outside the series' domain (Briggs +1 against a series trained at 0) is warned
    about through `warnings`, as the command line logs it, and recorded in the metrics."""
    with pytest.warns(r2d2_imaging.R2D2Warning, match=r"Briggs robust 1 is outside the series' range -1..0") as caught:
        p = r2d2_imaging.image(observations[2], size=128, robust=1.0, threads=1)
    assert any(str(w.message) in f"job {p.id}: {m}" for w in caught for m in p.metrics["warnings"])
    # vla-r2d2-512 (as near to Briggs 1 as vla-r2d2-128, and first), on its trained field's grid.
    assert p.metrics["settings"]["weighting"] == {"scheme": "briggs", "robust": 1.0, "grid_factor": 8.0}
    assert p.metrics["settings"]["step"]["series"] == "vla-r2d2-512"


def test_a_table_read_by_pyarrow_keeps_its_phase_centre(observations, clean_products):
    """pyarrow's read_table takes the metadata of the stored Arrow schema: the engine writes it
    there too, so what a Python user writes first images as the file does."""
    import pyarrow.parquet as pq
    table = pq.read_table(observations[0])
    assert b"phase_centre_ra_deg" in table.schema.metadata
    p = r2d2_imaging.image(table, id=observations[0].stem, **CLEAN)
    np.testing.assert_array_equal(p.dirty, clean_products.dirty)


def test_engine_log_records_reach_pythons_logging(observations, caplog):
    """The engine's log lines go to the `r2d2_imaging` logger at the level it is set to, and a
    job warning is also a WARNING record there."""
    with caplog.at_level("INFO", logger="r2d2_imaging"):
        r2d2_imaging.image(observations[2], **CLEAN)
    ours = [r for r in caplog.records if r.name.startswith("r2d2_imaging")]
    assert any("iteration 3 of 3" in r.getMessage() and r.levelname == "INFO" for r in ours), [r.getMessage() for r in ours]
    assert all(r.name == "r2d2_imaging" or r.name.startswith("r2d2_imaging.") for r in ours)
    caplog.clear()
    with caplog.at_level("WARNING", logger="r2d2_imaging"), pytest.warns(r2d2_imaging.R2D2Warning):
        r2d2_imaging.image(observations[2], size=128, robust=1.0, threads=1, iterations=1)
    messages = [r.getMessage() for r in caplog.records if r.name.startswith("r2d2_imaging")]
    assert any("Briggs robust 1 is outside" in m for m in messages), messages
    assert not any(r.levelname == "INFO" for r in caplog.records if r.name.startswith("r2d2_imaging")), "INFO is below the level set"


def test_series_are_found_without_environment_variables(tmp_path):
    """An installed package finds the series it ships: no R2D2_MODELS, run from elsewhere."""
    import os
    import sys
    env = {k: v for k, v in os.environ.items() if k != "R2D2_MODELS"}
    script = "import json, r2d2_imaging; i = r2d2_imaging.info(); print(json.dumps(i))"
    out = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, check=True, capture_output=True, text=True)
    info = json.loads(out.stdout)
    names = {s["name"]: s for s in info["series"]}
    assert {"vla-r2d2-512", "vla-r2d2-128", "vla-r2d2-512-broad"} <= set(names), info
    package = os.path.dirname(r2d2_imaging.__file__)
    assert names["vla-r2d2-512"]["path"].startswith(os.path.join(package, "models")), names["vla-r2d2-512"]
    shipped = len([f for f in os.listdir(names["vla-r2d2-512"]["path"]) if f.endswith(".onnx")])
    assert names["vla-r2d2-512"]["domain"]["telescopes"] == ["vla"] and names["vla-r2d2-512"]["networks"] == shipped > 0
    assert info["version"] == r2d2_imaging.__version__ and info["threads"] >= 1 and info["onnx_backend"]


def test_info_names_the_build_and_backend():
    i = r2d2_imaging.info()
    assert set(i) >= {"version", "gridder_simd", "threads", "onnx_backend", "model_dirs", "series"}
    assert "ONNX Runtime" in i["onnx_backend"] or "tract" in i["onnx_backend"], i


def test_channel_groups_return_every_groups_products(r2d2_bin, tmp_path):
    """`channels_out` (a MeasurementSet): a list of every group's products, then the whole
    band's with `join_channels`, each the files written at `name` (WSClean's names)."""
    obs = tmp_path / "obs.parquet"
    subprocess.run([str(r2d2_bin), "-q", "simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64",
                    "--nfreq", "2", "--freq-ratio", "1.2", "--seed", "3", "--out", str(obs)], check=True)
    subprocess.run([str(r2d2_bin), "-q", "convert", str(obs), str(tmp_path / "obs.ms")], check=True)
    every = r2d2_imaging.image(tmp_path / "obs.ms", size=64, step="clean", iterations=1, threads=1, channels_out=2,
                               join_channels=True, name=str(tmp_path / "out/obs"))
    assert [p.id for p in every] == ["obs-0000", "obs-0001", "obs-MFS"]
    for label, p in zip(["0000", "0001", "MFS"], every):
        data, header = read_fits(tmp_path / f"out/obs-{label}-model.fits")
        np.testing.assert_array_equal(p.model, data, err_msg=label)
    cube, header = read_fits(tmp_path / "out/obs-cube-image.fits")
    assert cube.shape == (2, 64, 64) and header["CTYPE3"] == "FREQ"
    one = r2d2_imaging.image(tmp_path / "obs.ms", size=64, step="clean", iterations=1, threads=1, channels_out=1)
    assert isinstance(one, r2d2_imaging.Products)
