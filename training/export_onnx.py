#!/usr/bin/env python3
"""Write the ONNX file of every network a series' manifest lists, from its PyTorch weights.

A series trained on a machine that sends back only a few files (a lent GPU) travels as its
manifest and `weights/`; this rebuilds the ONNX networks the engine runs, each checked against
PyTorch at two sizes as train.py checks them."""
import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from r2d2train import series  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--series", required=True, help="series directory holding manifest.yaml and weights/")
    p.add_argument("--force", action="store_true", help="rewrite ONNX files that exist")
    args = p.parse_args(argv)
    manifest = series.read_manifest(args.series)
    if manifest is None:
        raise SystemExit(f"{args.series}: no {series.MANIFEST}")
    for i, name in enumerate(manifest["networks"], start=1):
        if name != series.onnx_name(i):
            raise SystemExit(f"{args.series}: network {i} is listed as {name}, expected {series.onnx_name(i)}")
        out = os.path.join(args.series, name)
        if os.path.exists(out) and not args.force:
            continue
        model = series.load_network(args.series, manifest, i)
        series.export_onnx(model, out, manifest["image_sizes"][0])
        print(f"wrote {out}", flush=True)


if __name__ == "__main__":
    main()
