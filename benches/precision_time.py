"""The precision-time curve of a series: SNR and logSNR against wall time, per network count,
from the `-metrics.json` files of runs made with the truth (`r2d2 image --truth`, as
benches/vs_wsclean.py makes them: OUT/work/NNNNN/r2d2-metrics.json), and where the reference
v2 stop rule would end each run if it applied from the first network on.

    python3 benches/precision_time.py bench-out/vs_wsclean [more output directories ...] [--out curve.md]

Time at network k: the run's fixed stages (read, weights, grid, final CLEAN, products) plus
the step and residual seconds of networks 1..k, so the curve is what a run stopped at k would
have cost. The final CLEAN's cycles (iterations after the series) are left out of the curve.
The v2 rule (the engine's `StopRule`, src/job/stopping.rs): stop when the residual ratio
changes by less than 1e-4 relative, or rises at two consecutive networks.
"""

import argparse
import glob
import json
import os
import sys

import numpy as np


def v2_stop(ratios, tolerance=1e-4):
    """The network after which the v2 rule stops (1-based), or len(ratios)."""
    for n in range(2, len(ratios) + 1):
        r = ratios[:n]
        if n >= 3 and r[-1] > r[-2] > r[-3]:
            return n
        if abs(r[-1] - r[-2]) / r[-2] < tolerance:
            return n
    return len(ratios)


def curve(path):
    with open(path) as f:
        m = json.load(f)
    networks = m["settings"]["step"]["networks"] if "step" in m.get("settings", {}) else None
    rows = [r for r in m["iterations"] if networks is None or r["iteration"] <= networks]
    fixed = sum(v for k, v in m["stage_seconds"].items() if k not in ("step", "update"))
    t = fixed + np.cumsum([r["step_seconds"] + r["residual_seconds"] for r in rows])
    return {
        "snr": np.array([r.get("snr", np.nan) for r in rows], dtype=float),
        "logsnr": np.array([r.get("logsnr") if r.get("logsnr") is not None else np.nan for r in rows], dtype=float),
        "ratio": [r["residual_ratio"] for r in rows],
        "seconds": t,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dirs", nargs="+")
    ap.add_argument("--name", default="r2d2", help="the runs' product name (NAME-metrics.json)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    files = sorted(f for d in args.dirs for f in glob.glob(os.path.join(d, "work", "*", f"{args.name}-metrics.json")))
    if not files:
        sys.exit(f"no {args.name}-metrics.json under {args.dirs}")
    runs = [curve(f) for f in files]
    n = min(len(r["snr"]) for r in runs)
    snr = np.mean([r["snr"][:n] for r in runs], axis=0)
    logsnr = np.mean([r["logsnr"][:n] for r in runs], axis=0)
    seconds = np.mean([r["seconds"][:n] for r in runs], axis=0)
    lines = [f"{len(runs)} runs ({', '.join(sorted(set(os.path.dirname(os.path.dirname(os.path.dirname(f))) for f in files)))}); means:", "",
             "| networks | SNR (dB) | logSNR (dB) | wall (s) | share of the whole series' time |", "|---|---|---|---|---|"]
    for k in sorted(set([1, 2, 4, 8, 12, 16, 20, 24, 28, 32, 36, 40, n]) & set(range(1, n + 1))):
        lines.append(f"| {k} | {snr[k - 1]:.2f} | {logsnr[k - 1]:.2f} | {seconds[k - 1]:.1f} | {seconds[k - 1] / seconds[n - 1]:.2f} |")
    stops = [v2_stop(r["ratio"][:n]) for r in runs]
    at_stop = [(r["snr"][k - 1] - r["snr"][n - 1], r["logsnr"][k - 1] - r["logsnr"][n - 1], r["seconds"][k - 1] / r["seconds"][n - 1]) for r, k in zip(runs, stops)]
    lines += ["", f"The v2 rule from the first network on would stop after networks {stops} (of {n}): "
              f"SNR {np.mean([a[0] for a in at_stop]):+.2f} dB, logSNR {np.nanmean([a[1] for a in at_stop]):+.2f} dB against the whole series, "
              f"at {np.mean([a[2] for a in at_stop]):.2f} of its time (means)."]
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
