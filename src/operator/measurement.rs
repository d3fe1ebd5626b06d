//! The measurement operator `Phi = diag(sqrt(omega)) G F Z` for fixed baselines and weights:
//! the dirty image, the PSF and `kappa` it gives, the normal operator `D = kappa Re{Phi^H Phi}`
//! by a NUFFT round trip, the prediction of model visibilities, and the spectral norm of `D`.
//!
//! The operator is coplanar (a 2D NUFFT) or includes the w-term `exp(2 pi i w (n - 1))` (by
//! w-gridding, `crate::nufft::wgrid`), as [`WTermMode`] decides from the data and the field:
//! where the w-term turns no phase by more than the NUFFT's accuracy, the two are the same
//! operator to that accuracy, and the coplanar one is cheaper and has an exact Toeplitz form.

use super::geometry::ImageGeometry;
use crate::nufft::wgrid::{max_w_phase, WGridNormal, WGridPlan};
use crate::nufft::{Nufft2d, NufftParams};
use crate::{Error, Result};
use num_complex::{Complex32, Complex64};
use rayon::prelude::*;

/// A visibility value as the operator takes it, in single or double precision; the sums are
/// in double precision either way.
pub trait Visibility: Copy + Send + Sync {
    fn to_c64(self) -> Complex64;
}

impl Visibility for Complex64 {
    fn to_c64(self) -> Complex64 {
        self
    }
}

impl Visibility for Complex32 {
    fn to_c64(self) -> Complex64 {
        Complex64::new(f64::from(self.re), f64::from(self.im))
    }
}

/// Whether the operator includes the w-term.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum WTermMode {
    /// Included where it matters: where the largest phase it adds over the image exceeds the
    /// NUFFT's requested accuracy (WSClean corrects it always; where this leaves it out, the
    /// coplanar operator equals the w-corrected one to that accuracy).
    #[default]
    Auto,
    /// Always included (w-gridding, even where it changes nothing).
    On,
    /// Never: coplanar imaging, as the reference does by default (for comparison).
    Off,
}

impl WTermMode {
    /// Whether the w-term is included for data whose largest |w| is `max_abs_w` (wavelengths)
    /// on `geometry`, at the requested accuracy `epsilon`.
    pub fn includes(self, geometry: ImageGeometry, max_abs_w: f64, epsilon: f64) -> bool {
        match self {
            WTermMode::On => true,
            WTermMode::Off => false,
            WTermMode::Auto => max_w_phase(geometry.size, geometry.pixel_rad, max_abs_w) > epsilon,
        }
    }

    /// `auto`, `on` or `off`, as the command line and Python name it.
    pub fn from_name(name: &str) -> Result<WTermMode> {
        match name {
            "auto" => Ok(WTermMode::Auto),
            "on" => Ok(WTermMode::On),
            "off" => Ok(WTermMode::Off),
            other => Err(Error::parameter("w-term", format!("expected auto, on or off, got '{other}'"))),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            WTermMode::Auto => "auto",
            WTermMode::On => "on",
            WTermMode::Off => "off",
        }
    }
}

/// The transform behind an operator.
enum Plan {
    /// The 2D NUFFT; values in its sorted order.
    Coplanar(Nufft2d),
    /// w-gridding; values in the caller's order.
    WGridded(WGridPlan),
}

/// `Phi` for fixed baselines and weights: plans the NUFFT once and keeps the weights in the
/// plan's internal order so every application is a straight pass.
pub struct MeasurementOperator {
    geometry: ImageGeometry,
    plan: Plan,
    /// `omega` in the plan's order.
    weight: Vec<f64>,
    kappa: f64,
}

impl MeasurementOperator {
    /// `u`, `v` in wavelengths; `weight` the total weight per visibility (natural x imaging;
    /// zero excludes a visibility). Baselines weighted above zero beyond the image's Nyquist
    /// limit (`|u| >= 1 / (2 pixel)`) would alias and are rejected: choose a smaller pixel (the
    /// weighting gives those beyond the grid weight 0).
    pub fn new(
        geometry: ImageGeometry,
        u: &[f64],
        v: &[f64],
        weight: &[f64],
        nufft: NufftParams,
        threads: usize,
    ) -> Result<MeasurementOperator> {
        Self::normalised(Self::part_for_mode(false, geometry, u, v, &[], weight, nufft, threads)?)
    }

    /// As [`new`](Self::new), with the w-term: `w` in wavelengths, one per visibility.
    pub fn with_w_term(
        geometry: ImageGeometry,
        u: &[f64],
        v: &[f64],
        w: &[f64],
        weight: &[f64],
        nufft: NufftParams,
        threads: usize,
    ) -> Result<MeasurementOperator> {
        Self::normalised(Self::part_for_mode(true, geometry, u, v, w, weight, nufft, threads)?)
    }

    /// The operator `mode` asks for on these data: with the w-term or coplanar.
    #[allow(clippy::too_many_arguments)]
    pub fn for_mode(
        mode: WTermMode,
        geometry: ImageGeometry,
        u: &[f64],
        v: &[f64],
        w: &[f64],
        weight: &[f64],
        nufft: NufftParams,
        threads: usize,
    ) -> Result<MeasurementOperator> {
        let max_abs_w = w.iter().fold(0.0f64, |m, w| m.max(w.abs()));
        if mode.includes(geometry, max_abs_w, nufft.epsilon) {
            Self::with_w_term(geometry, u, v, w, weight, nufft, threads)
        } else {
            Self::new(geometry, u, v, weight, nufft, threads)
        }
    }

    /// The operator with the w-term (`w_term`: `w` in wavelengths, one per visibility) or
    /// coplanar (`w` unused), with `kappa` 1 and no PSF computed for it: what [`new`](Self::new)
    /// and [`with_w_term`](Self::with_w_term) normalise, and one part of an operator summed over
    /// parts (samples read a chunk at a time), whose `kappa` is the whole sum's.
    #[allow(clippy::too_many_arguments)]
    pub fn part_for_mode(
        w_term: bool,
        geometry: ImageGeometry,
        u: &[f64],
        v: &[f64],
        w: &[f64],
        weight: &[f64],
        nufft: NufftParams,
        threads: usize,
    ) -> Result<MeasurementOperator> {
        check_points(geometry, u, v, weight)?;
        if w_term {
            if w.len() != u.len() {
                return Err(Error::parameter("visibilities", "u and w arrays differ in length"));
            }
            // Images are real: the real-image plan folds negative w onto positive w (fewer
            // planes) and grids a real image's Hermitian pairs once.
            let plan = WGridPlan::new_real(geometry.size, geometry.pixel_rad, u, v, w, nufft, threads)?;
            return Ok(MeasurementOperator { geometry, plan: Plan::WGridded(plan), weight: weight.to_vec(), kappa: 1.0 });
        }
        let (x, y): (Vec<f64>, Vec<f64>) = u.iter().zip(v).map(|(&u, &v)| geometry.uv_to_phase(u, v)).unzip();
        let plan = Nufft2d::new(geometry.size, geometry.size, &x, &y, nufft, threads)?;
        drop((x, y));
        let weight: Vec<f64> = plan.order().iter().map(|&k| weight[k as usize]).collect();
        Ok(MeasurementOperator { geometry, plan: Plan::Coplanar(plan), weight, kappa: 1.0 })
    }

    /// Sets `kappa` from the PSF's peak.
    fn normalised(mut op: MeasurementOperator) -> Result<MeasurementOperator> {
        let peak = op.unnormalised_psf_peak();
        if !(peak > 0.0) {
            return Err(Error::parameter("weight", "all visibilities have zero weight: nothing to image"));
        }
        op.kappa = 1.0 / peak;
        Ok(op)
    }

    pub fn geometry(&self) -> ImageGeometry {
        self.geometry
    }
    /// `1 / max(Re{Phi^H Phi delta})`: the factor that gives the PSF a peak of 1.
    pub fn kappa(&self) -> f64 {
        self.kappa
    }
    pub fn len(&self) -> usize {
        self.weight.len()
    }
    pub fn is_empty(&self) -> bool {
        self.weight.is_empty()
    }
    /// The w-planes of a w-gridded operator; `None` for a coplanar one.
    pub fn w_planes(&self) -> Option<usize> {
        match &self.plan {
            Plan::Coplanar(_) => None,
            Plan::WGridded(plan) => Some(plan.planes()),
        }
    }

    /// The plan's order of the caller's visibilities (`None`: the caller's own).
    fn order(&self) -> Option<&[u32]> {
        match &self.plan {
            Plan::Coplanar(plan) => Some(plan.order()),
            Plan::WGridded(_) => None,
        }
    }

    fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        match &self.plan {
            Plan::Coplanar(plan) => plan.install(f),
            Plan::WGridded(plan) => plan.install(f),
        }
    }

    fn to_complex(x: &[f64]) -> Vec<Complex64> {
        x.iter().map(|&v| Complex64::new(v, 0.0)).collect()
    }

    /// `Re{Phi^H diag(omega) y}` for `y` in plan order (without kappa).
    fn back_project_sorted(&self, y_sorted: &[Complex64]) -> Vec<f64> {
        match &self.plan {
            Plan::Coplanar(plan) => {
                let mut img = vec![Complex64::default(); self.geometry.pixels()];
                plan.adjoint_sorted(y_sorted, &mut img);
                img.iter().map(|c| c.re).collect()
            }
            Plan::WGridded(plan) => plan.adjoint_real(y_sorted),
        }
    }

    /// `Phi_raw x` in the plan's order.
    fn forward_sorted(&self, x: &[f64]) -> Vec<Complex64> {
        match &self.plan {
            Plan::Coplanar(plan) => {
                let mut vis = vec![Complex64::default(); self.len()];
                plan.forward_sorted(&Self::to_complex(x), &mut vis);
                vis
            }
            Plan::WGridded(plan) => plan.forward_real(x),
        }
    }

    fn unnormalised_psf_peak(&self) -> f64 {
        let ones: Vec<Complex64> = self.weight.iter().map(|&w| Complex64::new(w, 0.0)).collect();
        let psf = self.back_project_sorted(&ones);
        let n = self.geometry.size;
        psf[(n / 2) * n + n / 2]
    }

    /// Bring per-visibility values from the caller's order into plan order.
    pub fn to_plan_order<T: Copy + Send + Sync>(&self, values: &[T]) -> Vec<T> {
        match self.order() {
            Some(order) => self.install(|| order.par_iter().map(|&k| values[k as usize]).collect()),
            None => values.to_vec(),
        }
    }

    /// Model visibilities `Phi_raw x` (unweighted), in the caller's order.
    pub fn model_visibilities(&self, x: &[f64]) -> Vec<Complex64> {
        match &self.plan {
            Plan::Coplanar(plan) => {
                let mut out = vec![Complex64::default(); self.len()];
                plan.forward(&Self::to_complex(x), &mut out);
                out
            }
            Plan::WGridded(plan) => plan.forward_real(x),
        }
    }

    /// Dirty image `kappa Re{Phi_raw^H (omega y)}` of visibilities `vis` in the caller's order.
    pub fn dirty_image(&self, vis: &[impl Visibility]) -> Vec<f64> {
        assert_eq!(vis.len(), self.len(), "number of visibilities");
        let weighted: Vec<Complex64> = self.install(|| match self.order() {
            Some(order) => order.par_iter().zip(self.weight.par_iter()).map(|(&k, &w)| vis[k as usize].to_c64() * w).collect(),
            None => vis.par_iter().zip(self.weight.par_iter()).map(|(v, &w)| v.to_c64() * w).collect(),
        });
        let mut img = self.back_project_sorted(&weighted);
        img.iter_mut().for_each(|p| *p *= self.kappa);
        img
    }

    /// PSF `kappa Re{Phi^H Phi delta}` with the delta at `(N/2, N/2)`: peak 1 at the centre.
    pub fn psf(&self) -> Vec<f64> {
        let ones: Vec<Complex64> = self.weight.iter().map(|&w| Complex64::new(w * self.kappa, 0.0)).collect();
        self.back_project_sorted(&ones)
    }

    /// [`dirty_image`](Self::dirty_image) and [`psf`](Self::psf) together: a w-gridded
    /// operator spreads both in one pass over its points and planes.
    pub fn dirty_image_and_psf(&self, vis: &[impl Visibility]) -> (Vec<f64>, Vec<f64>) {
        let Plan::WGridded(plan) = &self.plan else {
            return (self.dirty_image(vis), self.psf());
        };
        assert_eq!(vis.len(), self.len(), "number of visibilities");
        let (k, weight) = (self.kappa, &self.weight); // a w-gridded operator's are in the caller's order
        plan.adjoint_real_pair(|i| vis[i].to_c64() * (weight[i] * k), |i| Complex64::new(weight[i] * k, 0.0))
    }

    /// `D x = kappa Re{Phi^H Phi x}` by a NUFFT round trip.
    pub fn apply_normal(&self, x: &[f64]) -> Vec<f64> {
        if let Plan::WGridded(plan) = &self.plan {
            return plan.normal_real(x, &plan.to_plan_order(&self.kappa_weights()));
        }
        let k = self.kappa;
        let mut vis = self.forward_sorted(x);
        vis.par_iter_mut().zip(self.weight.par_iter()).for_each(|(y, &w)| *y *= w * k);
        self.back_project_sorted(&vis)
    }

    /// `D` alone, the operator's samples no longer needed otherwise: a w-gridded operator
    /// releases what only the caller's order of its samples needs.
    pub fn into_normal(self) -> NormalOperator {
        let weights = matches!(self.plan, Plan::WGridded(_)).then(|| self.kappa_weights());
        match (self.plan, weights) {
            (Plan::WGridded(plan), Some(weights)) => NormalOperator::WGridded(plan.into_normal(&weights)),
            (plan, _) => NormalOperator::Coplanar(MeasurementOperator { plan, ..self }),
        }
    }

    /// Each sample's weight times `kappa` (the operator's order): `D`'s weights.
    fn kappa_weights(&self) -> Vec<f64> {
        let k = self.kappa;
        self.install(|| self.weight.par_iter().map(|&w| w * k).collect())
    }
}

/// `D = kappa Re{Phi^H Phi}` of samples held, and nothing else of their operator
/// ([`MeasurementOperator::into_normal`]).
pub enum NormalOperator {
    Coplanar(MeasurementOperator),
    /// The weights scaled by `kappa`.
    WGridded(WGridNormal),
}

impl NormalOperator {
    /// `D x`.
    pub fn apply(&self, x: &[f64]) -> Vec<f64> {
        match self {
            NormalOperator::Coplanar(op) => op.apply_normal(x),
            NormalOperator::WGridded(normal) => normal.apply(x),
        }
    }

    /// The w-planes of a w-gridded operator; `None` for a coplanar one.
    pub fn w_planes(&self) -> Option<usize> {
        match self {
            NormalOperator::Coplanar(_) => None,
            NormalOperator::WGridded(normal) => Some(normal.planes()),
        }
    }
}

/// Model visibilities `Phi_raw x` of the image `x` on `geometry` at `(u, v, w)` (wavelengths,
/// the caller's order), with the w-term where `w_term` includes it: the one prediction the
/// simulator, the operator and `MODEL_DATA` share. Unlike [`MeasurementOperator::new`] it
/// takes baselines beyond the Nyquist limit of the image and predicts zero for them (a
/// flagged sample may lie there), and builds no PSF.
#[allow(clippy::too_many_arguments)]
pub fn predict(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    w: &[f64],
    x: &[f64],
    w_term: WTermMode,
    nufft: NufftParams,
    threads: usize,
) -> Result<Vec<Complex64>> {
    if u.len() != v.len() || u.len() != w.len() {
        return Err(Error::parameter("visibilities", "u, v and w arrays differ in length"));
    }
    let limit = 0.5 / geometry.pixel_rad;
    let inside: Vec<usize> = (0..u.len()).filter(|&k| u[k].abs() < limit && v[k].abs() < limit && u[k].is_finite() && v[k].is_finite()).collect();
    let pick = |a: &[f64]| -> Vec<f64> { inside.iter().map(|&k| a[k]).collect() };
    let (ui, vi, wi) = (pick(u), pick(v), pick(w));
    let max_abs_w = wi.iter().fold(0.0f64, |m, w| m.max(w.abs()));
    let predicted = if inside.is_empty() {
        Vec::new()
    } else if w_term.includes(geometry, max_abs_w, nufft.epsilon) {
        WGridPlan::new_real(geometry.size, geometry.pixel_rad, &ui, &vi, &wi, nufft, threads)?.forward_real(x)
    } else {
        let (px, py): (Vec<f64>, Vec<f64>) = ui.iter().zip(&vi).map(|(&u, &v)| geometry.uv_to_phase(u, v)).unzip();
        let plan = Nufft2d::new(geometry.size, geometry.size, &px, &py, nufft, threads)?;
        let mut out = vec![Complex64::default(); px.len()];
        plan.forward(&MeasurementOperator::to_complex(x), &mut out);
        out
    };
    let mut all = vec![Complex64::default(); u.len()];
    for (&k, value) in inside.iter().zip(predicted) {
        all[k] = value;
    }
    Ok(all)
}

/// Checks what [`MeasurementOperator::new`] needs of its points: equal lengths, baselines
/// weighted above zero within the image's Nyquist limit (`|u| >= 1 / (2 pixel)` would alias;
/// the weighting gives those beyond it weight 0), weights finite and not negative.
pub(crate) fn check_points(geometry: ImageGeometry, u: &[f64], v: &[f64], weight: &[f64]) -> Result<()> {
    if u.len() != v.len() || u.len() != weight.len() {
        return Err(Error::parameter("visibilities", "u, v and weight arrays differ in length"));
    }
    let limit = 0.5 / geometry.pixel_rad;
    let weighted = || u.iter().zip(v).zip(weight).filter(|(_, w)| **w != 0.0).map(|(uv, _)| uv);
    let beyond = weighted().filter(|(u, v)| u.abs() >= limit || v.abs() >= limit).count();
    if beyond > 0 {
        let max_uv = weighted().map(|(u, v)| u.abs().max(v.abs())).fold(0.0, f64::max);
        return Err(Error::parameter(
            "pixel size",
            format!(
                "{beyond} visibilities lie beyond the image's Nyquist limit ({limit:.1} wavelengths for a \
                 {:.4} arcsec pixel); the pixel must be at most {:.4} arcsec",
                geometry.pixel_arcsec(),
                (0.5 / max_uv).to_degrees() * 3600.0
            ),
        ));
    }
    if let Some(bad) = weight.iter().find(|w| !(**w >= 0.0) || !w.is_finite()) {
        return Err(Error::parameter("weight", format!("weights must be finite and >= 0, found {bad}")));
    }
    Ok(())
}

/// Largest eigenvalue of a symmetric operator on `n`-pixel images (the spectral norm, for a
/// positive semi-definite one such as `Re{Phi^H Phi}`), by the Lanczos method with full
/// reorthogonalisation, stopping when the top Ritz value changes by less than `tolerance`
/// (relative). Power iteration needs hundreds of applications here because the top
/// eigenvalues of a PSF convolution cluster; Lanczos needs tens.
pub fn spectral_norm(apply: impl Fn(&[f64]) -> Vec<f64>, n: usize, tolerance: f64, max_iterations: usize) -> f64 {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
    // A fixed pseudo-random start: generic enough not to be orthogonal to the top eigenvector.
    let mut q: Vec<f64> = (0..n).map(|i| ((i as f64 * 12.9898).sin() * 43758.5453).fract().abs() + 0.1).collect();
    let q_norm = dot(&q, &q).sqrt();
    q.iter_mut().for_each(|a| *a /= q_norm);
    let mut basis: Vec<Vec<f64>> = Vec::new();
    let (mut alpha, mut beta) = (Vec::new(), Vec::new());
    let mut value = 0.0;
    for iteration in 1..=max_iterations.min(n) {
        let mut w = apply(&q);
        let a = dot(&w, &q);
        alpha.push(a);
        basis.push(q);
        // Full reorthogonalisation (twice is enough) keeps the basis orthogonal in floating point.
        for _ in 0..2 {
            for b in &basis {
                let c = dot(&w, b);
                w.iter_mut().zip(b).for_each(|(w, b)| *w -= c * b);
            }
        }
        let ritz = largest_tridiagonal_eigenvalue(&alpha, &beta);
        let converged = iteration > 1 && (ritz - value).abs() <= tolerance * ritz.abs();
        value = ritz;
        let b = dot(&w, &w).sqrt();
        if converged || b <= 1e-14 * ritz.abs().max(f64::MIN_POSITIVE) {
            log::debug!("spectral norm {value:.8e} after {iteration} Lanczos iterations");
            return value;
        }
        beta.push(b);
        q = w.into_iter().map(|w| w / b).collect();
    }
    log::warn!("Lanczos stopped at {max_iterations} iterations before a relative change of {tolerance:e}");
    value
}

/// Largest eigenvalue of the symmetric tridiagonal matrix with diagonal `alpha` and
/// off-diagonal `beta` (`beta.len() >= alpha.len() - 1`), by bisection on Sturm counts.
fn largest_tridiagonal_eigenvalue(alpha: &[f64], beta: &[f64]) -> f64 {
    let k = alpha.len();
    // Gershgorin bounds.
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for i in 0..k {
        let r = if i > 0 { beta[i - 1].abs() } else { 0.0 } + if i + 1 < k { beta[i].abs() } else { 0.0 };
        lo = lo.min(alpha[i] - r);
        hi = hi.max(alpha[i] + r);
    }
    // Number of eigenvalues below x (Sturm sequence of the LDL^T pivots).
    let count_below = |x: f64| {
        let mut count = 0;
        let mut d = 1.0;
        for i in 0..k {
            let b2 = if i > 0 { beta[i - 1] * beta[i - 1] } else { 0.0 };
            d = alpha[i] - x - if i > 0 { b2 / d } else { 0.0 };
            if d == 0.0 {
                d = -f64::EPSILON * (x.abs() + 1.0);
            }
            if d < 0.0 {
                count += 1;
            }
        }
        count
    };
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo || mid >= hi {
            break;
        }
        if count_below(mid) == k {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    0.5 * (lo + hi)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Random baselines in a disc of radius `max_uv` wavelengths, random positive weights.
    pub(crate) fn baselines(m: usize, max_uv: f64, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut u = Vec::with_capacity(m);
        let mut v = Vec::with_capacity(m);
        while u.len() < m {
            let (a, b): (f64, f64) = (rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0));
            if a * a + b * b <= 1.0 {
                u.push(a * max_uv);
                v.push(b * max_uv);
            }
        }
        let w = (0..m).map(|_| rng.gen_range(0.5..2.0)).collect();
        (u, v, w)
    }

    pub(crate) fn setup(eps: f64) -> (ImageGeometry, Vec<f64>, Vec<f64>, Vec<f64>, MeasurementOperator) {
        let (u, v, w) = baselines(4000, 1000.0, 1);
        let geometry = ImageGeometry::from_superresolution(32, 1.5, 1000.0).unwrap();
        let op = MeasurementOperator::new(geometry, &u, &v, &w, NufftParams { epsilon: eps, oversampling: 2.0 }, 2).unwrap();
        (geometry, u, v, w, op)
    }

    pub(crate) fn dot(a: &[f64], b: &[f64]) -> f64 {
        a.iter().zip(b).map(|(a, b)| a * b).sum()
    }

    pub(crate) fn random_image(n: usize, seed: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| rng.gen_range(0.0..1.0)).collect()
    }

    #[test]
    fn psf_has_unit_peak_at_centre() {
        let (g, .., op) = setup(1e-9);
        let psf = op.psf();
        let n = g.size;
        let centre = psf[(n / 2) * n + n / 2];
        assert!((centre - 1.0).abs() < 1e-12);
        assert!(psf.iter().all(|&p| p <= centre + 1e-12));
    }

    #[test]
    fn dirty_image_matches_direct_sum_and_puts_a_source_on_its_pixel() {
        let (g, u, v, w, op) = setup(1e-9);
        let n = g.size;
        // A 2 Jy source 5 pixels east (lower ix) and 3 pixels north of the centre.
        let (ix0, iy0) = (n / 2 - 5, n / 2 + 3);
        let l0 = -g.pixel_rad * (ix0 as f64 - (n / 2) as f64);
        let m0 = g.pixel_rad * (iy0 as f64 - (n / 2) as f64);
        let vis: Vec<Complex64> = u
            .iter()
            .zip(&v)
            .map(|(&u, &v)| Complex64::from_polar(2.0, 2.0 * std::f64::consts::PI * (u * l0 + v * m0)))
            .collect();
        let dirty = op.dirty_image(&vis);
        let sum_w: f64 = w.iter().sum();
        let mut max_err: f64 = 0.0;
        for iy in 0..n {
            for ix in 0..n {
                let l = -g.pixel_rad * (ix as f64 - (n / 2) as f64);
                let m = g.pixel_rad * (iy as f64 - (n / 2) as f64);
                let direct: f64 = (0..u.len())
                    .map(|k| w[k] * (vis[k] * Complex64::from_polar(1.0, -2.0 * std::f64::consts::PI * (u[k] * l + v[k] * m))).re)
                    .sum::<f64>()
                    / sum_w;
                max_err = max_err.max((direct - dirty[iy * n + ix]).abs());
            }
        }
        assert!(max_err < 1e-8, "dirty image differs from the direct sum by {max_err}");
        let peak = dirty.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap().0;
        assert_eq!((peak % n, peak / n), (ix0, iy0));
        assert!((dirty[peak] - 2.0).abs() < 1e-8);
    }

    #[test]
    fn spectral_norm_matches_dense_eigenvalue() {
        // Small enough to build D densely from the direct DFT and iterate on the matrix.
        let (u, v, w) = baselines(300, 100.0, 9);
        let g = ImageGeometry::from_superresolution(8, 1.5, 100.0).unwrap();
        let op = MeasurementOperator::new(g, &u, &v, &w, NufftParams { epsilon: 1e-10, oversampling: 2.0 }, 1).unwrap();
        let n = g.size;
        let coord = |i: usize| (-g.pixel_rad * ((i % n) as f64 - (n / 2) as f64), g.pixel_rad * ((i / n) as f64 - (n / 2) as f64));
        let sum_w: f64 = w.iter().sum();
        let mut dense = vec![0.0; n * n * n * n];
        for p in 0..n * n {
            for q in 0..n * n {
                let ((lp, mp), (lq, mq)) = (coord(p), coord(q));
                dense[p * n * n + q] = (0..u.len())
                    .map(|k| w[k] * (2.0 * std::f64::consts::PI * (u[k] * (lp - lq) + v[k] * (mp - mq))).cos())
                    .sum::<f64>()
                    / sum_w;
            }
        }
        let dense_apply = |x: &[f64]| (0..n * n).map(|p| dot(&dense[p * n * n..(p + 1) * n * n], x)).collect::<Vec<_>>();
        // Reference: plain power iteration on the dense matrix, run to convergence.
        let mut x = vec![1.0; n * n];
        let mut reference = 0.0;
        for _ in 0..20000 {
            let y = dense_apply(&x);
            reference = dot(&y, &y).sqrt();
            x = y.into_iter().map(|v| v / reference).collect();
        }
        let ours = spectral_norm(|x| op.apply_normal(x), n * n, 1e-12, 5000);
        assert!((ours - reference).abs() < 1e-6 * reference, "{ours} vs dense {reference}");
    }

    #[test]
    fn tridiagonal_eigenvalue_of_a_known_matrix() {
        // Tridiagonal (2, -1): eigenvalues 2 - 2 cos(k pi / (n + 1)).
        let n = 30;
        let top = largest_tridiagonal_eigenvalue(&vec![2.0; n], &vec![-1.0; n - 1]);
        let expected = 2.0 - 2.0 * (n as f64 * std::f64::consts::PI / (n as f64 + 1.0)).cos();
        assert!((top - expected).abs() < 1e-12, "{top} vs {expected}");
    }

    #[test]
    fn baselines_beyond_nyquist_are_an_error_naming_the_limit() {
        let g = ImageGeometry::new(16, 1e-3).unwrap();
        let err = MeasurementOperator::new(g, &[600.0], &[0.0], &[1.0], NufftParams::default(), 1).err().unwrap().to_string();
        assert!(err.contains("Nyquist") && err.contains("arcsec"), "{err}");
        // Weighted 0 (left out by the weighting), a baseline beyond the limit changes nothing.
        let alone = MeasurementOperator::new(g, &[100.0], &[50.0], &[1.0], NufftParams::default(), 1).unwrap();
        let with = MeasurementOperator::new(g, &[100.0, 600.0], &[50.0, 0.0], &[1.0, 0.0], NufftParams::default(), 1).unwrap();
        assert!(alone.psf().iter().zip(with.psf()).all(|(a, b)| (a - b).abs() < 1e-12));
    }

    /// A wide field where the w-term matters: 48 pixels of 0.5 deg (24 deg), |w| up to the
    /// longest baseline, both signs.
    fn wide_field(m: usize, seed: u64) -> (ImageGeometry, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
        let geometry = ImageGeometry::new(48, 0.5f64.to_radians()).unwrap();
        let max_uv = 0.45 / geometry.pixel_rad;
        let (u, v, weight) = baselines(m, max_uv, seed);
        let mut rng = ChaCha8Rng::seed_from_u64(seed + 1);
        let w = (0..m).map(|_| rng.gen_range(-max_uv..max_uv)).collect();
        (geometry, u, v, w, weight)
    }

    #[test]
    fn the_w_term_operator_matches_a_direct_sum_with_the_w_term() {
        let (geometry, u, v, w, weight) = wide_field(300, 7);
        let nufft = NufftParams { epsilon: 1e-7, oversampling: 2.0 };
        let op = MeasurementOperator::for_mode(WTermMode::Auto, geometry, &u, &v, &w, &weight, nufft, 2).unwrap();
        assert!(op.w_planes().is_some_and(|p| p > 1), "auto includes the w-term on a 24 deg field: {:?}", op.w_planes());
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let vis: Vec<Complex64> = (0..u.len()).map(|_| Complex64::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0))).collect();
        let weighted: Vec<Complex64> = vis.iter().zip(&weight).map(|(v, w)| v * w).collect();
        let direct = crate::nufft::direct::adjoint_w(geometry.size, geometry.pixel_rad, &u, &v, &w, &weighted);
        let ones: Vec<Complex64> = weight.iter().map(|&w| Complex64::new(w, 0.0)).collect();
        let psf_direct = crate::nufft::direct::adjoint_w(geometry.size, geometry.pixel_rad, &u, &v, &w, &ones);
        let n = geometry.size;
        let kappa = 1.0 / psf_direct[(n / 2) * n + n / 2].re;
        let expect: Vec<f64> = direct.iter().map(|c| c.re * kappa).collect();
        let dirty = op.dirty_image(&vis);
        let err = dirty.iter().zip(&expect).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt() / expect.iter().map(|b| b * b).sum::<f64>().sqrt();
        assert!(err < 1e-6, "dirty image vs the direct sum with w: {err:e}");
        // The dirty image and PSF spread together are the two spread apart, to rounding, and
        // the PSF is the direct sum's.
        let (pair_dirty, pair_psf) = op.dirty_image_and_psf(&vis);
        let psf = op.psf();
        for (a, b) in pair_dirty.iter().zip(&dirty).chain(pair_psf.iter().zip(&psf)) {
            assert!((a - b).abs() <= 1e-12, "{a} against {b}");
        }
        let psf_expect: Vec<f64> = psf_direct.iter().map(|c| c.re * kappa).collect();
        let err = psf.iter().zip(&psf_expect).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt() / psf_expect.iter().map(|b| b * b).sum::<f64>().sqrt();
        assert!(err < 1e-6, "PSF vs the direct sum with w: {err:e}");
        // The coplanar operator is far off on this field: the test tells the two apart.
        let flat = MeasurementOperator::for_mode(WTermMode::Off, geometry, &u, &v, &w, &weight, nufft, 2).unwrap().dirty_image(&vis);
        let flat_err = flat.iter().zip(&expect).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt() / expect.iter().map(|b| b * b).sum::<f64>().sqrt();
        assert!(flat_err > 1e-2, "coplanar {flat_err:e}");
        // The prediction (MODEL_DATA, the simulator) against the direct forward sum.
        let x: Vec<f64> = (0..n * n).map(|_| rng.gen_range(0.0..1.0)).collect();
        let predicted = predict(geometry, &u, &v, &w, &x, WTermMode::Auto, nufft, 2).unwrap();
        let image: Vec<Complex64> = x.iter().map(|&p| Complex64::new(p, 0.0)).collect();
        let forward = crate::nufft::direct::forward_w(n, geometry.pixel_rad, &u, &v, &w, &image);
        let err = crate::nufft::direct::relative_error(&predicted, &forward);
        assert!(err < 1e-6, "prediction vs the direct forward sum with w: {err:e}");
        // D through the operator is kappa Re{Phi^H Phi}: the direct sums composed.
        let dx = op.apply_normal(&x);
        let fw: Vec<Complex64> = forward.iter().zip(&weight).map(|(c, w)| c * w).collect();
        let back = crate::nufft::direct::adjoint_w(n, geometry.pixel_rad, &u, &v, &w, &fw);
        let expect: Vec<f64> = back.iter().map(|c| c.re * kappa).collect();
        let err = dx.iter().zip(&expect).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt() / expect.iter().map(|b| b * b).sum::<f64>().sqrt();
        assert!(err < 1e-6, "D x vs the direct sums: {err:e}");
        // D alone, the caller's order released, is the same D to the last bit.
        let planes = op.w_planes();
        let normal = op.into_normal();
        assert_eq!(normal.w_planes(), planes);
        assert_eq!(normal.apply(&x), dx);
    }

    #[test]
    fn auto_leaves_the_w_term_out_only_where_it_is_below_the_accuracy() {
        let (geometry, u, v, mut w, weight) = wide_field(200, 3);
        let nufft = NufftParams { epsilon: 1e-6, oversampling: 2.0 };
        // |w| so small that the largest phase it adds is below epsilon: coplanar.
        let t = max_w_phase(geometry.size, geometry.pixel_rad, 1.0);
        w.iter_mut().for_each(|w| *w = 0.5e-6 / t * w.signum());
        let op = MeasurementOperator::for_mode(WTermMode::Auto, geometry, &u, &v, &w, &weight, nufft, 2).unwrap();
        assert_eq!(op.w_planes(), None);
        assert!(MeasurementOperator::for_mode(WTermMode::On, geometry, &u, &v, &w, &weight, nufft, 2).unwrap().w_planes().is_some());
        w.iter_mut().for_each(|w| *w *= 4.0);
        assert!(MeasurementOperator::for_mode(WTermMode::Auto, geometry, &u, &v, &w, &weight, nufft, 2).unwrap().w_planes().is_some());
    }
}
