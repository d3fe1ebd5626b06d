#!/usr/bin/env python3
"""Series against each other at the settings users choose, on held-out skies, in the engine.

    python3 training/compare_settings.py --series vla-r2d2-512 vla-r2d2-512-broad \
        [--telescope vla] [--seeds 900000 900001 900002 900003] \
        [--settings robust=-1 robust=0.5 robust=1 sr=2.0 sr=2.5] [--work DIR] [--r2d2 BIN]

Each sky (`procedural:SEED`, test seeds 900000..: never used for training or selection) is
observed once per setting by `r2d2 simulate` (the VLA: A 8 h + C 2 h at 300 s; MeerKAT: a
10 h track at 60 s over 2 channels; the noise for the setting's weighting at DR 1e4) and
imaged by `r2d2 image --step SERIES` at that setting, with the divergence guard as users
get it. The SNR (dB) of each kept model against the true sky is printed as a markdown
table, one cell per sky, with the series chosen by `auto` for the setting alongside.
Observations and images are cached in WORK and reused (remove WORK after changing a
series).
"""

import argparse
import json
import os
import subprocess
import sys

import numpy as np
from astropy.io import fits

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

OBSERVATION = {
    "vla": ["--configs", "a,c", "--hours", "8,2", "--integration-s", "300"],
    "meerkat": ["--hours", "10", "--nfreq", "2", "--freq-ratio", "1.5", "--integration-s", "60"],
}


def setting_args(setting):
    """`robust=R` or `sr=S` (or `base`, the series' own) as r2d2 options."""
    if setting == "base":
        return []
    key, value = setting.split("=")
    return {"robust": [f"--robust={value}"], "sr": ["--superresolution", value]}[key]


def run(cmd, cwd):
    out = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"failed: {' '.join(map(str, cmd))}\n{out.stderr[-3000:]}")
    return out.stderr


def snr_db(est, truth):
    return 20 * np.log10(np.linalg.norm(truth) / np.linalg.norm(truth - est))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--series", nargs="+", required=True)
    ap.add_argument("--telescope", default="vla", choices=sorted(OBSERVATION))
    ap.add_argument("--seeds", type=int, nargs="+", default=[900000, 900001, 900002, 900003])
    ap.add_argument("--settings", nargs="+", default=["robust=-1", "robust=0.5", "robust=1", "sr=2.0", "sr=2.5"])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--work", default=os.path.join(REPO, "bench-out", "compare_settings"))
    ap.add_argument("--r2d2", default=os.path.join(REPO, "target", "release", "r2d2"))
    args = ap.parse_args()
    r2d2 = os.path.abspath(args.r2d2)
    os.makedirs(args.work, exist_ok=True)
    rows, record = [], {}
    for setting in args.settings:
        tag = setting.replace("=", "")
        cells = {s: [] for s in args.series}
        chosen = set()
        for seed in args.seeds:
            obs = f"{args.telescope}-{tag}-{seed}.parquet"
            if not os.path.exists(os.path.join(args.work, obs)):
                noise = [a for a in setting_args(setting) if a.startswith("--robust")]
                pixel = setting_args(setting) if setting.startswith("sr=") else []
                run([r2d2, "simulate", "--telescope", args.telescope, *OBSERVATION[args.telescope], "--sky", f"procedural:{seed}",
                     "--size", args.size, "--dr", "1e4", *noise, *pixel, "--out", obs], args.work)
            truth = fits.getdata(os.path.join(args.work, obs.replace(".parquet", ".sky.fits"))).squeeze()
            for series in args.series:
                name = f"{args.telescope}-{tag}-{os.path.basename(os.path.normpath(series))}-{seed}"
                if not os.path.exists(os.path.join(args.work, f"{name}-model.fits")):
                    run([r2d2, "image", obs, "--size", args.size, "--step", series, *setting_args(setting),
                         "--truth", obs.replace(".parquet", ".sky.fits"), "--name", name], args.work)
                model = fits.getdata(os.path.join(args.work, f"{name}-model.fits")).squeeze()
                cells[series].append(float(snr_db(model, truth)))
            log = run([r2d2, "image", obs, "--size", args.size, *setting_args(setting), "--iterations", "1",
                       "--name", f"{args.telescope}-{tag}-auto-{seed}"], args.work)
            chosen.update(l.split("series '")[1].split("'")[0] for l in log.splitlines() if "series '" in l and "chosen" in l)
            chosen.update(["CLEAN"] if "built-in CLEAN" in log else [])
        record[setting] = {s: cells[s] for s in args.series} | {"auto": sorted(chosen)}
        rows.append(f"| {setting} | " + " | ".join(", ".join(f"{x:.1f}" for x in cells[s]) for s in args.series)
                    + f" | {', '.join(sorted(chosen))} |")
    header = "| setting | " + " | ".join(f"`{s}`" for s in args.series) + " | `auto` chose |\n|" + "---|" * (len(args.series) + 2)
    table = header + "\n" + "\n".join(rows)
    with open(os.path.join(args.work, f"compare_settings-{args.telescope}.json"), "w") as f:
        json.dump({"telescope": args.telescope, "seeds": args.seeds, "snr_db": record}, f, indent=1)
    print(table)


if __name__ == "__main__":
    main()
