//! How jobs plug into the pipeline machinery: the [`Payload`] the machinery sees, and its
//! generic types instanced for jobs.

use super::product::Product;
use super::run::RunContext;
use super::state::Job;
use crate::pipeline::{self, Payload};

/// The stage kinds jobs may pass through, by name.
pub type Registry = pipeline::Registry<Job>;
/// What a stage kind may look at while building a stage for jobs.
pub type BuildContext<'a> = pipeline::BuildContext<'a, Job>;
/// A stage built for jobs.
pub type Built = pipeline::Built<Job>;
/// A stage kind for jobs made of plain functions (how the built-in kinds are declared).
pub type KindFn = pipeline::KindFn<Job>;
/// Sends a job on one of a stage's ports.
pub type Emit<'a> = pipeline::Emit<'a, Job>;

impl Payload for Job {
    type Product = Product;
    type Context = RunContext;
    fn id(&self) -> &str {
        &self.id
    }
    fn iteration(&self) -> usize {
        self.iteration
    }
    fn iterations_planned(&self) -> usize {
        self.series_length
    }
    fn add_stage_seconds(&mut self, stage: &str, seconds: f64) {
        *self.stage_seconds.entry(stage.to_string()).or_insert(0.0) += seconds;
    }
}

