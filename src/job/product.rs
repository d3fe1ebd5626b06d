//! What a stage may need from a job, checked along the graph before a run.

use crate::pipeline::ProductKind;

/// What a stage needs a job to carry, or adds to it: checked along the graph before anything
/// runs, so that a missing stage is an error about the pipeline, not about a job.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Product {
    /// The visibilities and their metadata (sources).
    Visibilities,
    /// Image geometry and the total weight of each visibility (weighting).
    Weights,
    /// Dirty image, PSF and the estimate being improved (gridder).
    Imaging,
    /// The measurement operator and the visibilities, kept past gridding for an exact
    /// residual update (asked for by a `residual` stage with `method: nufft`).
    Operator,
    /// An estimate made by a network step. A stage that consumes one updates a residual: the
    /// gridder makes a form of `D` only where one is downstream (else the job's products are
    /// its dirty image and PSFs, as `r2d2 dirty` writes them).
    Model,
}

impl ProductKind for Product {
    fn describe(self) -> (&'static str, &'static str) {
        match self {
            Product::Visibilities => ("visibilities", "a source"),
            Product::Weights => ("weights", "a weighting stage"),
            Product::Imaging => ("a dirty image and PSF", "a gridder stage"),
            Product::Operator => ("the measurement operator", "a gridder stage"),
            Product::Model => ("a model", "a network step (clean, onnx, native)"),
        }
    }
}

