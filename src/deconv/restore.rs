//! Restoration: a model convolved with the restoring beam (by FFT).

use super::beam::{quadratic, quadratic_from_beam, Beam, FWHM_PER_SIGMA};
use crate::fft2::Fft2;
use num_complex::Complex64;
use rayon::prelude::*;
use rustfft::FftDirection;

/// Smallest `2^a 3^b 5^c >= n`: lengths rustfft transforms fastest.
pub(super) fn fast_len(n: usize) -> usize {
    (n.max(1)..)
        .find(|&k| {
            let mut k = k;
            for p in [2, 3, 5] {
                while k % p == 0 {
                    k /= p;
                }
            }
            k == 1
        })
        .expect("a 5-smooth number exists above any n")
}

/// The model (Jy/pixel) convolved with the restoring beam, a Gaussian of peak 1, so that the
/// result is in Jy/beam and a point source of S Jy peaks at S, as in WSClean's restored image
/// (which adds the residual to this). By FFT on a grid padded by the beam's extent (7.4 sigma,
/// where the Gaussian is below 1e-12), so nothing wraps around the image edges.
///
/// Panics unless the beam has positive, finite widths and `model` has `size * size` pixels.
pub fn restore(model: &[f64], size: usize, beam: &Beam, pixel_rad: f64) -> Vec<f64> {
    let n = size;
    assert_eq!(model.len(), n * n, "model: expected {n} x {n} pixels");
    assert!(
        beam.major_deg > 0.0 && beam.minor_deg > 0.0 && beam.major_deg.is_finite() && beam.minor_deg.is_finite(),
        "restoring beam must have positive finite widths, got {beam:?}"
    );
    assert!(pixel_rad > 0.0 && pixel_rad.is_finite(), "pixel size must be positive, got {pixel_rad}");
    let q = quadratic_from_beam(beam, pixel_rad);
    let major_pix = beam.major_deg.max(beam.minor_deg).to_radians() / pixel_rad / FWHM_PER_SIGMA;
    let reach = ((major_pix * (2.0 * 1e12f64.ln()).sqrt()).ceil() as usize).min(n);
    // Circular convolution of length M equals the linear one on the N x N output when
    // M >= N + reach.
    let len = fast_len(n + reach);
    let mut kernel = vec![Complex64::default(); len * len];
    for dy in -(reach as isize)..=reach as isize {
        for dx in -(reach as isize)..=reach as isize {
            let g = (-0.5 * quadratic(q, dx as f64, dy as f64)).exp();
            let (kx, ky) = (dx.rem_euclid(len as isize) as usize, dy.rem_euclid(len as isize) as usize);
            kernel[ky * len + kx] = Complex64::new(g, 0.0);
        }
    }
    let mut padded = vec![Complex64::default(); len * len];
    for (dst, src) in padded.chunks_mut(len).zip(model.chunks(n)) {
        dst[..n].iter_mut().zip(src).for_each(|(d, &s)| *d = Complex64::new(s, 0.0));
    }
    let forward = Fft2::new(len, len, FftDirection::Forward);
    forward.process(&mut kernel);
    forward.process(&mut padded);
    let scale = 1.0 / (len * len) as f64;
    padded.par_iter_mut().zip(kernel.par_iter()).for_each(|(a, k)| *a *= k * scale);
    Fft2::new(len, len, FftDirection::Inverse).process(&mut padded);
    padded.chunks(len).take(n).flat_map(|row| row[..n].iter().map(|c| c.re)).collect()
}
