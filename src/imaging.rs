//! Dirty image and PSF from visibilities: the first products of every imaging run.
//!
//! Ties the numerics together (pixel size, weighting, operator) without knowing about files:
//! the CLI and the pipeline stages call this with visibilities they read.

use crate::nufft::NufftParams;
use crate::operator::{ImageGeometry, MeasurementOperator};
use crate::vis::Visibilities;
use crate::weighting::{Weighting, DEFAULT_GRID_FACTOR};
use crate::{Error, Result};

/// How the pixel size is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PixelScale {
    /// `pixel = 1 / (SR * 2 * max_uv)` (the reference's super-resolution factor).
    SuperResolution(f64),
    /// A fixed pixel size in arcseconds.
    Arcsec(f64),
}

impl Default for PixelScale {
    fn default() -> Self {
        PixelScale::SuperResolution(1.5)
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
    pub threads: usize,
}

impl Default for DirtyParams {
    fn default() -> Self {
        DirtyParams {
            size: 512,
            pixel: PixelScale::default(),
            weighting: Weighting::Briggs { robust: 0.0 },
            grid_factor: DEFAULT_GRID_FACTOR,
            nufft: NufftParams::default(),
            threads: 0,
        }
    }
}

impl DirtyParams {
    /// The image geometry for these visibilities.
    pub fn geometry(&self, vis: &Visibilities) -> Result<ImageGeometry> {
        match self.pixel {
            PixelScale::SuperResolution(sr) => ImageGeometry::from_superresolution(self.size, sr, vis.max_uv()),
            PixelScale::Arcsec(p) => ImageGeometry::from_arcsec(self.size, p),
        }
    }
}

/// The measurement operator with its weights, and the dirty image and PSF it gives.
pub struct DirtyProducts {
    pub operator: MeasurementOperator,
    pub dirty: Vec<f64>,
    pub psf: Vec<f64>,
    /// Total weight per visibility (natural x imaging), in the visibilities' order.
    pub weight: Vec<f64>,
}

/// Total weights (natural x imaging) of `vis` on `geometry`.
pub fn total_weights(vis: &Visibilities, geometry: ImageGeometry, weighting: Weighting, grid_factor: f64) -> Result<Vec<f64>> {
    let point = |k: usize| geometry.uv_to_phase(vis.u[k], vis.v[k]);
    crate::weighting::total_weights(point, &vis.weight, geometry.size, weighting, grid_factor)
}

/// Dirty image and PSF (both N x N, PSF peak 1 at (N/2, N/2)).
pub fn dirty_image(vis: &Visibilities, params: &DirtyParams) -> Result<DirtyProducts> {
    if vis.is_empty() {
        return Err(Error::parameter("visibilities", "no usable visibilities to image (all flagged or empty?)"));
    }
    let geometry = params.geometry(vis)?;
    let weight = total_weights(vis, geometry, params.weighting, params.grid_factor)?;
    let operator = MeasurementOperator::new(geometry, &vis.u, &vis.v, &weight, params.nufft, params.threads)?;
    let dirty = operator.dirty_image(&vis.vis);
    let psf = operator.psf();
    Ok(DirtyProducts { operator, dirty, psf, weight })
}
