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


class Dataset:
    """Stacked arrays of one `r2d2 trainset` directory (float32 images, float64 PSF spectra)."""

    def __init__(self, path, limit=None):
        self.path = path
        sl = slice(None, limit)
        load = lambda name: np.load(os.path.join(path, name), mmap_mode="r")[sl]
        self.truth = torch.from_numpy(np.array(load("truth.npy"), dtype=np.float32))
        self.dirty = torch.from_numpy(np.array(load("dirty.npy"), dtype=np.float32))
        self.noise_dirty = torch.from_numpy(np.array(load("noise_dirty.npy"), dtype=np.float32))
        psf = torch.from_numpy(np.array(load("psf2n.npy"), dtype=np.float64))
        self.psf_hat = torch.fft.rfft2(psf)  # [S, 2N, N+1] complex128
        with open(os.path.join(path, "samples.json")) as f:
            self.samples = json.load(f)[sl]
        with open(os.path.join(path, "trainset.json")) as f:
            self.meta = json.load(f)
        self.dynamic_range = torch.tensor([s["dynamic_range"] for s in self.samples], dtype=torch.float64)

    def __len__(self):
        return self.truth.shape[0]

    @property
    def size(self):
        return self.truth.shape[-1]


def apply_d(x, psf_hat):
    """D x for a batch x [S, N, N] with the rFFT of the 2N PSFs [S, 2N, N+1]; float64."""
    n = x.shape[-1]
    xp = torch.zeros(x.shape[0], 2 * n, 2 * n, dtype=torch.float64)
    xp[:, :n, :n] = x.to(torch.float64)
    y = torch.fft.irfft2(torch.fft.rfft2(xp) * psf_hat, s=(2 * n, 2 * n))
    return y[:, n:, n:]


def residual(dirty, x, psf_hat, batch=64):
    """r = dirty - D x, float32, in batches (memory)."""
    out = torch.empty_like(dirty)
    for s in range(0, dirty.shape[0], batch):
        e = s + batch
        out[s:e] = (dirty[s:e].to(torch.float64) - apply_d(x[s:e], psf_hat[s:e])).to(torch.float32)
    return out


def network_input(iteration, dirty, x, r):
    """Normalised 2-channel input [B, 2, N, N] and alpha [B, 1, 1, 1] (reference order)."""
    if iteration == 1:
        alpha = dirty.mean(dim=(-2, -1), keepdim=True)
        inp = torch.stack([dirty / alpha, torch.zeros_like(dirty)], dim=1)
        prev = torch.zeros_like(dirty)
    else:
        alpha = x.mean(dim=(-2, -1), keepdim=True)
        inp = torch.stack([x / alpha, r / alpha], dim=1)
        prev = x / alpha
    return inp, alpha, prev


def update(iteration, run_network, dirty, x, r, batch=32):
    """x_i for every sample: max(0, x_{i-1}/alpha + N_i(input)) * alpha (float32)."""
    out = torch.empty_like(dirty)
    for s in range(0, dirty.shape[0], batch):
        e = s + batch
        inp, alpha, prev = network_input(iteration, dirty[s:e], x[s:e], r[s:e])
        inc = run_network(inp)[:, 0]
        out[s:e] = torch.clamp(prev + inc, min=0.0) * alpha
    return out


# Metrics (conventions file, "Metrics"), per sample, float64.
def snr(est, truth):
    est, truth = est.to(torch.float64), truth.to(torch.float64)
    return 20 * torch.log10(truth.flatten(1).norm(dim=1) / (truth - est).flatten(1).norm(dim=1))


def rlog(x, a):
    x = x.to(torch.float64).clamp(min=0)
    peak = x.flatten(1).max(dim=1).values.clamp(min=1e-300).view(-1, 1, 1)
    a = a.view(-1, 1, 1)
    return peak * torch.log1p(a * x / peak) / torch.log(a)


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
