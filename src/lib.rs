//! r2d2-imaging: radio-interferometric imaging with R2D2 deep-network series.
//!
//! The front door is the [`Engine`] (docs/embedding.md): stage kinds in a [`Registry`],
//! pipelines as [`PipelineSpec`]s (from YAML or built in code), observations in as files or
//! Arrow record batches ([`MemoryInput`]), products out as files or arrays ([`JobProducts`]).
//! A pipeline built in code names its stages' parameters with the typed structs of
//! [`params`] ([`StageSpec::typed`]).
//!
//! The numerical modules (`nufft`, `weighting`, `operator`, `simulate`, `metrics`) know
//! nothing of files, channels or configuration; `vis` holds the visibilities and their table
//! formats, `fits` the image files, and `imaging` ties operator and weighting into the dirty
//! products. The pipeline's machinery (`pipeline`, `stages`, `steps`) is internal but for the
//! contracts the facade re-exports.

mod deconv;
mod engine;
pub mod error;
mod fft2;
pub mod fits;
pub mod imaging;
pub mod job;
pub mod metrics;
#[cfg(feature = "ms")]
pub mod ms;
pub mod nufft;
pub mod operator;
mod parallel;
pub mod pipeline;
pub mod preview;
pub mod request;
mod sanity;
pub mod simulate;
mod stages;
pub mod steps;
pub mod vis;
pub mod weighting;

// For the `r2d2` binary and the benches, not part of the library's interface.
#[doc(hidden)]
pub mod allocator;
#[doc(hidden)]
pub mod bench;
#[doc(hidden)]
pub mod limits;
#[doc(hidden)]
pub mod progress;
#[doc(hidden)]
pub mod staging;

pub use engine::{is_ms, BackendChoice, Engine, EngineOptions, GraphOptimization, Observation, ProgressObserver};
pub use request::{GridOptions, ImageRequest, MsOptions, StepOptions};
pub use error::{Error, Result};
pub use parallel::claim_process;
pub use imaging::ImageConfig;
pub use job::{
    BuildContext, Built, Emit, ImageContext, Imaging, Iterate, IterationMetrics, Job, JobProducts, KindFn, LoopStop, Product, ProductSink, Reads, Registry,
    RunContext, SourceKind, SourceParams, StopReason, WriteOptions,
};
pub use pipeline::{Payload, PipelineSpec, Port, Progress, Role, RunReport, Source, Stage, StageKind, StageParams, StageSpec};
pub use vis::MemoryInput;
/// Reading visibility tables into jobs (the file and memory sources share it).
pub use stages::params;
pub use weighting::{Weighting, WeightingScheme};
