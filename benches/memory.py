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


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--rows", default="1e6,1e7")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--steps", default="clean,auto", help="r2d2 --step values to measure, comma-separated")
    p.add_argument("--dir", default="bench-out/memory")
    args = p.parse_args()
    os.makedirs(args.dir, exist_ok=True)
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
