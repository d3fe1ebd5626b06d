//! What goes wrong with visibility tables ([`TableError`]): the decoder's error, a missing or
//! mistyped column, bad metadata.

use std::path::{Path, PathBuf};

/// A visibility table (Parquet file, Arrow IPC stream, in-memory Arrow table) that cannot be
/// read or built. `table` names it (a path, or the name an in-memory table was given).
///
/// The decoder's error (parquet's, arrow's) is the [`source`](std::error::Error::source), not
/// part of the text; `Error`'s text adds it.
#[derive(Debug, thiserror::Error)]
pub enum TableError {
    /// The decoder failed on the bytes (`doing` says what was being read): not that format,
    /// or corrupt.
    #[error("{}: {doing}", path.display())]
    Decode {
        path: PathBuf,
        doing: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The decoder panicked on the bytes (a decoder bug that a damaged file triggers):
    /// `message` is the panic's, with the decoder's source location.
    #[error("{}: {doing}: the {decoder} decoder failed ({message})", path.display())]
    DecoderPanic { path: PathBuf, doing: String, decoder: &'static str, message: String },
    /// A column the reader uses is missing, repeated, of a type it does not accept, or has
    /// nulls; `message` names the column and says what was expected.
    #[error("{table}: {message}")]
    Column { table: String, column: String, message: String },
    /// A metadata key is missing, empty or not a valid value; `message` names the key and
    /// says what was expected.
    #[error("{table}: {message}")]
    Metadata { table: String, key: String, message: String },
    /// Arrow refused to build a record batch from a table's columns.
    #[error("invalid table{}: building a record batch", if table.is_empty() { String::new() } else { format!(" {table}") })]
    Build {
        table: String,
        #[source]
        source: arrow::error::ArrowError,
    },
    /// Writing a table failed (`doing` says at what); carried by the `io::Error` of
    /// `Error::Io`, whose path is the file written, as its inner error
    /// ([`get_ref`](std::io::Error::get_ref)), with parquet's or arrow's error as its source.
    #[error("{doing}")]
    Write {
        doing: &'static str,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

impl TableError {
    /// The table the error is about: its path, or the name it was given (empty for `Write`,
    /// whose `Error::Io` names the file).
    pub fn table(&self) -> std::borrow::Cow<'_, str> {
        match self {
            TableError::Decode { path, .. } | TableError::DecoderPanic { path, .. } => path.display().to_string().into(),
            TableError::Column { table, .. } | TableError::Metadata { table, .. } | TableError::Build { table, .. } => {
                table.as_str().into()
            }
            TableError::Write { .. } => "".into(),
        }
    }

    pub(crate) fn column(table: &str, column: &str, message: String) -> Self {
        TableError::Column { table: table.to_string(), column: column.to_string(), message }
    }

    pub(crate) fn decode(path: &Path, doing: &str, source: impl Into<Box<dyn std::error::Error + Send + Sync>>) -> Self {
        TableError::Decode { path: path.to_path_buf(), doing: doing.to_string(), source: source.into() }
    }
}
