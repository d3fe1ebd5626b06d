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

pub(crate) mod geometry;
pub(crate) mod measurement;
pub(crate) mod plan;
pub(crate) mod psf;
pub(crate) mod taylor;
pub(crate) mod toeplitz;

pub use geometry::{ImageGeometry, PixelScale, DEFAULT_SUPERRESOLUTION};
pub use measurement::{spectral_norm, MeasurementOperator, NormalOperator, WTermMode};
pub(crate) use measurement::predict;
pub(crate) use measurement::check_points;
pub use psf::PsfConvolution;
pub(crate) use psf::{doubled_psf, doubled_psf_of, normalise_by_psf_peak, DoubledKernelGridder, ImageGridder};
pub(crate) use psf::chunk_points;
pub(crate) use toeplitz::WToeplitz;
