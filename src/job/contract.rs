//! How jobs plug into the pipeline machinery: the [`Payload`] the machinery sees, and its
//! generic types instanced for jobs.

use super::product::Product;
use super::run::RunContext;
use super::source::SourceParams;
use super::state::Job;
use crate::pipeline::{self, Payload, PipelineSpec, Role, Source, StageKind, StageParams, StageSpec};
use crate::Result;
use std::marker::PhantomData;

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
    type SourceInfo = dyn SourceParams;
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

/// Builds a source from its parameters (and the rest of the build context).
pub type SourceBuild<P> = fn(P, &BuildContext<'_>) -> Result<Box<dyn Source<Job>>>;

/// A source stage kind, made of its parameters' type (its YAML `kind` is `P::KIND`, what it
/// says of its jobs `P`'s [`SourceParams`]) and its constructor: registered as one line,
/// `registry.register(SourceKind::new(MySource::new))`.
pub struct SourceKind<P> {
    build: SourceBuild<P>,
    params: PhantomData<fn() -> P>,
}

impl<P> SourceKind<P> {
    pub const fn new(build: SourceBuild<P>) -> SourceKind<P> {
        SourceKind { build, params: PhantomData }
    }
}

impl<P> Clone for SourceKind<P> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<P> Copy for SourceKind<P> {}

impl<P: StageParams + SourceParams> StageKind<Job> for SourceKind<P> {
    fn name(&self) -> &str {
        P::KIND
    }
    fn role(&self) -> Role {
        Role::Source
    }
    fn produces(&self) -> Vec<Product> {
        vec![Product::Visibilities]
    }
    fn build(&self, ctx: &BuildContext<'_>) -> Result<Built> {
        Ok(Built::Source((self.build)(ctx.params()?, ctx)?))
    }
    fn source_info(&self, pipeline: &PipelineSpec, stage: &StageSpec) -> Result<Option<Box<dyn SourceParams>>> {
        Ok(Some(Box::new(pipeline.stage_params::<P>(stage)?)))
    }
}
