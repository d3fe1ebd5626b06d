"""The precision-time curve of a series: SNR and logSNR against wall time, per network count.

Two ways, one script:

    python3 benches/precision_time.py run --data DIR [DIR ...] --out OUT [--skies 8] [--networks 8,12,16,20,24,28,33,37,43]
                                          [--series vla-r2d2-512] [--threads 2] [--v2-from-first]
    python3 benches/precision_time.py curve OUT_OR_VS_WSCLEAN_DIR [more ...] [--out curve.md]

`run` measures whole jobs: for each observation of each data directory (a `r2d2 trainset
--parquet` set: vis/NNNNN.parquet, vis/NNNNN.sky.fits, samples.json; e.g. benches/vs_wsclean.py's
--keep-data), `r2d2 image OBS --size N --truth SKY --iterations K` for every K of --networks
(the first K networks, then the final CLEAN as every job runs it), each under /usr/bin/time,
and WSClean's multiscale CLEAN (the paper's command, as benches/vs_wsclean.py runs it) once on
the observation's MeasurementSet, in the same run: the table gives each K's mean SNR, logSNR,
residual ratio, wall time and its ratio to WSClean's. With --v2-from-first, the series is also
run whole with the reference v2 stop rule from its first network on (a copy of its manifest
without `early_stop_from`). The K = whole-series run's metrics are kept as
OUT/work/SET-NNNNN/r2d2-metrics.json, so `curve` reads them too.

`curve` reads the `-metrics.json` files of runs made with the truth (`r2d2 image --truth`:
OUT/work/*/r2d2-metrics.json, as benches/vs_wsclean.py and `run` make them) and gives every
network count from one run per sky. Time at network k: the run's fixed stages (read, weights,
grid, final CLEAN, products) plus the step and residual seconds of networks 1..k (process
start and the final CLEAN's extra cycles after fewer networks are not in it: `run` measures
them). It also says where the reference v2 stop rule would end each run if it applied from
the first network on (the engine's `StopRule`, src/job/stopping.rs: stop when the residual
ratio changes by less than 1e-4 relative, or rises at two consecutive networks).

Seeds: choose on validation sets (500000.. classic, 510000.. extended, 520000.. field-filling);
report on test sets (900000.., 910000.., 930000..), never chosen on.
"""

import argparse
import glob
import json
import os
import re
import shutil
import sys

import numpy as np


def v2_stop(ratios, tolerance=1e-4):
    """The network after which the v2 rule stops (1-based), or len(ratios)."""
    for n in range(2, len(ratios) + 1):
        r = ratios[:n]
        if n >= 3 and r[-1] > r[-2] > r[-3]:
            return n
        if abs(r[-1] - r[-2]) / r[-2] < tolerance:
            return n
    return len(ratios)


def curve(path):
    with open(path) as f:
        m = json.load(f)
    networks = m["settings"]["step"]["networks"] if "step" in m.get("settings", {}) else None
    rows = [r for r in m["iterations"] if networks is None or r["iteration"] <= networks]
    fixed = sum(v for k, v in m["stage_seconds"].items() if k not in ("step", "update"))
    t = fixed + np.cumsum([r["step_seconds"] + r["residual_seconds"] for r in rows])
    return {
        "snr": np.array([r.get("snr", np.nan) for r in rows], dtype=float),
        "logsnr": np.array([r.get("logsnr") if r.get("logsnr") is not None else np.nan for r in rows], dtype=float),
        "ratio": [r["residual_ratio"] for r in rows],
        "seconds": t,
    }


def curve_main(args):
    files = sorted(f for d in args.dirs for f in glob.glob(os.path.join(d, "work", "*", f"{args.name}-metrics.json")))
    if not files:
        sys.exit(f"no {args.name}-metrics.json under {args.dirs}")
    runs = [curve(f) for f in files]
    n = min(len(r["snr"]) for r in runs)
    snr = np.mean([r["snr"][:n] for r in runs], axis=0)
    logsnr = np.mean([r["logsnr"][:n] for r in runs], axis=0)
    seconds = np.mean([r["seconds"][:n] for r in runs], axis=0)
    lines = [f"{len(runs)} runs ({', '.join(sorted(set(os.path.dirname(os.path.dirname(os.path.dirname(f))) for f in files)))}); means:", "",
             "| networks | SNR (dB) | logSNR (dB) | wall (s) | share of the whole series' time |", "|---|---|---|---|---|"]
    for k in sorted(set([1, 2, 4, 8, 12, 16, 20, 24, 28, 32, 36, 40, n]) & set(range(1, n + 1))):
        lines.append(f"| {k} | {snr[k - 1]:.2f} | {logsnr[k - 1]:.2f} | {seconds[k - 1]:.1f} | {seconds[k - 1] / seconds[n - 1]:.2f} |")
    stops = [v2_stop(r["ratio"][:n]) for r in runs]
    at_stop = [(r["snr"][k - 1] - r["snr"][n - 1], r["logsnr"][k - 1] - r["logsnr"][n - 1], r["seconds"][k - 1] / r["seconds"][n - 1]) for r, k in zip(runs, stops)]
    lines += ["", f"The v2 rule from the first network on would stop after networks {stops} (of {n}): "
              f"SNR {np.mean([a[0] for a in at_stop]):+.2f} dB, logSNR {np.nanmean([a[1] for a in at_stop]):+.2f} dB against the whole series, "
              f"at {np.mean([a[2] for a in at_stop]):.2f} of its time (means)."]
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")


HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)


def series_dir(name):
    d = name if os.path.isdir(name) else os.path.join(REPO, "models", name)
    if not os.path.exists(os.path.join(d, "manifest.yaml")):
        sys.exit(f"{name}: no series there (expected a name under models/ or a directory with manifest.yaml)")
    return os.path.abspath(d)


def v2_copy(src, out):
    """The series as it is, but with the v2 stop rule from its first network on: its files
    hard-linked (or copied; the engine refuses a network that links outside its series), its
    manifest without `early_stop_from`."""
    dst = os.path.join(out, "series-v2-from-first")
    shutil.rmtree(dst, ignore_errors=True)
    os.makedirs(dst)
    for f in os.listdir(src):
        if f != "manifest.yaml" and os.path.isfile(os.path.join(src, f)):
            try:
                os.link(os.path.join(src, f), os.path.join(dst, f))
            except OSError:
                shutil.copy2(os.path.join(src, f), os.path.join(dst, f))
    with open(os.path.join(src, "manifest.yaml")) as f:
        lines = [l for l in f if not l.startswith("early_stop_from:")]
    with open(os.path.join(dst, "manifest.yaml"), "w") as f:
        f.writelines(lines)
    return dst


def networks_of(src):
    with open(os.path.join(src, "manifest.yaml")) as f:
        text = f.read()
    m = re.search(r"^networks:\s*\[(.*?)\]", text, re.S | re.M)
    if not m:
        sys.exit(f"{src}/manifest.yaml: expected a one-line-per-list `networks: [...]` (one realisation)")
    return len([x for x in m.group(1).split(",") if x.strip()])


def noise_stop(data, k, metrics, total):
    """Where a data-fidelity stop would end the series, the residual compatible with the noise
    (||x_d - D x_i|| <= ||b||, b = kappa Re{Phi^H n} the back-projected noise that `r2d2
    trainset` records, as the reference prunes its training pairs): the network, and SNR /
    logSNR there against the whole series, both from the whole run's per-network metrics (the
    networks' images, before the final CLEAN). The true noise is known only in simulation: the
    best such a stop could do."""
    b = np.load(os.path.join(data, "noise_dirty.npy"), mmap_mode="r")[k]
    d = np.load(os.path.join(data, "dirty.npy"), mmap_mode="r")[k]
    floor = float(np.linalg.norm(b) / np.linalg.norm(d))
    with open(metrics) as f:
        its = [r for r in json.load(f)["iterations"] if r["iteration"] <= total]
    stop = next((r["iteration"] for r in its if r["residual_ratio"] <= floor), len(its))
    at, end = its[stop - 1], its[-1]
    return {"noise_ratio": floor, "network": stop, "snr_change_db": at["snr"] - end["snr"],
            "logsnr_change_db": at["logsnr"] - end["logsnr"]}


def run_main(args):
    sys.path.insert(0, HERE)
    import vs_wsclean as vw

    r2d2 = os.path.abspath(args.r2d2)
    out = os.path.abspath(args.out)
    os.makedirs(os.path.join(out, "work"), exist_ok=True)
    src = series_dir(args.series)
    total = networks_of(src)
    counts = sorted({min(int(k), total) for k in args.networks.split(",")} | {total})
    v2 = v2_copy(src, out) if args.v2_from_first else None
    records = []
    for data in args.data:
        data = os.path.abspath(data)
        with open(os.path.join(data, "trainset.json")) as f:
            ts = json.load(f)
        with open(os.path.join(data, "samples.json")) as f:
            samples = json.load(f)
        label = f"{ts.get('sky') or 'classic'}-{ts['seed']}"
        size, sr, robust = ts["size"], ts["superresolution"], ts["weighting"]["robust"]
        wargs = argparse.Namespace(wsclean=args.wsclean, size=size, threads=args.threads, robust=robust)
        for k in range(min(args.skies, len(samples))):
            obs = os.path.join(data, "vis", f"{k:05d}.parquet")
            sky = os.path.join(data, "vis", f"{k:05d}.sky.fits")
            work = os.path.join(out, "work", f"{label}-{k:05d}")
            os.makedirs(work, exist_ok=True)
            truth, th = vw.read_fits(sky)
            a = float(samples[k]["dynamic_range"])
            rec = {"set": label, "sky": k, "seed": samples[k].get("seed"), "dynamic_range": a, "runs": {}}
            ms = os.path.join(work, "obs.ms")
            vw.convert_ms(r2d2, obs, ms)
            _, wall, peak, _ = vw.image_wsclean(wargs, ms, work, abs(th["CDELT2"]) * 3600)
            restored, hdr = vw.read_fits(os.path.join(work, "ws-image.fits"))
            res, _ = vw.read_fits(os.path.join(work, "ws-residual.fits"))
            dirt, _ = vw.read_fits(os.path.join(work, "ws-dirty.fits"))
            rec["wsclean"] = {"wall_s": wall, "peak_mb": peak,
                              **vw.score(restored / vw.beam_area_pixels(hdr), truth, a, res, dirt)}
            shutil.rmtree(ms, ignore_errors=True)
            plans = [(str(K), ["--step", src, "--iterations", K]) for K in counts]
            if v2:
                plans.append(("v2", ["--step", v2]))
            for key, extra in plans:
                name = "r2d2" if key == str(total) else f"r2d2-{key}"
                cmd = [r2d2, "image", obs, "--size", size, "--name", name, "--truth", sky, "--threads", args.threads,
                       f"--robust={robust:g}", "--superresolution", sr, *extra]
                text, wall, peak = vw.run(cmd, cwd=work, timed=True, logfile=os.path.join(work, name + ".log"))
                img = lambda p: vw.read_fits(os.path.join(work, f"{name}-{p}.fits"))[0]
                s = vw.score(img("model"), truth, a, img("residual"), img("dirty"))
                s.update({"wall_s": wall, "peak_mb": peak,
                          "networks_run": len(re.findall(r"iteration \d+ of \d+ residual ratio", text))})
                rec["runs"][key] = s
            rec["noise_stop"] = noise_stop(data, k, os.path.join(work, "r2d2-metrics.json"), total)
            records.append(rec)
            vw.log(f"{label} sky {k}: WSClean {rec['wsclean']['snr_db']:.2f}/{rec['wsclean']['logsnr_db']:.2f} dB {rec['wsclean']['wall_s']:.1f} s; "
                   + ", ".join(f"{key}: {v['snr_db']:.2f}/{v['logsnr_db']:.2f} dB {v['wall_s']:.1f} s" for key, v in rec["runs"].items()))

    keys = [str(K) for K in counts] + (["v2"] if v2 else [])

    def means(recs):
        rows = {}
        for key in keys:
            runs = [r["runs"][key] for r in recs]
            rows[key] = {m: float(np.mean([x[m] for x in runs])) for m in ("snr_db", "logsnr_db", "residual_ratio", "wall_s", "networks_run")}
            rows[key]["of_wsclean_time"] = float(np.mean([r["runs"][key]["wall_s"] / r["wsclean"]["wall_s"] for r in recs]))
        rows["wsclean"] = {m: float(np.mean([r["wsclean"][m] for r in recs])) for m in ("snr_db", "logsnr_db", "residual_ratio", "wall_s")}
        rows["wsclean"]["of_wsclean_time"] = 1.0
        return rows

    sets = sorted({r["set"] for r in records})
    result = {"series": os.path.basename(src), "networks": total, "threads": args.threads, "counts": counts,
              "data": [os.path.basename(os.path.abspath(d)) for d in args.data],
              "r2d2_command": "r2d2 image OBS --size N --truth SKY --threads T --robust=R --superresolution SR --step SERIES --iterations K",
              "wsclean_command": "wsclean -size N N -scale PIXEL -j T -weight briggs R " + " ".join(vw.PAPER_WSCLEAN),
              "means": means(records), "per_set": {s: means([r for r in records if r["set"] == s]) for s in sets},
              "per_sky": records}
    counts_text = ", ".join(f"{s}: {sum(r['set'] == s for r in records)}" for s in sets)
    lines = [f"`{result['series']}` on {len(records)} skies ({counts_text}), "
             f"{args.threads} threads, each run alone; means. Each row a whole `r2d2 image` job (the final CLEAN included), "
             "WSClean multiscale (the paper's command) on the same observations in the same run.", "",
             "| networks | networks run | SNR (dB) | logSNR (dB) | residual ratio | wall (s) | of WSClean's time |", "|---|---|---|---|---|---|---|"]
    for key in keys + ["wsclean"]:
        m = result["means"][key]
        what = {"v2": "all, v2 stop from the first", "wsclean": "WSClean multiscale (restored / beam)"}.get(key, key)
        ran = f"{m['networks_run']:.1f}" if "networks_run" in m else "-"
        lines.append(f"| {what} | {ran} | {m['snr_db']:.2f} | {m['logsnr_db']:.2f} | {m['residual_ratio']:.2e} | {m['wall_s']:.2f} | {m['of_wsclean_time']:.2f} |")
    if len(sets) > 1:
        lines += ["", "Per set, SNR / logSNR (dB):", "", "| networks | " + " | ".join(sets) + " |", "|---|" + "---|" * len(sets)]
        for key in keys + ["wsclean"]:
            lines.append(f"| {key} | " + " | ".join(f"{result['per_set'][s][key]['snr_db']:.2f} / {result['per_set'][s][key]['logsnr_db']:.2f}" for s in sets) + " |")
    ns = [r["noise_stop"] for r in records]
    result["noise_stop"] = {m: float(np.mean([x[m] for x in ns])) for m in ("network", "snr_change_db", "logsnr_change_db")}
    lines += ["", f"A data-fidelity stop (the residual ratio at or below the true noise's, ||b|| / ||x_d||) would end the series after "
              f"networks {[x['network'] for x in ns]} (mean {result['noise_stop']['network']:.1f} of {total}): "
              f"SNR {result['noise_stop']['snr_change_db']:+.2f} dB, logSNR {result['noise_stop']['logsnr_change_db']:+.2f} dB "
              "against the whole series (the networks' images, before the final CLEAN)."]
    text = "\n".join(lines)
    with open(os.path.join(out, "precision_time.json"), "w") as f:
        json.dump(result, f, indent=1)
    with open(os.path.join(out, "precision_time.md"), "w") as f:
        f.write(text + "\n")
    plot(os.path.join(out, "precision_time.png"), result, keys)
    print(text)


def plot(path, result, keys):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, metric, label in ((axes[0], "snr_db", "SNR (dB)"), (axes[1], "logsnr_db", "logSNR (dB)")):
        for s, rows in [("all", result["means"])] + sorted(result["per_set"].items()):
            ks = [k for k in keys if k != "v2"]
            ax.plot([rows[k]["of_wsclean_time"] for k in ks], [rows[k][metric] for k in ks], "o-", label=s, lw=2 if s == "all" else 1)
            for k in ks:
                if s == "all":
                    ax.annotate(k, (rows[k]["of_wsclean_time"], rows[k][metric]), fontsize=7)
        ax.plot([1.0], [result["means"]["wsclean"][metric]], "k*", ms=10, label="WSClean multiscale (all)")
        ax.axvline(1.0, color="grey", ls=":")
        ax.set_xlabel("wall time / WSClean multiscale's")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{result['series']}: precision against time (labels: networks)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="mode", required=True)
    r = sub.add_parser("run", help="whole jobs at each network count, against WSClean in the same run")
    r.add_argument("--data", nargs="+", required=True, help="r2d2 trainset --parquet sets")
    r.add_argument("--out", required=True)
    r.add_argument("--skies", type=int, default=8, help="at most this many observations of each set")
    r.add_argument("--networks", default="8,12,16,20,24,28,33,37,43", help="network counts (the whole series is always run)")
    r.add_argument("--series", default="vla-r2d2-512")
    r.add_argument("--threads", type=int, default=2)
    r.add_argument("--v2-from-first", action="store_true", help="also run the series with the v2 stop rule from its first network")
    r.add_argument("--r2d2", default=os.path.join(REPO, "target", "release", "r2d2"))
    r.add_argument("--wsclean", default="wsclean")
    c = sub.add_parser("curve", help="every network count from the metrics of one run per sky")
    c.add_argument("dirs", nargs="+")
    c.add_argument("--name", default="r2d2", help="the runs' product name (NAME-metrics.json)")
    c.add_argument("--out", default=None)
    args = ap.parse_args()
    run_main(args) if args.mode == "run" else curve_main(args)


if __name__ == "__main__":
    main()

