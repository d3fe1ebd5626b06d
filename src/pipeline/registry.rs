//! The contract between the engine and its stage kinds: a [`Registry`] maps a YAML `kind` to a
//! [`StageKind`], which says what role the stage plays in the graph, what it needs from a job
//! and adds to it, and builds the stage from its parameters. The built-in kinds register
//! themselves in `crate::stages::builtin`; an embedding program adds its own the same way.

use super::config::{ImageConfig, PipelineSpec, StageParams, StageSpec};
use super::io::{MemoryInput, ProductSink};
use super::stage::{Source, Stage};
use crate::{Error, Result};
use serde::de::DeserializeOwned;
use std::sync::{Arc, Mutex};

/// What a stage does in the graph.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// Produces jobs (no input).
    Source,
    /// One job in, one job out.
    Transform,
    /// A network step of the imaging loop.
    Step,
    /// The residual update closing the loop (`to`: back to the step, `done`: out).
    Residual,
    /// Ends the pipeline (writers, the product sink).
    Sink,
}

/// What a stage needs a job to carry, or adds to it: checked along the graph before anything
/// runs, so that a missing stage is an error about the pipeline, not about a job.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Product {
    /// The visibilities and their metadata (sources).
    Visibilities,
    /// Image geometry and the total weight of each visibility (weighting).
    Weights,
    /// Dirty image, PSF and the estimate being improved (gridder).
    Imaging,
    /// The measurement operator and the visibilities, kept past gridding for an exact
    /// residual update (asked for by a `residual` stage with `method: nufft`).
    Operator,
    /// An estimate made by a network step.
    Model,
}

impl Product {
    /// The product as a user reads it, and the kind of stage that makes it.
    pub(crate) fn describe(self) -> (&'static str, &'static str) {
        match self {
            Product::Visibilities => ("visibilities", "a source"),
            Product::Weights => ("weights", "a weighting stage"),
            Product::Imaging => ("a dirty image and PSF", "a gridder stage"),
            Product::Operator => ("the measurement operator", "a gridder stage"),
            Product::Model => ("a model", "a network step (clean, onnx, native)"),
        }
    }
}

/// A constructed stage, ready to run on its thread.
pub enum Built {
    Source(Box<dyn Source>),
    Stage(Box<dyn Stage>),
}

/// A stage kind: the builder of the stages of one YAML `kind`.
pub trait StageKind: Send + Sync {
    /// The YAML `kind`.
    fn name(&self) -> &str;
    fn role(&self) -> Role;
    /// What a job must carry when it reaches the stage (may depend on the parameters).
    fn consumes(&self, _ctx: &BuildContext<'_>) -> Result<Vec<Product>> {
        Ok(Vec::new())
    }
    /// What the stage adds to a job.
    fn produces(&self) -> Vec<Product> {
        Vec::new()
    }
    /// A sink that may pass its jobs on (`to`) instead of ending the pipeline.
    fn passes_on(&self) -> bool {
        false
    }
    /// Parse the parameters and construct the stage (cheap: heavy work happens per job).
    fn build(&self, ctx: &BuildContext<'_>) -> Result<Built>;
}

/// A stage kind made of plain functions: how the built-in kinds are declared.
#[derive(Clone, Copy)]
pub struct KindFn {
    pub name: &'static str,
    pub role: Role,
    pub consumes: &'static [Product],
    pub produces: &'static [Product],
    /// Products needed besides `consumes`, read from the parameters.
    pub consumes_also: Option<fn(&BuildContext<'_>) -> Result<Vec<Product>>>,
    pub passes_on: bool,
    pub build: fn(&BuildContext<'_>) -> Result<Built>,
}

impl StageKind for KindFn {
    fn name(&self) -> &str {
        self.name
    }
    fn role(&self) -> Role {
        self.role
    }
    fn consumes(&self, ctx: &BuildContext<'_>) -> Result<Vec<Product>> {
        let mut all = self.consumes.to_vec();
        if let Some(more) = self.consumes_also {
            all.extend(more(ctx)?);
        }
        Ok(all)
    }
    fn produces(&self) -> Vec<Product> {
        self.produces.to_vec()
    }
    fn passes_on(&self) -> bool {
        self.passes_on
    }
    fn build(&self, ctx: &BuildContext<'_>) -> Result<Built> {
        (self.build)(ctx)
    }
}

/// The stage kinds a pipeline may use, by name.
#[derive(Clone, Default)]
pub struct Registry {
    kinds: Vec<Arc<dyn StageKind>>,
}

impl Registry {
    /// An empty registry (`crate::stages::builtin()` gives one with the built-in kinds).
    pub fn new() -> Registry {
        Registry::default()
    }

    /// Adds a kind; a name already taken is refused.
    pub fn register(&mut self, kind: impl StageKind + 'static) -> Result<()> {
        if self.get(kind.name()).is_some() {
            return Err(Error::parameter("stage kind", format!("'{}' is registered already", kind.name())));
        }
        self.kinds.push(Arc::new(kind));
        Ok(())
    }

    pub fn get(&self, name: &str) -> Option<&dyn StageKind> {
        self.kinds.iter().find(|k| k.name() == name).map(|k| k.as_ref())
    }

    /// Every kind's name, in registration order.
    pub fn names(&self) -> Vec<&str> {
        self.kinds.iter().map(|k| k.name()).collect()
    }

    /// The names of the kinds with `role`.
    pub fn names_with_role(&self, role: Role) -> Vec<&str> {
        self.kinds.iter().filter(|k| k.role() == role).map(|k| k.name()).collect()
    }

    /// The kind of `stage`, or an error at its `kind:` line listing the known kinds.
    pub fn kind_of(&self, spec: &PipelineSpec, stage: &StageSpec) -> Result<&dyn StageKind> {
        self.get(&stage.kind).ok_or_else(|| {
            spec.stage_error(
                &stage.name,
                Some("kind"),
                &format!("stages.{}.kind: unknown kind '{}' (one of: {})", stage.name, stage.kind, self.names().join(", ")),
            )
        })
    }
}

/// What a run hands to the stages that are not files: in-memory inputs and the product sink.
/// Each is taken by the one stage that uses it.
#[derive(Default)]
pub struct RunIo {
    inputs: Mutex<Option<Vec<MemoryInput>>>,
    sink: Mutex<Option<Box<dyn ProductSink>>>,
    /// Building to check the pipeline only (`validate`): nothing will run.
    validating: bool,
}

impl RunIo {
    pub fn new(inputs: Vec<MemoryInput>, sink: Option<Box<dyn ProductSink>>) -> RunIo {
        RunIo { inputs: Mutex::new(Some(inputs)), sink: Mutex::new(sink), validating: false }
    }

    /// For `validate`: stages build as they would for a run, with nothing to read or deliver.
    pub fn validating() -> RunIo {
        RunIo { validating: true, ..RunIo::default() }
    }
}

/// Everything a stage kind may look at while building a stage.
pub struct BuildContext<'a> {
    pub pipeline: &'a PipelineSpec,
    pub stage: &'a StageSpec,
    /// Threads for the stage's numerical work (the shared pool's size; 0: all cores).
    pub threads: usize,
    /// Products consumed by the stages this one's jobs reach (empty while the products are
    /// being checked, before any stage is built).
    pub(crate) downstream: Vec<Product>,
    /// The stages (indices in file order) whose jobs reach this one, and those its jobs reach.
    pub(crate) upstream_stages: Vec<usize>,
    pub(crate) downstream_stages: Vec<usize>,
    pub(crate) io: &'a RunIo,
}

impl BuildContext<'_> {
    /// The stage's name.
    pub fn name(&self) -> &str {
        &self.stage.name
    }

    /// The pipeline's image geometry.
    pub fn image(&self) -> &ImageConfig {
        &self.pipeline.image
    }

    /// The stage's parameters as the kind's config struct; errors name the file, line and key.
    pub fn params<T: DeserializeOwned>(&self) -> Result<T> {
        self.pipeline.stage_params(self.stage)
    }

    /// The parameters of the stages of `P`'s kind whose jobs reach this one, in file order:
    /// what a kind may know of the stages before it (the weighting a network series will see),
    /// typed, without reading their YAML. Errors are about those stages' keys.
    pub fn upstream_params<P: StageParams>(&self) -> Result<Vec<P>> {
        self.params_of(&self.upstream_stages)
    }

    /// The parameters of the stages of `P`'s kind that this one's jobs reach, in file order.
    pub fn downstream_params<P: StageParams>(&self) -> Result<Vec<P>> {
        self.params_of(&self.downstream_stages)
    }

    fn params_of<P: StageParams>(&self, stages: &[usize]) -> Result<Vec<P>> {
        stages.iter().map(|&i| &self.pipeline.stages[i]).filter(|s| s.kind == P::KIND).map(|s| self.pipeline.stage_params(s)).collect()
    }

    /// An error about the stage's `key` (or the stage), at its line when the spec came from a
    /// file: `stages.<name>.<key>: <message>`.
    pub fn error(&self, key: Option<&str>, message: impl std::fmt::Display) -> Error {
        let name = &self.stage.name;
        let path = match key {
            Some(k) => format!("stages.{name}.{k}"),
            None => format!("stages.{name}"),
        };
        self.pipeline.stage_error(name, key, &format!("{path}: {message}"))
    }

    /// [`error`](Self::error) for an error that the stage's `key` led to (a series that does
    /// not load), kept as the cause so that callers can still match on its kind.
    pub fn error_caused(&self, key: &str, cause: Error) -> Error {
        let name = &self.stage.name;
        self.pipeline.stage_error_caused(name, Some(key), &format!("stages.{name}.{key}: {cause}"), cause)
    }

    /// Whether a stage downstream of this one consumes `product`.
    pub fn consumed_downstream(&self, product: Product) -> bool {
        self.downstream.contains(&product)
    }

    /// Whether the pipeline is being checked only (`validate`): nothing will run.
    pub fn validating(&self) -> bool {
        self.io.validating
    }

    /// The run's in-memory inputs (for the one source that reads them); `None` once taken.
    pub fn take_inputs(&self) -> Option<Vec<MemoryInput>> {
        self.io.inputs.lock().expect("run inputs").take()
    }

    /// The run's product sink (for the one stage that delivers to it); `None` once taken or
    /// when the run has none.
    pub fn take_sink(&self) -> Option<Box<dyn ProductSink>> {
        self.io.sink.lock().expect("run sink").take()
    }
}

/// Checks that every stage finds what it consumes made by a stage upstream of it, and
/// returns, per stage, what the stages its jobs reach consume.
pub(crate) fn check_products(
    spec: &PipelineSpec,
    reach: &[Vec<bool>],
    consumes: &[Vec<Product>],
    produces: &[Vec<Product>],
) -> Result<Vec<Vec<Product>>> {
    let n = spec.stages.len();
    for j in 0..n {
        for &p in &consumes[j] {
            let made = (0..n).any(|i| i != j && reach[i][j] && produces[i].contains(&p));
            if !made {
                let (what, maker) = p.describe();
                let stage = &spec.stages[j];
                return Err(spec.stage_error(
                    &stage.name,
                    Some("kind"),
                    &format!("stages.{}: a {} stage needs {what}, which no stage before it makes: put {maker} upstream", stage.name, stage.kind),
                ));
            }
        }
    }
    Ok((0..n)
        .map(|i| {
            let mut wanted: Vec<Product> = (0..n).filter(|&j| j != i && reach[i][j]).flat_map(|j| consumes[j].iter().copied()).collect();
            wanted.dedup();
            wanted
        })
        .collect())
}
