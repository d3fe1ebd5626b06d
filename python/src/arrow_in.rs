//! Tables from Python without copies: anything exporting the Arrow PyCapsule stream interface
//! (`__arrow_c_stream__`: a `pyarrow.Table` or `RecordBatchReader`, polars, DuckDB ...) is
//! read through the Arrow C stream, its buffers shared, not copied.

use arrow::array::RecordBatchReader;
use arrow::datatypes::SchemaRef;
use arrow::ffi_stream::{ArrowArrayStreamReader, FFI_ArrowArrayStream};
use arrow::record_batch::RecordBatch;
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::types::PyCapsule;
use r2d2_imaging::ingest::TableReader;
use r2d2_imaging::vis::ObservationMeta;
use r2d2_imaging::{Error, Result};
use std::ffi::CStr;
use std::path::{Path, PathBuf};

const STREAM_CAPSULE: &CStr = c"arrow_array_stream";

/// The Arrow C stream `table` exports, taken over: `table` may be dropped afterwards (the stream
/// holds its own references to the buffers).
pub fn stream_of(table: &Bound<'_, PyAny>) -> PyResult<ArrowArrayStreamReader> {
    if !table.hasattr("__arrow_c_stream__")? {
        return Err(PyTypeError::new_err(format!(
            "expected a path, or a table with the Arrow stream interface (pyarrow.Table or RecordBatchReader), got {}",
            table.get_type().name()?
        )));
    }
    let capsule = table.call_method0("__arrow_c_stream__")?.downcast_into::<PyCapsule>()?;
    if capsule.name()? != Some(STREAM_CAPSULE) {
        return Err(PyTypeError::new_err("__arrow_c_stream__ returned a capsule that is not an arrow_array_stream"));
    }
    let raw = capsule.pointer() as *mut FFI_ArrowArrayStream;
    // SAFETY: the capsule's name says it holds an FFI_ArrowArrayStream (the Arrow PyCapsule
    // interface), valid while the capsule lives, which it does during this call. The stream is
    // moved out and an empty one (release = NULL) left in its place, which is how the interface
    // marks a consumed stream: the capsule's destructor then releases nothing.
    let stream = unsafe { std::ptr::replace(raw, FFI_ArrowArrayStream::empty()) };
    ArrowArrayStreamReader::try_new(stream).map_err(|e| crate::R2D2Error::new_err(format!("{}: {e}", table_name())))
}

/// How a table from Python is named in the engine's messages.
pub fn table_name() -> &'static str {
    "<arrow table>"
}

/// A table arriving through an Arrow C stream, read as the engine reads an Arrow IPC table:
/// the observation's metadata on the schema.
pub struct StreamTable {
    source: PathBuf,
    meta: ObservationMeta,
    reader: ArrowArrayStreamReader,
    failed: bool,
}

impl StreamTable {
    pub fn new(reader: ArrowArrayStreamReader, source: &str) -> Result<StreamTable> {
        let schema = reader.schema();
        let meta = ObservationMeta::from_pairs(schema.metadata().iter().map(|(k, v)| (k.as_str(), Some(v.as_str()))), source)?;
        Ok(StreamTable { source: PathBuf::from(source), meta, reader, failed: false })
    }
}

impl TableReader for StreamTable {
    fn source(&self) -> &Path {
        &self.source
    }
    fn meta(&self) -> &ObservationMeta {
        &self.meta
    }
    fn schema(&self) -> SchemaRef {
        self.reader.schema()
    }
    fn next_batch(&mut self) -> Option<Result<RecordBatch>> {
        if self.failed {
            return None;
        }
        let next = self.reader.next()?;
        Some(next.map_err(|e| {
            self.failed = true;
            Error::input(&self.source, format!("reading the table's next batch: {e}"))
        }))
    }
}
