//! `kind: parquet`: one imaging job per Parquet file (a path, a list, or glob patterns), or
//! several per file with `split_by` (time windows, frequency channels), read one record
//! batch at a time. A file of another format is refused, naming the kind that reads it.

use super::files::{Files, TableFiles};
use crate::job::{Reads, SourceKind, SourceParams};
use crate::pipeline::StageParams;
use crate::vis::{SplitBy, TableFormat};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// `kind: parquet`: Parquet visibility tables, one job per file.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ParquetParams {
    /// A file, a list of files, or glob patterns (relative to the working directory).
    pub files: Files,
    /// Rows per record batch read.
    #[serde(default = "crate::vis::default_batch_rows")]
    pub batch_rows: usize,
    /// Ground truth (FITS, Jy/pixel, same grid as the image) for SNR/logSNR per iteration.
    #[serde(default)]
    pub truth: Option<PathBuf>,
    /// Split each file into several jobs by a column.
    #[serde(default)]
    pub split_by: Option<SplitBy>,
}

impl ParquetParams {
    /// `files` with the defaults of the other keys.
    pub fn new(files: Files) -> ParquetParams {
        ParquetParams { files, batch_rows: crate::vis::default_batch_rows(), truth: None, split_by: None }
    }

    /// Why a source of these keys may make several jobs; `kind` names it in the reason.
    pub(super) fn several_jobs_of(&self, kind: &str) -> Option<String> {
        let why: Vec<String> = self.files.several_jobs(kind).into_iter().chain(self.split_by.as_ref().map(|_| format!("a {kind} source has split_by"))).collect();
        (!why.is_empty()).then(|| why.join("; "))
    }

    /// The source reading these files, each of `format`.
    pub(super) fn source(self, format: TableFormat, ctx: &crate::job::BuildContext<'_>) -> crate::Result<TableFiles> {
        TableFiles::new(format, &self.files, self.batch_rows, self.truth.as_deref(), self.split_by, ctx)
    }
}

impl StageParams for ParquetParams {
    const KIND: &'static str = "parquet";
}

impl SourceParams for ParquetParams {
    fn reads(&self) -> Reads {
        Reads::Files(self.files.patterns().iter().map(PathBuf::from).collect())
    }
    fn several_jobs(&self) -> Option<String> {
        self.several_jobs_of(Self::KIND)
    }
}

/// The kind, as registered.
pub(super) const KIND: SourceKind<ParquetParams> = SourceKind::new(|params, ctx| Ok(Box::new(params.source(TableFormat::Parquet, ctx)?)));
