"""Shared fixtures: the `r2d2` binary the CLI comparisons and the Stimela cabs run, and small
simulated observations."""

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def r2d2_bin() -> Path:
    """The `r2d2` command line: $R2D2_BIN (tests/python.rs sets it to the binary cargo built),
    else target/release/r2d2. Missing is a failure, not a skip: the cab and the CLI
    comparisons are what these tests are for."""
    path = Path(os.environ.get("R2D2_BIN", REPO / "target" / "release" / "r2d2"))
    assert path.is_file(), f"no r2d2 binary at {path}: run `cargo build --release` or set R2D2_BIN"
    return path


def simulate(r2d2_bin: Path, out: Path, seed: int, size: int = 128, **options) -> Path:
    """A small VLA observation (`r2d2 simulate`), with its true sky beside it."""
    args = [str(r2d2_bin), "-q", "simulate", "--sky", f"procedural:{seed}", "--configs", "a,c", "--hours", "1,0.5",
            "--dr", "1000", "--size", str(size), "--seed", str(seed), "--out", str(out)]
    for key, value in options.items():
        args += [f"--{key.replace('_', '-')}", str(value)]
    subprocess.run(args, check=True)
    return out


@pytest.fixture(scope="session")
def observations(r2d2_bin, tmp_path_factory) -> list:
    """Four 128 x 128 observations of different skies."""
    root = tmp_path_factory.mktemp("obs")
    return [simulate(r2d2_bin, root / f"obs{seed}.parquet", seed) for seed in range(1, 5)]


def read_fits(path: Path):
    """A product as astropy reads it (an independent FITS reader): the (N, N) image and its
    header."""
    with fits.open(path) as hdus:
        return np.squeeze(hdus[0].data), hdus[0].header
