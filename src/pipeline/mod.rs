//! The pipeline machinery: stages on their own threads, connected by bounded channels, built
//! from a YAML description by a registry of stage kinds, with cancellation.
//!
//! It knows nothing of what flows through it: everything here is generic over a [`Payload`]
//! (the imaging engine's is `crate::job::Job`), which names the products a stage may need
//! from an item and the context every stage is built with. The domain plugs into these
//! contracts; this module imports nothing of it (see `docs/architecture.md`).

pub(crate) mod cancel;
pub(crate) mod config;
pub(crate) mod graph;
pub(crate) mod located;
pub(crate) mod registry;
pub(crate) mod runner;
pub(crate) mod stage;

pub use config::{PipelineSpec, StageParams, StageSpec};
pub use registry::{BuildContext, Built, KindFn, Registry, Role, StageKind};
pub use runner::{Progress, RunReport};
pub use stage::{Emit, Payload, Port, ProductKind, Source, Stage};
