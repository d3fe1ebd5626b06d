//! The normal operator `D` and the measurement operator it comes from, in each of its forms.
mod measurement;
pub mod taylor;
pub mod toeplitz;

pub use measurement::*;
