//! Dirty image and PSF from visibilities: the first products of every imaging run.
//!
//! Ties the numerics together (pixel size, weighting, operator) without knowing about files:
//! the CLI and the pipeline stages call this with visibilities they read.

use crate::nufft::NufftParams;
use crate::operator::{ImageGeometry, MeasurementOperator};
use crate::vis::{chunk_weights, Visibilities};
use crate::weighting::{DensityGrid, UvControls, UvCounts, UvShape, Weighting, DEFAULT_GRID_FACTOR};
use crate::{Error, Result};

pub use crate::operator::{PixelScale, WTermMode, DEFAULT_SUPERRESOLUTION};

/// The image every stage of a pipeline shares (its `image` section): weighting, gridder and
/// a trained network series must all agree on it, so it is stated once.
#[derive(Clone, Debug, serde::Deserialize, serde::Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ImageConfig {
    /// Pixels per side.
    pub size: usize,
    /// Super-resolution factor (see [`PixelScale::SuperResolution`]);
    /// [`DEFAULT_SUPERRESOLUTION`] when neither it nor `pixel_arcsec` is given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub superresolution: Option<f64>,
    /// A fixed pixel size (arcsec), instead of the super-resolution factor.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_arcsec: Option<f64>,
    /// The longest baseline (wavelengths) the super-resolution factor is applied to, in place
    /// of each job's own: jobs imaged apart (the parts of a split on a cluster) on one grid.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub longest_baseline: Option<f64>,
}

impl ImageConfig {
    pub fn pixel_scale(&self) -> PixelScale {
        match self.pixel_arcsec {
            Some(p) => PixelScale::Arcsec(p),
            None => PixelScale::SuperResolution(self.superresolution.unwrap_or(DEFAULT_SUPERRESOLUTION)),
        }
    }
}

/// Parameters of a dirty image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DirtyParams {
    pub size: usize,
    pub pixel: PixelScale,
    pub weighting: Weighting,
    pub grid_factor: f64,
    pub nufft: NufftParams,
    /// The w-term (see [`WTermMode`]).
    pub w_term: WTermMode,
    pub threads: usize,
    /// uv cuts and tapers (none by default).
    pub uv: UvControls,
}

impl Default for DirtyParams {
    fn default() -> Self {
        DirtyParams {
            size: 512,
            pixel: PixelScale::default(),
            weighting: Weighting::Briggs { robust: 0.0 },
            grid_factor: DEFAULT_GRID_FACTOR,
            nufft: NufftParams::default(),
            w_term: WTermMode::Auto,
            threads: 0,
            uv: UvControls::default(),
        }
    }
}

impl DirtyParams {
    /// The image geometry for these visibilities (the super-resolution factor applies to the
    /// longest baseline `maxuv_l` keeps).
    pub fn geometry(&self, vis: &Visibilities) -> Result<ImageGeometry> {
        self.geometry_for(self.uv.longest_kept(vis.max_uv()))
    }

    /// The image geometry for samples whose longest baseline is `max_uv` wavelengths.
    pub fn geometry_for(&self, max_uv: f64) -> Result<ImageGeometry> {
        self.pixel.geometry(self.size, max_uv)
    }
}

/// The measurement operator with its weights, and the dirty image and PSF it gives.
pub struct DirtyProducts {
    pub(crate) operator: MeasurementOperator,
    pub dirty: Vec<f64>,
    pub psf: Vec<f64>,
    /// Total weight per visibility (natural x imaging), in the visibilities' order.
    pub weight: Vec<f64>,
}

/// Total weights (natural x imaging, cut and tapered by `uv`) of `vis` on `geometry`.
pub(crate) fn total_weights(vis: &Visibilities, geometry: ImageGeometry, weighting: Weighting, grid_factor: f64, uv: &UvControls) -> Result<Vec<f64>> {
    let shape = UvShape::new(uv, geometry.size, grid_factor, geometry.pixel_rad)?;
    if weighting == Weighting::Given {
        return chunk_weights(&vis.chunk(0..vis.len()), geometry, &DensityGrid::new(weighting, geometry.size, grid_factor)?.finish().with_uv(shape));
    }
    let point = |k: usize| geometry.uv_to_phase(vis.u[k], vis.v[k]);
    crate::weighting::total_weights(point, &vis.weight, geometry.size, weighting, grid_factor, shape)
}

/// How many samples of `vis` the uv cuts of `params` (and the grid's edge) leave out on
/// `geometry`, logged where any is; an error where none would remain.
fn count_left_out(vis: &Visibilities, geometry: ImageGeometry, params: &DirtyParams) -> Result<()> {
    let shape = UvShape::new(&params.uv, geometry.size, params.grid_factor, geometry.pixel_rad)?;
    if shape.is_none() && vis.max_uv() < 0.5 / geometry.pixel_rad {
        return Ok(());
    }
    let mut counts = UvCounts::default();
    (0..vis.len()).for_each(|k| counts.add(&shape, geometry.uv_to_phase(vis.u[k], vis.v[k])));
    let limit_l = 0.5 / geometry.pixel_rad;
    counts.check_kept(limit_l, geometry.pixel_arcsec())?;
    if let Some(text) = counts.describe(limit_l, geometry.pixel_arcsec()) {
        log::info!("{text}");
    }
    Ok(())
}

/// Dirty image and PSF (both N x N, PSF peak 1 at (N/2, N/2)).
pub fn dirty_image(vis: &Visibilities, params: &DirtyParams) -> Result<DirtyProducts> {
    if vis.is_empty() {
        return Err(Error::parameter("visibilities", "no usable visibilities to image (all flagged or empty?)"));
    }
    let (operator, weight) = weighted_operator(vis, params)?;
    let dirty = operator.dirty_image(&vis.vis);
    let psf = operator.psf();
    Ok(DirtyProducts { operator, dirty, psf, weight })
}

/// The measurement operator of `vis` on the image `params` describe, and the total weights it
/// applies.
fn weighted_operator(vis: &Visibilities, params: &DirtyParams) -> Result<(MeasurementOperator, Vec<f64>)> {
    let geometry = params.geometry(vis)?;
    count_left_out(vis, geometry, params)?;
    let weight = total_weights(vis, geometry, params.weighting, params.grid_factor, &params.uv)?;
    let operator = MeasurementOperator::for_mode(params.w_term, geometry, &vis.u, &vis.v, &vis.w, &weight, params.nufft, params.threads)?;
    Ok((operator, weight))
}

/// The normal operator `D = kappa Re{Phi^H W Phi}` of `vis` on the image `params` describe
/// (its weights and w-term rule): `D x` is the dirty image the sky `x` (Jy/pixel) would give.
pub struct NormalOperator {
    operator: MeasurementOperator,
}

impl NormalOperator {
    pub fn new(vis: &Visibilities, params: &DirtyParams) -> Result<NormalOperator> {
        Ok(NormalOperator { operator: weighted_operator(vis, params)?.0 })
    }

    /// `D x` (`x`: N x N, row-major).
    pub fn apply(&self, x: &[f64]) -> Vec<f64> {
        self.operator.apply_normal(x)
    }

    /// `||D||` (its largest eigenvalue) by power iteration, to relative `tolerance`.
    pub fn norm(&self, tolerance: f64, max_iterations: usize) -> f64 {
        crate::operator::spectral_norm(|x| self.apply(x), self.operator.geometry().pixels(), tolerance, max_iterations)
    }
}

/// What coplanar imaging leaves out of a field: the w-term's phase `2 pi |w| (1 - n)` at the
/// image's corners (l = m = N/2 pixels) for the largest |w| of the data.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct WTerm {
    pub max_abs_w: f64,
    pub max_phase_rad: f64,
}

impl WTerm {
    /// Phase (radians) beyond which the uncorrected w-term is warned about: the largest |w|
    /// turns a corner sample's phase by this much (a loss of about 1 % of a corner source's
    /// peak for a phase spread this wide; the error grows as the square of the field).
    pub const WARN_PHASE_RAD: f64 = 0.3;

    #[cfg(test)]
    pub fn of(vis: &Visibilities, geometry: ImageGeometry) -> WTerm {
        let max_abs_w = vis.w.iter().fold(0.0f64, |m, &w| m.max(w.abs()));
        let half = 0.5 * geometry.size as f64 * geometry.pixel_rad;
        let n = (1.0 - 2.0 * half * half).max(0.0).sqrt();
        WTerm { max_abs_w, max_phase_rad: 2.0 * std::f64::consts::PI * max_abs_w * (1.0 - n) }
    }

    /// The warning for a field where the w-term matters (none where it does not).
    pub fn warning(&self, geometry: ImageGeometry) -> Option<String> {
        (self.max_phase_rad > Self::WARN_PHASE_RAD).then(|| {
            format!(
                "the w-term is not corrected (coplanar imaging): over this {:.2} deg field the largest |w| ({:.3e} wavelengths) turns the phase by up to {:.2} rad at the image's corners, so emission away from the centre is blurred and dimmed against a w-corrected image (WSClean's); image a smaller field, or expect errors growing towards the edges",
                geometry.pixel_rad.to_degrees() * geometry.size as f64,
                self.max_abs_w,
                self.max_phase_rad
            )
        })
    }
}

#[cfg(test)]
mod w_term_tests {
    use super::*;

    #[test]
    fn the_w_term_warning_follows_field_and_w() {
        let vis = |w: f64| Visibilities { u: vec![1.0], v: vec![1.0], w: vec![w, -2.0 * w], vis: vec![Default::default(); 2], weight: vec![1.0; 2], frequency: vec![1e8; 2], ..Visibilities::default() };
        // LOFAR-like: |w| 2e3 wavelengths, 3.2 deg field: n - 1 ~ -1.6e-3 at the corners.
        let wide = ImageGeometry::new(512, 3.2f64.to_radians() / 512.0).unwrap();
        let t = WTerm::of(&vis(1e3), wide);
        assert_eq!(t.max_abs_w, 2e3);
        let half = 1.6f64.to_radians();
        let expected = 2.0 * std::f64::consts::PI * 2e3 * (1.0 - (1.0 - 2.0 * half * half).sqrt());
        assert!((t.max_phase_rad - expected).abs() < 1e-9 * expected && t.max_phase_rad > 1.0);
        assert!(t.warning(wide).unwrap().contains("w-term is not corrected"));
        // A VLA-like narrow field: nothing to say.
        let narrow = ImageGeometry::new(512, 0.1f64.to_radians() / 3600.0).unwrap();
        assert!(WTerm::of(&vis(1.7e5), narrow).warning(narrow).is_none());
    }
}

