"""R2D2 (`r2d2 image`) against WSClean's multiscale CLEAN on held-out 512 x 512 observations (VLA by default).

    python3 benches/vs_wsclean.py [--telescope vla|meerkat] [--skies 8] [--out bench-out/vs_wsclean] [--seed 900000]
                                  [--integration-s 300] [--series SERIES] [--threads 2]
                                  [--keep-data DIR] [--r2d2 target/release/r2d2] [--wsclean wsclean]
                                  [--robust R] [--superresolution SR] [--dr LOW HIGH]
                                  [--sky classic|extended|field-filling] [--truth-fwhm-px F]
                                  [--sky-fits FITS ... [--hours A,C]]

Settings a user chooses (issue 21's table): `--robust -1` / `--robust 1` (Briggs), `--superresolution
2` / `2.5`, `--dr 1e5 1e5`, `--size 1024`, and `--sky extended` (skies of extended emission:
textured lobes, spiral disks, halos and relics; test seeds 910000..) or `--sky field-filling`
(the same objects, one spanning the field inside a faint cocoon; 930000..), with `--truth-fwhm-px 2`
for those skies as imaged at a resolution of 2 pixels (real radio images used as truths are:
no texture finer than the data measure). The observations are
simulated at that setting (noise for its weighting, pixel from its SR) and every imager uses it:
WSClean `-weight briggs R` at the engine's pixel, `r2d2 image --robust R --superresolution SR`.

`--sky-fits FITS ...` benchmarks on skies of one's own (FITS images in Jy/pixel, --size square,
e.g. real radio images): each is observed by `r2d2 simulate --sky FITS` at the setting (its DR
drawn in --dr, the telescope's typical tracks or --hours, --integration-s) and scored as the
procedural skies are. The reference's example sky 3C353 (`data/3c353_gdth.fits` in
basp-group/R2D2-RI) is such test material: never trained or selected on.

Needs `wsclean` (Debian: apt-get install -y wsclean), GNU time at /usr/bin/time (apt package
`time`) and the Python packages in benches/requirements.txt (python-casacore, pyarrow, astropy,
numpy, matplotlib).

1. Held-out observations: `r2d2 trainset --telescope T --procedural K --seed 900000 --size 512
   --integration-s 300 --epsilon 1e-5 --parquet`, the project's 512 test recipe (seeds 900000..
   are never used for training or selection; `--telescope meerkat` draws MeerKAT's tracks at
   its preset's integration time). Each sample is a Parquet table (vis/NNNNN.parquet),
   its true sky (vis/NNNNN.sky.fits, Jy/pixel) and a samples.json row (dynamic range, ...).
   With --keep-data DIR the data are made once in DIR and reused.
2. Each table is also written as a MeasurementSet by the engine's converter (`r2d2 convert`):
   one row per (time, antenna1, antenna2), the distinct frequencies as channels of one
   spectral window, XX and YY both the table's Stokes I visibility with its weight, so that
   WSClean's Stokes I = (XX + YY) / 2 is the table's visibility. Round trip: WSClean's natural-weighted dirty image of the MS (-weight natural
   -niter 0) is compared with `r2d2 dirty --weighting natural` of the Parquet table at the
   same pixel scale; the relative difference is reported (and must be small).
3. Imaging (each under /usr/bin/time -v for wall time and peak RSS, --threads cores):
   - WSClean with the paper's multiscale CLEAN command (Aghabiglou et al. 2024, section
     "Benchmark algorithms & parameter choice", footnote: `wsclean -niter 2000000 -weight
     briggs 0 -j 1 -multiscale -mgain 0.8 -gain 0.1 -auto-threshold 0.5 -auto-mask 1.5
     -padding 2`), with -j THREADS, -size 512 512 and the engine's pixel scale. Scored: the
     restored image divided by the restoring beam's area in pixels (the paper's comparison,
     Jy/beam -> Jy/pixel) and the model image.
   - `r2d2 image OBS.parquet --size 512 --truth SKY.fits` (the series `r2d2 image` chooses for
     512 unless --series is given) and `r2d2 image --step clean` (the built-in Hogbom CLEAN:
     restored image / beam area, and model).
4. Scores against the truth with the project's definitions (training/r2d2train/common.py):
   SNR, logSNR (a = the sample's dynamic range from samples.json, rlog with each image's own
   peak), residual ratio ||residual|| / ||dirty|| from each imager's own residual and dirty
   images. Orientation is asserted per sky: the cross-correlation of the truth with each
   method's image peaks at zero shift.
5. Writes OUT/vs_wsclean.json (per sky and means, commands, versions), OUT/vs_wsclean.md
   (the table) and OUT/vs_wsclean.png (truth | R2D2 | WSClean restored/beam | engine CLEAN
   restored/beam for up to three skies, one log colour scale). Every imager's products and log
   are kept in OUT/work/NNNNN/ (the MeasurementSet too with --keep-ms).
"""

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

# The paper's WSClean command (footnote in "Benchmark algorithms & parameter choice"), without
# -j (set from --threads), -size, -scale, -name (set per observation) and the robustness
# (`-weight briggs R`, R from --robust; the paper's is 0).
PAPER_WSCLEAN = ["-niter", "2000000", "-multiscale", "-mgain", "0.8", "-gain", "0.1",
                 "-auto-threshold", "0.5", "-auto-mask", "1.5", "-padding", "2"]
MJD_OFFSET_S = 58849.0 * 86400.0  # 2020-01-01: the tables' times are seconds from the start
SPEED_OF_LIGHT = 299792458.0


def log(msg):
    print(msg, file=sys.stderr, flush=True)


def run(cmd, cwd=None, timed=False, logfile=None):
    """Run cmd (under /usr/bin/time -v if timed); returns (stdout + stderr, wall s, peak MB). With
    `logfile` the output goes there as it comes (a run that hangs shows where)."""
    full = (["/usr/bin/time", "-v"] if timed else []) + [str(c) for c in cmd]
    t = time.time()
    if logfile:
        with open(logfile, "w") as f:
            f.write(" ".join(full) + "\n")
            f.flush()
            code = subprocess.run(full, cwd=cwd, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL).returncode
        with open(logfile) as f:
            text = f.read()
    else:
        out = subprocess.run(full, cwd=cwd, capture_output=True, text=True, stdin=subprocess.DEVNULL)
        code, text = out.returncode, out.stdout + out.stderr
    wall = time.time() - t
    if code != 0:
        sys.exit(f"failed ({code}): {' '.join(full)}\n{text[-4000:]}")
    peak = None
    if timed:
        m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", text)
        peak = int(m.group(1)) / 1024 if m else None
        m = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([0-9:.]+)", text)
        if m:
            wall = sum(float(p) * 60 ** i for i, p in enumerate(reversed(m.group(1).split(":"))))
    return text, wall, peak


# ---------------------------------------------------------------- FITS
def read_fits(path):
    from astropy.io import fits
    with fits.open(path) as hdul:
        data = np.asarray(hdul[0].data, dtype=np.float64)
        header = hdul[0].header.copy()
    while data.ndim > 2:
        data = data[0]
    return data, header


def beam_area_pixels(header):
    """Area of the restoring beam (peak-1 Gaussian) in pixels: pi bmaj bmin / (4 ln 2) / pixel^2."""
    bmaj, bmin, pixel = header["BMAJ"], header["BMIN"], abs(header["CDELT2"])
    assert bmaj > 0 and bmin > 0, "no restoring beam in the header"
    return math.pi * bmaj * bmin / (4 * math.log(2)) / pixel ** 2


# ---------------------------------------------------------------- metrics (training/r2d2train/common.py)
def snr(est, truth):
    return 20 * np.log10(np.linalg.norm(truth) / np.linalg.norm(truth - est))


def rlog(x, a):
    x = np.clip(x, 0, None)
    peak = max(x.max(), 1e-300)
    return peak * np.log1p(a * x / peak) / np.log(a)


def log_snr(est, truth, a):
    return snr(rlog(est, a), rlog(truth, a))


def residual_ratio(r, dirty):
    return float(np.linalg.norm(r) / np.linalg.norm(dirty))


def xcorr_shift(a, b):
    """Integer shift (dy, dx) at the peak of the circular cross-correlation of a and b."""
    c = np.fft.irfft2(np.fft.rfft2(a) * np.conj(np.fft.rfft2(b)), s=a.shape)
    dy, dx = np.unravel_index(np.argmax(c), c.shape)
    n0, n1 = a.shape
    return (int((dy + n0 // 2) % n0 - n0 // 2), int((dx + n1 // 2) % n1 - n1 // 2))


# ---------------------------------------------------------------- MeasurementSet
def read_table(path):
    import pyarrow.parquet as pq
    t = pq.read_table(path)
    meta = {k.decode(): v.decode() for k, v in (pq.ParquetFile(path).metadata.metadata or {}).items()
            if not k.startswith(b"ARROW:")}
    cols = {name: t.column(name).to_numpy() for name in t.column_names}
    return cols, meta


def table_samples(cols):
    """A table's samples: count, distinct frequencies (the channels), each sample's channel,
    weight (default 1), flag (default false) and complex visibility (also tests/make_ms.py)."""
    n = len(cols["u"])
    freq = cols["frequency"].astype(np.float64)
    chans = np.unique(freq)
    ch = np.searchsorted(chans, freq)
    weight = cols["weight"].astype(np.float64) if "weight" in cols else np.ones(n)
    flag = cols["flag"].astype(bool) if "flag" in cols else np.zeros(n, bool)
    vis = cols["vis_re"].astype(np.float64) + 1j * cols["vis_im"].astype(np.float64)
    return n, chans, ch, weight, flag, vis


def convert_ms(r2d2, parquet, ms):
    """The table as a MeasurementSet, by the engine's converter (`r2d2 convert`): one row per
    (time, antenna1, antenna2), XX and YY both the table's Stokes I visibility and weight."""
    if os.path.exists(ms):
        shutil.rmtree(ms)
    text, _, _ = run([r2d2, "convert", parquet, ms])
    m = re.search(r"wrote (\d+) samples as (\d+) rows x (\d+) channels", text)
    if not m:
        sys.exit(f"r2d2 convert {parquet}: unexpected report: {text[-500:]}")
    return {"samples": int(m.group(1)), "rows": int(m.group(2)), "channels": int(m.group(3))}


# ---------------------------------------------------------------- the benchmark
def make_data(args, r2d2, data_dir):
    info = os.path.join(data_dir, "trainset.json")
    if os.path.exists(info):
        with open(info) as f:
            have = json.load(f)
        wanted = (args.telescope, args.seed, args.size, args.superresolution, args.robust, list(args.dr), args.sky, args.truth_fwhm_px)
        found = (have.get("telescope"), have.get("seed"), have.get("size"), have.get("superresolution"),
                 have.get("weighting", {}).get("robust"), have.get("dynamic_range"), have.get("sky") or "classic",
                 have.get("truth_fwhm_px"))
        if args.integration_s is not None and have.get("integration_s") != args.integration_s:
            found = None
        if found == wanted and have.get("samples", 0) >= args.skies and os.path.isdir(os.path.join(data_dir, "vis")):
            log(f"reusing {have['samples']} observations in {data_dir}")
            return
    log(f"simulating {args.skies} observations into {data_dir} ...")
    os.makedirs(os.path.dirname(os.path.abspath(data_dir)), exist_ok=True)
    integration = [] if args.integration_s is None else ["--integration-s", args.integration_s]
    smooth = [] if args.truth_fwhm_px is None else ["--truth-fwhm-px", args.truth_fwhm_px]
    _, wall, _ = run([r2d2, "trainset", "--telescope", args.telescope, "--procedural", args.skies, "--sky", args.sky, "--seed", args.seed,
                      "--size", args.size, *integration, *smooth, "--superresolution", args.superresolution,
                      f"--robust={args.robust:g}", "--dr-min", args.dr[0], "--dr-max", args.dr[1], "--epsilon", "1e-5",
                      "--threads", args.threads, "--parquet", "--out", data_dir])
    log(f"  {wall:.1f} s")


def make_data_fits(args, r2d2, data_dir):
    """Observations of the user's own skies (--sky-fits: FITS images in Jy/pixel, e.g. real radio
    images), simulated by `r2d2 simulate` at the benchmark's setting, one per file; the truth
    is written beside each table with the engine's pixel grid. The sky is observed on the grid
    the setting's --superresolution makes: a file's own pixel and centre are dropped (the
    simulation would keep them, and the images made at the setting's pixel would not match
    the truth). Always made afresh: the files may change."""
    from astropy.io import fits
    vis = os.path.join(data_dir, "vis")
    if os.path.isdir(vis):
        shutil.rmtree(vis)
    os.makedirs(vis)
    rng = np.random.default_rng(args.seed)
    samples = []
    for k, path in enumerate(args.sky_fits):
        truth, header = read_fits(path)
        if truth.shape != (args.size, args.size):
            sys.exit(f"{path}: a {truth.shape[1]} x {truth.shape[0]} image; this benchmark images --size {args.size}")
        if not np.isfinite(truth).all() or truth.min() < 0 or truth.max() <= 0:
            sys.exit(f"{path}: expected a finite, non-negative sky with emission (Jy/pixel)")
        dr = float(np.exp(rng.uniform(np.log(args.dr[0]), np.log(args.dr[1]))))
        obs = os.path.join(vis, f"{k:05d}.parquet")
        hours = [] if args.hours is None else ["--hours", args.hours]
        integration = [] if args.integration_s is None else ["--integration-s", args.integration_s]
        pixels_only = os.path.join(vis, f"{k:05d}.input.fits")
        fits.PrimaryHDU(truth.astype(np.float64), header=fits.Header([("BUNIT", "JY/PIXEL")])).writeto(pixels_only, overwrite=True)
        text, _, _ = run([r2d2, "simulate", "--sky", pixels_only, "--telescope", args.telescope, *hours, *integration,
                          "--dr", f"{dr:.6g}", "--superresolution", args.superresolution, f"--robust={args.robust:g}",
                          "--epsilon", "1e-5", "--seed", args.seed + k, "--threads", args.threads, "--out", obs])
        m = re.search(r"(\d+) visibilities", text)
        # The engine's pixel grid for the truth: its dirty image's header (the scale and centre).
        run([r2d2, "dirty", obs, "--size", args.size, "--weighting", "natural", "--superresolution", args.superresolution,
             "--name", os.path.join(vis, "grid"), "--threads", args.threads])
        _, grid = read_fits(os.path.join(vis, "grid-dirty.fits"))
        for f in ("grid-dirty.fits", "grid-psf.fits"):
            if os.path.exists(os.path.join(vis, f)):
                os.remove(os.path.join(vis, f))
        grid["BUNIT"] = "JY/PIXEL"
        fits.PrimaryHDU(truth.astype(np.float32), header=grid).writeto(os.path.join(vis, f"{k:05d}.sky.fits"), overwrite=True)
        samples.append({"index": k, "source": os.path.basename(path), "seed": args.seed + k, "dynamic_range": dr,
                        "points": int(m.group(1)) if m else None, "pixel_arcsec": abs(grid["CDELT2"]) * 3600})
    with open(os.path.join(data_dir, "samples.json"), "w") as f:
        json.dump(samples, f, indent=1)


def fits_pixel_arcsec(path):
    _, h = read_fits(path)
    return abs(h["CDELT2"]) * 3600, h


def image_wsclean(args, ms, work, scale_arcsec):
    cmd = [args.wsclean, "-size", args.size, args.size, "-scale", f"{scale_arcsec:.10g}asec", "-j", args.threads,
           "-weight", "briggs", f"{args.robust:g}", *PAPER_WSCLEAN, "-name", "ws", ms]
    text, wall, peak = run(cmd, cwd=work, timed=True, logfile=os.path.join(work, "ws.log"))
    return cmd, wall, peak, text


def image_wsclean_r2d2(args, ms, work, scale_arcsec):
    """WSClean with the R2D2 deconvolver (`python -m r2d2_imaging.wsclean`, the Python package
    installed for --python): the engine's pixel and weighting, the paper command's padding."""
    cmd = [args.python, "-m", "r2d2_imaging.wsclean", "-size", args.size, args.size, "-scale", f"{scale_arcsec:.10g}asec",
           "-j", args.threads, "-weight", "briggs", f"{args.robust:g}", "-padding", "2", *args.wsclean_r2d2_args.split(), "-name", "wsr2d2", ms]
    text, wall, peak = run(cmd, cwd=work, timed=True, logfile=os.path.join(work, "wsr2d2.log"))
    return cmd, wall, peak, text


def image_r2d2(args, r2d2, obs, sky, work, name, step):
    cmd = [r2d2, "image", obs, "--size", args.size, "--name", name, "--truth", sky, "--threads", args.threads,
           f"--robust={args.robust:g}", "--superresolution", args.superresolution]
    if step:
        cmd += ["--step", step]
    text, wall, peak = run(cmd, cwd=work, timed=True, logfile=os.path.join(work, name + ".log"))
    return cmd, wall, peak, text


def score(est, truth, a, resid, dirty):
    return {"snr_db": float(snr(est, truth)), "logsnr_db": float(log_snr(est, truth, a)),
            "residual_ratio": residual_ratio(resid, dirty)}


def check_orientation(truth, est, label):
    """The cross-correlation with the truth peaks within a pixel of zero shift (a flipped, transposed
    or offset image does not; a poor image of a compact source may peak one pixel off)."""
    shift = xcorr_shift(truth, est)
    assert max(abs(shift[0]), abs(shift[1])) <= 1, \
        f"{label}: image shifted by {shift} pixels from the truth (flipped or misplaced?)"
    return shift


METHODS = [
    ("r2d2", "R2D2 (`r2d2 image`)"),
    ("wsclean_restored", "WSClean multiscale, restored / beam"),
    ("wsclean_model", "WSClean multiscale, model"),
    ("clean_restored", "engine CLEAN, restored / beam"),
    ("clean_model", "engine CLEAN, model"),
]
TIMED = {"r2d2": "r2d2", "wsclean_restored": "wsclean", "wsclean_model": "wsclean",
         "clean_restored": "clean", "clean_model": "clean", "wsclean_r2d2": "wsclean_r2d2"}
#: With --wsclean-r2d2: WSClean with the R2D2 deconvolver, scored by its model.
WSCLEAN_R2D2 = ("wsclean_r2d2", "WSClean + R2D2 deconvolver (`r2d2-wsclean`), model")


def one_sky(args, r2d2, data_dir, k, sample, out):
    obs = os.path.abspath(os.path.join(data_dir, "vis", f"{k:05d}.parquet"))
    sky = os.path.abspath(os.path.join(data_dir, "vis", f"{k:05d}.sky.fits"))
    work = os.path.join(out, "work", f"{k:05d}")
    os.makedirs(work, exist_ok=True)
    ms = os.path.join(work, "obs.ms")
    truth, th = read_fits(sky)
    a = float(sample["dynamic_range"])
    rec = {"sky": k, "seed": sample.get("seed"), "dynamic_range": a, "points": sample.get("points"),
           "pixel_arcsec": sample.get("pixel_arcsec")}

    t = time.time()
    rec["ms"] = convert_ms(r2d2, obs, ms)
    rec["ms"]["seconds"] = time.time() - t

    # Round trip: natural-weighted dirty images of the Parquet table (engine) and the MS (WSClean).
    run([r2d2, "dirty", obs, "--size", args.size, "--weighting", "natural", "--superresolution", args.superresolution,
         "--name", "nat", "--threads", args.threads], cwd=work)
    scale, dh = fits_pixel_arcsec(os.path.join(work, "nat-dirty.fits"))
    assert abs(scale - abs(th["CDELT2"]) * 3600) < 1e-9 * scale, "engine dirty and truth differ in pixel size"
    # -padding 2 as in the paper's command (WSClean's default 1.2 is 4 % off at the image edges).
    run([args.wsclean, "-size", args.size, args.size, "-scale", f"{scale:.10g}asec", "-weight", "natural", "-niter", "0",
         "-padding", "2", "-j", args.threads, "-name", "wsnat", ms], cwd=work)
    d_engine, _ = read_fits(os.path.join(work, "nat-dirty.fits"))
    d_ws, wh = read_fits(os.path.join(work, "wsnat-dirty.fits"))
    assert abs(abs(wh["CDELT2"]) * 3600 - scale) < 1e-6 * scale and wh["CDELT1"] < 0
    rec["dirty_natural_rel_diff"] = float(np.linalg.norm(d_ws - d_engine) / np.linalg.norm(d_engine))
    rec["dirty_natural_shift"] = xcorr_shift(d_engine, d_ws)
    assert rec["dirty_natural_shift"] == (0, 0), f"sky {k}: WSClean's dirty image of the MS is shifted/flipped"
    assert rec["dirty_natural_rel_diff"] < 0.01, f"sky {k}: MS round trip differs by {rec['dirty_natural_rel_diff']:.3g}"

    runs = {}
    cmd, wall, peak, text = image_wsclean(args, ms, work, scale)
    runs["wsclean"] = {"command": " ".join(map(str, cmd)), "wall_s": wall, "peak_mb": peak}
    m = re.search(r"(\d+) major iterations were performed", text)
    runs["wsclean"]["major_iterations"] = int(m.group(1)) if m else None
    cmd, wall, peak, text = image_r2d2(args, r2d2, obs, sky, work, "r2d2", args.series)
    runs["r2d2"] = {"command": " ".join(map(str, cmd)), "wall_s": wall, "peak_mb": peak,
                    "series": sorted(set(re.findall(r"series '([^']+)' \(manifest", text))),
                    "series_log": [l.strip() for l in re.findall(r"[^\n]*(?:series|trained for)[^\n]*", text)][:4]}
    cmd, wall, peak, text = image_r2d2(args, r2d2, obs, sky, work, "clean", "clean")
    runs["clean"] = {"command": " ".join(map(str, cmd)), "wall_s": wall, "peak_mb": peak}
    if args.wsclean_r2d2:
        cmd, wall, peak, text = image_wsclean_r2d2(args, ms, work, scale)
        runs["wsclean_r2d2"] = {"command": " ".join(map(str, cmd)), "wall_s": wall, "peak_mb": peak,
                                "summary": re.findall(r"r2d2: series [^\n]*networks, kept[^\n]*", text)}
    rec["runs"] = runs

    img = lambda name: read_fits(os.path.join(work, name))
    images = {}
    x, _ = img("r2d2-model.fits")
    r, _ = img("r2d2-residual.fits")
    d, _ = img("r2d2-dirty.fits")
    images["r2d2"] = (x, r, d)
    # A CLEAN's two estimates, each scored with that imager's own residual and dirty image:
    # the restored image in Jy/pixel (divided by the beam area) and the model.
    for key, prefix in (("wsclean", "ws"), ("clean", "clean")):
        restored, header = img(f"{prefix}-image.fits")
        model, _ = img(f"{prefix}-model.fits")
        res, _ = img(f"{prefix}-residual.fits")
        dirt, _ = img(f"{prefix}-dirty.fits")
        rec[f"{key}_beam_pixels"] = beam_area_pixels(header)
        images[f"{key}_restored"] = (restored / rec[f"{key}_beam_pixels"], res, dirt)
        images[f"{key}_model"] = (model, res, dirt)
    if args.wsclean_r2d2:
        images["wsclean_r2d2"] = tuple(img(f"wsr2d2-{p}.fits")[0] for p in ("model", "residual", "dirty"))

    rec["scores"] = {}
    for key, (est, res, dirt) in images.items():
        assert est.shape == truth.shape, f"{key}: {est.shape} vs truth {truth.shape}"
        # A CLEAN model is a set of components: a poor one of a sparse sky can peak a few pixels
        # off in cross-correlation without being flipped; images are held to one pixel.
        s = score(est, truth, a, res, dirt)
        # An imager that diverged (its residual above its dirty image: worse than an empty model)
        # gives an image with no orientation to check; it is scored and marked as such.
        diverged = s["residual_ratio"] > 1
        if diverged:
            s["diverged"] = True
            print(f"  sky {k} {key}: diverged (residual ratio {s['residual_ratio']:.3g}); scored, orientation not checked")
        plain = key.endswith("_model") or diverged
        shift = xcorr_shift(truth, est) if plain else check_orientation(truth, est, f"sky {k} {key}")
        s["xcorr_shift"] = shift
        s.update({"wall_s": runs[TIMED[key]]["wall_s"], "peak_mb": runs[TIMED[key]]["peak_mb"]})
        rec["scores"][key] = s
    # The engine's own scoring of its R2D2 image (metrics.json) must agree with ours.
    mpath = os.path.join(work, "r2d2-metrics.json")
    if os.path.exists(mpath):
        with open(mpath) as f:
            engine_metrics = json.load(f)
        rec["engine_metrics_final"] = _final_metrics(engine_metrics)
        engine_snr = rec["engine_metrics_final"].get("snr")
        if engine_snr is not None:
            assert abs(engine_snr - rec["scores"]["r2d2"]["snr_db"]) < 0.05, \
                f"sky {k}: our SNR of the R2D2 image differs from the engine's {engine_snr:.3f} dB"
    return rec, {"truth": truth, **{key: v[0] for key, v in images.items()}}


def _final_metrics(m):
    """The snr/logsnr of the model an engine -metrics.json describes: the last iteration's, or
    where the divergence guard stopped the series, the kept iterate's (none for the empty
    model), with the stop recorded."""
    its = m.get("iterations") if isinstance(m, dict) else None
    if not (isinstance(its, list) and its):
        return {}
    stop = m.get("stop")
    kept = stop["kept_iteration"] if stop else its[-1].get("iteration")
    rows = [r for r in its if r.get("iteration") == kept]
    final = {k: rows[-1].get(k) for k in ("iteration", "snr", "logsnr", "residual_ratio") if k in rows[-1]} if rows else {"iteration": kept}
    if stop:
        final["stop"] = stop
    return final


def table_md(means, n):
    lines = [f"| method | SNR (dB) | logSNR (dB) | residual ratio | wall (s) | peak (MB) |",
             "|---|---|---|---|---|---|"]
    for key, label in METHODS + ([WSCLEAN_R2D2] if "wsclean_r2d2" in means else []):
        s = means[key]
        lines.append(f"| {label} | {s['snr_db']:.2f} | {s['logsnr_db']:.2f} | {s['residual_ratio']:.2e} | "
                     f"{s['wall_s']:.1f} | {s['peak_mb']:.0f} |")
    return "\n".join(lines)


def plot(path, panels, records, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = [("truth", "truth"), ("r2d2", "R2D2"), ("wsclean_restored", "WSClean restored / beam"),
            ("clean_restored", "engine CLEAN restored / beam")]
    if "wsclean_r2d2" in panels[0]:
        cols.append(("wsclean_r2d2", "WSClean + R2D2 deconvolver"))
    rows = len(panels)
    fig, axes = plt.subplots(rows, len(cols), figsize=(3.2 * len(cols) + 0.8, 3.3 * rows), squeeze=False)
    im = None
    for i, (pan, rec) in enumerate(zip(panels, records)):
        peak = pan["truth"].max()
        for j, (key, label) in enumerate(cols):
            ax = axes[i][j]
            v = np.log10(np.clip(pan[key] / peak, 1e-4, None))
            im = ax.imshow(v, origin="lower", cmap="inferno", vmin=-4, vmax=0, interpolation="nearest")
            heading = label if key == "truth" else f"{label}\n{rec['scores'][key]['snr_db']:.1f} / {rec['scores'][key]['logsnr_db']:.1f} dB"
            if key == "truth":
                heading += f"\nsky {rec['sky']}, DR {rec['dynamic_range']:.2g}"
            ax.set_title(heading, fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.subplots_adjust(left=0.02, right=0.88, bottom=0.03, top=1 - 0.75 / (3.3 * rows), wspace=0.04, hspace=0.25)
    cax = fig.add_axes([0.9, 0.1, 0.02, 0.8])
    cb = fig.colorbar(im, cax=cax)
    cb.set_label("log10(image / truth peak)")
    fig.suptitle(f"{title} (SNR / logSNR); north up, east left", fontsize=10, y=0.995)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def versions(r2d2, wsclean):
    out = {}
    try:
        out["wsclean"] = subprocess.run([wsclean, "-version"], capture_output=True, text=True).stdout.split("\n")[1].strip()
    except Exception:
        out["wsclean"] = None
    try:
        out["r2d2"] = subprocess.run([r2d2, "--version"], capture_output=True, text=True).stdout.strip()
        out["r2d2_info"] = subprocess.run([r2d2, "info"], capture_output=True, text=True).stdout.strip()
    except Exception:
        pass
    try:
        import casacore
        out["python-casacore"] = casacore.__version__
    except Exception:
        pass
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--skies", type=int, default=8)
    ap.add_argument("--seed", type=int, default=900000, help="first test seed (900000..: never trained or selected on)")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--telescope", default="vla", help="a telescope of data/telescopes/telescopes.yaml (vla, meerkat, ska-mid)")
    ap.add_argument("--integration-s", type=float, default=None,
                    help="default: 300 s for the VLA (the 512 test recipe), the telescope's training preset otherwise")
    ap.add_argument("--r2d2", default=os.path.join(REPO, "target", "release", "r2d2"))
    ap.add_argument("--wsclean", default="wsclean")
    ap.add_argument("--series", default=None, help="network series for `r2d2 image --step` (default: the one it chooses)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--keep-data", default=None, help="make the observations here once and reuse them")
    ap.add_argument("--plot-skies", type=int, default=3)
    ap.add_argument("--keep-ms", action="store_true", help="keep each sky's MeasurementSet (OUT/work/NNNNN/obs.ms)")
    ap.add_argument("--out", default="bench-out/vs_wsclean")
    ap.add_argument("--robust", type=float, default=0.0, help="Briggs robustness of the data's noise and of every imager")
    ap.add_argument("--superresolution", type=float, default=1.5, help="pixel = 1 / (SR 2 max_uv), for every imager")
    ap.add_argument("--dr", type=float, nargs=2, default=[1e3, 1e5], metavar=("LOW", "HIGH"),
                    help="target dynamic ranges of the skies (log-uniform)")
    ap.add_argument("--sky", choices=["classic", "extended", "field-filling"], default="classic",
                    help="procedural skies (classic), extended emission (test seeds 910000.. by default) or "
                         "field-filling extended emission in a faint cocoon (930000..)")
    ap.add_argument("--truth-fwhm-px", type=float, default=None,
                    help="convolve each true sky with a Gaussian of this FWHM (pixels): a sky as imaged at that resolution")
    ap.add_argument("--sky-fits", nargs="+", default=None, metavar="FITS",
                    help="image these skies (FITS, Jy/pixel, --size square, e.g. real radio images) instead of procedural ones: "
                         "each observed by `r2d2 simulate` at the setting, its DR drawn in --dr")
    ap.add_argument("--wsclean-r2d2", action="store_true",
                    help="also image with WSClean and the R2D2 deconvolver (`python -m r2d2_imaging.wsclean`, run by --python)")
    ap.add_argument("--wsclean-r2d2-args", default="", help="further WSClean options for --wsclean-r2d2 (e.g. '-use-wgridder')")
    ap.add_argument("--python", default=sys.executable, help="the Python with r2d2_imaging installed, for --wsclean-r2d2")
    ap.add_argument("--hours", default=None,
                    help="with --sky-fits: hours per array configuration (`r2d2 simulate --hours`, VLA A,C e.g. 5.5,1.1)")
    args = ap.parse_args()
    if args.integration_s is None and args.telescope == "vla":
        args.integration_s = 300.0
    if args.sky != "classic" and args.seed == 900000:
        args.seed = {"extended": 910000, "field-filling": 930000}[args.sky]

    r2d2 = os.path.abspath(args.r2d2)
    if not os.path.exists(r2d2):
        sys.exit(f"{r2d2} not found: cargo build --release first")
    if shutil.which(args.wsclean) is None:
        sys.exit("wsclean not found (Debian: apt-get install -y wsclean)")
    if not os.path.exists("/usr/bin/time"):
        sys.exit("/usr/bin/time not found (Debian: apt-get install -y time)")
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    data_dir = os.path.abspath(args.keep_data or os.path.join(out, "data"))
    if args.sky_fits:
        args.skies = len(args.sky_fits)
        make_data_fits(args, r2d2, data_dir)
    else:
        make_data(args, r2d2, data_dir)
    with open(os.path.join(data_dir, "samples.json")) as f:
        samples = json.load(f)

    records, panels = [], []
    for k in range(args.skies):
        t = time.time()
        rec, pan = one_sky(args, r2d2, data_dir, k, samples[k], out)
        records.append(rec)
        if not args.keep_ms:
            shutil.rmtree(os.path.join(out, "work", f"{k:05d}", "obs.ms"), ignore_errors=True)
        if k < args.plot_skies:
            panels.append(pan)
        s = rec["scores"]
        log(f"sky {k} (DR {rec['dynamic_range']:.3g}, {rec['ms']['samples']} vis): "
            + ", ".join(f"{key} {s[key]['snr_db']:.1f}/{s[key]['logsnr_db']:.1f} dB" for key in s)
            + f"; MS round trip {rec['dirty_natural_rel_diff']:.2e}; {time.time() - t:.0f} s")

    means = {key: {m: float(np.mean([r["scores"][key][m] for r in records]))
                   for m in ("snr_db", "logsnr_db", "residual_ratio", "wall_s", "peak_mb")} for key in records[0]["scores"]}
    rt = [r["dirty_natural_rel_diff"] for r in records]
    series_log = sorted({l for r in records for l in r["runs"]["r2d2"]["series_log"]})
    series_used = sorted({s for r in records for s in r["runs"]["r2d2"]["series"]}) or [args.series or "?"]
    result = {
        "telescope": args.telescope, "skies": args.skies, "seed": args.seed, "size": args.size, "integration_s": args.integration_s,
        "threads": args.threads, "data": data_dir,
        "setting": {"robust": args.robust, "superresolution": args.superresolution, "dynamic_range": args.dr, "sky": args.sky,
                    "truth_fwhm_px": args.truth_fwhm_px},
        "trainset_command": f"r2d2 trainset --telescope {args.telescope} --procedural {args.skies} --sky {args.sky} --seed {args.seed} --size {args.size} "
                            f"{'' if args.truth_fwhm_px is None else f'--truth-fwhm-px {args.truth_fwhm_px:g} '}"
                            f"{'' if args.integration_s is None else f'--integration-s {args.integration_s:g} '}--superresolution {args.superresolution:g} "
                            f"--robust={args.robust:g} --dr-min {args.dr[0]:g} --dr-max {args.dr[1]:g} --epsilon 1e-5 --parquet --out {data_dir}",
        "wsclean_paper_command": "wsclean -niter 2000000 -weight briggs 0 -j 1 -multiscale -mgain 0.8 -gain 0.1 "
                                 "-auto-threshold 0.5 -auto-mask 1.5 -padding 2",
        "wsclean_command": records[0]["runs"]["wsclean"]["command"],
        "r2d2_command": records[0]["runs"]["r2d2"]["command"],
        "clean_command": records[0]["runs"]["clean"]["command"],
        "r2d2_series": series_used,
        "r2d2_series_log": series_log,
        "ms_polarisation": "XX and YY, both the table's Stokes I visibility and weight",
        "ms_round_trip_rel_diff": {"mean": float(np.mean(rt)), "max": float(np.max(rt))},
        "versions": versions(r2d2, args.wsclean),
        "means": means,
        "per_sky": records,
    }
    fits_names = ", ".join(os.path.basename(p) for p in args.sky_fits or [])
    if args.sky_fits:
        result["setting"]["sky"] = "fits"
        result["sky_fits"] = [os.path.basename(p) for p in args.sky_fits]
        del result["trainset_command"]
        result["simulate_command"] = (f"r2d2 simulate --sky FITS --telescope {args.telescope} "
                                      f"{'' if args.hours is None else f'--hours {args.hours} '}"
                                      f"{'' if args.integration_s is None else f'--integration-s {args.integration_s:g} '}"
                                      f"--dr D --superresolution {args.superresolution:g} --robust={args.robust:g} --epsilon 1e-5 --seed S")
    md = table_md(means, args.skies)
    integration = "the telescope's training preset" if args.integration_s is None else f"{args.integration_s:g} s"
    if args.sky_fits:
        sky_what = f"the skies {fits_names}"
        data_how = f"`r2d2 simulate`{'' if args.hours is None else f', {args.hours} h'}, integration {integration}, seeds {args.seed}.."
        title = f"{args.size} x {args.size} {args.telescope}, the skies of {fits_names}"
    else:
        sky_what = (f"held-out {args.sky} skies{'' if args.truth_fwhm_px is None else f' smoothed to {args.truth_fwhm_px:g} px FWHM'}, "
                    f"seeds {args.seed}..{args.seed + args.skies - 1}")
        data_how = f"`r2d2 trainset --procedural`, its training preset's tracks, integration {integration}"
        title = f"held-out {args.size} x {args.size} {args.telescope} {args.sky} skies" + ("" if args.truth_fwhm_px is None else f" (smoothed to {args.truth_fwhm_px:g} px)")
    header = (f"{args.size} x {args.size} {args.telescope} observations of {sky_what} ({data_how}), Briggs {args.robust:g}, "
              f"SR {args.superresolution:g}, DR {args.dr[0]:g}..{args.dr[1]:g}; means over {args.skies} skies, {args.threads} threads each.\n\n")
    warned = [l for l in series_log if "WARN" in l]
    footer = (f"\n\nR2D2 series: {', '.join(series_used)}{' (' + warned[0].split('] ', 1)[-1] + ')' if warned else ''}. "
              f"MS round trip (WSClean natural dirty of the MS vs `r2d2 dirty` of the Parquet): relative difference "
              f"{np.mean(rt):.2e} mean, {np.max(rt):.2e} max.\n")
    with open(os.path.join(out, "vs_wsclean.json"), "w") as f:
        json.dump(result, f, indent=1)
    with open(os.path.join(out, "vs_wsclean.md"), "w") as f:
        f.write(header + md + footer)
    plot(os.path.join(out, "vs_wsclean.png"), panels, records[:len(panels)], title)
    print(header + md + footer)


if __name__ == "__main__":
    main()
