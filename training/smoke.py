#!/usr/bin/env python3
"""Smoke run of the whole training path in seconds (CI: tests/training.rs runs it).

Tiny data (4 training truths, 2 validation and 2 test procedural skies, 64 x 64) made by the
engine, two networks of one epoch, ONNX export, manifest, a resume that adds a third network (a second stage: early_stop_from),
on a copy, a stage validated on other skies (its baseline replayed on them) and one on other training data,
and the evaluation (series, engine CLEAN, dirty) -- with checks that fail loudly: a missing
Python package is an ImportError and a non-zero exit, never a skip.
"""
import argparse
import ast
import os
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

# Import everything up front so a missing dependency fails here, by name.
import numpy as np  # noqa: E402
import onnx  # noqa: E402
import onnxruntime  # noqa: E402,F401
import scipy  # noqa: E402,F401
import skimage  # noqa: E402,F401
import torch  # noqa: E402,F401
import yaml  # noqa: E402,F401
import astropy  # noqa: E402,F401
import matplotlib  # noqa: E402,F401

import evaluate  # noqa: E402
from r2d2train import series  # noqa: E402


def run(cmd):
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def check(cond, msg):
    if not cond:
        raise SystemExit(f"smoke check failed: {msg}")


def check_crop_loss():
    """train.crop_loss with a log weight equals the L1 plus the weighted L1 of common.rlog images."""
    from train import crop_loss
    from r2d2train.common import rlog
    g = torch.Generator().manual_seed(3)
    truth, pred = torch.rand(2, 1, 16, 16, generator=g) ** 4, torch.rand(2, 1, 16, 16, generator=g) ** 4 - 0.1
    a = torch.tensor([1e3, 1e4], dtype=torch.float64)
    peak = truth.amax(dim=(-2, -1), keepdim=True)
    # The loss normalises both images by the truth's peak; rlog each by its own: equal
    # peaks make the two the same transform.
    pred = torch.minimum(pred, 0.9 * peak)
    pred[..., 0, 0] = peak[..., 0, 0]
    want = (pred - truth).abs().mean() + 0.5 * (rlog(pred[:, 0], a) - rlog(truth[:, 0], a)).abs().mean()
    got = crop_loss(pred, truth, peak, a.float().view(-1, 1, 1, 1), 0.5)
    check(abs(float(got) - float(want)) < 1e-5 * float(want), f"crop_loss {float(got)} against L1 + rlog L1 {float(want)}")


def check_orientations():
    """series.turn puts f[y][x] where the engine's `series::Orientation` does (the same
    hand-written turns of [[0, 1, 2], [3, 4, 5], [6, 7, 8]] as its test), and turn_back undoes it."""
    f = torch.arange(9.0).reshape(1, 1, 3, 3)
    expected = {
        "identity": [0, 1, 2, 3, 4, 5, 6, 7, 8], "mirror_x": [2, 1, 0, 5, 4, 3, 8, 7, 6],
        "mirror_y": [6, 7, 8, 3, 4, 5, 0, 1, 2], "rotate_180": [8, 7, 6, 5, 4, 3, 2, 1, 0],
        "transpose": [0, 3, 6, 1, 4, 7, 2, 5, 8], "rotate_90": [2, 5, 8, 1, 4, 7, 0, 3, 6],
        "rotate_270": [6, 3, 0, 7, 4, 1, 8, 5, 2], "anti_transpose": [8, 5, 2, 7, 4, 1, 6, 3, 0],
    }
    check(sorted(expected) == sorted(series.ORIENTATIONS), f"orientations {sorted(series.ORIENTATIONS)}")
    for name, want in expected.items():
        got = series.turn(f, name)
        check(got.flatten().tolist() == want, f"turn {name}: {got.flatten().tolist()} against {want}")
        check(torch.equal(series.turn_back(got, name), f), f"turn_back {name} does not undo turn")
    m = {"orientation_cycle": ["mirror_x", "rotate_90"]}
    check([series.orientation(m, i) for i in (1, 2, 3)] == ["mirror_x", "rotate_90", "mirror_x"], "network k takes entry (k-1) mod the cycle's length")


def check_manifest_comments():
    """Rewriting a manifest keeps the comments that end its key lines (the why of a hand-chosen
    value), on the same key path, and takes no '#' inside quotes for one."""
    with tempfile.TemporaryDirectory() as d:
        with open(os.path.join(d, series.MANIFEST), "w") as f:
            f.write("format: 1\nvalidity:\n  robust: [-1.0, 0.0]  # -1 measured\nnote: 'a  # b'\nrobust: 2\n"
                    "items:\n- {limit: 1}\n- limit: 2  # one item's\n")
        m = series.read_manifest(d)
        m["test"] = [{"iteration": 1}]
        series.write_manifest(d, m)
        text = open(os.path.join(d, series.MANIFEST)).read()
        check("  robust: [-1.0, 0.0]  # -1 measured\n" in text, f"the nested key's comment is kept:\n{text}")
        check("\nrobust: 2\n" in text, f"the same key elsewhere gets no comment:\n{text}")
        check("one item's" not in text, f"a list item's key is not carried to other items:\n{text}")
        check(series.read_manifest(d) == m, "the rewritten manifest reads back as written")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--r2d2", required=True, help="the engine's binary")
    p.add_argument("--keep", default=None, help="work here instead of a temporary directory")
    a = p.parse_args(argv)
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        d = a.keep or tmp
        os.makedirs(d, exist_ok=True)
        common = ["--size", "64", "--integration-s", "1800", "--epsilon", "1e-6", "--threads", "2"]
        run([py, os.path.join(HERE, "prepare_truths.py"), "--count", "4", "--size", "64", "--seed", "3", "--out", f"{d}/truths"])
        run([a.r2d2, "-q", "trainset", "--truths", f"{d}/truths", "--seed", "3", *common, "--out", f"{d}/train"])
        run([a.r2d2, "-q", "trainset", "--procedural", "2", "--seed", "50", *common, "--out", f"{d}/val"])
        run([a.r2d2, "-q", "trainset", "--procedural", "2", "--seed", "90", "--parquet", *common, "--out", f"{d}/test"])
        sdir = f"{d}/series"
        train = [py, os.path.join(HERE, "train.py"), "--train", f"{d}/train", "--val", f"{d}/val", "--series", sdir,
                 "--work", f"{d}/checkpoints", "--epochs-first", "1", "--epochs", "1", "--batch", "2", "--bf16",
                 "--min-gain-db", "-1000"]  # accept every network: the check is the path, not the quality
        run(train + ["--max-networks", "2"])
        m = series.read_manifest(sdir)
        check(m["format"] == 1 and m["architecture"] == "r2d2" and m["layers"] == 1, "manifest header")
        check(m["networks"] == ["R2D2_UNet_N1.onnx", "R2D2_UNet_N2.onnx"], f"networks {m['networks']}")
        check([v["iteration"] for v in m["validation"]] == [1, 2], "validation rows")
        for name in m["networks"]:
            g = onnx.load(os.path.join(sdir, name))
            check(any(o.version == 17 for o in g.opset_import), f"{name}: opset 17")
            dims = [dd.dim_param or dd.dim_value for dd in g.graph.input[0].type.tensor_type.shape.dim]
            check(len(g.graph.input) == 1 and dims[:2] == [1, 2] and all(isinstance(x, str) for x in dims[2:]),
                  f"{name}: input [1,2,H,W] with dynamic H, W; got {dims}")
        # Refuses to overwrite without --resume; --resume adds network 3.
        refused = subprocess.run(train + ["--max-networks", "3"], capture_output=True, text=True)
        check(refused.returncode != 0 and "--resume" in refused.stderr, "training over an existing series without --resume")
        # Network 3 is a second stage (another loss): the early stop applies from it on.
        check("early_stop_from" not in series.read_manifest(sdir), "a one-stage series has no early_stop_from")
        shutil.copytree(sdir, f"{d}/series-other-data")
        run(train + ["--max-networks", "3", "--resume", "--loss-projection", "leaky"])
        m = series.read_manifest(sdir)
        check(len(m["networks"]) == 3, "resume added a third network")
        check(m.get("early_stop_from") == 3, f"a second stage from network 3: early_stop_from {m.get('early_stop_from')}")
        # A stage whose networks all exist has nothing to do: no replay either.
        idle = subprocess.run(train + ["--max-networks", "3", "--resume"], capture_output=True, text=True, check=True)
        check("nothing to train" in idle.stdout and "replay" not in idle.stdout, "a resume with every network there replayed")
        # A resume reads the replayed estimates from the cache; they equal a fresh replay. (A
        # fourth network is trained and refused by the stopping rule: the series keeps three.)
        # The cache holds the training's own PyTorch updates; a fresh replay on the CPU runs the
        # ONNX exports through ONNX Runtime, so this also checks that both give the same x.
        cache = f"{d}/checkpoints/replay"
        read_cache = lambda where: {name: torch.load(os.path.join(where, name), weights_only=True) for name in sorted(os.listdir(where))}
        max_relative = lambda ours, reference: float((ours - reference).abs().max() / reference.abs().max())
        refuse4 = train + ["--max-networks", "4", "--resume", "--min-gain-db", "1000"]
        resumed = subprocess.run(refuse4, capture_output=True, text=True, check=True)
        check("(6 of 6 samples read from the cache)" in resumed.stdout and "replayed N" not in resumed.stdout,
              f"resume did not use the replay cache: {resumed.stdout}")
        check(len(series.read_manifest(sdir)["networks"]) == 3, "the stopping rule kept the series at three networks")
        cached = read_cache(cache)
        check(len(cached) == 2, f"one cache file per set (training, validation): {sorted(cached)}")
        shutil.rmtree(cache)
        run(refuse4)
        fresh = read_cache(cache)
        check(sorted(cached) == sorted(fresh), "replay cache keys")
        for name in fresh:
            check(torch.equal(cached[name]["active"], fresh[name]["active"]), f"{name}: pruning")
            err = max_relative(cached[name]["x"], fresh[name]["x"])
            check(err < 1e-5, f"cached {name} differs from a fresh replay by {err:.2e}")
        # A stage that adds a set to the training data replays that set only, and what it
        # replays equals a fresh replay of the set alone.
        at = train.index("--train") + 2
        added = subprocess.run(train[:at] + [f"{d}/test"] + train[at:] + ["--max-networks", "4", "--resume", "--min-gain-db", "1000"],
                               capture_output=True, text=True, check=True)
        check("replayed N3 over 2 training samples" in added.stdout and "(6 of 8 samples read from the cache)" in added.stdout,
              f"a set added to the training data: {added.stdout}")
        with_test = read_cache(cache)
        only_test = train[:at - 1] + [f"{d}/test"] + train[at:]
        only_test[only_test.index("--work") + 1] = f"{d}/checkpoints-test"
        run(only_test + ["--max-networks", "4", "--resume", "--min-gain-db", "1000"])
        alone = read_cache(f"{d}/checkpoints-test/replay")
        new_sets = [name for name in with_test if name not in fresh]
        check(len(new_sets) == 1 and new_sets[0] in alone, f"the added set's cache: {sorted(with_test)} against {sorted(alone)}")
        err = max_relative(with_test[new_sets[0]]["x"], alone[new_sets[0]]["x"])
        check(err < 1e-6, f"the added set replayed beside cached sets differs from its replay alone by {err:.2e}")
        # A later stage validated on other skies (same loss and training data): its networks
        # are compared with the series replayed on that set (rows measured on another set are
        # not comparable) and record the set; a validation set alone is no stage boundary.
        odir = f"{d}/series-other-data"
        other = lambda x: x.replace(sdir, odir).replace(f"{d}/checkpoints", f"{d}/checkpoints-other")
        other_val = [other(x).replace(f"{d}/val", f"{d}/test") for x in train]
        stage = subprocess.run(other_val + ["--max-networks", "3", "--resume"], capture_output=True, text=True, check=True)
        check("the baseline is the replayed series on it" in stage.stdout, "a stage on another validation set: baseline")
        replayed = [ln for ln in stage.stdout.splitlines() if "replay of N1-N2: validation" in ln]
        so_far = [ln for ln in stage.stdout.splitlines() if "series so far" in ln]
        check(len(replayed) == 1 and len(so_far) == 1, f"replay and baseline lines: {stage.stdout}")
        metrics = ast.literal_eval(replayed[0].split("validation ", 1)[1].split("; ")[0])
        logged = [float(so_far[0].split(key)[1].split(" dB")[0]) for key in ("SNR ", "logSNR ")]
        check(abs(logged[0] - metrics["snr_db"]) < 0.006 and abs(logged[1] - metrics["logsnr_db"]) < 0.006,
              f"the baseline {logged} is not the replayed series on the new set {metrics}")
        mo = series.read_manifest(odir)
        rec = mo["provenance"]["networks"][-1]
        check(len(mo["networks"]) == 3 and rec.get("validation_data", [""])[0].endswith("test") and "train_data" not in rec,
              f"network 3 of the other stage records its validation set only: {rec}")
        check("early_stop_from" not in mo, "another validation set alone made a stage boundary")
        # Then a stage on other training data: the early stop applies from it on.
        at = other_val.index("--train") + 2
        other_train = other_val[:at] + [f"{d}/val"] + other_val[at:]
        run(other_train + ["--max-networks", "4", "--resume"])
        mo = series.read_manifest(odir)
        check(len(mo["networks"]) == 4 and mo["provenance"]["networks"][-1].get("train_data", [""])[-1].endswith("val"),
              f"network 4 records the stage's training sets: {mo['provenance']['networks'][-1]}")
        check(mo.get("early_stop_from") == 4, f"a stage on other training data from network 4: early_stop_from {mo.get('early_stop_from')}")
        # A series that travelled as manifest + weights (a lent GPU sends back few files): the
        # ONNX networks rebuilt by export_onnx.py answer as the ones train.py wrote.
        probe = np.random.default_rng(0).standard_normal((1, 2, 64, 64)).astype(np.float32)
        answer = lambda path: onnxruntime.InferenceSession(path, providers=["CPUExecutionProvider"]).run(None, {"input": probe})[0]
        written = {name: answer(os.path.join(sdir, name)) for name in series.read_manifest(sdir)["networks"]}
        for name in written:
            os.remove(os.path.join(sdir, name))
        run([py, os.path.join(HERE, "export_onnx.py"), "--series", sdir])
        for name, before in written.items():
            err = float(np.abs(answer(os.path.join(sdir, name)) - before).max() / np.abs(before).max())
            check(err < 1e-5, f"{name} rebuilt from its weights differs by {err:.2e}")
        # What makes crops valid samples: the bias-free U-Net is local (a crop's interior, beyond
        # the receptive field, gets exactly the full field's output) and positively homogeneous.
        from r2d2train.unet import UNet
        torch.manual_seed(0)
        net = UNet(8, 3, norm="none").eval()
        field = torch.rand(1, 2, 192, 192)
        with torch.no_grad():
            full, part, scaled = net(field), net(field[..., 32:160, 32:160]), net(3.0 * field)
        inner = (full[..., 80:112, 80:112] - part[..., 48:80, 48:80]).abs().max() / full.abs().max()
        check(float(inner) < 1e-5, f"norm none is not local: crop interior differs by {float(inner):.2e}")
        check(float((scaled - 3.0 * full).abs().max() / full.abs().max()) < 1e-5, "norm none is not homogeneous")
        # The crop path (local, bias-free U-Net; crops of the full-field samples).
        cdir = f"{d}/series-crops"
        run([py, os.path.join(HERE, "train.py"), "--train", f"{d}/train", f"{d}/val", "--val", f"{d}/val", "--series", cdir,
             "--work", f"{d}/checkpoints-crops", "--norm", "none", "--crop", "32", "--crops-per-sample", "2", "--epochs-first", "1",
             "--batch", "2", "--max-networks", "1", "--min-gain-db", "-1000", "--loss-projection", "leaky"])
        mc = series.read_manifest(cdir)
        check(mc["network"]["norm"] == "none" and mc["provenance"]["crops"] == {"side": 32, "per_sample_and_epoch": 2}, "crop manifest")
        check(mc["provenance"]["networks"][0]["loss_projection"] == "leaky", "the network's loss projection is recorded")
        check(not any(os.path.isabs(p) for p in mc["provenance"]["train_data"]["path"]), "provenance paths are not absolute")
        # A later stage of another width (--fresh-start): refused without the flag, recorded per
        # network; the next resume warm-starts from it and replays each network at its own width.
        crops = [py, os.path.join(HERE, "train.py"), "--train", f"{d}/train", f"{d}/val", "--val", f"{d}/val", "--series", cdir,
                 "--work", f"{d}/checkpoints-crops", "--norm", "none", "--crop", "32", "--crops-per-sample", "2", "--epochs", "1",
                 "--batch", "2", "--min-gain-db", "-1000", "--resume"]
        narrow = subprocess.run(crops + ["--max-networks", "2", "--base-channels", "8"], capture_output=True, text=True)
        check(narrow.returncode != 0 and "--fresh-start" in narrow.stderr, "another width without --fresh-start is refused")
        deeper = subprocess.run(crops + ["--max-networks", "2", "--poolings", "4", "--fresh-start"], capture_output=True, text=True)
        check(deeper.returncode != 0 and "may not pool more" in deeper.stderr, "a later network pooling more than the series is refused")
        run(crops + ["--max-networks", "2", "--base-channels", "8", "--fresh-start"])
        shutil.rmtree(f"{d}/checkpoints-crops/replay")
        run(crops + ["--max-networks", "3", "--base-channels", "8"])
        mc = series.read_manifest(cdir)
        recs = mc["provenance"]["networks"]
        check(len(mc["networks"]) == 3 and mc["network"]["base_channels"] == 16 and "network" not in recs[0]
              and recs[1]["network"]["base_channels"] == 8 and recs[1].get("fresh_start") is True
              and recs[2]["network"]["base_channels"] == 8 and "fresh_start" not in recs[2],
              f"per-network widths and fresh start recorded: {recs}")
        check(series.network_config(mc, 1)[1] == 16 and series.network_config(mc, 3)[1] == 8, "network_config per network")
        # --loss-log-weight: the loss adds the L1 of the logSNR's rlog images (common.rlog), and
        # the network records its weight.
        run(crops + ["--max-networks", "4", "--base-channels", "8", "--loss-log-weight", "0.1"])
        check(series.read_manifest(cdir)["provenance"]["networks"][3].get("loss_log_weight") == 0.1, "the log weight is recorded")
        check_crop_loss()
        check_orientations()
        check_manifest_comments()
        crop_only = subprocess.run([py, os.path.join(HERE, "train.py"), "--train", f"{d}/train", "--val", f"{d}/val", "--series",
                                    f"{d}/series-bad", "--work", f"{d}/checkpoints-bad", "--crop", "32"], capture_output=True, text=True)
        check(crop_only.returncode != 0 and "--norm none" in crop_only.stderr, "--crop with instance normalisation is refused")
        # The reference's U-WDSR trains through the same path (--arch uwdsr; local, so crops).
        wdir = f"{d}/series-uwdsr"
        run([py, os.path.join(HERE, "train.py"), "--train", f"{d}/train", "--val", f"{d}/val", "--series", wdir, "--work", f"{d}/checkpoints-uwdsr",
             "--arch", "uwdsr", "--base-channels", "4", "--poolings", "2", "--crop", "32", "--epochs-first", "1", "--batch", "2",
             "--max-networks", "1", "--min-gain-db", "-1000"])
        mw = series.read_manifest(wdir)
        check(mw["network"]["kind"] == "uwdsr" and mw["network"]["norm"] == "none" and len(mw["networks"]) == 1, f"uwdsr series {mw['network']}")
        report = evaluate.evaluate(sdir, f"{d}/test", a.r2d2, f"{d}/eval", clean_cycles=2, clean_components=50)
        check([r["method"] for r in report["rows"]] == ["dirty", "r2d2", "r2d2", "r2d2", "clean"], "evaluation rows")
        # The package's D against the engine's Toeplitz residual on the same CLEAN model.
        check(report["python_d_vs_engine_residual_max_rel"] < 1e-5,
              f"Python D differs from the engine: {report['python_d_vs_engine_residual_max_rel']:.2e}")
        check(os.path.getsize(f"{d}/eval/test-metrics.png") > 1000, "plot written")
    print("training smoke run: ok")


if __name__ == "__main__":
    main()
