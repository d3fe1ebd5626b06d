"""The Python package beyond one process: Dask throughput for 1 and 2 workers, and the cost of
a Python call against the command line for one job.

    python3 benches/python_dask.py [--jobs 16] [--size 256] [--step auto] [--dir bench-out/python_dask]

Needs the package (`pip install .`), dask[distributed], and target/release/r2d2. Simulates
`--jobs` observations (`r2d2 simulate`, different skies), then:

1. images them all on a LocalCluster of 1 worker process (one task at a time, the engine on
   every core) and of 2 worker processes (one task each, the engine on half the cores), with
   the products written by the workers (`prefix`): jobs per second, and each worker's peak
   memory (its process's maximum resident set, less its size before the first job);
2. images one observation `--repeat` times with `r2d2 image` (a process per job, as a shell
   script or a Stimela step runs it) and with `r2d2_imaging.image(...).write(...)` in this
   process (engine loaded once): median seconds per job, and their difference.

Prints one JSON object (and a Markdown table).
"""

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def simulate(r2d2, out, seed, size):
    subprocess.run([str(r2d2), "-q", "simulate", "--sky", f"procedural:{seed}", "--configs", "a,c", "--hours", "2,1",
                    "--dr", "1e4", "--size", str(size), "--seed", str(seed), "--out", str(out)], check=True)
    return out


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def dask_throughput(workers, observations, out, params):
    from distributed import Client, LocalCluster
    from r2d2_imaging.dask import image_many

    cores = os.cpu_count()
    threads = max(1, cores // workers)
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, Client(cluster) as client:
        before = client.run(peak_rss_mb)
        # One job first on every worker so that process start-up and the first load of the
        # models are not counted (a long-lived cluster has paid them once).
        image_many(client, observations[:workers], prefix=str(out / f"warm{workers}/{{job}}"), threads=threads, **params)
        start = time.perf_counter()
        results = image_many(client, observations, prefix=str(out / f"w{workers}/{{job}}"), threads=threads, **params)
        seconds = time.perf_counter() - start
        after = client.run(peak_rss_mb)
    assert len(results) == len(observations)
    return {
        "workers": workers,
        "threads_per_task": threads,
        "jobs": len(observations),
        "seconds": round(seconds, 2),
        "jobs_per_second": round(len(observations) / seconds, 3),
        "worker_peak_mb": round(max(after.values()), 1),
        "worker_peak_growth_mb": round(max(after[w] - before[w] for w in after), 1),
    }


def call_overhead(r2d2, obs, out, params, repeat):
    import r2d2_imaging

    cli_args = [str(r2d2), "-q", "image", str(obs), "--size", str(params["size"]), "--step", params["step"]]
    if params.get("iterations"):
        cli_args += ["--iterations", str(params["iterations"])]
    cli, python = [], []
    for i in range(repeat):
        start = time.perf_counter()
        subprocess.run(cli_args + ["--name", str(out / f"cli{i}/obs")], check=True)
        cli.append(time.perf_counter() - start)
        start = time.perf_counter()
        r2d2_imaging.image(obs, **params).write(str(out / f"py{i}/obs"))
        python.append(time.perf_counter() - start)
    return {
        "repeat": repeat,
        "cli_seconds": round(statistics.median(cli), 3),
        "python_seconds": round(statistics.median(python), 3),
        "python_minus_cli_seconds": round(statistics.median(python) - statistics.median(cli), 3),
        "python_over_cli": round(statistics.median(python) / statistics.median(cli), 3),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", type=int, default=16)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--step", default="auto", help="auto (the series for the size), clean, or a series")
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--dir", default=str(REPO / "bench-out" / "python_dask"))
    parser.add_argument("--r2d2", default=str(REPO / "target" / "release" / "r2d2"))
    args = parser.parse_args()
    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("R2D2_MODELS", str(REPO / "models"))
    observations = [simulate(args.r2d2, out / f"obs{seed:02d}.parquet", seed, args.size) for seed in range(1, args.jobs + 1)]
    params = {"size": args.size, "step": args.step}
    if args.iterations:
        params["iterations"] = args.iterations
    dask = [dask_throughput(w, observations, out, params) for w in (1, 2)]
    overhead = call_overhead(args.r2d2, observations[0], out, params, args.repeat)
    report = {"size": args.size, "step": args.step, "cores": os.cpu_count(), "dask": dask, "one_job": overhead,
              "speedup_2_over_1": round(dask[1]["jobs_per_second"] / dask[0]["jobs_per_second"], 3)}
    print(json.dumps(report, indent=1))
    print("\n| workers | threads/task | jobs | seconds | jobs/s | worker peak (MB) | growth per worker (MB) |\n|---|---|---|---|---|---|---|")
    for d in dask:
        print(f"| {d['workers']} | {d['threads_per_task']} | {d['jobs']} | {d['seconds']} | {d['jobs_per_second']} | {d['worker_peak_mb']} | {d['worker_peak_growth_mb']} |")
    print(f"\none job: CLI {overhead['cli_seconds']} s, Python {overhead['python_seconds']} s (median of {overhead['repeat']})")


if __name__ == "__main__":
    main()
