//! r2d2-imaging: radio-interferometric imaging with R2D2 deep-network series.
//!
//! The numerical modules (`nufft`, `weighting`, `operator`, `simulate`, `metrics`) know
//! nothing of files, channels or configuration; `vis` and `fits` are the file formats.

pub mod bench;
pub mod error;
pub mod fft2;
pub mod nufft;
pub mod simulate;

pub use error::{Error, Result};
