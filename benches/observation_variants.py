#!/usr/bin/env python3
"""A telescope's series on observations its training did not draw, beside the built-in CLEAN.

    python3 benches/observation_variants.py [--telescope meerkat] [--seeds 920000 920001]
        [--variants base60 short2h uhf dec10 flag30 track12h base8] [--out bench-out/variants]
        [--r2d2 target/release/r2d2]

Each variant is `r2d2 simulate --telescope T --sky procedural:SEED --seed SEED` with the
options below (the telescope's typical observation fills in the rest; the visibilities are
predicted with the w-term by the imaging's rule), imaged at 512 x 512 by `r2d2 image` (`auto`:
the series trained for the telescope) and by `r2d2 image --step clean --auto-threshold 3
--mgain 0.8` (WSClean's usual stopping rule). Scored against the simulated sky with the
project's definitions (benches/vs_wsclean.py): the series' model, CLEAN's restored image
divided by the beam area. Seeds 920000.. are used by nothing else (training 1000.. and
100000.., validation 500000.., test 900000..).

The variants (MeerKAT's training draws 8..12 h tracks at dec -60..0, 60 s samples, L band):
  base60    the typical observation at 60 s samples (training's sampling)
  base8     the typical observation as MeerKAT records it: 8 s dumps (7x the samples)
  short2h   a 2 h track
  uhf       UHF band (544 MHz up)
  dec10     dec +10 (low in MeerKAT's sky)
  flag30    30 % of the samples flagged
  track12h  a 12 h track at dec -60
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np
from astropy.io import fits

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from vs_wsclean import beam_area_pixels, log_snr, snr  # noqa: E402

VARIANTS = {
    "base60": ["--integration-s", "60"],
    "base8": [],
    "short2h": ["--hours", "2", "--integration-s", "60"],
    "uhf": ["--freq-mhz", "544", "--integration-s", "60"],
    "dec10": ["--dec", "10", "--integration-s", "60"],
    "flag30": ["--flag-fraction", "0.3", "--integration-s", "60"],
    "track12h": ["--hours", "12", "--dec", "-60", "--integration-s", "60"],
}


def run(cmd, cwd):
    t = time.time()
    p = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"{' '.join(map(str, cmd))} failed ({p.returncode}):\n{p.stderr[-2000:]}")
    return time.time() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--telescope", default="meerkat")
    ap.add_argument("--seeds", type=int, nargs="+", default=[920000, 920001])
    ap.add_argument("--variants", nargs="+", default=["base60", "short2h", "uhf", "dec10", "flag30", "track12h"],
                    choices=sorted(VARIANTS))
    ap.add_argument("--out", default="bench-out/variants")
    ap.add_argument("--r2d2", default="target/release/r2d2")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    r2d2 = os.path.abspath(args.r2d2)
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for v in args.variants:
        for seed in args.seeds:
            n = f"{v}-{seed}"
            if not os.path.exists(os.path.join(args.out, f"{n}.parquet")):
                run([r2d2, "simulate", "--telescope", args.telescope, "--sky", f"procedural:{seed}", "--seed", seed,
                     "--threads", args.threads, "--out", f"{n}.parquet", *VARIANTS[v]], args.out)
            common = ["--size", "512", "--threads", args.threads, "--truth", f"{n}.sky.fits"]
            t_series = run([r2d2, "image", f"{n}.parquet", "--name", f"{n}-r2d2", *common], args.out)
            t_clean = run([r2d2, "image", f"{n}.parquet", "--name", f"{n}-clean", "--step", "clean", "--niter", "1000000",
                           "--auto-threshold", "3", "--mgain", "0.8", *common], args.out)
            at = lambda s: os.path.join(args.out, s)  # noqa: E731
            truth = fits.getdata(at(f"{n}.sky.fits")).squeeze().astype(np.float64)
            metrics = json.load(open(at(f"{n}-r2d2-metrics.json")))
            model = fits.getdata(at(f"{n}-r2d2-model.fits")).squeeze()
            header = fits.getheader(at(f"{n}-clean-image.fits"))
            restored = fits.getdata(at(f"{n}-clean-image.fits")).squeeze() / beam_area_pixels(header)
            a = 1e4  # r2d2 simulate's default target dynamic range
            rows.append({"variant": v, "seed": seed, "series": metrics["settings"].get("step", {}).get("series"),
                         "r2d2_snr": snr(model, truth), "r2d2_logsnr": log_snr(model, truth, a),
                         "r2d2_residual_ratio": metrics["iterations"][-1]["residual_ratio"],
                         "r2d2_s": t_series, "warnings": metrics["warnings"],
                         "clean_snr": snr(restored, truth), "clean_logsnr": log_snr(restored, truth, a), "clean_s": t_clean})
            r = rows[-1]
            print(f"{n:18s} {r['series']}: {r['r2d2_snr']:6.2f} / {r['r2d2_logsnr']:6.2f} dB, ratio {r['r2d2_residual_ratio']:.4f},"
                  f" {t_series:5.1f} s, {len(r['warnings'])} warnings | CLEAN restored/beam {r['clean_snr']:6.2f} / "
                  f"{r['clean_logsnr']:6.2f} dB, {t_clean:5.1f} s", flush=True)
    with open(os.path.join(args.out, "variants.json"), "w") as f:
        json.dump(rows, f, indent=1)
    print("\n| variant | r2d2 SNR / logSNR (dB) | CLEAN restored SNR / logSNR (dB) | r2d2 s | CLEAN s |")
    print("|---|---|---|---|---|")
    for v in args.variants:
        rs = [r for r in rows if r["variant"] == v]
        mean = lambda k: np.mean([r[k] for r in rs])  # noqa: E731
        print(f"| {v} | {mean('r2d2_snr'):.2f} / {mean('r2d2_logsnr'):.2f} | {mean('clean_snr'):.2f} / {mean('clean_logsnr'):.2f}"
              f" | {mean('r2d2_s'):.1f} | {mean('clean_s'):.1f} |")


if __name__ == "__main__":
    main()
