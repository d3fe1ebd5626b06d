//! MeasurementSet to the Parquet visibility format, streamed chunk by chunk.

use super::{MsCounts, MsReader, MsSelection, ORIGIN_KEY};
use crate::vis::{write_parquet_from, TableReader, DEFAULT_BATCH_ROWS};
use crate::Result;
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
    let samples = write_parquet_from(&mut reader, &meta, out)?;
    Ok((reader.counts(), samples))
}
