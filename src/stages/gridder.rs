//! `kind: gridder`: dirty image, PSF (N and 2N), kappa and the restoring beam, with the w-term
//! where it matters (`w_term`). Releases the visibilities unless the residual update runs a
//! NUFFT round trip; keeps the operator where the w-term makes the PSF convolution inexact.

use super::params::GridderParams;
use crate::nufft::NufftParams;
use crate::operator::{dirty_and_psf, doubled_psf, MeasurementOperator, PsfConvolution, WTermMode};
use crate::job::{Emit, Imaging, Job};
use crate::pipeline::{Port, Stage};
use crate::Result;
use std::sync::Arc;

pub struct GridderStage {
    nufft: NufftParams,
    w_term: WTermMode,
    threads: usize,
    keep_operator: bool,
}

impl GridderStage {
    pub fn new(config: GridderParams, threads: usize, keep_operator: bool) -> Result<GridderStage> {
        let nufft = NufftParams { epsilon: config.epsilon, oversampling: config.oversampling };
        crate::nufft::kernel::KernelShape::for_accuracy(nufft.epsilon, nufft.oversampling)?;
        Ok(GridderStage { nufft, w_term: config.w_term, threads, keep_operator })
    }
}

impl Stage<Job> for GridderStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let (geometry, weight) = job.take_weights("gridder")?;
        let mut vis = job.take_visibilities("gridder")?;
        let (frequency_hz, bandwidth_hz) = vis.band().map_or((None, None), |(centre, width)| (Some(centre), width));
        let max_abs_w = vis.w.iter().fold(0.0f64, |m, w| m.max(w.abs()));
        let max_phase = crate::nufft::wgrid::max_w_phase(geometry.size, geometry.pixel_rad, max_abs_w);
        let w_term = self.w_term.includes(geometry, max_abs_w, self.nufft.epsilon);
        // Memory: each column goes as soon as nothing further needs it. The residual's NUFFT
        // method keeps everything.
        if !self.keep_operator {
            if !w_term {
                vis.w = Vec::new();
            }
            vis.frequency = Vec::new();
            vis.weight = Vec::new(); // natural weights: `weight` (set by the weighting stage) replaces them
        }
        // With the w-term the PSF convolution is not D (the response depends on the position
        // in the field): the operator is kept for the residual update. Without it and without
        // a NUFFT residual, the dirty image and PSF are gridded in chunks and nothing the size
        // of the table is built beside it.
        let (dirty, psf, kappa, operator) = if w_term || self.keep_operator {
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
            let dirty = operator.dirty_image(&vis.vis);
            if !self.keep_operator {
                vis.vis = Vec::new();
                vis.w = Vec::new();
            }
            (dirty, operator.psf(), operator.kappa(), Some(Arc::new(operator)))
        } else {
            let images = dirty_and_psf(geometry, &vis.u, &vis.v, &weight, &vis.vis, self.nufft, self.threads)?;
            vis.vis = Vec::new();
            (images.dirty, images.psf, images.kappa, None)
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
        let psf_2n = doubled_psf(geometry, &vis.u, &vis.v, &weight, kappa, self.nufft, self.threads)?;
        drop(weight);
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
        if self.keep_operator {
            job.vis = Some(vis);
        }
        emit(Port::Next, job)
    }
}
