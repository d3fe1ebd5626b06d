//! Observations handed in by the caller as Arrow record batches (the `arrow` source reads them).

use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use arrow::error::ArrowError;
use arrow::record_batch::{RecordBatchIterator, RecordBatchReader};
use super::reader::TableReader;
use super::{validate_schema, ObservationMeta};
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// One observation held in memory: a stream of Arrow record batches with the columns of the
/// Parquet format and its observation metadata (`phase_centre_ra_deg`, ...) in the schema's
/// metadata, as an Arrow IPC stream carries them. One job (or several with `split_by`).
pub struct MemoryInput {
    /// Job id (products are named after it).
    pub id: String,
    pub batches: Box<dyn RecordBatchReader + Send>,
}

impl MemoryInput {
    /// From any record batch reader (an IPC reader, a channel adapted to an iterator...).
    pub fn new(id: impl Into<String>, batches: impl RecordBatchReader + Send + 'static) -> MemoryInput {
        MemoryInput { id: id.into(), batches: Box::new(batches) }
    }

    /// From batches already made (they must all have `schema`).
    pub fn from_batches(id: impl Into<String>, schema: SchemaRef, batches: Vec<RecordBatch>) -> MemoryInput {
        Self::from_iter(id, schema, batches.into_iter().map(Ok))
    }

    /// From an iterator of batches, e.g. `receiver.into_iter().map(Ok)` over a channel that a
    /// producer thread fills: batches are read as they arrive.
    pub fn from_iter<I>(id: impl Into<String>, schema: SchemaRef, batches: I) -> MemoryInput
    where
        I: IntoIterator<Item = std::result::Result<RecordBatch, ArrowError>> + 'static,
        I::IntoIter: Send + 'static,
    {
        Self::new(id, RecordBatchIterator::new(batches, schema))
    }
}

/// An in-memory input read as a visibility table: the metadata and columns are checked when
/// it is opened, as for a file.
pub struct MemoryTable {
    id: String,
    /// Names the input in messages.
    source: PathBuf,
    meta: ObservationMeta,
    schema: SchemaRef,
    input: MemoryInput,
    failed: bool,
}

impl MemoryTable {
    /// `name` names the input in messages.
    pub fn new(input: MemoryInput, name: &str) -> Result<MemoryTable> {
        let schema = input.batches.schema();
        let meta = ObservationMeta::from_pairs(schema.metadata().iter().map(|(k, v)| (k.as_str(), Some(v.as_str()))), name)?;
        validate_schema(&schema, name)?;
        Ok(MemoryTable { id: input.id.clone(), source: PathBuf::from(name), meta, schema, input, failed: false })
    }
}

/// An in-memory input as a visibility table, its metadata and columns checked as a file's are,
/// for a caller that scans it itself (e.g. with [`super::split_rows`]); `name` names
/// it in messages.
pub fn memory_table(input: MemoryInput, name: &str) -> Result<MemoryTable> {
    MemoryTable::new(input, name)
}

impl TableReader for MemoryTable {
    fn source(&self) -> &Path {
        &self.source
    }
    fn meta(&self) -> &ObservationMeta {
        &self.meta
    }
    fn schema(&self) -> SchemaRef {
        self.schema.clone()
    }
    fn next_batch(&mut self) -> Option<Result<RecordBatch>> {
        if self.failed {
            return None;
        }
        match self.input.batches.next()? {
            Ok(batch) if batch.schema().fields() != self.schema.fields() => {
                self.failed = true;
                Some(Err(Error::input(&self.source, "a record batch's columns differ from the input's schema")))
            }
            Ok(batch) => Some(Ok(batch)),
            Err(e) => {
                self.failed = true;
                Some(Err(Error::input(&self.source, format!("reading a record batch: {e}"))))
            }
        }
    }
}

impl MemoryTable {
    /// The input's id (its job's, before any split).
    pub fn id(&self) -> &str {
        &self.id
    }
}
