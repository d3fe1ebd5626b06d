//! Inputs and outputs of a run that are not files: record batches handed in by the caller
//! (the `arrow` source reads them) and a sink receiving each finished job's products (the
//! `products` stage delivers to it).

use crate::products::JobProducts;
use crate::Result;
use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use arrow::error::ArrowError;
use arrow::record_batch::{RecordBatchIterator, RecordBatchReader};

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

/// Receives each finished job's products (the `products` stage calls it, one job at a time,
/// from the stage's thread). An error fails the run, naming the stage and job.
pub trait ProductSink: Send {
    fn deliver(&mut self, products: JobProducts) -> Result<()>;
}

impl<F: FnMut(JobProducts) -> Result<()> + Send> ProductSink for F {
    fn deliver(&mut self, products: JobProducts) -> Result<()> {
        self(products)
    }
}
