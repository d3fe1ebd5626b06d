//! The R2D2 step: a trained series of ONNX networks, run as the reference implementation does
//! (`../shared/reference/r2d2-conventions.md`, section "Inference loop"; docs/conventions.md).
//!
//! Iteration i (1-based) with network N_i, alpha = mean(x_{i-1}) (mean of the dirty image at
//! i = 1): the input is `[dirty/alpha, 0]` for i = 1 and `[x_{i-1}/alpha, r_{i-1}/alpha]` after
//! (image first); `x_i = max(0, (N_i(input) + x_{i-1}/alpha) * alpha)`. R3D3 components run J
//! layers on `[residual, image]` with a PSF data-fidelity update of the residual between them.
//!
//! A series of several realisations runs them one after the other, each from the dirty image:
//! the step numbers its iterations across them (realisation r's network i is iteration
//! (r - 1) I + i) and the step stage resets the job between them and images their mean.
//!
//! An image larger than the sizes a series was trained at runs each network in overlapping
//! tiles of the trained size (`tiles: auto`, `tiles.rs`), each tile one field as the series
//! knows it, blended into the image; the residual update stays global and exact.
//!
//! Networks load lazily and at most two are resident, whatever the series length. One job
//! walking the series keeps only the network running and the next, which loads on a background
//! thread while the current one infers (with `prefetch: false`, only the one running). When
//! several jobs go through the series interleaved, the two most recently used stay resident.

mod check;
mod mapped_weights;
pub mod runtime;
pub mod series;
mod step;
pub mod tiles;

pub use step::*;
