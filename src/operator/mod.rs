//! The measurement operator and the normal operator `D = kappa Re{Phi^H Phi}` in each of its
//! forms, with the plan that chooses among them; numerics only (nothing of files, channels or
//! configuration).
//!
//! - [`geometry`]: the image's size and pixel, and the one decision of the pixel size.
//! - [`measurement`]: `Phi` (coplanar or with the w-term), the dirty image, PSF and `kappa` it
//!   gives, `D` by a NUFFT round trip, the prediction of visibilities, the spectral norm.
//! - [`psf`]: images gridded in chunks with no operator held, and `D` as a convolution with
//!   the 2N PSF (exact for coplanar data).
//! - [`toeplitz`]: `D` with the w-term as one convolution per w-plane.
//! - [`taylor`]: `D` with a small w-term as a Taylor series in `w` of the PSF convolution.
//! - [`plan`]: which of these forms a job's `D` takes, why, and what it costs.
//!
//! Conventions (see `docs/conventions.md`): a source of flux S at direction cosines (l, m)
//! has visibility `S exp(+2 pi i (u l + v m))`; images are row-major `x[iy * N + ix]` with
//! `l = -pixel (ix - N/2)` (RA increases to the left, as FITS with CDELT1 < 0 shows it) and
//! `m = pixel (iy - N/2)`. `omega_k` is the total weight of visibility k: natural weight times
//! imaging weight (the reference code's `(nW * nWimag)^2`).

pub mod geometry;
pub mod measurement;
pub mod plan;
pub mod psf;
pub mod taylor;
pub mod toeplitz;

pub use geometry::{ImageGeometry, PixelScale, DEFAULT_SUPERRESOLUTION};
pub use measurement::{predict, spectral_norm, MeasurementOperator, Visibility, WTermMode};
pub(crate) use measurement::check_points;
pub use plan::OperatorPlan;
pub use psf::{dirty_and_psf, doubled_psf, doubled_psf_of, normalise_by_psf_peak, DirtyAndPsf, DoubledKernelGridder, GriddedImages, ImageGridder, PsfConvolution};
pub(crate) use psf::chunk_points;
pub use taylor::WTaylor;
pub use toeplitz::{WToeplitz, WToeplitzBuilder, WToeplitzPlan};
