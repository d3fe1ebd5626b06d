#!/usr/bin/env python3
"""Evaluate a series on a held-out test set: SNR, logSNR and residual ratio per iteration for
the shipped ONNX networks, the project's CLEAN step (`r2d2 run`, Hogbom + Toeplitz residual)
and the dirty image; a table on stdout, a plot (PNG) and a JSON file in --out.

The test set comes from `r2d2 trainset --parquet` (procedural radio skies, seeds never used
for training or validation). logSNR uses a = the sample's target dynamic range (the
procedural sky's faintest emission sits at 1/DR). The CLEAN residual, computed by the Rust
Toeplitz method, is also compared with this package's D (dirty - D model): the check that
training and the engine use the same normal operator.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np
import torch
from astropy.io import fits

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from r2d2train import common, series  # noqa: E402

# `w_term: off`: the series are evaluated on the coplanar images of the set (`r2d2 trainset`:
# the series learn D as the PSF convolution it then is), and this CLEAN row is a model-only
# baseline beside them. The tables hold visibilities predicted with their w (what other
# imagers see): `benches/vs_wsclean.py` images them as a user would, w-term included.
# Each sample's own pixel and Briggs robustness (a set drawn over ranges of settings has one
# per sample; a set of one setting records it too): CLEAN images the grid the set's PSF is of.
CLEAN_YAML = """name: clean-test
image: {{size: {size}, pixel_arcsec: {pixel_arcsec!r}}}
stages:
  read: {{kind: parquet, files: "{parquet}", to: weights}}
  weights: {{kind: weighting, scheme: briggs, robust: {robust!r}, to: grid}}
  grid: {{kind: gridder, epsilon: 1.0e-6, w_term: off, to: step}}
  step: {{kind: clean, gain: 0.1, components_per_cycle: {components}, major_cycles: {cycles}, threshold: {threshold}, to: update}}
  update: {{kind: residual, method: toeplitz, to: step, done: write}}
  write: {{kind: writer, prefix: "{prefix}"}}
"""


def read_fits(path):
    return np.asarray(fits.getdata(path), dtype=np.float64).squeeze()


def run_clean(r2d2, data, k, workdir, cycles, components):
    """CLEAN one test sample with the engine; returns (model, residual) as N x N arrays."""
    n = data.size
    sigma = float(data.noise_dirty[k].std())  # image-domain noise level
    parquet = os.path.join(data.path, "vis", f"{k:05d}.parquet")
    if not os.path.exists(parquet):
        raise SystemExit(f"{parquet}: missing; make the test set with `r2d2 trainset --parquet`")
    prefix = os.path.join(workdir, f"{k:05d}")
    yaml_path = os.path.join(workdir, f"clean-{k:05d}.yaml")
    with open(os.path.join(data.path, "samples.json")) as f:
        sample = json.load(f)[k]
    if sample.get("index", k) != k or "pixel_arcsec" not in sample:
        raise SystemExit(f"{data.path}/samples.json: row {k} has no pixel_arcsec of sample {k}")
    with open(yaml_path, "w") as f:
        f.write(CLEAN_YAML.format(size=n, parquet=parquet, prefix=prefix, cycles=cycles, components=components, threshold=sigma,
                                  pixel_arcsec=float(sample["pixel_arcsec"]), robust=float(sample.get("robust", 0.0))))
    proc = subprocess.run([r2d2, "-q", "run", yaml_path], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"r2d2 run {yaml_path} failed:\n{proc.stderr}")
    return read_fits(prefix + "-model.fits"), read_fits(prefix + "-residual.fits"), read_fits(prefix + "-dirty.fits")


def evaluate(series_dir, test_dir, r2d2, out, clean_cycles=10, clean_components=2000, limit=None, threads=2):
    manifest = series.read_manifest(series_dir)
    if not manifest or not manifest["networks"]:
        raise SystemExit(f"{series_dir}: no networks in the manifest")
    data = common.Dataset(test_dir, limit)
    os.makedirs(out, exist_ok=True)
    rows = []

    def row(method, iteration, x, r):
        m = {"method": method, "iteration": iteration, **common.metrics(x, r, data)}
        rows.append(m)
        return m

    row("dirty", 0, data.dirty, data.dirty)
    # The series, through the shipped ONNX files (what the engine runs).
    x, r = torch.zeros_like(data.dirty), data.dirty.clone()
    per_sample_final = None
    for i, name in enumerate(manifest["networks"], start=1):
        run = series.oriented(series.onnx_runner(os.path.join(series_dir, name), threads), series.orientation(manifest, i))
        x = common.update(i, run, data.dirty, x, r)
        r = common.residual(data.dirty, x, data.psf_hat)
        row("r2d2", i, x, r)
        per_sample_final = x
    # CLEAN by the engine.
    models, residuals, d_mismatch = [], [], []
    with tempfile.TemporaryDirectory(dir=out) as work:
        for k in range(len(data)):
            model, res, engine_dirty = run_clean(r2d2, data, k, work, clean_cycles, clean_components)
            models.append(model)
            residuals.append(res)
            # The engine's dirty - D model with this package's D vs the engine's Toeplitz
            # residual: the two D alone (the engine's dirty image is of the table's visibilities).
            dirty_k = torch.from_numpy(engine_dirty[None]).float()
            mine = common.residual(dirty_k, torch.from_numpy(model[None]).float(), data.psf_hat[k:k + 1])[0].double()
            d_mismatch.append(float((mine - torch.from_numpy(res)).norm() / dirty_k.double().norm()))
    clean_x = torch.from_numpy(np.stack(models)).float()
    clean_r = torch.from_numpy(np.stack(residuals)).float()
    row("clean", clean_cycles, clean_x, clean_r)

    report = {"series": manifest["name"], "test_set": common.repo_relative(test_dir), "samples": len(data),
              "clean": {"major_cycles": clean_cycles, "components_per_cycle": clean_components, "gain": 0.1,
                        "threshold": "1 x std of the back-projected noise"},
              "python_d_vs_engine_residual_max_rel": max(d_mismatch), "rows": rows}
    with open(os.path.join(out, "test-metrics.json"), "w") as f:
        json.dump(report, f, indent=2)
    print(f"{manifest['name']} on {len(data)} held-out test samples ({test_dir}); means over samples")
    print(f"{'method':<8} {'iter':>4} {'SNR dB':>8} {'logSNR dB':>10} {'res. ratio':>10}")
    for m in rows:
        print(f"{m['method']:<8} {m['iteration']:>4} {m['snr_db']:>8.2f} {m['logsnr_db']:>10.2f} {m['residual_ratio']:>10.4f}")
    print(f"max |(dirty - D_python model) - engine residual| / |dirty| over samples: {max(d_mismatch):.2e}")
    plot(rows, data, per_sample_final, clean_x, os.path.join(out, "test-metrics.png"), manifest["name"])
    return report


def plot(rows, data, r2d2_x, clean_x, path, name):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 4, figsize=(16, 7.5))
    series_rows = [m for m in rows if m["method"] == "r2d2"]
    its = [m["iteration"] for m in series_rows]
    for ax, key, label in zip(axes[0, :3], ["snr_db", "logsnr_db", "residual_ratio"], ["SNR (dB)", "logSNR (dB)", "residual ratio"]):
        ax.plot(its, [m[key] for m in series_rows], "o-", label="R2D2 series")
        for method, style in [("clean", "--"), ("dirty", ":")]:
            v = [m[key] for m in rows if m["method"] == method][0]
            ax.axhline(v, ls=style, color="k" if method == "clean" else "grey", label=f"{method}")
        ax.set_xlabel("iteration")
        ax.set_title(label)
        ax.grid(alpha=0.3)
        if key == "residual_ratio":
            ax.set_yscale("log")
    axes[0, 0].legend()
    axes[0, 3].axis("off")
    # One sample in log scale: truth, dirty, CLEAN model, R2D2.
    k = 0
    a = float(data.dynamic_range[k])
    show = lambda img: common.rlog(img[None], torch.tensor([a], dtype=torch.float64))[0].numpy()
    for ax, (title, img) in zip(axes[1], [("truth", data.truth[k]), ("dirty", data.dirty[k]), ("CLEAN model", clean_x[k]), ("R2D2", r2d2_x[k])]):
        ax.imshow(show(img), origin="lower", cmap="inferno")
        ax.set_title(f"{title} (rlog, a = {a:.0f})")
        ax.axis("off")
    fig.suptitle(f"{name}: held-out test set ({len(data)} samples)")
    fig.tight_layout()
    fig.savefig(path + ".tmp.png", dpi=80)
    os.replace(path + ".tmp.png", path)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--series", required=True)
    p.add_argument("--test", required=True, help="test set directory (r2d2 trainset --parquet)")
    p.add_argument("--r2d2", default="target/release/r2d2", help="the engine's binary")
    p.add_argument("--out", required=True, help="directory for test-metrics.json/.png")
    p.add_argument("--clean-cycles", type=int, default=10)
    p.add_argument("--clean-components", type=int, default=2000)
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--update-manifest", action="store_true", help="record the series' rows as the manifest's `test`")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    report = evaluate(a.series, a.test, a.r2d2, a.out, a.clean_cycles, a.clean_components, a.limit, a.threads)
    if a.update_manifest:
        manifest = series.read_manifest(a.series)
        manifest["test"] = [{"iteration": m["iteration"], **{k: round(m[k], 4) for k in ("snr_db", "logsnr_db", "residual_ratio")}}
                            for m in report["rows"] if m["method"] == "r2d2"]
        manifest["provenance"]["test_data"] = {"path": common.repo_relative(a.test), "samples": report["samples"],
                                               "clean_baseline": [{k: round(m[k], 4) if isinstance(m[k], float) else m[k] for k in m}
                                                                  for m in report["rows"] if m["method"] != "r2d2"]}
        series.write_manifest(a.series, manifest)


if __name__ == "__main__":
    main()
