//! r2d2-imaging: radio-interferometric imaging with R2D2 deep-network series.
//!
//! The numerical modules (`nufft`, `weighting`, `operator`, `simulate`, `metrics`) know
//! nothing of files, channels or configuration; `vis` and `fits` are the file formats, and
//! `imaging` ties operator and weighting into the dirty products.

pub mod allocator;
pub mod bench;
pub mod deconv;
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
pub mod pipeline;
pub mod preview;
pub mod progress;
pub mod sanity;
pub mod simulate;
pub mod staging;
pub mod stages;
pub mod steps;
pub mod vis;
pub mod weighting;

pub use error::{Error, Result};
