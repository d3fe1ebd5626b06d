"""Write a series of R2D2 reference U-Nets with random weights, for inference benchmarks.

    python3 benches/make_reference_unet.py OUT_DIR [--channels 64] [--pools 4] [--networks 15]

The architecture is the reference one (docs: ../shared/reference/r2d2-conventions.md,
"Networks"): fastMRI-style U-Net, per level two [3x3 conv without bias, InstanceNorm,
LeakyReLU(0.2)], 2x2 average pooling down, 2x2 transposed convolution + InstanceNorm +
LeakyReLU up, `[up, skip]` concatenation, final 1x1 convolution with bias; 64 base channels and
4 poolings give 31.0 M parameters. Input `[1, 2, H, W]`, output `[1, 1, H, W]`, H and W
symbolic. The weights are random (He-scaled): only the timing and memory mean anything.

OUT_DIR gets one network file, and a manifest listing it `--networks` times (the series runs
the same network at every iteration: loading and inference cost the same as distinct files).
"""

import argparse
import os

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


def build(channels, pools, seed=0):
    rng = np.random.default_rng(seed)
    nodes, inits = [], []
    count = [0]

    def weight(shape):
        name = f"w{len(inits)}"
        fan_in = int(np.prod(shape[1:]))
        inits.append(numpy_helper.from_array((rng.standard_normal(shape) * np.sqrt(2.0 / fan_in)).astype(np.float32), name))
        count[0] += int(np.prod(shape))
        return name

    def norm_act(x, c):
        s, b = f"s{len(inits)}", f"b{len(inits)}"
        inits.append(numpy_helper.from_array(np.ones(c, np.float32), s))
        inits.append(numpy_helper.from_array(np.zeros(c, np.float32), b))
        n = x + "_n"
        nodes.append(helper.make_node("InstanceNormalization", [x, s, b], [n]))
        a = x + "_a"
        nodes.append(helper.make_node("LeakyRelu", [n], [a], alpha=0.2))
        return a

    def conv_block(x, cin, cout, tag):
        c1 = tag + "_c1"
        nodes.append(helper.make_node("Conv", [x, weight((cout, cin, 3, 3))], [c1], pads=[1, 1, 1, 1]))
        a1 = norm_act(c1, cout)
        c2 = tag + "_c2"
        nodes.append(helper.make_node("Conv", [a1, weight((cout, cout, 3, 3))], [c2], pads=[1, 1, 1, 1]))
        return norm_act(c2, cout)

    def up_block(x, cin, cout, tag):
        t = tag + "_t"
        nodes.append(helper.make_node("ConvTranspose", [x, weight((cin, cout, 2, 2))], [t], strides=[2, 2]))
        return norm_act(t, cout)

    x, ch, skips = "input", channels, []
    x = conv_block(x, 2, ch, "d0")
    skips.append(x)
    for level in range(pools):
        p = f"pool{level}"
        nodes.append(helper.make_node("AveragePool", [x], [p], kernel_shape=[2, 2], strides=[2, 2]))
        if level < pools - 1:
            x = conv_block(p, ch, ch * 2, f"d{level + 1}")
            skips.append(x)
        else:
            x = conv_block(p, ch, ch * 2, "bottom")
        ch *= 2
    for level in range(pools):
        up = up_block(x, ch, ch // 2, f"u{level}")
        cat = f"cat{level}"
        nodes.append(helper.make_node("Concat", [up, skips.pop()], [cat], axis=1))
        x = conv_block(cat, ch, ch // 2, f"uc{level}")
        ch //= 2
    bias = "out_b"
    inits.append(numpy_helper.from_array(np.zeros(1, np.float32), bias))
    count[0] += 1
    nodes.append(helper.make_node("Conv", [x, weight((1, ch, 1, 1)), bias], ["output"]))
    graph = helper.make_graph(
        nodes, "r2d2_unet",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, 2, "H", "W"])],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, [1, 1, "H", "W"])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="r2d2-bench")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model, count[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--channels", type=int, default=64)
    ap.add_argument("--pools", type=int, default=4)
    ap.add_argument("--networks", type=int, default=15)
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    model, params = build(args.channels, args.pools)
    onnx.save(model, os.path.join(args.out, "unet.onnx"))
    with open(os.path.join(args.out, "manifest.yaml"), "w") as f:
        f.write(
            "format: 1\nname: bench-unet\n"
            f"description: reference U-Net ({args.channels} channels, {args.pools} poolings, {params} parameters), random weights, for benchmarks\n"
            "architecture: r2d2\nimage_sizes: []\nany_size: true\ninput_convention: reference\nnormalisation: mean\n"
            f"network: {{kind: unet, base_channels: {args.channels}, poolings: {args.pools}, parameters: {params}}}\n"
            "networks:\n" + "".join("  - unet.onnx\n" for _ in range(args.networks))
        )
    print(f"{args.out}/unet.onnx: {params} parameters ({params / 1e6:.1f} M), series of {args.networks}")


if __name__ == "__main__":
    main()
