//! MeasurementSet to the Parquet visibility format, streamed chunk by chunk.

use super::{MsCounts, MsReader, MsSelection, ORIGIN_KEY};
use crate::fits::TempSibling;
use crate::vis::TableReader;
use crate::vis::DEFAULT_BATCH_ROWS;
use crate::{Error, Result};
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use parquet::schema::types::ColumnPath;
use std::fs::File;
use std::path::Path;

/// Writes the selected Stokes I samples of the MS at `ms` as a Parquet table at `out` (every
/// sample, flagged ones with `flag` set; the `field` and `spw` columns besides the format's),
/// replacing `out` atomically. Returns the MS row counts and the samples written.
pub fn convert_ms_to_parquet(ms: &Path, selection: &MsSelection, out: &Path) -> Result<(MsCounts, u64)> {
    super::lock::check_conversion_output(ms, out, false)?;
    let mut reader = MsReader::open(ms, selection, DEFAULT_BATCH_ROWS)?;
    // The origin names this MS for the writer's model column; a Parquet copy is no longer it.
    let mut meta = reader.meta().clone();
    meta.extra.remove(ORIGIN_KEY);
    meta.extra.insert("converted_from".to_string(), ms.display().to_string());
    let metadata: Vec<KeyValue> = meta.to_pairs()?.into_iter().map(|(k, v)| KeyValue::new(k, v)).collect();
    let mut properties = WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::default()))
        .set_key_value_metadata(Some(metadata));
    // As `vis::write_parquet`: nearly all values distinct, a dictionary would be abandoned.
    for column in ["u", "v", "w", "vis_re", "vis_im", "time"] {
        properties = properties.set_column_dictionary_enabled(ColumnPath::from(column), false);
    }
    let write_error = |source| Error::from(super::MsError::Parquet { path: out.to_path_buf(), source });
    let tmp = TempSibling::new(out)?;
    let file = File::create(tmp.path()).map_err(|e| Error::io(out, e))?;
    // As `vis::write_parquet`: the metadata on the stored Arrow schema too (pyarrow reads it).
    let schema = std::sync::Arc::new(reader.schema().as_ref().clone().with_metadata(meta.to_pairs()?.into_iter().collect()));
    let mut writer = ArrowWriter::try_new(file, schema, Some(properties.build())).map_err(write_error)?;
    let mut samples = 0u64;
    while let Some(batch) = reader.next_batch() {
        let batch = batch?;
        samples += batch.num_rows() as u64;
        writer.write(&batch).map_err(write_error)?;
    }
    let file = writer.into_inner().map_err(write_error)?;
    file.sync_all().map_err(|e| Error::io(out, e))?;
    drop(file);
    tmp.persist()?;
    Ok((reader.counts(), samples))
}
