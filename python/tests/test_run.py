"""r2d2_imaging.run / validate: a YAML pipeline as `r2d2 run` / `r2d2 validate` runs it."""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import r2d2_imaging
from conftest import read_fits

PIPELINE = textwrap.dedent("""\
    name: small
    threads: 1
    image: {size: 64, superresolution: 1.5}
    stages:
      source: {kind: simulate, seed: 11, jobs: 2, configurations: [c], hours: [1], dynamic_range: 1.0e3, to: weights}
      weights: {kind: weighting, scheme: briggs, robust: 0, to: grid}
      grid: {kind: gridder, to: step}
      step: {kind: clean, major_cycles: 3, to: update}
      update: {kind: residual, method: toeplitz, to: step, done: write}
      write: {kind: writer, prefix: "out/{job}", previews: false}
    """)


def test_run_makes_the_cli_products(r2d2_bin, tmp_path):
    (tmp_path / "p.yaml").write_text(PIPELINE)
    report = r2d2_imaging.run(tmp_path / "p.yaml", set={"write.prefix": str(tmp_path / "py/{job}")})
    subprocess.run([str(r2d2_bin), "-q", "run", "p.yaml", "--set", f"write.prefix={tmp_path}/cli/{{job}}"], cwd=tmp_path, check=True)
    assert sorted(report["jobs"]) == ["sim-11", "sim-12"]
    assert [m["residual_ratio"] for m in report["metrics"]["sim-11"]["iterations"]] == [
        m["residual_ratio"] for m in json.loads((tmp_path / "cli/sim-11-metrics.json").read_text())["iterations"]]
    assert report["seconds"] > 0 and set(report["stage_seconds"]) == {"source", "weights", "grid", "step", "update", "write"}
    for job in report["jobs"]:
        for product in ["dirty", "psf", "model", "residual", "image"]:
            a, _ = read_fits(tmp_path / f"py/{job}-{product}.fits")
            b, _ = read_fits(tmp_path / f"cli/{job}-{product}.fits")
            np.testing.assert_array_equal(a, b, err_msg=f"{job} {product}")


def test_yaml_text_and_overrides_of_any_type(tmp_path):
    stages = r2d2_imaging.validate(PIPELINE, set={"image.size": 32, "step.major_cycles": 2, "write.prefix": tmp_path / "{job}"})
    assert stages == ["source", "weights", "grid", "step", "update", "write"]


def test_errors_carry_file_line_and_column(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(PIPELINE.replace("scheme: briggs", "schem: briggs"))
    with pytest.raises(r2d2_imaging.R2D2Error) as error:
        r2d2_imaging.validate(bad)
    message = str(error.value)
    assert f"{bad}: line 6, column 30" in message and "stages.weights.schem" in message, message
    # YAML text is named <string>; an override names the key.
    with pytest.raises(r2d2_imaging.R2D2Error, match="<string>: line 5"):
        r2d2_imaging.validate(PIPELINE.replace("kind: simulate", "kind: simulat"))
    with pytest.raises(r2d2_imaging.R2D2Error, match="nope"):
        r2d2_imaging.validate(PIPELINE, set={"step.nope": 1})


def test_a_failing_stage_names_itself_and_the_job(tmp_path):
    (tmp_path / "file").write_text("not a directory")
    with pytest.raises(r2d2_imaging.R2D2Error) as error:
        r2d2_imaging.run(PIPELINE, set={"write.prefix": str(tmp_path / "file/{job}")})
    message = str(error.value)
    assert "stage 'write' (writer)" in message and "job 'sim-1" in message, message


def test_module_errors_raise_their_own_subclass(tmp_path):
    """An error of a module that has its own kind raises that subclass of R2D2Error, with the
    file and the cause beneath in its message, each once; it pickles (Dask sends it back)."""
    import pickle

    library = tmp_path / "libnotes.so"
    library.write_text("not a library\n")
    native = PIPELINE.replace("step: {kind: clean, major_cycles: 3, to: update}", f"step: {{kind: native, library: '{library}', iterations: 1, to: update}}")
    with pytest.raises(r2d2_imaging.PluginError) as error:
        r2d2_imaging.validate(native)
    message = str(error.value)
    assert message.count(str(library)) == 1 and message.count("does not start with an ELF header") == 1, message
    assert isinstance(error.value, r2d2_imaging.R2D2Error)
    again = pickle.loads(pickle.dumps(error.value))
    assert type(again) is r2d2_imaging.PluginError and str(again) == message


def test_an_unreadable_table_raises_table_error(tmp_path):
    """A file that is not Parquet raises TableError (an R2D2Error) naming the file once, with
    the decoder's reason beneath; it pickles like the others."""
    import pickle

    obs = tmp_path / "obs.parquet"
    obs.write_text("u,v,w\n1,2,3\n")
    with pytest.raises(r2d2_imaging.TableError) as error:
        r2d2_imaging.image(str(obs), size=64, step="clean")
    message = str(error.value)
    assert message.count(str(obs)) == 1 and "not a visibility table" in message, message
    assert isinstance(error.value, r2d2_imaging.R2D2Error)
    again = pickle.loads(pickle.dumps(error.value))
    assert type(again) is r2d2_imaging.TableError and str(again) == message


def test_ctrl_c_stops_the_engine_cleanly(tmp_path):
    """SIGINT while the engine works (GIL released, on its own threads) raises
    KeyboardInterrupt within a job boundary, and leaves no partial products."""
    # The child takes Ctrl-C as an interactive Python does, whatever this process inherited
    # (a shell's background job starts with SIGINT ignored, and Python then leaves it so).
    script = textwrap.dedent(f"""\
        import signal, sys, time, r2d2_imaging
        signal.signal(signal.SIGINT, signal.default_int_handler)
        pipeline = {PIPELINE!r}.replace("jobs: 2", "jobs: 400").replace("size: 64", "size: 128")
        print("started", flush=True)
        try:
            r2d2_imaging.run(pipeline, set={{"write.prefix": {str(tmp_path / "out/{job}")!r}}})
        except KeyboardInterrupt:
            print("interrupted", flush=True)
            sys.exit(3)
        print("finished", flush=True)
        """)
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "started"
    time.sleep(3)
    sent = time.monotonic()
    child.send_signal(signal.SIGINT)
    out, err = child.communicate(timeout=60)
    stopped_after = time.monotonic() - sent
    assert child.returncode == 3 and "interrupted" in out, (child.returncode, out, err)
    assert stopped_after < 20, stopped_after
    written = sorted(p.name for p in (tmp_path / "out").iterdir()) if (tmp_path / "out").exists() else []
    # Whole jobs only: each job's products all there, nothing staged left behind.
    jobs = {name.rsplit("-", 1)[0] for name in written}
    assert 0 < len(jobs) < 400, written[:10]
    for job in jobs:
        for product in ["dirty", "psf", "model", "residual", "image"]:
            assert f"{job}-{product}.fits" in written, (job, product)
    assert all(not name.startswith(".") for name in written), written
