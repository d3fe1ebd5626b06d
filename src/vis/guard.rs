//! Decoders guarded: a panic inside arrow or parquet on damaged bytes becomes an error naming
//! the file, never an abort.

use super::error::TableError;
use std::path::{Path, PathBuf};

use arrow::array::RecordBatch;

use crate::Result;

/// Record batches decoded from untrusted bytes: decoding errors and panics become errors
/// naming the file and the row reached, and nothing is read after the first one.
pub(crate) struct GuardedBatches<I> {
    path: PathBuf,
    decoder: &'static str,
    batches: I,
    rows_decoded: u64,
    finished: bool,
}

impl<I, E> GuardedBatches<I>
where
    I: Iterator<Item = std::result::Result<RecordBatch, E>>,
    E: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    pub(crate) fn new(path: &Path, decoder: &'static str, batches: I) -> Self {
        GuardedBatches { path: path.to_path_buf(), decoder, batches, rows_decoded: 0, finished: false }
    }

    /// The next batch; `None` at the end or after an error.
    pub(crate) fn next_batch(&mut self) -> Option<Result<RecordBatch>> {
        if self.finished {
            return None;
        }
        let batches = &mut self.batches;
        let what = format!("corrupt {} data after row {}", self.decoder, self.rows_decoded);
        let item = contain_panics(&self.path, &what, self.decoder, || batches.next().transpose()).transpose();
        match &item {
            Some(Ok(batch)) => self.rows_decoded += batch.num_rows() as u64,
            _ => self.finished = true,
        }
        item
    }
}

/// Decoder names for [`contain_panics`]'s messages.
pub(crate) const PARQUET: &str = "Parquet";

pub(crate) const ARROW_IPC: &str = "Arrow IPC";

/// Runs decoding of untrusted bytes (Parquet, Arrow IPC: `decoder` names it), turning errors
/// and panics alike into a [`TableError`] naming the file (the decoder's error its source).
///
/// parquet 55 panics on some corrupt pages instead of returning an error (dictionary
/// indices are not bounds-checked: apache/arrow-rs#9434, fixed in later releases), and a
/// damaged file must not bring down the process. Unwinding is contained here, where
/// callers stop using the decoder after any failure (`VisReader` ends its iteration), so
/// no state it may have left half-updated is observed. The panic is not printed: the error
/// says it all, with the decoder's source location.
pub(crate) fn contain_panics<T, E: Into<Box<dyn std::error::Error + Send + Sync>>>(
    path: &Path,
    what: &str,
    decoder: &'static str,
    decode: impl FnOnce() -> std::result::Result<T, E>,
) -> Result<T> {
    match crate::error::catch_quietly(decode) {
        Ok(Ok(value)) => Ok(value),
        Ok(Err(e)) => Err(TableError::decode(path, what, e).into()),
        Err(message) => Err(TableError::DecoderPanic {
            path: path.to_path_buf(),
            doing: what.to_string(),
            decoder,
            message,
        }
        .into()),
    }
}
