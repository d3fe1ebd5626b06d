//! Visibility tables: the Parquet files of Stokes I samples, read in bounded batches, and
//! their Arrow form (the columns below), shared by the Parquet, Arrow IPC and in-memory
//! sources.
//!
//! One row per visibility sample. Columns (names fixed, other columns ignored):
//!
//! | column                 | type               | meaning                             |
//! |------------------------|--------------------|-------------------------------------|
//! | `u`, `v`, `w`          | float64            | baseline coordinates, metres        |
//! | `frequency`            | float64            | Hz                                  |
//! | `vis_re`, `vis_im`     | float32 or float64 | Stokes I visibility, Jy             |
//! | `weight` (optional)    | float32 or float64 | natural weight 1/sigma^2, default 1 |
//! | `flag` (optional)      | bool               | true = bad sample, default false    |
//! | `time` (optional)      | float64            | seconds (not read by the imager)    |
//! | `antenna1`, `antenna2` | int32 (optional)   | antenna indices (not read either)   |
//!
//! File key-value metadata: `phase_centre_ra_deg`, `phase_centre_dec_deg` and `telescope`
//! are required; simulated files add `noise_sigma` and `dynamic_range`; any other key is
//! kept in [`ObservationMeta::extra`].
//!
//! Baselines are stored in metres because that is what is measured and what is the same
//! for every channel; the reader converts them to wavelengths, the unit the imaging
//! operators work in, and drops rows that must not be imaged (flagged, non-finite,
//! physically impossible, non-positive weight), counting each reason in [`IngestStats`].

use super::data::{ObservationMeta, Visibilities, FREQUENCY_RANGE_HZ, MAX_BASELINE_M, SPEED_OF_LIGHT};
use super::error::TableError;
use std::borrow::Cow;
use std::fmt;
use std::fs::File;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, BooleanArray, Float32Array, Float64Array, Int32Array, RecordBatch};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};
use num_complex::{Complex32, Complex64};
use parquet::arrow::arrow_reader::{ParquetRecordBatchReader, ParquetRecordBatchReaderBuilder};
use parquet::arrow::{ArrowWriter, ProjectionMask};
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use parquet::schema::types::ColumnPath;

use crate::fits::TempSibling;
use crate::{Error, Result};

/// Batch size of [`read_parquet`]: large enough to amortise per-batch work, small
/// enough (a few MB per column) not to matter next to the visibilities themselves.
pub const DEFAULT_BATCH_ROWS: usize = 65_536;

/// [`DEFAULT_BATCH_ROWS`] as a serde default, for the sources that read tables in batches.
pub fn default_batch_rows() -> usize {
    DEFAULT_BATCH_ROWS
}

/// Rows per Parquet row group written: about 50 MB uncompressed, big enough for good
/// compression and cheap footers, small enough for readers to stream.
const ROW_GROUP_ROWS: usize = 1 << 20;

/// How many rows were read and why those not kept were excluded.
///
/// Each excluded row is counted once, under the first reason that applies, in the order
/// of the fields: flagged, then non-finite (any of u, v, w, frequency, visibility,
/// weight), then physically impossible (a baseline coordinate beyond [`MAX_BASELINE_M`],
/// a frequency outside [`FREQUENCY_RANGE_HZ`], a visibility or weight beyond the single
/// precision they are kept in, 3.4e38), then non-positive weight (also a weight below
/// single precision's smallest, 1.4e-45).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IngestStats {
    pub rows: u64,
    pub flagged: u64,
    pub non_finite: u64,
    pub impossible: u64,
    pub nonpositive_weight: u64,
}

impl IngestStats {
    /// Rows kept for imaging.
    pub fn kept(&self) -> u64 {
        self.rows - self.excluded()
    }

    /// Rows dropped, for any reason.
    pub fn excluded(&self) -> u64 {
        self.flagged + self.non_finite + self.impossible + self.nonpositive_weight
    }

    fn add(&mut self, other: &IngestStats) {
        self.rows += other.rows;
        self.flagged += other.flagged;
        self.non_finite += other.non_finite;
        self.impossible += other.impossible;
        self.nonpositive_weight += other.nonpositive_weight;
    }

    /// Logs the counts of a table read from `source`, with a warning when rows had values no
    /// instrument measures: the file is damaged or was written wrongly.
    pub fn log(&self, source: &Path) {
        log::info!("{}: {self}", source.display());
        if self.impossible > 0 {
            let (low, high) = FREQUENCY_RANGE_HZ;
            log::warn!(
                "{}: {} physically impossible rows excluded (a baseline coordinate beyond {MAX_BASELINE_M:e} m, a frequency outside {low:e} .. {high:e} Hz, or a visibility or weight beyond {:e}): is the file damaged?",
                source.display(),
                self.impossible,
                f32::MAX
            );
        }
    }
}

impl fmt::Display for IngestStats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} samples read, {} kept, {} excluded ({} flagged, {} non-finite, {} physically impossible, {} non-positive weight)",
            self.rows,
            self.kept(),
            self.excluded(),
            self.flagged,
            self.non_finite,
            self.impossible,
            self.nonpositive_weight
        )
    }
}

/// Types a column may have.
#[derive(Clone, Copy)]
enum ColumnType {
    Float64,
    /// Float32 or Float64: visibilities and weights rarely need double precision.
    AnyFloat,
    Boolean,
}

impl ColumnType {
    fn accepts(self, data_type: &DataType) -> bool {
        match self {
            ColumnType::Float64 => *data_type == DataType::Float64,
            ColumnType::AnyFloat => matches!(data_type, DataType::Float32 | DataType::Float64),
            ColumnType::Boolean => *data_type == DataType::Boolean,
        }
    }

    fn describe(self) -> &'static str {
        match self {
            ColumnType::Float64 => "Float64",
            ColumnType::AnyFloat => "Float32 or Float64",
            ColumnType::Boolean => "Boolean",
        }
    }
}

/// The columns the reader uses, with their accepted types; others are ignored.
const READ_COLUMNS: [(&str, ColumnType, bool); 9] = [
    ("u", ColumnType::Float64, true),
    ("v", ColumnType::Float64, true),
    ("w", ColumnType::Float64, true),
    ("frequency", ColumnType::Float64, true),
    ("vis_re", ColumnType::AnyFloat, true),
    ("vis_im", ColumnType::AnyFloat, true),
    ("weight", ColumnType::AnyFloat, false),
    ("flag", ColumnType::Boolean, false),
    ("imaging_weight", ColumnType::AnyFloat, false),
];

/// Checks that the columns the reader uses exist (when required), once, with an
/// accepted type.
pub(crate) fn validate_schema(schema: &Schema, source: &str) -> Result<()> {
    for (name, column_type, required) in READ_COLUMNS {
        let mut matching = schema.fields().iter().filter(|f| f.name() == name);
        match (matching.next(), matching.next()) {
            (None, _) if required => {
                return Err(TableError::column(
                    source,
                    name,
                    format!("missing required column `{name}` ({})", column_type.describe()),
                )
                .into())
            }
            (None, _) => {}
            (Some(_), Some(_)) => {
                return Err(TableError::column(source, name, format!("column `{name}` appears more than once")).into())
            }
            (Some(field), None) if !column_type.accepts(field.data_type()) => {
                return Err(TableError::column(
                    source,
                    name,
                    format!(
                        "column `{name}` has type {}; accepted types: {}",
                        field.data_type(),
                        column_type.describe()
                    ),
                )
                .into())
            }
            (Some(_), None) => {}
        }
    }
    Ok(())
}

/// Refuses nulls: a missing value is not a sample, and guessing one would be wrong.
pub(crate) fn check_no_nulls(array: &dyn Array, name: &str, source: &str, first_row: u64) -> Result<()> {
    if array.null_count() == 0 {
        return Ok(());
    }
    let first = (0..array.len()).find(|&i| array.is_null(i)).unwrap_or(0);
    Err(TableError::column(
        source,
        name,
        format!(
            "column `{name}` has {} null values (first at row {}); nulls are not allowed",
            array.null_count(),
            first_row + first as u64
        ),
    )
    .into())
}

/// A float column as f64, borrowed when it already is f64; `None` if the batch lacks it.
fn float_column<'a>(
    batch: &'a RecordBatch,
    name: &str,
    source: &str,
    first_row: u64,
) -> Result<Option<Cow<'a, [f64]>>> {
    let Some(array) = batch.column_by_name(name) else { return Ok(None) };
    check_no_nulls(array.as_ref(), name, source, first_row)?;
    if let Some(a) = array.as_any().downcast_ref::<Float64Array>() {
        Ok(Some(Cow::Borrowed(a.values().as_ref())))
    } else if let Some(a) = array.as_any().downcast_ref::<Float32Array>() {
        Ok(Some(Cow::Owned(a.values().iter().map(|&x| f64::from(x)).collect())))
    } else {
        Err(TableError::column(
            source,
            name,
            format!("column `{name}` has type {}; expected Float32 or Float64", array.data_type()),
        )
        .into())
    }
}

fn required_float_column<'a>(
    batch: &'a RecordBatch,
    name: &str,
    source: &str,
    first_row: u64,
) -> Result<Cow<'a, [f64]>> {
    float_column(batch, name, source, first_row)?
        .ok_or_else(|| TableError::column(source, name, format!("missing required column `{name}`")).into())
}

/// Converts one Arrow batch in the visibility format to imaging input: baselines to
/// wavelengths, excluded rows dropped and counted in `stats` (whose `rows` so far also
/// numbers the rows in error messages). `source` names the data in errors.
pub fn record_batch_to_visibilities(
    batch: &RecordBatch,
    stats: &mut IngestStats,
    source: &str,
) -> Result<Visibilities> {
    convert_batch(batch, stats, source, None)
}

/// As [`record_batch_to_visibilities`], also appending to `kept_rows` the batch row index of
/// each sample kept, so that callers can follow other columns (time, to split a table)
/// through the filter.
pub fn record_batch_to_visibilities_keeping_rows(
    batch: &RecordBatch,
    stats: &mut IngestStats,
    source: &str,
    kept_rows: &mut Vec<usize>,
) -> Result<Visibilities> {
    convert_batch(batch, stats, source, Some(kept_rows))
}

fn convert_batch(
    batch: &RecordBatch,
    stats: &mut IngestStats,
    source: &str,
    mut kept_rows: Option<&mut Vec<usize>>,
) -> Result<Visibilities> {
    validate_schema(batch.schema_ref(), source)?;
    let first_row = stats.rows;
    let column = |name| required_float_column(batch, name, source, first_row);
    let (u, v, w, frequency) = (column("u")?, column("v")?, column("w")?, column("frequency")?);
    let (re, im) = (column("vis_re")?, column("vis_im")?);
    let weight = float_column(batch, "weight", source, first_row)?;
    let imaging_weight = float_column(batch, "imaging_weight", source, first_row)?;
    let flag = match batch.column_by_name("flag") {
        Some(array) => {
            check_no_nulls(array.as_ref(), "flag", source, first_row)?;
            let flags = array.as_any().downcast_ref::<BooleanArray>().ok_or_else(|| {
                TableError::column(source, "flag", format!("column `flag` has type {}; expected Boolean", array.data_type()))
            })?;
            Some(flags)
        }
        None => None,
    };

    let n = batch.num_rows();
    let mut counts = IngestStats { rows: n as u64, ..IngestStats::default() };
    let mut out = Visibilities::with_capacity(n);
    for i in 0..n {
        if flag.is_some_and(|f| f.value(i)) {
            counts.flagged += 1;
            continue;
        }
        let wt = weight.as_ref().map_or(1.0, |w| w[i]);
        let imaging = imaging_weight.as_ref().map_or(1.0, |w| w[i]);
        let values = [u[i], v[i], w[i], frequency[i], re[i], im[i], wt, imaging];
        if !values.iter().all(|x| x.is_finite()) {
            counts.non_finite += 1;
            continue;
        }
        let (low, high) = FREQUENCY_RANGE_HZ;
        if [u[i], v[i], w[i]].iter().any(|x| x.abs() > MAX_BASELINE_M)
            || !(low..=high).contains(&frequency[i])
            || [re[i], im[i], wt, imaging].iter().any(|x| x.abs() > f64::from(f32::MAX))
            || imaging < 0.0
        {
            counts.impossible += 1;
            continue;
        }
        // Stored in single precision (see `Visibilities`): a weight too small for it is zero.
        let stored_weight = wt as f32;
        if stored_weight <= 0.0 {
            counts.nonpositive_weight += 1;
            continue;
        }
        let per_metre = frequency[i] / SPEED_OF_LIGHT;
        if let Some(rows) = kept_rows.as_mut() {
            rows.push(i);
        }
        out.push(
            [u[i] * per_metre, v[i] * per_metre],
            w[i] * per_metre,
            Complex32::new(re[i] as f32, im[i] as f32),
            stored_weight,
            frequency[i],
        );
        if imaging_weight.is_some() {
            out.imaging_weight.push(imaging as f32);
        }
    }
    stats.add(&counts);
    Ok(out)
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
        let total_rows = u64::try_from(file_metadata.num_rows()).unwrap_or(0);
        validate_schema(builder.schema(), &source)?;

        // Decode only the columns used: time and antennas would cost reading time and memory.
        let used: Vec<usize> = builder
            .schema()
            .fields()
            .iter()
            .enumerate()
            .filter(|(_, field)| {
                READ_COLUMNS.iter().any(|(name, _, _)| field.name() == name) || extra.contains(&field.name().as_str())
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
    pub fn stats(&self) -> IngestStats {
        self.stats
    }

    /// Rows in the file according to its footer, for progress reports.
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

/// Record batches decoded from untrusted bytes: decoding errors and panics become errors
/// naming the file and the row reached, and nothing is read after the first one.
pub(crate) struct GuardedBatches<I> {
    path: PathBuf,
    decoder: &'static str,
    batches: I,
    rows_decoded: u64,
    finished: bool,
}

impl<I, E> GuardedBatches<I>
where
    I: Iterator<Item = std::result::Result<RecordBatch, E>>,
    E: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    pub(crate) fn new(path: &Path, decoder: &'static str, batches: I) -> Self {
        GuardedBatches { path: path.to_path_buf(), decoder, batches, rows_decoded: 0, finished: false }
    }

    /// The next batch; `None` at the end or after an error.
    pub(crate) fn next_batch(&mut self) -> Option<Result<RecordBatch>> {
        if self.finished {
            return None;
        }
        let batches = &mut self.batches;
        let what = format!("corrupt {} data after row {}", self.decoder, self.rows_decoded);
        let item = contain_panics(&self.path, &what, self.decoder, || batches.next().transpose()).transpose();
        match &item {
            Some(Ok(batch)) => self.rows_decoded += batch.num_rows() as u64,
            _ => self.finished = true,
        }
        item
    }
}

/// Decoder names for [`contain_panics`]'s messages.
pub(crate) const PARQUET: &str = "Parquet";
pub(crate) const ARROW_IPC: &str = "Arrow IPC";

/// Runs decoding of untrusted bytes (Parquet, Arrow IPC: `decoder` names it), turning errors
/// and panics alike into a [`TableError`] naming the file (the decoder's error its source).
///
/// parquet 55 panics on some corrupt pages instead of returning an error (dictionary
/// indices are not bounds-checked: apache/arrow-rs#9434, fixed in later releases), and a
/// damaged file must not bring down the process. Unwinding is contained here, where
/// callers stop using the decoder after any failure (`VisReader` ends its iteration), so
/// no state it may have left half-updated is observed. The panic is not printed: the error
/// says it all, with the decoder's source location.
pub(crate) fn contain_panics<T, E: Into<Box<dyn std::error::Error + Send + Sync>>>(
    path: &Path,
    what: &str,
    decoder: &'static str,
    decode: impl FnOnce() -> std::result::Result<T, E>,
) -> Result<T> {
    match crate::error::catch_quietly(decode) {
        Ok(Ok(value)) => Ok(value),
        Ok(Err(e)) => Err(TableError::decode(path, what, e).into()),
        Err(message) => Err(TableError::DecoderPanic {
            path: path.to_path_buf(),
            doing: what.to_string(),
            decoder,
            message,
        }
        .into()),
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

/// A visibility table as the simulator produces it: every row, baselines in metres.
///
/// `u_m`, `v_m`, `w_m`, `frequency` and `vis` must have one entry per row; the columns
/// the format makes optional (`weight`, `flag`, `time`, `antenna1`, `antenna2`) may
/// instead be empty, and are then not written.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct VisTable {
    pub u_m: Vec<f64>,
    pub v_m: Vec<f64>,
    pub w_m: Vec<f64>,
    /// Hz.
    pub frequency: Vec<f64>,
    /// Stokes I, Jy.
    pub vis: Vec<Complex64>,
    /// Natural weight 1/sigma^2.
    pub weight: Vec<f64>,
    pub flag: Vec<bool>,
    /// Seconds.
    pub time: Vec<f64>,
    pub antenna1: Vec<i32>,
    pub antenna2: Vec<i32>,
}

impl VisTable {
    /// Number of rows.
    pub fn len(&self) -> usize {
        self.u_m.len()
    }

    pub fn is_empty(&self) -> bool {
        self.u_m.is_empty()
    }

    /// Checks the column lengths; returns the number of rows.
    fn check_lengths(&self) -> Result<usize> {
        let n = self.len();
        let required = [
            ("v_m", self.v_m.len()),
            ("w_m", self.w_m.len()),
            ("frequency", self.frequency.len()),
            ("vis", self.vis.len()),
        ];
        let optional = [
            ("weight", self.weight.len()),
            ("flag", self.flag.len()),
            ("time", self.time.len()),
            ("antenna1", self.antenna1.len()),
            ("antenna2", self.antenna2.len()),
        ];
        let bad = required.iter().find(|(_, len)| *len != n);
        let bad = bad.or_else(|| optional.iter().find(|(_, len)| *len != n && *len != 0));
        match bad {
            Some((name, len)) => Err(Error::parameter(
                format!("table.{name}"),
                format!("has {len} entries but table.u_m has {n} rows"),
            )),
            None => Ok(n),
        }
    }

    /// The imageable rows in wavelengths, excluded rows counted: exactly what reading the
    /// table back from Parquet would give (same conversion, same filter).
    pub fn to_visibilities(&self, source: &str) -> Result<(Visibilities, IngestStats)> {
        let n = self.check_lengths()?;
        let batch = RecordBatch::try_new(Arc::new(self.schema()), self.columns(0..n))
            .map_err(|e| TableError::Build { table: source.to_string(), source: e })?;
        let mut stats = IngestStats::default();
        let vis = record_batch_to_visibilities(&batch, &mut stats, source)?;
        Ok((vis, stats))
    }

    /// The Arrow schema of the written file: no nulls anywhere.
    fn schema(&self) -> Schema {
        let float64 = |name: &str| Field::new(name, DataType::Float64, false);
        let mut fields = ["u", "v", "w", "frequency", "vis_re", "vis_im"].map(float64).to_vec();
        if !self.weight.is_empty() {
            fields.push(float64("weight"));
        }
        if !self.flag.is_empty() {
            fields.push(Field::new("flag", DataType::Boolean, false));
        }
        if !self.time.is_empty() {
            fields.push(float64("time"));
        }
        for (name, column) in [("antenna1", &self.antenna1), ("antenna2", &self.antenna2)] {
            if !column.is_empty() {
                fields.push(Field::new(name, DataType::Int32, false));
            }
        }
        Schema::new(fields)
    }

    /// The rows in `rows` as arrays, in the order of `schema()`.
    fn columns(&self, rows: Range<usize>) -> Vec<ArrayRef> {
        let float64 =
            |values: &[f64]| Arc::new(Float64Array::from(values[rows.clone()].to_vec())) as ArrayRef;
        let vis = &self.vis[rows.clone()];
        let mut columns = vec![
            float64(&self.u_m),
            float64(&self.v_m),
            float64(&self.w_m),
            float64(&self.frequency),
            Arc::new(vis.iter().map(|z| z.re).collect::<Float64Array>()) as ArrayRef,
            Arc::new(vis.iter().map(|z| z.im).collect::<Float64Array>()) as ArrayRef,
        ];
        if !self.weight.is_empty() {
            columns.push(float64(&self.weight));
        }
        if !self.flag.is_empty() {
            columns.push(Arc::new(BooleanArray::from(self.flag[rows.clone()].to_vec())));
        }
        if !self.time.is_empty() {
            columns.push(float64(&self.time));
        }
        for column in [&self.antenna1, &self.antenna2] {
            if !column.is_empty() {
                columns.push(Arc::new(Int32Array::from(column[rows.clone()].to_vec())));
            }
        }
        columns
    }
}

/// A visibility table as Arrow record batches of at most `batch_rows` rows, the observation
/// metadata in the schema's metadata: what an Arrow IPC stream of the table carries, and what
/// the in-memory source (`kind: arrow`) reads.
pub fn to_record_batches(table: &VisTable, meta: &ObservationMeta, batch_rows: usize) -> Result<(SchemaRef, Vec<RecordBatch>)> {
    let n = table.check_lengths()?;
    let metadata = meta.to_pairs()?.into_iter().collect();
    let schema = Arc::new(table.schema().with_metadata(metadata));
    let batches = (0..n)
        .step_by(batch_rows.max(1))
        .map(|start| {
            let rows = start..(start + batch_rows.max(1)).min(n);
            RecordBatch::try_new(schema.clone(), table.columns(rows))
                .map_err(|e| TableError::Build { table: String::new(), source: e }.into())
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((schema, batches))
}

/// Writes a visibility table and its metadata as Parquet (zstd, row groups of about a
/// million rows), replacing `path` atomically: the file is written to a temporary
/// sibling, synced and renamed, and the temporary is removed on failure.
pub fn write_parquet(path: &Path, table: &VisTable, meta: &ObservationMeta) -> Result<()> {
    let n = table.check_lengths()?;
    let metadata: Vec<KeyValue> = meta.to_pairs()?.into_iter().map(|(k, v)| KeyValue::new(k, v)).collect();
    let mut properties = WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::default()))
        .set_max_row_group_size(ROW_GROUP_ROWS)
        .set_key_value_metadata(Some(metadata));
    // Nearly every value of these is distinct: a dictionary would only be built to be
    // abandoned. Frequency, weight, flag and antennas repeat and keep theirs.
    for column in ["u", "v", "w", "vis_re", "vis_im", "time"] {
        properties = properties.set_column_dictionary_enabled(ColumnPath::from(column), false);
    }
    let properties = properties.build();
    // The metadata also on the stored Arrow schema, which pyarrow's `read_table` prefers to the
    // file's key-value metadata: a table read back in Python keeps its phase centre.
    let schema = Arc::new(table.schema().with_metadata(meta.to_pairs()?.into_iter().collect()));
    let failed = |doing, source: Box<dyn std::error::Error + Send + Sync>| {
        Error::io(path, std::io::Error::other(TableError::Write { doing, source }))
    };
    let write_error = |e: parquet::errors::ParquetError| failed("writing Parquet", e.into());

    let tmp = TempSibling::new(path)?;
    let file = File::create(tmp.path()).map_err(|e| Error::io(path, e))?;
    let mut writer = ArrowWriter::try_new(file, schema.clone(), Some(properties)).map_err(write_error)?;
    // One row group at a time, so only one group's columns are copied into Arrow arrays.
    for start in (0..n).step_by(ROW_GROUP_ROWS) {
        let rows = start..(start + ROW_GROUP_ROWS).min(n);
        let batch = RecordBatch::try_new(schema.clone(), table.columns(rows))
            .map_err(|e| failed("building a record batch", e.into()))?;
        writer.write(&batch).map_err(write_error)?;
    }
    let file = writer.into_inner().map_err(write_error)?;
    file.sync_all().map_err(|e| Error::io(path, e))?;
    drop(file);
    tmp.persist()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn test_meta() -> ObservationMeta {
        ObservationMeta {
            phase_centre_ra_deg: 187.70593075,
            phase_centre_dec_deg: 12.39112331,
            telescope: "VLA".to_string(),
            noise_sigma: Some(0.012345678901234567),
            dynamic_range: Some(1.0e4),
            extra: BTreeMap::from([("simulator".to_string(), "r2d2-sim 0.1".to_string())]),
        }
    }

    /// `n` rows with distinct values and nothing to exclude.
    fn test_table(n: usize) -> VisTable {
        VisTable {
            u_m: (0..n).map(|i| 10.0 + i as f64).collect(),
            v_m: (0..n).map(|i| -3.5 * i as f64).collect(),
            w_m: (0..n).map(|i| 0.25 * i as f64).collect(),
            frequency: (0..n).map(|i| 1.0e9 + 1.0e6 * (i % 4) as f64).collect(),
            vis: (0..n).map(|i| Complex64::new(i as f64, -(i as f64) / 3.0)).collect(),
            weight: (0..n).map(|i| 1.0 + (i % 7) as f64).collect(),
            flag: vec![false; n],
            time: (0..n).map(|i| 4.5e9 + i as f64).collect(),
            antenna1: (0..n).map(|i| (i % 27) as i32).collect(),
            antenna2: (0..n).map(|i| (i % 27 + 1) as i32).collect(),
        }
    }

    /// Writes arbitrary columns and metadata, to make files our writer would not.
    fn write_custom(path: &Path, columns: Vec<(&str, ArrayRef)>, metadata: &[(&str, &str)]) {
        let batch = RecordBatch::try_from_iter(columns).unwrap();
        let kv = metadata.iter().map(|(k, v)| KeyValue::new(k.to_string(), v.to_string())).collect();
        let props = WriterProperties::builder().set_key_value_metadata(Some(kv)).build();
        let mut writer =
            ArrowWriter::try_new(File::create(path).unwrap(), batch.schema(), Some(props)).unwrap();
        writer.write(&batch).unwrap();
        writer.close().unwrap();
    }

    const GOOD_METADATA: &[(&str, &str)] =
        &[("phase_centre_ra_deg", "10.5"), ("phase_centre_dec_deg", "-30"), ("telescope", "MeerKAT")];

    fn f64s(values: &[f64]) -> ArrayRef {
        Arc::new(Float64Array::from(values.to_vec()))
    }

    fn f32s(values: &[f32]) -> ArrayRef {
        Arc::new(Float32Array::from(values.to_vec()))
    }

    /// The required columns, all float64, two rows.
    fn basic_columns() -> Vec<(&'static str, ArrayRef)> {
        vec![
            ("u", f64s(&[1.0, 2.0])),
            ("v", f64s(&[3.0, 4.0])),
            ("w", f64s(&[0.0, 0.5])),
            ("frequency", f64s(&[1e9, 2e9])),
            ("vis_re", f64s(&[1.0, 2.0])),
            ("vis_im", f64s(&[0.0, -1.0])),
        ]
    }

    /// A visibility as [`Visibilities`] keeps it.
    fn single(z: Complex64) -> Complex32 {
        Complex32::new(z.re as f32, z.im as f32)
    }

    fn open_error(path: &Path) -> String {
        match VisReader::open(path, 100) {
            Ok(_) => panic!("{} opened without error", path.display()),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn round_trip_converts_to_wavelengths_and_keeps_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("vis.parquet");
        let mut table = test_table(5);
        // 299.792458 m at 1 GHz is exactly 1000 wavelengths.
        table.u_m[2] = 299.792458;
        table.frequency[2] = 1.0e9;
        write_parquet(&path, &table, &test_meta()).unwrap();
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, vec!["vis.parquet"], "no temporary left behind");

        let (vis, meta, stats) = read_parquet(&path).unwrap();
        assert_eq!(meta, test_meta());
        assert_eq!(stats, IngestStats { rows: 5, ..IngestStats::default() });
        assert_eq!(vis.len(), 5);
        assert!((vis.u[2] - 1000.0).abs() < 1e-9, "u = {}", vis.u[2]);
        for i in 0..5 {
            let per_metre = table.frequency[i] / 299_792_458.0;
            assert_eq!(vis.u[i], table.u_m[i] * per_metre);
            assert_eq!(vis.v[i], table.v_m[i] * per_metre);
            assert_eq!(vis.w[i], table.w_m[i] * per_metre);
            assert_eq!(vis.vis[i], single(table.vis[i]));
            assert_eq!(vis.weight[i], table.weight[i] as f32);
            assert_eq!(vis.frequency[i], table.frequency[i]);
        }
        let expected_max = (0..5).map(|i| vis.u[i].hypot(vis.v[i])).fold(0.0, f64::max);
        assert_eq!(vis.max_uv(), expected_max);
    }

    #[test]
    fn excluded_rows_are_dropped_and_counted_once() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad-rows.parquet");
        let mut table = test_table(10);
        table.flag[0] = true;
        table.flag[1] = true;
        table.vis[1] = Complex64::new(f64::NAN, 0.0); // flagged and NaN: counted as flagged
        table.vis[2] = Complex64::new(0.0, f64::NAN);
        table.u_m[3] = f64::INFINITY;
        table.weight[4] = 0.0;
        table.weight[5] = -2.0;
        table.weight[6] = f64::NAN; // non-finite before non-positive
        write_parquet(&path, &table, &test_meta()).unwrap();

        let (vis, _, stats) = read_parquet(&path).unwrap();
        assert_eq!(stats, IngestStats { rows: 10, flagged: 2, non_finite: 3, impossible: 0, nonpositive_weight: 2 });
        assert_eq!(stats.kept(), 3);
        assert_eq!(vis.len(), 3);
        assert_eq!(vis.vis, [7, 8, 9].map(|i| single(table.vis[i])));
        assert_eq!(
            stats.to_string(),
            "10 samples read, 3 kept, 7 excluded (2 flagged, 3 non-finite, 0 physically impossible, 2 non-positive weight)"
        );
    }

    #[test]
    fn physically_impossible_rows_are_excluded_and_counted() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("impossible.parquet");
        let mut table = test_table(10);
        table.u_m[0] = 1e9; // a million kilometres: no telescope on Earth
        table.v_m[1] = -1e300;
        table.w_m[2] = 2e7;
        table.frequency[3] = 0.0;
        table.frequency[4] = -1.4e9;
        table.frequency[5] = 1e20;
        table.frequency[6] = 10.0;
        write_parquet(&path, &table, &test_meta()).unwrap();
        let (vis, _, stats) = read_parquet(&path).expect("impossible rows are excluded, not an error");
        assert_eq!((stats.rows, stats.kept()), (10, 3));
        assert_eq!(vis.vis, [7, 8, 9].map(|i| single(table.vis[i])));
        let text = stats.to_string();
        assert!(text.contains("7 physically impossible"), "{text}");
        // Beyond what single precision holds (the visibilities' and weights' type), and a
        // weight it rounds to zero.
        let mut table = test_table(6);
        table.vis[0] = Complex64::new(1e39, 0.0);
        table.vis[1] = Complex64::new(0.0, -4e38);
        table.weight[2] = 1e300;
        table.weight[3] = 1e-50;
        write_parquet(&path, &table, &test_meta()).unwrap();
        let (vis, _, stats) = read_parquet(&path).unwrap();
        assert_eq!((stats.impossible, stats.nonpositive_weight, stats.kept()), (3, 1, 2), "{stats}");
        assert_eq!(vis.weight, [table.weight[4] as f32, table.weight[5] as f32]);
    }

    #[test]
    fn right_ascension_outside_0_to_360_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ra.parquet");
        for ra in ["360", "-0.5", "1e300", "inf"] {
            write_custom(&path, basic_columns(), &[("phase_centre_ra_deg", ra), GOOD_METADATA[1], GOOD_METADATA[2]]);
            let err = open_error(&path);
            assert!(err.contains(&format!("`phase_centre_ra_deg` = {ra}")) && err.contains("[0, 360)"), "{ra}: {err}");
        }
        write_custom(&path, basic_columns(), &[("phase_centre_ra_deg", "359.9"), GOOD_METADATA[1], GOOD_METADATA[2]]);
        assert!(VisReader::open(&path, 100).is_ok());
    }

    #[test]
    fn float32_columns_are_accepted_and_optional_columns_default() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f32.parquet");
        let mut columns = basic_columns();
        columns[4] = ("vis_re", f32s(&[1.5, 2.5]));
        columns[5] = ("vis_im", f32s(&[-0.5, 0.25]));
        write_custom(&path, columns.clone(), GOOD_METADATA);
        let (vis, meta, stats) = read_parquet(&path).unwrap();
        assert_eq!(vis.vis, vec![Complex32::new(1.5, -0.5), Complex32::new(2.5, 0.25)]);
        assert_eq!(vis.weight, vec![1.0, 1.0]);
        assert_eq!(stats.kept(), 2);
        assert_eq!((meta.phase_centre_dec_deg, meta.telescope.as_str()), (-30.0, "MeerKAT"));
        assert_eq!((meta.noise_sigma, meta.dynamic_range), (None, None));
        assert!(meta.extra.is_empty(), "{:?}", meta.extra);

        columns.push(("weight", f32s(&[2.0, 0.5])));
        columns.push(("flag", Arc::new(BooleanArray::from(vec![true, false]))));
        write_custom(&path, columns, GOOD_METADATA);
        let (vis, _, stats) = read_parquet(&path).unwrap();
        assert_eq!((vis.weight, stats.flagged), (vec![0.5], 1));
    }

    #[test]
    fn missing_vis_im_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no-im.parquet");
        let columns = basic_columns().into_iter().filter(|(name, _)| *name != "vis_im").collect();
        write_custom(&path, columns, GOOD_METADATA);
        let err = open_error(&path);
        assert!(err.contains("no-im.parquet") && err.contains("`vis_im`"), "{err}");
    }

    /// A program can tell what went wrong from the error's kind, not its text, and reach the
    /// decoder's own error through `source()`.
    #[test]
    fn table_errors_are_typed_and_keep_the_decoder_error() {
        let dir = tempfile::tempdir().unwrap();
        let not_parquet = dir.path().join("text.parquet");
        std::fs::write(&not_parquet, "u,v,w\n1,2,3\n").unwrap();
        let Err(err) = VisReader::open(&not_parquet, 100) else { panic!("a text file opened as Parquet") };
        let Error::Table(TableError::Decode { path, doing, .. }) = &err else { panic!("not a decoding error: {err:?}") };
        assert_eq!((path.as_path(), doing.as_str()), (not_parquet.as_path(), "not a readable Parquet file"));
        let module = err.module_error().expect("a module error");
        assert!(module.is::<TableError>());
        let chain: Vec<&(dyn std::error::Error + 'static)> =
            std::iter::successors(Some(&err as &(dyn std::error::Error + 'static)), |e| e.source()).collect();
        let parquet = chain.iter().find_map(|e| e.downcast_ref::<parquet::errors::ParquetError>());
        let parquet = parquet.unwrap_or_else(|| panic!("no ParquetError in the chain of {err:?}"));
        // Said once, after what was being done: the cause is the source, not also the text.
        let said = err.to_string();
        assert_eq!(said, format!("{}: not a readable Parquet file: {parquet}", not_parquet.display()));
        assert!(!module.to_string().contains(&parquet.to_string()), "{module}");

        let path = dir.path().join("no-u.parquet");
        let columns = basic_columns().into_iter().filter(|(name, _)| *name != "u").collect();
        write_custom(&path, columns, GOOD_METADATA);
        let Err(err) = VisReader::open(&path, 100) else { panic!("a table without `u` opened") };
        let Error::Table(TableError::Column { column, table, .. }) = &err else { panic!("not a column error: {err:?}") };
        assert_eq!((column.as_str(), table.as_str()), ("u", path.display().to_string().as_str()));
        assert!(std::error::Error::source(&err).is_some_and(|e| e.is::<TableError>()));
    }

    #[test]
    fn integer_u_is_rejected_with_accepted_types() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("int-u.parquet");
        let mut columns = basic_columns();
        columns[0] = ("u", Arc::new(arrow::array::Int64Array::from(vec![1, 2])));
        write_custom(&path, columns, GOOD_METADATA);
        let err = open_error(&path);
        assert!(err.contains("`u`") && err.contains("Int64") && err.contains("Float64"), "{err}");
    }

    #[test]
    fn missing_or_bad_metadata_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("meta.parquet");
        write_custom(&path, basic_columns(), &GOOD_METADATA[..2]);
        let err = open_error(&path);
        assert!(err.contains("`telescope`") && err.contains("missing"), "{err}");

        let bad_dec = [GOOD_METADATA[0], ("phase_centre_dec_deg", "95"), GOOD_METADATA[2]];
        write_custom(&path, basic_columns(), &bad_dec);
        let err = open_error(&path);
        assert!(err.contains("`phase_centre_dec_deg` = 95"), "{err}");

        let not_a_number = [("phase_centre_ra_deg", "ten"), GOOD_METADATA[1], GOOD_METADATA[2]];
        write_custom(&path, basic_columns(), &not_a_number);
        assert!(open_error(&path).contains("`phase_centre_ra_deg`"));
    }

    #[test]
    fn nulls_are_rejected_with_row() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("nulls.parquet");
        let mut columns = basic_columns();
        columns[2] = ("w", Arc::new(Float64Array::from(vec![Some(0.0), None])));
        write_custom(&path, columns, GOOD_METADATA);
        let err = read_parquet(&path).unwrap_err().to_string();
        assert!(err.contains("`w`") && err.contains("row 1"), "{err}");
    }

    #[test]
    fn batches_stream_with_bounded_size() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.parquet");
        let table = test_table(10_000);
        write_parquet(&path, &table, &test_meta()).unwrap();

        let mut reader = VisReader::open(&path, 1000).unwrap();
        assert_eq!(reader.total_rows(), 10_000);
        assert_eq!(reader.meta().telescope, "VLA");
        let mut batches = 0;
        let mut all = Visibilities::default();
        for batch in reader.by_ref() {
            let batch = batch.unwrap();
            assert!(batch.len() <= 1000);
            batches += 1;
            all.push_batch(batch);
        }
        assert!(batches >= 10, "{batches} batches");
        assert_eq!(reader.stats().rows, 10_000);
        assert_eq!(all.len(), 10_000);
        assert_eq!(all.vis[9_999], single(table.vis[9_999]));
        assert!(matches!(VisReader::open(&path, 0), Err(Error::Parameter { .. })));
    }

    #[test]
    fn corrupt_files_give_errors_not_panics() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("good.parquet");
        write_parquet(&path, &test_table(20_000), &test_meta()).unwrap();
        let bytes = std::fs::read(&path).unwrap();

        let truncated = dir.path().join("truncated.parquet");
        std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
        assert!(open_error(&truncated).contains("truncated.parquet"));

        // Garbage in the column data, footer intact: opening works, reading must fail.
        let corrupt = dir.path().join("corrupt.parquet");
        let mut damaged = bytes.clone();
        for (i, b) in damaged[bytes.len() / 8..bytes.len() / 3].iter_mut().enumerate() {
            *b = (i as u8).wrapping_mul(37) ^ 0x5a;
        }
        std::fs::write(&corrupt, &damaged).unwrap();
        let result = VisReader::open(&corrupt, 1000).and_then(|reader| reader.collect::<Result<Vec<_>>>());
        let err = result.expect_err("corrupt data read without error").to_string();
        assert!(err.contains("corrupt.parquet"), "{err}");

        // Damage at many places of a dictionary-encoded file (as most writers produce):
        // every outcome must be a value or an Err, never a panic. parquet 55 panics on
        // some of these (apache/arrow-rs#9434); VisReader must contain that.
        let n = 20_000;
        let ramp = |scale: f64| f64s(&(0..n).map(|i| scale * (i % 5000) as f64).collect::<Vec<_>>());
        let columns = vec![
            ("u", ramp(1.0)),
            ("v", ramp(-2.0)),
            ("w", ramp(0.1)),
            ("frequency", f64s(&vec![1.4e9; n])),
            ("vis_re", ramp(0.5)),
            ("vis_im", ramp(0.25)),
        ];
        let dictionary_encoded = dir.path().join("dictionary.parquet");
        write_custom(&dictionary_encoded, columns, GOOD_METADATA);
        let bytes = std::fs::read(&dictionary_encoded).unwrap();
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        for _ in 0..60 {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            let mut damaged = bytes.clone();
            let start = (seed % damaged.len() as u64) as usize;
            let end = (start + 1 + (seed >> 40) as usize % 48).min(damaged.len());
            damaged[start..end].fill((seed >> 32) as u8);
            std::fs::write(&corrupt, &damaged).unwrap();
            let outcome = std::panic::catch_unwind(|| {
                VisReader::open(&corrupt, 1000).and_then(|reader| reader.collect::<Result<Vec<_>>>()).err()
            });
            let err = outcome.unwrap_or_else(|_| panic!("panic escaped for damage at {start}..{end}"));
            if let Some(err) = err {
                assert!(err.to_string().contains("corrupt.parquet"), "{err}");
            }
        }

        let not_parquet = dir.path().join("text.parquet");
        std::fs::write(&not_parquet, "u,v,w\n1,2,3\n").unwrap();
        assert!(open_error(&not_parquet).contains("not a readable Parquet file"));
        assert!(open_error(&dir.path().join("absent.parquet")).contains("absent.parquet"));
    }

    #[test]
    fn decoder_panics_become_errors_naming_the_file() {
        let path = Path::new("some/file.parquet");
        let err = contain_panics(path, "reading", PARQUET, || -> std::result::Result<(), String> { panic!("boom") })
            .unwrap_err()
            .to_string();
        assert!(err.contains("some/file.parquet") && err.contains("boom"), "{err}");
        let err = contain_panics(path, "reading", PARQUET, || Err::<(), _>("bad page")).unwrap_err().to_string();
        assert_eq!(err, "some/file.parquet: reading: bad page");
    }

    #[test]
    fn writer_checks_lengths_and_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.parquet");
        let mut table = test_table(4);
        table.w_m.pop();
        let err = write_parquet(&path, &table, &test_meta()).unwrap_err().to_string();
        assert!(err.contains("table.w_m") && err.contains("3 entries"), "{err}");

        let mut meta = test_meta();
        meta.extra.insert("telescope".to_string(), "x".to_string());
        let err = write_parquet(&path, &test_table(4), &meta).unwrap_err().to_string();
        assert!(err.contains("telescope"), "{err}");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);

        // Optional columns may be left empty; the reader then uses the defaults.
        let table = VisTable {
            weight: vec![],
            flag: vec![],
            time: vec![],
            antenna1: vec![],
            antenna2: vec![],
            ..test_table(3)
        };
        write_parquet(&path, &table, &test_meta()).unwrap();
        let (vis, _, _) = read_parquet(&path).unwrap();
        assert_eq!(vis.weight, vec![1.0; 3]);
    }

    #[test]
    fn partition_keeps_order_within_groups() {
        let (vis, _) = test_table(5).to_visibilities("t").unwrap();
        let parts = vis.clone().partition(&[1, 0, 1, 2, 0], 4);
        assert_eq!(parts.iter().map(Visibilities::len).collect::<Vec<_>>(), [2, 2, 1, 0]);
        assert_eq!(parts[0].u, [vis.u[1], vis.u[4]]);
        assert_eq!(parts[1].vis, [vis.vis[0], vis.vis[2]]);
        assert_eq!(parts[2].frequency, [vis.frequency[3]]);
    }

    #[test]
    fn push_batch_appends_and_max_uv_of_empty_is_zero() {
        let mut a = Visibilities::default();
        assert_eq!(a.max_uv(), 0.0);
        assert!(a.is_empty());
        let mut b = Visibilities::with_capacity(1);
        b.push([3.0, -4.0], 1.0, Complex32::new(1.0, 2.0), 0.5, 1.4e9);
        a.push_batch(b.clone());
        a.push_batch(b);
        assert_eq!(a.len(), 2);
        assert_eq!(a.max_uv(), 5.0);
        assert_eq!(a.frequency, vec![1.4e9, 1.4e9]);
    }
}
