"""Data sets written by `r2d2 trainset`, the normal operator D, the R2D2 update and metrics.

Conventions (shared/reference/r2d2-conventions.md, docs/conventions.md):
- D x = crop(IFFT(FFT(pad(x)) * FFT(psf_2N))): x padded into the top-left N x N of a 2N x 2N
  grid, PSF peak at (N, N), output pixel p read at p + N -- exactly the Rust `PsfConvolution`.
- Iteration i: alpha = mean(x_{i-1}) (mean(dirty) for i = 1); input [dirty/alpha, 0] for
  i = 1, [x/alpha, r/alpha] for i >= 2; x_i = max(0, x_{i-1}/alpha + N_i(input)) * alpha;
  r_i = dirty - D x_i.
"""
import json
import os

import numpy as np
import torch


REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def repo_relative(path):
    """A path as provenance records it: relative to the repository, never the machine's."""
    rel = os.path.relpath(os.path.abspath(path), REPO)
    return rel if not rel.startswith("..") else os.path.basename(os.path.normpath(path))


def portable(meta):
    """`meta` with every absolute path made repository-relative (recursively)."""
    if isinstance(meta, dict):
        return {k: portable(v) for k, v in meta.items()}
    if isinstance(meta, list):
        return [portable(v) for v in meta]
    if isinstance(meta, str) and os.path.isabs(meta):
        return repo_relative(meta)
    return meta


class Dataset:
    """Stacked arrays of one or more `r2d2 trainset` directories (float32 images, float64 PSF
    spectra), concatenated in the order given."""

    def __init__(self, paths, limit=None):
        paths = [paths] if isinstance(paths, str) else list(paths)
        self.path = paths[0] if len(paths) == 1 else paths
        # The first `limit` samples of the concatenation, cut before loading (memory).
        parts = []
        for p in paths:
            left = None if limit is None else limit - sum(len(part["samples"]) for part in parts)
            if left is not None and left <= 0:
                break
            parts.append(_load_set(p, left))
        cat = lambda key: torch.cat([part[key] for part in parts])
        self.truth, self.dirty, self.noise_dirty = cat("truth"), cat("dirty"), cat("noise_dirty")
        self.psf_hat = cat("psf_hat")  # [S, 2N, N+1] complex128
        self.samples = [s for part in parts for s in part["samples"]]
        # Each set's directory and how many of its samples were taken, in order.
        self.parts = [(p, len(part["samples"])) for p, part in zip(paths, parts)]
        self.meta = parts[0]["meta"] if len(paths) == 1 else {"sets": [part["meta"] for part in parts]}
        self.dynamic_range = torch.tensor([s["dynamic_range"] for s in self.samples], dtype=torch.float64)

    def spectra_to(self, device):
        """Keep the PSF spectra on `device`: D x then runs there (the images stay on the CPU)."""
        self.psf_hat = self.psf_hat.to(device)
        return self

    def __len__(self):
        return self.truth.shape[0]

    @property
    def size(self):
        return self.truth.shape[-1]


def _load_set(path, limit=None):
    """One set's first `limit` samples (all with None)."""
    sl = slice(None, limit)
    load = lambda name: np.load(os.path.join(path, name), mmap_mode="r")[sl]
    psf = load("psf2n.npy")
    # The PSF spectra in chunks: the 2N PSFs as float64 all at once would double the peak.
    psf_hat = torch.cat([torch.fft.rfft2(torch.from_numpy(np.array(psf[s:s + 32], dtype=np.float64)))
                         for s in range(0, psf.shape[0], 32)])
    with open(os.path.join(path, "samples.json")) as f:
        samples = json.load(f)[sl]
    with open(os.path.join(path, "trainset.json")) as f:
        meta = json.load(f)
    images = {name: torch.from_numpy(np.array(load(f"{name}.npy"), dtype=np.float32)) for name in ("truth", "dirty", "noise_dirty")}
    return {**images, "psf_hat": psf_hat, "samples": samples, "meta": meta}


def apply_d(x, psf_hat):
    """D x for a batch x [S, N, N] with the rFFT of the 2N PSFs [S, 2N, N+1]; float64, computed
    where the spectra are (a GPU when `Dataset.spectra_to` put them there), returned on x's device."""
    n = x.shape[-1]
    xp = torch.zeros(x.shape[0], 2 * n, 2 * n, dtype=torch.float64, device=psf_hat.device)
    xp[:, :n, :n] = x.to(psf_hat.device, torch.float64)
    y = torch.fft.irfft2(torch.fft.rfft2(xp) * psf_hat, s=(2 * n, 2 * n))
    return y[:, n:, n:].to(x.device)


def residual(dirty, x, psf_hat, batch=64):
    """r = dirty - D x, float32, in batches (memory)."""
    out = torch.empty_like(dirty)
    for s in range(0, dirty.shape[0], batch):
        e = s + batch
        out[s:e] = (dirty[s:e].to(torch.float64) - apply_d(x[s:e], psf_hat[s:e])).to(torch.float32)
    return out


# Added to the mean, as the reference and the engine do (src/steps/onnx.rs).
NORMALISATION_EPSILON = 1e-10


def network_input(iteration, dirty, x, r):
    """Normalised 2-channel input [B, 2, N, N] and alpha [B, 1, 1] (reference order)."""
    if iteration == 1:
        alpha = dirty.mean(dim=(-2, -1), keepdim=True) + NORMALISATION_EPSILON
        inp = torch.stack([dirty / alpha, torch.zeros_like(dirty)], dim=1)
        prev = torch.zeros_like(dirty)
    else:
        alpha = x.mean(dim=(-2, -1), keepdim=True) + NORMALISATION_EPSILON
        inp = torch.stack([x / alpha, r / alpha], dim=1)
        prev = x / alpha
    return inp, alpha, prev


def update(iteration, run_network, dirty, x, r, batch=None):
    """x_i for every sample: max(0, x_{i-1}/alpha + N_i(input)) * alpha (float32)."""
    out = torch.empty_like(dirty)
    batch = batch or max(1, (32 * 128 * 128) // (dirty.shape[-1] * dirty.shape[-2]))
    for s in range(0, dirty.shape[0], batch):
        e = s + batch
        inp, alpha, prev = network_input(iteration, dirty[s:e], x[s:e], r[s:e])
        inc = run_network(inp)[:, 0]
        out[s:e] = torch.clamp((prev + inc) * alpha, min=0.0)
    return out


# Metrics (conventions file, "Metrics"), per sample, float64.
def snr(est, truth):
    est, truth = est.to(torch.float64), truth.to(torch.float64)
    return 20 * torch.log10(truth.flatten(1).norm(dim=1) / (truth - est).flatten(1).norm(dim=1))


def rlog_at(x, a, peak):
    """peak log(1 + a x / peak) / log a of max(x, 0), with a and peak broadcast against x (the
    dtype is the inputs'): the logSNR's transform at a given peak, which a loss on crops takes
    from the full-field truth."""
    return peak * torch.log1p(a * x.clamp(min=0) / peak) / torch.log(a)


def rlog(x, a):
    """The logSNR's transform of images [B, N, N], each at its own peak, in float64."""
    x = x.to(torch.float64).clamp(min=0)
    peak = x.flatten(1).max(dim=1).values.clamp(min=1e-300).view(-1, 1, 1)
    return rlog_at(x, a.view(-1, 1, 1), peak)


def log_snr(est, truth, a):
    return snr(rlog(est, a), rlog(truth, a))


def residual_ratio(r, dirty):
    return r.to(torch.float64).flatten(1).norm(dim=1) / dirty.to(torch.float64).flatten(1).norm(dim=1)


def metrics(x, r, data):
    """Mean SNR, logSNR (a = the sample's target dynamic range) and residual ratio."""
    return {
        "snr_db": float(snr(x, data.truth).mean()),
        "logsnr_db": float(log_snr(x, data.truth, data.dynamic_range).mean()),
        "residual_ratio": float(residual_ratio(r, data.dirty).mean()),
    }
