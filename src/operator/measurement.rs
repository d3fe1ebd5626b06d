//! The measurement operator `Phi = diag(sqrt(omega)) G F Z` and what imaging derives from it:
//! the dirty image, the PSF, `kappa`, the normal operator `D = kappa Re{Phi^H Phi}` (by a NUFFT
//! round trip or, exactly for coplanar data, as a convolution with the 2N x 2N PSF) and its
//! spectral norm.
//!
//! The operator is coplanar (a 2D NUFFT) or includes the w-term `exp(2 pi i w (n - 1))` (by
//! w-gridding, `crate::nufft::wgrid`), as [`WTermMode`] decides from the data and the field:
//! where the w-term turns no phase by more than the NUFFT's accuracy, the two are the same
//! operator to that accuracy, and the coplanar one is cheaper and has an exact Toeplitz form.
//!
//! Conventions (see `docs/conventions.md`): a source of flux S at direction cosines (l, m)
//! has visibility `S exp(+2 pi i (u l + v m))`; images are row-major `x[iy * N + ix]` with
//! `l = -pixel (ix - N/2)` (RA increases to the left, as FITS with CDELT1 < 0 shows it) and
//! `m = pixel (iy - N/2)`. `omega_k` is the total weight of visibility k: natural weight times
//! imaging weight (the reference code's `(nW * nWimag)^2`).

use crate::fft2::Fft2;
use crate::nufft::wgrid::{max_w_phase, WGridPlan};
use crate::nufft::{ChunkedAdjoint, Nufft2d, NufftParams};
use crate::{Error, Result};
use num_complex::{Complex32, Complex64};
use rayon::prelude::*;
use rustfft::FftDirection;

/// Image size and pixel scale.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageGeometry {
    /// Pixels per side (even).
    pub size: usize,
    /// Pixel size in radians.
    pub pixel_rad: f64,
}

impl ImageGeometry {
    /// Pixel size from the super-resolution factor: `pixel = 1 / (SR * 2 * max_uv)` radians
    /// (max_uv in wavelengths), i.e. the longest baseline is sampled SR times finer than
    /// Nyquist.
    pub fn from_superresolution(size: usize, superresolution: f64, max_uv: f64) -> Result<ImageGeometry> {
        if !(superresolution >= 1.0) || !superresolution.is_finite() {
            return Err(Error::parameter(
                "superresolution",
                format!("expected a factor >= 1 (pixel no coarser than Nyquist), got {superresolution}"),
            ));
        }
        if !(max_uv > 0.0) || !max_uv.is_finite() {
            return Err(Error::parameter("uv coverage", "no baseline longer than zero: cannot derive a pixel size"));
        }
        Self::new(size, 1.0 / (superresolution * 2.0 * max_uv))
    }

    pub fn from_arcsec(size: usize, pixel_arcsec: f64) -> Result<ImageGeometry> {
        Self::new(size, pixel_arcsec.to_radians() / 3600.0)
    }

    pub fn new(size: usize, pixel_rad: f64) -> Result<ImageGeometry> {
        if size < crate::limits::MIN_IMAGE_SIZE || !size.is_multiple_of(2) {
            return Err(Error::parameter("size", format!("expected an even image size of at least {} pixels, got {size}", crate::limits::MIN_IMAGE_SIZE)));
        }
        if !(pixel_rad > 0.0) || !pixel_rad.is_finite() {
            return Err(Error::parameter("pixel size", format!("expected a positive pixel size, got {pixel_rad} rad")));
        }
        // The sine projection holds where l^2 + m^2 < 1: at the image's corners, a field
        // (N x pixel) under sqrt(2) rad, about 81 deg.
        let field = pixel_rad * size as f64;
        if 2.0 * (0.5 * field).powi(2) >= 1.0 {
            return Err(Error::parameter(
                "pixel size",
                format!(
                    "a field of {size} x {:.4} deg = {:.1} deg is wider than the sine projection allows (l^2 + m^2 < 1 at the corners: under {:.1} deg): use fewer or smaller pixels",
                    pixel_rad.to_degrees(),
                    field.to_degrees(),
                    std::f64::consts::SQRT_2.to_degrees()
                ),
            ));
        }
        Ok(ImageGeometry { size, pixel_rad })
    }

    pub fn pixel_arcsec(&self) -> f64 {
        self.pixel_rad.to_degrees() * 3600.0
    }

    pub fn pixels(&self) -> usize {
        self.size * self.size
    }

    /// The operator's uv coordinates in radians per pixel, `(x, y) = (-2 pi u dl, 2 pi v dl)`:
    /// the sign of x makes RA increase towards lower pixel index.
    pub fn uv_to_phase(&self, u: f64, v: f64) -> (f64, f64) {
        let s = 2.0 * std::f64::consts::PI * self.pixel_rad;
        (-s * u, s * v)
    }

    /// The same geometry with twice the field of view (for the 2N PSF).
    pub fn doubled(&self) -> ImageGeometry {
        ImageGeometry { size: 2 * self.size, pixel_rad: self.pixel_rad }
    }
}

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
    /// zero excludes a visibility). Baselines beyond the image's Nyquist limit (`|u| >= 1 / (2
    /// pixel)`) would alias and are rejected: choose a smaller pixel.
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
        let mut vis = self.forward_sorted(x);
        let k = self.kappa;
        vis.par_iter_mut().zip(self.weight.par_iter()).for_each(|(y, &w)| *y *= w * k);
        self.back_project_sorted(&vis)
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
/// within the image's Nyquist limit (`|u| >= 1 / (2 pixel)` would alias), weights finite and
/// not negative.
pub(crate) fn check_points(geometry: ImageGeometry, u: &[f64], v: &[f64], weight: &[f64]) -> Result<()> {
    if u.len() != v.len() || u.len() != weight.len() {
        return Err(Error::parameter("visibilities", "u, v and weight arrays differ in length"));
    }
    let limit = 0.5 / geometry.pixel_rad;
    let beyond = u.iter().zip(v).filter(|(u, v)| u.abs() >= limit || v.abs() >= limit).count();
    if beyond > 0 {
        let max_uv = u.iter().zip(v).map(|(u, v)| u.abs().max(v.abs())).fold(0.0, f64::max);
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

/// Points per chunk of [`grid_in_chunks`]: a sixteenth of the points, so that the chunk's
/// sorting and values (about 70 bytes a point) stay small beside the caller's arrays, but no
/// fewer than 2^16, below which merging the tiles into the grid would cost more than spreading
/// the points, and no more than 2^20, beyond which larger chunks no longer save time.
/// Points per chunk when `n` points are gridded in chunks (also what the gridder bench times).
pub(crate) fn chunk_points(n: usize) -> usize {
    (n / 16).clamp(1 << 16, 1 << 20)
}

/// `Re{Phi_raw^H c_t}` on `geometry` for each `t < transforms`, `c_t[k] = value(t, k)`, gridded
/// in chunks of points (see [`crate::nufft::ChunkedAdjoint`]): no plan for all the points is
/// ever held, so beside the caller's arrays memory is the grids and one chunk.
#[allow(clippy::too_many_arguments)]
fn grid_in_chunks(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    transforms: usize,
    value: impl Fn(usize, usize) -> Complex64 + Sync,
    nufft: NufftParams,
    threads: usize,
    chunk: usize,
) -> Result<Vec<Vec<f64>>> {
    check_points(geometry, u, v, weight)?;
    let mut gridder = ChunkedAdjoint::new(geometry.size, geometry.size, transforms, nufft, threads)?;
    add_in_steps(&mut gridder, geometry, u, v, chunk, value)?;
    Ok(gridder.finish().into_iter().map(|image| image.into_iter().map(|c| c.re).collect()).collect())
}

/// Adds the samples at `(u, v)` (wavelengths) to `gridder`, `step` at a time (each step's
/// sorting is its memory), `value(t, k)` for transform `t` of sample `k`.
fn add_in_steps(
    gridder: &mut ChunkedAdjoint,
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    step: usize,
    value: impl Fn(usize, usize) -> Complex64 + Sync,
) -> Result<()> {
    for start in (0..u.len()).step_by(step) {
        let end = (start + step).min(u.len());
        let (x, y): (Vec<f64>, Vec<f64>) =
            u[start..end].iter().zip(&v[start..end]).map(|(&u, &v)| geometry.uv_to_phase(u, v)).unzip();
        gridder.add(&x, &y, |t, k| value(t, start + k))?;
    }
    Ok(())
}

/// The dirty image, PSF and `kappa` of [`MeasurementOperator`] (to the NUFFT's accuracy; the
/// sums run in another order), for callers that need no operator afterwards: the points are
/// gridded in chunks, so memory beyond the caller's arrays does not grow with their number.
pub fn dirty_and_psf(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    vis: &[impl Visibility],
    nufft: NufftParams,
    threads: usize,
) -> Result<DirtyAndPsf> {
    dirty_and_psf_in_chunks(geometry, u, v, weight, vis, nufft, threads, chunk_points(u.len()))
}

#[allow(clippy::too_many_arguments)]
fn dirty_and_psf_in_chunks(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    vis: &[impl Visibility],
    nufft: NufftParams,
    threads: usize,
    chunk: usize,
) -> Result<DirtyAndPsf> {
    if vis.len() != weight.len() {
        return Err(Error::parameter("visibilities", "visibility and weight arrays differ in length"));
    }
    let value = |t: usize, k: usize| if t == 0 { vis[k].to_c64() * weight[k] } else { Complex64::new(weight[k], 0.0) };
    let [mut dirty, mut psf]: [Vec<f64>; 2] = grid_in_chunks(geometry, u, v, weight, 2, value, nufft, threads, chunk)?
        .try_into()
        .expect("two transforms");
    let kappa = normalise_by_psf_peak(geometry.size, &mut dirty, &mut psf)?;
    Ok(DirtyAndPsf { dirty, psf, kappa })
}

/// Scales `dirty` and the `n x n` `psf` by `kappa = 1 / psf peak` (at `(n/2, n/2)`) and returns
/// it; an error where the peak is not positive (every weight zero).
pub fn normalise_by_psf_peak(n: usize, dirty: &mut [f64], psf: &mut [f64]) -> Result<f64> {
    let peak = psf.get((n / 2) * n + n / 2).copied().unwrap_or(0.0);
    if !(peak > 0.0) {
        return Err(Error::parameter("weight", "all visibilities have zero weight: nothing to image"));
    }
    let kappa = 1.0 / peak;
    dirty.iter_mut().chain(psf.iter_mut()).for_each(|p| *p *= kappa);
    Ok(kappa)
}

/// What [`dirty_and_psf`] gives.
pub struct DirtyAndPsf {
    /// `kappa Re{Phi_raw^H (omega y)}`.
    pub dirty: Vec<f64>,
    /// `kappa Re{Phi^H Phi delta}`, peak 1 at `(N/2, N/2)`.
    pub psf: Vec<f64>,
    pub kappa: f64,
}

/// The PSF over twice the field of view (`2N x 2N`, centre at `(N, N)`) for the same
/// visibilities, scaled by `kappa` of the N x N operator: the kernel of the Toeplitz form of D.
/// Gridded in chunks (see [`dirty_and_psf`]).
pub fn doubled_psf(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    kappa: f64,
    nufft: NufftParams,
    threads: usize,
) -> Result<Vec<f64>> {
    doubled_psf_of(geometry, u, v, weight, |_| Complex64::new(1.0, 0.0), kappa, nufft, threads)
}

/// [`doubled_psf`] of the samples' weights times `factor(k)` (complex: the real part of the
/// transform is kept, as for the PSF): the kernels of [`crate::operator::taylor`].
#[allow(clippy::too_many_arguments)]
pub fn doubled_psf_of(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    factor: impl Fn(usize) -> Complex64 + Sync,
    kappa: f64,
    nufft: NufftParams,
    threads: usize,
) -> Result<Vec<f64>> {
    let value = |_, k: usize| factor(k) * (weight[k] * kappa);
    let [psf]: [Vec<f64>; 1] = grid_in_chunks(geometry.doubled(), u, v, weight, 1, value, nufft, threads, chunk_points(u.len()))?
        .try_into()
        .expect("one transform");
    Ok(psf)
}

/// [`doubled_psf_of`] of samples given a chunk at a time, as a table is read (the kernels of
/// [`crate::operator::taylor`] where the samples are not held): memory is the grid and one chunk.
pub struct DoubledKernelGridder {
    geometry: ImageGeometry,
    adjoint: ChunkedAdjoint,
}

impl DoubledKernelGridder {
    pub fn new(geometry: ImageGeometry, nufft: NufftParams, threads: usize) -> Result<DoubledKernelGridder> {
        let doubled = geometry.doubled();
        Ok(DoubledKernelGridder { geometry, adjoint: ChunkedAdjoint::new(doubled.size, doubled.size, 1, nufft, threads)? })
    }

    /// Adds samples at `(u, v)` (wavelengths) with total weights `weight`, each times
    /// `factor(k)`. Baselines beyond the image's Nyquist limit are refused.
    pub fn add(&mut self, u: &[f64], v: &[f64], weight: &[f64], factor: impl Fn(usize) -> Complex64 + Sync) -> Result<()> {
        check_points(self.geometry, u, v, weight)?;
        // As ImageGridder::add: the caller's chunk whole, up to where larger ones save no time.
        add_in_steps(&mut self.adjoint, self.geometry, u, v, u.len().clamp(1, 1 << 20), |_, k| factor(k) * weight[k])
    }

    /// The kernel (`2N x 2N`, centre at `(N, N)`), scaled by `kappa`.
    pub fn finish(self, kappa: f64) -> Vec<f64> {
        self.adjoint.finish().into_iter().next().unwrap_or_default().into_iter().map(|c| c.re * kappa).collect()
    }
}

/// The dirty image, the PSF, the 2N PSF and `kappa` of samples given a chunk at a time, as a
/// table is read: one pass over the data makes every image the imaging needs, and memory is
/// the grids and one chunk, whatever the number of samples. The same sums as [`dirty_and_psf`]
/// and [`doubled_psf`] (to the order of floating-point additions).
pub struct ImageGridder {
    geometry: ImageGeometry,
    /// `None`: the 2N PSF only (the dirty image is made elsewhere: with the w-term).
    dirty: Option<ChunkedAdjoint>,
    psf_2n: ChunkedAdjoint,
    samples: usize,
}

/// What [`ImageGridder`] makes.
pub struct GriddedImages {
    /// Empty where the gridder made the 2N PSF only.
    pub dirty: Vec<f64>,
    /// Peak 1 at `(N/2, N/2)`; empty where the gridder made the 2N PSF only.
    pub psf: Vec<f64>,
    /// `2N x 2N`, centre at `(N, N)`, scaled by the same `kappa`.
    pub psf_2n: Vec<f64>,
    pub kappa: f64,
}

impl ImageGridder {
    pub fn new(geometry: ImageGeometry, nufft: NufftParams, threads: usize) -> Result<ImageGridder> {
        let n = geometry.size;
        Ok(ImageGridder {
            geometry,
            dirty: Some(ChunkedAdjoint::new(n, n, 2, nufft, threads)?),
            psf_2n: ChunkedAdjoint::new(2 * n, 2 * n, 1, nufft, threads)?,
            samples: 0,
        })
    }

    /// A gridder of the (coplanar) 2N PSF alone.
    pub fn doubled_psf_only(geometry: ImageGeometry, nufft: NufftParams, threads: usize) -> Result<ImageGridder> {
        let n = geometry.size;
        Ok(ImageGridder { geometry, dirty: None, psf_2n: ChunkedAdjoint::new(2 * n, 2 * n, 1, nufft, threads)?, samples: 0 })
    }

    /// Adds samples at `(u, v)` (wavelengths) with total weights `weight` and values `vis`.
    /// Baselines beyond the image's Nyquist limit are refused (see [`MeasurementOperator::new`]).
    pub fn add(&mut self, u: &[f64], v: &[f64], weight: &[f64], vis: &[impl Visibility]) -> Result<()> {
        check_points(self.geometry, u, v, weight)?;
        if vis.len() != weight.len() {
            return Err(Error::parameter("visibilities", "visibility and weight arrays differ in length"));
        }
        // The caller's chunk is gridded whole (its size sets the sorting's memory), up to the
        // size beyond which larger chunks no longer save time.
        let step = u.len().clamp(1, 1 << 20);
        for start in (0..u.len()).step_by(step) {
            let end = (start + step).min(u.len());
            let (x, y): (Vec<f64>, Vec<f64>) =
                u[start..end].iter().zip(&v[start..end]).map(|(&u, &v)| self.geometry.uv_to_phase(u, v)).unzip();
            if let Some(dirty) = &mut self.dirty {
                let value = |t: usize, k: usize| if t == 0 { vis[start + k].to_c64() * weight[start + k] } else { Complex64::new(weight[start + k], 0.0) };
                dirty.add(&x, &y, value)?;
            }
            self.psf_2n.add(&x, &y, |_, k| Complex64::new(weight[start + k], 0.0))?;
        }
        self.samples += u.len();
        Ok(())
    }

    /// The images, normalised by `kappa` (`None`: from the N PSF's peak, as the operator's; a
    /// gridder of the 2N PSF alone must be given it).
    pub fn finish(self, kappa: Option<f64>) -> Result<GriddedImages> {
        let n = self.geometry.size;
        if self.samples == 0 {
            return Err(Error::parameter("weight", "all visibilities have zero weight: nothing to image"));
        }
        let (mut dirty, mut psf, mut psf_2n) = self.unnormalised();
        let kappa = match kappa {
            Some(kappa) => {
                dirty.iter_mut().chain(psf.iter_mut()).for_each(|p| *p *= kappa);
                kappa
            }
            None => normalise_by_psf_peak(n, &mut dirty, &mut psf)?,
        };
        psf_2n.iter_mut().for_each(|p| *p *= kappa);
        Ok(GriddedImages { dirty, psf, psf_2n, kappa })
    }

    /// The dirty image, PSF and 2N PSF as gridded, not normalised (empty dirty image and PSF
    /// for a gridder of the 2N PSF alone): one part of images summed over parts.
    pub fn unnormalised(self) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let real = |image: Vec<Complex64>| -> Vec<f64> { image.into_iter().map(|c| c.re).collect() };
        let (dirty, psf) = match self.dirty {
            Some(d) => {
                let mut images = d.finish().into_iter().map(real);
                (images.next().unwrap_or_default(), images.next().unwrap_or_default())
            }
            None => (Vec::new(), Vec::new()),
        };
        let psf_2n = real(self.psf_2n.finish().into_iter().next().unwrap_or_default());
        (dirty, psf, psf_2n)
    }
}

/// `D x = kappa Re{Phi^H Phi x}` as a linear convolution with the 2N x 2N PSF, by FFT:
/// `crop(IFFT(FFT(pad(x)) FFT(psf_2N)))`. Exact (to NUFFT accuracy) for coplanar data, and
/// once built its cost no longer depends on the number of visibilities.
pub struct PsfConvolution {
    size: usize,
    /// FFT of the 2N x 2N PSF, divided by (2N)^2 for the unnormalised inverse FFT, transposed
    /// as the image's spectrum is (`Fft2::process_from_rows_transposed`).
    kernel_hat: Vec<Complex64>,
    forward: Fft2,
    inverse: Fft2,
    /// The padded image and the transposes' scratch, kept from one application to the next
    /// (made afresh, their pages were mapped and zeroed at every update).
    buffers: std::sync::Mutex<(Vec<Complex64>, Vec<Complex64>)>,
}

impl PsfConvolution {
    /// `psf_2n`: the doubled PSF (`2N x 2N`, centre at `(N, N)`).
    pub fn new(size: usize, psf_2n: &[f64]) -> Result<PsfConvolution> {
        let m = 2 * size;
        if psf_2n.len() != m * m {
            return Err(Error::parameter("psf", format!("expected a {m} x {m} PSF for a {size} x {size} image, got {} pixels", psf_2n.len())));
        }
        let forward = Fft2::new(m, m, FftDirection::Forward);
        let inverse = Fft2::new(m, m, FftDirection::Inverse);
        let scale = 1.0 / (m * m) as f64;
        let mut kernel_hat: Vec<Complex64> = psf_2n.iter().map(|&p| Complex64::new(p * scale, 0.0)).collect();
        forward.process_from_rows_transposed(&mut kernel_hat, m, &mut vec![Complex64::default(); m * m]);
        Ok(PsfConvolution { size, kernel_hat, forward, inverse, buffers: Default::default() })
    }

    pub fn size(&self) -> usize {
        self.size
    }

    /// `D x` for an N x N image.
    pub fn apply(&self, x: &[f64]) -> Vec<f64> {
        let (n, m) = (self.size, 2 * self.size);
        assert_eq!(x.len(), n * n, "image size");
        // A poisoned lock only means an earlier application panicked: its arrays are rewritten here.
        let mut buffers = self.buffers.lock().unwrap_or_else(|e| e.into_inner());
        let (padded, scratch) = &mut *buffers;
        padded.resize(m * m, Complex64::default());
        scratch.resize(m * m, Complex64::default());
        padded.par_chunks_mut(m).enumerate().for_each(|(iy, row)| {
            if iy < n {
                row[..n].iter_mut().zip(&x[iy * n..][..n]).for_each(|(p, &v)| *p = Complex64::new(v, 0.0));
                row[n..].fill(Complex64::default());
            } else {
                row.fill(Complex64::default());
            }
        });
        // The image fills the first N rows; the result is read from the last N.
        self.forward.process_from_rows_transposed(padded, n, scratch);
        padded.par_iter_mut().zip(self.kernel_hat.par_iter()).for_each(|(a, k)| *a *= k);
        self.inverse.process_transposed_to_rows(padded, n, scratch);
        // Linear convolution with a kernel centred at (N, N): output pixel p sits at p + N.
        let mut out = vec![0.0; n * n];
        out.par_chunks_mut(n).enumerate().for_each(|(iy, row)| {
            row.iter_mut().zip(&padded[(iy + n) * m + n..][..n]).for_each(|(o, p)| *o = p.re);
        });
        out
    }
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
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Random baselines in a disc of radius `max_uv` wavelengths, random positive weights.
    fn baselines(m: usize, max_uv: f64, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
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

    fn setup(eps: f64) -> (ImageGeometry, Vec<f64>, Vec<f64>, Vec<f64>, MeasurementOperator) {
        let (u, v, w) = baselines(4000, 1000.0, 1);
        let geometry = ImageGeometry::from_superresolution(32, 1.5, 1000.0).unwrap();
        let op = MeasurementOperator::new(geometry, &u, &v, &w, NufftParams { epsilon: eps, oversampling: 2.0 }, 2).unwrap();
        (geometry, u, v, w, op)
    }

    fn dot(a: &[f64], b: &[f64]) -> f64 {
        a.iter().zip(b).map(|(a, b)| a * b).sum()
    }

    fn random_image(n: usize, seed: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| rng.gen_range(0.0..1.0)).collect()
    }

    #[test]
    fn dirty_and_psf_in_chunks_match_the_operator() {
        let (g, u, v, w, op) = setup(1e-9);
        let vis: Vec<Complex64> = u.iter().zip(&v).map(|(&u, &v)| Complex64::new((u * 1e-3).cos(), (v * 2e-3).sin())).collect();
        let nufft = NufftParams { epsilon: 1e-9, oversampling: 2.0 };
        let (dirty, psf) = (op.dirty_image(&vis), op.psf());
        // One chunk, several of uneven size (the last one short), and one point per chunk.
        for chunk in [u.len(), 999, 1] {
            let chunked = dirty_and_psf_in_chunks(g, &u, &v, &w, &vis, nufft, 2, chunk).unwrap();
            let max_diff = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(max_diff(&chunked.dirty, &dirty) < 1e-12, "chunk {chunk}: dirty differs by {}", max_diff(&chunked.dirty, &dirty));
            assert!(max_diff(&chunked.psf, &psf) < 1e-12, "chunk {chunk}: psf differs by {}", max_diff(&chunked.psf, &psf));
            assert!((chunked.kappa / op.kappa() - 1.0).abs() < 1e-13);
        }
        let err = dirty_and_psf(g, &u, &v, &vec![0.0; w.len()], &vis, nufft, 2).err().unwrap().to_string();
        assert!(err.contains("zero weight"), "{err}");
        let err = dirty_and_psf(g, &u, &v, &w, &vis[1..], nufft, 2).err().unwrap().to_string();
        assert!(err.contains("differ in length"), "{err}");
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
    fn toeplitz_and_nufft_normal_operators_agree_and_are_symmetric() {
        let (g, u, v, w, op) = setup(1e-9);
        let psf2 = doubled_psf(g, &u, &v, &w, op.kappa(), NufftParams { epsilon: 1e-9, oversampling: 2.0 }, 2).unwrap();
        let conv = PsfConvolution::new(g.size, &psf2).unwrap();
        let x = random_image(g.pixels(), 5);
        let y = random_image(g.pixels(), 6);
        let d_nufft = op.apply_normal(&x);
        let d_toeplitz = conv.apply(&x);
        let diff = d_nufft.iter().zip(&d_toeplitz).map(|(a, b)| (a - b) * (a - b)).sum::<f64>().sqrt();
        let norm = d_nufft.iter().map(|a| a * a).sum::<f64>().sqrt();
        assert!(diff / norm <= 1e-6, "relative difference {}", diff / norm);
        let by_nufft = |x: &[f64]| op.apply_normal(x);
        let by_fft = |x: &[f64]| conv.apply(x);
        let forms: [&dyn Fn(&[f64]) -> Vec<f64>; 2] = [&by_nufft, &by_fft];
        for apply in forms {
            let lhs = dot(&apply(&x), &y);
            let rhs = dot(&x, &apply(&y));
            assert!((lhs - rhs).abs() <= 1e-9 * lhs.abs(), "<Dx,y> {lhs} vs <x,Dy> {rhs}");
        }
        // D applied to a centred delta is the PSF.
        let n = g.size;
        let mut delta = vec![0.0; n * n];
        delta[(n / 2) * n + n / 2] = 1.0;
        let psf = op.psf();
        let d_delta = conv.apply(&delta);
        assert!(psf.iter().zip(&d_delta).all(|(a, b)| (a - b).abs() < 1e-7));
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
