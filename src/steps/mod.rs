//! Network steps: the regularisation step of the imaging loop. R2D2 runs a trained network
//! here; the built-in `clean` step runs a Hogbom minor cycle in the same place, so the loop
//! and everything around it is shared. Native plugins (`native`, a shared library through a
//! versioned C ABI) and ONNX series implement the same trait.

pub(crate) mod clean;
pub mod driven;
mod error;
pub(crate) mod native;
pub(crate) mod native_file;
pub(crate) mod native_host;
pub(crate) mod onnx;

pub(crate) use onnx::{runtime, series};

use crate::Result;

/// What a step sees at iteration i: the previous estimate and its residual dirty image.
pub struct StepInput<'a> {
    /// The job being imaged (a step serving several jobs tells them apart by it).
    pub job: &'a str,
    pub size: usize,
    /// `x_{i-1}` (Jy/pixel).
    pub model: &'a [f64],
    /// `r_{i-1} = x_d - D x_{i-1}` (Jy/beam).
    pub residual: &'a [f64],
    pub dirty: &'a [f64],
    /// PSF, N x N, peak 1 at (N/2, N/2).
    pub psf: &'a [f64],
    /// PSF over twice the field, 2N x 2N, peak at (N, N).
    pub psf_2n: &'a [f64],
    /// `D x` as a convolution with `psf_2n`, prepared once per job by the gridder.
    pub psf_convolution: &'a crate::operator::PsfConvolution,
    /// Where the model may have emission (the user's mask, N x N, true inside); none: the
    /// whole image. CLEAN takes components there only; the stage keeps any other step's
    /// model to it.
    pub mask: Option<&'a [bool]>,
}

/// What a step may check about a job before its first iteration: where the data come from
/// and how finely its pixel samples the longest baseline.
#[derive(Clone, Copy, Debug)]
pub struct JobDomain<'a> {
    pub telescope: &'a str,
    pub superresolution: Option<f64>,
    /// Hours the source was tracked (summed over tracks) and the integration time, seconds,
    /// where the data carry times.
    pub track_hours: Option<f64>,
    pub integration_s: Option<f64>,
    /// The mean of the job's dirty image (a series normalises its first input by it).
    pub dirty_mean: Option<f64>,
    /// The weighting grid's cells across where the weights depend on it (uniform, Briggs).
    pub weighting_cells: Option<usize>,
}

pub trait NetworkStep: Send {
    /// Where `job` lies outside what the step was made for (a series' domain), one sentence
    /// per problem; an error where the step refuses such jobs (`validity: error`).
    fn domain_problems(&self, _job: &JobDomain<'_>) -> Result<Vec<String>> {
        Ok(Vec::new())
    }
    /// What ran, for the metrics file's `settings.step` (a series' name and domain).
    fn describe(&self) -> Option<serde_json::Value> {
        None
    }
    /// Number of iterations the series runs (networks in an R2D2 series, major cycles for CLEAN),
    /// over all its realisations.
    fn series_length(&self) -> usize;
    /// Independently trained realisations, run one after the other, each over
    /// `series_length() / realisations()` iterations from the dirty image; the stage keeps
    /// each one's final model and images their mean (1: a single series).
    fn realisations(&self) -> usize {
        1
    }
    /// The iteration from which the residual stage's early stop (stalled, converged) may end
    /// the series (a series' manifest `early_stop_from`; 1: from the first).
    fn early_stop_from(&self) -> usize {
        1
    }
    /// The `auto_mask` level (noise sigmas) a series keeps its model to
    /// ([`crate::deconv::EmissionMask`]), given or by default, for the products' record.
    fn auto_mask(&self) -> Option<f64> {
        None
    }
    /// Iteration `iteration` (1-based): the new estimate `x_i`.
    fn step(&mut self, iteration: usize, input: &StepInput<'_>) -> Result<Vec<f64>>;
    /// After the last job, before anything the step computed is committed: releases what the
    /// step holds (a plugin torn down) and says whether that went well.
    fn finish(&mut self) -> Result<()> {
        Ok(())
    }
    /// Whether the products include a restored image (`-image.fits`: the model convolved with
    /// the fitted restoring beam plus the residual, Jy/beam), as WSClean users and the tools
    /// that read WSClean's products expect. Every built-in step restores; an R2D2 model stays
    /// the image in Jy/pixel (`-model.fits`), the restored one is its view at the beam.
    fn restores(&self) -> bool {
        true
    }
}
