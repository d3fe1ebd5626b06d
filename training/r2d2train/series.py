"""A series directory (models/<series>/): manifest (format 1, docs/models.md), ONNX
networks, PyTorch weights for resuming, all written to a temporary name and renamed."""
import os

import onnx
import onnxruntime as ort
import numpy as np
import torch
import yaml

from .unet import UNet, parameter_count
from .uwdsr import UWDSR

KINDS = ("unet", "uwdsr")


def make_network(kind, base_channels, poolings, norm="instance"):
    """The project's U-Net, or the reference's U-WDSR (which has no feature normalisation)."""
    if kind == "uwdsr":
        return UWDSR(base_channels, poolings)
    return UNet(base_channels, poolings, norm=norm)


def network_kind(manifest):
    return manifest["network"].get("kind", "unet")

MANIFEST = "manifest.yaml"


def onnx_name(i):
    return f"R2D2_UNet_N{i}.onnx"


def weights_name(i):
    return os.path.join("weights", f"R2D2_UNet_N{i}.pt")


def read_manifest(series_dir):
    path = os.path.join(series_dir, MANIFEST)
    if not os.path.exists(path):
        return None
    with open(path) as f:
        m = yaml.safe_load(f)
    if m.get("format") != 1:
        raise SystemExit(f"{path}: expected format: 1, got {m.get('format')!r}")
    return m


def write_manifest(series_dir, manifest):
    path = os.path.join(series_dir, MANIFEST)
    tmp = path + ".tmp"
    try:
        with open(tmp, "w") as f:
            f.write("# R2D2 series manifest (format 1). Written by training/train.py; test metrics by training/evaluate.py.\n")
            yaml.safe_dump(manifest, f, sort_keys=False, default_flow_style=None, width=120)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def new_manifest(name, model, size, description, provenance):
    return {
        "format": 1,
        "name": name,
        "description": description,
        "telescope": "vla",
        "architecture": "r2d2",
        "network": {"kind": "uwdsr" if isinstance(model, UWDSR) else "unet", "base_channels": model.base_channels,
                    "poolings": model.poolings, "norm": getattr(model, "norm", "none"), "parameters": parameter_count(model)},
        "image_sizes": [size],
        "any_size": True,
        "superresolution": 1.5,
        "weighting": {"scheme": "briggs", "robust": 0},
        "dynamic_range": [1.0e3, 1.0e5],
        "input_convention": "reference",
        "normalisation": "mean",
        "networks": [],
        "layers": 1,
        "provenance": provenance,
        "validation": [],
        "test": [],
    }


def save_weights(series_dir, i, model):
    path = os.path.join(series_dir, weights_name(i))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    torch.save({k: v.cpu() for k, v in model.state_dict().items()}, path + ".tmp")
    os.replace(path + ".tmp", path)


def network_norm(manifest):
    """The U-Net's normalisation ("instance" for series written before the option existed)."""
    return manifest["network"].get("norm", "instance")


def load_model(series_dir, i, base_channels, poolings, norm="instance", kind="unet"):
    model = make_network(kind, base_channels, poolings, norm)
    model.load_state_dict(torch.load(os.path.join(series_dir, weights_name(i)), weights_only=True, map_location="cpu"))
    return model.eval()


def export_onnx(model, path, size):
    """[1,2,H,W] -> [1,1,H,W], opset 17, H and W dynamic; checked against PyTorch at two sizes."""
    model = model.eval()
    tmp = path + ".tmp.onnx"
    dummy = torch.randn(1, 2, size, size)
    torch.onnx.export(
        model, (dummy,), tmp, input_names=["input"], output_names=["output"], opset_version=17,
        dynamic_axes={"input": {2: "H", 3: "W"}, "output": {2: "H", 3: "W"}}, dynamo=False,
    )
    onnx.checker.check_model(onnx.load(tmp))
    session = ort.InferenceSession(tmp, providers=["CPUExecutionProvider"])
    for h, w in [(size, size), (2 * size, size + 64)]:
        x = torch.randn(1, 2, h, w)
        with torch.no_grad():
            ref = model(x).numpy()
        got = session.run(None, {session.get_inputs()[0].name: x.numpy()})[0]
        if got.shape != (1, 1, h, w) or not np.allclose(got, ref, rtol=1e-3, atol=1e-4 * np.abs(ref).max()):
            raise SystemExit(f"{path}: ONNX output differs from PyTorch at {h} x {w}")
    os.replace(tmp, path)


def onnx_runner(path, threads=2):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    session = ort.InferenceSession(path, sess_options=opts, providers=["CPUExecutionProvider"])
    name = session.get_inputs()[0].name

    def run(batch):
        # One image at a time: the shipped graphs are run with batch 1 by the engine.
        outs = [session.run(None, {name: batch[k:k + 1].numpy().astype(np.float32)})[0] for k in range(batch.shape[0])]
        return torch.from_numpy(np.concatenate(outs, axis=0))

    return run
