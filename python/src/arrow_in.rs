//! Tables from Python without copies: anything exporting the Arrow PyCapsule stream interface
//! (`__arrow_c_stream__`: a `pyarrow.Table` or `RecordBatchReader`, polars, DuckDB ...) is
//! read through the Arrow C stream, its buffers shared, not copied.

use arrow::array::{RecordBatchReader, StructArray};
use arrow::datatypes::{DataType, Schema, SchemaRef};
use arrow::error::ArrowError;
use arrow::ffi::{from_ffi_and_data_type, FFI_ArrowArray, FFI_ArrowSchema};
use arrow::ffi_stream::FFI_ArrowArrayStream;
use arrow::record_batch::RecordBatch;
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::types::PyCapsule;
use std::ffi::CStr;
use std::sync::Arc;

const STREAM_CAPSULE: &CStr = c"arrow_array_stream";

/// The Arrow C stream `table` exports, taken over: `table` may be dropped afterwards (the stream
/// holds its own references to the buffers).
pub fn stream_of(table: &Bound<'_, PyAny>) -> PyResult<ArrowStream> {
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
    ArrowStream::try_new(stream).map_err(|e| crate::R2D2Error::new_err(format!("{}: {e}", table_name())))
}

/// Record batches from an Arrow C stream, as arrow's `ArrowArrayStreamReader` reads them, but
/// with every buffer brought to its type's alignment first: a table that went through pickle
/// (Dask sends tables to its workers so) can hold buffers at any address, and arrow refuses
/// (panics on) a misaligned one. Aligned buffers, the usual case, are shared, not copied.
pub struct ArrowStream {
    stream: FFI_ArrowArrayStream,
    schema: SchemaRef,
}

impl ArrowStream {
    fn try_new(mut stream: FFI_ArrowArrayStream) -> std::result::Result<ArrowStream, ArrowError> {
        let get_schema = stream.get_schema.filter(|_| stream.release.is_some());
        let get_schema = get_schema.ok_or_else(|| ArrowError::CDataInterface("the Arrow stream is released".into()))?;
        let mut schema = FFI_ArrowSchema::empty();
        // SAFETY: a stream that is not released has valid callbacks (C stream interface), and
        // `schema` is a valid place for the callback to write an FFI_ArrowSchema into.
        let code = unsafe { get_schema(&mut stream, &mut schema) };
        if code != 0 {
            return Err(ArrowError::CDataInterface(format!("the stream gave no schema: {}", last_error(&mut stream))));
        }
        Ok(ArrowStream { schema: Arc::new(Schema::try_from(&schema)?), stream })
    }
}

/// The stream's message for its last failed call.
fn last_error(stream: &mut FFI_ArrowArrayStream) -> String {
    let Some(get_last_error) = stream.get_last_error else { return "no message".into() };
    // SAFETY: the callback of a live stream returns NULL or a NUL-terminated string that stays
    // valid until the next call on the stream; it is copied at once.
    unsafe {
        let message = get_last_error(stream);
        if message.is_null() { "no message".into() } else { CStr::from_ptr(message).to_string_lossy().into_owned() }
    }
}

impl Iterator for ArrowStream {
    type Item = std::result::Result<RecordBatch, ArrowError>;

    fn next(&mut self) -> Option<Self::Item> {
        let get_next = self.stream.get_next?;
        let mut array = FFI_ArrowArray::empty();
        // SAFETY: as for get_schema: a live stream's callback, writing into a valid place.
        if unsafe { get_next(&mut self.stream, &mut array) } != 0 {
            return Some(Err(ArrowError::CDataInterface(last_error(&mut self.stream))));
        }
        if array.is_released() {
            return None; // the end of the stream
        }
        // SAFETY: `array` is the stream's next batch, a struct array of the stream's schema
        // (C stream interface); it is consumed here.
        let data = unsafe { from_ffi_and_data_type(array, DataType::Struct(self.schema.fields().clone())) };
        Some(data.map(|mut data| {
            data.align_buffers();
            RecordBatch::from(StructArray::from(data)).with_schema(self.schema.clone()).expect("the batch has the stream's fields")
        }))
    }
}

impl RecordBatchReader for ArrowStream {
    fn schema(&self) -> SchemaRef {
        self.schema.clone()
    }
}

/// How a table from Python is named in the engine's messages.
pub fn table_name() -> &'static str {
    "<arrow table>"
}
