//! `kind: mat`: MATLAB .mat observations as the reference implementation keeps them (v5 or
//! v7.3), one imaging job per file (a path, a list, or glob patterns), or several per file with
//! `split_by`. Each file is read whole by its format. A file of another format is refused,
//! naming the kind that reads it.

use super::parquet::ParquetParams;
use crate::job::{Reads, SourceKind, SourceParams};
use crate::pipeline::StageParams;
use crate::vis::TableFormat;
use serde::{Deserialize, Serialize};

/// `kind: mat`: .mat observation files, one job per file. Its keys are those of
/// [`ParquetParams`]: `files`, `batch_rows`, `truth`, `split_by`.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(transparent)]
pub struct MatParams(pub ParquetParams);

impl StageParams for MatParams {
    const KIND: &'static str = "mat";
}

impl SourceParams for MatParams {
    fn reads(&self) -> Reads {
        self.0.reads()
    }
    fn several_jobs(&self) -> Option<String> {
        self.0.several_jobs_of(Self::KIND)
    }
}

/// The kind, as registered.
pub(super) const KIND: SourceKind<MatParams> = SourceKind::new(|params, ctx| Ok(Box::new(params.0.source(TableFormat::Mat, ctx)?)));
