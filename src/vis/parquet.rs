//! Parquet visibility tables read one row group at a time ([`VisReader`]).

use super::data::{ObservationMeta, Visibilities};
use super::convert::{record_batch_to_visibilities, validate_schema, IngestStats, INTERVAL_COLUMN, READ_COLUMNS, TIME_COLUMN};
use super::error::TableError;
use super::guard::{contain_panics, GuardedBatches, PARQUET};
use std::fs::File;
use std::path::{Path, PathBuf};

use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use parquet::arrow::arrow_reader::{ParquetRecordBatchReader, ParquetRecordBatchReaderBuilder};
use parquet::arrow::ProjectionMask;

use crate::{Error, Result};

/// Batch size of [`read_parquet`]: large enough to amortise per-batch work, small
/// enough (a few MB per column) not to matter next to the visibilities themselves.
pub const DEFAULT_BATCH_ROWS: usize = 65_536;

/// [`DEFAULT_BATCH_ROWS`] as a serde default, for the sources that read tables in batches.
pub fn default_batch_rows() -> usize {
    DEFAULT_BATCH_ROWS
}

/// Streams a visibility Parquet file in batches of at most `batch_rows` rows, so memory
/// is bounded however large the file. Schema and metadata are checked when opening;
/// each item is one batch of kept samples (possibly empty if all rows were excluded).
/// After an error the iterator ends.
pub struct VisReader {
    path: PathBuf,
    source: String,
    meta: ObservationMeta,
    stats: IngestStats,
    #[cfg(test)]
    total_rows: u64,
    /// The file's whole schema (the batches hold only the columns read).
    schema: SchemaRef,
    batches: GuardedBatches<ParquetRecordBatchReader>,
    finished: bool,
}

impl VisReader {
    /// Opens `path`, reading and checking the footer: columns, types and metadata.
    pub fn open(path: &Path, batch_rows: usize) -> Result<VisReader> {
        Self::open_with_columns(path, batch_rows, &[])
    }

    /// As [`VisReader::open`], also decoding the columns `extra` (when the file has them) into
    /// the batches of [`VisReader::next_record_batch`], e.g. `time` to split the table.
    pub fn open_with_columns(path: &Path, batch_rows: usize, extra: &[&str]) -> Result<VisReader> {
        if batch_rows == 0 {
            return Err(Error::parameter("batch_rows", "must be at least 1"));
        }
        let file = File::open(path).map_err(|e| Error::io(path, e))?;
        let builder = contain_panics(path, "not a readable Parquet file", PARQUET, || {
            ParquetRecordBatchReaderBuilder::try_new(file)
        })?;
        let source = path.display().to_string();
        let file_metadata = builder.metadata().file_metadata();
        let pairs = file_metadata.key_value_metadata().map(Vec::as_slice).unwrap_or_default();
        let meta = ObservationMeta::from_pairs(
            pairs.iter().map(|kv| (kv.key.as_str(), kv.value.as_deref())),
            &source,
        )?;
        #[cfg(test)]
        let total_rows = u64::try_from(file_metadata.num_rows()).unwrap_or(0);
        validate_schema(builder.schema(), &source)?;

        // Decode only the columns used: antennas would cost reading time and memory (times
        // tell the track a series' domain is checked against).
        let used: Vec<usize> = builder
            .schema()
            .fields()
            .iter()
            .enumerate()
            .filter(|(_, field)| {
                let name = field.name().as_str();
                READ_COLUMNS.iter().any(|(read, _, _)| name == *read) || [TIME_COLUMN, INTERVAL_COLUMN].contains(&name) || extra.contains(&name)
            })
            .map(|(index, _)| index)
            .collect();
        let projection = ProjectionMask::roots(builder.parquet_schema(), used);
        let schema = builder.schema().clone();
        let batches = builder
            .with_batch_size(batch_rows)
            .with_projection(projection)
            .build()
            .map_err(|e| TableError::decode(path, "cannot set up reading", e))?;
        Ok(VisReader {
            path: path.to_path_buf(),
            source,
            meta,
            stats: IngestStats::default(),
            #[cfg(test)]
            total_rows,
            schema,
            batches: GuardedBatches::new(path, PARQUET, batches),
            finished: false,
        })
    }

    /// The file being read.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The file's schema: every column, including those not read.
    pub fn schema(&self) -> &SchemaRef {
        &self.schema
    }

    /// The next batch as decoded (the columns used and the `extra` ones, no row dropped yet);
    /// `None` at the end or after an error.
    pub fn next_record_batch(&mut self) -> Option<Result<RecordBatch>> {
        if self.finished {
            return None;
        }
        self.batches.next_batch()
    }

    /// The observation metadata from the file footer.
    pub fn meta(&self) -> &ObservationMeta {
        &self.meta
    }

    /// Counts over the batches read so far.
    #[cfg(test)]
    pub fn stats(&self) -> IngestStats {
        self.stats
    }

    /// Rows in the file according to its footer, for progress reports.
    #[cfg(test)]
    pub fn total_rows(&self) -> u64 {
        self.total_rows
    }
}

impl Iterator for VisReader {
    type Item = Result<Visibilities>;

    fn next(&mut self) -> Option<Self::Item> {
        let item = match self.next_record_batch()? {
            Ok(batch) => record_batch_to_visibilities(&batch, &mut self.stats, &self.source),
            Err(e) => Err(e),
        };
        self.finished = item.is_err();
        Some(item)
    }
}

/// Reads a whole visibility file: the kept samples, the metadata and the counts.
pub fn read_parquet(path: &Path) -> Result<(Visibilities, ObservationMeta, IngestStats)> {
    let mut reader = VisReader::open(path, DEFAULT_BATCH_ROWS)?;
    let mut vis = Visibilities::default();
    for batch in reader.by_ref() {
        vis.push_batch(batch?);
    }
    Ok((vis, reader.meta.clone(), reader.stats))
}
