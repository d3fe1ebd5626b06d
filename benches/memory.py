"""Peak memory of `r2d2 image` per visibility row, beside WSClean on the same data.

    python3 benches/memory.py [--rows 1e6,1e7] [--size 512] [--steps clean,auto] [--dir bench-out/memory]

Simulates VLA-C observations of about 1e4 (the baseline: the image-size cost) and each of
--rows samples (`r2d2 simulate`, 8 h at 10 s, channels scale the count), converts each to a
MeasurementSet (`r2d2 convert`), then images each under /usr/bin/time (peak RSS, wall):
`r2d2 image OBS.parquet --size N --step S` for each of --steps (`clean`: the built-in
Hogbom CLEAN; `auto`: the default, the R2D2 series shipped for the size) and `wsclean -size
N N -scale <r2d2's pixel> -niter 0` on the MS. Bytes per row = (peak - baseline peak) / rows,
where the baseline is the same command on the small observation: what is left is the cost
that grows with the rows (a series' networks cost the same at any row count, and where they
peak above the visibilities this comes out below the visibilities' real cost); peak/row is
the whole peak over the rows, an upper bound. Build first:
cargo build --release. Prints a table and one JSON object.

    python3 benches/memory.py --dask 1,2 [--rows 1e6,1e8] [--parts 4] [--ms] [--python PY]

The Dask path instead (no MeasurementSet, no WSClean): each observation is cut into --parts
Parquet files (row groups, a part at a time) and imaged by `r2d2_imaging.dask.image_parts` on
a LocalCluster of each count of worker processes (one thread each, the machine's cores shared
among their tasks), beside `r2d2 image` of the whole file in the same run: wall time, the
client's peak, each worker's peak, and the largest difference of the dirty image and model
from the single-process run's, relative to its peak. --python: an interpreter with the
r2d2_imaging package (default target/python-tests-venv/bin/python, which `cargo test` makes).
--ms: each part also converted to a MeasurementSet, imaged by the Dask path and by WSClean
(`-niter 0`, the parts given together as one observation).
"""

import argparse
import json
import os
import subprocess

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
R2D2 = os.path.join(REPO, "target", "release", "r2d2")


def timed(cmd, cwd):
    out = subprocess.run(["/usr/bin/time", "-f", "%e %M"] + cmd, cwd=cwd, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out.stderr[-3000:]}")
    wall, rss_kb = out.stderr.strip().splitlines()[-1].split()
    return float(wall), int(rss_kb) / 1024


def fits_header_value(path, key):
    with open(path, "rb") as f:
        while True:
            block = f.read(2880)
            if not block:
                raise SystemExit(f"{path}: no {key}")
            for i in range(0, 2880, 80):
                card = block[i:i + 80].decode("ascii", "replace")
                if card[:8].strip() == key:
                    return float(card[10:].split("/")[0])


# Channels per `r2d2 simulate` run: the simulator holds its whole observation (about 200 bytes
# a sample), so larger observations are simulated in parts of this many channels and joined.
PART_CHANNELS = 10


def observation(d, name, hours, channels):
    parquet = os.path.join(d, f"{name}.parquet")
    if not os.path.exists(parquet):
        if channels <= PART_CHANNELS:
            subprocess.run([R2D2, "simulate", "--configs", "c", "--hours", str(hours), "--integration-s", "10", "--nfreq", str(channels),
                            "--freq-ratio", "1.5" if channels > 1 else "1", "--seed", "1", "--out", parquet, "-q"], check=True)
        else:
            join_parts(d, name, hours, channels, parquet)
    ms = os.path.join(d, f"{name}.ms")
    if not os.path.isdir(ms):
        subprocess.run([R2D2, "convert", parquet, ms, "-q"], check=True)
    rows = int(subprocess.run(["python3", "-c", f"import pyarrow.parquet as pq; print(pq.ParquetFile('{parquet}').metadata.num_rows)"],
                              capture_output=True, text=True, check=True).stdout)
    return parquet, ms, rows


def join_parts(d, name, hours, channels, parquet):
    """The 1400..2100 MHz band in `channels` channels, simulated PART_CHANNELS at a time (the
    same procedural sky on a fixed pixel, the same tracks) and joined a row group at a time."""
    import pyarrow.parquet as pq
    low, high = 1400.0, 2100.0
    step = (high - low) / (channels - 1)
    parts = []
    for start in range(0, channels, PART_CHANNELS):
        count = min(PART_CHANNELS, channels - start)
        lowest = low + start * step
        part = os.path.join(d, f"{name}-part{start // PART_CHANNELS:03d}.parquet")
        if not os.path.exists(part):
            subprocess.run([R2D2, "simulate", "--configs", "c", "--hours", str(hours), "--integration-s", "10", "--nfreq", str(count),
                            "--freq-mhz", str(lowest), "--freq-ratio", str((lowest + (count - 1) * step) / lowest),
                            "--pixel-arcsec", "2.8", "--seed", "1", "--out", part, "-q"], check=True)
        parts.append(part)
    tmp = parquet + ".tmp"
    first = pq.ParquetFile(parts[0])
    with pq.ParquetWriter(tmp, first.schema_arrow, compression="zstd") as writer:
        for part in parts:
            f = pq.ParquetFile(part)
            for group in range(f.num_row_groups):
                writer.write_table(f.read_row_group(group))
    os.replace(tmp, parquet)
    for part in parts:
        os.remove(part)
        sky = part[: -len(".parquet")] + ".sky.fits"
        if os.path.exists(sky):
            os.remove(sky)


def measure(d, name, parquet, ms, size, steps):
    r2d2 = {step: timed([R2D2, "image", parquet, "--size", str(size), "--step", step, "--name", f"{name}-r2d2-{step}", "-q"], d)
            for step in steps}
    scale_arcsec = abs(fits_header_value(os.path.join(d, f"{name}-r2d2-{steps[0]}-dirty.fits"), "CDELT2")) * 3600
    wsclean = timed(["wsclean", "-quiet", "-size", str(size), str(size), "-scale", f"{scale_arcsec}asec", "-niter", "0", "-j", "2",
                     "-name", f"{name}-wsclean", ms], d)
    return r2d2, wsclean


def split_parts(parquet, count):
    """`parquet` as `count` files of consecutive rows, nearly equal, written a batch at a time."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    stem = parquet[: -len(".parquet")]
    paths = [f"{stem}-of{count}-{k}.parquet" for k in range(count)]
    if all(os.path.exists(p) for p in paths):
        return paths
    f = pq.ParquetFile(parquet)
    rows = f.metadata.num_rows
    share = -(-rows // count)
    batches = f.iter_batches(batch_size=1 << 20)
    pending = None
    for k, path in enumerate(paths):
        left = share
        with pq.ParquetWriter(path + ".tmp", f.schema_arrow, compression="zstd") as writer:
            while left > 0:
                batch = pending if pending is not None else next(batches, None)
                pending = None
                if batch is None:
                    break
                if batch.num_rows > left:
                    batch, pending = batch.slice(0, left), batch.slice(left)
                writer.write_table(pa.Table.from_batches([batch], schema=f.schema_arrow))
                left -= batch.num_rows
        os.replace(path + ".tmp", path)
    return paths


DASK_CHILD = """
import json, sys, time
import numpy as np
from distributed import Client, LocalCluster
from r2d2_imaging.dask import image_parts
from astropy.io import fits
workers, size, prefix, parts = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4:]
cores = len(__import__("os").sched_getaffinity(0))


def peak_mb():
    # VmHWM: this process's own peak (getrusage's maxrss carries the parent's across exec).
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024

with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, Client(cluster) as client:
    start = time.time()
    products = image_parts(client, parts, id="dask", part_threads=max(1, cores // workers), size=size, step="clean", iterations=1)
    wall = time.time() - start
    peaks = client.run(peak_mb)
diff = {}
for name in ["dirty", "model"]:
    single = np.squeeze(fits.getdata(f"{prefix}-{name}.fits")).astype(np.float64)
    mine = getattr(products, name).astype(np.float64)
    diff[name] = float(np.max(np.abs(single - mine)) / np.max(np.abs(single)))
print(json.dumps({"seconds": wall, "client_mb": peak_mb(),
                  "worker_mb": sorted(peaks.values()), "relative_difference": diff}))
"""


def dask_run(d, name, size, workers, paths, python):
    out = subprocess.run([python, "-c", DASK_CHILD, str(workers), str(size), os.path.join(d, f"{name}-single")] + paths,
                         capture_output=True, text=True, cwd=d)
    if out.returncode != 0:
        raise SystemExit(f"the Dask run of {name} on {workers} workers failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def measure_dask(d, name, parquet, size, counts, parts, python, ms):
    single = timed([R2D2, "image", parquet, "--size", str(size), "--step", "clean", "--iterations", "1", "--name", f"{name}-single", "-q"], d)
    paths = split_parts(parquet, parts)
    result = {"single": {"seconds": single[0], "peak_mb": single[1]},
              "dask": {workers: dask_run(d, name, size, workers, paths, python) for workers in counts}}
    if ms:
        # Each part as a MeasurementSet (`r2d2 convert` holds a part whole), imaged by the Dask
        # path and by WSClean, which takes the parts as one observation.
        mss = []
        for path in paths:
            out = path[: -len(".parquet")] + ".ms"
            if not os.path.isdir(out):
                subprocess.run([R2D2, "convert", path, out, "-q"], check=True)
            mss.append(out)
        result["dask_ms"] = {workers: dask_run(d, name, size, workers, mss, python) for workers in counts}
        scale_arcsec = abs(fits_header_value(os.path.join(d, f"{name}-single-dirty.fits"), "CDELT2")) * 3600
        wsclean = timed(["wsclean", "-quiet", "-size", str(size), str(size), "-scale", f"{scale_arcsec}asec", "-niter", "0", "-j", "2",
                         "-name", f"{name}-wsclean-parts"] + mss, d)
        result["wsclean"] = {"seconds": wsclean[0], "peak_mb": wsclean[1]}
    return result


def main_dask(args):
    d = os.path.abspath(args.dir)
    counts = [int(c) for c in args.dask.split(",")]
    results = []
    for target in [float(r) for r in args.rows.split(",")]:
        channels = max(1, round(target / 1e6))
        name = f"rows{channels}m"
        parquet = os.path.join(d, f"{name}.parquet")
        if not os.path.exists(parquet):
            if channels <= PART_CHANNELS:
                observation(d, name, 8, channels)
            else:
                join_parts(d, name, 8, channels, parquet)
        import pyarrow.parquet as pq
        rows = pq.ParquetFile(parquet).metadata.num_rows
        results.append({"rows": rows, "parts": args.parts, **measure_dask(d, name, parquet, args.size, counts, args.parts, args.python, args.ms)})
    print(f"{args.size} x {args.size}, `--step clean --iterations 1`; Dask: image_parts over {args.parts} Parquet parts, LocalCluster")
    print(f"{'rows':>10} {'run':>12} {'s':>7} {'client MB':>10} {'worker MB':>16} {'dirty diff':>11} {'model diff':>11}")
    for r in results:
        s = r["single"]
        print(f"{r['rows']:>10} {'r2d2 image':>12} {s['seconds']:>7.1f} {s['peak_mb']:>10.0f} {'-':>16} {'-':>11} {'-':>11}")
        for label, runs in [("dask", r["dask"]), ("dask MS", r.get("dask_ms", {}))]:
            for workers, run in runs.items():
                peaks = ", ".join(f"{mb:.0f}" for mb in run["worker_mb"])
                diff = run["relative_difference"]
                print(f"{r['rows']:>10} {f'{label} x{workers}':>12} {run['seconds']:>7.1f} {run['client_mb']:>10.0f} {peaks:>16} {diff['dirty']:>11.1e} {diff['model']:>11.1e}")
        if "wsclean" in r:
            w = r["wsclean"]
            print(f"{r['rows']:>10} {'WSClean MS':>12} {w['seconds']:>7.1f} {w['peak_mb']:>10.0f} {'-':>16} {'(-niter 0)':>11} {'':>11}")
    print(json.dumps({"size": args.size, "results": results}, indent=2))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--rows", default="1e6,1e7")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--steps", default="clean,auto", help="r2d2 --step values to measure, comma-separated")
    p.add_argument("--dir", default="bench-out/memory")
    p.add_argument("--dask", default="", help="worker counts: measure the Dask path (image_parts) instead, e.g. 1,2")
    p.add_argument("--parts", type=int, default=4, help="Parquet parts of each observation for the Dask path")
    p.add_argument("--ms", action="store_true", help="the Dask path also over the parts as MeasurementSets, and WSClean on them")
    p.add_argument("--python", default=os.path.join(REPO, "target", "python-tests-venv", "bin", "python"),
                   help="an interpreter with r2d2_imaging installed (the Dask path)")
    args = p.parse_args()
    os.makedirs(args.dir, exist_ok=True)
    if args.dask:
        return main_dask(args)
    steps = args.steps.split(",")
    d = os.path.abspath(args.dir)
    base = observation(d, "base", 0.08, 1)
    (base_r2d2, base_wsclean) = measure(d, "base", base[0], base[1], args.size, steps)
    per_row = lambda peak, base_peak, rows: (peak - base_peak) * 2**20 / (rows - base[2])
    results = []
    for target in [float(r) for r in args.rows.split(",")]:
        channels = max(1, round(target / 1e6))
        parquet, ms, rows = observation(d, f"rows{channels}m", 8, channels)
        (r2d2, wsclean) = measure(d, f"rows{channels}m", parquet, ms, args.size, steps)
        results.append({
            "rows": rows,
            "r2d2": {step: {"seconds": t, "peak_mb": mb, "bytes_per_row": per_row(mb, base_r2d2[step][1], rows),
                            "peak_bytes_per_row": mb * 2**20 / rows}
                     for step, (t, mb) in r2d2.items()},
            "wsclean": {"seconds": wsclean[0], "peak_mb": wsclean[1], "bytes_per_row": per_row(wsclean[1], base_wsclean[1], rows)},
        })
    bases = ", ".join(f"r2d2 --step {step} {mb:.0f} MB" for step, (_, mb) in base_r2d2.items())
    print(f"{args.size} x {args.size}; baseline ({base[2]} rows): {bases}, WSClean {base_wsclean[1]:.0f} MB")
    print(f"{'rows':>10} {'':>8} {'peak MB':>8} {'B/row':>7} {'peak/row':>9} {'s':>6} {'s / WSClean':>12}")
    for r in results:
        b = r["wsclean"]
        for step, a in r["r2d2"].items():
            print(f"{r['rows']:>10} {step:>8} {a['peak_mb']:>8.0f} {a['bytes_per_row']:>7.1f} {a['peak_bytes_per_row']:>9.1f} {a['seconds']:>6.1f} {a['seconds'] / b['seconds']:>12.2f}")
        print(f"{r['rows']:>10} {'WSClean':>8} {b['peak_mb']:>8.0f} {b['bytes_per_row']:>7.1f} {b['peak_mb'] * 2**20 / r['rows']:>9.1f} {b['seconds']:>6.1f} {1:>12.2f}")
    print(json.dumps({"size": args.size, "baseline_rows": base[2],
                      "baseline": {"r2d2_mb": {step: mb for step, (_, mb) in base_r2d2.items()}, "wsclean_mb": base_wsclean[1]},
                      "results": results}, indent=2))


if __name__ == "__main__":
    main()
