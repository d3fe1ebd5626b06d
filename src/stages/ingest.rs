//! Visibility tables into imaging jobs, shared by the `parquet` and `arrow-ipc` sources:
//! reading Arrow IPC (a stream or a file, standard input included) batch by batch, and
//! splitting one table into several jobs by a column (time windows, frequency channels).
//!
//! Arrow IPC carries the same columns as the Parquet format (`crate::vis`), and the
//! observation metadata (`phase_centre_ra_deg`, ...) as schema metadata, which is where
//! `pyarrow.ipc.new_stream(sink, schema.with_metadata({...}))` puts it.

use crate::pipeline::Job;
pub use super::memory::memory_table;
use crate::vis::{
    check_no_nulls, contain_panics, record_batch_to_visibilities, record_batch_to_visibilities_keeping_rows,
    validate_schema, IngestStats, ObservationMeta, VisReader, Visibilities, ARROW_IPC,
};
use crate::{Error, Result};
use arrow::array::{Array, Float64Array, RecordBatch};
use arrow::datatypes::{DataType, Schema, SchemaRef};
use arrow::ipc::reader::{read_dictionary, read_record_batch};
use arrow::ipc::MessageHeader;
use serde::{Deserialize, Serialize};
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// How to split one table into jobs.
///
/// `{column: time, window: 600}`: windows of `window` (in the column's unit: seconds for
/// `time`) counted from the column's smallest value, one job per window holding samples;
/// `{column: frequency}`: one job per distinct value (one per channel). Job ids are the
/// table's id, then `-t003` (time), `-ch01` (frequency) or `-<column>NN`, numbered from 0
/// by window (so an empty window leaves a gap) or by rank of the value.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct SplitBy {
    pub column: String,
    #[serde(default)]
    pub window: Option<f64>,
}

impl SplitBy {
    /// Checks the window; the message is about the `window` key.
    pub fn check(&self) -> std::result::Result<(), String> {
        match self.window {
            Some(w) if !(w > 0.0 && w.is_finite()) => Err(format!("expected a positive window, got {w}")),
            _ => Ok(()),
        }
    }

    /// Checks that `schema` has the column and that it is numeric; the message lists the
    /// available columns.
    pub fn check_schema(&self, schema: &Schema) -> std::result::Result<(), String> {
        let names: Vec<&str> = schema.fields().iter().map(|f| f.name().as_str()).collect();
        match schema.field_with_name(&self.column) {
            Err(_) => Err(format!("no column `{}` to split by (columns: {})", self.column, names.join(", "))),
            Ok(field) if !field.data_type().is_numeric() => Err(format!(
                "column `{}` has type {}; splitting needs a numeric column (columns: {})",
                self.column,
                field.data_type(),
                names.join(", ")
            )),
            Ok(_) => Ok(()),
        }
    }

    /// The job-id label of a part: `t` for time, `ch` for frequency channels.
    fn label(&self) -> &str {
        match self.column.as_str() {
            "time" => "t",
            "frequency" => "ch",
            other => other,
        }
    }
}

/// A visibility table read one record batch at a time.
pub trait TableReader {
    /// Names the table in messages (a path, or `standard input`).
    fn source(&self) -> &Path;
    fn meta(&self) -> &ObservationMeta;
    /// Every column of the table.
    fn schema(&self) -> SchemaRef;
    /// The next batch as decoded (no row dropped yet); `None` at the end or after an error.
    fn next_batch(&mut self) -> Option<Result<RecordBatch>>;
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

/// An Arrow IPC table: the stream format (from a file or standard input) or the file format
/// (from a file), told apart by the file format's leading magic bytes.
///
/// Messages are framed here rather than by arrow's `StreamReader`, which allocates whatever a
/// header declares (a 1 TiB body aborted the process): every declared size is checked first
/// against what the input can still hold (a file's remaining bytes) and the memory available,
/// and buffers grow with the bytes that actually arrive. The file format is read through the
/// stream it embeds (its messages in order, up to the end-of-stream marker before the footer),
/// so the footer's block sizes, which are as untrusted, are never used.
pub struct IpcReader {
    source: PathBuf,
    meta: ObservationMeta,
    schema: SchemaRef,
    messages: IpcMessages,
    rows: u64,
    finished: bool,
    /// Accept a stream that ends without its end-of-stream marker (with a warning).
    allow_truncated: bool,
}

/// The IPC file format starts with these bytes; the stream format with a message length.
const IPC_FILE_MAGIC: &[u8] = b"ARROW1";

impl IpcReader {
    /// Opens `input` (a path, or `-` for standard input) and reads the schema and metadata.
    /// With `allow_truncated`, a stream that ends between two messages without its end-of-stream
    /// marker is taken as complete (with a warning) instead of an error.
    pub fn open(input: &str, allow_truncated: bool) -> Result<IpcReader> {
        if input == STDIN {
            let source = PathBuf::from("standard input");
            let mut reader = BufReader::new(std::io::stdin());
            if peek_is_file_format(&mut reader, &source)? {
                return Err(Error::input(
                    &source,
                    "this is the Arrow IPC file format, which needs a seekable file: send the stream format on standard input, or give the file's path",
                ));
            }
            return Self::new(source, IpcMessages::new(Box::new(reader), None), allow_truncated);
        }
        let source = PathBuf::from(input);
        let file = std::fs::File::open(&source).map_err(|e| Error::io(&source, e))?;
        let length = file.metadata().map_err(|e| Error::io(&source, e))?.len();
        let mut reader = BufReader::new(file);
        let header = if peek_is_file_format(&mut reader, &source)? { skip_file_header(&mut reader, &source)? } else { 0 };
        Self::new(source, IpcMessages::new(Box::new(reader), Some(length.saturating_sub(header))), allow_truncated)
    }

    fn new(source: PathBuf, mut messages: IpcMessages, allow_truncated: bool) -> Result<IpcReader> {
        let first = contain_panics(&source, "not a readable Arrow IPC stream", ARROW_IPC, || messages.next(None))?;
        let IpcMessage::Schema(schema) = first else {
            return Err(Error::input(&source, "not a readable Arrow IPC stream: it does not start with a schema"));
        };
        let schema = Arc::new(schema);
        let name = source.display().to_string();
        let meta = ObservationMeta::from_pairs(schema.metadata().iter().map(|(k, v)| (k.as_str(), Some(v.as_str()))), &name)?;
        validate_schema(&schema, &name)?;
        Ok(IpcReader { source, meta, schema, messages, rows: 0, finished: false, allow_truncated })
    }
}

/// Whether the buffered input starts with the IPC file magic (without consuming it).
fn peek_is_file_format<R: Read>(reader: &mut BufReader<R>, source: &Path) -> Result<bool> {
    let head = reader.fill_buf().map_err(|e| Error::io(source, e))?;
    if head.is_empty() {
        return Err(Error::input(source, "empty input: expected an Arrow IPC stream or file"));
    }
    Ok(head.starts_with(IPC_FILE_MAGIC))
}

/// Skips the file format's magic and the padding after it (to 8 bytes, or to 64 as arrow-rs
/// writes it), up to its first message; the bytes skipped.
fn skip_file_header(reader: &mut BufReader<std::fs::File>, source: &Path) -> Result<u64> {
    let mut magic = [0u8; 8];
    reader.read_exact(&mut magic).map_err(|_| Error::input(source, "too short for the Arrow IPC file format"))?;
    let mut skipped = magic.len();
    // Zero words before the schema can only be padding: a stream does not start by ending.
    while skipped < 64 && reader.fill_buf().map_err(|e| Error::io(source, e))?.starts_with(&[0; 4]) {
        reader.consume(4);
        skipped += 4;
    }
    Ok(skipped as u64)
}

impl TableReader for IpcReader {
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
        while !self.finished {
            let what = format!("corrupt Arrow IPC data after row {}", self.rows);
            let (messages, schema) = (&mut self.messages, &self.schema);
            match contain_panics(&self.source, &what, ARROW_IPC, || messages.next(Some(schema))) {
                Ok(IpcMessage::Batch(batch)) => {
                    self.rows += batch.num_rows() as u64;
                    return Some(Ok(batch));
                }
                Ok(IpcMessage::Other) => continue,
                Ok(IpcMessage::Schema(_)) => {
                    self.finished = true;
                    return Some(Err(Error::input(&self.source, format!("{what}: a second schema in the stream"))));
                }
                Ok(IpcMessage::End) => self.finished = true,
                Ok(IpcMessage::EndOfInput) => {
                    // A sender that died between two batches leaves a stream that looks whole
                    // but for the marker: imaging it silently would pass part of an
                    // observation off as all of it.
                    self.finished = true;
                    let ended = format!("the Arrow IPC stream ended after row {} without its end-of-stream marker", self.rows);
                    if !self.allow_truncated {
                        return Some(Err(Error::input(
                            &self.source,
                            format!("{ended}: the sender may have stopped part-way (if these rows are all there is, set allow_truncated: true on the source)"),
                        )));
                    }
                    log::warn!("{}: {ended}: imaging the rows received (allow_truncated)", self.source.display());
                }
                Err(e) => {
                    self.finished = true;
                    return Some(Err(e));
                }
            }
        }
        None
    }
}

/// One message of an IPC stream, decoded.
enum IpcMessage {
    Schema(Schema),
    Batch(RecordBatch),
    /// A dictionary (kept for the batches that follow) or an empty message.
    Other,
    /// The end-of-stream marker.
    End,
    /// The input ended between two messages, without the end-of-stream marker.
    EndOfInput,
}

/// Marks a message length that follows (IPC format 0.15 and later).
const CONTINUATION: [u8; 4] = [0xff; 4];

/// Largest message header (a flatbuffer: the schema and its metadata, or a batch's buffer
/// list) accepted. A visibility table's take a few kilobytes.
const MAX_HEADER_BYTES: u64 = 16 << 20;

/// Bodies are read in steps that double up to what the header declares, so that a lying
/// header costs at most twice the bytes that actually arrived.
const FIRST_READ_BYTES: usize = 1 << 20;

/// The messages of an Arrow IPC stream, framed and bounded (see [`IpcReader`]).
struct IpcMessages {
    input: Box<dyn Read>,
    /// Bytes left in the input, when it is a file.
    left: Option<u64>,
    dictionaries: std::collections::HashMap<i64, arrow::array::ArrayRef>,
}

impl IpcMessages {
    fn new(input: Box<dyn Read>, left: Option<u64>) -> IpcMessages {
        IpcMessages { input, left, dictionaries: Default::default() }
    }

    /// Reads until `buf` is full or the input ends; the number of bytes read.
    fn fill(&mut self, buf: &mut [u8]) -> std::result::Result<usize, String> {
        let mut got = 0;
        while got < buf.len() {
            match self.input.read(&mut buf[got..]) {
                Ok(0) => break,
                Ok(n) => got += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(format!("reading: {e}")),
            }
        }
        if let Some(left) = &mut self.left {
            *left = left.saturating_sub(got as u64);
        }
        Ok(got)
    }

    /// Refuses a declared size beyond what the input holds or `limit` allows.
    fn check_declared(&self, what: &str, declared: u64, limit: u64, limit_text: &dyn std::fmt::Display) -> std::result::Result<(), String> {
        if let Some(left) = self.left.filter(|&left| declared > left) {
            return Err(format!("a {what} of {declared} bytes is declared, but only {left} bytes are left in the input"));
        }
        if declared > limit {
            let size = crate::limits::format_bytes(declared as f64);
            return Err(format!("a {what} of {declared} bytes ({size}) is declared, more than {limit_text}"));
        }
        Ok(())
    }

    /// Reads `length` bytes (already checked) into an aligned buffer.
    fn read_block(&mut self, length: u64, what: &str) -> std::result::Result<arrow::buffer::Buffer, String> {
        let length = usize::try_from(length).map_err(|_| format!("a {what} of {length} bytes does not fit in memory"))?;
        let mut block = arrow::buffer::MutableBuffer::new(0);
        while block.len() < length {
            let start = block.len();
            let end = length.min(start + start.max(FIRST_READ_BYTES));
            block.resize(end, 0);
            if self.fill(&mut block.as_slice_mut()[start..end])? < end - start {
                return Err(format!("the input ends part-way through a {what} (truncated)"));
            }
        }
        Ok(block.into())
    }

    /// The next message; `schema` is the stream's, once read.
    fn next(&mut self, schema: Option<&SchemaRef>) -> std::result::Result<IpcMessage, String> {
        let mut word = [0u8; 4];
        match self.fill(&mut word)? {
            0 => return Ok(IpcMessage::EndOfInput),
            4 => {}
            _ => return Err("the input ends part-way through a message length (truncated)".into()),
        }
        if word == CONTINUATION && self.fill(&mut word)? < 4 {
            return Err("the input ends part-way through a message length (truncated)".into());
        }
        let length = i32::from_le_bytes(word);
        if length == 0 {
            return Ok(IpcMessage::End);
        }
        let length = u64::try_from(length).map_err(|_| format!("a negative message header length ({length})"))?;
        self.check_declared("message header", length, MAX_HEADER_BYTES, &"the largest header accepted (16 MiB)")?;
        let header = self.read_block(length, "message header")?;
        let message = arrow::ipc::root_as_message(&header).map_err(|e| format!("not an Arrow IPC message header: {e}"))?;
        let body_length = message.bodyLength();
        let body_length = u64::try_from(body_length).map_err(|_| format!("a negative message body length ({body_length})"))?;
        let budget = crate::limits::memory_budget();
        self.check_declared("message body", body_length, budget.bytes, &budget)?;
        let body = self.read_block(body_length, "message body")?;
        let version = message.version();
        let missing = |what: &str| format!("a {what} message without its header");
        match message.header_type() {
            MessageHeader::Schema => {
                let schema = message.header_as_schema().ok_or_else(|| missing("schema"))?;
                Ok(IpcMessage::Schema(arrow::ipc::convert::fb_to_schema(schema)))
            }
            MessageHeader::RecordBatch => {
                let schema = schema.ok_or("a record batch before the schema")?;
                let batch = message.header_as_record_batch().ok_or_else(|| missing("record batch"))?;
                read_record_batch(&body, batch, schema.clone(), &self.dictionaries, None, &version)
                    .map(IpcMessage::Batch)
                    .map_err(|e| e.to_string())
            }
            MessageHeader::DictionaryBatch => {
                let schema = schema.ok_or("a dictionary before the schema")?;
                let dictionary = message.header_as_dictionary_batch().ok_or_else(|| missing("dictionary"))?;
                read_dictionary(&body, dictionary, schema, &mut self.dictionaries, &version).map_err(|e| e.to_string())?;
                Ok(IpcMessage::Other)
            }
            MessageHeader::NONE => Ok(IpcMessage::Other),
            other => Err(format!("unexpected {other:?} message (a visibility table has a schema and record batches)")),
        }
    }
}

/// One job's share of a table: its id suffix (`t003`) when the table is split.
pub struct Part {
    pub suffix: Option<String>,
    pub vis: Visibilities,
}

/// Most jobs one table may be split into (windows counted from the first to the last, empty
/// ones included). A day in windows of one second is 86 400; more means a value far from the
/// others (a corrupt time) or a window too small, and the window index would overflow or the
/// parts fill memory long before the imaging started.
pub const MAX_SPLIT_PARTS: usize = 100_000;

/// Reads the whole table: one part, or one per group of `split` (in group order). `split_key`
/// names the split's YAML key (`stages.source.split_by`) in errors. `None` when `cancelled()`
/// turned true.
pub fn read_parts(
    reader: &mut dyn TableReader,
    split: Option<&SplitBy>,
    split_key: &str,
    cancelled: &dyn Fn() -> bool,
) -> Result<Option<(Vec<Part>, IngestStats)>> {
    let Some(scan) = scan(reader, split, split_key, cancelled)? else { return Ok(None) };
    let Some(split) = split else {
        return Ok(Some((vec![Part { suffix: None, vis: scan.vis }], scan.stats)));
    };
    let grouping = grouping(&scan, split, split_key, &reader.source().display().to_string())?;
    let parts = scan
        .vis
        .partition(&grouping.group, grouping.suffixes.len())
        .into_iter()
        .zip(grouping.suffixes)
        .filter(|(vis, _)| !vis.is_empty())
        .map(|(vis, suffix)| Part { suffix: Some(suffix), vis })
        .collect();
    Ok(Some((parts, scan.stats)))
}

/// The rows (0-based, over the whole table) of each job `split` makes of the table, as
/// [`read_parts`] splits it: only rows kept for imaging, each part's in table order, parts in
/// group order with their id suffixes. For a caller that ships each part elsewhere as a table
/// of its own (the Python package's Dask fan-out), which then images exactly as the part.
pub fn split_rows(
    reader: &mut dyn TableReader,
    split: &SplitBy,
    split_key: &str,
    cancelled: &dyn Fn() -> bool,
) -> Result<Option<Vec<(String, Vec<u64>)>>> {
    let Some(scan) = scan(reader, Some(split), split_key, cancelled)? else { return Ok(None) };
    let grouping = grouping(&scan, split, split_key, &reader.source().display().to_string())?;
    let mut rows: Vec<Vec<u64>> = vec![Vec::new(); grouping.suffixes.len()];
    for (&g, &row) in grouping.group.iter().zip(&scan.kept_rows) {
        rows[g].push(row);
    }
    Ok(Some(grouping.suffixes.into_iter().zip(rows).filter(|(_, rows)| !rows.is_empty()).collect()))
}

/// A table read for imaging: the kept samples and, with a split, each one's split-column
/// value and table row.
struct Scan {
    vis: Visibilities,
    stats: IngestStats,
    keys: Vec<f64>,
    kept_rows: Vec<u64>,
    /// The split column's smallest value over all rows (windows start at the observation's
    /// start, flagged rows included).
    smallest: f64,
}

fn scan(reader: &mut dyn TableReader, split: Option<&SplitBy>, split_key: &str, cancelled: &dyn Fn() -> bool) -> Result<Option<Scan>> {
    let source = reader.source().display().to_string();
    if let Some(split) = split {
        split.check_schema(&reader.schema()).map_err(|m| Error::parameter(format!("{split_key}.column"), format!("{source}: {m}")))?;
    }
    let mut scan = Scan { vis: Visibilities::default(), stats: IngestStats::default(), keys: Vec::new(), kept_rows: Vec::new(), smallest: f64::INFINITY };
    let mut kept_in_batch = Vec::new();
    while let Some(batch) = reader.next_batch() {
        if cancelled() {
            return Ok(None);
        }
        let batch = batch?;
        let Some(split) = split else {
            scan.vis.push_batch(record_batch_to_visibilities(&batch, &mut scan.stats, &source)?);
            continue;
        };
        let first_row = scan.stats.rows;
        kept_in_batch.clear();
        let vis = record_batch_to_visibilities_keeping_rows(&batch, &mut scan.stats, &source, &mut kept_in_batch)?;
        let values = split_values(&batch, &split.column, &source, first_row)?;
        scan.smallest = values.values().iter().copied().filter(|v| v.is_finite()).fold(scan.smallest, f64::min);
        for &row in &kept_in_batch {
            let value = values.value(row);
            if !value.is_finite() {
                return Err(Error::input(
                    &source,
                    format!("column `{}` at row {} is {value}: a sample needs a finite value to be split by", split.column, first_row + row as u64),
                ));
            }
            scan.keys.push(value);
            scan.kept_rows.push(first_row + row as u64);
        }
        scan.vis.push_batch(vis);
    }
    Ok(Some(scan))
}

/// Each kept sample's group, and every group's id suffix (`t003`, `ch01`), empty ones included.
struct Grouping {
    group: Vec<usize>,
    suffixes: Vec<String>,
}

fn grouping(scan: &Scan, split: &SplitBy, split_key: &str, source: &str) -> Result<Grouping> {
    let (keys, smallest) = (&scan.keys, scan.smallest);
    let too_many = |key: &str, what: String| {
        Error::parameter(
            format!("{split_key}.{key}"),
            format!("{source}: {what}: more than the {MAX_SPLIT_PARTS} jobs one table may be split into (a value far from the others, or a window too small?)"),
        )
    };
    let (group, min_width): (Vec<usize>, usize) = match split.window {
        Some(window) => {
            // Counted in f64 before any index is made: a far-off value would wrap a usize or
            // ask for billions of windows.
            let largest = keys.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let windows = if keys.is_empty() { 0.0 } else { ((largest - smallest) / window).floor() + 1.0 };
            if !(windows <= MAX_SPLIT_PARTS as f64) {
                let column = &split.column;
                return Err(too_many("window", format!("column `{column}` spans {smallest:e} to {largest:e}, {windows:.3e} windows of {window}")));
            }
            (keys.iter().map(|k| ((k - smallest) / window).floor() as usize).collect(), 3)
        }
        None => {
            let mut distinct = keys.clone();
            distinct.sort_by(f64::total_cmp);
            distinct.dedup_by(|a, b| a.total_cmp(b).is_eq());
            if distinct.len() > MAX_SPLIT_PARTS {
                return Err(too_many("column", format!("column `{}` has {} distinct values", split.column, distinct.len())));
            }
            let rank = |k: &f64| distinct.binary_search_by(|d| d.total_cmp(k)).expect("every key is among the distinct values");
            (keys.iter().map(rank).collect(), 2)
        }
    };
    let groups = group.iter().max().map_or(0, |g| g + 1);
    let width = (groups.saturating_sub(1)).to_string().len().max(min_width);
    let suffixes = (0..groups).map(|g| format!("{}{g:0width$}", split.label())).collect();
    Ok(Grouping { group, suffixes })
}

/// The split column as f64 (any numeric type), nulls refused.
fn split_values(batch: &RecordBatch, column: &str, source: &str, first_row: u64) -> Result<Float64Array> {
    let array = batch
        .column_by_name(column)
        .ok_or_else(|| Error::input(source, format!("a batch lacks the split column `{column}`")))?;
    check_no_nulls(array.as_ref(), column, source, first_row)?;
    let cast = arrow::compute::cast(array, &DataType::Float64)
        .map_err(|e| Error::input(source, format!("column `{column}`: cannot read as numbers: {e}")))?;
    Ok(cast.as_any().downcast_ref::<Float64Array>().expect("cast to Float64 gives a Float64Array").clone())
}

/// The ground truth shared by a source's jobs, read when the source is built.
pub struct Truth {
    image: Vec<f64>,
    dynamic_range: Option<f64>,
    path: PathBuf,
    wcs: Option<crate::fits::ImageWcs>,
}

impl Truth {
    /// Reads the truth for `size x size` images; another size is an error (it was ignored,
    /// leaving the metrics without SNR and the user without a word).
    pub fn load(path: Option<&Path>, size: usize) -> Result<Option<Truth>> {
        let Some(path) = path else { return Ok(None) };
        let image = crate::fits::read_image(path)?;
        if (image.nx, image.ny) != (size, size) {
            return Err(Error::input(
                path,
                format!("the truth is {} x {} pixels, but the pipeline images {size} x {size} (image.size): it must be on the image's grid", image.nx, image.ny),
            ));
        }
        Ok(Some(Truth { dynamic_range: crate::metrics::dynamic_range(&image.data), image: image.data, path: path.to_path_buf(), wcs: image.wcs }))
    }
}

/// Emits one job per part, ids `<id>` or `<id>-<suffix>`.
/// `source` is the file the parts were read from (none for memory and standard input): with the
/// truth's file it is the job's inputs, which its products never replace.
pub fn emit_parts(
    id: &str,
    meta: &ObservationMeta,
    parts: Vec<Part>,
    truth: Option<&Truth>,
    source: Option<&Path>,
    emit: &mut dyn FnMut(Job) -> Result<()>,
) -> Result<()> {
    for part in parts {
        let job_id = match &part.suffix {
            Some(s) => format!("{id}-{s}"),
            None => id.to_string(),
        };
        log::info!("job {job_id}: {} visibilities", part.vis.len());
        let mut job = Job::new(job_id, meta.clone(), part.vis);
        if let Some(t) = truth {
            job.truth = Some(t.image.clone());
            job.truth_dynamic_range = t.dynamic_range;
            job.truth_wcs = t.wcs;
            job.inputs.push(t.path.clone());
        }
        job.inputs.extend(source.map(Path::to_path_buf));
        emit(job)?;
    }
    Ok(())
}

/// Why `id` cannot name a job, if it cannot: it becomes a file name inside the writer's
/// prefix (`{job}`), so it must be one name, neither empty nor a path.
pub fn job_id_problem(id: &str) -> Option<String> {
    if id.trim().is_empty() {
        return Some("expected a non-empty job id".into());
    }
    if id.contains(['/', '\\']) || id == "." || id == ".." {
        return Some(format!("job id '{id}' is a path: a job id is one file name (it replaces {{job}} in the writer's prefix, and must not lead out of its directory)"));
    }
    None
}

/// A table's job id: the file name without its extension.
pub fn stem_id(path: &Path) -> String {
    path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "job".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn job_ids_are_one_file_name() {
        assert_eq!(job_id_problem("obs-field01"), None);
        for bad in ["", "  ", "a/b", "../x", "..", ".", "a\\b"] {
            assert!(job_id_problem(bad).is_some(), "{bad:?}");
        }
    }
    use crate::vis::{write_parquet, VisTable};
    use num_complex::Complex64;

    fn meta() -> ObservationMeta {
        ObservationMeta::new(10.0, 40.0, "VLA")
    }

    /// 40 rows: times 1000 + 10 i s, two channels alternating, rows 3 and 4 flagged.
    fn table() -> VisTable {
        let n = 40;
        VisTable {
            u_m: (0..n).map(|i| 100.0 + i as f64).collect(),
            v_m: vec![5.0; n],
            w_m: vec![0.0; n],
            frequency: (0..n).map(|i| if i % 2 == 0 { 1.4e9 } else { 1.2e9 }).collect(),
            vis: (0..n).map(|i| Complex64::new(i as f64, 0.0)).collect(),
            weight: vec![1.0; n],
            flag: (0..n).map(|i| i == 3 || i == 4).collect(),
            time: (0..n).map(|i| 1000.0 + 10.0 * i as f64).collect(),
            antenna1: vec![],
            antenna2: vec![],
        }
    }

    fn parts_of(split: Option<SplitBy>, batch_rows: usize) -> (Vec<Part>, IngestStats) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("obs.parquet");
        write_parquet(&path, &table(), &meta()).unwrap();
        let extra: Vec<&str> = split.iter().map(|s| s.column.as_str()).collect();
        let mut reader = VisReader::open_with_columns(&path, batch_rows, &extra).unwrap();
        read_parts(&mut reader, split.as_ref(), "split_by", &|| false).unwrap().unwrap()
    }

    /// The `vis` real parts are the row numbers, so each part says which rows it holds.
    fn rows(part: &Part) -> Vec<usize> {
        part.vis.vis.iter().map(|z| z.re as usize).collect()
    }

    #[test]
    fn time_windows_start_at_the_first_time_and_keep_row_order() {
        // Windows of 100 s from t = 1000: rows 0-9, 10-19, 20-29, 30-39; batches of 7 rows
        // cut across windows.
        let (parts, stats) = parts_of(Some(SplitBy { column: "time".into(), window: Some(100.0) }), 7);
        assert_eq!(stats.rows, 40);
        assert_eq!(stats.flagged, 2);
        let suffixes: Vec<_> = parts.iter().map(|p| p.suffix.clone().unwrap()).collect();
        assert_eq!(suffixes, ["t000", "t001", "t002", "t003"]);
        assert_eq!(rows(&parts[0]), [0, 1, 2, 5, 6, 7, 8, 9]);
        assert_eq!(rows(&parts[3]), (30..40).collect::<Vec<_>>());
    }

    #[test]
    fn windows_without_samples_leave_a_gap_in_the_numbering() {
        // Windows of 15 s: rows 3 and 4 (t = 1030, 1040) are flagged, so window 2 ([1030, 1045))
        // is empty and no job is made for it.
        let (parts, _) = parts_of(Some(SplitBy { column: "time".into(), window: Some(15.0) }), 100);
        let suffixes: Vec<_> = parts.iter().map(|p| p.suffix.clone().unwrap()).collect();
        assert_eq!(&suffixes[..3], ["t000", "t001", "t003"]);
        assert_eq!(rows(&parts[1]), [2]);
        assert_eq!(rows(&parts[2]), [5]);
        assert_eq!(parts.iter().map(|p| p.vis.len()).sum::<usize>(), 38);
    }

    #[test]
    fn one_job_per_channel_in_frequency_order() {
        let (parts, _) = parts_of(Some(SplitBy { column: "frequency".into(), window: None }), 9);
        assert_eq!(parts.len(), 2);
        assert_eq!(parts[0].suffix.as_deref(), Some("ch00"));
        assert!(parts[0].vis.frequency.iter().all(|&f| f == 1.2e9));
        assert!(parts[1].vis.frequency.iter().all(|&f| f == 1.4e9));
        assert_eq!(rows(&parts[1]), [0, 2, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30, 32, 34, 36, 38]);
        // u is converted to wavelengths at each sample's own frequency, as without a split.
        assert_eq!(parts[0].vis.u[0], 101.0 * (1.2e9 / crate::vis::SPEED_OF_LIGHT));
    }

    /// `split_rows` names the same parts as `read_parts` and gives each the table rows it holds
    /// (the visibilities' real parts are the row numbers), for windows with a gap and channels.
    #[test]
    fn split_rows_are_the_rows_of_read_parts() {
        for split in [SplitBy { column: "time".into(), window: Some(15.0) }, SplitBy { column: "frequency".into(), window: None }] {
            let (parts, _) = parts_of(Some(split.clone()), 7);
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("obs.parquet");
            write_parquet(&path, &table(), &meta()).unwrap();
            let mut reader = VisReader::open_with_columns(&path, 7, &[split.column.as_str()]).unwrap();
            let split_rows = split_rows(&mut reader, &split, "split_by", &|| false).unwrap().unwrap();
            assert_eq!(split_rows.len(), parts.len());
            for ((suffix, rows_of_part), part) in split_rows.iter().zip(&parts) {
                assert_eq!(Some(suffix), part.suffix.as_ref());
                assert_eq!(rows_of_part.iter().map(|&r| r as usize).collect::<Vec<_>>(), rows(part));
            }
        }
    }

    #[test]
    fn without_a_split_everything_is_one_part() {
        let (parts, stats) = parts_of(None, 6);
        assert_eq!(parts.len(), 1);
        assert!(parts[0].suffix.is_none());
        assert_eq!(parts[0].vis.len() as u64, stats.kept());
        assert_eq!(stats.kept(), 38);
    }

    /// `table()` with row 7's time moved to `time`: one far-off sample.
    fn split_error_with_outlier(time: f64) -> String {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("obs.parquet");
        let mut t = table();
        t.time[7] = time;
        write_parquet(&path, &t, &meta()).unwrap();
        let mut reader = VisReader::open_with_columns(&path, 100, &["time"]).unwrap();
        let split = SplitBy { column: "time".into(), window: Some(600.0) };
        match read_parts(&mut reader, Some(&split), "stages.source.split_by", &|| false) {
            Ok(_) => panic!("a time of {time} split without error"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn window_counts_are_bounded_before_anything_is_allocated() {
        // 1e300 s wraps a usize window index; 1e13 s asks for ~1.7e10 windows (~133 GB).
        for time in [1e300, 1e13] {
            let err = split_error_with_outlier(time);
            for expected in ["obs.parquet", "`time`", "window", "stages.source.split_by.window", &format!("to {time:e},")] {
                assert!(err.contains(expected), "{time}: '{expected}' missing from: {err}");
            }
        }
    }

    #[test]
    fn split_columns_must_exist_and_be_numeric() {
        let schema = Schema::new(vec![
            arrow::datatypes::Field::new("time", DataType::Float64, false),
            arrow::datatypes::Field::new("flag", DataType::Boolean, false),
        ]);
        let missing = SplitBy { column: "tme".into(), window: None }.check_schema(&schema).unwrap_err();
        assert!(missing.contains("`tme`") && missing.contains("columns: time, flag"), "{missing}");
        let boolean = SplitBy { column: "flag".into(), window: None }.check_schema(&schema).unwrap_err();
        assert!(boolean.contains("numeric"), "{boolean}");
        assert!(SplitBy { column: "time".into(), window: Some(0.0) }.check().is_err());
        assert!(SplitBy { column: "time".into(), window: Some(f64::NAN) }.check().is_err());
    }
}
