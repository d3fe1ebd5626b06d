//! The main table, read in row chunks into the Parquet format's record batches.

use super::{
    array_f64, invalid, MsError, as_f64, as_i64, column_index, combine_weights, describe, open_table, optional_column, read_cells, Layout,
    MsSelection, Origin, SampleColumns, StokesI, Window, ORIGIN_KEY,
};
use crate::vis::TableReader;
use crate::vis::{ObservationMeta, BAND_EDGES_KEY, CHANNEL_WIDTH_KEY, DATE_OBS_KEY, OBJECT_KEY};
use crate::{Error, Result};
use arrow::array::{ArrayRef, BooleanArray, Float64Array, Int32Array, RecordBatch};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};
use casacure::record::{ArrayData, RecordValue};
use casacure::Table;
use std::collections::BTreeSet;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Main-table rows that gave no samples, and why.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MsCounts {
    /// Main-table rows read.
    pub rows: u64,
    /// `ANTENNA1 == ANTENNA2`: never imaged.
    pub autocorrelations: u64,
    /// Rows of another field, or of a window not selected.
    pub unselected: u64,
}

impl fmt::Display for MsCounts {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} MS rows, {} autocorrelation rows and {} rows of other fields or windows skipped",
            self.rows, self.autocorrelations, self.unselected
        )
    }
}

/// Where the hands' weights come from.
#[derive(Clone, Copy, Debug)]
enum WeightSource {
    /// `WEIGHT_SPECTRUM` (per channel and correlation).
    Spectrum(usize),
    /// `WEIGHT` (per correlation).
    Row(usize),
    /// `1 / SIGMA^2` (per correlation).
    Sigma(usize),
    /// None of them: weight 1.
    Unit,
}

struct Columns {
    time: usize,
    /// `INTERVAL`, else `EXPOSURE`: the integration time a series' domain is checked against.
    interval: Option<usize>,
    antenna1: usize,
    antenna2: usize,
    field: usize,
    data_desc: usize,
    uvw: usize,
    flag_row: Option<usize>,
    flag: Option<usize>,
    data: usize,
    weight: WeightSource,
    /// `WEIGHT`, for rows whose `WEIGHT_SPECTRUM` cell is empty.
    weight_row: Option<usize>,
}

/// Streams an MS as Stokes I samples, `batch_rows` samples at most per batch (one main-table
/// chunk of rows), so memory is bounded by the chunk, not the MS.
pub struct MsReader {
    path: PathBuf,
    table: Table,
    pub(super) layout: Layout,
    columns: Columns,
    data_column: String,
    meta: ObservationMeta,
    schema: SchemaRef,
    next_row: u64,
    rows_per_chunk: u64,
    counts: MsCounts,
    finished: bool,
}

/// The batch schema: the Parquet format's columns, plus `field` and `spw` to split by.
pub fn batch_schema() -> Schema {
    let float64 = |name: &str| Field::new(name, DataType::Float64, false);
    let int32 = |name: &str| Field::new(name, DataType::Int32, false);
    let mut fields: Vec<Field> = ["u", "v", "w", "frequency", "vis_re", "vis_im", "weight"].map(float64).to_vec();
    fields.push(Field::new("flag", DataType::Boolean, false));
    fields.push(float64("time"));
    fields.push(float64(crate::vis::INTERVAL_COLUMN));
    fields.extend(["antenna1", "antenna2", "field", "spw"].map(int32));
    Schema::new(fields)
}

/// The fields that have rows in the main table: id and `FIELD.NAME`, in id order.
pub fn fields_with_rows(path: &Path) -> Result<Vec<(usize, String)>> {
    let table = open_table(path, "the MeasurementSet's main table")?;
    let field = column_index(&table, path, "FIELD_ID")?;
    let ids = scan_column(&table, path, field, "FIELD_ID")?;
    let names = super::field_names(path)?;
    Ok(ids.into_iter().map(|id| (id, names.get(id).cloned().unwrap_or_default())).collect())
}

/// Rows per integer-column scan at open: bounded memory for any MS.
const SCAN_ROWS: u64 = 1 << 16;

impl MsReader {
    /// Opens the MS at `path` and resolves `selection` against its subtables; samples come in
    /// batches of at most about `batch_rows` (a row's channels are never split).
    pub fn open(path: &Path, selection: &MsSelection, batch_rows: usize) -> Result<MsReader> {
        Self::open_part(path, selection, batch_rows, None)
    }

    /// As [`MsReader::open`], recording in the metadata that the jobs made from it are one
    /// part of a split (`split`: the column), which the writer's `model_column` refuses.
    pub fn open_part(path: &Path, selection: &MsSelection, batch_rows: usize, split: Option<&str>) -> Result<MsReader> {
        if batch_rows == 0 {
            return Err(Error::parameter("batch_rows", "must be at least 1"));
        }
        if !path.exists() {
            return Err(invalid(path, "no such MeasurementSet"));
        }
        let table = open_table(path, "the MeasurementSet's main table")?;
        let column = |name| column_index(&table, path, name);
        // The column as WSClean chooses it when none is named: the calibrated data if present.
        let mut selection = selection.clone();
        if selection.data_column.eq_ignore_ascii_case(super::AUTO_DATA_COLUMN) {
            let calibrated = optional_column(&table, "CORRECTED_DATA").is_some();
            selection.data_column = if calibrated { "CORRECTED_DATA" } else { "DATA" }.to_string();
            log::debug!("{}: imaging {} ({})", path.display(), selection.data_column, if calibrated { "the calibrated data" } else { "no CORRECTED_DATA column" });
        }
        let selection = &selection;
        let data = column(&selection.data_column)?;
        let weight = match (optional_column(&table, "WEIGHT_SPECTRUM"), optional_column(&table, "WEIGHT"), optional_column(&table, "SIGMA")) {
            (Some(c), _, _) => WeightSource::Spectrum(c),
            (None, Some(c), _) => WeightSource::Row(c),
            (None, None, Some(c)) => WeightSource::Sigma(c),
            (None, None, None) => {
                log::warn!("{}: no WEIGHT_SPECTRUM, WEIGHT or SIGMA column: every sample has weight 1", path.display());
                WeightSource::Unit
            }
        };
        let columns = Columns {
            time: column("TIME")?,
            interval: optional_column(&table, "INTERVAL").or_else(|| optional_column(&table, "EXPOSURE")),
            antenna1: column("ANTENNA1")?,
            antenna2: column("ANTENNA2")?,
            field: column("FIELD_ID")?,
            data_desc: column("DATA_DESC_ID")?,
            uvw: column("UVW")?,
            flag_row: optional_column(&table, "FLAG_ROW"),
            flag: optional_column(&table, "FLAG"),
            data,
            weight,
            weight_row: optional_column(&table, "WEIGHT"),
        };
        let (used_fields, used_dd) = scan_ids(&table, path, &columns)?;
        let layout = Layout::read(path, selection, &used_fields, &used_dd)?;
        let widest = layout.windows.iter().flatten().map(|w| w.channels.len()).max().unwrap_or(1).max(1);
        let rows_per_chunk = (batch_rows / widest).max(1) as u64;
        let origin = Origin {
            path: path.to_path_buf(),
            field_id: layout.field_id,
            selection: selection.clone(),
            split: split.map(str::to_string),
        };
        let mut extra = std::collections::BTreeMap::new();
        extra.insert("ms_field".to_string(), layout.field_name.clone());
        if !layout.field_name.trim().is_empty() {
            extra.insert(OBJECT_KEY.to_string(), layout.field_name.trim().to_string());
        }
        extra.insert("ms_data_column".to_string(), selection.data_column.clone());
        if let Some(width) = layout.windows.iter().flatten().filter_map(|w| w.width_hz).reduce(f64::max) {
            extra.insert(CHANNEL_WIDTH_KEY.to_string(), width.to_string());
        }
        let edges: Option<Vec<(f64, f64)>> = layout.windows.iter().flatten().map(|w| w.edges_hz).collect();
        if let Some((low, high)) = edges.and_then(|e| e.into_iter().reduce(|a, b| (a.0.min(b.0), a.1.max(b.1)))) {
            extra.insert(BAND_EDGES_KEY.to_string(), format!("{low} {high}"));
        }
        if let Some(date) = &layout.date_obs {
            extra.insert(DATE_OBS_KEY.to_string(), date.clone());
        }
        extra.insert(ORIGIN_KEY.to_string(), serde_json::to_string(&origin).expect("the origin serialises"));
        let meta = ObservationMeta {
            phase_centre_ra_deg: layout.ra_deg,
            phase_centre_dec_deg: layout.dec_deg,
            telescope: layout.telescope.clone(),
            noise_sigma: None,
            dynamic_range: None,
            extra,
        };
        let nrows = table.nrows();
        log::debug!("{}: {nrows} rows, field {} '{}', {rows_per_chunk} rows per chunk", path.display(), layout.field_id, layout.field_name);
        Ok(MsReader {
            path: path.to_path_buf(),
            table,
            layout,
            columns,
            data_column: selection.data_column.clone(),
            meta,
            schema: Arc::new(batch_schema()),
            next_row: 0,
            rows_per_chunk,
            counts: MsCounts::default(),
            finished: false,
        })
    }

    /// Rows skipped so far and why.
    pub fn counts(&self) -> MsCounts {
        self.counts
    }

    /// The field read: its id and name.
    pub fn field(&self) -> (usize, &str) {
        (self.layout.field_id, &self.layout.field_name)
    }

    fn read_chunk(&mut self, start: u64, n: u64) -> Result<RecordBatch> {
        let path = self.path.as_path();
        let table = &self.table;
        let cells = |column: usize, name: &str| read_cells(table, path, column, name, start, n);
        let c = &self.columns;
        let time = scalars(&cells(c.time, "TIME")?, "TIME", path, start, as_f64)?;
        // Not imaged: a missing or unreadable interval leaves the integration unknown (NaN).
        let interval: Vec<f64> = match c.interval.map(|col| cells(col, "INTERVAL")) {
            Some(Ok(values)) => values.iter().map(|v| as_f64(v).unwrap_or(f64::NAN)).collect(),
            _ => vec![f64::NAN; n as usize],
        };
        let antenna1 = scalars(&cells(c.antenna1, "ANTENNA1")?, "ANTENNA1", path, start, as_i64)?;
        let antenna2 = scalars(&cells(c.antenna2, "ANTENNA2")?, "ANTENNA2", path, start, as_i64)?;
        let field = scalars(&cells(c.field, "FIELD_ID")?, "FIELD_ID", path, start, as_i64)?;
        let data_desc = scalars(&cells(c.data_desc, "DATA_DESC_ID")?, "DATA_DESC_ID", path, start, as_i64)?;
        let flag_row = match c.flag_row {
            Some(col) => scalars(&cells(col, "FLAG_ROW")?, "FLAG_ROW", path, start, |v| match v {
                RecordValue::Bool(b) => Some(*b),
                _ => None,
            })?,
            None => vec![false; n as usize],
        };
        let uvw = cells(c.uvw, "UVW")?;
        let flag = c.flag.map(|col| cells(col, "FLAG")).transpose()?;
        let data = cells(c.data, &self.data_column)?;
        let weight = match c.weight {
            WeightSource::Spectrum(col) => Some(("WEIGHT_SPECTRUM", cells(col, "WEIGHT_SPECTRUM")?)),
            WeightSource::Row(col) => Some(("WEIGHT", cells(col, "WEIGHT")?)),
            WeightSource::Sigma(col) => Some(("SIGMA", cells(col, "SIGMA")?)),
            WeightSource::Unit => None,
        };
        // A declared but never written WEIGHT_SPECTRUM has empty cells: WEIGHT stands in for
        // them, as in casacore-based imagers.
        let spectrum_gaps = matches!(&weight, Some(("WEIGHT_SPECTRUM", cells)) if cells.iter().any(is_empty_array));
        let row_weights = match c.weight_row {
            Some(col) if spectrum_gaps => Some(cells(col, "WEIGHT")?),
            _ => None,
        };

        let mut out = SampleColumns::default();
        for r in 0..n as usize {
            let row = start + r as u64;
            if antenna1[r] == antenna2[r] {
                self.counts.autocorrelations += 1;
                continue;
            }
            let window = usize::try_from(data_desc[r]).ok().and_then(|dd| self.layout.windows.get(dd)).and_then(Option::as_ref);
            let Some(window) = window.filter(|_| field[r] == self.layout.field_id as i64) else {
                self.counts.unselected += 1;
                continue;
            };
            let cell_error = |name: &str, found: &str| {
                invalid(
                    path,
                    format!(
                        "column `{name}` at row {row}: expected {found} for spectral window {} ({} channels, {} correlations)",
                        window.spw,
                        window.frequencies.len(),
                        window.ncorr
                    ),
                )
            };
            let uvw_row = array_f64(&uvw[r])
                .and_then(|(_, values)| <[f64; 3]>::try_from(values).ok())
                .ok_or_else(|| cell_error("UVW", &format!("3 numbers, found {}", describe(&uvw[r]))))?;
            let shape = [window.frequencies.len() as u32, window.ncorr as u32];
            let vis = numbers_cell(&data[r], &shape, true).ok_or_else(|| {
                cell_error(&self.data_column, &format!("a complex array of shape {shape:?}, found {}", describe(&data[r])))
            })?;
            let flags = match &flag {
                Some(cells) => Some(bool_cell(&cells[r], &shape).ok_or_else(|| {
                    cell_error("FLAG", &format!("a Bool array of shape {shape:?}, found {}", describe(&cells[r])))
                })?),
                None => None,
            };
            let (name, cell, source) = match (&weight, &row_weights) {
                (Some((_, spectrum)), Some(row_cells)) if is_empty_array(&spectrum[r]) => ("WEIGHT", Some(&row_cells[r]), WeightSource::Row(0)),
                (Some((name, cells)), _) => (*name, Some(&cells[r]), c.weight),
                (None, _) => ("", None, c.weight),
            };
            let weights = match cell {
                Some(cell) => {
                    let expected: &[u32] = if matches!(source, WeightSource::Spectrum(_)) { &shape } else { &shape[1..] };
                    Some(numbers_cell(cell, expected, false).ok_or_else(|| {
                        cell_error(name, &format!("a float array of shape {expected:?}, found {}", describe(cell)))
                    })?)
                }
                None => None,
            };
            let row = Row { uvw: uvw_row, time: time[r], interval: interval[r], antenna1: antenna1[r], antenna2: antenna2[r], field: field[r] };
            out.push_row(window, &row, &RowCells { flag_row: flag_row[r], vis, flags, weights, weight: source });
        }
        self.counts.rows += n;
        out.into_batch(self.schema.clone(), path)
    }
}

/// Scalars of one column as `T`; an error names the column and row of a wrong cell.
fn scalars<T>(cells: &[RecordValue], name: &str, path: &Path, start: u64, get: impl Fn(&RecordValue) -> Option<T>) -> Result<Vec<T>> {
    cells
        .iter()
        .enumerate()
        .map(|(i, v)| {
            get(v).ok_or_else(|| invalid(path, format!("column `{name}` at row {}: unexpected {}", start + i as u64, describe(v))))
        })
        .collect()
}

/// The distinct `FIELD_ID` and `DATA_DESC_ID` values of the main table.
fn scan_ids(table: &Table, path: &Path, columns: &Columns) -> Result<(Vec<usize>, Vec<usize>)> {
    Ok((scan_column(table, path, columns.field, "FIELD_ID")?, scan_column(table, path, columns.data_desc, "DATA_DESC_ID")?))
}

/// The distinct values of an id column, read in chunks (bounded memory for any MS).
fn scan_column(table: &Table, path: &Path, column: usize, name: &str) -> Result<Vec<usize>> {
    let mut ids = BTreeSet::new();
    let nrows = table.nrows();
    for start in (0..nrows).step_by(SCAN_ROWS as usize) {
        let n = SCAN_ROWS.min(nrows - start);
        for (i, v) in read_cells(table, path, column, name, start, n)?.iter().enumerate() {
            let id = as_i64(v).and_then(|x| usize::try_from(x).ok()).ok_or_else(|| {
                invalid(path, format!("column `{name}` at row {}: expected a non-negative id, found {}", start + i as u64, describe(v)))
            })?;
            ids.insert(id);
        }
    }
    Ok(ids.into_iter().collect())
}

/// An array cell's numbers, borrowed from the decoded cell (no copy per row).
#[derive(Clone, Copy)]
enum Numbers<'a> {
    Complex(&'a [(f32, f32)]),
    DComplex(&'a [(f64, f64)]),
    Float(&'a [f32]),
    Double(&'a [f64]),
}

impl Numbers<'_> {
    fn complex(self, i: usize) -> (f64, f64) {
        match self {
            Numbers::Complex(v) => (f64::from(v[i].0), f64::from(v[i].1)),
            Numbers::DComplex(v) => v[i],
            Numbers::Float(v) => (f64::from(v[i]), 0.0),
            Numbers::Double(v) => (v[i], 0.0),
        }
    }

    fn real(self, i: usize) -> f64 {
        self.complex(i).0
    }
}

/// An array cell of exactly `shape`: complex numbers when `complex`, else real ones.
fn numbers_cell<'a>(value: &'a RecordValue, shape: &[u32], complex: bool) -> Option<Numbers<'a>> {
    let RecordValue::Array(array) = value else { return None };
    if array.shape != shape {
        return None;
    }
    match (&array.data, complex) {
        (ArrayData::Complex(v), true) => Some(Numbers::Complex(v)),
        (ArrayData::DComplex(v), true) => Some(Numbers::DComplex(v)),
        (ArrayData::Float(v), false) => Some(Numbers::Float(v)),
        (ArrayData::Double(v), false) => Some(Numbers::Double(v)),
        _ => None,
    }
}

/// An array cell without elements (an undefined cell of a variable-shape column).
fn is_empty_array(value: &RecordValue) -> bool {
    matches!(value, RecordValue::Array(a) if a.shape.is_empty() || a.shape.contains(&0))
}

fn bool_cell<'a>(value: &'a RecordValue, shape: &[u32]) -> Option<&'a [bool]> {
    match value {
        RecordValue::Array(array) if array.shape == shape => match &array.data {
            ArrayData::Bool(v) => Some(v),
            _ => None,
        },
        _ => None,
    }
}

/// The scalar columns of one main-table row.
struct Row {
    uvw: [f64; 3],
    time: f64,
    interval: f64,
    antenna1: i64,
    antenna2: i64,
    field: i64,
}

/// The array cells of one row, flattened channel-major (`[channel][correlation]`).
struct RowCells<'a> {
    flag_row: bool,
    vis: Numbers<'a>,
    flags: Option<&'a [bool]>,
    weights: Option<Numbers<'a>>,
    weight: WeightSource,
}

/// Columns of a batch being built.
impl SampleColumns {
    /// One Stokes I sample per selected channel of the row.
    fn push_row(&mut self, window: &Window, row: &Row, cells: &RowCells<'_>) {
        let ncorr = window.ncorr;
        let hand_weight = |channel: usize, k: usize| -> f64 {
            let Some(values) = cells.weights else { return 1.0 };
            match cells.weight {
                WeightSource::Spectrum(_) => values.real(channel * ncorr + k),
                WeightSource::Row(_) => values.real(k),
                WeightSource::Sigma(_) => {
                    let sigma = values.real(k);
                    if sigma > 0.0 {
                        1.0 / (sigma * sigma)
                    } else {
                        0.0
                    }
                }
                WeightSource::Unit => 1.0,
            }
        };
        let flagged = |channel: usize, k: usize| cells.flags.is_some_and(|f| f[channel * ncorr + k]);
        for channel in window.channels.clone() {
            let at = |k: usize| cells.vis.complex(channel * ncorr + k);
            let (vis, weight, flag) = match window.stokes {
                StokesI::Direct(i) => (at(i), hand_weight(channel, i), flagged(channel, i)),
                StokesI::Mean(a, b) => {
                    let (va, vb) = (at(a), at(b));
                    (
                        (0.5 * (va.0 + vb.0), 0.5 * (va.1 + vb.1)),
                        combine_weights(hand_weight(channel, a), hand_weight(channel, b)),
                        flagged(channel, a) || flagged(channel, b),
                    )
                }
            };
            self.u.push(row.uvw[0]);
            self.v.push(row.uvw[1]);
            self.w.push(row.uvw[2]);
            self.frequency.push(window.frequencies[channel]);
            self.re.push(vis.0);
            self.im.push(vis.1);
            self.weight.push(weight);
            self.flag.push(cells.flag_row || flag);
            self.time.push(row.time);
            self.interval.push(row.interval);
            // Ids beyond i32 cannot occur in a valid MS (casacore stores them as Int).
            self.antenna1.push(row.antenna1 as i32);
            self.antenna2.push(row.antenna2 as i32);
            self.field.push(row.field as i32);
            self.spw.push(window.spw as i32);
        }
    }

    fn into_batch(self, schema: SchemaRef, path: &Path) -> Result<RecordBatch> {
        let f64s = |v: Vec<f64>| Arc::new(Float64Array::from(v)) as ArrayRef;
        let i32s = |v: Vec<i32>| Arc::new(Int32Array::from(v)) as ArrayRef;
        let columns = vec![
            f64s(self.u),
            f64s(self.v),
            f64s(self.w),
            f64s(self.frequency),
            f64s(self.re),
            f64s(self.im),
            f64s(self.weight),
            Arc::new(BooleanArray::from(self.flag)) as ArrayRef,
            f64s(self.time),
            f64s(self.interval),
            i32s(self.antenna1),
            i32s(self.antenna2),
            i32s(self.field),
            i32s(self.spw),
        ];
        RecordBatch::try_new(schema, columns).map_err(|e| MsError::Arrow { path: path.to_path_buf(), what: "building a record batch".into(), source: e }.into())
    }
}

impl TableReader for MsReader {
    fn source(&self) -> &Path {
        &self.path
    }

    fn summary(&self) -> Option<String> {
        Some(self.counts.to_string())
    }

    fn meta(&self) -> &ObservationMeta {
        &self.meta
    }

    fn schema(&self) -> SchemaRef {
        self.schema.clone()
    }

    fn next_batch(&mut self) -> Option<Result<RecordBatch>> {
        let nrows = self.table.nrows();
        if self.finished || self.next_row >= nrows {
            return None;
        }
        let start = self.next_row;
        let n = self.rows_per_chunk.min(nrows - start);
        self.next_row += n;
        let batch = self.read_chunk(start, n);
        self.finished = batch.is_err();
        // The chunk's pages are copied out: let the kernel drop them (casacore's bounded cache).
        self.table.drop_data_file_pages();
        Some(batch)
    }
}
