//! `kind: gridder`: dirty image, PSF (N and 2N), kappa and the restoring beam, with the w-term
//! where it matters (`w_term`). Releases the visibilities unless the residual update runs a
//! NUFFT round trip; keeps the operator where the w-term makes the PSF convolution inexact.

use super::params::GridderParams;
use crate::nufft::NufftParams;
use crate::operator::{doubled_psf, MeasurementOperator, PsfConvolution, WTermMode};
use crate::job::{Emit, Imaging, Job};
use crate::pipeline::{Port, Stage};
use crate::vis::{chunk_weights, source_images, DataOperator, PartPass, StreamedOperator, VisSource};
use crate::{Error, Result};
use std::sync::Arc;

/// What an operator holds per sample (baselines, value, weight, its plan's sorting and
/// positions): what a streamed table costs when the residual update needs the operator.
const OPERATOR_BYTES_PER_SAMPLE: f64 = 100.0;

/// What a chunk of a streamed operator costs per sample: the samples as read, their weights
/// and the chunk's plan (measured at 1e8 samples: 140).
const STREAMED_BYTES_PER_SAMPLE: f64 = 150.0;

pub struct GridderStage {
    nufft: NufftParams,
    w_term: WTermMode,
    hold_bytes: f64,
    chunk_rows: usize,
    threads: usize,
    keep_operator: bool,
}

impl GridderStage {
    pub fn new(config: GridderParams, threads: usize, keep_operator: bool) -> Result<GridderStage> {
        let nufft = NufftParams { epsilon: config.epsilon, oversampling: config.oversampling };
        crate::nufft::kernel::KernelShape::for_accuracy(nufft.epsilon, nufft.oversampling)?;
        if !(config.hold_mb >= 0.0) || !config.hold_mb.is_finite() {
            return Err(Error::parameter("hold_mb", format!("expected a number of megabytes >= 0, got {}", config.hold_mb)));
        }
        if config.chunk_rows == 0 {
            return Err(Error::parameter("chunk_rows", "expected at least 1 sample per chunk"));
        }
        Ok(GridderStage { nufft, w_term: config.w_term, hold_bytes: config.hold_mb * 1e6, chunk_rows: config.chunk_rows, threads, keep_operator })
    }
}

impl Stage<Job> for GridderStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let (geometry, rule) = job.take_weights("gridder")?;
        let source = job.take_visibilities("gridder")?;
        let summary = source.summary();
        let (frequency_hz, bandwidth_hz) = summary.band().map_or((None, None), |(centre, width)| (Some(centre), width));
        let max_abs_w = summary.max_abs_w;
        let max_phase = crate::nufft::wgrid::max_w_phase(geometry.size, geometry.pixel_rad, max_abs_w);
        let w_term = self.w_term.includes(geometry, max_abs_w, self.nufft.epsilon);
        // With the w-term the PSF convolution is not D (the response depends on the position
        // in the field): the operator, which holds the samples, is kept for the residual
        // update. Otherwise the samples are gridded a chunk at a time as they are read, and
        // nothing the size of the table is ever held.
        let needs_operator = w_term || self.keep_operator;
        let in_parts = matches!(source, VisSource::Parts(_));
        if in_parts && self.keep_operator {
            return Err(Error::parameter(
                "method",
                format!("job '{}' is in parts gridded where they live, and the residual update's exact NUFFT round trip needs its samples in one process: use method: toeplitz", job.id),
            ));
        }
        let held_bytes = OPERATOR_BYTES_PER_SAMPLE * summary.samples as f64;
        let stream_operator = needs_operator && (in_parts || (source.is_streamed() && held_bytes > self.hold_bytes));
        let scheme = rule.scheme();
        let pass = |w_term: bool, chunk_rows: usize| PartPass::new(geometry, scheme, 0.0, w_term, self.nufft, self.threads, chunk_rows);
        let (dirty, psf, psf_2n, operator, kept) = if stream_operator {
            if let VisSource::Parts(parts) = &source {
                log::info!("job {}: the operator applies to the {} samples where they live ({}) at each residual update", job.id, summary.samples, parts.passes.describe());
            } else {
                let from = match &source {
                    VisSource::Streamed(table) => table.read_by_each_pass(),
                    _ => "the file".into(),
                };
                log::info!(
                    "job {}: the operator reads the {} samples again from {from} at each residual update (holding them would take about {}, above the gridder's hold_mb {})",
                    job.id,
                    summary.samples,
                    crate::limits::format_bytes(held_bytes),
                    self.hold_bytes / 1e6
                );
            }
            // Chunks as large as the hold limit allows: each costs its w-planes' FFTs.
            let chunk_rows = self.chunk_rows.max((self.hold_bytes / STREAMED_BYTES_PER_SAMPLE) as usize);
            let g = StreamedOperator::grid(source, rule, pass(w_term, chunk_rows))?;
            (g.dirty, g.psf, g.psf_2n, Some(Arc::new(DataOperator::Streamed(g.operator))), None)
        } else if needs_operator {
            if source.is_streamed() {
                crate::limits::check_memory(held_bytes, &format!("the {} samples of job '{}' held for the operator", summary.samples, job.id))
                    .map_err(|m| Error::parameter("gridder", format!("{m}: lower the gridder's hold_mb so that the samples are read from the file at each update instead")))?;
                log::info!("job {}: the operator holds the {} samples in memory (about {})", job.id, summary.samples, crate::limits::format_bytes(held_bytes));
            }
            let mut vis = source.into_held()?;
            let weight = chunk_weights(&vis.chunk(0..vis.len()), geometry, &rule)?;
            drop(rule);
            if !self.keep_operator {
                vis.frequency = Vec::new();
                vis.weight = Vec::new(); // natural weights: the total weights replace them
                vis.imaging_weight = Vec::new();
            }
            let operator = MeasurementOperator::for_mode(
                if w_term { WTermMode::On } else { WTermMode::Off },
                geometry,
                &vis.u,
                &vis.v,
                &vis.w,
                &weight,
                self.nufft,
                self.threads,
            )?;
            let (dirty, psf) = operator.dirty_image_and_psf(&vis.vis);
            if !self.keep_operator {
                vis.vis = Vec::new();
                vis.w = Vec::new();
            }
            let psf_2n = doubled_psf(geometry, &vis.u, &vis.v, &weight, operator.kappa(), self.nufft, self.threads)?;
            let kept = self.keep_operator.then_some(vis);
            (dirty, psf, psf_2n, Some(Arc::new(DataOperator::Held(operator))), kept)
        } else {
            // Gridded a chunk at a time as read (or where its parts live), then released.
            let images = source_images(&source, &pass(false, self.chunk_rows), &rule)?.normalise(geometry.size)?;
            drop(source);
            (images.dirty, images.psf, images.psf_2n, None, None)
        };
        let planes = operator.as_ref().and_then(|op| op.w_planes());
        let toeplitz_inexact = w_term.then(|| {
            format!("the operator includes the w-term (phase up to {max_phase:.3} rad over the field), which a PSF convolution does not")
        });
        match (w_term, self.w_term) {
            (true, _) => log::info!(
                "job {}: the w-term is corrected by w-gridding ({} w-planes; |w| up to {max_abs_w:.4e} wavelengths turns the phase by up to {max_phase:.3} rad at the field's corners)",
                job.id,
                planes.unwrap_or(1)
            ),
            (false, WTermMode::Off) => {
                if let Some(warning) = (crate::imaging::WTerm { max_abs_w, max_phase_rad: max_phase }).warning(geometry) {
                    job.warn(format!("{warning} (w_term: off)"));
                }
            }
            (false, _) => log::info!("job {}: the w-term is left out: it turns no phase by more than {max_phase:.2e} rad over the field (below the NUFFT's accuracy)", job.id),
        }
        job.settings.insert(
            "w_term".into(),
            serde_json::json!({"mode": self.w_term.name(), "corrected": w_term, "planes": planes, "max_abs_w": max_abs_w, "max_phase_rad": max_phase}),
        );
        crate::sanity::check_image(&dirty, geometry.size, "dirty image", "the visibilities or weights hold values too large to image (check the data column and the weights)")?;
        let psf_convolution = PsfConvolution::new(geometry.size, &psf_2n)?;
        let beam = match crate::deconv::restoring_beam(&psf, geometry.size, geometry.pixel_rad) {
            Ok((b, warning)) => {
                if let Some(w) = warning {
                    job.warn(w);
                }
                Some(b)
            }
            Err(e) => {
                job.warn(format!("no restoring beam: {e}"));
                None
            }
        };
        let n = geometry.pixels();
        job.imaging = Some(Imaging {
            geometry,
            residual: dirty.clone(),
            dirty,
            psf,
            psf_convolution: Arc::new(psf_convolution),
            psf_2n: Arc::new(psf_2n),
            operator,
            toeplitz_inexact,
            nufft: self.nufft,
            w_term,
            model: vec![0.0; n],
            beam,
            frequency_hz,
            bandwidth_hz,
            best: None,
        });
        if let Some(vis) = kept {
            job.vis = Some(VisSource::Held(Arc::new(vis)));
        }
        emit(Port::Next, job)
    }
}
