"""Import the reference implementation's checkpoints (basp-group/R2D2-RI v2: R2D2 U-Net or
U-WDSR series, R3D3, one realisation or several) as an ONNX series the engine runs.

    python3 training/import_reference.py CHECKPOINTS OUT [--name NAME] [--check-size 512]

CHECKPOINTS holds `<stem>_N{i}.ckpt` (e.g. R2D2_UNet_N1.ckpt .. or R2D2_UWDSR_N1.ckpt ..), or
realisation folders V1/ .. V{R}/ each holding them (r2d2train/reference.py lists the layouts).
OUT (a new directory) receives one ONNX network per checkpoint and layer (`V{r}/<stem>_N{i}.onnx`,
`_L{l}` added for R3D3 layers) and a manifest (docs/models.md) recording the source files and
their SHA-256, the architecture and its hyper-parameters, the conventions, the validity ranges
(the published series': sizes 512, SR 1.5..2.5, Briggs robust -1..1; --superresolution, --robust,
--weighting, --image-sizes set others) and the realisations. Each exported network is run by
ONNX Runtime on a random input of --check-size pixels and must reproduce PyTorch to a relative
--tolerance (max |difference| / max |PyTorch|); the figures go into the manifest.
--check-out DIR also saves that input and PyTorch's outputs (raw float32) for other backends.
OUT appears whole or not at all.
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np
import onnx
import onnxruntime as ort
import torch
import yaml

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from r2d2train import reference  # noqa: E402
from r2d2train.series import MANIFEST  # noqa: E402
from r2d2train.unet import parameter_count  # noqa: E402


def export(net, path, size):
    dummy = torch.zeros(1, 2, size, size)
    torch.onnx.export(net, (dummy,), path, input_names=["input"], output_names=["output"], opset_version=17,
                      dynamic_axes={"input": {2: "H", 3: "W"}, "output": {2: "H", 3: "W"}}, dynamo=False)
    onnx.checker.check_model(path)


def relative_error(got, expected):
    return float(np.abs(got - expected).max() / max(np.abs(expected).max(), np.finfo(np.float32).tiny))


def git_commit():
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True,
                              cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoints")
    ap.add_argument("out")
    ap.add_argument("--name", help="series name (default: OUT's directory name)")
    ap.add_argument("--telescope", default="vla")
    ap.add_argument("--image-sizes", type=int, nargs="+", default=reference.PUBLISHED_VALIDITY["image_sizes"])
    ap.add_argument("--superresolution", type=float, nargs=2, default=reference.PUBLISHED_VALIDITY["superresolution"], metavar=("MIN", "MAX"))
    ap.add_argument("--robust", type=float, nargs=2, default=reference.PUBLISHED_VALIDITY["robust"], metavar=("MIN", "MAX"))
    ap.add_argument("--weighting", nargs="+", default=reference.PUBLISHED_VALIDITY["weighting"], choices=["briggs", "uniform", "natural"])
    ap.add_argument("--check-size", type=int, default=512, help="image side of the ONNX-vs-PyTorch check (default 512)")
    ap.add_argument("--tolerance", type=float, default=1e-5)
    ap.add_argument("--check-out", help="save the check's input and PyTorch outputs (raw float32) here")
    ap.add_argument("--threads", type=int, default=0, help="PyTorch and ONNX Runtime threads (0: their default)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if os.path.exists(args.out):
        raise SystemExit(f"{args.out}: exists; importing writes a new series directory (remove it or choose another)")
    realisations, stem, in_folders = reference.discover(args.checkpoints)
    name = args.name or os.path.basename(os.path.normpath(args.out))
    parent = os.path.dirname(os.path.abspath(args.out))
    os.makedirs(parent, exist_ok=True)
    work = tempfile.mkdtemp(prefix=f".{name}.importing-", dir=parent)
    rng = np.random.default_rng(0)
    check_input = rng.random((1, 2, args.check_size, args.check_size), dtype=np.float32)
    if args.check_out:
        os.makedirs(args.check_out, exist_ok=True)
        check_input.tofile(os.path.join(args.check_out, "input.f32"))
    options = ort.SessionOptions()
    if args.threads:
        options.intra_op_num_threads = args.threads
    try:
        sources, networks, checks = [], [], []
        shape = None
        hyper = None
        for r, files in enumerate(realisations, start=1):
            listed = []
            for i, path in enumerate(files, start=1):
                ckpt = reference.load_checkpoint(path)
                if hyper is None:
                    hyper = reference.plain_hyper_parameters(ckpt)
                layers = reference.split_layers(ckpt["state_dict"], path)
                relative = os.path.relpath(path, args.checkpoints)
                sources.append({"path": relative, "sha256": reference.sha256(path), "bytes": os.path.getsize(path)})
                layer_files = []
                for l, weights in layers.items():
                    net, arch, chans, pools = reference.build_network(weights, path)
                    this = (arch, chans, pools, len(layers))
                    if shape is None:
                        shape = this
                        parameters = parameter_count(net)
                    elif this != shape:
                        raise SystemExit(f"{path}: {this} differs from the series' first network {shape} (architecture, channels, poolings, layers)")
                    if args.check_size % (1 << pools):
                        raise SystemExit(f"--check-size {args.check_size}: must be a multiple of 2^{pools} for these networks")
                    base = f"{os.path.splitext(os.path.basename(path))[0]}" + (f"_L{l}" if len(layers) > 1 else "")
                    onnx_name = (f"V{r}/" if in_folders else "") + base + ".onnx"
                    target = os.path.join(work, onnx_name)
                    os.makedirs(os.path.dirname(target), exist_ok=True)
                    export(net, target, min(args.check_size, 64))
                    with torch.no_grad():
                        expected = net(torch.from_numpy(check_input)).numpy()
                    session = ort.InferenceSession(target, sess_options=options, providers=["CPUExecutionProvider"])
                    got = session.run(None, {"input": check_input})[0]
                    error = relative_error(got, expected)
                    checks.append({"network": onnx_name, "onnxruntime_relative_error": error})
                    if not error <= args.tolerance:
                        raise SystemExit(f"{path}: ONNX Runtime output differs from PyTorch by {error:.2e} (relative) at {args.check_size}^2, above {args.tolerance:g}")
                    if args.check_out:
                        expected.astype(np.float32).tofile(os.path.join(args.check_out, onnx_name.replace("/", "-").replace(".onnx", ".f32")))
                    print(f"{relative} layer {l} -> {onnx_name} (ONNX Runtime vs PyTorch at {args.check_size}^2: {error:.1e})", flush=True)
                    layer_files.append(onnx_name)
                listed.append(layer_files[0] if len(layer_files) == 1 else layer_files)
            networks.append(listed)
        arch, chans, pools, layer_count = shape
        network = {"kind": arch, "base_channels": chans, "poolings": pools, "parameters": parameters}
        if arch == "uwdsr":
            from r2d2train import uwdsr
            network.update(residual_units=uwdsr.RESIDUAL_UNITS, blocks=uwdsr.BLOCKS, width_multiplier=uwdsr.WIDTH_MULTIPLIER, image_mean=uwdsr.IMAGE_MEAN)
        else:
            network["norm"] = "instance"
        manifest = {
            "format": 1,
            "name": name,
            "description": f"{'R2D2' if layer_count == 1 else f'R3D3 ({layer_count} layers)'} {arch} series ({chans} channels, {pools} poolings), "
                           f"{len(realisations)} realisation(s) of {len(realisations[0])} networks, imported from the reference's checkpoints '{stem}'",
            "telescope": args.telescope,
            "architecture": "r2d2" if layer_count == 1 else "r3d3",
            "network": network,
            "image_sizes": args.image_sizes,
            "any_size": True,
            "validity": {"telescopes": [args.telescope], "image_sizes": args.image_sizes, "superresolution": args.superresolution,
                         "robust": args.robust, "weighting": args.weighting},
            "input_convention": "reference",
            "normalisation": "mean",
            "layers": layer_count,
        }
        if len(realisations) == 1:
            manifest["networks"] = networks[0]
        else:
            manifest["realisations"] = networks
        manifest["provenance"] = {
            "imported_from": {
                "implementation": "basp-group/R2D2-RI v2 (PyTorch Lightning checkpoints)",
                "stem": stem,
                "layout": "V{r}/<stem>_N{i}.ckpt" if in_folders else "<stem>_N{i}.ckpt",
                "files": sources,
                "reference_conventions": {
                    "input_order": "rec_res (network 1: [dirty/a, 0], then [x/a, r/a]); R3D3 layers take [r/a, x/a]",
                    "normalisation": "a = mean of the previous estimate (of the dirty image at i = 1) + epsilon",
                    "output": "x_i = max(0, (N_i(input) + x_{i-1}/a) a)",
                },
                "hyper_parameters": hyper,
            },
            "command": "python3 training/import_reference.py " + " ".join(os.path.relpath(a) if os.path.exists(a) else a for a in sys.argv[1:]),
            "git_commit": git_commit(),
            "torch": str(torch.__version__),
            "onnxruntime": str(ort.__version__),
            "onnx_check": {"size": args.check_size, "tolerance": args.tolerance, "networks": checks},
        }
        with open(os.path.join(work, MANIFEST), "w") as f:
            f.write("# R2D2 series manifest (format 1). Written by training/import_reference.py.\n")
            yaml.safe_dump(manifest, f, sort_keys=False, default_flow_style=None, width=120)
        os.replace(work, args.out)
        work = None
        print(f"{args.out}: {len(realisations)} realisation(s) x {len(realisations[0])} networks ({arch}, {chans} channels, {pools} poolings, {layer_count} layer(s))")
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
