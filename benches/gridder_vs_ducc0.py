#!/usr/bin/env python3
"""Gridding / degridding throughput of r2d2's NUFFT against ducc0.wgridder.

Both sides get the same kind of data: N visibilities uniform in the uv disc, one channel,
w = 0, a size x size image whose pixel is 1/1.5 of the Nyquist size (super-resolution 1.5:
pixsize = 1 / (1.5 * 2 * max_uv)), double precision, the same requested epsilon. ducc0 runs
with do_wgridding=False and picks its own oversampling and kernel; r2d2 runs its benchmark
(`r2d2 bench gridder`) as a subprocess and reports JSON.

Throughputs are million visibilities per second, best of --repeats runs. ducc0 builds its
visibility index (sorts) inside every call, so r2d2's number here includes its plan (point
sorting) too; r2d2's "planned" throughput (plan reused, as in iterative imaging) is shown
separately. Each side's accuracy is measured against a direct DFT on a sample of outputs so
that neither is faster by being less accurate.

Usage: python3 benches/gridder_vs_ducc0.py [--visibilities 2000000] [--size 512]
       [--epsilon 1e-5] [--threads 1,2] [--repeats 3] [--r2d2 'target/release/r2d2 bench gridder']
"""

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time

import numpy as np

try:
    import ducc0
except ImportError:  # pragma: no cover - environment problem, say what to do
    sys.exit("ducc0 is not installed: pip install ducc0")

SPEED_OF_LIGHT = 299792458.0
MAX_UV = 1000.0  # wavelengths; only the product with the pixel size matters


def make_data(n, npix, seed):
    """uvw (metres, w = 0) for one channel at f = c (so metres = wavelengths), complex
    visibilities, a random real image for degridding, and the pixel size."""
    rng = np.random.default_rng(seed)
    r = MAX_UV * np.sqrt(rng.random(n))
    theta = 2.0 * np.pi * rng.random(n)
    uvw = np.zeros((n, 3))
    uvw[:, 0] = r * np.cos(theta)
    uvw[:, 1] = r * np.sin(theta)
    vis = (rng.uniform(-1, 1, n) + 1j * rng.uniform(-1, 1, n)).reshape(n, 1)
    image = rng.uniform(-1, 1, (npix, npix))
    pixsize = 1.0 / (1.5 * 2.0 * MAX_UV)
    return uvw, np.array([SPEED_OF_LIGHT]), vis, image, pixsize


def capture_fd1(fn):
    """Run fn() while capturing what C++ code writes to file descriptor 1."""
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 1)
        try:
            result = fn()
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode(errors="replace")
    return result, text


def best_of(repeats, fn):
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def rel_error(approx, exact):
    return float(np.sqrt(np.sum(np.abs(approx - exact) ** 2) / np.sum(np.abs(exact) ** 2)))


def ducc0_errors(uvw, vis, dirty, image, model_vis, pixsize, seed):
    """Relative L2 errors of vis2dirty (16 random pixels) and dirty2vis (64 random
    visibilities) against direct sums. ducc0's sign convention is found by trying both."""
    rng = np.random.default_rng(seed + 1)
    npix = image.shape[0]
    u, v = uvw[:, 0], uvw[:, 1]
    pix = rng.integers(0, npix, (16, 2))
    errs = []
    for sign in (+1, -1):
        exact = np.empty(len(pix))
        for k, (i, j) in enumerate(pix):
            l, m = (i - npix // 2) * pixsize, (j - npix // 2) * pixsize
            exact[k] = np.real(np.sum(vis[:, 0] * np.exp(sign * 2j * np.pi * (u * l + v * m))))
        errs.append(rel_error(dirty[pix[:, 0], pix[:, 1]], exact))
    grid_err = min(errs)
    rows = rng.integers(0, len(u), 64)
    lm = (np.arange(npix) - npix // 2) * pixsize
    errs = []
    for sign in (+1, -1):
        exact = np.empty(len(rows), complex)
        for k, r in enumerate(rows):
            ph_l = np.exp(sign * 2j * np.pi * u[r] * lm)
            ph_m = np.exp(sign * 2j * np.pi * v[r] * lm)
            exact[k] = ph_l @ image @ ph_m
        errs.append(rel_error(model_vis[rows, 0], exact))
    return grid_err, min(errs)


def run_ducc0(data, epsilon, threads, repeats, seed):
    uvw, freq, vis, image, pixsize = data
    npix = image.shape[0]
    common = dict(uvw=uvw, freq=freq, pixsize_x=pixsize, pixsize_y=pixsize, epsilon=epsilon,
                  do_wgridding=False, nthreads=threads, divide_by_n=False)

    def grid(verbosity=0):
        return ducc0.wgridder.vis2dirty(vis=vis, npix_x=npix, npix_y=npix, verbosity=verbosity, **common)

    def degrid(verbosity=0):
        return ducc0.wgridder.dirty2vis(dirty=image, verbosity=verbosity, **common)

    # One verbose run each (untimed) tells the kernel support and grid ducc0 chose.
    _, log_g = capture_fd1(lambda: grid(1))
    _, log_d = capture_fd1(lambda: degrid(1))
    info = {}
    for key, log in (("grid", log_g), ("degrid", log_d)):
        supp = re.search(r"supp=(\d+)", log)
        shape = re.search(r"grid=\((\d+)x(\d+)\)", log)
        info[key] = {
            "support": int(supp.group(1)) if supp else None,
            "grid": f"{shape.group(1)}x{shape.group(2)}" if shape else None,
        }
    t_grid, dirty = best_of(repeats, grid)
    t_degrid, model_vis = best_of(repeats, degrid)
    grid_err, degrid_err = ducc0_errors(uvw, vis, dirty, image, model_vis, pixsize, seed)
    n = len(uvw) / 1e6
    return {
        "grid_mvis_per_s": n / t_grid,
        "degrid_mvis_per_s": n / t_degrid,
        "grid_seconds": t_grid,
        "degrid_seconds": t_degrid,
        "grid_support": info["grid"]["support"],
        "degrid_support": info["degrid"]["support"],
        "grid_shape": info["grid"]["grid"],
        "degrid_shape": info["degrid"]["grid"],
        "grid_rel_error": grid_err,
        "degrid_rel_error": degrid_err,
    }


def run_r2d2(command, n, size, epsilon, threads, repeats):
    args = shlex.split(command) + [
        "--visibilities", str(n), "--size", str(size), "--epsilon", repr(epsilon),
        "--threads", str(threads), "--repeats", str(repeats),
    ]
    proc = subprocess.run(args, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"r2d2 benchmark failed ({' '.join(args)}):\n{proc.stderr}")
    out = proc.stdout
    return json.loads(out[out.index("{"): out.rindex("}") + 1])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--visibilities", type=int, default=2_000_000)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--epsilon", type=float, default=1e-5)
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--r2d2", default="target/release/r2d2 bench gridder",
                    help="command running r2d2's gridder benchmark (flags are appended)")
    ap.add_argument("--json", help="also write all measurements to this file")
    a = ap.parse_args()

    data = make_data(a.visibilities, a.size, a.seed)
    print(f"{a.visibilities} visibilities, {a.size}^2 image, epsilon {a.epsilon:g}, f64, "
          f"super-resolution 1.5, ducc0 {ducc0.__version__} "
          f"(SIMD lanes f32/f64: {ducc0.misc.native_vector_lengths()})", flush=True)
    rows = []
    for threads in [int(t) for t in a.threads.split(",")]:
        d = run_ducc0(data, a.epsilon, threads, a.repeats, a.seed)
        r = run_r2d2(a.r2d2, a.visibilities, a.size, a.epsilon, threads, a.repeats)
        rows.append({"threads": threads, "ducc0": d, "r2d2": r})

    head = (f"{'direction':<8} {'thr':>3} {'ducc0':>8} {'r2d2':>8} {'ratio':>6} {'r2d2 planned':>12}"
            f"  {'supp d/r':>8} {'grid ducc0':>10} {'grid r2d2':>9}  {'err ducc0':>9} {'err r2d2':>9}")
    print()
    print("Mvis/s; r2d2 includes its plan (ducc0 sorts inside every call); ratio = r2d2 / ducc0")
    print(head)
    print("-" * len(head))
    for row in rows:
        d, r = row["ducc0"], row["r2d2"]
        for key in ("grid", "degrid"):
            ratio = r[f"{key}_mvis_per_s"] / d[f"{key}_mvis_per_s"]
            supp = f"{d[f'{key}_support'] or '?'}/{r['support']}"
            print(f"{key:<8} {row['threads']:>3} {d[f'{key}_mvis_per_s']:>8.2f} {r[f'{key}_mvis_per_s']:>8.2f} "
                  f"{ratio:>6.2f} {r[f'{key}_mvis_per_s_planned']:>12.2f}  {supp:>8} "
                  f"{d[f'{key}_shape'] or '?':>10} {r['grid_size']}x{r['grid_size']:<4}"
                  f"  {d[f'{key}_rel_error']:>9.2e} {r[f'{key}_rel_error']:>9.2e}")
        # The gridder stage's own path: all points in chunks, each sorted alone (no plan kept).
        ratio = r["grid_mvis_per_s_chunked"] / d["grid_mvis_per_s"]
        print(f"{'chunked':<8} {row['threads']:>3} {d['grid_mvis_per_s']:>8.2f} {r['grid_mvis_per_s_chunked']:>8.2f} "
              f"{ratio:>6.2f} {'':>12}  {'':>8} {'':>10} {'':>9}  {'':>9} {r['grid_chunked_rel_diff']:>9.2e}")
    print()
    print("Kernel supports and grids of ducc0 are parsed from its verbosity=1 log ('?' if absent).")
    print("Errors: relative L2 against a direct DFT on sampled outputs (16 pixels / 64 visibilities);")
    print("ducc0 computes a real image (Hermitian gridding), r2d2 a complex one.")
    print("chunked: r2d2's adjoint as its gridder stage runs it (points in chunks, no plan kept),")
    print("against ducc0's gridding; its error column is the difference from r2d2's one-plan adjoint.")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
