#!/usr/bin/env python3
"""Ground truths for training from scikit-image's bundled images (no downloads).

The paper's recipe (Section 3.2, Terris et al. 2023): take low-dynamic-range images, denoise
and soft-threshold them so the background is exactly zero, break recognisable structure
(concatenate, rotate, translate, smooth edges) and crop to the training size. The
exponentiation to a high dynamic range happens later, per sample, in `r2d2 trainset`
(`--source-dr` is the dynamic range these images are given here: the soft threshold removes
everything below 1/source_dr of the peak's scale).

Each output is an N x N float32 .npy with peak 1, zero background and emission tapered to
zero before the border (sources cut by the edge would alias in from the other side).
"""
import argparse
import os
import sys

import numpy as np
from scipy import ndimage
import skimage.data
from skimage.transform import resize, rotate

# Medical/biological, optical astronomy and other natural images bundled in scikit-image 0.26
# (BSD-3 package; see skimage/data/README.txt for each image's licence: public domain, CC0 or
# CC-BY, none restricts this use). Radio-like images are kept for validation/testing
# (the project's procedural radio skies), as the paper keeps its sources apart.
SOURCES = [
    "hubble_deep_field", "moon", "retina", "cell", "microaneurysms",
    "camera", "astronaut", "coins", "brick", "grass", "gravel", "rocket", "coffee",
    "chelsea", "page", "text",
]


def load_gray(name):
    img = np.asarray(getattr(skimage.data, name)(), dtype=np.float64)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2) if name != "retina" else img[..., 1]
    return img / max(img.max(), 1e-12)


def random_patch(img, n, rng):
    """A rotated, flipped crop of random scale, resized to n x n."""
    h, w = img.shape
    side = int(rng.uniform(0.25, 1.0) * min(h, w))
    side = max(side, min(h, w, n // 2))
    y0 = rng.integers(0, h - side + 1)
    x0 = rng.integers(0, w - side + 1)
    patch = img[y0:y0 + side, x0:x0 + side]
    patch = rotate(patch, rng.uniform(0, 360), mode="reflect")
    patch = resize(patch, (n, n), anti_aliasing=True)
    if rng.random() < 0.5:
        patch = patch[:, ::-1]
    if rng.random() < 0.5:
        patch = patch[::-1, :]
    return patch


def smooth_mask(n, rng):
    """A random smooth blob mask in [0, 1]: breaks anatomy and leaves empty sky between."""
    field = ndimage.gaussian_filter(rng.standard_normal((n, n)), sigma=rng.uniform(n / 16, n / 6))
    field = (field - field.mean()) / (field.std() + 1e-12)
    return np.clip((field - rng.uniform(-0.5, 0.8)) / 0.7, 0.0, 1.0)


def border_taper(n, support=0.85):
    """1 in the central `support` box, cosine to 0 over 6% of the side, 0 outside."""
    x = (np.arange(n) + 0.5) / n - 0.5
    edge, width = support / 2, 0.06
    t = np.clip((edge - np.abs(x)) / width, 0.0, 1.0)
    t = 0.5 - 0.5 * np.cos(np.pi * t)
    return np.outer(t, t)


def make_truth(images, n, rng, source_dr):
    """Combine 1-3 patches through smooth masks, denoise, soft-threshold, taper, normalise."""
    out = np.zeros((n, n))
    for _ in range(rng.integers(1, 4)):
        patch = random_patch(images[rng.integers(len(images))], n, rng)
        patch = patch ** rng.uniform(1.0, 3.0)  # contrast: bright features stand out
        out = np.maximum(out, patch * smooth_mask(n, rng))
    # Denoise (the 8-bit quantisation and sensor noise) with a small Gaussian, then
    # soft-threshold at a random level so the background is exactly zero.
    out = ndimage.gaussian_filter(out, sigma=rng.uniform(0.5, 1.5))
    out *= border_taper(n)
    peak = out.max()
    if peak <= 0:
        return None
    out /= peak
    level = np.quantile(out, rng.uniform(0.4, 0.85))
    out = np.maximum(out - max(level, 1.0 / source_dr), 0.0)
    if out.max() <= 0 or np.count_nonzero(out) < 20:
        return None
    return (out / out.max()).astype(np.float32)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--count", type=int, required=True)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--source-dr", type=float, default=50.0)
    p.add_argument("--out", required=True, help="directory for 00000.npy ... (created)")
    a = p.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    images = [load_gray(name) for name in SOURCES]
    os.makedirs(a.out, exist_ok=True)
    k = 0
    while k < a.count:
        t = make_truth(images, a.size, rng, a.source_dr)
        if t is None:
            continue
        tmp = os.path.join(a.out, f".{k:05d}.npy")
        np.save(tmp, t)
        os.replace(tmp, os.path.join(a.out, f"{k:05d}.npy"))
        k += 1
    print(f"wrote {a.count} ground truths ({a.size} x {a.size}) to {a.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
