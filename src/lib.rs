//! r2d2-imaging: radio-interferometric imaging with R2D2 deep-network series.
//!
//! The front door is the [`Engine`] (docs/embedding.md): an [`ImageRequest`] or a pipeline
//! ([`PipelineSpec`], from YAML or built in code with the typed parameters of [`params`]) runs
//! on observations given as files or Arrow record batches ([`MemoryInput`]); products come out
//! as files or arrays ([`JobProducts`]). New stage kinds, sources and network steps plug in
//! through [`Registry`], [`StageKind`], [`SourceKind`] and [`NetworkStep`].
//!
//! Beside the engine, a few tools with small surfaces: [`fits`] (image files), [`vis`]
//! (visibility tables), [`simulate`] (observations of a sky), [`metrics`], [`imaging`] (dirty
//! image, PSF and the normal operator `D`), [`parts`] (one observation
//! gridded where its parts live), [`models`] (series on disk) and [`cli`] (the `r2d2` command). The machinery (pipeline
//! runner, stages, gridder, deconvolution, readers) is private.

pub mod cli;
pub mod error;
pub mod fits;
pub mod imaging;
pub mod metrics;
pub mod models;
pub mod parts;
pub mod request;
pub mod simulate;
pub mod vis;
pub mod weighting;

mod allocator;
mod bench;
mod deconv;
mod engine;
mod fft2;
mod job;
mod limits;
#[cfg(feature = "ms")]
mod ms;
mod nufft;
mod operator;
mod parallel;
mod pipeline;
mod preview;
mod primary_beam;
mod progress;
mod sanity;
mod stages;
mod staging;
mod steps;

pub use allocator::LargeBlocksOnHugePages;
pub use engine::{BackendChoice, Engine, EngineOptions, GraphOptimization, Observation, ProgressObserver};
pub use error::{Error, Result};
pub use imaging::ImageConfig;
pub use job::{
    BuildContext, Built, ChannelProducts, Emit, ImageContext, Imaging, Iterate, IterationMetrics, Job, JobProducts, KindFn, LoopStop, Product, ProductSink, Reads, Registry,
    RunContext, SourceKind, SourceParams, StopReason, StopRule, WriteOptions,
};
pub use nufft::NufftParams;
pub use parallel::claim_process;
pub use pipeline::{Payload, PipelineSpec, Port, Progress, Role, RunReport, Source, Stage, StageKind, StageParams, StageSpec};
pub use request::{DirtyRequest, GridOptions, ImageRequest, MsOptions, NamedValue, StepOptions};
/// The typed parameters of the built-in stage kinds, for pipelines built in code.
pub use stages::params;
pub use nufft::SimdLevel;
pub use operator::PsfConvolution;
pub use steps::driven::{Cycle, DrivenConfig, DrivenOutcome, DrivenSeries};
pub use steps::series::ImagingSetup;
pub use steps::{JobDomain, NetworkStep, StepInput};
pub use vis::MemoryInput;
pub use weighting::{Weighting, WeightingScheme};
