//! The reader contract every visibility table format implements: a table read one record
//! batch at a time, with its observation metadata.

use super::{ObservationMeta, VisReader};
use crate::Result;
use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use std::path::Path;

/// A visibility table read one record batch at a time.
pub trait TableReader {
    /// Names the table in messages (a path, or `standard input`).
    fn source(&self) -> &Path;
    fn meta(&self) -> &ObservationMeta;
    /// Every column of the table.
    fn schema(&self) -> SchemaRef;
    /// The next batch as decoded (no row dropped yet); `None` at the end or after an error.
    fn next_batch(&mut self) -> Option<Result<RecordBatch>>;
    /// What the table holds beyond its samples, for the log (a MeasurementSet's rows, fields
    /// and windows), when the format has more to say.
    fn summary(&self) -> Option<String> {
        None
    }
}

impl TableReader for VisReader {
    fn source(&self) -> &Path {
        self.path()
    }
    fn meta(&self) -> &ObservationMeta {
        VisReader::meta(self)
    }
    fn schema(&self) -> SchemaRef {
        VisReader::schema(self).clone()
    }
    fn next_batch(&mut self) -> Option<Result<RecordBatch>> {
        self.next_record_batch()
    }
}

/// What `path: -` reads.
pub const STDIN: &str = "-";
