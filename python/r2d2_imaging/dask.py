"""Many imaging jobs over the workers of a ``dask.distributed`` cluster: one engine per task.

The jobs are a list of observations (paths or Arrow tables), or observations split by a column
exactly as a pipeline's ``split_by`` splits them (one job per channel, time window, field ...).
Each job is one Dask task that images it with :func:`r2d2_imaging.image` on a worker; the
products come back to the client, or are written by the workers under a shared prefix and only
their metrics come back. On the Dask dashboard the tasks of a call make one ``r2d2-image``
group (one progress bar), each keyed by its job id.

    from dask.distributed import Client
    from r2d2_imaging.dask import image_many
    client = Client("tcp://scheduler:8786")        # or LocalCluster(), or dask-jobqueue
    results = image_many(client, ["a.parquet", "b.parquet"], size=512, prefix="out/{job}")

One observation too big for one machine is imaged by :func:`image_parts`: its parts (files of
one observation: channels, time ranges, row ranges) are each gridded by a worker that can read
them, the grids summed here, and the image-domain loop run once, in this process; the products
are the single-process run's (see :func:`image_parts`).

    products = image_parts(client, ["obs-part0.parquet", "obs-part1.parquet"], size=512)
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import r2d2_imaging
from r2d2_imaging import _native

__all__ = ["Job", "JobResult", "jobs", "split", "image_many", "image_parts", "read_parquet"]

Observation = Union[str, "os.PathLike[str]", pa.Table]


@dataclass
class Job:
    """One imaging job: its id (products are named after it) and its observation: a path, a
    table, or the rows ``rows`` of the table at ``path`` (a part of a split file, read by the
    worker itself from a file system it shares with the client). A part of a split carries
    the split's ``longest_baseline`` (wavelengths), which sets the pixel size every part
    shares, as the engine's own split does."""

    id: str
    obs: Any
    rows: Optional[np.ndarray] = None
    longest_baseline: Optional[float] = None

    def observation(self):
        """What :func:`r2d2_imaging.image` takes for this job (on the worker)."""
        if self.rows is None:
            return self.obs
        return read_parquet(self.obs).take(self.rows)


def read_parquet(path) -> pa.Table:
    """A Parquet visibility table with the observation's metadata on its schema, where the
    engine expects it of a table (pyarrow puts the file's key-value metadata there only when
    the file carries no Arrow schema of its own)."""
    file = pq.ParquetFile(path)
    meta = {k: v for k, v in (file.metadata.metadata or {}).items() if k != b"ARROW:schema"}
    table = file.read()
    return table.replace_schema_metadata({**(table.schema.metadata or {}), **meta})


@dataclass
class JobResult:
    """What a worker sends back when it wrote the products itself: the job's id, the product
    prefix, the per-iteration metrics and the FITS header."""

    id: str
    prefix: str
    metrics: dict
    header: dict


def _stem(obs, index: int) -> str:
    """A job's id: the file name without its extension, as the engine's sources name jobs; a
    table without a name is ``table<index>``."""
    if isinstance(obs, (str, os.PathLike)):
        return Path(obs).stem
    return f"table{index}"


def split(obs: Observation, column: str, window: Optional[float] = None, id: Optional[str] = None) -> list[Job]:
    """The jobs ``split_by: {column, window}`` makes of one observation (a Parquet path or an
    Arrow table), named ``<id>-ch00``, ``<id>-t003`` ... exactly as the engine names and fills
    them (the rows it keeps for imaging, windows counted from the first sample). The split is
    computed here (the table is read once); each path job carries only its row numbers, for
    the worker to read from the shared file."""
    name = id or _stem(obs, 0)
    table = read_parquet(obs) if isinstance(obs, (str, os.PathLike)) else obs
    parts, longest = _native.split_rows(table, str(obs) if isinstance(obs, (str, os.PathLike)) else name, column, window)
    if isinstance(obs, (str, os.PathLike)):
        return [Job(f"{name}-{suffix}", os.fspath(obs), rows, longest) for suffix, rows in parts]
    return [Job(f"{name}-{suffix}", table.take(rows), longest_baseline=longest) for suffix, rows in parts]


def jobs(observations: Union[Observation, Sequence[Observation], Mapping[str, Observation]], split_by: Optional[Mapping[str, Any]] = None) -> list[Job]:
    """The jobs of a list of observations (ids from file names) or a mapping id -> observation,
    each one job, or each split by ``split_by`` (``{"column": "frequency"}``,
    ``{"column": "time", "window": 600}``). Repeated ids are refused: their products would
    overwrite each other. A single observation (a path or a table) is one job: a string is
    not taken for a list of its characters."""
    if isinstance(observations, (str, os.PathLike, pa.Table)):
        observations = [observations]
    items = list(observations.items()) if isinstance(observations, Mapping) else [(_stem(o, i), o) for i, o in enumerate(observations)]
    if split_by is None:
        out = [Job(name, os.fspath(obs) if isinstance(obs, os.PathLike) else obs) for name, obs in items]
    else:
        unknown = set(split_by) - {"column", "window"}
        if unknown or "column" not in split_by:
            raise ValueError(f"split_by: expected {{column, window}}, got {dict(split_by)}")
        out = [job for name, obs in items for job in split(obs, split_by["column"], split_by.get("window"), id=name)]
    seen = set()
    for job in out:
        if job.id in seen:
            raise ValueError(f"job id '{job.id}' comes twice: the second job's products would overwrite the first's (name the observations with a mapping)")
        seen.add(job.id)
    return out


def _image_job(job: Job, prefix: Optional[str], params: dict):
    """One task: one engine, one job (runs on a worker)."""
    if job.longest_baseline is not None and "longest_baseline" not in params:
        params = dict(params, longest_baseline=job.longest_baseline)
    products = r2d2_imaging.image(job.observation(), id=job.id, **params)
    if prefix is None:
        return products
    target = prefix.format(job=job.id)
    products.write(target)
    return JobResult(job.id, target, products.metrics, products.header)


def image_many(client, observations, *, split_by: Optional[Mapping[str, Any]] = None, prefix: Optional[str] = None,
               progress: bool = False, **params) -> list:
    """Image every job of ``observations`` (see :func:`jobs`) on ``client``'s workers, one
    task and one engine per job, and return the results in job order.

    ``params`` are :func:`r2d2_imaging.image`'s (``size``, ``step``, ``weighting``, ``threads``
    ...); ``threads`` is per task: give each task the cores of one worker thread (the default,
    0, uses every core of the worker's machine for each task). With ``prefix`` (``{job}`` its
    placeholder, on a file system the workers share) each worker writes its job's products
    there (as ``r2d2 image --name``) and returns a :class:`JobResult`; without, the products
    (:class:`r2d2_imaging.Products`, numpy arrays) come back to the client. ``progress`` shows a
    progress bar here; the dashboard shows the ``r2d2-image`` group either way. The first failed
    job raises its :class:`r2d2_imaging.R2D2Error`."""
    if prefix is not None and "{job}" not in prefix:
        raise ValueError(f"prefix {prefix!r}: expected the {{job}} placeholder, or every job would write the same files")
    todo = jobs(observations, split_by)
    # Tables go to the cluster once, as data of their own, rather than inside the task graph.
    shipped = [client.scatter(job, hash=False) if isinstance(job.obs, pa.Table) else job for job in todo]
    # Keys (r2d2-image-<token>, job id): the dashboard groups every task of the call under
    # `r2d2-image` (one progress bar) and names each job.
    token = os.urandom(8).hex()
    futures = [client.submit(_image_job, job, prefix, params, key=(f"r2d2-image-{token}", todo[i].id), pure=False) for i, job in enumerate(shipped)]
    if progress:
        from distributed import progress as show
        show(futures)
    return _gather(client, futures)


def _gather(client, futures):
    """The futures' results; at the first failure the tasks not yet started are cancelled
    (their results would be thrown away) before the error is raised. A task already running
    finishes on its worker: Dask cannot stop a running task."""
    try:
        return client.gather(futures)
    except BaseException:
        client.cancel(futures)
        raise


class _DaskPasses:
    """The passes over one observation's parts that the engine asks for (called from its
    thread): each a task per part on a worker that reads it, their results summed here in
    part order, so that a run is reproducible to the bit. Each part is a file the workers read
    (a shared file system, or each part on the worker ``workers`` names for it)."""

    def __init__(self, client, parts, workers, threads):
        self.client = client
        self.parts = parts
        self.workers = workers
        self.threads = threads
        self.token = os.urandom(6).hex()
        self.calls = itertools.count()
        self.rule = (None, None)
        # What each part's first reading found (its summary's ``check``): every pass over a
        # part is checked against it where it runs, so a part replaced or written to between
        # passes fails the pass, named, rather than summing samples of two tables.
        self.checks = [None] * len(parts)

    def describe(self) -> str:
        return f"{len(self.parts)} parts on a Dask cluster"

    def _pass(self, text: str) -> str:
        # The part's threads are the worker's, not those of the engine in this process.
        spec = json.loads(text)
        spec["threads"] = self.threads
        return json.dumps(spec)

    def _submit(self, function, *args, checked=True):
        """``function(part, check, *args)`` for every part (``function(part, *args)`` where not
        ``checked``), one task each: the futures in part order."""
        name = f"r2d2-parts-{self.token}-{next(self.calls)}"
        where = [{} if self.workers is None else {"workers": [self.workers[i]], "allow_other_workers": False} for i in range(len(self.parts))]
        first = [(part, self.checks[i]) if checked else (part,) for i, part in enumerate(self.parts)]
        return [self.client.submit(function, *first[i], *args, key=(name, i), pure=False, **where[i]) for i in range(len(self.parts))]

    def _map(self, function, *args, checked=True):
        """``function(part, check, *args)`` for every part, one task each; the results in part order."""
        return _gather(self.client, self._submit(function, *args, checked=checked))

    def _scattered_rule(self, density, f2):
        """The weighting rule on the workers, sent once (every pass after the density's uses it)."""
        digest = (hashlib.sha1(np.ascontiguousarray(density).view(np.uint8)).hexdigest(), f2)
        if self.rule[0] != digest:
            self.rule = (digest, self.client.scatter(np.asarray(density), broadcast=True, hash=False))
        return self.rule[1]

    def density(self, text):
        results = self._map(_native.part_density, self._pass(text))
        return functools.reduce(np.add, [d for d, _ in results]), float(sum(s for _, s in results))

    def images(self, text, density, f2):
        results = self._map(_native.part_images, self._pass(text), self._scattered_rule(density, f2), f2)
        dirty, psf, psf_2n = (functools.reduce(np.add, [r[k] for r in results]) for k in range(3))
        planes = [r[4] for r in results if r[4] is not None]
        return dirty, psf, psf_2n, int(sum(r[3] for r in results)), max(planes) if planes else None

    def w_toeplitz_images(self, text, density, f2, max_abs_w, max_uv):
        """The parts' dirty images and the kernels of their w-aware Toeplitz forms, summed in
        part order as each arrives (one part's kernels held here at a time beside the sum)."""
        futures = self._submit(_native.part_w_toeplitz, self._pass(text), self._scattered_rule(density, f2), f2, max_abs_w, max_uv)
        total, samples, planes, keys = None, 0, [], set()
        try:
            for future in futures:
                result = future.result()
                future.release()
                if result is None:
                    # A part cannot build the form (accuracy, or its worker's memory): the
                    # residual update runs through the operator over the parts instead.
                    self.client.cancel(futures)
                    return None
                dirty, count, chunk_planes, kernels, psf_2n, key = result
                del result
                keys.add(key)
                if total is None:
                    total = [dirty, kernels, psf_2n]
                else:
                    for acc, part in zip(total, (dirty, kernels, psf_2n)):
                        np.add(acc, part, out=acc)
                del dirty, kernels, psf_2n
                samples += int(count)
                if chunk_planes is not None:
                    planes.append(chunk_planes)
        except BaseException:
            self.client.cancel(futures)
            raise
        if len(keys) != 1:
            raise RuntimeError(f"the parts built their w-Toeplitz kernels on different planes: {sorted(keys)}")
        return total[0], samples, max(planes) if planes else None, total[1], total[2], keys.pop()

    def apply_normal(self, text, density, f2, x):
        x = self.client.scatter(np.asarray(x), broadcast=True, hash=False)
        return functools.reduce(np.add, self._map(_native.part_apply_normal, self._pass(text), self._scattered_rule(density, f2), f2, x))


def _part_summary_and_identity(part: str):
    """A part's metadata and summary, and what tells it from the others where it is read: its
    real path and its file's (device, inode), the same for a part named twice through another
    path, a link or a hard link."""
    meta, summary = _native.part_summary(part)
    status = os.stat(part)
    return meta, summary, (os.path.realpath(part), (status.st_dev, status.st_ino))


def _refuse_parts_given_twice(parts, workers, identities):
    """A part given twice would be summed twice into every image (its samples weigh double):
    refused, naming both, where two parts read on one worker (or on the shared file system)
    have the same real path or the same file."""
    first_of = {}
    for i, (path, file) in enumerate(identities):
        where = None if workers is None else workers[i]
        for key in ((where, "path", path), (where, "file", file)):
            if key in first_of:
                j = first_of[key]
                raise ValueError(
                    f"parts: part {j} ({parts[j]}) and part {i} ({parts[i]}) are one file ({path}): "
                    "each part must be given once (its samples would be summed twice)")
            first_of[key] = i


def image_parts(client, parts: Sequence[Union[str, "os.PathLike[str]"]], *, id: Optional[str] = None,
                workers: Optional[Sequence[str]] = None, part_threads: int = 0, **params):
    """Image one observation kept in ``parts`` (files the engine reads: Parquet, Arrow IPC,
    MeasurementSets; channels, time or row ranges of one observation, with one phase centre)
    on ``client``'s workers, and return its :class:`r2d2_imaging.Products`.

    Each pass over the samples is a task per part, run where the part is read (``workers``:
    the worker address holding each part, else any worker, on a shared file system): the
    summary that fixes the pixel size and the w-term, the uv density of uniform and Briggs
    weighting, then the dirty image and PSFs, whose sums come back here. The image-domain loop
    (the networks, CLEAN, the PSF-convolution residual) runs once, in this process. With the
    w-term, each part also sends the kernels of its w-aware Toeplitz form (8 bytes x (2N)^2 a
    w-plane), summed here, so the residual update needs the parts no more; where that form does
    not fit or reach the accuracy, each residual update is one more task per part (the part's
    operator applied to the model). ``part_threads``: each task's threads (0: every core of its
    worker).

    The products equal :func:`r2d2_imaging.image` of the parts joined in one table: coplanar to
    the rounding of the sums, and with the w-term to the NUFFT's accuracy (each part has
    w-planes of its own for its dirty image). ``params`` are :func:`r2d2_imaging.image`'s (``size``, ``step``,
    ``weighting`` ...); ``id`` names the job (default: the first part's file name)."""
    parts = [os.fspath(p) for p in parts]
    if not parts:
        raise ValueError("parts: expected at least one part")
    if workers is not None and len(workers) != len(parts):
        raise ValueError(f"workers: expected one worker per part ({len(parts)}), got {len(workers)}")
    passes = _DaskPasses(client, parts, list(workers) if workers is not None else None, part_threads)
    summaries = passes._map(_part_summary_and_identity, checked=False)
    passes.checks = [summary.get("check") for _, summary, _ in summaries]
    _refuse_parts_given_twice(parts, workers, [identity for _, _, identity in summaries])
    described = [(part, meta, summary) for part, (meta, summary, _) in zip(parts, summaries)]
    name = id or _stem(parts[0], 0)
    observation = _native.Parts(name, described, passes, passes.describe())
    return r2d2_imaging.image(observation, id=name, **params)
