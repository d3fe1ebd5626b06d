"""A reduced-precision (int8) copy of a series, for CPUs where it pays (AVX-512 VNNI, AMX).

    python3 training/quantise_series.py SERIES OUT --mode int8-dynamic
    python3 training/quantise_series.py SERIES OUT --mode int8-static --calibration TRAINSET [--samples 4]

int8-dynamic needs no data; int8-static calibrates its activation scales on the networks'
inputs along the float32 series over --samples of TRAINSET (an `r2d2 trainset` directory of
training or validation data, never the test set). OUT is a new series directory; run it like
any other (`r2d2 image OBS --step OUT`). Measured speed and precision cost: docs/models.md,
"Reduced precision" (benches/reduced_precision.py).
"""
import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from r2d2train import common, precision  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("series")
    ap.add_argument("out")
    ap.add_argument("--mode", choices=precision.MODES, required=True)
    ap.add_argument("--calibration", help="trainset directory (int8-static)")
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    calibration = common.Dataset(args.calibration, args.samples) if args.calibration else None
    precision.quantise_series(args.series, args.out, args.mode, calibration, args.threads)
    print(f"{args.out}: {args.mode} copy of {args.series}")


if __name__ == "__main__":
    main()
