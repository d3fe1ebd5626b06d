//! Network-step stages (`kind: clean`, `onnx`, `native`): run the job's next step of
//! the series and pass it to the residual update.

use crate::pipeline::{Emit, Job, Port, Stage};
use crate::steps::clean::{CleanConfig, CleanStep};
use crate::steps::onnx::{OnnxConfig, OnnxStep};
use crate::steps::native::{NativeConfig, NativeStep};
use crate::steps::{NetworkStep, StepInput};
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
    pub fn onnx(config: OnnxConfig, size: usize, threads: usize) -> Result<StepStage> {
        Ok(StepStage { kind: "onnx", step: Box::new(OnnxStep::new(&config, size, threads)?) })
    }

    /// Loads and creates the plugin now, so that every plugin error comes before imaging.
    pub fn native(config: NativeConfig, image_size: usize, stage: &str) -> Result<StepStage> {
        Ok(StepStage { kind: "native", step: Box::new(NativeStep::new(config, image_size, stage)?) })
    }
}

impl Stage for StepStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let began = Instant::now();
        let iteration = job.iteration + 1;
        let Job { id, imaging, .. } = &mut job;
        let im = imaging.as_mut().ok_or_else(|| crate::pipeline::not_gridded(self.kind, id))?;
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
        im.model = model;
        job.iteration = iteration;
        job.series_finished = iteration >= self.step.series_length();
        job.step_kind = Some(if self.step.restores() { format!("{}+restore", self.kind) } else { self.kind.to_string() });
        job.last_step_seconds = began.elapsed().as_secs_f64();
        emit(Port::Next, job)
    }
}
