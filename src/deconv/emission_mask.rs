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
    /// Per scale, the pixels found at it so far: only new ones need their surroundings added.
    found: Vec<Vec<bool>>,
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
        let found = vec![vec![false; n * n]; scales.len()];
        EmissionMask { n, inside: vec![false; n * n], scales, dilation, found, sigmas }
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
        let before = self.inside.iter().filter(|&&p| p).count();
        for scale in 0..self.scales.len() {
            let smoothed = box_mean(residual, n, self.scales[scale]);
            let sigma = sampled_robust_sigma(&smoothed);
            if !(sigma > 0.0) {
                continue;
            }
            let level = self.sigmas * sigma;
            let found = &mut self.found[scale];
            let new: Vec<usize> = (0..n * n).filter(|&i| smoothed[i] > level && !found[i]).collect();
            new.iter().for_each(|&i| found[i] = true);
            let reach = self.dilation[scale];
            let side = (2 * reach + 1).min(n);
            if new.len().saturating_mul(side * side) <= n * n {
                // Few new pixels (the usual case once the bright emission is in): their boxes
                // directly.
                for &i in &new {
                    let (x, y) = (i % n, i / n);
                    for yy in y.saturating_sub(reach)..(y + reach + 1).min(n) {
                        self.inside[yy * n + x.saturating_sub(reach)..yy * n + (x + reach + 1).min(n)].fill(true);
                    }
                }
            } else {
                let mut seeds = vec![0.0; n * n];
                new.iter().for_each(|&i| seeds[i] = 1.0);
                // A pixel near a seed has a mean of at least one over the box's area; the
                // sliding sums leave rounding dust, not that, where there is none.
                let least = 0.5 / (side * side) as f64;
                let near = box_mean(&seeds, n, reach);
                self.inside.iter_mut().zip(&near).filter(|(_, &v)| v > least).for_each(|(inside, _)| *inside = true);
            }
        }
        self.inside.iter().filter(|&&p| p).count() - before
    }
}

/// The values a noise level is measured on, at most: the smoothed image is correlated over its
/// box, so a spread sample measures its noise as well as every pixel and costs a fraction.
const NOISE_SAMPLE: usize = 1 << 16;

/// The robust standard deviation of an image from at most [`NOISE_SAMPLE`] of its values,
/// taken at an odd stride (so that the samples wander across the columns).
fn sampled_robust_sigma(image: &[f64]) -> f64 {
    let stride = image.len().div_ceil(NOISE_SAMPLE) | 1;
    if stride == 1 {
        return robust_sigma(image);
    }
    robust_sigma(&image.iter().step_by(stride).copied().collect::<Vec<_>>())
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
/// the edges (no wrapping: the far side of the field is not a neighbour). Along rows by prefix
/// sums, then down columns by a window of whole rows (contiguous memory both ways).
fn box_mean(image: &[f64], n: usize, r: usize) -> Vec<f64> {
    let mut rows = vec![0.0; n * n];
    let mut prefix = vec![0.0; n + 1];
    for (line, out) in image.chunks_exact(n).zip(rows.chunks_exact_mut(n)) {
        for k in 0..n {
            prefix[k + 1] = prefix[k] + line[k];
        }
        for (k, o) in out.iter_mut().enumerate() {
            let (lo, hi) = (k.saturating_sub(r), (k + r + 1).min(n));
            *o = (prefix[hi] - prefix[lo]) / (hi - lo) as f64;
        }
    }
    let mut out = vec![0.0; n * n];
    // The sum of rows lo..hi, kept as the window slides down; summed afresh every so many rows
    // so that rounding does not build up.
    let mut window = vec![0.0; n];
    let (mut lo, mut hi) = (0, 0);
    for y in 0..n {
        let (want_lo, want_hi) = (y.saturating_sub(r), (y + r + 1).min(n));
        if y % 64 == 0 {
            window.fill(0.0);
            rows[want_lo * n..want_hi * n].chunks_exact(n).for_each(|row| window.iter_mut().zip(row).for_each(|(w, v)| *w += v));
        } else {
            for row in hi..want_hi {
                window.iter_mut().zip(&rows[row * n..(row + 1) * n]).for_each(|(w, v)| *w += v);
            }
            for row in lo..want_lo {
                window.iter_mut().zip(&rows[row * n..(row + 1) * n]).for_each(|(w, v)| *w -= v);
            }
        }
        (lo, hi) = (want_lo, want_hi);
        let count = (hi - lo) as f64;
        out[y * n..(y + 1) * n].iter_mut().zip(&window).for_each(|(o, w)| *o = w / count);
    }
    out
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

    /// The mask after a few growths is, pixel for pixel, every pixel within a scale's reach
    /// (a square) of a pixel that stood above the level at that scale at some growth: new
    /// pixels painted one by one or, when many, by a box sum, the same set.
    #[test]
    fn the_mask_is_the_union_of_the_reach_around_every_pixel_found() {
        let n = 96;
        let images: Vec<Vec<f64>> = (0..3u64)
            .map(|k| {
                (0..n * n)
                    .map(|i| {
                        let (x, y) = ((i % n) as f64, (i / n) as f64);
                        let h = ((i as u64 + 17 * k).wrapping_mul(2654435761) % 1000) as f64 / 500.0 - 1.0;
                        h + 40.0 / (k as f64 + 1.0) * (-((x - 20.0 - 25.0 * k as f64).powi(2) + (y - 60.0).powi(2)) / 18.0).exp()
                    })
                    .collect()
            })
            .collect();
        let mut mask = EmissionMask::new(n, 3.0, 5.0);
        let mut expected = vec![false; n * n];
        for image in &images {
            mask.grow(image);
            for (&radius, &reach) in mask.scales.iter().zip(&mask.dilation) {
                let smoothed = box_mean(image, n, radius);
                let level = 5.0 * sampled_robust_sigma(&smoothed);
                for i in (0..n * n).filter(|&i| smoothed[i] > level) {
                    let (x, y) = (i % n, i / n);
                    for yy in y.saturating_sub(reach)..(y + reach + 1).min(n) {
                        for xx in x.saturating_sub(reach)..(x + reach + 1).min(n) {
                            expected[yy * n + xx] = true;
                        }
                    }
                }
            }
            assert_eq!(mask.inside(), &expected[..]);
        }
        assert!(mask.fraction() > 0.01 && mask.fraction() < 0.9, "{}", mask.fraction());
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
        // Against the direct sum over each box, past the window's fresh restarts.
        let n = 150;
        let image: Vec<f64> = (0..n * n).map(|i| ((i * 7919) % 1009) as f64 - 500.0).collect();
        for r in [0, 3, 40] {
            let m = box_mean(&image, n, r);
            for (x, y) in [(0usize, 0usize), (149, 0), (75, 63), (75, 64), (75, 65), (10, 130), (149, 149)] {
                let (ys, xs) = (y.saturating_sub(r)..(y + r + 1).min(n), x.saturating_sub(r)..(x + r + 1).min(n));
                let image = &image;
                let direct = ys.clone().flat_map(|yy| xs.clone().map(move |xx| image[yy * n + xx])).sum::<f64>() / (ys.len() * xs.len()) as f64;
                assert!((m[y * n + x] - direct).abs() < 1e-9, "r {r} at ({x}, {y}): {} against {direct}", m[y * n + x]);
            }
        }
    }
}
