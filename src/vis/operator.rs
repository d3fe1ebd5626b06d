//! The measurement operator and the weights of a job's visibilities, held or read again from
//! their file at each pass ([`VisSource`]): the total weight of each chunk's samples, and `D`
//! summed over the chunks where the samples are not held.

use super::stream::{VisChunk, VisSource, VisSummary};
use crate::nufft::NufftParams;
use crate::operator::{normalise_by_psf_peak, ImageGeometry, ImageGridder, MeasurementOperator};
use crate::weighting::{DensityGrid, WeightRule, Weighting};
use crate::{Error, Result};

/// Why `weighting` cannot weight samples of which `summary` tells, if it cannot: `given`
/// needs imaging weights given with the data.
pub fn weighting_problem(weighting: Weighting, summary: &VisSummary) -> Option<Error> {
    (weighting == Weighting::Given && !summary.imaging_weights).then(no_given_weights)
}

fn no_given_weights() -> Error {
    Error::parameter(
        "weighting",
        "`given` uses the imaging weights given with the data (a table's `imaging_weight` column, a .mat file's `nWimag`), and these visibilities carry none: choose natural, uniform or briggs",
    )
}

/// The imaging weight of every sample of `vis` (of which `summary` tells) on `geometry`: for uniform and Briggs, a pass
/// over the samples gathers the density of the uv-coverage first.
pub fn weight_rule(vis: &VisSource, summary: &VisSummary, geometry: ImageGeometry, weighting: Weighting, grid_factor: f64) -> Result<WeightRule> {
    if let Some(e) = weighting_problem(weighting, summary) {
        return Err(e);
    }
    let mut density = DensityGrid::new(weighting, geometry.size, grid_factor)?;
    if weighting.needs_density() {
        vis.for_each_chunk(1 << 20, &mut |c| {
            density.add(c.len(), |k| geometry.uv_to_phase(c.u[k], c.v[k]), |k| f64::from(c.weight[k]));
            Ok(())
        })?;
    }
    Ok(density.finish())
}

/// Total weights (natural x imaging, x the given imaging weight for `given`) of a chunk's
/// samples.
pub fn chunk_weights(chunk: &VisChunk<'_>, geometry: ImageGeometry, rule: &WeightRule) -> Result<Vec<f64>> {
    let n = chunk.len();
    let natural = |k: usize| f64::from(chunk.weight[k]);
    if rule.scheme() == Weighting::Given {
        if chunk.imaging_weight.len() != n {
            return Err(no_given_weights());
        }
        return Ok((0..n).map(|k| natural(k) * f64::from(chunk.imaging_weight[k])).collect());
    }
    Ok((0..n).map(|k| rule.imaging_weight(geometry.uv_to_phase(chunk.u[k], chunk.v[k])) * natural(k)).collect())
}

/// The operator the residual update runs through where the PSF convolution is not `D` (the
/// w-term), or where the exact NUFFT round trip is asked for.
pub enum DataOperator {
    /// The samples held in memory, in one operator planned once.
    Held(MeasurementOperator),
    /// The samples read again from their file at each application, a chunk at a time.
    Streamed(StreamedOperator),
}

impl DataOperator {
    /// `D x`.
    pub fn apply_normal(&self, x: &[f64]) -> Result<Vec<f64>> {
        match self {
            DataOperator::Held(op) => Ok(op.apply_normal(x)),
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

/// `D` of samples read again from their file at every application, a chunk at a time: each
/// chunk's operator is planned, applied and dropped, and their images summed (`D` is a sum
/// over samples), so memory is the images and one chunk's plan, whatever the number of
/// samples. The price is a pass over the file and each chunk's planning per application.
pub struct StreamedOperator {
    vis: VisSource,
    rule: WeightRule,
    geometry: ImageGeometry,
    w_term: bool,
    nufft: NufftParams,
    threads: usize,
    chunk_rows: usize,
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

impl StreamedOperator {
    /// One pass over `vis`: the dirty image and PSF through the operator (with the w-term
    /// where `w_term`), the coplanar 2N PSF, and `kappa` from the PSF's peak.
    #[allow(clippy::too_many_arguments)]
    pub fn grid(
        vis: VisSource,
        rule: WeightRule,
        geometry: ImageGeometry,
        w_term: bool,
        nufft: NufftParams,
        threads: usize,
        chunk_rows: usize,
    ) -> Result<StreamedGridding> {
        let pixels = geometry.pixels();
        let (mut dirty, mut psf) = (vec![0.0; pixels], vec![0.0; pixels]);
        let mut doubled = ImageGridder::doubled_psf_only(geometry, nufft, threads)?;
        let mut planes: Option<usize> = None;
        vis.for_each_chunk(chunk_rows, &mut |c| {
            let weight = chunk_weights(&c, geometry, &rule)?;
            let op = MeasurementOperator::part_for_mode(w_term, geometry, c.u, c.v, c.w, &weight, nufft, threads)?;
            add_to(&mut dirty, &op.dirty_image(c.vis));
            add_to(&mut psf, &op.psf());
            planes = planes.max(op.w_planes());
            drop(op);
            doubled.add(c.u, c.v, &weight, c.vis)
        })?;
        let kappa = normalise_by_psf_peak(geometry.size, &mut dirty, &mut psf)?;
        let psf_2n = doubled.finish(Some(kappa))?.psf_2n;
        let operator = StreamedOperator { vis, rule, geometry, w_term, nufft, threads, chunk_rows, kappa, planes };
        Ok(StreamedGridding { operator, dirty, psf, psf_2n })
    }

    /// `D x = kappa Re{Phi^H Phi x}`, summed over the chunks of a pass.
    pub fn apply_normal(&self, x: &[f64]) -> Result<Vec<f64>> {
        let mut sum = vec![0.0; x.len()];
        let geometry = self.geometry;
        self.vis.for_each_chunk(self.chunk_rows, &mut |c| {
            let weight = chunk_weights(&c, geometry, &self.rule)?;
            let op = MeasurementOperator::part_for_mode(self.w_term, geometry, c.u, c.v, c.w, &weight, self.nufft, self.threads)?;
            add_to(&mut sum, &op.apply_normal(x));
            Ok(())
        })?;
        sum.iter_mut().for_each(|p| *p *= self.kappa);
        Ok(sum)
    }

    pub fn kappa(&self) -> f64 {
        self.kappa
    }
}

fn add_to(sum: &mut [f64], part: &[f64]) {
    sum.iter_mut().zip(part).for_each(|(s, p)| *s += p);
}
