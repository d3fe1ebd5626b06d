"""Reduced-precision copies of a series (ONNX Runtime's quantisation tools).

Modes:
- `int8-dynamic`: weights stored as int8, activations quantised per inference from their
  observed range (ConvInteger); needs no data.
- `int8-static`: weights and activations int8 with fixed activation scales (QDQ format),
  calibrated on the networks' inputs along the float32 series' trajectory on a calibration
  set (training or validation data, never the test set).

The copy is a new series directory: the same manifest with `precision` recorded in its
provenance, one quantised file per network.
"""
import os
import shutil
import tempfile

import numpy as np
import torch
import yaml

from . import common, series

MODES = ("int8-dynamic", "int8-static")


def _inputs_along_series(src, manifest, calibration, threads):
    """{network file: [inputs [1, 2, N, N]]} along the float32 series on the calibration set."""
    data = calibration
    x, r = torch.zeros_like(data.dirty), data.dirty.clone()
    inputs = {}
    for i, name in enumerate(manifest["networks"], start=1):
        seen = []
        run = series.onnx_runner(os.path.join(src, name), threads)

        # The inputs as the network sees them (turned to its orientation).
        def recording(batch, run=run, seen=seen):
            seen.extend(batch[k:k + 1].numpy().astype(np.float32) for k in range(batch.shape[0]))
            return run(batch)

        x = common.update(i, series.oriented(recording, series.orientation(manifest, i)), data.dirty, x, r)
        r = common.residual(data.dirty, x, data.psf_hat)
        inputs[name] = seen
    return inputs


def quantise_series(src, dst, mode, calibration=None, threads=2):
    from onnxruntime import quantization as q

    if mode not in MODES:
        raise SystemExit(f"mode: expected one of {MODES}, got {mode!r}")
    if os.path.exists(dst):
        raise SystemExit(f"{dst}: exists (a reduced-precision copy is written to a new directory)")
    manifest = series.read_manifest(src)
    if not manifest or not manifest.get("networks"):
        raise SystemExit(f"{src}: expected a series with a manifest listing its networks")
    if mode == "int8-static" and calibration is None:
        raise SystemExit("int8-static needs a calibration set (training or validation data)")
    inputs = _inputs_along_series(src, manifest, calibration, threads) if mode == "int8-static" else None
    parent = os.path.dirname(os.path.abspath(dst))
    work = tempfile.mkdtemp(prefix=".quantising-", dir=parent)
    try:
        for name in manifest["networks"]:
            source, target = os.path.join(src, name), os.path.join(work, name)
            os.makedirs(os.path.dirname(target), exist_ok=True)
            if mode == "int8-dynamic":
                q.quantize_dynamic(source, target, weight_type=q.QuantType.QInt8)
            else:
                samples = iter({"input": a} for a in inputs[name])

                class Reader(q.CalibrationDataReader):
                    def get_next(self):
                        return next(samples, None)

                q.quantize_static(source, target, Reader(), quant_format=q.QuantFormat.QDQ, activation_type=q.QuantType.QUInt8,
                                  weight_type=q.QuantType.QInt8, per_channel=True)
        manifest = dict(manifest)
        manifest["name"] = os.path.basename(os.path.normpath(dst))
        manifest["description"] = f"{manifest.get('description', '')} [{mode}]"
        manifest["provenance"] = {**(manifest.get("provenance") or {}), "precision": {"mode": mode, "from": manifest.get("name"),
                                  "calibration": getattr(calibration, "path", None) and common.repo_relative(calibration.path)}}
        with open(os.path.join(work, series.MANIFEST), "w") as f:
            f.write(f"# R2D2 series manifest (format 1): {mode} copy written by training/quantise_series.py.\n")
            yaml.safe_dump(manifest, f, sort_keys=False, default_flow_style=None, width=120)
        os.replace(work, dst)
        work = None
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
