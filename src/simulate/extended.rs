//! Procedural skies dominated by extended emission, with what real radio images have and the
//! classic procedural skies (`sky`) lack: lobes with filamentary texture and smooth faint
//! envelopes (FR I and FR II radio galaxies), diffuse disks with spiral arms and clumps,
//! cluster halos and relics, and emission spread over `1/DR .. 1` of the peak across large
//! areas.
//!
//! Each object is drawn on a linear scale at a modest dynamic range ([`SOURCE_DR`]: smooth
//! envelopes that fade into the background) and the whole image is then exponentiated to the
//! target dynamic range, as the reference does with its training images (Terris et al. 2022):
//! the linear fading of an envelope becomes emission spanning decades of brightness, which is
//! where a series trained only on compact sources and Gaussian blobs leaves stripes and holes.
//! The objects' compact parts (cores, hotspots, jets, bulges, clumps, embedded galaxies) are
//! drawn apart and added after the exponentiation, their brightest at a random fraction
//! ([`COMPACT_TO_DIFFUSE`]) of the diffuse peak: drawn before it, a one-pixel core became the
//! image's peak and the exponentiation pushed the lobes to ~1e-3 of it, so most of the flux sat
//! in one or two pixels and a series was selected on delta recovery. Background compact
//! sources follow, with the Euclidean power law on `[1/DR, 1]` of the classic skies.
//!
//! [`field_filling_sky`] draws the same objects larger, one of them spanning the support box,
//! inside a faint cocoon at `1e-4 .. 1e-3` of the peak, all of it lumpy with lognormal
//! turbulence: the plateau around and between a real radio galaxy's lobes, which covers a
//! third of a field such as 3C353's and which [`extended_sky`] (faint emission over a tenth of
//! the field, smooth envelopes) leaves rare.
//!
//! Like `sky`, a sky is a pure function of its parameters, has peak 1, no negative pixels, and
//! an exactly empty border outside the support box.

use super::sky::{box_blur_periodic, exponentiate, normalise_and_cut, taper_window, uniform_in, Canvas, SkyParams};
use crate::error::Result;
use rand::Rng;
use rand_chacha::rand_core::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Poisson, StandardNormal};
use std::f64::consts::PI;

/// Dynamic range of the linear drawing before exponentiation: envelopes are drawn down to
/// this fraction of the peak.
pub const SOURCE_DR: f64 = 200.0;

/// Range of the brightest compact part's peak relative to the exponentiated diffuse peak.
const COMPACT_TO_DIFFUSE: std::ops::Range<f64> = 0.2..1.5;

/// Random stream of extended skies (the classic skies use stream 0 of the same seed).
const STREAM_EXTENDED: u64 = 21;

/// Random stream of field-filling skies.
const STREAM_FIELD_FILLING: u64 = 22;

/// Range of a field-filling sky's cocoon level, linear before exponentiation (log-uniform):
/// at the default dynamic ranges, `1e-4 .. 1e-3` of the peak after it.
const COCOON_LEVEL: std::ops::Range<f64> = 0.008..0.06;

/// Range of the standard deviation of a field-filling sky's log-brightness turbulence.
const TURBULENCE_DEPTH: std::ops::Range<f64> = 0.4..0.9;

/// How a sky's objects are laid out.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Layout {
    /// One to three objects, the largest 0.45..0.9 of the support.
    Extended,
    /// One or two objects, the first 0.7..0.9 of the support inside a faint cocoon.
    FieldFilling,
}

/// An extended-emission sky, row-major, peak 1, background exactly 0, faintest nonzero pixel
/// at or above `1 / dynamic_range`. The target dynamic range must exceed `e * SOURCE_DR`
/// (the exponentiation's limit), so at least 600.
pub fn extended_sky(p: &SkyParams) -> Result<Vec<f64>> {
    draw(p, Layout::Extended)
}

/// A field-filling sky: as [`extended_sky`], with its first object spanning the support box
/// inside a textured cocoon (its level drawn in [`COCOON_LEVEL`]), the whole diffuse emission
/// modulated by lognormal turbulence. Same contract.
pub fn field_filling_sky(p: &SkyParams) -> Result<Vec<f64>> {
    draw(p, Layout::FieldFilling)
}

fn draw(p: &SkyParams, layout: Layout) -> Result<Vec<f64>> {
    p.validate()?;
    let n = p.size;
    let nf = n as f64;
    let dr = p.dynamic_range;
    let mut rng = ChaCha8Rng::seed_from_u64(p.seed);
    rng.set_stream(if layout == Layout::Extended { STREAM_EXTENDED } else { STREAM_FIELD_FILLING });

    let lo = 0.5 * (1.0 - p.support_fraction) * nf;
    let hi = nf - lo;
    let taper = (0.04 * nf).max(2.0);
    let (inner_lo, inner_hi) = (lo + taper, hi - taper);
    let span = inner_hi - inner_lo;

    let texture = filaments(&mut rng, n);
    let mut img = vec![0.0; n * n];
    let mut compact = Canvas::new(n, 1e-4);
    // One dominant object, then up to two smaller ones of lower brightness.
    let (objects, first_scale, style) = match layout {
        Layout::Extended => (rng.gen_range(1..=3), 0.45..0.9, Style::COMPACT_LOBES),
        // Less than the support: the wide lobes' and the cocoon's wings fade out inside it.
        Layout::FieldFilling => (rng.gen_range(1..=2), 0.7..0.9, Style::WIDE_LOBES),
    };
    let mut first = None;
    for k in 0..objects {
        let (scale, amp) = if k == 0 { (rng.gen_range(first_scale.clone()), 1.0) } else { (rng.gen_range(0.15..0.4), rng.gen_range(0.2..0.7)) };
        let extent = scale * span;
        let cx = uniform_in(&mut rng, inner_lo + 0.5 * extent, inner_hi - 0.5 * extent);
        let cy = uniform_in(&mut rng, inner_lo + 0.5 * extent, inner_hi - 0.5 * extent);
        let shape = Placement { cx, cy, extent, amp, theta: rng.gen_range(0.0..PI) };
        match rng.gen_range(0..4) {
            0 => fr2_galaxy(&mut img, &mut compact, &mut rng, n, &shape, &texture, &style),
            1 => fr1_galaxy(&mut img, &mut compact, &mut rng, n, &shape, &texture),
            2 => spiral_disk(&mut img, &mut compact, &mut rng, n, &shape, &texture),
            _ => halo_and_relic(&mut img, &mut compact, &mut rng, n, &shape, &texture),
        }
        first = first.or(Some(shape));
    }
    normalise_and_cut(&mut img, SOURCE_DR);
    if let (Layout::FieldFilling, Some(at)) = (layout, first) {
        // Added to the normalised drawing, so that its level (not the objects' brightness
        // draws) sets where it lands after the exponentiation.
        let level = (rng.gen_range(COCOON_LEVEL.start.ln()..COCOON_LEVEL.end.ln())).exp();
        cocoon(&mut img, &mut rng, n, &at, level, &texture);
        let depth = rng.gen_range(TURBULENCE_DEPTH);
        for (v, t) in img.iter_mut().zip(turbulence(&mut rng, n, depth)) {
            *v *= t;
        }
        normalise_and_cut(&mut img, SOURCE_DR);
    }
    exponentiate(&mut img, SOURCE_DR, dr)?;
    let compact_peak = compact.data.iter().copied().fold(0.0, f64::max);
    if compact_peak > 0.0 {
        let scale = rng.gen_range(COMPACT_TO_DIFFUSE) / compact_peak;
        for (v, c) in img.iter_mut().zip(&compact.data) {
            *v += scale * c;
        }
    }

    // Compact sources: fewer than in the classic skies, so the extended emission dominates.
    let mut canvas = Canvas::new(n, 0.01 / dr);
    let (n_min, n_max) = ((n / 32).max(1), (n / 8).max(1));
    let mean = 0.5 * (n_min + n_max) as f64;
    let count = (Poisson::new(mean).map(|d| d.sample(&mut rng)).unwrap_or(mean) as usize).clamp(n_min, n_max);
    let s_min = 1.0 / dr;
    let trunc = 1.0 - s_min.powf(1.5);
    for _ in 0..count {
        let s = (s_min * (1.0 - rng.gen::<f64>() * trunc).powf(-1.0 / 1.5)).min(1.0);
        let x = uniform_in(&mut rng, inner_lo + 3.0, inner_hi - 3.0);
        let y = uniform_in(&mut rng, inner_lo + 3.0, inner_hi - 3.0);
        let sig = rng.gen_range(0.5..1.5);
        canvas.add_gaussian(x, y, s, sig, sig * rng.gen_range(0.6..1.0), rng.gen_range(0.0..PI));
    }
    for (v, c) in img.iter_mut().zip(&canvas.data) {
        *v += c;
    }

    let w = taper_window(n, lo, hi, taper);
    for iy in 0..n {
        for ix in 0..n {
            img[iy * n + ix] *= w[iy] * w[ix];
        }
    }
    normalise_and_cut(&mut img, dr);
    Ok(img)
}

/// Where an object sits: centre, overall size (pixels), peak brightness (linear) and
/// orientation (radians from the x axis).
#[derive(Clone, Copy)]
struct Placement {
    cx: f64,
    cy: f64,
    extent: f64,
    amp: f64,
    theta: f64,
}

/// A texture of thin bright ridges in `[0, 1]`: the zero crossings of two smooth random
/// fields of different correlation lengths (the look of filaments in radio lobes and relics).
fn filaments(rng: &mut ChaCha8Rng, n: usize) -> Vec<f64> {
    let nf = n as f64;
    let mut out = vec![0.0; n * n];
    for (weight, corr, width) in [(0.6, rng.gen_range(0.015..0.03) * nf, 0.3), (0.4, rng.gen_range(0.005..0.012) * nf, 0.25)] {
        let mut field: Vec<f64> = (0..n * n).map(|_| rng.sample::<f64, _>(StandardNormal)).collect();
        box_blur_periodic(&mut field, n, corr);
        let sd = rms(&field);
        for (o, f) in out.iter_mut().zip(&field) {
            let ridge = (1.0 - (f / sd).abs() / width).max(0.0);
            *o += weight * ridge * ridge;
        }
    }
    out
}

/// Root mean square of a random field (kept above 0: fields are divided by it).
fn rms(field: &[f64]) -> f64 {
    (field.iter().map(|v| v * v).sum::<f64>() / field.len() as f64).sqrt().max(f64::MIN_POSITIVE)
}

/// Add `amp * envelope(x, y) * (base + (1 - base) * texture)` over the pixels within `reach`
/// of (cx, cy); `envelope` takes pixel coordinates.
#[allow(clippy::too_many_arguments)]
fn add_textured(img: &mut [f64], n: usize, cx: f64, cy: f64, reach: f64, amp: f64, base: f64, texture: &[f64], envelope: impl Fn(f64, f64) -> f64) {
    let nf = n as f64;
    let x0 = (cx - reach).floor().clamp(0.0, nf - 1.0) as usize;
    let x1 = (cx + reach).ceil().clamp(0.0, nf - 1.0) as usize;
    let y0 = (cy - reach).floor().clamp(0.0, nf - 1.0) as usize;
    let y1 = (cy + reach).ceil().clamp(0.0, nf - 1.0) as usize;
    for iy in y0..=y1 {
        for ix in x0..=x1 {
            let e = envelope(ix as f64, iy as f64);
            if e > 1e-6 {
                let k = iy * n + ix;
                img[k] += amp * e * (base + (1.0 - base) * texture[k]);
            }
        }
    }
}

/// Shape ranges of an FR II's lobes (drawn per lobe, in the same order for every style, so
/// that a style changes shapes, not the random sequence).
struct Style {
    /// Lobe length as a fraction of the core-to-hotspot distance.
    lobe_len: std::ops::Range<f64>,
    /// Lobe width as a fraction of its length.
    lobe_width: std::ops::Range<f64>,
    /// How far a lobe is drawn, in units of its semi-major axis (its wings are cut there).
    lobe_reach: f64,
}

impl Style {
    const COMPACT_LOBES: Style = Style { lobe_len: 0.35..0.6, lobe_width: 0.4..0.9, lobe_reach: 4.0 };
    /// Lobes reaching back towards the core, as the backflow of a large FR II does.
    const WIDE_LOBES: Style = Style { lobe_len: 0.6..1.0, lobe_width: 0.5..1.0, lobe_reach: 8.0 };
}

/// A smooth faint envelope around an object, at `level` of the normalised drawing: elongated
/// along the object's axis, with broad wings and the filaments' texture.
fn cocoon(img: &mut [f64], rng: &mut ChaCha8Rng, n: usize, at: &Placement, level: f64, texture: &[f64]) {
    // Sized so that at the highest level the wings fade out inside the object's extent (the
    // support box's taper would otherwise cut them along straight lines).
    let sa = 0.5 * at.extent * rng.gen_range(0.4..0.6);
    let sb = sa * rng.gen_range(0.35..0.8);
    let p = rng.gen_range(0.65..0.9);
    let base = rng.gen_range(0.5..0.8);
    let (cx, cy, theta) = (at.cx, at.cy, at.theta);
    add_textured(img, n, cx, cy, 0.75 * at.extent, level, base, texture, |x, y| soft_blob(x - cx, y - cy, theta, sa, sb, p));
}

/// A lognormal modulation `exp(depth g)`, `g` a unit-variance random field with structure on
/// scales from a few pixels to a tenth of the field (a power-law mix of smoothed noise): the
/// lumpy, turbulent look of real lobes and bridges, which a smooth envelope lacks and where a
/// series trained on smooth ones leaves the faint emission striped.
fn turbulence(rng: &mut ChaCha8Rng, n: usize, depth: f64) -> Vec<f64> {
    let nf = n as f64;
    let mut g = vec![0.0; n * n];
    for corr in [0.005, 0.012, 0.03, 0.08] {
        let mut field: Vec<f64> = (0..n * n).map(|_| rng.sample::<f64, _>(StandardNormal)).collect();
        box_blur_periodic(&mut field, n, (corr * nf).max(1.0));
        let sd = rms(&field);
        // Larger scales carry more of the variance, as in a turbulent medium.
        let weight = corr.sqrt();
        for (o, f) in g.iter_mut().zip(&field) {
            *o += weight * f / sd;
        }
    }
    let sd = rms(&g);
    g.iter().map(|v| (depth * v / sd).exp()).collect()
}

/// A soft elliptical blob with broad wings: `exp(-q^p)`, `q` the squared elliptical radius,
/// `p < 1` flattening the top and widening the wings as real lobes do.
fn soft_blob(dx: f64, dy: f64, theta: f64, sa: f64, sb: f64, p: f64) -> f64 {
    let (s, c) = theta.sin_cos();
    let a = (c * dx + s * dy) / sa;
    let b = (-s * dx + c * dy) / sb;
    (-(a * a + b * b).powf(p)).exp()
}

/// An FR II radio galaxy: a core, thin jets, and two textured lobes bent off the axis with
/// compact hotspots at their outer ends.
fn fr2_galaxy(img: &mut [f64], canvas: &mut Canvas, rng: &mut ChaCha8Rng, n: usize, at: &Placement, texture: &[f64], style: &Style) {
    let half = 0.5 * at.extent;
    let (s, c) = at.theta.sin_cos();
    canvas.add_gaussian(at.cx, at.cy, at.amp, 1.0, 1.0, 0.0);
    for side in [-1.0, 1.0] {
        let reach = half * rng.gen_range(0.75..0.95);
        let bend = rng.gen_range(-0.25..0.25);
        let axis = at.theta + bend * side;
        let (sa, ca) = axis.sin_cos();
        let (hx, hy) = (at.cx + side * reach * ca, at.cy + side * reach * sa);
        let lobe_len = reach * rng.gen_range(style.lobe_len.clone());
        let (lx, ly) = (hx - side * 0.5 * lobe_len * ca, hy - side * 0.5 * lobe_len * sa);
        let (la, lb) = (0.55 * lobe_len, 0.55 * lobe_len * rng.gen_range(style.lobe_width.clone()));
        let p = rng.gen_range(0.6..0.9);
        let lobe_amp = at.amp * rng.gen_range(0.08..0.35);
        add_textured(img, n, lx, ly, style.lobe_reach * la, lobe_amp, 0.3, texture, |x, y| soft_blob(x - lx, y - ly, axis, la, lb, p));
        canvas.add_gaussian(hx, hy, at.amp * rng.gen_range(0.2..0.9), rng.gen_range(0.8..2.0), rng.gen_range(0.6..1.2), axis);
        // A thin jet of small Gaussians from the core towards the hotspot, fading outwards.
        let jet = at.amp * rng.gen_range(0.01..0.05) * if side > 0.0 { 1.0 } else { 0.3 };
        let steps = (reach / 2.0).ceil() as usize;
        for k in 1..steps {
            let t = k as f64 / steps as f64;
            canvas.add_gaussian(at.cx + side * t * reach * c, at.cy + side * t * reach * s, jet * (1.0 - 0.7 * t), 1.0, 0.7, at.theta);
        }
    }
}

/// An FR I radio galaxy: a bright core and jets that widen into textured plumes, bent as by
/// motion through a cluster, fading with distance.
fn fr1_galaxy(img: &mut [f64], canvas: &mut Canvas, rng: &mut ChaCha8Rng, n: usize, at: &Placement, texture: &[f64]) {
    let half = 0.5 * at.extent;
    canvas.add_gaussian(at.cx, at.cy, at.amp, 1.2, 1.2, 0.0);
    let curvature = rng.gen_range(-1.2..1.2) / half;
    for side in [-1.0, 1.0] {
        let steps = (half / 1.5).ceil().max(4.0) as usize;
        let start = at.amp * rng.gen_range(0.1..0.4);
        let width0 = rng.gen_range(0.01..0.03) * at.extent;
        for k in 1..=steps {
            let t = k as f64 / steps as f64;
            let along = side * t * half;
            let across = curvature * along * along;
            let (s, c) = at.theta.sin_cos();
            let x = at.cx + along * c - across * s;
            let y = at.cy + along * s + across * c;
            let width = width0 + t * 0.18 * at.extent;
            let amp = start * (1.0 - 0.85 * t) / (1.0 + 3.0 * t);
            let tangent = at.theta + (2.0 * curvature * along).atan();
            add_textured(img, n, x, y, 3.5 * width, amp * 0.6, 0.45, texture, |px, py| soft_blob(px - x, py - y, tangent, width, 0.7 * width, 1.0));
        }
    }
}

/// An inclined spiral disk: exponential profile, two to four logarithmic arms, a bulge and
/// clumps of star formation along the arms.
fn spiral_disk(img: &mut [f64], canvas: &mut Canvas, rng: &mut ChaCha8Rng, n: usize, at: &Placement, texture: &[f64]) {
    let h = at.extent * rng.gen_range(0.1..0.18);
    let cos_i = rng.gen_range(0.3..1.0);
    let arms = rng.gen_range(2..=4) as f64;
    let tan_pitch = rng.gen_range(10.0f64..30.0).to_radians().tan();
    let phase = rng.gen_range(0.0..2.0 * PI);
    let contrast = rng.gen_range(2.0..4.0);
    let (s, c) = at.theta.sin_cos();
    let disk_amp = at.amp * rng.gen_range(0.15..0.4);
    let (cx, cy) = (at.cx, at.cy);
    let arm = move |px: f64, py: f64| -> (f64, f64) {
        let (dx, dy) = (px - cx, py - cy);
        let a = c * dx + s * dy;
        let b = (-s * dx + c * dy) / cos_i;
        let r = (a * a + b * b).sqrt().max(1e-3);
        let phi = b.atan2(a);
        let wave = 0.5 * (1.0 + (arms * (phi - (r / h).ln() / tan_pitch) + phase).cos());
        (r, wave)
    };
    add_textured(img, n, cx, cy, 0.5 * at.extent, disk_amp, 0.75, texture, |px, py| {
        let (r, wave) = arm(px, py);
        (-r / h).exp() * (0.25 + 0.75 * wave.powf(contrast)) * (1.0 - (r / (0.5 * at.extent)).powi(4)).max(0.0)
    });
    canvas.add_gaussian(cx, cy, at.amp * rng.gen_range(0.3..1.0), 0.4 * h, 0.4 * h * cos_i.max(0.5), at.theta);
    // Clumps where the arms are bright.
    for _ in 0..rng.gen_range(5..25) {
        let (px, py) = (cx + rng.gen_range(-2.5..2.5) * h, cy + rng.gen_range(-2.5..2.5) * h);
        let (r, wave) = arm(px, py);
        if wave > 0.7 && r < 0.5 * at.extent {
            canvas.add_gaussian(px, py, disk_amp * (-r / h).exp() * rng.gen_range(0.5..2.0), rng.gen_range(0.6..1.8), rng.gen_range(0.5..1.2), rng.gen_range(0.0..PI));
        }
    }
}

/// A cluster's smooth faint halo with a filamentary arc-shaped relic at its edge and a few
/// embedded compact galaxies.
fn halo_and_relic(img: &mut [f64], canvas: &mut Canvas, rng: &mut ChaCha8Rng, n: usize, at: &Placement, texture: &[f64]) {
    let (cx, cy) = (at.cx, at.cy);
    let sigma = 0.22 * at.extent;
    let elong = rng.gen_range(0.6..1.0);
    add_textured(img, n, cx, cy, 0.5 * at.extent, at.amp * rng.gen_range(0.05..0.15), 0.85, texture, |x, y| {
        soft_blob(x - cx, y - cy, at.theta, sigma, sigma * elong, 0.8)
    });
    let radius = 0.38 * at.extent;
    let width = rng.gen_range(0.02..0.05) * at.extent;
    let arc = rng.gen_range(0.4..1.0);
    let facing = rng.gen_range(0.0..2.0 * PI);
    add_textured(img, n, cx, cy, 0.5 * at.extent, at.amp * rng.gen_range(0.15..0.5), 0.2, texture, |x, y| {
        let (dx, dy) = (x - cx, y - cy);
        let r = (dx * dx + dy * dy).sqrt();
        let dphi = ((dy.atan2(dx) - facing + PI).rem_euclid(2.0 * PI)) - PI;
        (-0.5 * ((r - radius) / width).powi(2)).exp() * (-0.5 * (dphi / arc).powi(2)).exp()
    });
    for _ in 0..rng.gen_range(2..6) {
        let (x, y) = (cx + rng.gen_range(-1.0..1.0) * sigma, cy + rng.gen_range(-1.0..1.0) * sigma);
        canvas.add_gaussian(x, y, at.amp * rng.gen_range(0.2..1.0), rng.gen_range(0.7..1.5), rng.gen_range(0.6..1.2), rng.gen_range(0.0..PI));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sky contract: a pure function of the seed, peak 1, nothing below 1/DR but exact
    /// zeros, nothing outside the support box (default 0.85 of the side).
    fn assert_sky_contract(sky: fn(&SkyParams) -> Result<Vec<f64>>, n: usize, dr: f64, seed: u64) -> Vec<f64> {
        let img = sky(&SkyParams::new(n, dr, seed)).unwrap();
        assert_eq!(img, sky(&SkyParams::new(n, dr, seed)).unwrap(), "a pure function of the seed");
        let peak = img.iter().copied().fold(0.0, f64::max);
        assert!((peak - 1.0).abs() < 1e-12);
        assert!(img.iter().all(|&v| v == 0.0 || (v >= 1.0 / dr * (1.0 - 1e-12) && v.is_finite())));
        let edge = (0.075 * n as f64).floor() as usize;
        for iy in 0..n {
            for ix in 0..n {
                if ix < edge || iy < edge || ix >= n - edge || iy >= n - edge {
                    assert_eq!(img[iy * n + ix], 0.0, "seed {seed}: emission at ({ix}, {iy}) outside the support");
                }
            }
        }
        img
    }

    #[test]
    fn extended_skies_keep_the_sky_contract_and_spread_faint_emission_over_large_areas() {
        for seed in 0..12 {
            let n = 128;
            let img = assert_sky_contract(extended_sky, n, 1e4, seed);
            // Faint emission (1e-4 .. 1e-2 of the peak) over a large area, not just a few
            // compact sources: the point of these skies.
            let faint = img.iter().filter(|&&v| v > 0.0 && v < 1e-2).count() as f64 / (n * n) as f64;
            assert!(faint > 0.03, "seed {seed}: faint emission over only {:.1} % of the image", 100.0 * faint);
        }
    }

    #[test]
    fn flux_is_spread_over_the_objects_not_held_by_a_few_compact_pixels() {
        // A series selected on skies whose flux sits in one core pixel learns delta recovery.
        for seed in 0..8 {
            let mut v = extended_sky(&SkyParams::new(256, 1e4, seed)).unwrap();
            v.sort_by(|a, b| b.total_cmp(a));
            let total: f64 = v.iter().sum();
            let brightest: f64 = v[..16].iter().sum();
            assert!(brightest < 0.3 * total, "seed {seed}: the 16 brightest pixels hold {:.0} % of the flux", 100.0 * brightest / total);
        }
    }

    #[test]
    fn field_filling_skies_keep_the_contract_and_cover_a_large_part_of_the_field_faintly() {
        // What they are for: a plateau at 1e-4..1e-3 of the peak over a far larger area than
        // the extended skies have (3C353: a third of its field above 1e-4 of the peak).
        let (n, dr) = (256, 1e4);
        let above = |img: &[f64], t: f64| img.iter().filter(|&&v| v > t).count() as f64 / img.len() as f64;
        let (mut filled, mut extended) = (0.0, 0.0);
        for seed in 0..8 {
            let img = assert_sky_contract(field_filling_sky, n, dr, seed);
            let other = extended_sky(&SkyParams::new(n, dr, seed)).unwrap();
            assert_ne!(img, other);
            let plateau = above(&img, 1e-4) - above(&img, 1e-3);
            assert!(plateau > 0.05, "seed {seed}: only {:.1} % of the field at 1e-4..1e-3 of the peak", 100.0 * plateau);
            filled += above(&img, 1e-4) / 8.0;
            extended += above(&other, 1e-4) / 8.0;
        }
        assert!(filled > 0.2 && filled > 1.25 * extended, "field-filling {:.1} % above 1e-4 of the peak, extended {:.1} %", 100.0 * filled, 100.0 * extended);
    }

    #[test]
    fn differ_from_the_classic_sky_of_the_same_seed() {
        let p = SkyParams::new(64, 1e3, 5);
        assert_ne!(extended_sky(&p).unwrap(), super::super::sky::procedural_sky(&p).unwrap());
        assert!(extended_sky(&SkyParams::new(64, 1e3, 5)).is_ok());
    }
}
