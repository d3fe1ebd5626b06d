#!/usr/bin/env python3
"""Sequential training of an R2D2 series (paper Section 3; conventions file, "Training").

Network i learns from (truth, x_{i-1}, r_{i-1}) divided by alpha = mean(x_{i-1}) (mean of the
dirty image for i = 1); loss mean L1 between truth/alpha and max(0, x_{i-1}/alpha + N_i(.));
RMSprop, learning rate 1e-4; network i starts from network i-1's weights. After each network
the training pairs whose residual reached the noise level (||r||^2 <= ||b||^2) are pruned, the
network is exported to ONNX and the manifest gets its validation metrics; the series stops
growing when validation SNR and logSNR stop improving.

Checkpoints: every finished network is in the series directory (ONNX + PyTorch weights +
manifest) and every epoch in --work; --resume continues an interrupted network or adds
networks to an existing series (the previous networks are replayed to rebuild x and r).
"""
import argparse
import hashlib
import itertools
import math
import os
import subprocess
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from r2d2train import common, series  # noqa: E402


# The slope of `--loss-projection leaky` below zero: small enough that the loss treats a
# negative output almost as the clipped loss does (as zero), large enough to leave a gradient.
LEAKY_SLOPE = 0.01


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def git_commit():
    try:
        here = os.path.dirname(os.path.abspath(__file__))
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def commit_series(series_dir, message):
    """Commit only the series directory, so a long run leaves every finished network usable."""
    try:
        subprocess.run(["git", "add", "--", "."], cwd=series_dir, check=True)
        subprocess.run(["git", "commit", "-q", "-m", message, "--", "."], cwd=series_dir, check=True)
    except (OSError, subprocess.CalledProcessError) as e:
        log(f"warning: could not commit {series_dir}: {e}")


def replay_keys(args, manifest, networks, data):
    """One key per set of `data`: what the set's replayed estimates depend on (each network's
    weights and orientation, the set's records and how many of its samples are taken). Cached
    per set, a stage that adds a set to those of the last replays only the new one."""
    h = hashlib.sha256()
    for k in range(1, networks + 1):
        with open(os.path.join(args.series, series.weights_name(k)), "rb") as f:
            h.update(hashlib.sha256(f.read()).digest())
        if series.orientation(manifest, k) != "identity":
            h.update(series.orientation(manifest, k).encode())
    keys = []
    for path, count in data.parts:
        key = h.copy()
        key.update(os.path.abspath(path).encode())
        # A set regenerated at the same path (another generator, other seeds) is other data:
        # its records (trainset.json holds the run's parameters and timings) change the key.
        for record in ("samples.json", "trainset.json"):
            record_path = os.path.join(path, record)
            if os.path.exists(record_path):
                with open(record_path, "rb") as f:
                    key.update(hashlib.sha256(f.read()).digest())
        key.update(repr((count, networks)).encode())
        keys.append(key.hexdigest())
    return keys


def spans(data):
    """(start, end) of each set's samples in `data`."""
    ends = list(itertools.accumulate(count for _, count in data.parts))
    return list(zip([0] + ends[:-1], ends))


def replay_path(work, key):
    return os.path.join(work, "replay", f"{key}.pt")


def load_replay(work, data, keys):
    """The replayed estimates x and pruning mask of the sets of `data` found in the cache, and
    the ranges of samples still to replay: the sets not found, adjacent ones merged (x 0 there,
    active everywhere but where the cache pruned)."""
    x = torch.zeros_like(data.dirty)
    active = torch.ones(len(data), dtype=torch.bool)
    missing = []
    for (start, end), key in zip(spans(data), keys):
        path = replay_path(work, key)
        cache = torch.load(path, weights_only=True, map_location="cpu") if os.path.exists(path) else {}
        if cache.get("key") == key and cache["x"].shape == x[start:end].shape:
            x[start:end], active[start:end] = cache["x"], cache["active"]
        elif missing and missing[-1][1] == start:
            missing[-1] = (missing[-1][0], end)
        else:
            missing.append((start, end))
    return x, active, missing


def save_replay(work, sets):
    """Caches each set's estimates (`sets`: (data, keys, x, active) per dataset) and removes the
    cached sets no longer current (those of fewer networks or of sets left out)."""
    os.makedirs(os.path.join(work, "replay"), exist_ok=True)
    current = set()
    for data, keys, x, active in sets:
        for (start, end), key in zip(spans(data), keys):
            path = replay_path(work, key)
            current.add(os.path.basename(path))
            if not os.path.exists(path):
                torch.save({"key": key, "x": x[start:end].cpu().clone(), "active": active[start:end].cpu().clone()}, path + ".tmp")
                os.replace(path + ".tmp", path)
    for name in os.listdir(os.path.join(work, "replay")):
        if name not in current:
            os.remove(os.path.join(work, "replay", name))


def energy(images):
    """Per sample, the sum of squares of its image."""
    return images.flatten(1).pow(2).sum(1)


def torch_runner(model, device):
    def run(batch):
        with torch.no_grad():
            return model(batch.to(device)).float().cpu()
    return run


def crop_batches(count, size, crop, crops_per_sample, batch, generator):
    """Shuffled batches of (sample, row, column) crop origins, `crops_per_sample` per sample."""
    samples = torch.arange(count).repeat_interleave(crops_per_sample)
    if crop >= size:
        rows = cols = torch.zeros_like(samples)
    else:
        rows = torch.randint(0, size - crop + 1, (len(samples),), generator=generator)
        cols = torch.randint(0, size - crop + 1, (len(samples),), generator=generator)
    order = torch.randperm(len(samples), generator=generator)
    samples, rows, cols = samples[order], rows[order], cols[order]
    return [(samples[s:s + batch], rows[s:s + batch], cols[s:s + batch]) for s in range(0, len(samples), batch)]


def gather_crops(images, samples, rows, cols, crop):
    """[B, ..., crop, crop] cut from images [S, ..., N, N] at the given origins."""
    return torch.stack([images[k, ..., y:y + crop, x:x + crop] for k, y, x in zip(samples.tolist(), rows.tolist(), cols.tolist())])


def crop_loss(pred, truth, peak, a, log_weight=0.0):
    """Mean L1 between prediction and truth [B, 1, H, W], plus `log_weight` times the mean L1
    between their rlog images (`common.rlog_at`, with each sample's full-field truth peak and
    dynamic range a [B, 1, 1, 1]). Both images are normalised by the truth's peak (the logSNR
    takes each image's own, which a crop does not hold; the two agree where the estimate's peak
    is right)."""
    loss = torch.nn.functional.l1_loss(pred, truth)
    if log_weight > 0:
        loss = loss + log_weight * torch.nn.functional.l1_loss(common.rlog_at(pred, a, peak), common.rlog_at(truth, a, peak))
    return loss


def train_network(i, model, train, x, r, active, args, work, device):
    """Train network i in place on the active samples; returns (epochs, seconds, last loss).

    Inputs are normalised on the full field (alpha = the full image's mean, as at inference);
    with --crop, each step sees crops of them: valid samples for a local network (norm none)."""
    opt = torch.optim.RMSprop(model.parameters(), lr=args.lr)
    epochs = args.epochs_first if i == 1 else args.epochs
    start_epoch, seconds, resumed_loss = 0, 0.0, float("nan")
    ckpt = os.path.join(work, "current.pt")
    if os.path.exists(ckpt):
        state = torch.load(ckpt, weights_only=False, map_location=device)
        if state["iteration"] == i:
            model.load_state_dict(state["model"])
            opt.load_state_dict(state["optimizer"])
            start_epoch, seconds = state["epoch"], state["seconds"]
            # The last epoch's loss, for the provenance when no epoch is left to run.
            resumed_loss = state.get("loss", float("nan"))
            log(f"N{i}: resuming after epoch {start_epoch}")
    idx = torch.nonzero(active).flatten()
    inp_all, alpha, prev = common.network_input(i, train.dirty[idx], x[idx], r[idx])
    target = train.truth[idx] / alpha
    # On a GPU the whole normalised set stays there: crops are cut on the device, not copied
    # over at every step.
    inp_all, prev, target = inp_all.to(device), prev.unsqueeze(1).to(device), target.unsqueeze(1).to(device)
    # The log term (--loss-log-weight) compares rlog images, each with its sample's dynamic
    # range and full-field truth peak (a crop may not hold the peak).
    log_peak = target.amax(dim=(-2, -1), keepdim=True).clamp(min=1e-30)
    log_a = train.dynamic_range[idx].to(device=device, dtype=torch.float32).view(-1, 1, 1, 1)
    crop = args.crop or train.size
    loss_value = resumed_loss
    for epoch in range(start_epoch, epochs):
        t0 = time.time()
        model.train()
        gen = torch.Generator().manual_seed(args.seed * 100003 + i * 1009 + epoch)
        total, count = 0.0, 0
        for b, rows, cols in crop_batches(len(idx), train.size, crop, args.crops_per_sample, args.batch, gen):
            inp = gather_crops(inp_all, b, rows, cols, crop)
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=args.bf16):
                out = model(inp)
            pred = gather_crops(prev, b, rows, cols, crop) + out.float()
            if args.loss_projection == "clip":
                # The reference's loss: the positivity projection inside it. Where a network's
                # output is negative everywhere it passes no gradient (a dead network 1).
                pred = torch.clamp(pred, min=0.0)
            elif args.loss_projection == "leaky":
                pred = torch.where(pred > 0, pred, LEAKY_SLOPE * pred)
            loss = crop_loss(pred, gather_crops(target, b, rows, cols, crop), log_peak[b], log_a[b], args.loss_log_weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(b)
            count += len(b)
        loss_value = total / count
        seconds += time.time() - t0
        torch.save({"iteration": i, "epoch": epoch + 1, "seconds": seconds, "model": model.state_dict(),
                    "optimizer": opt.state_dict(), "loss": loss_value}, ckpt + ".tmp")
        os.replace(ckpt + ".tmp", ckpt)
        log(f"N{i} epoch {epoch + 1}/{epochs}: L1 {loss_value:.5f} on {count} crops of {crop} from {len(idx)} samples, {time.time() - t0:.1f} s")
    return epochs, seconds, loss_value


def telescope_name(key):
    """The telescope's TELESCOPE_NAME from the registry (data/telescopes/telescopes.yaml)."""
    import yaml
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "data", "telescopes", "telescopes.yaml")
    with open(path) as f:
        entry = (yaml.safe_load(f) or {}).get(key) or {}
    return entry.get("name", key.upper())


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--train", required=True, nargs="+", help="training set directories (r2d2 trainset), concatenated")
    p.add_argument("--val", required=True, nargs="+", help="validation set directories (r2d2 trainset), concatenated")
    p.add_argument("--series", required=True, help="series directory, e.g. models/vla-r2d2-128")
    p.add_argument("--name", default=None, help="series name (default: directory name)")
    p.add_argument("--work", required=True, help="directory for per-epoch checkpoints")
    p.add_argument("--resume", action="store_true", help="continue an existing series")
    p.add_argument("--max-networks", type=int, default=15)
    p.add_argument("--epochs-first", type=int, default=20)
    p.add_argument("--epochs", type=int, default=8, help="epochs of networks 2, 3, ...")
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--loss-projection", choices=["clip", "none", "leaky"], default="clip",
                   help="clip: L1 to max(0, x + N), the reference's loss; none: L1 to x + N (positivity at inference "
                        "only), which keeps a gradient where the output is negative (a network 1 that outputs only "
                        "negatives under `clip` never recovers); leaky: negative outputs scaled by "
                        f"{LEAKY_SLOPE} inside the L1, a gradient everywhere and a background pushed below 0, which "
                        "positivity then clears (under `none` half the empty sky comes out as small positive specks)")
    p.add_argument("--loss-log-weight", type=float, default=0.0,
                   help="add this weight times the L1 between the rlog images (the logSNR's transform, each sample's "
                        "dynamic range): the faint emission's share of the loss, which the linear L1 all but ignores")
    p.add_argument("--base-channels", type=int, default=16)
    p.add_argument("--poolings", type=int, default=3)
    p.add_argument("--arch", choices=series.KINDS, default="unet",
                   help="unet (the project's U-Net) or uwdsr (the reference's U-Net of WDSR blocks, no feature normalisation)")
    p.add_argument("--norm", choices=["instance", "none"], default="instance",
                   help="U-Net feature normalisation; none (local, bias-free) is required for --crop")
    p.add_argument("--crop", type=int, default=None,
                   help="train on random crops of this side cut from the full-field samples")
    p.add_argument("--crops-per-sample", type=int, default=1, help="crops per sample and epoch")
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda")
    p.add_argument("--bf16", action="store_true", help="bf16 autocast for training steps (CPU)")
    p.add_argument("--min-gain-db", type=float, default=0.05,
                   help="a network joins the series only if it raises validation SNR or logSNR by this much")
    p.add_argument("--limit-train", type=int, default=None)
    p.add_argument("--limit-val", type=int, default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--commit", action="store_true", help="git-commit the series directory after each network")
    p.add_argument("--fresh-start", action="store_true",
                   help="the first network of this run starts from random weights, not from the network before; "
                        "with it a resumed series may go on with another architecture (--arch, --base-channels, "
                        "--poolings, --norm), recorded per network in the manifest")
    args = p.parse_args(argv)
    if args.arch == "uwdsr":
        args.norm = "none"  # U-WDSR has no feature normalisation: local, crops are valid samples
    if args.crop is not None and args.norm != "none":
        p.error("--crop needs --norm none: instance normalisation takes statistics over the whole input, "
                "so a crop would not see what the full field gives the network")
    if not (args.loss_log_weight >= 0 and math.isfinite(args.loss_log_weight)):
        p.error(f"--loss-log-weight must be a finite weight >= 0, got {args.loss_log_weight}")
    if args.crop is not None and args.crop % (2 ** args.poolings):
        p.error(f"--crop must be a multiple of {2 ** args.poolings}")
    device = torch.device("cuda" if args.device == "auto" and torch.cuda.is_available() else
                          ("cpu" if args.device == "auto" else args.device))
    torch.set_num_threads(args.threads)
    # Images per forward pass when replaying a network over a set: the CPU default bounds the
    # memory; a GPU takes more at once.
    ubatch = 16 if device.type == "cuda" else None
    os.makedirs(args.series, exist_ok=True)
    os.makedirs(args.work, exist_ok=True)

    manifest = series.read_manifest(args.series)
    if manifest and manifest["networks"] and not args.resume:
        raise SystemExit(f"{args.series} already holds {len(manifest['networks'])} networks: pass --resume to add to it, or choose a new --series")
    if manifest and len(manifest["networks"]) >= args.max_networks:
        # A recipe in stages reruns each stage: one whose networks exist has nothing to add
        # (and no replay to pay for).
        log(f"{args.series} already holds {len(manifest['networks'])} networks (--max-networks {args.max_networks}): nothing to train")
        return

    train = common.Dataset(args.train, args.limit_train).spectra_to(device)
    val = common.Dataset(args.val, args.limit_val).spectra_to(device)
    size = train.size
    log(f"{len(train)} training and {len(val)} validation samples, {size} x {size}, on {device}")
    if manifest is None or not manifest["networks"]:
        name = args.name or os.path.basename(os.path.normpath(args.series))
        provenance = {
            "command": " ".join(["python3", common.repo_relative(sys.argv[0])] +
                                [common.repo_relative(a) if os.path.exists(a) and os.path.isabs(a) else a for a in sys.argv[1:]]),
            "git_commit": git_commit(),
            "torch": str(torch.__version__),
            "seed": args.seed,
            "optimizer": {"kind": "rmsprop", "lr": args.lr, "batch": args.batch, "bf16_autocast": args.bf16},
            "loss": {"kind": "l1", "projection": args.loss_projection, **({"log_weight": args.loss_log_weight} if args.loss_log_weight else {})},
            "crops": {"side": args.crop, "per_sample_and_epoch": args.crops_per_sample} if args.crop else None,
            "device": device.type,
            "train_data": {"path": [common.repo_relative(t) for t in args.train], "samples": len(train), **common.portable(train.meta)},
            "validation_data": {"path": [common.repo_relative(v) for v in args.val], "samples": len(val), **common.portable(val.meta)},
            "networks": [],
        }
        validity = series.domain(train.meta, size)
        fmt = lambda r: f"{r[0]:g}" if r[0] == r[1] else f"{r[0]:g}..{r[1]:g}"
        desc = (f"R2D2 {args.arch} series ({args.base_channels} channels, {args.poolings} poolings, norm {args.norm}) for "
                f"{'/'.join(telescope_name(t) for t in validity['telescopes'])}, Briggs {fmt(validity['robust'])}, "
                f"SR {fmt(validity['superresolution'])}, trained at {size}x{size}; H and W must be multiples of {2 ** args.poolings}")
        model = series.make_network(args.arch, args.base_channels, args.poolings, args.norm)
        manifest = series.new_manifest(name, model, size, desc, provenance, validity)
    last = series.network_config(manifest, len(manifest["networks"]))
    wanted = (args.arch, args.base_channels, args.poolings, args.norm)
    if last != wanted and not args.fresh_start:
        raise SystemExit(f"{args.series}: the series' last network is {last[0]}, {last[1]} channels / {last[2]} poolings / norm {last[3]}; "
                         f"got --arch {args.arch} --base-channels {args.base_channels} --poolings {args.poolings} --norm {args.norm} "
                         f"(--fresh-start trains a network of another architecture from random weights)")
    if args.poolings > manifest["network"]["poolings"]:
        # The engine checks a job's image size against `network.poolings` (a multiple of 2^P).
        raise SystemExit(f"{args.series}: the series pools {manifest['network']['poolings']} times (network.poolings); "
                         f"a later network may not pool more (got --poolings {args.poolings})")

    # Replay the existing networks: x, r of every sample, the pruned training set. The replayed
    # estimates are cached in --work per set (keyed by the networks' weights and the set), so
    # that a resumed series does not run every network over the data again, and a stage that
    # adds a set replays only that one.
    history = [dict(v) for v in manifest["validation"]]
    have = len(manifest["networks"])
    keys_tr, keys_va = replay_keys(args, manifest, have, train), replay_keys(args, manifest, have, val)
    x_tr, active, missing_tr = load_replay(args.work, train, keys_tr)
    x_va, active_va, missing_va = load_replay(args.work, val, keys_va)
    # The pruning's noise levels, once: each network compares its residuals with them.
    noise_tr, noise_va = energy(train.noise_dirty), energy(val.noise_dirty)
    # The ranges still to replay, run through every network in turn: their x in place (views
    # of the sets' arrays), their residuals beside.
    todo = [{"kind": kind, "data": data, "x": x, "active": act, "noise": noise, "at": slice(start, end),
             "r": data.dirty[start:end].clone()}
            for kind, data, x, act, noise, missing in (("training", train, x_tr, active, noise_tr, missing_tr),
                                                       ("validation", val, x_va, active_va, noise_va, missing_va))
            for start, end in (missing if have else [])]
    replayed = {kind: sum(p["at"].stop - p["at"].start for p in todo if p["kind"] == kind) for kind in ("training", "validation")}
    for k in range(1, have + 1 if todo else 1):
        # On a CPU the series' own ONNX exports (what the engine runs) go through ONNX Runtime,
        # several times faster than PyTorch here: the replay of a long series over a few hundred
        # samples is most of a resumed stage's time.
        onnx = os.path.join(args.series, manifest["networks"][k - 1])
        run = series.onnx_runner(onnx, args.threads) if device.type == "cpu" and os.path.exists(onnx) else \
            torch_runner(series.load_network(args.series, manifest, k).to(device), device)
        run = series.oriented(run, series.orientation(manifest, k))
        for part in todo:
            data, at = part["data"], part["at"]
            part["x"][at] = common.update(k, run, data.dirty[at], part["x"][at], part["r"], batch=ubatch)
            part["r"] = common.residual(data.dirty[at], part["x"][at], data.psf_hat[at])
            part["active"][at] &= energy(part["r"]) > part["noise"][at]
        log(f"replayed N{k} over " + " and ".join(f"{n} {kind}" for kind, n in replayed.items() if n) + " samples")
    r_tr = common.residual(train.dirty, x_tr, train.psf_hat)
    r_va = common.residual(val.dirty, x_va, val.psf_hat)
    model = series.load_network(args.series, manifest, have).to(device) if have else None
    if have:
        log(f"replay of N1-N{have}: validation {common.metrics(x_va, r_va, val)}; {int(active.sum())} training samples active"
            f" ({len(train) + len(val) - sum(replayed.values())} of {len(train) + len(val)} samples read from the cache)")
    if todo:
        save_replay(args.work, [(train, keys_tr, x_tr, active), (val, keys_va, x_va, active_va)])

    # The stopping rule compares with the best validation so far on this run's validation
    # set: the rows measured on it, where the series' last network was (a later stage may
    # validate on other skies), else the replayed series measured on it now.
    as_list = lambda p: p if isinstance(p, list) else [p] if p is not None else []
    train_paths = [common.repo_relative(t) for t in args.train]
    val_paths = [common.repo_relative(v) for v in args.val]
    series_train_paths = as_list((manifest["provenance"].get("train_data") or {}).get("path")) or train_paths
    series_val_paths = as_list((manifest["provenance"].get("validation_data") or {}).get("path")) or val_paths
    val_of = {n["iteration"]: as_list(n.get("validation_data", series_val_paths)) for n in manifest["provenance"]["networks"]}
    on_this_set = lambda h: val_of.get(h["iteration"], series_val_paths) == val_paths
    best = {"snr_db": -1e9, "logsnr_db": -1e9}
    if history and on_this_set(history[-1]):
        for h in history:
            if on_this_set(h):
                best = {key: max(best[key], h[key]) for key in best}
    elif have:
        best = {key: v for key, v in common.metrics(x_va, r_va, val).items() if key in best}
        log(f"validation set {val_paths} is not the one the series' last network was selected on: "
            f"the baseline is the replayed series on it")
    if have:
        log(f"series so far: best validation SNR {best['snr_db']:.2f} dB, logSNR {best['logsnr_db']:.2f} dB")
    first_of_run = len(manifest["networks"]) + 1
    for i in range(first_of_run, args.max_networks + 1):
        if int(active.sum()) < args.batch:
            log(f"stop: only {int(active.sum())} training samples left after pruning")
            break
        torch.manual_seed(args.seed * 7919 + i)
        new = series.make_network(args.arch, args.base_channels, args.poolings, args.norm).to(device)
        fresh = model is None or (args.fresh_start and i == first_of_run)
        if not fresh:
            new.load_state_dict(model.state_dict())  # network i starts from network i-1
        else:
            log(f"N{i}: {args.arch}, {args.base_channels} channels / {args.poolings} poolings, norm {args.norm}, "
                f"{series.parameter_count(new)} parameters, from random weights")
        epochs, seconds, loss = train_network(i, new, train, x_tr, r_tr, active, args, args.work, device)
        new.eval()
        # Validated (and replayed) as the engine will run it: in its orientation of the
        # manifest's cycle (it is trained as drawn, in none).
        run = series.oriented(torch_runner(new, device), series.orientation(manifest, i))
        x_va_new = common.update(i, run, val.dirty, x_va, r_va, batch=ubatch)
        r_va_new = common.residual(val.dirty, x_va_new, val.psf_hat)
        m = common.metrics(x_va_new, r_va_new, val)
        log(f"N{i}: validation SNR {m['snr_db']:.2f} dB, logSNR {m['logsnr_db']:.2f} dB, residual ratio {m['residual_ratio']:.4f}")
        if m["snr_db"] < best["snr_db"] + args.min_gain_db and m["logsnr_db"] < best["logsnr_db"] + args.min_gain_db:
            rejected = os.path.join(args.work, f"rejected_N{i}.pt")
            torch.save(new.state_dict(), rejected)
            os.remove(os.path.join(args.work, "current.pt"))
            log(f"stop: N{i} does not improve validation SNR/logSNR by {args.min_gain_db} dB (kept aside as {rejected})")
            break
        best = {key: max(best[key], m[key]) for key in best}
        # Commit the network to the series: weights, ONNX, then the manifest that lists it.
        series.save_weights(args.series, i, new)
        series.export_onnx(new.cpu(), os.path.join(args.series, series.onnx_name(i)), size)
        new.to(device)
        x_tr = common.update(i, run, train.dirty, x_tr, r_tr, batch=ubatch)
        r_tr = common.residual(train.dirty, x_tr, train.psf_hat)
        before = int(active.sum())
        active &= energy(r_tr) > noise_tr
        active_va &= energy(r_va_new) > noise_va
        x_va, r_va, model = x_va_new, r_va_new, new
        manifest["networks"].append(series.onnx_name(i))
        # The first network of a later stage (resumed with another loss or other training
        # data): it and those after trade a little residual for fewer artefacts or for
        # emission the first stage missed, so the engine's early stop (ratio stalled) applies
        # from it on, not before, where it would skip the stage. The loss of the network
        # before: its own record, else the series' (older manifests record it once); where
        # neither says, no stage boundary is assumed from the loss. Another validation set
        # alone trains nothing differently: no boundary.
        before_it = manifest["provenance"]["networks"][-1] if manifest["provenance"]["networks"] else None
        if before_it and "early_stop_from" not in manifest:
            previous = before_it.get("loss_projection", (manifest["provenance"].get("loss") or {}).get("projection"))
            other_loss = (previous is not None and previous != args.loss_projection) or \
                before_it.get("loss_log_weight", 0.0) != args.loss_log_weight
            other_data = as_list(before_it.get("train_data", series_train_paths)) != train_paths
            if other_loss or other_data:
                manifest["early_stop_from"] = i
        manifest["validation"].append({"iteration": i, **{k: round(v, 4) for k, v in m.items()},
                                       **({"validation_data": val_paths} if val_paths != series_val_paths else {})})
        record = series.config_record(new)
        manifest["provenance"]["networks"].append({
            "iteration": i, "epochs": epochs, "train_seconds": round(seconds, 1), "train_samples": before, "loss_projection": args.loss_projection,
            "limit_train": args.limit_train, "device": device.type,
            **({"loss_log_weight": args.loss_log_weight} if args.loss_log_weight else {}),
            # An architecture other than the series' (a later stage's, --fresh-start).
            **({"network": record} if record != manifest["network"] else {}),
            **({"fresh_start": True} if fresh and i > 1 else {}),
            # A later stage's own data (the series-level record is the first stage's).
            **({"train_data": train_paths} if train_paths != series_train_paths else {}),
            **({"validation_data": val_paths} if val_paths != series_val_paths else {}),
            "pruned_after": before - int(active.sum()), "final_l1": round(loss, 6) if math.isfinite(loss) else None, "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        })
        series.write_manifest(args.series, manifest)
        os.remove(os.path.join(args.work, "current.pt"))
        save_replay(args.work, [(train, replay_keys(args, manifest, i, train), x_tr, active),
                                (val, replay_keys(args, manifest, i, val), x_va, active_va)])
        log(f"N{i} added to {args.series}; {int(active.sum())} of {len(train)} training samples remain after pruning")
        if args.commit:
            commit_series(args.series, f"models: {manifest['name']} network {i} (validation SNR {m['snr_db']:.2f} dB, logSNR {m['logsnr_db']:.2f} dB)")
    log("done")


if __name__ == "__main__":
    main()
