//! Procedural radio skies for training and testing, and the ground-truth exponentiation that
//! raises an image's dynamic range.
//!
//! The paper trains on optical/radio images reworked into radio-like ground truths; a
//! procedural generator gives an unlimited, license-free supply with a controlled dynamic
//! range and, crucially for a radio image, no emission at the border (the PSF sidelobes of a
//! source cut by the edge would alias in from the other side). A sky is a sum of three
//! populations, each chosen to exercise a different regime of the deconvolution:
//!
//! * compact sources (points and marginally resolved Gaussians) with a Euclidean
//!   `N(>S) ∝ S^-1.5` brightness distribution, so most are faint and a few are bright;
//! * one to three extended sources: elliptical Gaussian complexes or double-lobed radio
//!   galaxies (core, jets, lobes, optional hotspots);
//! * low-brightness diffuse emission with compact support (a thresholded smooth random field).
//!
//! The brightest extended source has amplitude 1, so the final normalisation to peak 1 keeps
//! the faint end near `1/DR`; every pixel below `1/DR` is then set exactly to 0.

use crate::error::{Error, Result};
use rand::Rng;
use rand_chacha::rand_core::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Poisson, StandardNormal};

/// Parameters of a procedural sky.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SkyParams {
    /// Image side in pixels (the image is `size x size`). At least 32.
    pub size: usize,
    /// Target dynamic range: peak / faintest nonzero emission. Must exceed 1.
    pub dynamic_range: f64,
    /// Seed of the random generator; the sky is a pure function of the parameters.
    pub seed: u64,
    /// Fraction of the image side, centred, that may hold emission (default 0.85). Emission
    /// tapers smoothly to exactly 0 at the edge of this central box, so the outer
    /// `(1 - support_fraction) / 2` of the image on each side is empty.
    pub support_fraction: f64,
}

impl SkyParams {
    /// Parameters with the default support fraction (0.85).
    pub fn new(size: usize, dynamic_range: f64, seed: u64) -> Self {
        SkyParams {
            size,
            dynamic_range,
            seed,
            support_fraction: 0.85,
        }
    }

    /// Check the parameters are usable.
    pub fn validate(&self) -> Result<()> {
        if self.size < 32 {
            return Err(Error::parameter(
                "size",
                format!(
                    "a procedural sky needs at least 32 pixels per side, got {}",
                    self.size
                ),
            ));
        }
        if !(self.dynamic_range.is_finite() && self.dynamic_range > 1.0) {
            return Err(Error::parameter(
                "dynamic_range",
                format!(
                    "must be a finite number greater than 1, got {}",
                    self.dynamic_range
                ),
            ));
        }
        if !(self.support_fraction > 0.3 && self.support_fraction <= 1.0) {
            return Err(Error::parameter(
                "support_fraction",
                format!("must be in (0.3, 1], got {}", self.support_fraction),
            ));
        }
        Ok(())
    }
}

/// A procedural radio sky, row-major (`[iy * size + ix]`), with peak exactly 1, background
/// exactly 0, no negative pixels, and the faintest nonzero pixel at or just above
/// `1 / dynamic_range`. All emission lies inside the central `support_fraction` of the image.
///
/// Brightnesses are peak (per-pixel) values, not integrated fluxes: the dynamic range of an
/// image is a ratio of pixel values, which is what the power law and the threshold control.
///
/// Cost is about `O(size^2)` plus the area of the components' windows: every Gaussian is
/// evaluated only where it exceeds 1% of the threshold (at least ±4 sigma), and the diffuse
/// field is smoothed with a cascade of running box sums whose cost does not depend on the
/// smoothing width.
pub fn procedural_sky(p: &SkyParams) -> Result<Vec<f64>> {
    p.validate()?;
    let n = p.size;
    let nf = n as f64;
    let dr = p.dynamic_range;
    let mut rng = ChaCha8Rng::seed_from_u64(p.seed);

    // Geometry: emission lives in [lo, hi) on each axis and is tapered to 0 over `taper`
    // pixels at its edge; component centres keep a further margin from the taper.
    let lo = 0.5 * (1.0 - p.support_fraction) * nf;
    let hi = nf - lo;
    let taper = (0.04 * nf).max(2.0);
    let inner_lo = lo + taper;
    let inner_hi = hi - taper;

    // Tails below 1% of the final threshold are dropped: the brightest component has
    // amplitude 1, so after normalisation the truncation is far below what is kept.
    let mut canvas = Canvas::new(n, 0.01 / dr);

    // (b) Extended sources first, so their random draws do not depend on the number of
    // compact sources (changing the compact population then leaves the galaxies in place).
    let n_ext = rng.gen_range(1..=3);
    for k in 0..n_ext {
        let amp = if k == 0 {
            1.0
        } else {
            dr.powf(-rng.gen_range(0.0..0.5))
        };
        let extent = rng.gen_range(0.05..0.25) * nf;
        // Keep the whole structure (extent/2 from its centre) inside the untapered box.
        let half = 0.5 * extent;
        let cx = uniform_in(&mut rng, inner_lo + half, inner_hi - half);
        let cy = uniform_in(&mut rng, inner_lo + half, inner_hi - half);
        if rng.gen_bool(0.65) {
            add_radio_galaxy(&mut canvas, &mut rng, cx, cy, extent, amp);
        } else {
            add_gaussian_complex(&mut canvas, &mut rng, cx, cy, extent, amp);
        }
    }

    // (a) Compact sources: a Poisson count clamped to [n/16, n/4], brightness from the
    // truncated Euclidean power law on [1/DR, 1].
    let (n_min, n_max) = ((n / 16).max(1), (n / 4).max(1));
    let mean = 0.5 * (n_min + n_max) as f64;
    let count = (Poisson::new(mean)
        .map(|d| d.sample(&mut rng))
        .unwrap_or(mean) as usize)
        .clamp(n_min, n_max);
    let s_min = 1.0 / dr;
    let trunc = 1.0 - s_min.powf(1.5); // 1 - (Smin/Smax)^1.5 with Smax = 1
    let margin = 3.0;
    for _ in 0..count {
        let u: f64 = rng.gen();
        let s = (s_min * (1.0 - u * trunc).powf(-1.0 / 1.5)).min(1.0);
        let x = uniform_in(&mut rng, inner_lo + margin, inner_hi - margin);
        let y = uniform_in(&mut rng, inner_lo + margin, inner_hi - margin);
        if rng.gen_bool(0.3) {
            canvas.add_point(x, y, s);
        } else {
            let sig = rng.gen_range(0.5..1.5);
            let ratio = rng.gen_range(0.6..1.0);
            let theta = rng.gen_range(0.0..std::f64::consts::PI);
            canvas.add_gaussian(x, y, s, sig, sig * ratio, theta);
        }
    }

    // (c) Diffuse emission.
    let diffuse = diffuse_emission(&mut rng, n, dr, inner_lo, inner_hi);
    let mut img = canvas.data;
    for (v, d) in img.iter_mut().zip(&diffuse) {
        *v += d;
    }

    // Taper to exactly 0 at the edge of the support box, normalise, threshold.
    let w = taper_window(n, lo, hi, taper);
    for iy in 0..n {
        for ix in 0..n {
            img[iy * n + ix] *= w[iy] * w[ix];
        }
    }
    debug_assert!(img.iter().any(|&v| v > 0.0));
    normalise_and_cut(&mut img, dr);
    Ok(img)
}

/// Raise the dynamic range of a ground truth by exponentiation (Terris et al. 2022, as in
/// the R2D2 reference): on the image normalised to peak 1, `x -> (a^x - 1) / a`, then
/// renormalised to peak 1 (i.e. divided by `(a - 1) / a`). `a` solves
/// `(1 + a sigma)^(1 / sigma0) = a` with `sigma0 = 1 / source_dr` and
/// `sigma = 1 / target_dr`, which makes the old faint level `sigma0` land on `sigma`:
/// `(a^sigma0 - 1) / a = sigma`.
///
/// The equation always has a trivial root near `a = 1 + sigma/sigma0` (where the map is
/// nearly linear and does nothing useful); the wanted root is the larger one. Writing
/// `g(L) = ln(1 + sigma e^L) / sigma0 - L` with `L = ln a`, `g` is convex with its minimum at
/// `a* = sigma0 / (sigma (1 - sigma0))`; the two roots straddle `a*`, and the nontrivial root
/// is found by bisection on `L` between `a*` and a point where `g > 0`. If `g(a*) >= 0` there
/// is no nontrivial root: that happens when the target is less than about `e` times the
/// source dynamic range, and is reported as an error.
///
/// The image is first divided by its maximum (so it need not be normalised on entry); it
/// must have a positive maximum. Negative pixels, if any, go through the same map (which is
/// defined and monotone for them). Returns `a`.
pub fn exponentiate(image: &mut [f64], source_dr: f64, target_dr: f64) -> Result<f64> {
    if !(source_dr.is_finite() && source_dr > 1.0) {
        return Err(Error::parameter(
            "source_dr",
            format!("must be a finite number greater than 1, got {source_dr}"),
        ));
    }
    if !target_dr.is_finite() || target_dr <= source_dr {
        return Err(Error::parameter(
            "dynamic_range",
            format!(
                "exponentiation raises the dynamic range, so the target must exceed the \
                 source's {source_dr}; got {target_dr} (an image already at or above the \
                 target needs no exponentiation)"
            ),
        ));
    }
    let peak = image.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !(peak.is_finite() && peak > 0.0) || image.iter().any(|v| !v.is_finite()) {
        return Err(Error::parameter(
            "image",
            format!(
                "exponentiation needs finite pixels and a positive maximum, got maximum {peak}"
            ),
        ));
    }
    let a = solve_exponent_base(source_dr, target_dr)?;
    let ln_a = a.ln();
    // (a^x - 1)/a / ((a - 1)/a) = expm1(x ln a) / expm1(ln a): accurate for small x.
    let norm = ln_a.exp_m1();
    for v in image.iter_mut() {
        *v = (*v / peak * ln_a).exp_m1() / norm;
    }
    Ok(a)
}

/// The nontrivial root `a` of `(1 + a sigma)^(1/sigma0) = a`; see [`exponentiate`].
pub fn solve_exponent_base(source_dr: f64, target_dr: f64) -> Result<f64> {
    let s0 = 1.0 / source_dr;
    let s = 1.0 / target_dr;
    let g = |l: f64| (s * l.exp()).ln_1p() / s0 - l;
    let l_star = (s0 / (s * (1.0 - s0))).ln();
    if g(l_star) >= 0.0 {
        return Err(Error::parameter(
            "dynamic_range",
            format!(
                "exponentiation from dynamic range {source_dr} to {target_dr} has no \
                 nontrivial solution (the ratio must be at least about e = 2.72); use a \
                 larger target"
            ),
        ));
    }
    // g grows like L (1/sigma0 - 1) for large L: step outwards until it is positive.
    let mut step = 1.0;
    let mut l_hi = l_star + step;
    while g(l_hi) <= 0.0 {
        step *= 2.0;
        l_hi = l_star + step;
        if !l_hi.is_finite() || step > 1e6 {
            return Err(Error::parameter(
                "dynamic_range",
                format!("could not bracket the exponentiation base for {source_dr} -> {target_dr}"),
            ));
        }
    }
    let mut l_lo = l_star;
    for _ in 0..200 {
        let mid = 0.5 * (l_lo + l_hi);
        if mid <= l_lo || mid >= l_hi {
            break;
        }
        if g(mid) > 0.0 {
            l_hi = mid;
        } else {
            l_lo = mid;
        }
    }
    Ok((0.5 * (l_lo + l_hi)).exp())
}

/// Accumulates Gaussian and point components into an image, evaluating each Gaussian only
/// over the window where it exceeds `cut` (at least ±4 sigma).
pub(super) struct Canvas {
    n: usize,
    pub(super) data: Vec<f64>,
    cut: f64,
}

impl Canvas {
    pub(super) fn new(n: usize, cut: f64) -> Self {
        Canvas {
            n,
            data: vec![0.0; n * n],
            cut,
        }
    }

    /// A single-pixel source at the pixel nearest (x, y); pixel centres are at integers.
    pub(super) fn add_point(&mut self, x: f64, y: f64, amp: f64) {
        let (ix, iy) = (x.round(), y.round());
        if ix >= 0.0 && iy >= 0.0 && (ix as usize) < self.n && (iy as usize) < self.n {
            self.data[iy as usize * self.n + ix as usize] += amp;
        }
    }

    /// An elliptical Gaussian of peak `amp` centred at (x, y) with standard deviations
    /// `sig_major` along the direction `theta` (radians from the x axis) and `sig_minor`
    /// across it.
    pub(super) fn add_gaussian(
        &mut self,
        x: f64,
        y: f64,
        amp: f64,
        sig_major: f64,
        sig_minor: f64,
        theta: f64,
    ) {
        if amp <= 0.0 {
            return;
        }
        let reach = (2.0 * (amp / self.cut).max(1.0).ln()).sqrt().max(4.0);
        let r = reach * sig_major.max(sig_minor);
        let n = self.n as f64;
        let x0 = (x - r).floor().max(0.0) as usize;
        let x1 = ((x + r).ceil().min(n - 1.0)).max(0.0) as usize;
        let y0 = (y - r).floor().max(0.0) as usize;
        let y1 = ((y + r).ceil().min(n - 1.0)).max(0.0) as usize;
        if x - r > n - 1.0 || y - r > n - 1.0 || x + r < 0.0 || y + r < 0.0 {
            return;
        }
        let (s, c) = theta.sin_cos();
        let (ia, ib) = (1.0 / sig_major, 1.0 / sig_minor);
        for iy in y0..=y1 {
            let dy = iy as f64 - y;
            let row = &mut self.data[iy * self.n..(iy + 1) * self.n];
            for (ix, px) in row.iter_mut().enumerate().take(x1 + 1).skip(x0) {
                let dx = ix as f64 - x;
                let a = (c * dx + s * dy) * ia;
                let b = (-s * dx + c * dy) * ib;
                let q = a * a + b * b;
                if q < 2.0 * reach * reach {
                    *px += amp * (-0.5 * q).exp();
                }
            }
        }
    }
}

/// Uniform draw in [a, b); if the interval is empty (tiny images, huge sources) the midpoint.
pub(super) fn uniform_in(rng: &mut ChaCha8Rng, a: f64, b: f64) -> f64 {
    if b > a {
        rng.gen_range(a..b)
    } else {
        0.5 * (a + b)
    }
}

/// A double-lobed radio galaxy of overall length `extent` centred at (cx, cy): a compact
/// core, two lobes (each a few overlapping elliptical Gaussians, at slightly different
/// distances and bent off the axis, as in real FR I/II sources), optional compact hotspots
/// at the lobes' outer ends, and a jet and fainter counter-jet of small Gaussians fading
/// away from the core.
fn add_radio_galaxy(
    canvas: &mut Canvas,
    rng: &mut ChaCha8Rng,
    cx: f64,
    cy: f64,
    extent: f64,
    amp: f64,
) {
    let axis = rng.gen_range(0.0..std::f64::consts::PI);
    let core_amp = amp * rng.gen_range(0.3..1.0);
    canvas.add_gaussian(
        cx,
        cy,
        core_amp,
        rng.gen_range(0.6..1.2),
        rng.gen_range(0.6..1.2),
        0.0,
    );
    let jet_amp = amp * rng.gen_range(0.05..0.3);
    for (side, sign) in [(0, 1.0), (1, -1.0)] {
        let bend: f64 = rng.gen_range(-0.25..0.25);
        let dir = axis + bend;
        let (sd, cd) = dir.sin_cos();
        let dist = 0.5 * extent * rng.gen_range(0.7..1.0);
        let lx = cx + sign * dist * cd;
        let ly = cy + sign * dist * sd;
        let lobe_amp = amp * rng.gen_range(0.3..1.0);
        let sig_maj = (extent * rng.gen_range(0.06..0.12)).max(1.0);
        let sig_min = sig_maj * rng.gen_range(0.5..0.9);
        // The main lobe Gaussian plus 1-2 offset sub-lobes give the irregular lobe shape.
        canvas.add_gaussian(lx, ly, lobe_amp, sig_maj, sig_min, dir);
        for _ in 0..rng.gen_range(1..=2) {
            let ox = lx + sig_maj * rng.gen_range(-1.0..1.0);
            let oy = ly + sig_maj * rng.gen_range(-1.0..1.0);
            let f = rng.gen_range(0.3..0.7);
            canvas.add_gaussian(
                ox,
                oy,
                lobe_amp * f,
                sig_maj * f.sqrt(),
                sig_min * f.sqrt(),
                dir + rng.gen_range(-0.5..0.5),
            );
        }
        if rng.gen_bool(0.5) {
            // FR II hotspot where the jet hits the lobe's outer edge.
            let hd = dist + 0.5 * sig_maj;
            let hs = rng.gen_range(0.8..2.0);
            canvas.add_gaussian(
                cx + sign * hd * cd,
                cy + sign * hd * sd,
                lobe_amp * rng.gen_range(0.8..2.0),
                hs,
                hs * rng.gen_range(0.6..1.0),
                dir,
            );
        }
        // Jet from the core towards the lobe; the counter-jet (side 1) is Doppler-dimmed.
        let jet_sig = rng.gen_range(0.8..2.0);
        let side_amp = if side == 0 {
            jet_amp
        } else {
            jet_amp * rng.gen_range(0.1..0.5)
        };
        let decay = rng.gen_range(1.0..3.0);
        let steps = ((dist / (1.2 * jet_sig)).ceil() as usize).max(3);
        for k in 1..steps {
            let t = k as f64 / steps as f64;
            canvas.add_gaussian(
                cx + sign * t * dist * cd,
                cy + sign * t * dist * sd,
                side_amp * (-decay * t).exp(),
                jet_sig * (1.0 + t),
                jet_sig,
                dir,
            );
        }
    }
}

/// An extended elliptical source of overall size `extent` (±3 sigma of the main component:
/// at a high dynamic range a Gaussian stays above the floor out to ~4.3 sigma, so a
/// narrower definition would let one source fill the field) with 1-3 fainter offset
/// sub-components, so it is not a perfect ellipse.
fn add_gaussian_complex(
    canvas: &mut Canvas,
    rng: &mut ChaCha8Rng,
    cx: f64,
    cy: f64,
    extent: f64,
    amp: f64,
) {
    let sig_maj = (extent / 6.0).max(1.0);
    let sig_min = sig_maj * rng.gen_range(0.3..1.0);
    let theta = rng.gen_range(0.0..std::f64::consts::PI);
    canvas.add_gaussian(cx, cy, amp, sig_maj, sig_min, theta);
    for _ in 0..rng.gen_range(1..=3) {
        let ox = cx + sig_maj * rng.gen_range(-1.2..1.2);
        let oy = cy + sig_maj * rng.gen_range(-1.2..1.2);
        let f = rng.gen_range(0.2..0.6);
        canvas.add_gaussian(
            ox,
            oy,
            amp * f,
            sig_maj * rng.gen_range(0.2..0.6),
            sig_min * rng.gen_range(0.2..0.6),
            rng.gen_range(0.0..std::f64::consts::PI),
        );
    }
}

/// Low-brightness diffuse emission with compact support: white noise smoothed to a
/// correlation length of a few percent of the image, soft-thresholded (`max(0, f - t)`, so
/// patches fade continuously to 0), and multiplied by an envelope of 1-3 broad Gaussians so
/// the patches cluster in a few regions instead of covering the field. Peak brightness is
/// `DR^-u` with u in [0.4, 0.75]: faint, but well above the floor, so the diffuse structure
/// spans a useful part of the dynamic range.
fn diffuse_emission(
    rng: &mut ChaCha8Rng,
    n: usize,
    dr: f64,
    inner_lo: f64,
    inner_hi: f64,
) -> Vec<f64> {
    let nf = n as f64;
    let mut field: Vec<f64> = (0..n * n)
        .map(|_| rng.sample::<f64, _>(StandardNormal))
        .collect();
    let corr = rng.gen_range(0.02..0.05) * nf;
    box_blur_periodic(&mut field, n, corr);
    let mean = field.iter().sum::<f64>() / (n * n) as f64;
    let var = field.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / (n * n) as f64;
    let sd = var.sqrt().max(f64::MIN_POSITIVE);
    let t = rng.gen_range(0.8..1.5);

    let mut env = Canvas::new(n, 1e-3);
    for _ in 0..rng.gen_range(1..=3) {
        let s = rng.gen_range(0.08..0.18) * nf;
        let x = uniform_in(rng, inner_lo, inner_hi);
        let y = uniform_in(rng, inner_lo, inner_hi);
        env.add_gaussian(
            x,
            y,
            1.0,
            s,
            s * rng.gen_range(0.6..1.0),
            rng.gen_range(0.0..std::f64::consts::PI),
        );
    }
    let mut out: Vec<f64> = field
        .iter()
        .zip(&env.data)
        .map(|(f, e)| (((f - mean) / sd - t).max(0.0)) * e.min(1.0))
        .collect();
    let peak = out.iter().copied().fold(0.0, f64::max);
    if peak > 0.0 {
        let amp = dr.powf(-rng.gen_range(0.4..0.75)) / peak;
        for v in out.iter_mut() {
            *v *= amp;
        }
    }
    out
}

/// The sky as an instrument of resolution `fwhm_px` (Gaussian FWHM, pixels) images it:
/// convolved with that Gaussian (zero outside the image, so nothing wraps), renormalised to
/// peak 1 and cut below `1 / dynamic_range`, so it keeps the sky contract (peak 1, no negative
/// pixels, nothing fainter than the dynamic range) with its support widened by the blur.
pub fn smooth_to_resolution(image: Vec<f64>, n: usize, fwhm_px: f64, dynamic_range: f64) -> Vec<f64> {
    let sigma = fwhm_px / (8.0 * std::f64::consts::LN_2).sqrt();
    let mut out = crate::deconv::gaussian_blur(&image, n, sigma, 4.0);
    normalise_and_cut(&mut out, dynamic_range);
    out
}

/// Divide by the peak and zero what falls below `1 / dynamic_range` of it: the sky contract's
/// last step (peak 1, nothing fainter than the dynamic range). An all-zero image stays zero.
pub(super) fn normalise_and_cut(image: &mut [f64], dynamic_range: f64) {
    let peak = image.iter().copied().fold(0.0, f64::max);
    if peak > 0.0 {
        let floor = 1.0 / dynamic_range;
        for v in image.iter_mut() {
            *v = if *v / peak < floor { 0.0 } else { *v / peak };
        }
    }
}

/// Approximate Gaussian smoothing with standard deviation `sigma` (pixels) by four passes of
/// a periodic running-box mean along each axis. Four boxes of half-width r have variance
/// `4 r (r + 1) / 3`, so r is chosen to match sigma^2. The cost is O(n^2) whatever sigma,
/// and the arithmetic is plain additions, so results are reproducible bit for bit.
pub(super) fn box_blur_periodic(field: &mut [f64], n: usize, sigma: f64) {
    let r = (((1.0 + 3.0 * sigma * sigma).sqrt() - 1.0) * 0.5)
        .round()
        .max(1.0) as usize;
    let r = r.min((n - 1) / 2);
    let mut line = vec![0.0; n];
    let mut tmp = vec![0.0; n];
    // Rows.
    for iy in 0..n {
        line.copy_from_slice(&field[iy * n..(iy + 1) * n]);
        for _ in 0..4 {
            box_pass(&line, &mut tmp, r);
            std::mem::swap(&mut line, &mut tmp);
        }
        field[iy * n..(iy + 1) * n].copy_from_slice(&line);
    }
    // Columns.
    for ix in 0..n {
        for iy in 0..n {
            line[iy] = field[iy * n + ix];
        }
        for _ in 0..4 {
            box_pass(&line, &mut tmp, r);
            std::mem::swap(&mut line, &mut tmp);
        }
        for iy in 0..n {
            field[iy * n + ix] = line[iy];
        }
    }
}

/// One periodic box mean of half-width r: `out[i] = mean(inp[i-r ..= i+r])` (indices mod n).
fn box_pass(inp: &[f64], out: &mut [f64], r: usize) {
    let n = inp.len();
    let w = (2 * r + 1) as f64;
    let mut sum: f64 = (0..=2 * r).map(|k| inp[(k + n - r) % n]).sum();
    for i in 0..n {
        out[i] = sum / w;
        sum += inp[(i + r + 1) % n] - inp[(i + n - r) % n];
    }
}

/// Separable taper: 1 on [lo + taper, hi - taper], cos^2 down to exactly 0 at lo and hi,
/// 0 outside.
pub(super) fn taper_window(n: usize, lo: f64, hi: f64, taper: f64) -> Vec<f64> {
    (0..n)
        .map(|i| {
            let x = i as f64;
            let d = (x - lo).min(hi - x); // distance inside the support box
            if d <= 0.0 {
                0.0
            } else if d >= taper {
                1.0
            } else {
                let s = (0.5 * std::f64::consts::PI * d / taper).sin();
                s * s
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    /// A point smoothed to FWHM F is the Gaussian of that FWHM: it falls to half its peak F/2
    /// pixels from the centre (interpolated between pixels), and the result keeps the sky
    /// contract; emission cut below 1/DR after the blur is zero.
    #[test]
    fn smoothing_to_a_resolution_gives_that_fwhm_and_keeps_the_sky_contract() {
        let n = 64;
        let mut point = vec![0.0; n * n];
        point[32 * n + 32] = 1.0;
        for fwhm in [1.5, 3.0, 6.0] {
            let out = smooth_to_resolution(point.clone(), n, fwhm, 1e4);
            assert!((out[32 * n + 32] - 1.0).abs() < 1e-12);
            let row = &out[32 * n..33 * n];
            let k = (32..n).find(|&i| row[i] < 0.5).unwrap();
            let half = (k - 1) as f64 + (row[k - 1] - 0.5) / (row[k - 1] - row[k]) - 32.0;
            let exact = 0.5 * fwhm;
            // Linear interpolation of a Gaussian between pixels errs by a small fraction of a pixel.
            assert!((half - exact).abs() < 0.06 * fwhm.max(1.0), "FWHM {fwhm}: half maximum at {half}, expected {exact}");
            let column: Vec<f64> = (0..n).map(|iy| out[iy * n + 32]).collect();
            assert!(column.iter().zip(row).all(|(a, b)| (a - b).abs() < 1e-12), "the blur is isotropic");
            assert!(out.iter().all(|&v| v == 0.0 || (1e-4..=1.0).contains(&v)));
        }
        let smooth = smooth_to_resolution(procedural_sky(&SkyParams::new(n, 1e3, 5)).unwrap(), n, 2.0, 1e3);
        assert_eq!(smooth.iter().copied().fold(0.0, f64::max), 1.0);
        assert!(smooth.iter().all(|&v| v == 0.0 || (1e-3..=1.0).contains(&v)));
    }

    fn stats(img: &[f64]) -> (f64, f64, f64, f64) {
        let peak = img.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let min = img.iter().copied().fold(f64::INFINITY, f64::min);
        let nz: Vec<f64> = img.iter().copied().filter(|&v| v > 0.0).collect();
        let min_nz = nz.iter().copied().fold(f64::INFINITY, f64::min);
        (peak, min, min_nz, nz.len() as f64 / img.len() as f64)
    }

    #[test]
    fn sky_is_deterministic_in_the_seed() {
        let a = procedural_sky(&SkyParams::new(128, 1e3, 7)).unwrap();
        let b = procedural_sky(&SkyParams::new(128, 1e3, 7)).unwrap();
        let c = procedural_sky(&SkyParams::new(128, 1e3, 8)).unwrap();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn sky_has_unit_peak_zero_background_and_requested_range() {
        for (size, dr) in [
            (64usize, 30.0),
            (128, 1e2),
            (256, 1e3),
            (256, 1e4),
            (200, 1e5),
        ] {
            for seed in 0..6u64 {
                let img = procedural_sky(&SkyParams::new(size, dr, seed)).unwrap();
                assert_eq!(img.len(), size * size);
                let (peak, min, min_nz, frac) = stats(&img);
                let tag = format!("size {size} dr {dr} seed {seed}");
                assert_eq!(peak, 1.0, "{tag}");
                assert_eq!(min, 0.0, "{tag}");
                assert!(min_nz >= 1.0 / dr, "{tag}: faintest {min_nz}");
                assert!(
                    min_nz <= 10.0 / dr,
                    "{tag}: faintest {min_nz} leaves the range unused"
                );
                assert!(
                    (0.005..=0.6).contains(&frac),
                    "{tag}: nonzero fraction {frac}"
                );
            }
        }
    }

    #[test]
    fn sky_has_no_emission_near_the_border() {
        for seed in 0..8u64 {
            let n = 256;
            let img = procedural_sky(&SkyParams::new(n, 1e4, seed)).unwrap();
            let edge = (0.05 * n as f64).ceil() as usize;
            for iy in 0..n {
                for ix in 0..n {
                    if ix < edge || iy < edge || ix >= n - edge || iy >= n - edge {
                        assert_eq!(img[iy * n + ix], 0.0, "seed {seed} pixel ({ix}, {iy})");
                    }
                }
            }
        }
    }

    #[test]
    fn sky_rejects_bad_parameters() {
        assert!(procedural_sky(&SkyParams::new(16, 1e3, 0)).is_err());
        assert!(procedural_sky(&SkyParams::new(64, 1.0, 0)).is_err());
        assert!(procedural_sky(&SkyParams::new(64, f64::NAN, 0)).is_err());
        let p = SkyParams {
            support_fraction: 1.5,
            ..SkyParams::new(64, 1e3, 0)
        };
        assert!(procedural_sky(&p).is_err());
    }

    #[test]
    fn sky_512_generation_time() {
        let t0 = Instant::now();
        let img = procedural_sky(&SkyParams::new(512, 1e4, 42)).unwrap();
        let dt = t0.elapsed();
        let (_, _, _, frac) = stats(&img);
        println!(
            "procedural_sky 512x512 DR 1e4: {:.1} ms, nonzero fraction {frac:.3}",
            dt.as_secs_f64() * 1e3
        );
    }

    #[test]
    fn exponent_base_solves_the_defining_equation() {
        for (s, t) in [
            (10.0, 1e3),
            (100.0, 1e4),
            (1e3, 1e5),
            (1e3, 1e4),
            (50.0, 200.0),
            (1e4, 1e6),
        ] {
            let a = solve_exponent_base(s, t).unwrap();
            let (s0, sig) = (1.0 / s, 1.0 / t);
            let lhs = (1.0 + a * sig).powf(1.0 / s0);
            assert!(((lhs - a) / a).abs() < 1e-9, "{s} -> {t}: a {a}, lhs {lhs}");
            // The nontrivial root: well above the minimum of g, not the a ~ 1 root.
            assert!(a > s0 / (sig * (1.0 - s0)), "{s} -> {t}: a {a}");
            // The old faint level lands on the new one after renormalisation.
            let mapped = (s0 * a.ln()).exp_m1() / a.ln().exp_m1();
            assert!(
                ((mapped - sig) / sig).abs() < 0.01 + 1.0 / (a - 1.0),
                "{s} -> {t}: {mapped}"
            );
        }
    }

    #[test]
    fn exponentiate_maps_zero_to_zero_and_peak_to_one() {
        let mut img = vec![0.0, 0.01, 0.1, 0.5, 1.0];
        let a = exponentiate(&mut img, 100.0, 1e4).unwrap();
        // Before renormalisation 1 -> (a - 1)/a; after it, exactly the peak.
        assert_eq!(img[0], 0.0);
        assert!((img[4] - 1.0).abs() < 1e-15);
        assert!(
            (img[1] - 1e-4).abs() < 1e-6,
            "faint level {} (a = {a})",
            img[1]
        );
        assert!(img.windows(2).all(|w| w[0] < w[1]), "monotone");
        // Unnormalised input: divided by its maximum first.
        let mut scaled = vec![0.0, 0.05, 0.5, 2.5, 5.0];
        exponentiate(&mut scaled, 100.0, 1e4).unwrap();
        assert!(scaled.iter().zip(&img).all(|(x, y)| (x - y).abs() < 1e-12));
    }

    #[test]
    fn exponentiate_raises_a_sky_to_the_target_range() {
        let mut img = procedural_sky(&SkyParams::new(128, 100.0, 3)).unwrap();
        exponentiate(&mut img, 100.0, 1e4).unwrap();
        let (peak, min, min_nz, _) = stats(&img);
        assert!((peak - 1.0).abs() < 1e-12 && min == 0.0);
        assert!(min_nz >= 0.9e-4 && min_nz < 2e-4, "faintest {min_nz}");
    }

    #[test]
    fn exponentiate_rejects_bad_ranges() {
        let mut img = vec![0.0, 1.0];
        let e = exponentiate(&mut img, 1e3, 1e3).unwrap_err().to_string();
        assert!(e.contains("dynamic_range"), "{e}");
        assert!(exponentiate(&mut img, 1e3, 10.0).is_err());
        assert!(exponentiate(&mut img, 1.0, 10.0).is_err());
        // Too small a ratio: no nontrivial root.
        let e = exponentiate(&mut img, 100.0, 150.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no nontrivial solution"), "{e}");
        let mut dark = vec![0.0; 4];
        assert!(exponentiate(&mut dark, 10.0, 1e3).is_err());
        assert_eq!(img, vec![0.0, 1.0], "untouched on error");
    }
}
