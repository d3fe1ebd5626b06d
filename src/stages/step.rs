//! Network-step stages (`kind: clean`, `onnx`, `native`): run the job's next step of
//! the series and pass it to the residual update.

use crate::job::{Emit, Job};
use crate::pipeline::{Port, Stage};
use crate::steps::clean::{CleanConfig, CleanStep};
use crate::steps::onnx::{OnnxConfig, OnnxStep};
use crate::steps::series::ImagingSetup;
use crate::steps::native::{NativeConfig, NativeStep};
use crate::steps::{JobDomain, NetworkStep, StepInput};
use crate::Result;
use std::time::Instant;

pub struct StepStage {
    kind: &'static str,
    step: Box<dyn NetworkStep>,
}

impl StepStage {
    pub fn clean(config: CleanConfig) -> Result<StepStage> {
        Ok(StepStage { kind: "clean", step: Box::new(CleanStep::new(config)?) })
    }

    /// An R2D2/R3D3 series for `size x size` images (checked now, before any job runs).
    pub fn onnx(config: OnnxConfig, size: usize, threads: usize, setup: &ImagingSetup) -> Result<StepStage> {
        Ok(StepStage { kind: "onnx", step: Box::new(OnnxStep::new(&config, size, threads, setup)?) })
    }

    /// Loads and creates the plugin now, so that every plugin error comes before imaging.
    pub fn native(config: NativeConfig, image_size: usize, stage: &str) -> Result<StepStage> {
        Ok(StepStage { kind: "native", step: Box::new(NativeStep::new(config, image_size, stage)?) })
    }
}

impl StepStage {
    /// Before `iteration` of a step of several realisations: when the previous realisation has
    /// run its series, keep its final model and start the next from the dirty image (model 0,
    /// residual = dirty). True once every realisation is done.
    fn next_realisation(&self, job: &mut Job, iteration: usize, realisations: usize) -> Result<bool> {
        let per = self.step.series_length() / realisations;
        if iteration > 1 && (iteration - 1) % per == 0 {
            let im = job.imaging_mut(self.kind)?;
            let done = std::mem::replace(&mut im.model, vec![0.0; im.dirty.len()]);
            im.residual = im.dirty.clone();
            job.realisation_models.push(done);
        }
        job.realisation = (iteration - 1) / per + 1;
        Ok(job.realisation_models.len() == realisations)
    }
}

impl Stage<Job> for StepStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let began = Instant::now();
        let iteration = job.iteration + 1;
        let realisations = self.step.realisations();
        if realisations > 1 && self.next_realisation(&mut job, iteration, realisations)? {
            // Every realisation is done: the image is their mean, whose residual comes next.
            let mean = crate::metrics::pixel_mean(&job.realisation_models);
            job.imaging_mut(self.kind)?.model = mean;
            job.realisation = 0;
            job.iteration = iteration;
            job.series_finished = true;
            job.last_step_seconds = began.elapsed().as_secs_f64();
            return emit(Port::Next, job);
        }
        if iteration == 1 {
            // Before a job's first step: is it inside what the step was made for?
            let dirty_mean = job.imaging.as_ref().map(|im| im.dirty.iter().sum::<f64>() / im.dirty.len().max(1) as f64);
            let domain = JobDomain {
                telescope: &job.meta.telescope,
                superresolution: job.superresolution,
                track_hours: job.track_hours,
                integration_s: job.integration_s,
                dirty_mean,
            };
            for problem in self.step.domain_problems(&domain)? {
                job.warn(problem);
            }
            if let Some(described) = self.step.describe() {
                job.settings.insert("step".into(), described);
            }
        }
        let Job { id, imaging, .. } = &mut job;
        let im = imaging.as_mut().ok_or_else(|| crate::job::missing(self.kind, id, crate::job::Product::Imaging))?;
        let input = StepInput {
            job: id,
            size: im.geometry.size,
            model: &im.model,
            residual: &im.residual,
            dirty: &im.dirty,
            psf: &im.psf,
            psf_2n: &im.psf_2n,
            psf_convolution: &im.psf_convolution,
        };
        let model = self.step.step(iteration, &input)?;
        let cause = format!("the {} step made it from a finite residual: a diverging network or plugin", self.kind);
        crate::sanity::check_image(&model, im.geometry.size, &format!("model after step {iteration}"), &cause)?;
        im.model = model;
        job.iteration = iteration;
        job.series_finished = realisations == 1 && iteration >= self.step.series_length();
        job.series_length = self.step.series_length();
        job.early_stop_from = self.step.early_stop_from();
        job.step_kind = Some(self.kind.to_string());
        job.restores = self.step.restores();
        job.last_step_seconds = began.elapsed().as_secs_f64();
        emit(Port::Next, job)
    }

    fn finish(&mut self) -> Result<()> {
        self.step.finish()
    }
}
