//! The measurement operator and the weights of a job's visibilities, held or read again from
//! their file at each pass ([`VisSource`]): the total weight of each chunk's samples, and `D`
//! summed over the chunks where the samples are not held.

use super::parted::{PartImages, PartPass};
use super::parts::{density_and_counts, no_given_weights, part_apply_normal, part_doubled_psf_of, part_images};
use super::data::VisSummary;
use super::stream::VisSource;
use crate::nufft::NufftParams;
use crate::operator::{ImageGeometry, NormalOperator};
use crate::weighting::{DensityGrid, UvControls, UvCounts, UvShape, WeightRule, Weighting};
use crate::{Error, Result};
use num_complex::Complex64;

/// Why `weighting` cannot weight samples of which `summary` tells, if it cannot: `given`
/// needs imaging weights given with the data.
pub fn weighting_problem(weighting: Weighting, summary: &VisSummary) -> Option<Error> {
    (weighting == Weighting::Given && !summary.imaging_weights).then(no_given_weights)
}

/// The imaging weight of every sample of `vis` (of which `summary` tells) on `geometry`, with
/// the uv cuts and tapers `uv`: for uniform and Briggs, a pass over the samples (over every
/// part, where in parts) gathers the density of the uv-coverage first. Where a sample may be
/// left out (a cut is asked for, or a baseline reaches beyond the grid), how many each cut
/// leaves out is counted in the same pass (or a pass of its own), except in parts.
pub(crate) fn weight_rule(vis: &VisSource, summary: &VisSummary, geometry: ImageGeometry, weighting: Weighting, grid_factor: f64, uv: &UvControls) -> Result<(WeightRule, Option<UvCounts>)> {
    if let Some(e) = weighting_problem(weighting, summary) {
        return Err(e);
    }
    let shape = UvShape::new(uv, geometry.size, grid_factor, geometry.pixel_rad)?;
    let pass = PartPass::new(geometry, weighting, grid_factor, false, NufftParams::default(), 0, 1 << 20);
    let may_exclude = !shape.is_none() || summary.max_uv >= 0.5 / geometry.pixel_rad;
    let (density, counts) = match vis {
        VisSource::Parts(parts) if weighting.needs_density() => (parts.passes.density(&pass)?, None),
        VisSource::Parts(_) => (DensityGrid::new(weighting, geometry.size, grid_factor)?, None),
        _ => density_and_counts(vis, &pass, may_exclude.then_some(&shape))?,
    };
    Ok((density.finish().with_uv(shape), counts))
}

/// The operator the residual update runs through where the PSF convolution is not `D` (the
/// w-term), or where the exact NUFFT round trip is asked for.
pub enum DataOperator {
    /// The samples held in memory, in one operator planned once.
    Held(NormalOperator),
    /// The samples read again from their file at each application, a chunk at a time.
    Streamed(StreamedOperator),
}

impl DataOperator {
    /// `D x`.
    pub fn apply_normal(&self, x: &[f64]) -> Result<Vec<f64>> {
        match self {
            DataOperator::Held(op) => Ok(op.apply(x)),
            DataOperator::Streamed(op) => op.apply_normal(x),
        }
    }

    /// The w-planes of a w-gridded operator (the most of any chunk where streamed); `None`
    /// for a coplanar one.
    pub fn w_planes(&self) -> Option<usize> {
        match self {
            DataOperator::Held(op) => op.w_planes(),
            DataOperator::Streamed(op) => op.planes,
        }
    }
}

/// `D` of samples read again at every application, from their file a chunk at a time or
/// where their parts live: each chunk's operator is planned, applied and dropped, and their
/// images summed (`D` is a sum over samples), so memory is the images and one chunk's plan,
/// whatever the number of samples. The price is a pass over the samples and each chunk's
/// planning per application.
pub struct StreamedOperator {
    vis: VisSource,
    rule: WeightRule,
    pass: PartPass,
    kappa: f64,
    planes: Option<usize>,
}

/// The images of a streamed operator's gridding pass, and the operator.
pub struct StreamedGridding {
    pub operator: StreamedOperator,
    pub dirty: Vec<f64>,
    pub psf: Vec<f64>,
    pub psf_2n: Vec<f64>,
}

/// The images of `vis` weighted by `rule`, made as `pass` says, summed over its parts where
/// in parts, and not yet normalised.
pub fn source_images(vis: &VisSource, pass: &PartPass, rule: &WeightRule) -> Result<PartImages> {
    match vis {
        VisSource::Parts(parts) => {
            let images = parts.passes.images(pass, rule)?;
            check_gridded_samples(vis, images.samples)?;
            Ok(images)
        }
        _ => part_images(vis, pass, rule),
    }
}

/// An error where a pass over `vis` gridded another number of samples than its first reading
/// found: a part (or the file) changed, or went missing, meanwhile.
pub fn check_gridded_samples(vis: &VisSource, gridded: u64) -> Result<()> {
    let found = vis.summary().samples;
    if gridded == found {
        return Ok(());
    }
    Err(match vis {
        VisSource::Parts(parts) => Error::parameter(
            "parts",
            format!(
                "the parts of job '{}' ({}) gridded {gridded} samples where their first reading found {found}: was a part written to meanwhile? nothing was written",
                parts.id,
                parts.passes.describe(),
            ),
        ),
        _ => Error::parameter("visibilities", format!("the gridding pass read {gridded} samples where the first reading found {found}: was the input written to meanwhile? nothing was written")),
    })
}

impl StreamedOperator {
    /// One pass over `vis`: the dirty image and PSF through the operator (with the w-term
    /// where `pass.w_term`), the coplanar 2N PSF, and `kappa` from the PSF's peak.
    pub fn grid(vis: VisSource, rule: WeightRule, pass: PartPass) -> Result<StreamedGridding> {
        let images = source_images(&vis, &pass, &rule)?.normalise(pass.size)?;
        let operator = StreamedOperator { vis, rule, pass, kappa: images.kappa, planes: images.planes };
        Ok(StreamedGridding { operator, dirty: images.dirty, psf: images.psf, psf_2n: images.psf_2n })
    }

    /// `D x = kappa Re{Phi^H Phi x}`, summed over the chunks (or parts) of a pass.
    pub fn apply_normal(&self, x: &[f64]) -> Result<Vec<f64>> {
        let mut sum = match &self.vis {
            VisSource::Parts(parts) => parts.passes.apply_normal(&self.pass, &self.rule, x)?,
            vis => part_apply_normal(vis, &self.pass, &self.rule, x)?,
        };
        sum.iter_mut().for_each(|p| *p *= self.kappa);
        Ok(sum)
    }

    pub fn kappa(&self) -> f64 {
        self.kappa
    }

    /// The 2N PSF with each sample's total weight times `factor(w)`, scaled as `D` (a kernel of
    /// the Taylor series in w, `crate::operator::taylor`), in one more pass over the samples read from
    /// their file (not where they live in parts elsewhere).
    pub fn doubled_psf_of(&self, factor: impl Fn(f64) -> Complex64 + Sync) -> Result<Vec<f64>> {
        if let VisSource::Parts(parts) = &self.vis {
            return Err(Error::parameter("parts", format!("the parts ({}) make no kernels of the Taylor series in w", parts.passes.describe())));
        }
        let mut kernel = part_doubled_psf_of(&self.vis, &self.pass, &self.rule, factor)?;
        kernel.iter_mut().for_each(|k| *k *= self.kappa);
        Ok(kernel)
    }
}
