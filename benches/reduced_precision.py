"""Reduced-precision inference: its speed and its precision cost against float32, side by side.

    python3 benches/reduced_precision.py [--series models/vla-r2d2-512]
        [--test training/data/512/test] [--calibration training/data/512/train-radio]
        [--calibration-samples 4] [--threads 2]

1. Precision: the trained series (float32) and its int8 copies (training/r2d2train/precision.py:
   dynamic, and static calibrated on --calibration, training data) image the held-out test set
   (the series loop with ONNX Runtime, as training/evaluate.py runs it); mean SNR and logSNR of
   the final images, and their differences from float32.
2. Speed: one network's inference at the test set's size with ONNX Runtime (--threads), float32
   against each int8 copy, for the series' network and for the reference U-Net with 32
   channels (random weights: speed only).
Precision can only be judged on trained weights, hence the project's series; random-weight
networks give the speed.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import onnxruntime as ort
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "training"))
from r2d2train import common, precision, series  # noqa: E402


def final_metrics(series_dir, data, threads):
    manifest = series.read_manifest(series_dir)
    x, r = torch.zeros_like(data.dirty), data.dirty.clone()
    for i, name in enumerate(manifest["networks"], start=1):
        run = series.oriented(series.onnx_runner(os.path.join(series_dir, name), threads), series.orientation(manifest, i))
        x = common.update(i, run, data.dirty, x, r)
        r = common.residual(data.dirty, x, data.psf_hat)
    snr = common.snr(x, data.truth)
    logsnr = common.log_snr(x, data.truth, data.dynamic_range)
    return snr.numpy(), logsnr.numpy()


def inference_seconds(path, size, threads, repeats=3):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    s = ort.InferenceSession(path, sess_options=opts, providers=["CPUExecutionProvider"])
    x = np.random.default_rng(0).random((1, 2, size, size), dtype=np.float32)
    s.run(None, {"input": x})
    best = float("inf")
    for _ in range(repeats):
        t = time.time()
        s.run(None, {"input": x})
        best = min(best, time.time() - t)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--series", default=os.path.join(ROOT, "models/vla-r2d2-512"))
    ap.add_argument("--test", default=os.path.join(ROOT, "training/data/512/test"))
    ap.add_argument("--calibration", default=os.path.join(ROOT, "training/data/512/train-radio"))
    ap.add_argument("--calibration-samples", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    work = args.work or tempfile.mkdtemp(prefix="r2d2-precision-")
    os.makedirs(work, exist_ok=True)
    calibration = common.Dataset(args.calibration, args.calibration_samples)
    copies = {"float32": args.series}
    for mode in precision.MODES:
        copies[mode] = os.path.join(work, f"series-{mode}")
        if not os.path.exists(copies[mode]):
            precision.quantise_series(args.series, copies[mode], mode, calibration if mode == "int8-static" else None, args.threads)
    data = common.Dataset(args.test)
    size = data.size
    # The reference U-Net (32 channels, 4 poolings), random weights, for speed.
    ref = os.path.join(work, "reference-unet")
    if not os.path.exists(ref):
        subprocess.run([sys.executable, os.path.join(ROOT, "tests/make_reference_checkpoints.py"), ref + "-ckpt", "--arch", "unet", "--networks", "1"], check=True)
        subprocess.run([sys.executable, os.path.join(ROOT, "training/import_reference.py"), ref + "-ckpt", ref, "--check-size", "64"], check=True,
                       capture_output=True)
    ref_net = os.path.join(ref, "R2D2_UNet_N1.onnx")
    from onnxruntime import quantization as q
    ref_copies = {"float32": ref_net, "int8-dynamic": os.path.join(work, "reference-int8-dynamic.onnx")}
    if not os.path.exists(ref_copies["int8-dynamic"]):
        q.quantize_dynamic(ref_net, ref_copies["int8-dynamic"], weight_type=q.QuantType.QInt8)
    rows = {}
    for mode, d in copies.items():
        snr, logsnr = final_metrics(d, data, args.threads)
        first = series.read_manifest(d)["networks"][0]
        rows[mode] = {"snr_db": float(snr.mean()), "logsnr_db": float(logsnr.mean()), "per_sample_snr": snr.tolist(), "per_sample_logsnr": logsnr.tolist(),
                      "series_network_s": inference_seconds(os.path.join(d, first), size, args.threads),
                      "reference_unet_s": inference_seconds(ref_copies[mode], size, args.threads) if mode in ref_copies else None}
        print(json.dumps({mode: rows[mode]}), flush=True)
    base = rows["float32"]
    print(f"\n{len(data)} held-out {size}^2 test skies, series {os.path.basename(os.path.normpath(args.series))}, ONNX Runtime {ort.__version__}, {args.threads} threads")
    print(f"{'precision':<13} {'SNR dB':>7} {'dSNR':>7} {'max|dSNR|':>9} {'logSNR':>7} {'dlogSNR':>8} {'series net s':>12} {'speed-up':>8} {'ref U-Net s':>11} {'speed-up':>8}")
    for mode, r in rows.items():
        d_snr = np.abs(np.array(r["per_sample_snr"]) - np.array(base["per_sample_snr"])).max()
        ref_s = r["reference_unet_s"]
        print(f"{mode:<13} {r['snr_db']:>7.2f} {r['snr_db'] - base['snr_db']:>+7.3f} {d_snr:>9.3f} {r['logsnr_db']:>7.2f} {r['logsnr_db'] - base['logsnr_db']:>+8.3f} "
              f"{r['series_network_s']:>12.3f} {base['series_network_s'] / r['series_network_s']:>8.2f} "
              + (f"{ref_s:>11.3f} {base['reference_unet_s'] / ref_s:>8.2f}" if ref_s else f"{'-':>11} {'-':>8}"))
    with open(os.path.join(work, "reduced-precision.json"), "w") as f:
        json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
