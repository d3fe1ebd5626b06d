//! A job's state as it flows through the stages: the visibilities, the imaging set-up and
//! images, the loop's iterates, figures and warnings.

use super::product::Product;
use crate::pipeline::ProductKind;
use crate::fits::{Beam, ImageWcs};
use crate::metrics;
use crate::nufft::NufftParams;
use crate::operator::{ImageGeometry, PsfConvolution};
use crate::vis::{DataOperator, ObservationMeta, VisSource, Visibilities};
use crate::operator::taylor::WTaylor;
use crate::operator::toeplitz::WToeplitz;
use crate::weighting::WeightRule;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Images and operators of a job once it is gridded.
pub struct Imaging {
    pub geometry: ImageGeometry,
    pub dirty: Vec<f64>,
    pub psf: Vec<f64>,
    /// `D x` as a convolution with the 2N PSF.
    pub psf_convolution: Arc<PsfConvolution>,
    /// The doubled PSF itself (2N x 2N), for steps that subtract shifted PSFs.
    pub psf_2n: Arc<Vec<f64>>,
    /// Kept when the residual update runs through the operator: asked for (`method: nufft`),
    /// or with the w-term where its Toeplitz form (`w_toeplitz`) was not built.
    pub operator: Option<Arc<DataOperator>>,
    /// Why the PSF convolution is not `D` to the NUFFT's accuracy for this job (the operator
    /// includes the w-term), so the residual update uses `w_toeplitz` or the operator; `None`
    /// where it is.
    pub toeplitz_inexact: Option<String>,
    /// `D` with the w-term as one convolution per w-plane, where it was built in the gridding
    /// pass: the residual update's, in place of the operator.
    pub w_toeplitz: Option<Arc<WToeplitz>>,
    /// `D` with the w-term as a Taylor series in `w` of the PSF convolution, where the gridder
    /// found one that agrees with the operator (kept beside it): the residual update's.
    pub w_taylor: Option<Arc<WTaylor>>,
    /// The NUFFT the images were made with and whether it included the w-term: what a
    /// prediction from the model (`MODEL_DATA`) must use.
    pub nufft: NufftParams,
    pub w_term: bool,
    /// Current estimate `x_i` (Jy/pixel) and residual dirty image `r_i = x_d - D x_i`.
    pub model: Vec<f64>,
    pub residual: Vec<f64>,
    /// Centre of the observed band, Hz (for the FITS FREQ axis), and its width when the
    /// samples span more than one frequency.
    pub frequency_hz: Option<f64>,
    pub bandwidth_hz: Option<f64>,
    /// Restoring beam fitted to the PSF main lobe (FWHM degrees, PA degrees east of north).
    pub beam: Option<Beam>,
    /// The iterate of lowest residual ratio so far, kept by the residual update's divergence
    /// guard (`None`: the empty model, ratio 1, is the best so far).
    pub best: Option<Iterate>,
}

impl Imaging {
    /// Whether the updates apply the Taylor series in `w` in the operator's place (the
    /// operator kept beside it for the residual written).
    pub fn updates_by_taylor(&self) -> bool {
        self.w_toeplitz.is_none() && self.w_taylor.is_some() && self.operator.is_some()
    }

    /// `D x` as the residual updates (`method: toeplitz`) apply it: the w-aware Toeplitz
    /// kernels, the Taylor series in `w`, the operator (the samples), or the PSF convolution
    /// where it is exact (the operator is kept with the w-term, or for `method: nufft`, whose
    /// updates apply it too); `who` names the caller in the error where none of them is `D`.
    pub fn normal_at_updates(&self, x: &[f64], who: &str) -> Result<Vec<f64>> {
        if let Some(w_toeplitz) = &self.w_toeplitz {
            return Ok(w_toeplitz.apply(x));
        }
        if let (Some(w_taylor), true) = (&self.w_taylor, self.updates_by_taylor()) {
            return Ok(w_taylor.apply(x));
        }
        if let Some(op) = &self.operator {
            return op.apply_normal(x);
        }
        match &self.toeplitz_inexact {
            Some(why) => Err(Error::parameter(who, format!("the PSF convolution is not exact here ({why}) and the gridder kept no operator"))),
            None => Ok(self.psf_convolution.apply(x)),
        }
    }

    /// Where the updates ran by the Taylor series in `w`, the residual of the model again
    /// through the operator (the residual written is the operator's): how far the series was
    /// from it, relative to `D x`, and a warning where that is beyond its tolerance (`seen_by`
    /// names what worked on the series' residuals). `None` (nothing recomputed) elsewhere.
    pub fn residual_through_the_operator(&mut self, seen_by: &str) -> Result<Option<(f64, Option<String>)>> {
        let Some(op) = self.operator.as_ref().filter(|_| self.updates_by_taylor()) else { return Ok(None) };
        let exact = op.apply_normal(&self.model)?;
        // The series' D x, as the last update left it in the residual.
        let by_taylor: Vec<f64> = self.dirty.iter().zip(&self.residual).map(|(d, r)| d - r).collect();
        let found = crate::operator::taylor::final_deviation(&by_taylor, &exact, self.nufft.epsilon, seen_by);
        self.residual = self.dirty.iter().zip(&exact).map(|(d, x)| d - x).collect();
        Ok(Some(found))
    }
}

/// One iterate of the imaging loop, kept so that a diverging series can fall back to it.
#[derive(Clone, Debug)]
pub struct Iterate {
    pub iteration: usize,
    pub residual_ratio: f64,
    pub model: Vec<f64>,
    pub residual: Vec<f64>,
}

/// Why the imaging loop of a job ended before its series did (the metrics file's `stop`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// The residual ratio rose above 1: the model explained the data worse than an empty one.
    Diverged,
    /// The residual ratio rose at two consecutive iterations, by more than half in all, to above 0.05.
    Rising,
    /// The residual ratio rose slightly at two consecutive iterations (reference v2): the
    /// series is at its noise floor; the last iterate is kept.
    Stalled,
    /// The residual ratio changed by less than the tolerance (reference v2).
    Converged,
}

impl StopReason {
    /// The divergence guard's stops: the step's model was rejected for an earlier iterate.
    pub fn is_rejection(self) -> bool {
        matches!(self, StopReason::Diverged | StopReason::Rising)
    }
}

/// How and where the loop stopped early, and which iterate became the model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoopStop {
    pub reason: StopReason,
    /// The iteration after which the loop stopped.
    pub after_iteration: usize,
    /// The iterate kept as the model (0: the empty model) and its residual ratio.
    pub kept_iteration: usize,
    pub kept_residual_ratio: f64,
}

/// The error of a stage given a job without `product`. The products check before the run
/// guarantees every product a stage kind declares it consumes: this is a kind that consumes
/// more than it declares, or one upstream that declares more than it makes.
pub(crate) fn missing(stage: &str, job: &str, product: Product) -> Error {
    let (what, maker) = product.describe();
    Error::parameter(format!("stage '{stage}'"), format!("job '{job}' reached it without {what}: put {maker} upstream"))
}

/// One iteration's figures, as written to `<prefix>-metrics.json`.
#[derive(Clone, Debug, Serialize)]
pub struct IterationMetrics {
    pub iteration: usize,
    /// The realisation this iteration belongs to (steps of several realisations only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub realisation: Option<usize>,
    pub residual_ratio: f64,
    pub step_seconds: f64,
    pub residual_seconds: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub snr: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub logsnr: Option<f64>,
}

/// One iteration's figures for `model` and its residual (SNR and logSNR against `truth` where
/// it is known and on the same grid), its step having taken `step_seconds`; the iteration's
/// number and realisation are the job's to set.
pub(crate) fn iteration_figures(model: &[f64], residual: &[f64], dirty: &[f64], truth: Option<&[f64]>, truth_dynamic_range: Option<f64>, step_seconds: f64) -> IterationMetrics {
    let (snr, logsnr) = match truth {
        Some(t) if t.len() == model.len() => (Some(metrics::snr(model, t)), truth_dynamic_range.map(|dr| metrics::log_snr(model, t, dr))),
        _ => (None, None),
    };
    IterationMetrics { iteration: 0, realisation: None, residual_ratio: metrics::residual_ratio(residual, dirty), step_seconds, residual_seconds: 0.0, snr, logsnr }
}

/// A dataset being imaged, with everything the stages have made of it so far.
pub struct Job {
    pub id: String,
    pub meta: ObservationMeta,
    /// Visibilities, held or read again from their file at each pass; released by the gridder
    /// (which holds them in its operator where the residual update needs them).
    pub vis: Option<VisSource>,
    /// Ground truth on the image grid, when known (simulated data), for SNR/logSNR.
    pub truth: Option<Vec<f64>>,
    /// Dynamic range of the truth, for logSNR.
    pub truth_dynamic_range: Option<f64>,
    /// The truth's grid (from its FITS header), checked against the job's.
    pub truth_wcs: Option<ImageWcs>,
    /// Image geometry and the imaging weight of every sample, set by the weighting stage.
    pub geometry: Option<ImageGeometry>,
    pub weight: Option<WeightRule>,
    pub imaging: Option<Imaging>,
    /// Network steps done so far.
    pub iteration: usize,
    /// Set by the network step when it ran the last network of its series.
    pub series_finished: bool,
    /// The steps the network step will run at most (its series' length; 0 before the first).
    pub series_length: usize,
    /// The iteration from which the early stop may end the loop (the step's
    /// [`early_stop_from`](crate::steps::NetworkStep::early_stop_from)).
    pub early_stop_from: usize,
    /// Name of the step that made the model (products are named after what made them).
    pub step_kind: Option<String>,
    /// Whether that step's model is restored (a CLEAN-like step: `-image.fits` is written),
    /// and the restored image once made (a job's products are made once per sink, the
    /// restoration only once).
    pub restores: bool,
    pub restored: Option<Vec<f32>>,
    /// A step of several realisations: the realisation running (1-based; 0 otherwise, and for
    /// the final step that images their mean) and the final models of those done.
    pub realisation: usize,
    pub realisation_models: Vec<Vec<f64>>,
    /// Seconds of the last step, recorded into the next metrics row.
    pub last_step_seconds: f64,
    pub metrics: Vec<IterationMetrics>,
    /// Seconds spent per stage (summed over iterations).
    pub stage_seconds: BTreeMap<String, f64>,
    /// Set when the imaging loop stopped before the end of its series.
    pub stop: Option<LoopStop>,
    /// Warnings about this job (outside a series' domain, a diverging series, ...): logged
    /// when raised and kept for the metrics file.
    pub warnings: Vec<String>,
    /// The imaging settings the job ran with and where each came from (weighting, pixel,
    /// series), for the metrics file.
    pub settings: BTreeMap<String, serde_json::Value>,
    /// The super-resolution of the job's pixel: its longest baseline is sampled this many
    /// times finer than Nyquist (set with the geometry).
    pub superresolution: Option<f64>,
    /// The theoretic restoring beam's FWHM (radians): 1 / the longest baseline kept, or the
    /// Gaussian taper's FWHM where that is wider, as WSClean's (set with the geometry).
    pub theoretic_beam_rad: Option<f64>,
    /// The longest baseline (wavelengths) of all the jobs one table was split into, for a job
    /// of a split: the pixel size is set by it, so that every job of the split is imaged on one
    /// grid (time windows of A and C configurations compared or stacked pixel for pixel).
    pub split_max_uv: Option<f64>,
    /// Hours the data's source was tracked, summed over its tracks, and their integration
    /// time, seconds ([`crate::vis::ObservedTimes`]): known where the data carry times (set
    /// with the geometry).
    pub track_hours: Option<f64>,
    pub integration_s: Option<f64>,
    /// The weighting grid's cells across where the weights depend on it (uniform and Briggs;
    /// `None` for natural or given weights), set by the weighting stage: a series sees the PSF
    /// it was trained on only with its trained field's cells.
    pub weighting_cells: Option<usize>,
    /// The files the job was read from (visibilities, truth, mask): its products never
    /// replace them.
    pub inputs: Vec<std::path::PathBuf>,
    /// Where the model may have emission (the step's `fits_mask`, on the job's grid), set by
    /// the step stage at the job's first step: the final CLEAN cycles keep to it as well.
    pub mask: Option<Arc<Vec<bool>>>,
}

impl Job {
    /// Where an image's coordinates `wcs` put it on another grid than the job's `geometry`
    /// (pixel size, or centre against the phase centre, each to a thousandth of a pixel), one
    /// phrase per difference; none where it is on the job's grid.
    pub fn grid_differences(&self, wcs: &ImageWcs, geometry: &ImageGeometry) -> Vec<String> {
        let pixel_deg = geometry.pixel_rad.to_degrees();
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-3 * pixel_deg;
        let mut problems = Vec::new();
        if !close(wcs.pixel_deg, pixel_deg) {
            problems.push(format!("its pixel is {:.6e} deg, the image's {pixel_deg:.6e} deg", wcs.pixel_deg));
        }
        let (ra, dec) = (self.meta.phase_centre_ra_deg, self.meta.phase_centre_dec_deg);
        let dra = (wcs.ra_deg - ra + 540.0).rem_euclid(360.0) - 180.0;
        if !close(dra * dec.to_radians().cos(), 0.0) || !close(wcs.dec_deg, dec) {
            problems.push(format!("its centre is RA {:.6} Dec {:.6} deg, the phase centre RA {ra:.6} Dec {dec:.6} deg", wcs.ra_deg, wcs.dec_deg));
        }
        problems
    }

    pub fn new(id: impl Into<String>, meta: ObservationMeta, vis: Visibilities) -> Job {
        Job::from_source(id, meta, VisSource::Held(Arc::new(vis)))
    }

    /// A job whose visibilities are held or read from their file at each pass.
    pub fn from_source(id: impl Into<String>, meta: ObservationMeta, vis: VisSource) -> Job {
        Job {
            id: id.into(),
            meta,
            vis: Some(vis),
            truth: None,
            truth_dynamic_range: None,
            truth_wcs: None,
            geometry: None,
            weight: None,
            imaging: None,
            iteration: 0,
            series_finished: false,
            series_length: 0,
            early_stop_from: 1,
            step_kind: None,
            restores: false,
            restored: None,
            realisation: 0,
            realisation_models: Vec::new(),
            last_step_seconds: 0.0,
            metrics: Vec::new(),
            stage_seconds: BTreeMap::new(),
            stop: None,
            warnings: Vec::new(),
            settings: BTreeMap::new(),
            superresolution: None,
            theoretic_beam_rad: None,
            split_max_uv: None,
            track_hours: None,
            integration_s: None,
            weighting_cells: None,
            inputs: Vec::new(),
            mask: None,
        }
    }

    /// Log a warning about this job and keep it for the metrics file.
    pub fn warn(&mut self, message: impl Into<String>) {
        let message = message.into();
        log::warn!("job {}: {message}", self.id);
        self.warnings.push(message);
    }

    /// The gridded state, or an error naming the stage that needed it.
    pub fn imaging_mut(&mut self, stage: &str) -> Result<&mut Imaging> {
        let id = &self.id;
        self.imaging.as_mut().ok_or_else(|| missing(stage, id, Product::Imaging))
    }

    /// The visibilities, or an error naming the stage that needed them (released by the
    /// gridder unless a stage after it consumes the operator).
    pub fn visibilities(&self, stage: &str) -> Result<&VisSource> {
        self.vis.as_ref().ok_or_else(|| missing(stage, &self.id, Product::Visibilities))
    }

    /// Takes the visibilities out of the job (the gridder's: it releases them).
    pub fn take_visibilities(&mut self, stage: &str) -> Result<VisSource> {
        self.vis.take().ok_or_else(|| missing(stage, &self.id, Product::Visibilities))
    }

    /// Takes the weights out of the job, with the geometry they were made for (the gridder's).
    pub fn take_weights(&mut self, stage: &str) -> Result<(ImageGeometry, WeightRule)> {
        match (self.geometry, self.weight.take()) {
            (Some(geometry), Some(weight)) => Ok((geometry, weight)),
            (_, weight) => {
                self.weight = weight;
                Err(missing(stage, &self.id, Product::Weights))
            }
        }
    }

    /// Record iteration figures after a residual update.
    pub fn record_iteration(&mut self, residual_seconds: f64) {
        let Some(im) = &self.imaging else { return };
        let mut figures = iteration_figures(&im.model, &im.residual, &im.dirty, self.truth.as_deref(), self.truth_dynamic_range, self.last_step_seconds);
        figures.residual_seconds = residual_seconds;
        self.push_iteration(figures);
    }

    /// Records `figures` as the job's current iteration (its number and realisation set here).
    pub(crate) fn push_iteration(&mut self, mut figures: IterationMetrics) {
        figures.iteration = self.iteration;
        figures.realisation = (self.realisation > 0).then_some(self.realisation);
        self.metrics.push(figures);
    }
}

