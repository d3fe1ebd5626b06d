//! The restoring beam: an elliptical Gaussian fitted to the PSF's main lobe, checked against
//! it, with a stated fallback where the fit fails or is absurd.

use crate::{Error, Result};

/// Restoring beam (Gaussian), written as BMAJ, BMIN, BPA.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Beam {
    /// Full width at half maximum along the major axis, degrees.
    pub major_deg: f64,
    /// Full width at half maximum along the minor axis, degrees.
    pub minor_deg: f64,
    /// Position angle of the major axis, degrees east of north.
    pub pa_deg: f64,
}

/// `FWHM = FWHM_PER_SIGMA * sigma` for a Gaussian.
pub(super) const FWHM_PER_SIGMA: f64 = 2.354_820_045_030_949_3; // 2 sqrt(2 ln 2)

/// Fraction of the peak down to which the main lobe is fitted (CASA's `psfcutoff` default):
/// low enough to include the half-power contour, high enough to stay clear of the first null.
const MAIN_LOBE_LEVEL: f64 = 0.35;

/// The restoring beam: an elliptical Gaussian with peak 1 and centre `(N/2, N/2)` fitted by
/// least squares to the PSF's main lobe (the pixels connected to the centre that are at least
/// 0.35 of the peak, plus the centre's eight neighbours so that narrow beams keep three
/// independent constraints). The three parameters start from a weighted linear fit of
/// `ln psf` (a quadratic form) and are refined by Levenberg–Marquardt on the Gaussian itself.
///
/// WSClean instead fits every pixel of a box ten FWHM wide, sidelobes included, which pulls the
/// fit slightly when the sidelobes are strong; fitting the main lobe only, as CASA does, gives
/// the width of the central peak whatever the sidelobes.
///
/// The PSF is divided by its centre value, so only its shape matters. Returns FWHM in degrees
/// and the position angle in degrees east of north in (-90, 90].
pub fn fit_beam(psf: &[f64], size: usize, pixel_rad: f64) -> Result<Beam> {
    let n = size;
    if n < 3 || psf.len() != n * n {
        return Err(Error::parameter(
            "psf",
            format!("expected a {n} x {n} PSF (at least 3 x 3), got {} pixels", psf.len()),
        ));
    }
    if !(pixel_rad > 0.0) || !pixel_rad.is_finite() {
        return Err(Error::parameter("pixel size", format!("expected a positive pixel size, got {pixel_rad} rad")));
    }
    if let Some(bad) = psf.iter().position(|v| !v.is_finite()) {
        return Err(Error::parameter(
            "psf",
            format!("pixel ({}, {}) is {}: the PSF must be finite to fit a beam", bad % n, bad / n, psf[bad]),
        ));
    }
    let (cx, cy) = (n / 2, n / 2);
    let peak = psf[cy * n + cx];
    if !(peak > 0.0) {
        return Err(Error::parameter(
            "psf",
            format!("the PSF is {peak} at its centre pixel ({cx}, {cy}); a beam needs a positive peak there"),
        ));
    }
    let (imax, vmax) = psf.iter().enumerate().fold((0, f64::NEG_INFINITY), |b, (i, &v)| if v > b.1 { (i, v) } else { b });
    if vmax > peak * (1.0 + 1e-6) {
        return Err(Error::parameter(
            "psf",
            format!(
                "the PSF peaks at pixel ({}, {}) with {vmax}, not at the centre ({cx}, {cy}) where it is {peak}: \
                 expected a PSF centred on the image",
                imax % n,
                imax / n
            ),
        ));
    }

    let lobe = main_lobe(psf, n, peak);
    let initial = log_quadratic_fit(&lobe).unwrap_or_else(|| {
        // Too few positive pixels for the log fit: a circle with the lobe's area.
        let area = lobe.iter().filter(|p| p.2 >= MAIN_LOBE_LEVEL).count() as f64;
        let sigma2 = area / (2.0 * std::f64::consts::PI * (1.0 / MAIN_LOBE_LEVEL).ln());
        [1.0 / sigma2, 0.0, 1.0 / sigma2]
    });
    let q = levenberg_marquardt(&lobe, initial);
    beam_from_quadratic(q, pixel_rad).ok_or_else(|| {
        Error::parameter("psf", "the main lobe of the PSF does not fit an elliptical Gaussian (no positive-definite fit)")
    })
}

/// The shape a restoring beam is fitted with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BeamFit {
    /// An elliptical Gaussian ([`fit_beam`]).
    Elliptical,
    /// A circular Gaussian, one width fitted to the whole main lobe ([`fit_circular_beam`]).
    Circular,
}

/// The circular Gaussian (peak 1, centre `(N/2, N/2)`) fitted by least squares to the PSF's
/// main lobe, the same pixels [`fit_beam`] fits: as WSClean's `-circular-beam` fits one width
/// to the PSF rather than keeping one axis of the elliptical fit, so that a restored source's
/// peak is that of a beam as wide as the lobe on average.
pub fn fit_circular_beam(psf: &[f64], size: usize, pixel_rad: f64) -> Result<Beam> {
    // The elliptical fit checks the PSF and gives the starting width (the geometric mean).
    let elliptical = fit_beam(psf, size, pixel_rad)?;
    let peak = psf[(size / 2) * size + size / 2];
    let lobe = main_lobe(psf, size, peak);
    let sigma_pix = |fwhm_deg: f64| fwhm_deg.to_radians() / pixel_rad / FWHM_PER_SIGMA;
    let start = sigma_pix((elliptical.major_deg * elliptical.minor_deg).sqrt());
    let cost = |sigma: f64| {
        let a = 0.5 / (sigma * sigma);
        lobe.iter().map(|&(x, y, p)| ((-a * (x * x + y * y)).exp() - p).powi(2)).sum::<f64>()
    };
    // The cost of one width is unimodal between the minor and major axes' widths (and a
    // little beyond): a golden-section search on ln sigma over a bracket around them.
    let (mut lo, mut hi) = ((start / 4.0).ln(), (start * 4.0).ln());
    let ratio = (5f64.sqrt() - 1.0) / 2.0;
    let (mut x1, mut x2) = (hi - ratio * (hi - lo), lo + ratio * (hi - lo));
    let (mut f1, mut f2) = (cost(x1.exp()), cost(x2.exp()));
    while hi - lo > 1e-10 {
        if f1 <= f2 {
            (hi, x2, f2) = (x2, x1, f1);
            x1 = hi - ratio * (hi - lo);
            f1 = cost(x1.exp());
        } else {
            (lo, x1, f1) = (x1, x2, f2);
            x2 = lo + ratio * (hi - lo);
            f2 = cost(x2.exp());
        }
    }
    let fwhm_deg = ((0.5 * (lo + hi)).exp() * pixel_rad * FWHM_PER_SIGMA).to_degrees();
    Ok(Beam { major_deg: fwhm_deg, minor_deg: fwhm_deg, pa_deg: 0.0 })
}

/// The restoring beam of a PSF: [`fit_beam`] (or [`fit_circular_beam`]), checked against the
/// PSF's main lobe. A fit that fails, is wider than the field, or whose area at the main
/// lobe's level differs from the lobe's by more than a factor 3 (a sparse snapshot's PSF gave
/// a beam of 882 335 deg) is replaced by a circular beam of the main lobe's area; the warning
/// says so.
pub fn restoring_beam(psf: &[f64], size: usize, pixel_rad: f64, shape: BeamFit) -> Result<(Beam, Option<String>)> {
    let fitted = match shape {
        BeamFit::Elliptical => fit_beam(psf, size, pixel_rad),
        BeamFit::Circular => fit_circular_beam(psf, size, pixel_rad),
    };
    let peak = psf.get((size / 2) * size + size / 2).copied().unwrap_or(0.0);
    if !(peak > 0.0) {
        return fitted.map(|b| (b, None));
    }
    let lobe = main_lobe(psf, size, peak);
    let lobe_area = lobe.iter().filter(|p| p.2 >= MAIN_LOBE_LEVEL).count().max(1) as f64;
    let level_area = |beam: &Beam| {
        let q = quadratic_from_beam(beam, pixel_rad);
        let det = q[0] * q[2] - q[1] * q[1];
        2.0 * std::f64::consts::PI * (1.0 / MAIN_LOBE_LEVEL).ln() / det.sqrt()
    };
    let field_deg = (size as f64 * pixel_rad).to_degrees();
    let problem = match &fitted {
        Ok(beam) if beam.major_deg > field_deg => Some(format!("the fitted beam ({:.4} deg) is wider than the field ({field_deg:.4} deg)", beam.major_deg)),
        Ok(beam) => {
            let ratio = level_area(beam) / lobe_area;
            (!(1.0 / 3.0..=3.0).contains(&ratio)).then(|| format!("the fitted beam ({:.4} x {:.4} deg) covers {ratio:.2} times the PSF's main lobe", beam.major_deg, beam.minor_deg))
        }
        Err(e) => Some(format!("no elliptical Gaussian fits the PSF's main lobe ({e})")),
    };
    let Some(problem) = problem else { return fitted.map(|b| (b, None)) };
    // A circle of the lobe's area at MAIN_LOBE_LEVEL: pi r^2 = lobe_area, FWHM from sigma.
    let sigma_pix = (lobe_area / (2.0 * std::f64::consts::PI * (1.0 / MAIN_LOBE_LEVEL).ln())).sqrt();
    let fwhm_deg = (sigma_pix * pixel_rad * FWHM_PER_SIGMA).to_degrees();
    let beam = Beam { major_deg: fwhm_deg, minor_deg: fwhm_deg, pa_deg: 0.0 };
    let warning = format!("{problem}: restoring with a circular beam of the main lobe's area instead ({fwhm_deg:.4} deg FWHM)");
    Ok((beam, Some(warning)))
}

/// `(x, y, psf / peak)` over the main lobe, coordinates in pixels from the centre.
fn main_lobe(psf: &[f64], n: usize, peak: f64) -> Vec<(f64, f64, f64)> {
    let (cx, cy) = (n / 2, n / 2);
    let mut inside = vec![false; n * n];
    let mut stack = vec![(cx, cy)];
    inside[cy * n + cx] = true;
    // The centre's neighbours always count, whatever their level.
    for iy in cy.saturating_sub(1)..=(cy + 1).min(n - 1) {
        for ix in cx.saturating_sub(1)..=(cx + 1).min(n - 1) {
            if !inside[iy * n + ix] {
                inside[iy * n + ix] = true;
                if psf[iy * n + ix] >= MAIN_LOBE_LEVEL * peak {
                    stack.push((ix, iy));
                }
            }
        }
    }
    // Flood fill (4-connected) over pixels at or above the level.
    while let Some((ix, iy)) = stack.pop() {
        let neighbours = [(ix.wrapping_sub(1), iy), (ix + 1, iy), (ix, iy.wrapping_sub(1)), (ix, iy + 1)];
        for (jx, jy) in neighbours {
            if jx < n && jy < n && !inside[jy * n + jx] && psf[jy * n + jx] >= MAIN_LOBE_LEVEL * peak {
                inside[jy * n + jx] = true;
                stack.push((jx, jy));
            }
        }
    }
    let mut lobe = Vec::new();
    for iy in 0..n {
        for ix in 0..n {
            if inside[iy * n + ix] {
                lobe.push((ix as f64 - cx as f64, iy as f64 - cy as f64, psf[iy * n + ix] / peak));
            }
        }
    }
    lobe
}

/// `Q(x, y) = a x^2 + 2 b x y + c y^2`; the Gaussian is `exp(-Q / 2)`.
pub(super) fn quadratic(q: [f64; 3], x: f64, y: f64) -> f64 {
    q[0] * x * x + 2.0 * q[1] * x * y + q[2] * y * y
}

fn positive_definite(q: [f64; 3]) -> bool {
    q[0] > 0.0 && q[2] > 0.0 && q[0] * q[2] - q[1] * q[1] > 0.0 && q.iter().all(|v| v.is_finite())
}

/// Least squares of `-2 ln p = Q(x, y)` over positive lobe pixels, weighted by `p^2` (the log
/// amplifies errors on faint pixels by `1 / p`). `None` unless the result is positive definite.
fn log_quadratic_fit(lobe: &[(f64, f64, f64)]) -> Option<[f64; 3]> {
    let mut ata = [[0.0; 3]; 3];
    let mut atb = [0.0; 3];
    for &(x, y, p) in lobe.iter().filter(|l| l.2 > 0.01 && l.2 < 1.0) {
        let row = [x * x, 2.0 * x * y, y * y];
        let (w, target) = (p * p, -2.0 * p.ln());
        for i in 0..3 {
            for j in 0..3 {
                ata[i][j] += w * row[i] * row[j];
            }
            atb[i] += w * row[i] * target;
        }
    }
    solve3(ata, atb).filter(|&q| positive_definite(q))
}

/// Levenberg–Marquardt on `sum (exp(-Q/2) - p)^2` in the parameters `(a, b, c)` of `Q`, which
/// keeps the model smooth in its parameters (no angle wrap-around); steps that leave the
/// positive-definite cone are rejected like steps that raise the cost.
fn levenberg_marquardt(lobe: &[(f64, f64, f64)], start: [f64; 3]) -> [f64; 3] {
    let cost = |q: [f64; 3]| lobe.iter().map(|&(x, y, p)| ((-0.5 * quadratic(q, x, y)).exp() - p).powi(2)).sum::<f64>();
    let mut q = start;
    let mut current = cost(q);
    let mut lambda = 1e-3;
    for _ in 0..200 {
        let mut jtj = [[0.0; 3]; 3];
        let mut jtr = [0.0; 3];
        for &(x, y, p) in lobe {
            let g = (-0.5 * quadratic(q, x, y)).exp();
            let jac = [-0.5 * x * x * g, -x * y * g, -0.5 * y * y * g];
            for i in 0..3 {
                for j in 0..3 {
                    jtj[i][j] += jac[i] * jac[j];
                }
                jtr[i] += jac[i] * (g - p);
            }
        }
        let mut improved = false;
        while lambda < 1e12 {
            let mut damped = jtj;
            for (i, row) in damped.iter_mut().enumerate() {
                row[i] += lambda * jtj[i][i].max(1e-300);
            }
            let Some(step) = solve3(damped, jtr.map(|v| -v)) else {
                lambda *= 10.0;
                continue;
            };
            let trial = [q[0] + step[0], q[1] + step[1], q[2] + step[2]];
            let trial_cost = if positive_definite(trial) { cost(trial) } else { f64::INFINITY };
            if trial_cost <= current {
                let small = step.iter().map(|s| s.abs()).sum::<f64>() <= 1e-13 * (q[0].abs() + q[2].abs());
                q = trial;
                current = trial_cost;
                lambda = (lambda * 0.1).max(1e-12);
                improved = !small;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    q
}

/// Solves a 3 x 3 system by Gaussian elimination with partial pivoting; `None` if singular.
fn solve3(mut a: [[f64; 3]; 3], mut b: [f64; 3]) -> Option<[f64; 3]> {
    let scale = a.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    if !(scale > 0.0) {
        return None;
    }
    for col in 0..3 {
        let pivot = (col..3).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[pivot][col].abs() <= 1e-14 * scale {
            return None;
        }
        a.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..3 {
            let f = a[row][col] / a[col][col];
            for k in col..3 {
                a[row][k] -= f * a[col][k];
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = [0.0; 3];
    for row in (0..3).rev() {
        let s: f64 = (row + 1..3).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// The beam of the Gaussian `exp(-Q/2)`: the major axis is the eigenvector of the smaller
/// eigenvalue. With the major axis along `(-sin PA, cos PA)` in pixel terms, the principal-axis
/// angle `atan2(2b, a - c) / 2` (measured from +x, for the larger eigenvalue) is the PA itself.
fn beam_from_quadratic(q: [f64; 3], pixel_rad: f64) -> Option<Beam> {
    if !positive_definite(q) {
        return None;
    }
    let [a, b, c] = q;
    let mean = 0.5 * (a + c);
    let spread = (0.25 * (a - c) * (a - c) + b * b).sqrt();
    let (small, large) = (mean - spread, mean + spread);
    if !(small > 0.0) {
        return None;
    }
    let to_deg = |sigma_pix: f64| (sigma_pix * pixel_rad * FWHM_PER_SIGMA).to_degrees();
    let mut pa = 0.5 * (2.0 * b).atan2(a - c).to_degrees();
    if pa <= -90.0 {
        pa += 180.0;
    }
    Some(Beam { major_deg: to_deg(1.0 / small.sqrt()), minor_deg: to_deg(1.0 / large.sqrt()), pa_deg: pa })
}

/// The quadratic form `(a, b, c)` of a beam in pixel coordinates (inverse of
/// [`beam_from_quadratic`]): major axis along `(-sin PA, cos PA)`, minor along `(cos PA, sin PA)`.
pub(super) fn quadratic_from_beam(beam: &Beam, pixel_rad: f64) -> [f64; 3] {
    let sigma = |fwhm_deg: f64| fwhm_deg.to_radians() / pixel_rad / FWHM_PER_SIGMA;
    let (major, minor) = (sigma(beam.major_deg), sigma(beam.minor_deg));
    let (s, c) = beam.pa_deg.to_radians().sin_cos();
    let (inv_major, inv_minor) = (1.0 / (major * major), 1.0 / (minor * minor));
    [s * s * inv_major + c * c * inv_minor, s * c * (inv_minor - inv_major), c * c * inv_major + s * s * inv_minor]
}
