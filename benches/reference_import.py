"""The reference's published architectures through the importer and the engine, at 512 x 512.

    python3 benches/reference_import.py [--size 512] [--threads 2] [--memory-networks 2]
                                        [--realisations 5] [--r2d2 target/release/r2d2]

For the reference U-Net (32 channels) and U-WDSR (64 channels), 4 poolings, random weights in
the published checkpoints' layout (tests/make_reference_checkpoints.py; the published files
cannot be downloaded here):
1. the import of one checkpoint (training/import_reference.py, with its ONNX Runtime check at
   --size), its seconds;
2. one network's inference at --size, side by side: PyTorch (the reference's runtime), ONNX
   Runtime from Python, and the engine's two backends (examples/run_network.rs: native ONNX
   Runtime and tract), with each engine backend's largest difference from PyTorch relative to
   PyTorch's peak;
3. peak resident memory and wall time of `r2d2 image` with a U-Net series of --realisations
   realisations x --memory-networks networks on a simulated observation, against one
   realisation of the same series.
Build first: cargo build --release --example run_network.
"""
import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "training"))
from r2d2train import reference  # noqa: E402


def run(cmd, **kw):
    t = time.time()
    out = subprocess.run(cmd, capture_output=True, text=True, **kw)
    if out.returncode != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{out.stdout}\n{out.stderr}")
    return out, time.time() - t


def best_of(f, repeats):
    best = float("inf")
    for _ in range(repeats):
        t = time.time()
        f()
        best = min(best, time.time() - t)
    return best


def architecture(name, channels, args, work):
    ckpt, series, check = (os.path.join(work, f"{p}-{name}") for p in ("ckpt", "series", "check"))
    run([sys.executable, os.path.join(ROOT, "tests/make_reference_checkpoints.py"), ckpt, "--arch", name, "--networks", "1",
         "--channels", str(channels)])
    ckpt_file = os.path.join(ckpt, os.listdir(ckpt)[0])
    _, t_import = run([sys.executable, os.path.join(ROOT, "training/import_reference.py"), ckpt, series, "--check-size", str(args.size),
                       "--check-out", check, "--threads", str(args.threads)])
    onnx_name = [f for f in os.listdir(series) if f.endswith(".onnx")][0]
    net, *_ = reference.build_network(reference.split_layers(reference.load_checkpoint(ckpt_file)["state_dict"], ckpt_file)[1], ckpt_file)
    torch.set_num_threads(args.threads)
    x = torch.from_numpy(np.fromfile(os.path.join(check, "input.f32"), dtype=np.float32).reshape(1, 2, args.size, args.size))
    with torch.no_grad():
        t_torch = best_of(lambda: net(x), args.repeats)
    import onnxruntime as ort
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = args.threads
    session = ort.InferenceSession(os.path.join(series, onnx_name), sess_options=opts, providers=["CPUExecutionProvider"])
    t_ort_py = best_of(lambda: session.run(None, {"input": x.numpy()}), args.repeats)
    engine = {}
    expected = os.path.join(check, onnx_name.replace(".onnx", ".f32"))
    for backend in ["ort", "tract"]:
        out, _ = run([args.run_network, os.path.join(series, onnx_name), str(args.size), backend, os.path.join(check, "input.f32"), expected,
                      str(args.repeats if backend == "ort" else 1)], env={**os.environ, "RAYON_NUM_THREADS": str(args.threads)})
        engine[backend] = json.loads(out.stdout.strip().splitlines()[-1])
    with open(os.path.join(series, "manifest.yaml")) as f:
        ort_check = re.search(r"onnxruntime_relative_error: ([0-9.e+-]+)", f.read()).group(1)
    row = {"architecture": name, "channels": channels, "parameters_M": sum(p.numel() for p in net.parameters()) / 1e6,
           "checkpoint_MB": os.path.getsize(ckpt_file) / 1e6, "import_s": t_import, "pytorch_s": t_torch, "onnxruntime_python_s": t_ort_py,
           "engine_ort_s": engine["ort"]["inference_seconds"], "engine_ort_load_s": engine["ort"]["load_seconds"],
           "engine_tract_s": engine["tract"]["inference_seconds"], "engine_tract_load_s": engine["tract"]["load_seconds"],
           "engine_ort_rel_error": engine["ort"]["relative_error"], "engine_tract_rel_error": engine["tract"]["relative_error"],
           "importer_ort_rel_error": float(ort_check)}
    print(json.dumps(row), flush=True)
    return row


def memory(args, work):
    ckpt, series = os.path.join(work, "ckpt-mem"), os.path.join(work, "series-mem")
    run([sys.executable, os.path.join(ROOT, "tests/make_reference_checkpoints.py"), ckpt, "--arch", "unet", "--networks", str(args.memory_networks),
         "--realisations", str(args.realisations)])
    run([sys.executable, os.path.join(ROOT, "training/import_reference.py"), ckpt, series, "--check-size", "64"])
    obs = os.path.join(work, "obs.parquet")
    run([args.r2d2, "simulate", "--configs", "a,c", "--hours", "8,2", "--integration-s", "60", "--size", str(args.size), "--out", obs])
    rows = []
    for label, extra in [("all", []), ("one", ["--set", "step.realisation=1"])]:
        yaml_text = (f"image: {{size: {args.size}}}\nthreads: {args.threads}\nstages:\n  read: {{kind: parquet, files: {obs}, to: weights}}\n"
                     f"  weights: {{kind: weighting, scheme: briggs, robust: 0, to: grid}}\n  grid: {{kind: gridder, to: step}}\n"
                     f"  step: {{kind: onnx, series: {series}, backend: ort, to: update}}\n  update: {{kind: residual, to: step, done: write}}\n"
                     f"  write: {{kind: writer, prefix: \"{work}/out-{label}/{{job}}\"}}\n")
        path = os.path.join(work, f"{label}.yaml")
        with open(path, "w") as f:
            f.write(yaml_text)
        out, wall = run(["/usr/bin/time", "-v", args.r2d2, "run", path] + extra)
        peak = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr).group(1)) / 1024
        rows.append({"run": label, "realisations": args.realisations if label == "all" else 1, "networks_each": args.memory_networks,
                     "wall_s": wall, "peak_rss_MB": peak})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--realisations", type=int, default=5)
    ap.add_argument("--memory-networks", type=int, default=2)
    ap.add_argument("--architectures", nargs="+", default=["unet", "uwdsr"])
    ap.add_argument("--skip-memory", action="store_true")
    ap.add_argument("--r2d2", default=os.path.join(ROOT, "target/release/r2d2"))
    ap.add_argument("--run-network", default=os.path.join(ROOT, "target/release/examples/run_network"))
    ap.add_argument("--work", default=None)
    args = ap.parse_args()
    work = args.work or tempfile.mkdtemp(prefix="r2d2-reference-")
    os.makedirs(work, exist_ok=True)
    channels = {"unet": 32, "uwdsr": 64}
    rows = [architecture(a, channels[a], args, work) for a in args.architectures]
    print(f"\nper network at {args.size}^2, {args.threads} threads (best of {args.repeats}; tract once):")
    print(f"{'arch':<6} {'params':>7} {'import':>7} {'PyTorch':>8} {'ORT py':>7} {'engine ORT':>10} {'tract':>7} {'tract/ORT':>9} {'ORT/PyTorch':>11} {'rel.err ORT':>11} {'tract':>9}")
    for r in rows:
        print(f"{r['architecture']:<6} {r['parameters_M']:>6.1f}M {r['import_s']:>6.1f}s {r['pytorch_s']:>7.2f}s {r['onnxruntime_python_s']:>6.2f}s "
              f"{r['engine_ort_s']:>9.2f}s {r['engine_tract_s']:>6.2f}s {r['engine_tract_s'] / r['engine_ort_s']:>9.2f} "
              f"{r['engine_ort_s'] / r['pytorch_s']:>11.2f} {r['engine_ort_rel_error']:>11.1e} {r['engine_tract_rel_error']:>9.1e}")
    if not args.skip_memory:
        mem = memory(args, work)
        print(f"\nU-Net series, {args.memory_networks} networks per realisation, at {args.size}^2: "
              + "; ".join(f"{m['realisations']} realisation(s): {m['wall_s']:.1f} s, peak {m['peak_rss_MB']:.0f} MB" for m in mem)
              + f" (peak ratio {mem[0]['peak_rss_MB'] / mem[1]['peak_rss_MB']:.2f})")


if __name__ == "__main__":
    main()
