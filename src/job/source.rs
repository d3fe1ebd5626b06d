//! What a source says of its jobs before any is read ([`SourceParams`]): answered by each
//! source kind's parameters, in the kind's own file, and handed to the stages after it by the
//! kind ([`SourceKind`](super::SourceKind)).
//!
//! A writer asks whether a model column can be written (`model_column` needs a
//! MeasurementSet), and whether several jobs may reach one prefix; an `auto` step asks the
//! telescope. They ask the sources upstream through the registry
//! ([`BuildContext::upstream_sources`](crate::pipeline::BuildContext::upstream_sources)), so
//! no list of source kinds is kept anywhere: a source kind is its file and its registration.

use crate::Result;
use std::path::PathBuf;

/// What a source reads its jobs' visibilities from, as the stages after it need to know.
#[derive(Clone, Debug, PartialEq)]
pub enum Reads {
    /// Table files, as named (a glob pattern among them is not a file until expanded).
    Files(Vec<PathBuf>),
    /// A MeasurementSet, whose columns a writer may predict the model into.
    MeasurementSet(PathBuf),
    /// Record batches the embedding program hands in, which may carry a MeasurementSet's
    /// origin (batches an MS reader made, its origin in their metadata).
    Memory,
    /// Nothing: the source makes its data (a simulation).
    Nothing,
}

impl Reads {
    /// Whether the jobs may come from a MeasurementSet (a writer's `model_column` needs one).
    pub fn may_be_measurement_set(&self) -> bool {
        matches!(self, Reads::MeasurementSet(_) | Reads::Memory)
    }

    /// The files named, in order (a MeasurementSet's directory included).
    pub fn paths(&self) -> &[PathBuf] {
        match self {
            Reads::Files(paths) => paths,
            Reads::MeasurementSet(path) => std::slice::from_ref(path),
            Reads::Memory | Reads::Nothing => &[],
        }
    }
}

/// What a source says of its jobs from its parameters alone (nothing is opened but for the
/// telescope a file names): implemented by each source kind's parameters, in the kind's file.
pub trait SourceParams: Send + Sync {
    /// What the source reads.
    fn reads(&self) -> Reads;

    /// Why the source may make several jobs (a list or pattern of files, a `split_by`, several
    /// seeds), if it may: a writer whose prefix has no `{job}` is then refused before anything
    /// runs. `None` where it makes one, or cannot tell before it runs.
    fn several_jobs(&self) -> Option<String>;

    /// The telescope the data come from, where the source can tell before reading samples (an
    /// `auto` step prefers a series trained for it). By default the first file the source
    /// names says, read without its samples; a glob pattern is not opened.
    fn telescope(&self) -> Result<Option<String>> {
        let first = self.reads().paths().first().cloned();
        Ok(first.filter(|p| !p.to_string_lossy().contains(['*', '?', '['])).and_then(|p| crate::vis::telescope_of(&p)))
    }
}
