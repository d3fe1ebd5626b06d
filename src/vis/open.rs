//! One way in for every table format: [`format_of`] tells a path's format by its content (a
//! file's leading bytes, a MeasurementSet's directory), [`open`] gives its reader, and
//! [`read_table`] reads it whole. The command line, the engine and the Python package all go
//! through here, so a format added here is one every entry point reads.

use super::reader::{TableReader, STDIN};
use super::error::TableError;
use super::split::read_parts;
use super::stream::{part_changed, PartCheck};
use super::mat::MatReader;
use super::{named_telescope, StreamedTable, VisSource, IngestStats, IpcReader, ObservationMeta, VisReader, Visibilities, DEFAULT_BATCH_ROWS};
use crate::{Error, Result};
use crate::fits::TempSibling;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use parquet::schema::types::ColumnPath;
use std::fs::File;
use std::io::Read;
use std::path::Path;

/// A visibility table's format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TableFormat {
    /// Parquet with the columns of `docs/formats.md` (the engine's own format).
    Parquet,
    /// An Arrow IPC stream or file with the same columns.
    ArrowIpc,
    /// A casacore MeasurementSet (a directory).
    MeasurementSet,
    /// A MATLAB .mat file as the reference implementation keeps observations (v5 or v7.3).
    Mat,
}

impl TableFormat {
    pub fn name(self) -> &'static str {
        match self {
            TableFormat::Parquet => "Parquet",
            TableFormat::ArrowIpc => "Arrow IPC",
            TableFormat::MeasurementSet => "MeasurementSet",
            TableFormat::Mat => "MATLAB .mat",
        }
    }
}

/// What a table is read with beyond its path.
#[derive(Clone, Debug, Default)]
pub struct OpenOptions {
    /// Rows per record batch (0: the default).
    pub batch_rows: usize,
    /// Which part of a MeasurementSet (field, windows, channels, data column).
    #[cfg(feature = "ms")]
    pub ms: crate::ms::MsSelection,
    /// Accept an Arrow IPC stream that ends without its end-of-stream marker (with a warning).
    pub allow_truncated: bool,
}

/// The format of the table at `path`, by content: a directory holding `table.dat` is a
/// MeasurementSet; a file starting with `PAR1` is Parquet; one starting with `ARROW1` (the
/// IPC file format) or with an IPC message (a continuation marker or a message length) is
/// Arrow IPC; one starting with a MAT header is a MATLAB .mat file. `-` (standard input) is
/// an Arrow IPC stream.
pub fn format_of(path: &Path) -> Result<TableFormat> {
    if path.as_os_str() == STDIN {
        return Ok(TableFormat::ArrowIpc);
    }
    let metadata = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if metadata.is_dir() {
        if path.join("table.dat").is_file() {
            return Ok(TableFormat::MeasurementSet);
        }
        return Err(Error::input(path, "a directory, but not a MeasurementSet (no table.dat): expected a MeasurementSet, a Parquet or an Arrow IPC file"));
    }
    if !metadata.is_file() {
        // Never opened: a FIFO's open waits for a writer, and its bytes come only once, while
        // a table is read more than once (its first bytes here, then the reader, then each pass).
        return Err(Error::input(
            path,
            format!(
                "{}, not a regular file: a table is read more than once (its format told from its first bytes, then each pass), and this gives its bytes only once; save it to a file and give that",
                crate::error::file_kind(&metadata)
            ),
        ));
    }
    let mut head = [0u8; 20];
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut got = 0;
    while got < head.len() {
        match file.read(&mut head[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(Error::io(path, e)),
        }
    }
    let head = &head[..got];
    if head.starts_with(b"PAR1") {
        return Ok(TableFormat::Parquet);
    }
    if super::mat::is_mat(head) {
        return Ok(TableFormat::Mat);
    }
    // The IPC file format's magic, or a stream's first message: the continuation marker
    // 0xFFFFFFFF (current streams) or a little-endian metadata length (pre-1.0 streams).
    if head.starts_with(b"ARROW1") || head.starts_with(&[0xff; 4]) {
        return Ok(TableFormat::ArrowIpc);
    }
    let what = if head.is_empty() { "the file is empty".to_string() } else { format!("the file starts with bytes {}", hex(head)) };
    Err(TableError::decode(
        path,
        "not a visibility table (expected a Parquet file, which starts with PAR1, an Arrow IPC stream or file, a MATLAB .mat file or a MeasurementSet directory)",
        what,
    )
    .into())
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect::<Vec<_>>().join(" ")
}

/// Opens `path` as a visibility table of whatever format it holds.
pub fn open(path: &Path, options: &OpenOptions) -> Result<Box<dyn TableReader>> {
    let batch_rows = if options.batch_rows == 0 { DEFAULT_BATCH_ROWS } else { options.batch_rows };
    Ok(match format_of(path)? {
        TableFormat::Parquet => Box::new(VisReader::open(path, batch_rows)?),
        TableFormat::ArrowIpc => Box::new(IpcReader::open(&path.to_string_lossy(), options.allow_truncated)?),
        TableFormat::Mat => Box::new(MatReader::open(path, batch_rows)?),
        #[cfg(feature = "ms")]
        TableFormat::MeasurementSet => Box::new(crate::ms::MsReader::open(path, &options.ms, batch_rows)?),
        #[cfg(not(feature = "ms"))]
        TableFormat::MeasurementSet => return Err(Error::input(path, "a MeasurementSet, but this r2d2 was built without the `ms` feature")),
    })
}

/// The telescope a table says its data come from (its `telescope` metadata, an MS's
/// `OBSERVATION::TELESCOPE_NAME`), read without its samples or any selection; none where it
/// names none (or `unknown`), where it does not open (its reader reports that), for a .mat
/// file (the format names none) and for standard input, which is read once.
pub fn telescope_of(path: &Path) -> Option<String> {
    if path.as_os_str() == STDIN {
        return None;
    }
    let telescope = match format_of(path).ok()? {
        TableFormat::Parquet | TableFormat::ArrowIpc => open(path, &OpenOptions::default()).ok()?.meta().telescope.clone(),
        #[cfg(feature = "ms")]
        TableFormat::MeasurementSet => crate::ms::telescope_name(path).ok()?,
        _ => return None,
    };
    named_telescope(&telescope)
}


/// Reads a whole table of any format: the kept samples, the metadata and the counts.
pub fn read_table(path: &Path, options: &OpenOptions) -> Result<(Visibilities, ObservationMeta, IngestStats)> {
    let mut reader = open(path, options)?;
    let (mut parts, stats) = read_parts(reader.as_mut(), None, "split_by", &|| false)?.expect("never cancelled");
    if let Some(summary) = reader.summary() {
        log::info!("{}: {summary}", path.display());
    }
    let vis = parts.pop().map(|p| p.vis).unwrap_or_default();
    Ok((vis, reader.meta().clone(), stats))
}

/// A table as a job's source, with its metadata: read again from its file at every pass
/// (Parquet, Arrow IPC, a MeasurementSet), or held where its format is read whole (.mat).
/// One part of an observation in parts is opened so where it lives.
pub fn open_source(path: &Path, options: &OpenOptions) -> Result<(ObservationMeta, VisSource)> {
    if format_of(path)? == TableFormat::Mat {
        let (vis, meta, _) = read_table(path, options)?;
        return Ok((meta, VisSource::Held(std::sync::Arc::new(vis))));
    }
    let (file, opts) = (path.to_path_buf(), options.clone());
    let reopen = move || open(&file, &opts);
    let table = StreamedTable::scan(reopen()?, Box::new(reopen), Some(&super::spill_dir()), &|| false)?.expect("never cancelled");
    Ok((table.meta().clone(), VisSource::Streamed(std::sync::Arc::new(table))))
}

/// A table for one pass of a part of an observation, not read first (see
/// [`StreamedTable::unscanned`]): the pass fails, naming the part, where its samples are not
/// those its first reading found (`expected`: [`VisSource::part_check`] of [`open_source`]'s).
pub fn open_pass(path: &Path, options: &OpenOptions, expected: Option<&PartCheck>) -> Result<VisSource> {
    if format_of(path)? == TableFormat::Mat {
        let held = VisSource::Held(std::sync::Arc::new(read_table(path, options)?.0));
        if let (Some(first), Some(now)) = (expected, held.part_check()) {
            if now != *first {
                return Err(part_changed(path, first, &now));
            }
        }
        return Ok(held);
    }
    let (file, opts) = (path.to_path_buf(), options.clone());
    let reopen = move || open(&file, &opts);
    Ok(VisSource::Streamed(std::sync::Arc::new(StreamedTable::unscanned(reopen()?, Box::new(reopen), expected.copied()))))
}

/// Streams every batch of `reader` into a Parquet table at `out` with `meta` as its metadata
/// (on the file and on the stored Arrow schema, where pyarrow reads it), replacing `out`
/// atomically. Returns the samples written.
pub fn write_parquet_from(reader: &mut dyn TableReader, meta: &ObservationMeta, out: &Path) -> Result<u64> {
    let metadata: Vec<KeyValue> = meta.to_pairs()?.into_iter().map(|(k, v)| KeyValue::new(k, v)).collect();
    let mut properties = WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::default()))
        .set_key_value_metadata(Some(metadata));
    // As `vis::write_parquet`: nearly all values distinct, a dictionary would be abandoned.
    for column in ["u", "v", "w", "vis_re", "vis_im", "time"] {
        properties = properties.set_column_dictionary_enabled(ColumnPath::from(column), false);
    }
    let write_error = |source: parquet::errors::ParquetError| -> Error { TableError::Write { doing: "writing Parquet", source: Box::new(source) }.into() };
    let tmp = TempSibling::new(out)?;
    let file = File::create(tmp.path()).map_err(|e| Error::io(out, e))?;
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
    Ok(samples)
}
