"""MeasurementSet read throughput: the engine's MS reader against python-casacore.

    python3 benches/ms_read.py [--rows 312500] [--channels 32] [--dir bench-out/ms_read]

Writes an MS with python-casacore (XX, YY; DATA, FLAG, WEIGHT_SPECTRUM, UVW, TIME, antennas,
ids; StandardStMan as default_ms makes it; rows x channels Stokes I samples, 1e7 by default),
then reads it (1) with `target/release/r2d2 bench ms-read` (the `ms` source's reader: Stokes I
samples in 64k-sample chunks, exclusions counted) and (2) with python-casacore reading the same
columns in the same row chunks (getcol, no Stokes I arithmetic), each under /usr/bin/time for
wall time and peak memory. Build first: cargo build --release.
Prints one JSON object.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import time

import numpy as np

READ_SCRIPT = r"""
import sys, time
from casacore.tables import table
t = table(sys.argv[1], ack=False)
n, chunk = t.nrows(), int(sys.argv[2])
start = time.time()
for r in range(0, n, chunk):
    k = min(chunk, n - r)
    for c in ("TIME", "ANTENNA1", "ANTENNA2", "FIELD_ID", "DATA_DESC_ID", "FLAG_ROW", "UVW", "FLAG", "DATA", "WEIGHT_SPECTRUM"):
        t.getcol(c, r, k)
print(time.time() - start)
"""


def make_ms(path, rows, channels):
    from casacore.tables import default_ms, makearrcoldesc, maketabdesc, table
    desc = maketabdesc([
        makearrcoldesc("DATA", 0j, valuetype="complex", shape=[channels, 2]),
        makearrcoldesc("FLAG", False, valuetype="boolean", shape=[channels, 2]),
        makearrcoldesc("WEIGHT_SPECTRUM", 0.0, valuetype="float", shape=[channels, 2]),
    ])
    t = default_ms(path, desc)
    t.addrows(rows)
    rng = np.random.default_rng(1)
    step = 50_000
    for r in range(0, rows, step):
        k = min(step, rows - r)
        t.putcol("TIME", 4.9e9 + np.arange(r, r + k) // 351 * 30.0, r, k)
        pair = np.arange(r, r + k) % 351
        i = (np.sqrt(2 * pair + 0.25) + 0.5).astype(np.int32)
        t.putcol("ANTENNA1", (pair - i * (i - 1) // 2).astype(np.int32), r, k)
        t.putcol("ANTENNA2", i, r, k)
        t.putcol("UVW", rng.normal(0, 3000, (k, 3)), r, k)
        t.putcol("DATA", (rng.normal(size=(k, channels, 2)) + 1j * rng.normal(size=(k, channels, 2))).astype(np.complex64), r, k)
        t.putcol("FLAG", rng.random((k, channels, 2)) < 0.05, r, k)
        t.putcol("WEIGHT_SPECTRUM", np.ones((k, channels, 2), np.float32), r, k)
    t.close()
    for name, rowsdata in (("SPECTRAL_WINDOW", None), ("POLARIZATION", None), ("DATA_DESCRIPTION", None), ("FIELD", None), ("OBSERVATION", None)):
        sub = table(f"{path}/{name}", readonly=False, ack=False)
        sub.addrows(1)
        if name == "SPECTRAL_WINDOW":
            sub.putcell("NUM_CHAN", 0, channels)
            sub.putcell("CHAN_FREQ", 0, 1.4e9 + 1e6 * np.arange(channels))
        elif name == "POLARIZATION":
            sub.putcell("NUM_CORR", 0, 2)
            sub.putcell("CORR_TYPE", 0, np.array([9, 12], np.int32))
        elif name == "FIELD":
            for c in ("PHASE_DIR", "DELAY_DIR", "REFERENCE_DIR"):
                sub.putcell(c, 0, np.array([[1.0, 0.5]]))
            sub.putcell("NAME", 0, "TARGET")
        elif name == "OBSERVATION":
            sub.putcell("TELESCOPE_NAME", 0, "VLA")
        sub.close()


def timed(cmd):
    out = subprocess.run(["/usr/bin/time", "-f", "%e %M"] + cmd, capture_output=True, text=True, check=True)
    wall, rss_kb = out.stderr.strip().splitlines()[-1].split()
    return out.stdout, float(wall), int(rss_kb) / 1024


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--rows", type=int, default=312_500)
    p.add_argument("--channels", type=int, default=32)
    p.add_argument("--dir", default="bench-out/ms_read")
    args = p.parse_args()
    os.makedirs(args.dir, exist_ok=True)
    ms = os.path.join(args.dir, "bench.ms")
    samples = args.rows * args.channels
    if not os.path.isdir(ms):
        make_ms(ms, args.rows, args.channels)
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    exe = os.path.join(repo, "target", "release", "r2d2")
    ours, wall, rss = timed([exe, "bench", "ms-read", ms])
    ours = json.loads(ours)
    chunk = max(1, 65536 // args.channels)
    py_inner, py_wall, py_rss = timed([sys.executable, "-c", READ_SCRIPT, ms, str(chunk)])
    result = {
        "samples": samples,
        "ms_bytes": sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(ms) for f in fs),
        "r2d2": {"seconds": wall, "samples_per_second": samples / wall, "peak_mb": rss, "inner_seconds": ours["seconds"], "kept": ours["kept"]},
        "python_casacore": {"seconds": py_wall, "samples_per_second": samples / py_wall, "peak_mb": py_rss,
                            "inner_seconds": float(py_inner)},
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
