#!/usr/bin/env python3
"""Self-calibration with r2d2's model against the same loop with WSClean's, on one simulated
observation whose antennas carry known gain errors.

The model a calibration-to-image pipeline predicts into MODEL_DATA is what it calibrates
against, round after round: a model whose fluxes or structure are wrong puts its errors into
the gains. This runs, for each imager, rounds of

    image (CORRECTED_DATA, DATA at round 0) -> MODEL_DATA -> gain solve -> CORRECTED_DATA

on its own copy of the MS: r2d2 (`r2d2 image --model-column MODEL_DATA`, the default series and
its final CLEAN) and WSClean (multiscale, `-mgain 0.8 -auto-threshold 1 -auto-mask 3`, which
fills MODEL_DATA itself). The gain solve is StEFCal (Salvini & Wijnholds 2014): one complex
gain per antenna over the whole observation, both hands, natural weights; phases only in the
first `--phase-rounds` rounds (1), as self-calibration is run. Reported per round: the gains'
rms error against the truth (after removing the phase of a reference antenna, which no solve
can know), the same without the phase a shift of the whole sky puts on the gains (which no
self-calibration can know either), their common amplitude scale, the model's flux over the
true sky's and the model's SNR against the true sky, and the error without the sky's shift
and without that scale too (the gains relative to one another: self-calibration takes the
flux scale from the model it starts from and keeps it, so pipelines take it from the flux
calibrator and normalise the amplitude solutions). Then the floor: the same errors after one
solve against the true sky's own model visibilities (what the noise leaves, which no model
removes).

Skies: `compact` (30 point sources, 1e-3..1, and a small Gaussian) or `extended` (the
simulator's procedural radio sky). The corruption: phases uniform in +-`--phase-deg`,
amplitudes 1 +- `--amp` (uniform), seeded.

Usage: python3 benches/selfcal.py [--sky compact|extended] [--rounds 6] [--size 512]
       [--phase-rounds 1] [--r2d2 target/release/r2d2] [--r2d2-args '--auto-threshold 1'] [--out DIR] [--seed 1]
Needs python-casacore, astropy and WSClean (`apt-get install wsclean`).
"""

import argparse
import json
import os
import shutil
import subprocess
import sys

import numpy as np
from astropy.io import fits
from casacore.tables import table


def run(cmd, cwd):
    out = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return out


def compact_sky(n, path, seed):
    """30 point sources (fluxes 1e-3..1, at least n/25 pixels apart, away from the edges) and a
    small Gaussian, Jy/pixel without a WCS (the simulation's pixel), at `path`; the sources'
    x, y and flux in `sources.txt` beside it (tests/onnx.rs scores fluxes against them)."""
    rng = np.random.default_rng(seed)
    sky = np.zeros((n, n))
    pos = []
    margin = n * 5 // 64
    while len(pos) < 30:
        x, y = rng.integers(margin, n - margin, 2)
        if all((x - a) ** 2 + (y - b) ** 2 > (n // 25) ** 2 for a, b in pos):
            pos.append((x, y))
    flux = 10 ** rng.uniform(-3, 0, 30)
    flux[0] = 1.0
    for (x, y), f in zip(pos, flux):
        sky[y, x] += f
    yy, xx = np.mgrid[0:n, 0:n]
    g = np.exp(-((xx - n * 75 // 128) ** 2 + (yy - n * 75 // 256) ** 2) / 8.0)
    sky += 0.3 * g / g.sum()
    fits.writeto(path, sky.astype(np.float32), overwrite=True)
    np.savetxt(os.path.join(os.path.dirname(path), "sources.txt"), [(x, y, f) for (x, y), f in zip(pos, flux)])


def stefcal(ms, column, iterations=100, tolerance=1e-8, phase_only=False):
    """One complex gain per antenna: DATA ~ g_p MODEL conj(g_q), over every unflagged sample
    of both hands; with `phase_only`, gains of modulus 1 (each step's solution projected)."""
    t = table(ms, ack=False)
    a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
    data, model = t.getcol(column), t.getcol("MODEL_DATA")
    flag = t.getcol("FLAG") | t.getcol("FLAG_ROW")[:, None, None]
    weight = t.getcol("WEIGHT")[:, None, :] * np.ones(data.shape)
    t.close()
    hands = [0, data.shape[2] - 1]
    v = data[:, :, hands].reshape(len(a1), -1)
    m = model[:, :, hands].reshape(len(a1), -1)
    w = np.where(flag[:, :, hands].reshape(len(a1), -1), 0.0, weight[:, :, hands].reshape(len(a1), -1))
    cross = a1 != a2
    a1, a2, v, m, w = a1[cross], a2[cross], v[cross], m[cross], w[cross]
    n = int(max(a1.max(), a2.max())) + 1
    g = np.ones(n, complex)
    for it in range(iterations):
        num = np.zeros(n, complex)
        den = np.zeros(n)
        # As antenna 1: V_pq = g_p (M_pq conj(g_q)); as antenna 2: conj(V_qp) = g_p conj(M_qp) conj(g_q).
        z = m * np.conj(g[a2])[:, None]
        np.add.at(num, a1, (w * v * np.conj(z)).sum(1))
        np.add.at(den, a1, (w * np.abs(z) ** 2).sum(1))
        z = np.conj(m) * np.conj(g[a1])[:, None]
        np.add.at(num, a2, (w * np.conj(v) * np.conj(z)).sum(1))
        np.add.at(den, a2, (w * np.abs(z) ** 2).sum(1))
        new = np.where(den > 0, num / np.where(den > 0, den, 1), g)
        if it % 2 == 1:
            new = 0.5 * (new + g)
        if phase_only:
            new = np.exp(1j * np.angle(new))
        done = np.abs(new - g).max() < tolerance
        g = new
        if done:
            break
    return g


def apply(ms, gains):
    t = table(ms, ack=False, readonly=False)
    a1, a2, data = t.getcol("ANTENNA1"), t.getcol("ANTENNA2"), t.getcol("DATA")
    corrected = data / (gains[a1] * np.conj(gains[a2]))[:, None, None]
    if "CORRECTED_DATA" not in t.colnames():
        from casacore.tables import makearrcoldesc, maketabdesc
        desc = t.getcoldesc("DATA")
        desc["name"] = "CORRECTED_DATA"
        t.addcols(maketabdesc(makearrcoldesc("CORRECTED_DATA", 0j, valuetype="complex", ndim=desc.get("ndim", 2))))
    t.putcol("CORRECTED_DATA", corrected.astype(data.dtype))
    t.close()


def gain_error(estimate, truth, present):
    """rms |g_est - g_true| over the antennas in the data, each set rotated so that the first
    one's phase is zero (the phase no solve can know)."""
    reference = int(np.flatnonzero(present)[0])
    e = estimate * np.exp(-1j * np.angle(estimate[reference]))
    t = truth * np.exp(-1j * np.angle(truth[reference]))
    return float(np.sqrt(np.mean(np.abs(e[present] - t[present]) ** 2)))


def gain_error_unshifted(estimate, truth, present, positions):
    """gain_error after taking out of the estimate the phase linear in the antennas'
    positions that fits it best: the phase a shift of the whole sky puts on the gains.
    Self-calibration cannot tell where the sky is (its model came from the data it corrects;
    astrometry is the phase calibrator's), so a loop whose model drifted by a fraction of a
    beam has gains that look wrong and images that are right."""
    reference = int(np.flatnonzero(present)[0])
    ratio = (estimate / estimate[reference]) / (truth / truth[reference])
    x = positions[present] - positions[present].mean(0)
    design = np.column_stack([np.ones(len(x)), x])
    phase = np.angle(ratio[present])
    fit = np.zeros(design.shape[1])
    # Gauss-Newton on exp(i phase) ~ exp(i design @ fit): a phase wrapped past +-pi does not
    # pull the fit.
    for _ in range(20):
        misfit = np.angle(np.exp(1j * (phase - design @ fit)))
        step = np.linalg.lstsq(design, misfit, rcond=None)[0]
        fit += step
        if np.abs(step).max() < 1e-10:
            break
    corrected = estimate.copy()
    corrected[present] = corrected[present] * np.exp(-1j * (design @ fit))
    return gain_error(corrected, truth, present)


def gain_scale(estimate, truth, present):
    """The common amplitude scale of the estimate against the truth (the geometric mean of
    |g_est| / |g_true|): what a model's flux scale error puts into every gain alike."""
    return float(np.exp(np.mean(np.log(np.abs(estimate[present]) / np.abs(truth[present])))))


def snr(model, truth):
    return float(20 * np.log10(np.linalg.norm(truth) / np.linalg.norm(truth - model)))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sky", choices=["compact", "extended"], default="compact")
    p.add_argument("--rounds", type=int, default=6, help="rounds after the first image (6: both loops have settled on every sky measured)")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--phase-deg", type=float, default=30.0)
    p.add_argument("--amp", type=float, default=0.1)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--r2d2", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "target", "release", "r2d2"))
    p.add_argument("--wsclean", default="wsclean")
    p.add_argument("--phase-rounds", type=int, default=1,
                   help="solve for phases only in the first this many rounds, as self-calibration is run: an amplitude solve "
                        "against the first model, made from data whose phase errors decorrelate the sources, keeps its low flux scale (0: amplitudes from the first round)")
    p.add_argument("--r2d2-args", default="", help="further options for `r2d2 image` (e.g. '--auto-threshold 1', the final CLEAN as deep as WSClean's here)")
    p.add_argument("--out", default="selfcal-bench")
    p.add_argument("--json", help="write the figures here too")
    a = p.parse_args()
    r2d2 = os.path.abspath(a.r2d2)
    os.makedirs(a.out, exist_ok=True)
    d = a.out
    n = a.size
    if a.sky == "compact":
        compact_sky(n, os.path.join(d, "sky.fits"), a.seed)
        run([r2d2, "simulate", "--sky", "sky.fits", "--seed", str(a.seed), "--out", "obs.parquet"], d)
    else:
        run([r2d2, "simulate", "--sky", f"procedural:{a.seed}", "--size", str(n), "--seed", str(a.seed), "--out", "obs.parquet"], d)
        shutil.copy(os.path.join(d, "obs.sky.fits"), os.path.join(d, "sky.fits"))
    truth = fits.getdata(os.path.join(d, "sky.fits")).squeeze().astype(float)
    for name in ["clean.ms", "r2d2.ms", "wsclean.ms"]:
        shutil.rmtree(os.path.join(d, name), ignore_errors=True)
    run([r2d2, "convert", "obs.parquet", "clean.ms"], d)
    # The corruption: DATA = g_p V conj(g_q).
    t = table(os.path.join(d, "clean.ms"), ack=False, readonly=False)
    a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
    nant = int(max(a1.max(), a2.max())) + 1
    present = np.zeros(nant, bool)
    present[a1] = True
    present[a2] = True
    with table(os.path.join(d, "clean.ms", "ANTENNA"), ack=False) as antennas:
        positions = antennas.getcol("POSITION")
    rng = np.random.default_rng(a.seed + 1000)
    g_true = (1 + rng.uniform(-a.amp, a.amp, nant)) * np.exp(1j * np.radians(rng.uniform(-a.phase_deg, a.phase_deg, nant)))
    data = t.getcol("DATA")
    t.putcol("DATA", (data * (g_true[a1] * np.conj(g_true[a2]))[:, None, None]).astype(data.dtype))
    t.close()
    pixel = None
    results = {}
    for imager in ["r2d2", "wsclean"]:
        ms = f"{imager}.ms"
        shutil.copytree(os.path.join(d, "clean.ms"), os.path.join(d, ms))
        rows = []
        g = np.ones(nant, complex)
        for k in range(a.rounds + 1):
            column = "DATA" if k == 0 else "CORRECTED_DATA"
            name = f"{imager}-r{k}"
            if imager == "r2d2":
                out = subprocess.run([r2d2, "image", ms, "--size", str(n), "--data-column", column, "--model-column", "MODEL_DATA", "--name", name] + a.r2d2_args.split(), cwd=d, capture_output=True, text=True)
                if out.returncode not in (0, 3):
                    sys.exit(f"r2d2 image failed:\n{out.stderr[-3000:]}")
                pixel = abs(fits.getheader(os.path.join(d, f"{name}-model.fits"))["CDELT1"]) * 3600
            else:
                run([a.wsclean, "-quiet", "-size", str(n), str(n), "-scale", f"{pixel}asec", "-weight", "briggs", "0", "-multiscale", "-mgain", "0.8",
                     "-niter", "1000000", "-auto-threshold", "1", "-auto-mask", "3", "-use-wgridder", "-data-column", column, "-name", name, ms], d)
            model = fits.getdata(os.path.join(d, f"{name}-model.fits")).squeeze().astype(float)
            g_error = gain_error(g, g_true, present)
            scale = gain_scale(g, g_true, present)
            unshifted = gain_error_unshifted(g, g_true, present, positions)
            rows.append({"round": k, "gain_error": g_error, "gain_error_unshifted": unshifted, "gain_scale": scale,
                         "gain_error_relative": gain_error_unshifted(g / scale, g_true, present, positions),
                         "model_snr_db": snr(model, truth), "model_flux_ratio": float(model.sum() / truth.sum())})
            print(f"{imager:8s} round {k}: gain rms error {g_error:.4f} ({unshifted:.4f} without a shift of the sky; common amplitude scale {scale:.4f}), "
                  f"model SNR {rows[-1]['model_snr_db']:.2f} dB, model flux / true {rows[-1]['model_flux_ratio']:.4f}", flush=True)
            if k < a.rounds:
                g = stefcal(os.path.join(d, ms), column="DATA", phase_only=k < a.phase_rounds)
                apply(os.path.join(d, ms), g)
        results[imager] = rows
    # The floor: one solve against the true sky's model visibilities (WSClean's prediction of
    # the true sky on the images' grid). What is left is the noise's, which no model removes.
    shutil.rmtree(os.path.join(d, "truth.ms"), ignore_errors=True)
    shutil.copytree(os.path.join(d, "clean.ms"), os.path.join(d, "truth.ms"))
    header = fits.getheader(os.path.join(d, "r2d2-r0-model.fits"))
    shape = fits.getdata(os.path.join(d, "r2d2-r0-model.fits")).shape
    fits.writeto(os.path.join(d, "truth-model.fits"), truth.reshape(shape).astype(np.float32), header, overwrite=True)
    run([a.wsclean, "-quiet", "-predict", "-size", str(n), str(n), "-scale", f"{pixel}asec", "-use-wgridder", "-name", "truth", "truth.ms"], d)
    g = stefcal(os.path.join(d, "truth.ms"), column="DATA")
    floor = {"gain_error": gain_error(g, g_true, present), "gain_error_unshifted": gain_error_unshifted(g, g_true, present, positions),
             "gain_scale": gain_scale(g, g_true, present)}
    floor["gain_error_relative"] = gain_error_unshifted(g / floor["gain_scale"], g_true, present, positions)
    print("\nround | gain rms error r2d2 | WSClean | without a sky shift: r2d2 | WSClean | and without the flux scale: r2d2 | WSClean | amplitude scale r2d2 | WSClean | model SNR r2d2 (dB) | WSClean")
    for k in range(a.rounds + 1):
        r, w = results["r2d2"][k], results["wsclean"][k]
        print(f"{k} | {r['gain_error']:.4f} | {w['gain_error']:.4f} | {r['gain_error_unshifted']:.4f} | {w['gain_error_unshifted']:.4f} | "
              f"{r['gain_error_relative']:.4f} | {w['gain_error_relative']:.4f} | {r['gain_scale']:.4f} | {w['gain_scale']:.4f} | {r['model_snr_db']:.2f} | {w['model_snr_db']:.2f}")
    print(f"(uncorrected gains: rms error {gain_error(np.ones(nant, complex), g_true, present):.4f}; solved against the true sky: "
          f"{floor['gain_error']:.4f}, {floor['gain_error_unshifted']:.4f} without a sky shift, {floor['gain_error_relative']:.4f} without the flux scale too, "
          f"amplitude scale {floor['gain_scale']:.4f})")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"sky": a.sky, "size": n, "results": results, "true_sky": floor}, f, indent=1)


if __name__ == "__main__":
    main()
