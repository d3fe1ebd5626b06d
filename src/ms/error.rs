//! What goes wrong with MeasurementSets ([`MsError`]), keeping casacore's error as the source.

use std::path::{Path, PathBuf};

/// What went wrong with a MeasurementSet (or, converting to one, with its source table). Each
/// variant names the table; casacore's own error, where there is one, is the
/// [`source`](std::error::Error::source) (a `casacure` error type).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MsError {
    /// The casacore table library failed on a table: opening, reading cells, writing.
    #[error("{}: {what}", path.display())]
    Table {
        path: PathBuf,
        what: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The table decoder panicked on the table's bytes (a damaged table): an error, not a crash.
    #[error("{}: {what}: the casacore table decoder failed ({message})", path.display())]
    DecoderPanic { path: PathBuf, what: String, message: String },
    /// A table, column or cell is not what a MeasurementSet holds, or the selection (field,
    /// windows) matches nothing in it.
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
    /// The Parquet table written from an MS (`r2d2 convert`) could not be written.
    #[error("{}: writing Parquet", path.display())]
    Parquet {
        path: PathBuf,
        #[source]
        source: parquet::errors::ParquetError,
    },
    /// The samples read could not be made into a record batch.
    #[error("{}: {what}", path.display())]
    Arrow {
        path: PathBuf,
        what: String,
        #[source]
        source: arrow::error::ArrowError,
    },
}

impl MsError {
    /// The table (or file) the error is about.
    pub fn path(&self) -> &Path {
        match self {
            MsError::Table { path, .. }
            | MsError::DecoderPanic { path, .. }
            | MsError::Invalid { path, .. }
            | MsError::Parquet { path, .. }
            | MsError::Arrow { path, .. } => path,
        }
    }

    pub(super) fn path_mut(&mut self) -> &mut PathBuf {
        match self {
            MsError::Table { path, .. }
            | MsError::DecoderPanic { path, .. }
            | MsError::Invalid { path, .. }
            | MsError::Parquet { path, .. }
            | MsError::Arrow { path, .. } => path,
        }
    }
}
