#!/usr/bin/env python3
"""Compact-source fluxes of r2d2's model against WSClean's, in one run, on the compact fields of
benches/selfcal.py (30 point sources, 1e-3..1, and a small Gaussian; VLA A+C as
`r2d2 simulate` observes them, no gain errors).

For each seed: the sources above 100 times the residual's robust noise, each model's flux in a
5 x 5 pixel box around the source against the true sky's in the same box (boxes may hold a
neighbour's or the Gaussian's flux: both sides hold it), the median and largest error, the
residual's peak in robust sigmas and the model's flux against the truth's; for `r2d2 image`
(the default, and with each `--variant`'s options) and WSClean multiscale (`-mgain 0.8
-auto-threshold 1 -auto-mask 3 -padding 2`, the issue's settings) on the same MS.

Usage: python3 benches/compact_fluxes.py [--seeds 1 2 3 4] [--size 128]
       [--variant '--auto-threshold 1' ...] [--out bench-out/compact_fluxes] [--r2d2 BIN]
Needs WSClean, astropy and python-casacore.
"""

import argparse
import os
import subprocess
import sys

import numpy as np
from astropy.io import fits

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from selfcal import compact_sky  # noqa: E402


def run(cmd, cwd):
    out = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"{' '.join(map(str, cmd))} failed ({out.returncode}):\n{out.stderr[-3000:]}")


def image(path):
    return fits.getdata(path).astype(np.float64).squeeze()


def score(model, residual, truth, sources):
    sigma = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    errors = []
    for x, y, flux in sources:
        if flux > 100 * sigma:
            box = (slice(int(y) - 2, int(y) + 3), slice(int(x) - 2, int(x) + 3))
            errors.append(abs(model[box].sum() / truth[box].sum() - 1))
    errors.sort()
    return len(errors), errors[len(errors) // 2], errors[-1], np.abs(residual).max() / sigma, model.sum() / truth.sum()


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--variant", action="append", default=[], help="further `r2d2 image` options, imaged beside the default")
    p.add_argument("--r2d2", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "target", "release", "r2d2"))
    p.add_argument("--wsclean", default="wsclean")
    p.add_argument("--out", default="bench-out/compact_fluxes")
    args = p.parse_args()
    r2d2 = os.path.abspath(args.r2d2)
    n = args.size
    print("| seed | imager | sources > 100 sigma | flux error median / largest | residual peak (sigma) | model flux / truth |")
    print("|---|---|---|---|---|---|")
    for seed in args.seeds:
        d = os.path.join(args.out, f"seed{seed}")
        os.makedirs(d, exist_ok=True)
        compact_sky(n, os.path.join(d, "sky.fits"), seed)
        run([r2d2, "simulate", "--sky", "sky.fits", "--seed", seed, "--out", "obs.parquet"], d)
        run([r2d2, "convert", "obs.parquet", "obs.ms"], d)
        names = [("r2d2", [])] + [(f"r2d2 {v}", v.split()) for v in args.variant]
        for k, (_, options) in enumerate(names):
            run([r2d2, "image", "obs.parquet", "--size", n, "--name", f"r2d2-{k}", *options], d)
        scale = abs(fits.getheader(os.path.join(d, "r2d2-0-model.fits"))["CDELT2"]) * 3600
        run([args.wsclean, "-size", n, n, "-scale", f"{scale}asec", "-weight", "briggs", "0", "-multiscale", "-niter", "100000",
             "-mgain", "0.8", "-auto-threshold", "1", "-auto-mask", "3", "-padding", "2", "-j", "2", "-name", "ws", "obs.ms"], d)
        truth = image(os.path.join(d, "sky.fits"))
        sources = np.loadtxt(os.path.join(d, "sources.txt"))
        prefixes = [(label, f"r2d2-{k}") for k, (label, _) in enumerate(names)] + [("WSClean", "ws")]
        for label, prefix in prefixes:
            count, median, largest, peak, flux = score(image(os.path.join(d, f"{prefix}-model.fits")),
                                                       image(os.path.join(d, f"{prefix}-residual.fits")), truth, sources)
            print(f"| {seed} | {label} | {count} | {100 * median:.2f} % / {100 * largest:.2f} % | {peak:.1f} | {flux:.4f} |", flush=True)


if __name__ == "__main__":
    main()
