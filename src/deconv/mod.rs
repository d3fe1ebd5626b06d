//! Classical deconvolution in the image plane: Högbom CLEAN minor cycles, the restoring beam
//! fitted to the PSF main lobe, and restoration of a model with that beam.
//!
//! Images follow `operator`'s conventions: row-major `x[iy * N + ix]`, PSF peak 1 at
//! `(N/2, N/2)`, doubled PSF `2N x 2N` with its peak at `(N, N)`. In pixel terms east is `-x`
//! and north `+y`, so a position angle (east of north) turns from `+y` towards `-x`.

mod beam;
mod hogbom;
mod restore;

pub use beam::{restoring_beam, Beam, BeamFit};
pub use hogbom::{hogbom, HogbomParams};
pub use restore::restore;

#[cfg(test)]
mod tests;
