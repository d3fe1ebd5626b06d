"""Write the tiny ONNX networks the tests use (no training: their effect is known analytically).

    python3 tests/make_test_models.py OUT_DIR [--gain G [--first-gain G1]]

OUT_DIR/
  landweber/        R2D2 series of 4 networks, manifest: a 1x1 convolution returning
                    G x (the residual channel) + 0.01, so that with the reference loop
                    x_i = max(0, x_{i-1} + G r_{i-1} + 0.01 alpha_i): projected Landweber
                    plus a term that shows the normalisation alpha is applied and undone.
                    G (default 0.5) must be below 2 / ||D|| for the iterations to converge:
                    tests on real observations pass 1 / ||D||.
                    Network 1 reads channel 0 (the dirty image), the others channel 1.
  landweber-ref/    the same networks under the reference file names R2D2_UNet_N{i}.onnx,
                    no manifest.
  r3d3/             R3D3 series, 2 components of 3 layers (reference names): each layer
                    returns 0.5 x channel 0 (the residual), no bias.
  unet.onnx         a small random U-Net (3x3 convs, instance norm, LeakyReLU, average pooling,
                    transposed convolution, skip concatenation, 1x1 output conv): the backend
                    comparison (16 and 32 channels).
  unet-external.onnx  the same U-Net with its weights in unet-external.onnx.data (ONNX
                    external data).
  bad-*.onnx        networks with a wrong input/output signature, and a corrupt file.
  fixed64.onnx      a network whose input is fixed to 64 x 64.
"""

import os
import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17


def save(graph, path, external=None):
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="r2d2-tests")
    model.ir_version = 8
    onnx.checker.check_model(model)
    if external:
        # Every weight in the side file `external` (ONNX external data).
        onnx.save(model, path, save_as_external_data=True, all_tensors_to_one_file=True, location=external, size_threshold=0)
    else:
        onnx.save(model, path)


def io(name, channels, size=("H", "W"), rank4=True):
    dims = [1, channels, *size] if rank4 else [channels, *size]
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, dims)


def conv1x1(path, weights, bias, in_channels=2, out_channels=1, size=("H", "W"), rank4_in=True):
    w = np.array(weights, dtype=np.float32).reshape(out_channels, in_channels, 1, 1)
    b = np.full(out_channels, bias, dtype=np.float32)
    node = helper.make_node("Conv", ["x", "w", "b"], ["y"], kernel_shape=[1, 1])
    graph = helper.make_graph(
        [node], "conv1x1", [io("x", in_channels, size, rank4_in)], [io("y", out_channels, size)],
        [numpy_helper.from_array(w, "w"), numpy_helper.from_array(b, "b")],
    )
    save(graph, path)


def unet(path, seed=1, external=None):
    rng = np.random.default_rng(seed)
    inits, nodes = [], []

    def weight(name, shape):
        fan_in = int(np.prod(shape[1:]))
        inits.append(numpy_helper.from_array((rng.standard_normal(shape) / np.sqrt(fan_in)).astype(np.float32), name))
        return name

    def block(x, name, cin, cout):
        nodes.append(helper.make_node("Conv", [x, weight(name + "_w", (cout, cin, 3, 3))], [name + "_c"], pads=[1, 1, 1, 1]))
        inits.append(numpy_helper.from_array(np.ones(cout, np.float32), name + "_s"))
        inits.append(numpy_helper.from_array(np.zeros(cout, np.float32), name + "_b"))
        nodes.append(helper.make_node("InstanceNormalization", [name + "_c", name + "_s", name + "_b"], [name + "_n"]))
        nodes.append(helper.make_node("LeakyRelu", [name + "_n"], [name], alpha=0.2))
        return name

    # 16 and 32 channels: some weights are over 4 KiB (mapped from the file by ONNX Runtime),
    # some under (kept in the model's skeleton), so both paths run.
    e1 = block("x", "e1", 2, 16)
    nodes.append(helper.make_node("AveragePool", [e1], ["p1"], kernel_shape=[2, 2], strides=[2, 2]))
    e2 = block("p1", "e2", 16, 32)
    nodes.append(helper.make_node("ConvTranspose", [e2, weight("up_w", (32, 16, 2, 2))], ["up"], strides=[2, 2]))
    nodes.append(helper.make_node("Concat", ["up", e1], ["cat"], axis=1))
    d1 = block("cat", "d1", 32, 16)
    inits.append(numpy_helper.from_array(np.array([0.05], np.float32), "out_b"))
    nodes.append(helper.make_node("Conv", [d1, weight("out_w", (1, 16, 1, 1)), "out_b"], ["y"]))
    graph = helper.make_graph(nodes, "unet", [io("x", 2)], [io("y", 1)], inits)
    save(graph, path, external)


def manifest(path, name, networks, architecture="r2d2", sizes=(64,), any_size=True, layers=1):
    lines = [
        "format: 1",
        f"name: {name}",
        "description: tiny analytic test series",
        "telescope: none",
        f"architecture: {architecture}",
        f"image_sizes: [{', '.join(map(str, sizes))}]",
        f"any_size: {'true' if any_size else 'false'}",
        "input_convention: reference",
        "normalisation: mean",
        f"layers: {layers}",
        "networks:",
        *[f"  - {n}" for n in networks],
    ]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main(out, gain, first_gain=None):
    os.makedirs(out, exist_ok=True)
    if first_gain is not None:
        # A series whose first network overshoots (a gain beyond Landweber's on the dirty
        # image) and whose later ones are convergent Landweber steps: the divergence guard's
        # tolerated overshoot.
        d = os.path.join(out, "overshoot")
        os.makedirs(d, exist_ok=True)
        files = [f"os{i}.onnx" for i in range(1, 5)]
        for i, f in enumerate(files, 1):
            conv1x1(os.path.join(d, f), [first_gain, 0.0] if i == 1 else [0.0, gain], 0.0)
        manifest(os.path.join(d, "manifest.yaml"), "overshoot", files)
    # Landweber series: network 1 reads the dirty image (channel 0), later ones the residual (channel 1).
    for d, named in (("landweber", False), ("landweber-ref", True)):
        os.makedirs(os.path.join(out, d), exist_ok=True)
        files = []
        for i in range(1, 5):
            f = f"R2D2_UNet_N{i}.onnx" if named else f"lw{i}.onnx"
            conv1x1(os.path.join(out, d, f), [gain, 0.0] if i == 1 else [0.0, gain], 0.01)
            files.append(f)
        if not named:
            manifest(os.path.join(out, d, "manifest.yaml"), "landweber", files)
    # R3D3: layers read [residual, image]; 0.5 x residual, no bias.
    for i in range(1, 3):
        sub = os.path.join(out, "r3d3", f"R3D3_R2D2Net_3Layers_N{i}")
        os.makedirs(sub, exist_ok=True)
        for layer in range(1, 4):
            conv1x1(os.path.join(sub, f"R3D3_R2D2Net_3Layers_N{i}_L{layer}.onnx"), [0.5, 0.0], 0.0)
    unet(os.path.join(out, "unet.onnx"))
    unet(os.path.join(out, "unet-external.onnx"), external="unet-external.onnx.data")
    conv1x1(os.path.join(out, "bad-output-channels.onnx"), [0.5, 0.0, 0.0, 0.5], 0.0, out_channels=2)
    conv1x1(os.path.join(out, "bad-input-channels.onnx"), [0.5, 0.0, 0.0], 0.0, in_channels=3)
    conv1x1(os.path.join(out, "bad-rank.onnx"), [0.5, 0.0], 0.0, rank4_in=False)
    conv1x1(os.path.join(out, "fixed64.onnx"), [0.0, 0.5], 0.0, size=(64, 64))
    with open(os.path.join(out, "bad-corrupt.onnx"), "wb") as f:
        f.write(b"\x08\x07this is not a protobuf model" * 4)


if __name__ == "__main__":
    args = sys.argv[1:]
    if len(args) == 5 and args[1] == "--gain" and args[3] == "--first-gain":
        main(args[0], float(args[2]), float(args[4]))
    elif len(args) == 3 and args[1] == "--gain":
        main(args[0], float(args[2]))
    elif len(args) == 1:
        main(args[0], 0.5)
    else:
        sys.exit(__doc__)
