"""r2d2_imaging.dask on a LocalCluster of two worker processes: every job's products equal a
single-process run's, pixel for pixel."""

import os
import numpy as np
from dask.utils import key_split
import pytest
from distributed import Client, LocalCluster, get_task_stream

import pyarrow.parquet as pq
import r2d2_imaging
from r2d2_imaging.dask import JobResult, image_many, image_parts, jobs, read_parquet
from conftest import read_fits, simulate

# CLEAN keeps these tests quick; one thread per task, as in the single-process runs they are
# compared with (the gridder's sums follow the thread count).
PARAMS = dict(size=128, step="clean", iterations=3, threads=1)
ARRAYS = ["dirty", "psf", "model", "residual", "image"]


@pytest.fixture(scope="module")
def client():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, Client(cluster) as client:
        yield client


@pytest.fixture(scope="module")
def channels(r2d2_bin, tmp_path_factory):
    """One observation of 3 channels with a tenth of its samples flagged."""
    return simulate(r2d2_bin, tmp_path_factory.mktemp("split") / "multi.parquet", 21, nfreq=3, freq_ratio=1.5, flag_fraction=0.1)


def assert_same(a, b, what):
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"{what}: {name}")
    assert a.header == b.header, what
    assert figures(a.metrics) == figures(b.metrics), what


def figures(metrics):
    """The metrics without the seconds, which differ from run to run."""
    return [(m["iteration"], m["residual_ratio"], m["snr"], m["logsnr"]) for m in metrics["iterations"]]


def test_every_job_equals_a_single_process_run(client, observations):
    with get_task_stream(client) as stream:
        results = image_many(client, observations, **PARAMS)
    assert [r.id for r in results] == [p.stem for p in observations]
    for path, result in zip(observations, results):
        assert_same(result, r2d2_imaging.image(path, **PARAMS), path.name)
    # The jobs ran on both workers, one engine per task, as one group on the dashboard.
    assert len({task["worker"] for task in stream.data}) == 2
    assert {key_split(task["key"]) for task in stream.data} == {"r2d2-image"}


def test_split_by_channel_equals_the_engines_own_split(client, channels, tmp_path):
    """Split here and imaged on the workers, written under a prefix, against one `r2d2 run` of
    the file with `split_by`: the same jobs and the same files."""
    results = image_many(client, [channels], split_by={"column": "frequency"}, prefix=str(tmp_path / "dask/{job}"), **PARAMS)
    assert all(isinstance(r, JobResult) for r in results)
    yaml = f"""\
name: split
threads: 1
image: {{size: 128, superresolution: 1.5}}
stages:
  read: {{kind: parquet, files: "{channels}", split_by: {{column: frequency}}, to: weights}}
  weights: {{kind: weighting, scheme: briggs, robust: 0, to: grid}}
  grid: {{kind: gridder, to: step}}
  step: {{kind: clean, major_cycles: 3, to: update}}
  update: {{kind: residual, method: toeplitz, to: step, done: write}}
  write: {{kind: writer, prefix: "{tmp_path}/single/{{job}}"}}
"""
    report = r2d2_imaging.run(yaml)
    assert sorted(r.id for r in results) == sorted(report["jobs"]) == ["multi-ch00", "multi-ch01", "multi-ch02"]
    written = sorted(p.name for p in (tmp_path / "dask").iterdir())
    assert written == sorted(p.name for p in (tmp_path / "single").iterdir())
    for name in written:
        if name.endswith(".fits"):
            a, ha = read_fits(tmp_path / "dask" / name)
            b, hb = read_fits(tmp_path / "single" / name)
            np.testing.assert_array_equal(a, b, err_msg=name)
            assert ha == hb, name


def test_time_windows_of_a_table_in_memory(client, channels):
    table = read_parquet(channels)
    todo = jobs({"obs": table}, split_by={"column": "time", "window": 1200})
    results = image_many(client, {"obs": table}, split_by={"column": "time", "window": 1200}, **PARAMS)
    assert [r.id for r in results] == [j.id for j in todo] and len(todo) >= 3
    for job, result in zip(todo, results):
        assert_same(result, r2d2_imaging.image(job.obs, id=job.id, longest_baseline=job.longest_baseline, **PARAMS), job.id)
    # The windows of A and C configurations share one grid, as the engine's own split's do.
    assert len({r.metrics["settings"]["pixel_arcsec"] for r in results}) == 1, [r.metrics["settings"]["pixel_arcsec"] for r in results]


def test_a_failed_job_raises_the_engines_error(client, observations, tmp_path):
    missing = tmp_path / "missing.parquet"
    with pytest.raises(r2d2_imaging.R2D2Error, match="missing.parquet"):
        image_many(client, [observations[0], missing], **PARAMS)
    # The other job, still running when the missing one failed, was cancelled: nothing of the
    # call is left on the cluster (or it would finish into a later call's task stream).
    left = [key for keys in client.processing().values() for key in keys]
    assert not [key for key in left if key_split(key) == "r2d2-image"], left


def test_prefix_needs_the_job_placeholder(client, observations):
    with pytest.raises(ValueError, match="placeholder"):
        image_many(client, observations, prefix="out/same", **PARAMS)


def test_a_single_path_or_table_is_one_job(tmp_path):
    # A string is one observation, not a list of characters ("Failed to open local file 'o'").
    (one,) = jobs(str(tmp_path / "obs.parquet"))
    assert one.id == "obs"
    (one,) = jobs(tmp_path / "obs.parquet")
    assert one.id == "obs"
    import pyarrow as pa
    (one,) = jobs(pa.table({"u": [0.0]}))
    assert one.id == "table0"


@pytest.fixture(scope="module")
def parted(r2d2_bin, tmp_path_factory):
    """One observation in one file, and the same rows in three Parquet parts of unequal sizes
    (as row ranges of a track), each with the observation's metadata."""
    root = tmp_path_factory.mktemp("parts")
    whole = simulate(r2d2_bin, root / "whole.parquet", 31)
    table = read_parquet(whole)
    bounds = [0, table.num_rows // 5, table.num_rows // 2, table.num_rows]
    parts = []
    for k, (start, stop) in enumerate(zip(bounds, bounds[1:])):
        part = root / f"part{k}.parquet"
        pq.write_table(table.slice(start, stop - start), part)
        parts.append(part)
    return whole, parts


@pytest.mark.parametrize("w_term", ["off", "on"])
def test_an_observation_in_parts_images_as_the_whole_table(client, parted, w_term):
    """Each part gridded by a worker, the sums imaged here: the products of the whole table in
    one process, coplanar to the rounding of the sums, with the w-term to the NUFFT's accuracy
    (each part's w-planes are its own; the kernels of the residual update's w-aware Toeplitz
    form summed over the parts); the parts' tasks ran on both workers."""
    whole, parts = parted
    params = dict(PARAMS, w_term=w_term, weighting="briggs", robust=0.0)
    with get_task_stream(client) as stream:
        products = image_parts(client, parts, id="whole", part_threads=1, **params)
    single = r2d2_imaging.image(whole, **params)
    tolerance = 1e-6 if w_term == "off" else 1e-5
    for name in ["dirty", "psf", "model", "residual"]:
        a, b = getattr(single, name), getattr(products, name)
        assert np.max(np.abs(a - b)) <= tolerance * np.max(np.abs(a)), (w_term, name)
    assert products.id == "whole"
    assert products.metrics["settings"]["w_term"]["corrected"] == (w_term == "on")
    # With the w-term, each part sent the kernels of its w-aware Toeplitz form: the residual
    # update convolved, as the single process's did.
    for run in (products, single):
        assert (run.metrics["settings"]["w_term"]["toeplitz_planes"] is not None) == (w_term == "on")
    assert figures(products.metrics)[-1][0] == figures(single.metrics)[-1][0]
    assert len({task["worker"] for task in stream.data}) == 2
    assert {key_split(task["key"]) for task in stream.data} == {"r2d2-parts"}


def test_parts_of_two_observations_are_refused_naming_the_part(client, parted, r2d2_bin, tmp_path):
    _, parts = parted
    other = simulate(r2d2_bin, tmp_path / "elsewhere.parquet", 32, dec=10)
    with pytest.raises(r2d2_imaging.R2D2Error, match="elsewhere.parquet.*another observation"):
        image_parts(client, [parts[0], other], **PARAMS)


def test_a_part_changed_between_passes_is_refused_naming_it(client, parted, tmp_path, monkeypatch):
    """A part replaced after its summary by one of as many samples with other values (w x 0.9,
    the weights doubled): the next pass over it fails naming it, as a table read again at each
    pass does (the sum of the parts' sample counts, all that was compared, was unchanged)."""
    import shutil
    import pyarrow.compute as pc
    import r2d2_imaging.dask as dask_module
    _, parts = parted
    copies = [shutil.copy(part, tmp_path / os.path.basename(part)) for part in parts]
    density = dask_module._DaskPasses.density

    def replace_then_density(self, text):
        table = pq.read_table(copies[1])
        for column, factor in [("w", 0.9), ("weight", 2.0)]:
            i = table.schema.get_field_index(column)
            table = table.set_column(i, table.schema.field(i), pc.multiply(table.column(column), factor).cast(table.schema.field(i).type))
        pq.write_table(table, copies[1])
        return density(self, text)

    monkeypatch.setattr(dask_module._DaskPasses, "density", replace_then_density)
    with pytest.raises(r2d2_imaging.R2D2Error, match=r"part1\.parquet: this part of the observation changed between passes: a later pass found as many samples"):
        image_parts(client, copies, **dict(PARAMS, weighting="briggs", robust=0.0))


def test_a_part_given_twice_is_refused_naming_both(client, parted, tmp_path):
    """The same part twice, by its own path, through a link, or by another spelling of the
    path: its samples would be summed twice into every image; refused before any pass."""
    _, parts = parted
    link = tmp_path / "again.parquet"
    link.symlink_to(parts[1])
    hard = tmp_path / "hard.parquet"
    os.link(parts[2], hard)
    spelled = os.path.join(os.path.dirname(parts[0]), ".", os.path.basename(parts[0]))
    for twice, names in [([parts[0], parts[1], parts[0]], (0, 2)), ([parts[0], parts[1], link], (1, 2)),
                         ([hard, parts[1], parts[2]], (0, 2)), ([parts[0], spelled], (0, 1))]:
        with pytest.raises(ValueError, match=rf"part {names[0]} \(.*\) and part {names[1]} \(.*\) are one file"):
            image_parts(client, twice, **PARAMS)
