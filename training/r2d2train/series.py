"""A series directory (models/<series>/): manifest (format 1, docs/models.md), ONNX
networks, PyTorch weights for resuming, all written to a temporary name and renamed."""
import os
import re

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


class _PlainDumper(yaml.SafeDumper):
    """Writes a value shared by two keys twice, never as a YAML anchor and alias."""

    def ignore_aliases(self, data):
        return True


_KEY_LINE = re.compile(r"^( *)([A-Za-z_][\w-]*):")


def _key_lines(lines):
    """(line index, key path) of each `key:` line of block-style YAML, the path from the
    indentation of the keys above it."""
    stack = []
    for i, line in enumerate(lines):
        m = _KEY_LINE.match(line)
        if not m:
            continue
        indent = len(m.group(1))
        while stack and stack[-1][0] >= indent:
            stack.pop()
        stack.append((indent, m.group(2)))
        yield i, tuple(k for _, k in stack)


def _trailing_comment(line):
    """The `  # ...` ending a line, outside quotes, or None."""
    quote = None
    for j, c in enumerate(line):
        if quote:
            quote = None if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c == "#" and line[j - 2:j] == "  ":
            return line[j - 2:]
    return None


def _carry_comments(old_text, new_text):
    """The hand-written comments ending key lines of the manifest being replaced, put back
    on the same keys of the new one: they say why a value was chosen, which a YAML dump drops."""
    def unique(lines):
        # Keys of list items (`- key:`) and of wrapped flow mappings share paths: only a key
        # line whose path is its own is carried.
        paths = list(_key_lines(lines))
        counts = {}
        for _, path in paths:
            counts[path] = counts.get(path, 0) + 1
        return [(i, path) for i, path in paths if counts[path] == 1]

    old_lines = old_text.split("\n")
    comments = {}
    for i, path in unique(old_lines):
        c = _trailing_comment(old_lines[i])
        if c:
            comments[path] = c
    new_lines = new_text.split("\n")
    for i, path in unique(new_lines):
        if path in comments and _trailing_comment(new_lines[i]) is None:
            new_lines[i] += comments[path]
    carried = "\n".join(new_lines)
    # A comment after a value the dump wrapped onto the next line would change that value:
    # then the manifest is written without the comments.
    try:
        same = yaml.safe_load(carried) == yaml.safe_load(new_text)
    except yaml.YAMLError:
        same = False
    return carried if same else new_text


def write_manifest(series_dir, manifest):
    path = os.path.join(series_dir, MANIFEST)
    tmp = path + ".tmp"
    text = ("# R2D2 series manifest (format 1). Written by training/train.py; test metrics by training/evaluate.py.\n"
            + yaml.dump(manifest, Dumper=_PlainDumper, sort_keys=False, default_flow_style=None, width=120))
    if os.path.exists(path):
        with open(path) as f:
            text = _carry_comments(f.read(), text)
    try:
        with open(tmp, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _span(values):
    """[low, high] of values that are numbers or [low, high] pairs."""
    flat = [float(x) for v in values for x in (v if isinstance(v, (list, tuple)) else [v])]
    return [min(flat), max(flat)]


def domain(train_meta, size):
    """The manifest's `validity:` from what the series was trained on: the union of the
    training sets' settings (`trainset.json` of each set). Sets written before a setting was
    recorded had the then-fixed value: VLA, A 5..10 h + C 1..3 h, Briggs."""
    sets = train_meta.get("sets", [train_meta])
    tracks = [s.get("track_hours", {"a": [5.0, 10.0], "c": [1.0, 3.0]}) for s in sets]
    return {
        "telescopes": sorted({s.get("telescope", "vla") for s in sets}),
        "image_sizes": [size],
        "superresolution": _span(s["superresolution"] for s in sets),
        "weighting": sorted({s["weighting"]["scheme"] for s in sets}),
        "robust": _span(s["weighting"]["robust"] for s in sets),
        "dynamic_range": _span(s["dynamic_range"] for s in sets),
        # Every configuration of a sample is observed in turn: a track is their sum.
        "track_hours": [min(sum(h[0] for h in t.values()) for t in tracks), max(sum(h[1] for h in t.values()) for t in tracks)],
        "integration_s": _span(s["integration_s"] for s in sets),
    }


def central(validity):
    """The series' own setting (what a job that sets none uses): the middle of each range,
    rounded to the reference's usual values (SR 1.5 and Briggs 0 where the range holds them)."""
    sr, robust = validity["superresolution"], validity["robust"]
    return (1.5 if sr[0] <= 1.5 <= sr[1] else sr[0]), (0.0 if robust[0] <= 0.0 <= robust[1] else robust[0])


def new_manifest(name, model, size, description, provenance, validity):
    sr, robust = central(validity)
    return {
        "format": 1,
        "name": name,
        "description": description,
        "telescope": validity["telescopes"][0],
        "architecture": "r2d2",
        "network": config_record(model),
        "image_sizes": [size],
        "any_size": True,
        "superresolution": sr,
        "weighting": {"scheme": validity["weighting"][0], "robust": robust},
        "dynamic_range": validity["dynamic_range"],
        "validity": validity,
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


def network_config(manifest, i):
    """(kind, base_channels, poolings, norm) of network i: its own record where a later stage
    changed the architecture (`provenance.networks[].network`), else the series'."""
    for n in manifest["provenance"]["networks"]:
        if n["iteration"] == i and "network" in n:
            c = n["network"]
            return c.get("kind", "unet"), c["base_channels"], c["poolings"], c.get("norm", "instance")
    return network_kind(manifest), manifest["network"]["base_channels"], manifest["network"]["poolings"], network_norm(manifest)


def config_record(model):
    """The manifest's description of a network: kind, channels, poolings, norm, parameters."""
    return {"kind": "uwdsr" if isinstance(model, UWDSR) else "unet", "base_channels": model.base_channels,
            "poolings": model.poolings, "norm": getattr(model, "norm", "none"), "parameters": parameter_count(model)}


def load_network(series_dir, manifest, i):
    """Network i of a series, built with its own architecture (`network_config`)."""
    kind, channels, poolings, norm = network_config(manifest, i)
    return load_model(series_dir, i, channels, poolings, norm, kind)


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


# The manifest's `orientation_cycle` entries (the engine's `series::Orientation`, images
# [..., y, x]): the axes reversed first, then whether the image is transposed.
ORIENTATIONS = {
    "identity": ((), False), "mirror_x": ((-1,), False), "mirror_y": ((-2,), False), "rotate_180": ((-2, -1), False),
    "transpose": ((), True), "rotate_90": ((-1,), True), "rotate_270": ((-2,), True), "anti_transpose": ((-2, -1), True),
}


def orientation(manifest, i):
    """The orientation network i (1-based) sees its images in, as the engine turns them: entry
    (i - 1) mod the length of the manifest's `orientation_cycle` (none: `identity`)."""
    cycle = manifest.get("orientation_cycle") or []
    name = cycle[(i - 1) % len(cycle)] if cycle else "identity"
    if name not in ORIENTATIONS:
        raise SystemExit(f"orientation_cycle: unknown orientation {name!r} (expected one of {', '.join(ORIENTATIONS)})")
    return name


def turn(batch, name):
    """A batch of images [..., y, x] turned to orientation `name`."""
    axes, transposed = ORIENTATIONS[name]
    out = torch.flip(batch, axes) if axes else batch
    return out.transpose(-2, -1) if transposed else out


def turn_back(batch, name):
    """The inverse of `turn`."""
    axes, transposed = ORIENTATIONS[name]
    out = batch.transpose(-2, -1) if transposed else batch
    return torch.flip(out, axes) if axes else out


def oriented(run, name):
    """`run` (a batch of network inputs -> outputs) with its inputs turned to orientation `name`
    and its outputs turned back."""
    if name == "identity":
        return run
    return lambda batch: turn_back(run(turn(batch, name).contiguous()), name)


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
