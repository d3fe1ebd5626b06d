//! The imaging job: one dataset being imaged, with what the stages have made of it (its
//! imaging set-up, the loop's iterates and figures), the products a stage may need from it,
//! and how it plugs into the pipeline machinery ([`crate::pipeline::Payload`]).
//!
//! A job flows source -> weighting -> gridder -> (network step <-> residual update)* ->
//! writer. The machinery (`crate::pipeline`) is generic; the aliases here ([`Registry`],
//! [`BuildContext`], ...) are its instances for jobs, as the built-in stages and an embedding
//! program use them.

mod channels;
mod contract;
#[cfg(feature = "ms")]
mod model_column;
mod parts;
mod product;
mod products;
mod run;
mod source;
mod state;
mod stopping;

pub use channels::ChannelProducts;
pub(crate) use channels::{group_label, MFS_LABEL};
pub use contract::{BuildContext, Built, Emit, KindFn, Registry, SourceKind};
pub use product::Product;
#[cfg(feature = "ms")]
pub use model_column::write_job_model;
pub use parts::{emit_parts, emit_streamed, emit_parted, job_id_problem, stem_id, Truth};
pub use products::{check_spares_inputs, record_command_line, JobProducts, ProductSet, WriteOptions};
pub(crate) use products::{beam_telescope, Staged};
pub use run::{FilesWritten, ImageContext, ProductSink, RunContext};
pub use source::{Reads, SourceParams};
pub use state::{Imaging, Iterate, IterationMetrics, Job, LoopStop, StopReason};
pub(crate) use state::iteration_figures;
pub use stopping::{StopRule, DIVERGING_RISE};
pub(crate) use state::missing;
