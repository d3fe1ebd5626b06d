"""Imaging with a full-size R2D2 series: where the time goes, and native vs tract inference.

    python3 benches/r2d2_series.py [--size 512] [--visibilities 1e6] [--networks 15]
                                   [--channels 64] [--tract-networks 1] [--r2d2 target/release/r2d2]

1. Writes the reference U-Net (64 channels, 4 poolings, 31 M parameters, random weights) as a
   series of --networks (benches/make_reference_unet.py).
2. Simulates one VLA A+C observation with about --visibilities samples (r2d2 simulate).
3. Images it with `r2d2 image --step SERIES --backend ort` under /usr/bin/time, with
   prefetching on and off (and once with ONNX Runtime's `all` graph optimisations), and
   reports the seconds per network step and per residual update (from the -metrics.json the
   run writes), the share of the total that is not network inference, and the peak resident
   memory against the budget (visibilities + two networks + 300 MB).
4. Runs the first --tract-networks networks with the tract backend: native/tract ratio.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def run(cmd, **kw):
    t = time.time()
    out = subprocess.run(cmd, capture_output=True, text=True, **kw)
    if out.returncode != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{out.stderr}")
    return out, time.time() - t


def timed_image(r2d2, obs, size, series, backend, networks, name, work, prefetch=True, optimization="extended"):
    cmd = ["/usr/bin/time", "-v", r2d2, "-v", "image", obs, "--size", str(size), "--step", series,
           "--backend", backend, "--iterations", str(networks), "--name", name]
    if not prefetch:
        cmd.append("--no-prefetch")
    if backend == "ort":
        cmd += ["--graph-optimization", optimization]
    out, wall = run(cmd, cwd=work)
    peak_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr).group(1))
    with open(os.path.join(work, name + "-metrics.json")) as f:
        metrics = json.load(f)
    # Network loading is part of the step's seconds; the step logs each load at debug level.
    # Loads on the prefetch thread overlap inference and are not subtracted.
    metrics["load_seconds"] = [float(s) for s in re.findall(r"loaded .*\.onnx in ([0-9.]+) s$", out.stderr, re.M)]
    metrics["background_loads"] = len(re.findall(r"in the background", out.stderr))
    return wall, peak_kb / 1024, metrics


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--visibilities", type=float, default=1e6)
    ap.add_argument("--networks", type=int, default=15)
    ap.add_argument("--channels", type=int, default=64)
    ap.add_argument("--tract-networks", type=int, default=1)
    ap.add_argument("--r2d2", default="target/release/r2d2")
    ap.add_argument("--work", default=None, help="working directory (default: a temporary one)")
    args = ap.parse_args()
    r2d2 = os.path.abspath(args.r2d2)
    work = args.work or tempfile.mkdtemp(prefix="r2d2-series-")
    os.makedirs(work, exist_ok=True)
    series = os.path.join(work, "series")
    run([sys.executable, os.path.join(HERE, "make_reference_unet.py"), series, "--channels", str(args.channels),
         "--networks", str(args.networks)])
    # VLA A (8 h) + C (2 h): 27 antennas -> 351 baselines; integration chosen for the target count.
    integration = max(1.0, 351 * 10 * 3600 / args.visibilities)
    obs = os.path.join(work, "obs.parquet")
    sim, t_sim = run([r2d2, "simulate", "--configs", "a,c", "--hours", "8,2", "--integration-s", f"{integration:.2f}",
                    "--size", str(args.size), "--out", obs])
    nvis = int(re.search(r"(\d+) visibilities", sim.stderr).group(1))
    print(f"{nvis:.3g} visibilities, {args.size}^2, series of {args.networks} x reference U-Net "
          f"({args.channels} channels), work dir {work} (simulation {t_sim:.1f} s)")

    model_mb = os.path.getsize(os.path.join(series, "unet.onnx")) / 2**20
    vis_mb = nvis * (3 * 8 + 8 + 16 + 8) / 2**20  # uvw, weight, complex value, imaging weight
    budget = vis_mb + 2 * model_mb + 300
    print(f"memory budget: visibilities {vis_mb:.0f} MB + 2 networks {2 * model_mb:.0f} MB + 300 MB = {budget:.0f} MB")

    results, rows = {}, []
    runs = [("graph optimisation extended (default)", prefetch, "extended") for prefetch in (True, False)]
    runs += [("graph optimisation all", True, "all")]
    for label, prefetch, optimization in runs:
        name = f"ort-{'prefetch' if prefetch else 'noprefetch'}-{optimization}"
        wall, peak_mb, m = timed_image(r2d2, obs, args.size, series, "ort", args.networks, name, work, prefetch, optimization)
        it = m["iterations"]
        step = [x["step_seconds"] for x in it]
        upd = [x["residual_seconds"] for x in it]
        loads = m["load_seconds"]
        inference = sum(step) - sum(loads)
        results[name] = inference / len(step)
        rows.append((label, "on" if prefetch else "off", wall, inference / len(step), sum(loads) / max(1, len(loads)),
                     100 * (wall - inference) / wall, peak_mb))
        print(f"\nnative ONNX Runtime, {label}, prefetch {'on' if prefetch else 'off'}: {wall:.1f} s wall, "
              f"peak RSS {peak_mb:.0f} MB ({'within' if peak_mb <= budget else 'OVER'} the {budget:.0f} MB budget)")
        print(f"  network step: {sum(step) / len(step):.2f} s per network (min {min(step):.2f}, max {max(step):.2f}), "
              f"of which loading {sum(loads) / max(1, len(loads)):.3f} s ({len(loads)} loads in the step, "
              f"{m['background_loads']} in the background)")
        print(f"  inference alone: {inference / len(step):.2f} s per network; residual update: {sum(upd) / len(upd):.3f} s per iteration")
        print(f"  stage seconds: {json.dumps({k: round(v, 2) for k, v in m['stage_seconds'].items()})}")
        print(f"  not network inference: {100 * (wall - inference) / wall:.1f} % of the wall time (target <= 10 %)")

    print(f"\n| ONNX Runtime, {args.networks} networks | prefetch | wall | inference per network | load in step | not inference | peak RSS (budget {budget:.0f} MB) |")
    print("|---|---|---|---|---|---|---|")
    for label, prefetch, wall, per, load, share, peak in rows:
        print(f"| {label} | {prefetch} | {wall:.1f} s | {per:.2f} s | {load:.3f} s | {share:.1f} % | {peak:.0f} MB |")

    if args.tract_networks > 0:
        wall_t, peak_t, mt = timed_image(r2d2, obs, args.size, series, "tract", args.tract_networks, "tract", work)
        step_t = [x["step_seconds"] for x in mt["iterations"]]
        per_t = (sum(step_t) - sum(mt["load_seconds"])) / len(step_t)
        per_n = results["ort-prefetch-extended"]
        print(f"\ntract: {per_t:.2f} s inference per network ({args.tract_networks} run), peak RSS {peak_t:.0f} MB")
        print(f"  tract / native ONNX Runtime inference time: {per_t / per_n:.1f}")


if __name__ == "__main__":
    main()
