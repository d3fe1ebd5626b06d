//! Two-dimensional non-uniform FFTs between an `nx x ny` image and points in the plane.
//!
//! * type 2 ("degridding", [`Nufft2d::forward`]):
//!   `c_k = sum_{jx, jy} f[jy, jx] exp(+i (x_k jx + y_k jy))`
//! * type 1 ("gridding", [`Nufft2d::adjoint`]), its exact adjoint:
//!   `f[jy, jx] = sum_k c_k exp(-i (x_k jx + y_k jy))`
//!
//! with `jx = ix - nx/2 in [-nx/2, nx/2)` (likewise `jy`), images row-major `f[iy * nx + ix]`,
//! and point coordinates `x_k, y_k` in radians per pixel (any real value; the transform is
//! 2 pi periodic in them). Both directions spread with the exponential-of-semicircle kernel on
//! an oversampled grid, FFT with rustfft, and divide out the kernel's Fourier transform.
//! Accumulation is in f64. The w-term is not part of this transform (coplanar imaging).
//!
//! Points are sorted once per plan by grid tile so that gridding and degridding walk memory
//! in order; gridding accumulates each tile in a small private buffer and adds it to the shared
//! grid under a lock, so threads never contend per visibility. [`ChunkedAdjoint`] grids points
//! given a chunk at a time, for callers that need no plan afterwards: its memory does not grow
//! with the number of points.

// First: the macro is in scope for the modules declared after it.
#[macro_use]
mod dispatch;
#[doc(hidden)]
pub mod direct;
pub mod kernel;
mod permute;
pub mod simd;
mod transform;

pub use simd::SimdLevel;
pub use transform::{wgrid, *};
