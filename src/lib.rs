//! r2d2-imaging: radio-interferometric imaging with R2D2 deep-network series.
//!
//! The numerical modules (`nufft`, `weighting`, `operator`, `simulate`, `metrics`) know
//! nothing of files, channels or configuration; `vis` and `fits` are the file formats, and
//! `imaging` ties operator and weighting into the dirty products.

pub mod allocator;
pub mod bench;
pub mod deconv;
mod engine;
pub mod error;
pub mod fft2;
pub mod fits;
pub mod imaging;
pub mod ingest;
pub mod limits;
pub mod metrics;
#[cfg(feature = "ms")]
pub mod ms;
pub mod nufft;
pub mod operator;
pub mod parallel;
pub mod pipeline;
pub mod preview;
pub mod products;
pub mod progress;
pub mod simulate;
pub mod staging;
pub mod stages;
pub mod steps;
pub mod vis;
pub mod weighting;

pub use engine::{is_ms, BackendChoice, Engine, EngineOptions, GraphOptimization, ImageParams, Observation, ProgressObserver, StepChoice};
pub use error::{Error, Result};
pub use pipeline::{
    BuildContext, Built, Emit, ImageConfig, IterationMetrics, Job, KindFn, MemoryInput, PipelineSpec, Product, ProductSink, Progress,
    Registry, Role, RunReport, Source, Stage, StageKind, StageSpec,
};
pub use products::{JobProducts, WriteOptions};
pub use weighting::Weighting;
