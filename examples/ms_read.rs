//! Reads a MeasurementSet the way the `ms` source does (Stokes I samples in row chunks,
//! exclusions counted) and prints samples per second, for benches/ms_read.py.
//!
//!     cargo run --release --example ms_read -- OBS.ms [DATA_COLUMN]

use r2d2_imaging::vis::TableReader;
use r2d2_imaging::ms::{MsReader, MsSelection};
use r2d2_imaging::vis::{record_batch_to_visibilities, IngestStats};
use std::path::PathBuf;
use std::time::Instant;

fn main() -> r2d2_imaging::Result<()> {
    let mut args = std::env::args().skip(1);
    let path = PathBuf::from(args.next().expect("usage: ms_read OBS.ms [DATA_COLUMN]"));
    let selection = MsSelection { data_column: args.next().unwrap_or_else(|| "DATA".into()), ..MsSelection::default() };
    let start = Instant::now();
    let mut reader = MsReader::open_default(&path, &selection)?;
    let mut stats = IngestStats::default();
    let mut kept = 0usize;
    while let Some(batch) = reader.next_batch() {
        kept += record_batch_to_visibilities(&batch?, &mut stats, "bench")?.len();
    }
    let seconds = start.elapsed().as_secs_f64();
    println!(
        "{{\"samples\": {}, \"kept\": {kept}, \"seconds\": {seconds:.3}, \"samples_per_second\": {:.0}}}",
        stats.rows,
        stats.rows as f64 / seconds
    );
    Ok(())
}
