//! Classical deconvolution in the image plane: Högbom CLEAN minor cycles, the final CLEAN's
//! major cycles on what a series leaves, the restoring beam fitted to the PSF main lobe,
//! restoration of a model with that beam; and the emission mask a network series' model is
//! kept to (found from the residual as the series runs).
//!
//! Images follow `operator`'s conventions: row-major `x[iy * N + ix]`, PSF peak 1 at
//! `(N/2, N/2)`, doubled PSF `2N x 2N` with its peak at `(N, N)`. In pixel terms east is `-x`
//! and north `+y`, so a position angle (east of north) turns from `+y` towards `-x`.

mod beam;
mod blur;
mod emission_mask;
pub mod final_clean;
mod hogbom;
mod restore;

pub use beam::{restoring_beam, Beam, BeamFit};
pub use blur::gaussian_blur;
pub use emission_mask::{main_lobe_fwhm_px, EmissionMask, DEFAULT_AUTO_MASK};
pub use hogbom::{hogbom, HogbomParams};
pub use restore::restore;

/// WSClean's usual `-mgain`: the fraction of the residual's peak a major cycle cleans away.
pub const DEFAULT_MAJOR_GAIN: f64 = 0.8;

#[cfg(test)]
mod tests;
