//! `kind: gridder`: dirty image, PSF (N and 2N), kappa and the restoring beam. Releases the
//! visibilities unless the residual update runs a NUFFT round trip.

use super::params::GridderParams;
use crate::nufft::NufftParams;
use crate::operator::{dirty_and_psf, doubled_psf, MeasurementOperator, PsfConvolution};
use crate::job::{Emit, Imaging, Job};
use crate::pipeline::{Port, Stage};
use crate::Result;
use std::sync::Arc;

pub struct GridderStage {
    nufft: NufftParams,
    threads: usize,
    keep_operator: bool,
}

impl GridderStage {
    pub fn new(config: GridderParams, threads: usize, keep_operator: bool) -> Result<GridderStage> {
        let nufft = NufftParams { epsilon: config.epsilon, oversampling: config.oversampling };
        crate::nufft::kernel::KernelShape::for_accuracy(nufft.epsilon, nufft.oversampling)?;
        Ok(GridderStage { nufft, threads, keep_operator })
    }
}

impl Stage<Job> for GridderStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let (geometry, weight) = job.take_weights("gridder")?;
        let mut vis = job.take_visibilities("gridder")?;
        let (frequency_hz, bandwidth_hz) = vis.band().map_or((None, None), |(centre, width)| (Some(centre), width));
        // Memory: each column goes as soon as nothing further needs it. The residual's NUFFT
        // method keeps everything.
        if !self.keep_operator {
            vis.w = Vec::new();
            vis.frequency = Vec::new();
            vis.weight = Vec::new(); // natural weights: `weight` (set by the weighting stage) replaces them
        }
        // Without a NUFFT residual no operator is kept, so the dirty image and PSF are
        // gridded in chunks and nothing the size of the table is built beside it.
        let (dirty, psf, kappa, operator) = if self.keep_operator {
            let operator = MeasurementOperator::new(geometry, &vis.u, &vis.v, &weight, self.nufft, self.threads)?;
            let dirty = operator.dirty_image(&vis.vis);
            (dirty, operator.psf(), operator.kappa(), Some(Arc::new(operator)))
        } else {
            let images = dirty_and_psf(geometry, &vis.u, &vis.v, &weight, &vis.vis, self.nufft, self.threads)?;
            vis.vis = Vec::new();
            (images.dirty, images.psf, images.kappa, None)
        };
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
