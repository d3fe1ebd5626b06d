"""The Stimela2 cabs (r2d2_imaging/r2d2.yml) in a two-step recipe on the native backend:
simulate, then image; the products must be those `r2d2 image` makes from the same file."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

import r2d2_imaging
from conftest import read_fits

RECIPE = Path(__file__).with_name("recipe.yml")
PRODUCTS = ["dirty", "psf", "model", "residual"]


def test_the_cab_ships_with_the_package():
    assert (Path(r2d2_imaging.__file__).parent / "r2d2.yml").is_file()


def test_recipe_simulates_then_images(r2d2_bin, tmp_path):
    shutil.copy(RECIPE, tmp_path / "recipe.yml")
    env = dict(os.environ, COLUMNS="1000", PATH=f"{r2d2_bin.parent}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    stimela = Path(sys.executable).parent / "stimela"
    done = subprocess.run([str(stimela), "run", "recipe.yml", "simulate_and_image", "size=128", "prefix=products/obs"],
                          cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-4000:]
    assert "recipe 'simulate_and_image' executed successfully" in done.stdout + done.stderr

    # Every implicit output of the image cab exists, the restored image included.
    for product in PRODUCTS + ["image"]:
        assert (tmp_path / f"products/obs-{product}.fits").is_file(), product
    metrics = json.loads((tmp_path / "products/obs-metrics.json").read_text())
    # The truth the simulate step wrote reached the image step: SNR per iteration, and the series
    # improves on its first network.
    snr = [row["snr"] for row in metrics["iterations"]]
    assert len(snr) >= 2 and snr[-1] > snr[0], snr

    # The same file imaged by the command line directly gives the same products, pixel for pixel.
    direct = tmp_path / "direct"
    subprocess.run([str(r2d2_bin), "-q", "image", str(tmp_path / "obs.parquet"), "--size", "128", "--truth",
                    str(tmp_path / "obs.sky.fits"), "--name", str(direct / "obs")], check=True)
    for product in PRODUCTS:
        a, _ = read_fits(tmp_path / f"products/obs-{product}.fits")
        b, _ = read_fits(direct / f"obs-{product}.fits")
        assert a.dtype.kind == "f" and a.dtype.itemsize == 4 and a.shape == (128, 128)
        np.testing.assert_array_equal(a, b, err_msg=product)


def test_recipe_images_in_wsclean_with_the_r2d2_deconvolver(r2d2_bin, tmp_path):
    """The `r2d2-wsclean` cab: WSClean with the R2D2 deconvolver, on an MS the recipe writes."""
    shutil.copy(RECIPE, tmp_path / "recipe.yml")
    env = dict(os.environ, COLUMNS="1000", PATH=f"{r2d2_bin.parent}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    stimela = Path(sys.executable).parent / "stimela"
    done = subprocess.run([str(stimela), "run", "recipe.yml", "simulate_and_image_in_wsclean"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-4000:]
    log = (tmp_path / "logs" / "log-simulate_and_image_in_wsclean.image.txt").read_text()
    assert "r2d2: series vla-r2d2-512 (43 networks) on 128 x 128; telescope VLA, super-resolution 1.5" in log, log[-3000:]
    assert "was not trained for this job" not in log, "the recipe's pixel is the series' super-resolution"
    model, header = read_fits(tmp_path / "products/ws-model.fits")
    truth, _ = read_fits(tmp_path / "obs.sky.fits")
    snr = 20 * np.log10(np.linalg.norm(truth) / np.linalg.norm(truth - model))
    assert model.shape == (128, 128) and snr > 10, f"SNR {snr:.2f} dB"
