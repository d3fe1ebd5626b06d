//! Where a network series' model may hold emission, found from the data as the series runs:
//! the analogue for a series of WSClean's `-auto-mask` for CLEAN.
//!
//! A series trained on a field of one size, run on a larger one, meets far sidelobes and large
//! empty areas it never saw, and its networks make emission there that the data do not hold.
//! The mask keeps the model to the pixels where the residual, smoothed to the beam or wider
//! (faint extended emission stands out only on its own scale), has stood above `sigmas` times
//! its own robust noise at that scale at some step, and their surroundings. The noise is
//! measured on the smoothed residual itself, so sidelobes of emission not yet modelled count
//! as noise: early on only the bright emission is in, and fainter emission joins as the model
//! takes the sidelobes away, as a CLEAN's auto-mask grows with its cycles.

use crate::metrics::robust_sigma;

/// The level a series' mask grows at where none is given, noise sigmas (a usual WSClean
/// `-auto-mask`).
pub const DEFAULT_AUTO_MASK: f64 = 5.0;

/// A mask that only grows, on an N x N grid (row-major, true inside).
pub struct EmissionMask {
    n: usize,
    inside: Vec<bool>,
    /// Half-widths of the boxes the residual is smoothed with, pixels: the beam and wider, so
    /// that faint extended emission, below the level pixel by pixel, is found on its own scale.
    scales: Vec<usize>,
    /// How far around a pixel found at a scale the mask reaches (a beam beyond the box).
    dilation: Vec<usize>,
    sigmas: f64,
}

/// The smoothing scales past the beam's grow by this factor, up to a sixteenth of the image.
const SCALE_FACTOR: f64 = 4.0;

impl EmissionMask {
    /// An empty mask for an N x N image whose PSF main lobe is `beam_fwhm_px` wide, growing
    /// where the residual smoothed to the beam, or to 4 or 16 beams, exceeds `sigmas` robust
    /// standard deviations of itself.
    pub fn new(n: usize, beam_fwhm_px: f64, sigmas: f64) -> EmissionMask {
        let beam = if beam_fwhm_px.is_finite() { beam_fwhm_px.max(1.0) } else { 1.0 };
        let mut scales = vec![(beam / 2.0).round().max(1.0) as usize];
        for k in 1..3 {
            let radius = (beam / 2.0 * SCALE_FACTOR.powi(k)).round() as usize;
            if radius <= n / 16 {
                scales.push(radius);
            }
        }
        let dilation = scales.iter().map(|&r| r + beam.round() as usize).collect();
        EmissionMask { n, inside: vec![false; n * n], scales, dilation, sigmas }
    }

    pub fn inside(&self) -> &[bool] {
        &self.inside
    }

    /// The fraction of the image inside.
    pub fn fraction(&self) -> f64 {
        self.inside.iter().filter(|&&p| p).count() as f64 / self.inside.len().max(1) as f64
    }

    /// Adds the pixels where `residual` (N x N), smoothed at any of the mask's scales, stands
    /// above `sigmas` times its robust noise at that scale, and their surroundings. Returns how
    /// many pixels joined.
    pub fn grow(&mut self, residual: &[f64]) -> usize {
        let n = self.n;
        let mut joined = 0;
        for (&radius, &reach) in self.scales.iter().zip(&self.dilation) {
            let smoothed = box_mean(residual, n, radius);
            let sigma = robust_sigma(&smoothed);
            if !(sigma > 0.0) {
                continue;
            }
            let level = self.sigmas * sigma;
            let above: Vec<f64> = smoothed.iter().map(|&v| if v > level { 1.0 } else { 0.0 }).collect();
            let near = box_mean(&above, n, reach);
            for (inside, &v) in self.inside.iter_mut().zip(&near) {
                if !*inside && v > 0.0 {
                    *inside = true;
                    joined += 1;
                }
            }
        }
        joined
    }
}

/// The width of a PSF's main lobe (N x N, peak 1 at (N/2, N/2)), pixels: where it falls
/// to half its peak along the centre row and column (linearly interpolated), the geometric
/// mean of the two widths; an estimate good enough to size smoothing and dilation.
pub fn main_lobe_fwhm_px(psf: &[f64], n: usize) -> f64 {
    let c = n / 2;
    // The distance from the centre at which `at(k)` (the value k pixels out) first falls below
    // half; the edge of the image if it never does.
    let half = |at: &dyn Fn(usize) -> f64| {
        let mut previous = at(0);
        for k in 1..c {
            let v = at(k);
            if v < 0.5 {
                return (k - 1) as f64 + (previous - 0.5) / (previous - v);
            }
            previous = v;
        }
        c as f64
    };
    let across = half(&|k| psf[c * n + c + k]) + half(&|k| psf[c * n + c - k]);
    let along = half(&|k| psf[(c + k) * n + c]) + half(&|k| psf[(c - k) * n + c]);
    (across * along).sqrt()
}

/// The mean over a (2r+1) x (2r+1) box around each pixel of an N x N image, the box cut at
/// the edges (no wrapping: the far side of the field is not a neighbour).
fn box_mean(image: &[f64], n: usize, r: usize) -> Vec<f64> {
    let pass = |inp: &[f64], stride_along: usize, stride_across: usize| {
        let mut out = vec![0.0; n * n];
        let mut prefix = vec![0.0; n + 1];
        for line in 0..n {
            for k in 0..n {
                prefix[k + 1] = prefix[k] + inp[line * stride_across + k * stride_along];
            }
            for k in 0..n {
                let (lo, hi) = (k.saturating_sub(r), (k + r + 1).min(n));
                out[line * stride_across + k * stride_along] = (prefix[hi] - prefix[lo]) / (hi - lo) as f64;
            }
        }
        out
    };
    let rows = pass(image, 1, n);
    pass(&rows, n, 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A faint extended source beside noise and a far sidelobe pattern: the first growth takes
    /// the bright source only; once its sidelobes are gone from the residual, the faint one
    /// joins; noise alone never does.
    #[test]
    fn the_mask_takes_bright_emission_first_and_faint_emission_once_the_sidelobes_are_gone() {
        let n = 128;
        let mut rng = 12345u64;
        let mut gauss = || {
            // Box-Muller from a 64-bit LCG: the test's noise, reproducible.
            let mut u = || {
                rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((rng >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (a, b) = (u(), u());
            (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
        };
        let blob = |cx: f64, cy: f64, w: f64, a: f64, x: usize, y: usize| a * (-((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)) / (2.0 * w * w)).exp();
        let noise: Vec<f64> = (0..n * n).map(|_| gauss()).collect();
        // Sidelobes: a ripple of amplitude 20 noise sigmas over the whole field, on the scale of
        // the faint source (so smoothing does not take it away).
        let ripple = |x: usize, y: usize| 20.0 * ((x as f64 * std::f64::consts::TAU / 40.0).sin() * (y as f64 * std::f64::consts::TAU / 50.0).cos());
        let bright = |x, y| blob(30.0, 30.0, 3.0, 500.0, x, y);
        let faint = |x, y| blob(90.0, 90.0, 6.0, 4.0, x, y);
        let first: Vec<f64> = (0..n * n).map(|i| noise[i] + ripple(i % n, i / n) + bright(i % n, i / n) + faint(i % n, i / n)).collect();
        let mut mask = EmissionMask::new(n, 3.0, 5.0);
        assert!(mask.grow(&first) > 0);
        let at = |x: usize, y: usize| mask.inside()[y * n + x];
        assert!(at(30, 30), "the bright source is in");
        assert!(!at(90, 90), "the faint source is under the sidelobes at first");
        let far = (0..n * n).filter(|&i| mask.inside()[i] && blob(30.0, 30.0, 3.0, 1.0, i % n, i / n) < 1e-12).count();
        assert_eq!(far, 0, "sidelobes stay out");
        // The bright source modelled: its sidelobes gone, the faint source stands out.
        let later: Vec<f64> = (0..n * n).map(|i| noise[i] + faint(i % n, i / n)).collect();
        mask.grow(&later);
        let at = |x: usize, y: usize| mask.inside()[y * n + x];
        assert!(at(30, 30), "the mask only grows");
        assert!(at(90, 90), "the faint source joins");
        let from = |cx: f64, cy: f64, i: usize| ((i % n) as f64 - cx).hypot((i / n) as f64 - cy);
        let in_noise = (0..n * n).filter(|&i| mask.inside()[i] && from(30.0, 30.0, i) > 40.0 && from(90.0, 90.0, i) > 40.0).count();
        assert!(in_noise < 20, "noise alone hardly joins: {in_noise} pixels");
    }

    #[test]
    fn the_main_lobe_width_of_a_gaussian_psf_is_its_fwhm() {
        let n = 64;
        for fwhm in [2.0, 4.0, 7.0] {
            let s = fwhm / (8.0 * 2f64.ln()).sqrt();
            let psf: Vec<f64> = (0..n * n).map(|i| {
                let (x, y) = ((i % n) as f64 - 32.0, (i / n) as f64 - 32.0);
                (-(x * x + y * y) / (2.0 * s * s)).exp()
            }).collect();
            let w = main_lobe_fwhm_px(&psf, n);
            assert!((w - fwhm).abs() <= 0.1 * fwhm, "fwhm {fwhm}: {w}");
        }
    }

    #[test]
    fn box_mean_is_the_mean_over_the_box_cut_at_the_edges() {
        let n = 5;
        let image: Vec<f64> = (0..n * n).map(|i| i as f64).collect();
        let m = box_mean(&image, n, 1);
        // Corner (0,0): pixels 0,1,5,6.
        assert!((m[0] - 3.0).abs() < 1e-12);
        // Centre (2,2): the mean of a 3 x 3 box of a linear ramp is the centre value.
        assert!((m[12] - 12.0).abs() < 1e-12);
    }
}
