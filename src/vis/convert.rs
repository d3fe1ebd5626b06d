//! Arrow record batches in the visibility format to imaging input: the columns checked once,
//! baselines to wavelengths, excluded rows dropped and counted ([`IngestStats`]).

use super::data::{Visibilities, FREQUENCY_RANGE_HZ, MAX_BASELINE_M, SPEED_OF_LIGHT};
use super::error::TableError;
use std::borrow::Cow;
use std::fmt;
use std::path::Path;

use arrow::array::{Array, BooleanArray, Float32Array, Float64Array, RecordBatch};
use arrow::datatypes::{DataType, Schema};
use num_complex::Complex32;

use crate::Result;

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
    /// instrument measures (not finite, or impossible): the file is damaged or was written
    /// wrongly.
    pub fn log(&self, source: &Path) {
        log::info!("{}: {self}", source.display());
        if self.non_finite > 0 {
            log::warn!(
                "{}: {} of {} samples excluded: a value not finite (NaN or infinite: a visibility, baseline coordinate, frequency or weight), where every value of an unflagged sample must be: is the file damaged?",
                source.display(),
                self.non_finite,
                self.rows
            );
        }
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
pub(super) enum ColumnType {
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
pub(super) const READ_COLUMNS: [(&str, ColumnType, bool); 9] = [
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

/// The optional column of each sample's time (its integration's centre), seconds.
pub const TIME_COLUMN: &str = "time";

/// The optional column of each sample's integration time, seconds (a MeasurementSet's
/// `INTERVAL`).
pub const INTERVAL_COLUMN: &str = "interval";

/// A time column where the batch has one of float64 type; `None` otherwise. Times are not
/// imaged: a table whose times are of another type (or absent) is read as before, its track
/// unknown, rather than refused.
fn time_column<'a>(batch: &'a RecordBatch, name: &str) -> Option<&'a Float64Array> {
    batch.column_by_name(name).and_then(|a| a.as_any().downcast_ref::<Float64Array>())
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

    let (time, interval) = (time_column(batch, TIME_COLUMN), time_column(batch, INTERVAL_COLUMN));

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
        if let Some(time) = time.and_then(|t| t.is_valid(i).then(|| t.value(i))) {
            out.times.add_time(time);
        }
        if let Some(interval) = interval.and_then(|t| t.is_valid(i).then(|| t.value(i))) {
            out.times.add_integration(interval);
        }
    }
    stats.add(&counts);
    Ok(out)
}
