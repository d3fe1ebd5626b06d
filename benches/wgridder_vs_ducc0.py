#!/usr/bin/env python3
"""W-gridding / w-degridding throughput of r2d2's w-term transforms against ducc0.wgridder.

Both sides get the same kind of data: N visibilities uniform in the uv disc whose radius
makes the pixel 1/1.5 of the Nyquist size, w uniform in [-w_factor, w_factor] times that
radius, one channel, a size x size image covering a --fov degree field (where the w-term
matters: the report gives the largest w phase), double precision, the same requested
epsilon. ducc0 runs vis2dirty / dirty2vis with do_wgridding=True and divide_by_n=False and
picks its own oversampling and kernel; r2d2 runs its benchmark (`r2d2 bench wgridder`) as a subprocess and reports JSON.

Throughputs are million visibilities per second, best of --repeats runs. ducc0 builds its
index inside every call, so r2d2's number here includes its plan (sorting) too; r2d2's
"planned" throughput (plan reused, as in iterative imaging) is shown separately. Each side's
accuracy is measured against a direct sum with the w-term on a sample of outputs.

ducc0 computes a real image and therefore folds visibilities of negative w onto positive w
(Hermitian symmetry), which halves its w range; r2d2's real-image plan (WGridPlan::new_real)
does the same and is the one compared, and its complex-image plan (whole w range) is shown
alongside. The planes column shows what each used.

Usage: python3 benches/wgridder_vs_ducc0.py [--visibilities 1000000] [--size 1024]
       [--fov 15] [--w-factor 1] [--epsilon 1e-5] [--threads 1,2] [--repeats 2]
       [--r2d2 'target/release/r2d2 bench wgridder']
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


def make_data(n, npix, fov_deg, w_factor, seed):
    """uvw (metres, one channel at f = c so metres = wavelengths), complex visibilities, a
    random real image for degridding, and the pixel size."""
    rng = np.random.default_rng(seed)
    pixsize = np.deg2rad(fov_deg) / npix
    max_uv = 1.0 / (1.5 * 2.0 * pixsize)
    r = max_uv * np.sqrt(rng.random(n))
    theta = 2.0 * np.pi * rng.random(n)
    uvw = np.empty((n, 3))
    uvw[:, 0] = r * np.cos(theta)
    uvw[:, 1] = r * np.sin(theta)
    uvw[:, 2] = max_uv * w_factor * rng.uniform(-1, 1, n)
    vis = (rng.uniform(-1, 1, n) + 1j * rng.uniform(-1, 1, n)).reshape(n, 1)
    image = rng.uniform(-1, 1, (npix, npix))
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


def n_minus_one(l, m):
    r2 = l * l + m * m
    return -r2 / (1.0 + np.sqrt(1.0 - r2))


def ducc0_errors(uvw, vis, dirty, image, model_vis, pixsize, seed):
    """Relative L2 errors of vis2dirty (16 random pixels) and dirty2vis (64 random
    visibilities) against direct sums with the w-term, ducc0's axes (l along the first
    image axis). ducc0's w-term has the sign opposite to its uv terms, exp(s 2 pi i (u l +
    v m - w (n - 1))); the overall sign s is found by trying both."""
    rng = np.random.default_rng(seed + 1)
    npix = image.shape[0]
    u, v, w = uvw[:, 0], uvw[:, 1], uvw[:, 2]
    pix = rng.integers(0, npix, (16, 2))
    errs = []
    for sign in (+1, -1):
        exact = np.empty(len(pix))
        for k, (i, j) in enumerate(pix):
            l, m = (i - npix // 2) * pixsize, (j - npix // 2) * pixsize
            ph = u * l + v * m - w * n_minus_one(l, m)
            exact[k] = np.real(np.sum(vis[:, 0] * np.exp(sign * 2j * np.pi * ph)))
        errs.append(rel_error(dirty[pix[:, 0], pix[:, 1]], exact))
    grid_err = min(errs)
    rows = rng.integers(0, len(u), 64)
    lm = (np.arange(npix) - npix // 2) * pixsize
    ll, mm = np.meshgrid(lm, lm, indexing="ij")
    t = n_minus_one(ll, mm)
    errs = []
    for sign in (+1, -1):
        exact = np.empty(len(rows), complex)
        for k, r in enumerate(rows):
            exact[k] = np.sum(image * np.exp(sign * 2j * np.pi * (u[r] * ll + v[r] * mm - w[r] * t)))
        errs.append(rel_error(model_vis[rows, 0], exact))
    return grid_err, min(errs)


def run_ducc0(data, epsilon, threads, repeats, seed):
    uvw, freq, vis, image, pixsize = data
    npix = image.shape[0]
    common = dict(uvw=uvw, freq=freq, pixsize_x=pixsize, pixsize_y=pixsize, epsilon=epsilon,
                  do_wgridding=True, nthreads=threads, divide_by_n=False)

    def grid(verbosity=0):
        return ducc0.wgridder.vis2dirty(vis=vis, npix_x=npix, npix_y=npix, verbosity=verbosity, **common)

    def degrid(verbosity=0):
        return ducc0.wgridder.dirty2vis(dirty=image, verbosity=verbosity, **common)

    # One verbose run each (untimed) tells the kernel support, grid and planes ducc0 chose.
    _, log_g = capture_fd1(lambda: grid(1))
    _, log_d = capture_fd1(lambda: degrid(1))
    info = {}
    for key, log in (("grid", log_g), ("degrid", log_d)):
        supp = re.search(r"supp=(\d+)", log)
        shape = re.search(r"grid=\((\d+)x(\d+)x(\d+)\)", log)
        info[key] = {
            "support": int(supp.group(1)) if supp else None,
            "grid": f"{shape.group(1)}x{shape.group(2)}" if shape else None,
            "planes": int(shape.group(3)) if shape else None,
        }
    t_grid, dirty = best_of(repeats, grid)
    t_degrid, model_vis = best_of(repeats, degrid)
    grid_err, degrid_err = ducc0_errors(uvw, vis, dirty, image, model_vis, pixsize, seed)
    n = len(uvw) / 1e6
    out = {
        "grid_mvis_per_s": n / t_grid,
        "degrid_mvis_per_s": n / t_degrid,
        "grid_seconds": t_grid,
        "degrid_seconds": t_degrid,
        "grid_rel_error": grid_err,
        "degrid_rel_error": degrid_err,
    }
    for key in ("grid", "degrid"):
        out[f"{key}_support"] = info[key]["support"]
        out[f"{key}_shape"] = info[key]["grid"]
        out[f"{key}_planes"] = info[key]["planes"]
    return out


def run_r2d2(command, a, threads):
    args = shlex.split(command) + [
        "--visibilities", str(a.visibilities), "--size", str(a.size), "--fov", repr(a.fov),
        "--w-factor", repr(a.w_factor), "--epsilon", repr(a.epsilon), "--threads", str(threads),
        "--repeats", str(a.repeats), "--oversampling", repr(a.oversampling),
    ]
    proc = subprocess.run(args, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"r2d2 benchmark failed ({' '.join(args)}):\n{proc.stderr}")
    out = proc.stdout
    return json.loads(out[out.index("{"): out.rindex("}") + 1])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--visibilities", type=int, default=1_000_000)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--fov", type=float, default=15.0, help="field of view (image edge), degrees")
    ap.add_argument("--w-factor", type=float, default=1.0, help="|w| up to this times the uv disc radius")
    ap.add_argument("--epsilon", type=float, default=1e-5)
    ap.add_argument("--oversampling", type=float, default=0.0,
                    help="r2d2's grid oversampling (0: the one its cost model suggests)")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--r2d2", default="target/release/r2d2 bench wgridder",
                    help="command running r2d2's w-gridder benchmark (flags are appended)")
    ap.add_argument("--json", help="also write all measurements to this file")
    a = ap.parse_args()

    data = make_data(a.visibilities, a.size, a.fov, a.w_factor, a.seed)
    rows = []
    for threads in [int(t) for t in a.threads.split(",")]:
        d = run_ducc0(data, a.epsilon, threads, a.repeats, a.seed)
        r = run_r2d2(a.r2d2, a, threads)
        rows.append({"threads": threads, "ducc0": d, "r2d2": r})
    r0 = rows[0]["r2d2"]
    print(f"{a.visibilities} visibilities, {a.size}^2 image, {a.fov:g} deg field, |w| <= {r0['w_max']:.0f} "
          f"(uv max {r0['uv_max']:.0f}; largest w phase {r0['max_w_phase']:.0f} rad), epsilon {a.epsilon:g}, "
          f"f64, ducc0 {ducc0.__version__} (SIMD lanes f32/f64: {ducc0.misc.native_vector_lengths()})")

    head = (f"{'direction':<8} {'thr':>3} {'ducc0':>8} {'r2d2':>8} {'ratio':>6} {'planned':>8} {'complex':>8}"
            f"  {'supp d/r':>8} {'grid ducc0':>10} {'grid r2d2':>9} {'planes d/r/c':>12}"
            f"  {'err ducc0':>9} {'err r2d2':>9} {'err cplx':>9}")
    print()
    print("Mvis/s. r2d2: real-image plan (negative w mirrored, as ducc0 does for its real images),")
    print("including its plan (ducc0 indexes inside every call); planned: the same with the plan")
    print("reused; complex: r2d2's complex-image plan (whole w range), including its plan.")
    print("ratio = r2d2 / ducc0")
    print(head)
    print("-" * len(head))
    for row in rows:
        d, r = row["ducc0"], row["r2d2"]
        re, cx = r["real"], r["complex"]
        for key in ("grid", "degrid"):
            ratio = re[f"{key}_mvis_per_s"] / d[f"{key}_mvis_per_s"]
            supp = f"{d[f'{key}_support'] or '?'}/{re['support']}"
            planes = f"{d[f'{key}_planes'] or '?'}/{re['planes']}/{cx['planes']}"
            print(f"{key:<8} {row['threads']:>3} {d[f'{key}_mvis_per_s']:>8.3f} {re[f'{key}_mvis_per_s']:>8.3f} "
                  f"{ratio:>6.2f} {re[f'{key}_mvis_per_s_planned']:>8.3f} {cx[f'{key}_mvis_per_s']:>8.3f}"
                  f"  {supp:>8} {d[f'{key}_shape'] or '?':>10} {re['grid_size']}x{re['grid_size']:<4} {planes:>12}"
                  f"  {d[f'{key}_rel_error']:>9.2e} {re[f'{key}_rel_error']:>9.2e} {cx[f'{key}_rel_error']:>9.2e}")
    print()
    print(f"r2d2's complex plan: oversampling {r0['complex']['oversampling']:.3g}, support {r0['complex']['support']}, "
          f"grid {r0['complex']['grid_size']}; the columns show its real plan's.")
    print("Kernel supports, grids and w-planes of ducc0 are parsed from its verbosity=1 log ('?' if absent).")
    print("Errors: relative L2 against a direct sum with the w-term on sampled outputs (16 pixels /")
    print("64 visibilities); ducc0 and r2d2's real plan compute real images (the real part of the")
    print("complex plan's).")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
