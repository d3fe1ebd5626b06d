//! `kind: gridder`: dirty image, PSF (N and 2N), kappa and the restoring beam, and the form of
//! `D` the residual update applies, as `crate::operator::plan` chooses it from the job's
//! samples and the gridder's limits (`crate::vis::grid_planned` builds it); none where no stage
//! after it updates a residual (the dirty image and the PSFs are the job's products).

use super::params::RestoringBeam;
use super::params::GridderParams;
use crate::deconv::Beam;
use crate::imaging::WTerm;
use crate::job::{Emit, Imaging, Job};
use crate::nufft::NufftParams;
use crate::operator::plan::{OperatorPlan, PlanParams, Samples};
use crate::operator::{PsfConvolution, WTermMode};
use crate::pipeline::{Port, Stage};
use crate::vis::{grid_planned, VisSource};
use crate::{Error, Result};
use std::sync::Arc;

pub struct GridderStage {
    params: PlanParams,
    restoring_beam: RestoringBeam,
}

impl GridderStage {
    /// `keep_operator`: a stage after it runs the exact NUFFT round trip; `images_only`: no
    /// stage after it applies `D` (no residual update), so no form of `D` is made.
    pub fn new(config: GridderParams, threads: usize, keep_operator: bool, images_only: bool) -> Result<GridderStage> {
        let nufft = NufftParams { epsilon: config.epsilon, oversampling: config.oversampling.unwrap_or(crate::nufft::DEFAULT_OVERSAMPLING) };
        crate::nufft::kernel::KernelShape::for_accuracy(nufft.epsilon, nufft.oversampling)?;
        for (key, mb) in [("hold_mb", config.hold_mb), ("kernel_mb", config.kernel_mb)] {
            if !(mb >= 0.0) || !mb.is_finite() {
                return Err(Error::parameter(key, format!("expected a number of megabytes >= 0, got {mb}")));
            }
        }
        config.restoring_beam.check("restoring_beam")?;
        if config.chunk_rows == 0 {
            return Err(Error::parameter("chunk_rows", "expected at least 1 sample per chunk"));
        }
        Ok(GridderStage { params: PlanParams { nufft, w_term: config.w_term, hold_bytes: config.hold_mb * 1e6, kernel_bytes: config.kernel_mb * 1e6, chunk_rows: config.chunk_rows, threads, keep_operator, images_only, operator_chooses_oversampling: config.oversampling.is_none() }, restoring_beam: config.restoring_beam })
    }
}

impl Stage<Job> for GridderStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let (geometry, rule) = job.take_weights("gridder")?;
        let source = job.take_visibilities("gridder")?;
        let summary = source.summary();
        // The band edge to edge: the selected channels' where the reader knows them (WSClean's
        // CRVAL3 and CDELT3), else the samples' span plus a channel's width where that is
        // known, else the span of the samples' frequencies (none for one frequency).
        let channel_width = job.meta.extra.get(crate::vis::CHANNEL_WIDTH_KEY).and_then(|w| w.parse::<f64>().ok()).filter(|w| w.is_finite() && *w > 0.0);
        let edges = job.meta.extra.get(crate::vis::BAND_EDGES_KEY).and_then(|e| {
            let (low, high) = e.split_once(' ')?;
            let (low, high) = (low.parse::<f64>().ok()?, high.parse::<f64>().ok()?);
            (low.is_finite() && high > low).then_some((low, high))
        });
        let (frequency_hz, bandwidth_hz) = match (edges, summary.band()) {
            (Some((low, high)), Some(_)) => (Some(0.5 * (low + high)), Some(high - low)),
            (None, Some((centre, span))) => (Some(centre), channel_width.map(|w| span.unwrap_or(0.0) + w).or(span)),
            (_, None) => (None, None),
        };
        let in_parts = matches!(source, VisSource::Parts(_));
        if in_parts && self.params.keep_operator {
            return Err(Error::parameter(
                "method",
                format!("job '{}' is in parts gridded where they live, and the residual update's exact NUFFT round trip needs its samples in one process: use method: toeplitz", job.id),
            ));
        }
        let (max_abs_w, streamed) = (summary.max_abs_w, source.is_streamed());
        let plan = OperatorPlan::new(geometry, Samples { count: summary.samples, max_abs_w, max_uv: summary.max_uv, streamed, in_parts }, self.params);
        let (w_term, max_phase) = (plan.w_term, plan.max_phase_rad);
        let g = grid_planned(&job.id, source, rule, plan)?;
        let toeplitz_inexact = w_term.then(|| format!("the operator includes the w-term (phase up to {max_phase:.3} rad over the field), which a PSF convolution does not"));
        match (w_term, self.params.w_term) {
            (true, _) => log::info!(
                "job {}: the w-term is corrected by w-gridding ({} w-planes; |w| up to {max_abs_w:.4e} wavelengths turns the phase by up to {max_phase:.3} rad at the field's corners)",
                job.id,
                g.planes.unwrap_or(1)
            ),
            (false, WTermMode::Off) => {
                if let Some(warning) = (WTerm { max_abs_w, max_phase_rad: max_phase }).warning(geometry) {
                    job.warn(format!("{warning} (w_term: off)"));
                }
            }
            (false, _) => log::info!("job {}: the w-term is left out: it turns no phase by more than {max_phase:.2e} rad over the field (below the NUFFT's accuracy)", job.id),
        }
        job.settings.insert(
            "w_term".into(),
            serde_json::json!({"mode": self.params.w_term.name(), "corrected": w_term, "planes": g.planes, "max_abs_w": max_abs_w, "max_phase_rad": max_phase,
                "toeplitz_planes": g.w_toeplitz.as_ref().map(|op| op.planes()),
                "taylor_order": g.w_taylor.as_ref().map(|(form, _)| form.order()),
                "taylor_deviation": g.w_taylor.as_ref().map(|(_, deviation)| *deviation)}),
        );
        crate::sanity::check_image(&g.dirty, geometry.size, "dirty image", "the visibilities or weights hold values too large to image (check the data column and the weights)")?;
        let psf_convolution = Arc::new(PsfConvolution::new(geometry.size, &g.psf_2n)?);
        let beam = match choose_beam(self.restoring_beam, &g.psf, geometry.size, geometry.pixel_rad, job.theoretic_beam_rad) {
            Ok((b, how, warning)) => {
                warning.into_iter().for_each(|w| job.warn(w));
                job.settings.insert("restoring_beam".into(), serde_json::json!({"how": how, "major_arcsec": b.major_deg * 3600.0, "minor_arcsec": b.minor_deg * 3600.0, "pa_deg": b.pa_deg}));
                Some(b)
            }
            Err(e) => {
                job.warn(format!("no restoring beam: {e}"));
                None
            }
        };
        let (nufft, model) = (self.params.nufft, vec![0.0; geometry.pixels()]);
        let (residual, w_taylor) = (g.dirty.clone(), g.w_taylor.map(|(form, _)| Arc::new(form)));
        let (dirty, psf, psf_2n, operator, w_toeplitz) = (g.dirty, g.psf, Arc::new(g.psf_2n), g.operator, g.w_toeplitz);
        job.imaging = Some(Imaging { geometry, residual, dirty, psf, psf_convolution, psf_2n, operator, toeplitz_inexact, w_toeplitz, w_taylor, nufft, w_term, model, beam, frequency_hz, bandwidth_hz, best: None });
        if let Some(vis) = g.kept {
            job.vis = Some(VisSource::Held(Arc::new(vis)));
        }
        emit(Port::Next, job)
    }
}

/// The restoring beam `choice` asks for, how it was chosen (for the products' headers), and a
/// warning where a fit was replaced.
fn choose_beam(choice: RestoringBeam, psf: &[f64], size: usize, pixel_rad: f64, theoretic_rad: Option<f64>) -> Result<(Beam, String, Option<String>)> {
    use crate::deconv::{restoring_beam, BeamFit};
    let fitted = |shape| restoring_beam(psf, size, pixel_rad, shape);
    Ok(match choice {
        RestoringBeam::Fit => {
            let (beam, warning) = fitted(BeamFit::Elliptical)?;
            (beam, BEAM_FITTED.into(), warning)
        }
        RestoringBeam::FitCircular => {
            let (beam, warning) = fitted(BeamFit::Circular)?;
            (beam, BEAM_FITTED_CIRCULAR.into(), warning)
        }
        RestoringBeam::Theoretic => {
            let fwhm = theoretic_rad.ok_or_else(|| Error::parameter("restoring_beam", "a theoretic beam needs the longest baseline, and the job has none"))?.to_degrees();
            (Beam { major_deg: fwhm, minor_deg: fwhm, pa_deg: 0.0 }, BEAM_THEORETIC.into(), None)
        }
        RestoringBeam::Given { major_arcsec, minor_arcsec, pa_deg } => {
            (Beam { major_deg: major_arcsec / 3600.0, minor_deg: minor_arcsec / 3600.0, pa_deg }, BEAM_GIVEN.into(), None)
        }
    })
}

/// How each restoring beam was chosen, as the products' headers say it.
pub(crate) const BEAM_FITTED: &str = "Restoring beam: an elliptical Gaussian fitted by least squares to the PSF main lobe (the pixels connected to the centre above 0.35 of the peak, as CASA psfcutoff); WSClean fits a box ten FWHM wide, sidelobes included. A fit that fails is replaced by the main lobe's circle, with a warning.";
const BEAM_FITTED_CIRCULAR: &str = "Restoring beam: a circular Gaussian fitted by least squares to the PSF main lobe (the pixels connected to the centre above 0.35 of the peak), as asked (circular beam). A fit that fails is replaced by the main lobe's circle, with a warning.";
const BEAM_THEORETIC: &str = "Restoring beam: not fitted; circular, FWHM 1 / the longest baseline kept (radians), or the Gaussian taper's FWHM where wider, as WSClean's theoretic beam.";
const BEAM_GIVEN: &str = "Restoring beam: given by the request (beam size or shape), not fitted to the PSF.";
