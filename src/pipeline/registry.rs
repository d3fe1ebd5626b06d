//! How stage kinds plug in: a [`Registry`] maps a YAML `kind` to a [`StageKind`], which says
//! what role the stage plays in the graph, what it needs from an item and adds to it
//! ([`ProductKind`]s of the payload), and builds the stage from its parameters. The imaging
//! engine's built-in kinds register themselves in `crate::stages::builtin`; an embedding
//! program adds its own the same way.

use super::config::{PipelineSpec, StageParams, StageSpec};
use super::stage::{Payload, Source, Stage};
use crate::{Error, Result};
use serde::de::DeserializeOwned;
use std::sync::Arc;

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

/// A constructed stage, ready to run on its thread.
pub enum Built<J> {
    Source(Box<dyn Source<J>>),
    Stage(Box<dyn Stage<J>>),
}

/// A stage kind: the builder of the stages of one YAML `kind`.
pub trait StageKind<J: Payload>: Send + Sync {
    /// The YAML `kind`.
    fn name(&self) -> &str;
    fn role(&self) -> Role;
    /// What a job must carry when it reaches the stage (may depend on the parameters).
    fn consumes(&self, _ctx: &BuildContext<'_, J>) -> Result<Vec<J::Product>> {
        Ok(Vec::new())
    }
    /// What the stage adds to a job.
    fn produces(&self) -> Vec<J::Product> {
        Vec::new()
    }
    /// A sink that may pass its jobs on (`to`) instead of ending the pipeline.
    fn passes_on(&self) -> bool {
        false
    }
    /// Parse the parameters and construct the stage (cheap: heavy work happens per job).
    fn build(&self, ctx: &BuildContext<'_, J>) -> Result<Built<J>>;
    /// What a source stage of this kind says of the items it will make, read from its
    /// parameters alone (nothing is built, opened or read): the stages after it ask
    /// ([`BuildContext::upstream_sources`]). `None`: the kind says nothing.
    fn source_info(&self, _pipeline: &PipelineSpec, _stage: &StageSpec) -> Result<Option<Box<J::SourceInfo>>> {
        Ok(None)
    }
}

/// A stage kind made of plain functions: how the built-in kinds are declared.
pub struct KindFn<J: Payload> {
    pub name: &'static str,
    pub role: Role,
    pub consumes: &'static [J::Product],
    pub produces: &'static [J::Product],
    /// Products needed besides `consumes`, read from the parameters.
    pub consumes_also: Option<fn(&BuildContext<'_, J>) -> Result<Vec<J::Product>>>,
    pub passes_on: bool,
    pub build: fn(&BuildContext<'_, J>) -> Result<Built<J>>,
}

impl<J: Payload> Clone for KindFn<J> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<J: Payload> Copy for KindFn<J> {}

impl<J: Payload> StageKind<J> for KindFn<J> {
    fn name(&self) -> &str {
        self.name
    }
    fn role(&self) -> Role {
        self.role
    }
    fn consumes(&self, ctx: &BuildContext<'_, J>) -> Result<Vec<J::Product>> {
        let mut all = self.consumes.to_vec();
        if let Some(more) = self.consumes_also {
            all.extend(more(ctx)?);
        }
        Ok(all)
    }
    fn produces(&self) -> Vec<J::Product> {
        self.produces.to_vec()
    }
    fn passes_on(&self) -> bool {
        self.passes_on
    }
    fn build(&self, ctx: &BuildContext<'_, J>) -> Result<Built<J>> {
        (self.build)(ctx)
    }
}

/// The stage kinds a pipeline may use, by name.
pub struct Registry<J: Payload> {
    kinds: Vec<Arc<dyn StageKind<J>>>,
}

impl<J: Payload> Clone for Registry<J> {
    fn clone(&self) -> Self {
        Registry { kinds: self.kinds.clone() }
    }
}

impl<J: Payload> Default for Registry<J> {
    fn default() -> Self {
        Registry { kinds: Vec::new() }
    }
}

impl<J: Payload> Registry<J> {
    /// An empty registry (`crate::stages::builtin()` gives one with the built-in kinds).
    pub fn new() -> Registry<J> {
        Registry::default()
    }

    /// Adds a kind; a name already taken is refused.
    pub fn register(&mut self, kind: impl StageKind<J> + 'static) -> Result<()> {
        if self.get(kind.name()).is_some() {
            return Err(Error::parameter("stage kind", format!("'{}' is registered already", kind.name())));
        }
        self.kinds.push(Arc::new(kind));
        Ok(())
    }

    pub fn get(&self, name: &str) -> Option<&dyn StageKind<J>> {
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
    pub fn kind_of(&self, spec: &PipelineSpec, stage: &StageSpec) -> Result<&dyn StageKind<J>> {
        self.get(&stage.kind).ok_or_else(|| {
            spec.stage_error(
                &stage.name,
                Some("kind"),
                &format!("stages.{}.kind: unknown kind '{}' (one of: {})", stage.name, stage.kind, self.names().join(", ")),
            )
        })
    }
}

/// Everything a stage kind may look at while building a stage.
pub struct BuildContext<'a, J: Payload> {
    pub pipeline: &'a PipelineSpec,
    pub stage: &'a StageSpec,
    /// Threads for the stage's numerical work (the shared pool's size; 0: all cores).
    pub threads: usize,
    /// Products consumed by the stages this one's jobs reach (empty while the products are
    /// being checked, before any stage is built).
    pub(crate) downstream: Vec<J::Product>,
    /// The stages (indices in file order) whose jobs reach this one, and those its jobs reach.
    pub(crate) upstream_stages: Vec<usize>,
    pub(crate) downstream_stages: Vec<usize>,
    /// What the domain hands every build (see [`Payload::Context`]).
    pub context: &'a J::Context,
    /// The kinds the pipeline is built from (what the stages before this one say of their items).
    pub(crate) registry: &'a Registry<J>,
    /// Building to check the pipeline only (`validate`): nothing will run.
    pub(crate) validating: bool,
}

impl<J: Payload> BuildContext<'_, J> {
    /// The stage's name.
    pub fn name(&self) -> &str {
        &self.stage.name
    }

    /// The stage's parameters as the kind's config struct; errors name the file, line and key.
    pub fn params<T: DeserializeOwned + Clone + 'static>(&self) -> Result<T> {
        self.pipeline.stage_params(self.stage)
    }

    /// The parameters of the stages of `P`'s kind whose jobs reach this one, in file order:
    /// what a kind may know of the stages before it (the weighting a network series will see),
    /// typed, without reading their YAML. Errors are about those stages' keys.
    pub fn upstream_params<P: StageParams>(&self) -> Result<Vec<P>> {
        self.params_of(&self.upstream_stages)
    }

    /// The stages whose jobs reach this one, as (name, kind), in file order.
    pub fn upstream_stages(&self) -> Vec<(&str, &str)> {
        self.upstream_stages.iter().map(|&i| &self.pipeline.stages[i]).map(|s| (s.name.as_str(), s.kind.as_str())).collect()
    }

    /// The source stages whose jobs reach this one, in file order, each with what its kind says
    /// of its jobs ([`StageKind::source_info`]; a kind that says nothing is left out). Errors
    /// are about those stages' keys.
    pub fn upstream_sources(&self) -> Result<Vec<(&StageSpec, Box<J::SourceInfo>)>> {
        let mut sources = Vec::new();
        for stage in self.upstream_stages.iter().map(|&i| &self.pipeline.stages[i]) {
            if let Some(info) = self.registry.get(&stage.kind).map(|k| k.source_info(self.pipeline, stage)).transpose()?.flatten() {
                sources.push((stage, info));
            }
        }
        Ok(sources)
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

    /// A constructor's parameter error ([`Error::Parameter`]) at the line of the stage key it
    /// names, else the error as it is. The library names the fields of the parameters it was
    /// given (`params`): the stage's keys, as `params` serializes them.
    pub fn at_field(&self, params: &impl serde::Serialize, e: Error) -> Error {
        let is_key = |name: &str| serde_yaml::to_value(params).is_ok_and(|fields| fields.get(name).is_some());
        match &e {
            Error::Parameter { name, .. } if is_key(name) => self.error_caused(&name.clone(), e),
            _ => e,
        }
    }

    /// Whether a stage downstream of this one consumes `product`.
    pub fn consumed_downstream(&self, product: J::Product) -> bool {
        self.downstream.contains(&product)
    }

    /// Whether the pipeline is being checked only (`validate`): nothing will run.
    pub fn validating(&self) -> bool {
        self.validating
    }
}

/// Checks that every stage finds what it consumes made by a stage upstream of it, and
/// returns, per stage, what the stages its jobs reach consume.
pub(crate) fn check_products<P: super::stage::ProductKind>(
    spec: &PipelineSpec,
    reach: &[Vec<bool>],
    consumes: &[Vec<P>],
    produces: &[Vec<P>],
) -> Result<Vec<Vec<P>>> {
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
            let mut wanted: Vec<P> = (0..n).filter(|&j| j != i && reach[i][j]).flat_map(|j| consumes[j].iter().copied()).collect();
            wanted.dedup();
            wanted
        })
        .collect())
}
