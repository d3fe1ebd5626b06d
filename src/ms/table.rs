//! casacore table access shared by the MeasurementSet reader and writers: opening tables and
//! columns, the selection (field, windows, channels, data column), the layout of windows and
//! correlations, Stokes I from the hands present, and the provenance of converted tables.

use super::error::MsError;
use crate::{Error, Result};
use casacure::record::{ArrayData, RecordValue};
use casacure::Table;
use crate::vis::ChannelGroup;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};

/// An MS content error as the crate's error.
pub(crate) fn invalid(path: impl AsRef<Path>, message: impl Into<String>) -> Error {
    MsError::Invalid { path: path.as_ref().to_path_buf(), message: message.into() }.into()
}

/// Runs a casacore table operation on `path`; its error (kept as the source) and a panic of the
/// decoder become errors naming the table and `what` was being done.
pub(crate) fn casacore<T, E: std::error::Error + Send + Sync + 'static>(path: &Path, what: &str, operation: impl FnOnce() -> std::result::Result<T, E>) -> Result<T> {
    match crate::error::catch_quietly(operation) {
        Ok(Ok(value)) => Ok(value),
        Ok(Err(e)) => Err(MsError::Table { path: path.to_path_buf(), what: what.to_string(), source: Box::new(e) }.into()),
        Err(message) => Err(MsError::DecoderPanic { path: path.to_path_buf(), what: what.to_string(), message }.into()),
    }
}

/// Whether `path` looks like a casacore table (an MS): a directory holding `table.dat`.
pub fn is_measurement_set(path: &Path) -> bool {
    path.is_dir() && path.join("table.dat").is_file()
}

/// A field chosen by its `FIELD` row number or by its `NAME`.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(untagged)]
pub enum FieldSelector {
    Id(usize),
    Name(String),
}

impl fmt::Display for FieldSelector {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FieldSelector::Id(id) => write!(f, "{id}"),
            FieldSelector::Name(name) => write!(f, "'{name}'"),
        }
    }
}

impl std::str::FromStr for FieldSelector {
    type Err = std::convert::Infallible;

    /// A number is a field id, anything else a name.
    fn from_str(s: &str) -> std::result::Result<Self, Self::Err> {
        Ok(match s.parse::<usize>() {
            Ok(id) => FieldSelector::Id(id),
            Err(_) => FieldSelector::Name(s.to_string()),
        })
    }
}

/// What of an MS to read (the `ms` source's keys, and `r2d2 image/dirty/convert` options).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct MsSelection {
    /// The complex column holding the visibilities (WSClean's `-data-column`); `auto` (the
    /// default) takes `CORRECTED_DATA` when the MS has it, else `DATA`, as WSClean does.
    #[serde(default = "default_data_column")]
    pub data_column: String,
    /// The field to image; required when the MS has rows of several fields.
    #[serde(default)]
    pub field: Option<FieldSelector>,
    /// Spectral windows (`SPECTRAL_WINDOW` row numbers); default: all.
    #[serde(default)]
    pub spw: Option<Vec<usize>>,
    /// Channels `[start, end)` of every selected window (WSClean's `-channel-range`).
    #[serde(default)]
    pub channels: Option<[usize; 2]>,
    /// One of `count` groups of the selected channels, as WSClean's `-channels-out` makes
    /// them: every selected channel of every window, in order of frequency, cut into `count`
    /// runs of (nearly) equal numbers of channels; `index` counts from the lowest frequency.
    #[serde(default)]
    pub channel_group: Option<ChannelGroup>,
}


/// The data column chosen as WSClean chooses it ([`MsSelection::data_column`]).
pub const AUTO_DATA_COLUMN: &str = "auto";

pub fn default_data_column() -> String {
    AUTO_DATA_COLUMN.into()
}

impl Default for MsSelection {
    fn default() -> Self {
        MsSelection { data_column: default_data_column(), field: None, spw: None, channels: None, channel_group: None }
    }
}

/// Opens a table read-only; errors (and panics of the decoder) name the table and `what` it is.
pub(crate) fn open_table(path: &Path, what: &str) -> Result<Table> {
    if !path.join("table.dat").is_file() {
        return Err(invalid(path, format!("{what} is missing: no casacore table here (no table.dat)")));
    }
    casacore(path, &format!("cannot open {what}"), || Table::open(path, true))
}

/// A subtable of `ms`, e.g. `SPECTRAL_WINDOW`.
pub(crate) fn open_subtable(ms: &Path, name: &str) -> Result<Table> {
    let path = ms.join(name);
    if !path.join("table.dat").is_file() {
        return Err(invalid(ms, format!("the {name} subtable is missing (expected {})", path.display())));
    }
    open_table(&path, &format!("the {name} subtable"))
}

/// A column's index, or an error naming the table and the column.
pub(crate) fn column_index(table: &Table, table_path: &Path, name: &str) -> Result<usize> {
    optional_column(table, name).ok_or_else(|| {
        invalid(table_path, format!("column `{name}` is missing (columns: {})", table.colnames().join(", ")))
    })
}

pub(crate) fn optional_column(table: &Table, name: &str) -> Option<usize> {
    table.colnames().iter().position(|c| c == name)
}

/// Cells `start..start + n` of a column, decoder failures and panics as errors naming the
/// table, column and rows.
pub(crate) fn read_cells(table: &Table, path: &Path, column: usize, name: &str, start: u64, n: u64) -> Result<Vec<RecordValue>> {
    let what = format!("column `{name}`, rows {start}..{}", start + n);
    casacore(path, &what, || table.getcol(column, start, n))
}

/// A whole column of a subtable.
pub(crate) fn read_column(table: &Table, path: &Path, name: &str) -> Result<Vec<RecordValue>> {
    let column = column_index(table, path, name)?;
    read_cells(table, path, column, name, 0, table.nrows())
}

/// A scalar cell as f64 (any numeric type).
pub(crate) fn as_f64(value: &RecordValue) -> Option<f64> {
    Some(match *value {
        RecordValue::Double(x) => x,
        RecordValue::Float(x) => f64::from(x),
        RecordValue::Int(x) => f64::from(x),
        RecordValue::UInt(x) => f64::from(x),
        RecordValue::Short(x) => f64::from(x),
        RecordValue::UShort(x) => f64::from(x),
        RecordValue::UChar(x) => f64::from(x),
        RecordValue::Int64(x) => x as f64,
        _ => return None,
    })
}

/// A scalar cell as an integer id (any integer type).
pub(crate) fn as_i64(value: &RecordValue) -> Option<i64> {
    Some(match *value {
        RecordValue::Int(x) => i64::from(x),
        RecordValue::UInt(x) => i64::from(x),
        RecordValue::Short(x) => i64::from(x),
        RecordValue::UShort(x) => i64::from(x),
        RecordValue::UChar(x) => i64::from(x),
        RecordValue::Int64(x) => x,
        _ => return None,
    })
}

/// An array cell's elements as f64, with its shape (casacure's logical order: the last axis
/// varies fastest, as numpy shows an MS cell).
pub(crate) fn array_f64(value: &RecordValue) -> Option<(Vec<u32>, Vec<f64>)> {
    let RecordValue::Array(array) = value else { return None };
    let data = match &array.data {
        ArrayData::Double(v) => v.clone(),
        ArrayData::Float(v) => v.iter().map(|&x| f64::from(x)).collect(),
        ArrayData::Int(v) => v.iter().map(|&x| f64::from(x)).collect(),
        ArrayData::Short(v) => v.iter().map(|&x| f64::from(x)).collect(),
        ArrayData::UInt(v) => v.iter().map(|&x| f64::from(x)).collect(),
        ArrayData::Int64(v) => v.iter().map(|&x| x as f64).collect(),
        _ => return None,
    };
    Some((array.shape.clone(), data))
}

/// Describes a cell's type for messages.
pub(crate) fn describe(value: &RecordValue) -> String {
    match value {
        RecordValue::Array(a) => {
            let kind = match &a.data {
                ArrayData::Bool(_) => "Bool",
                ArrayData::UChar(_) => "UChar",
                ArrayData::Short(_) => "Short",
                ArrayData::UShort(_) => "UShort",
                ArrayData::Int(_) => "Int",
                ArrayData::UInt(_) => "UInt",
                ArrayData::Int64(_) => "Int64",
                ArrayData::Float(_) => "Float",
                ArrayData::Double(_) => "Double",
                ArrayData::Complex(_) => "Complex",
                ArrayData::DComplex(_) => "DComplex",
                ArrayData::String(_) => "String",
            };
            format!("an array of {kind} with shape {:?}", a.shape)
        }
        // The variant's name: `Float(1.0)` -> `Float`.
        other => format!("a scalar {}", format!("{other:?}").split('(').next().unwrap_or("value")),
    }
}

/// Stokes and correlation codes of `POLARIZATION.CORR_TYPE` (casacore `Stokes::StokesTypes`).
pub(crate) fn correlation_name(code: i64) -> String {
    const NAMES: [&str; 13] = ["?", "I", "Q", "U", "V", "RR", "RL", "LR", "LL", "XX", "XY", "YX", "YY"];
    usize::try_from(code).ok().and_then(|c| NAMES.get(c)).map_or_else(|| format!("code {code}"), |s| s.to_string())
}

/// How Stokes I is made from a row's correlations: one correlation that is I, or the mean of
/// two hands (indices into the correlation axis).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum StokesI {
    Direct(usize),
    Mean(usize, usize),
}

impl StokesI {
    /// From `CORR_TYPE` codes: I (1), else XX (9) and YY (12), else RR (5) and LL (8).
    pub(crate) fn from_codes(codes: &[i64]) -> Option<StokesI> {
        let at = |code: i64| codes.iter().position(|&c| c == code);
        if let Some(i) = at(1) {
            return Some(StokesI::Direct(i));
        }
        for (a, b) in [(9, 12), (5, 8)] {
            if let (Some(i), Some(j)) = (at(a), at(b)) {
                return Some(StokesI::Mean(i, j));
            }
        }
        None
    }

    /// Whether correlation `k` takes a model's Stokes I (the hands, or I itself; an
    /// unpolarised source has XX = YY = I and no cross-hand signal).
    pub(crate) fn carries_i(self, k: usize) -> bool {
        match self {
            StokesI::Direct(i) => k == i,
            StokesI::Mean(i, j) => k == i || k == j,
        }
    }
}

/// Stokes I weight from the hands' weights: the inverse variance of `(A + B) / 2`. A
/// non-positive hand weight makes the sample's weight 0 (so it is counted as such), a NaN
/// keeps it NaN (counted as non-finite).
pub(crate) fn combine_weights(wa: f64, wb: f64) -> f64 {
    if wa.is_nan() || wb.is_nan() {
        f64::NAN
    } else if wa <= 0.0 || wb <= 0.0 {
        0.0
    } else {
        4.0 / (1.0 / wa + 1.0 / wb)
    }
}

/// One row of `DATA_DESCRIPTION` as the reader uses it: its window's (selected) channels and
/// how to make I.
#[derive(Clone, Debug)]
pub(crate) struct Window {
    pub spw: usize,
    /// Channel indices in the window kept by the channel selection.
    pub channels: std::ops::Range<usize>,
    /// Every channel's frequency, Hz.
    pub frequencies: Vec<f64>,
    /// The widest |CHAN_WIDTH| (Hz) of the channels kept; `None` where the MS has no
    /// usable widths.
    pub width_hz: Option<f64>,
    /// The lowest and highest edge (Hz) of the channels kept (`CHAN_FREQ` -+ half of
    /// |`CHAN_WIDTH`|), where the widths are usable.
    pub edges_hz: Option<(f64, f64)>,
    pub ncorr: usize,
    pub stokes: StokesI,
}

/// The subtables' facts for a selection: fields, windows, phase centre, telescope, start.
#[derive(Clone, Debug)]
pub(crate) struct Layout {
    /// Per DATA_DESC_ID: the window, or None when not selected.
    pub windows: Vec<Option<Window>>,
    pub field_id: usize,
    pub field_name: String,
    pub ra_deg: f64,
    pub dec_deg: f64,
    pub telescope: String,
    /// When the observation began (FITS `DATE-OBS` text), where the MS says.
    pub date_obs: Option<String>,
}

/// Field names of the `FIELD` subtable, in row order.
pub(crate) fn field_names(ms: &Path) -> Result<Vec<String>> {
    let table = open_subtable(ms, "FIELD")?;
    let path = ms.join("FIELD");
    read_column(&table, &path, "NAME")?
        .into_iter()
        .map(|v| match v {
            RecordValue::String(s) => Ok(s),
            other => Err(invalid(&path, format!("column `NAME`: expected strings, found {}", describe(&other)))),
        })
        .collect()
}

/// "0 'TARGET', 1 'OTHER'".
pub(crate) fn list_fields(ids: impl IntoIterator<Item = usize>, names: &[String]) -> String {
    // An error stays readable for an MS of a thousand fields: the first few, then a count.
    const SHOWN: usize = 12;
    let ids: Vec<usize> = ids.into_iter().collect();
    let mut text = ids.iter().take(SHOWN).map(|&id| format!("{id} '{}'", names.get(id).map_or("?", String::as_str))).collect::<Vec<_>>().join(", ");
    if ids.len() > SHOWN {
        text.push_str(&format!(", ... and {} more", ids.len() - SHOWN));
    }
    text
}

impl Layout {
    /// Reads the subtables and resolves `selection`; `used_fields` and `used_dd` are the
    /// `FIELD_ID` and `DATA_DESC_ID` values present in the main table.
    pub(crate) fn read(ms: &Path, selection: &MsSelection, used_fields: &[usize], used_dd: &[usize]) -> Result<Layout> {
        if used_fields.is_empty() {
            return Err(invalid(ms, "the MS holds no rows (its main table is empty): nothing to read"));
        }
        let names = field_names(ms)?;
        let field_id = match &selection.field {
            None => match used_fields {
                [] => 0,
                [only] => *only,
                several => {
                    return Err(invalid(
                        ms,
                        format!(
                            "the MS has rows of {} fields ({}): choose one (the option `field`: an ID or NAME)",
                            several.len(),
                            list_fields(several.iter().copied(), &names)
                        ),
                    ))
                }
            },
            Some(sel) => {
                let found = match sel {
                    FieldSelector::Id(id) => (*id < names.len()).then_some(*id),
                    FieldSelector::Name(name) => {
                        let ids: Vec<usize> = names.iter().enumerate().filter(|(_, n)| *n == name).map(|(i, _)| i).collect();
                        if ids.len() > 1 {
                            return Err(invalid(
                                ms.join("FIELD"),
                                format!("field {sel} names {} rows of column `NAME` ({}): choose one by its id", ids.len(), list_fields(ids.iter().copied(), &names)),
                            ));
                        }
                        ids.first().copied()
                    }
                };
                let id = found.ok_or_else(|| {
                    invalid(
                        ms.join("FIELD"),
                        format!("field {sel} matches no row of column `NAME` (fields: {})", list_fields(0..names.len(), &names)),
                    )
                })?;
                if !used_fields.contains(&id) {
                    return Err(invalid(
                        ms,
                        format!(
                            "field {sel} (id {id}) has no rows in column `FIELD_ID` (fields with rows: {})",
                            list_fields(used_fields.iter().copied(), &names)
                        ),
                    ));
                }
                id
            }
        };
        let field_name = names.get(field_id).cloned().unwrap_or_default();
        let (ra_deg, dec_deg) = phase_centre(ms, field_id)?;
        let (telescope, date_obs) = observation(ms)?;
        let windows = read_windows(ms, selection, used_dd)?;
        if windows.iter().all(Option::is_none) {
            // Only a window selection can leave none: every window in use is otherwise kept.
            let wanted = selection.spw.as_ref().map(|s| s.iter().map(usize::to_string).collect::<Vec<_>>().join(", ")).unwrap_or_default();
            let dd_path = ms.join("DATA_DESCRIPTION");
            let spw_of = id_column(&open_subtable(ms, "DATA_DESCRIPTION")?, &dd_path, "SPECTRAL_WINDOW_ID")?;
            let used: std::collections::BTreeSet<i64> = used_dd.iter().filter_map(|&dd| spw_of.get(dd).copied()).collect();
            let used = used.iter().map(i64::to_string).collect::<Vec<_>>().join(", ");
            return Err(invalid(
                ms,
                format!("the MS holds no rows in spectral window {wanted} (the option `spw`): its rows are in window {used}"),
            ));
        }
        Ok(Layout { windows, field_id, field_name, ra_deg, dec_deg, telescope, date_obs })
    }
}

/// RA and Dec (degrees, RA in [0, 360)) of `FIELD.PHASE_DIR` at row `field` (its first
/// polynomial term).
pub(crate) fn phase_centre(ms: &Path, field: usize) -> Result<(f64, f64)> {
    let table = open_subtable(ms, "FIELD")?;
    let path = ms.join("FIELD");
    let column = column_index(&table, &path, "PHASE_DIR")?;
    let cell = read_cells(&table, &path, column, "PHASE_DIR", field as u64, 1)?;
    let (_, values) = cell.first().and_then(array_f64).ok_or_else(|| {
        invalid(&path, format!("column `PHASE_DIR` at row {field}: expected an array of directions in radians"))
    })?;
    match values[..] {
        [ra, dec, ..] if ra.is_finite() && dec.is_finite() && dec.abs() <= std::f64::consts::FRAC_PI_2 + 1e-12 => {
            Ok((ra.to_degrees().rem_euclid(360.0), dec.to_degrees().clamp(-90.0, 90.0)))
        }
        _ => Err(invalid(
            &path,
            format!("column `PHASE_DIR` at row {field} is {values:?}; expected [RA, Dec] in radians with |Dec| <= pi/2"),
        )),
    }
}

/// From the first row of `OBSERVATION`: `TELESCOPE_NAME` (`unknown` when empty), and when the
/// observation began as FITS `DATE-OBS` text (UTC, ISO 8601: the start of `TIME_RANGE`;
/// `None` where it is missing, zero or unreadable: a date is a courtesy to the products, never
/// a reason to refuse the data).
pub(crate) fn observation(ms: &Path) -> Result<(String, Option<String>)> {
    let table = open_subtable(ms, "OBSERVATION")?;
    let path = ms.join("OBSERVATION");
    let names = read_column(&table, &path, "TELESCOPE_NAME")?;
    let telescope = match names.first() {
        Some(RecordValue::String(s)) if !s.trim().is_empty() => s.trim().to_string(),
        _ => crate::vis::UNKNOWN_TELESCOPE.to_string(),
    };
    let start = read_column(&table, &path, "TIME_RANGE").ok().and_then(|cells| {
        let (_, range) = array_f64(cells.first()?)?;
        mjd_seconds_to_iso(*range.first()?)
    });
    Ok((telescope, start))
}

/// The MS's `OBSERVATION::TELESCOPE_NAME` (`unknown` when empty), read from that subtable
/// alone: no field or window selection, no pass over the rows.
pub fn telescope_name(ms: &Path) -> Result<String> {
    observation(ms).map(|(telescope, _)| telescope)
}

/// Modified Julian Date in seconds (casacore's epoch) as `YYYY-MM-DDThh:mm:ss.s`; `None`
/// outside years 1900..2200 (no real observation; zero is the common "unset").
pub(crate) fn mjd_seconds_to_iso(mjd_s: f64) -> Option<String> {
    // MJD 15020 is 1900-01-01, MJD 124593 is 2200-01-01.
    if !(mjd_s.is_finite() && (15020.0 * 86400.0..124593.0 * 86400.0).contains(&mjd_s)) {
        return None;
    }
    let days = (mjd_s / 86400.0).floor();
    let seconds = mjd_s - days * 86400.0;
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm); MJD 40587 is that day.
    let z = days as i64 - 40587 + 719468;
    let era = z.div_euclid(146097);
    let doe = z - era * 146097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    let tenths = (seconds * 10.0).round() as i64;
    let (h, m, s10) = (tenths / 36000, tenths / 600 % 60, tenths % 600);
    Some(format!("{year:04}-{month:02}-{day:02}T{h:02}:{m:02}:{:02}.{}", s10 / 10, s10 % 10))
}

/// Integer ids of a subtable column (`DATA_DESCRIPTION.SPECTRAL_WINDOW_ID`, ...).
pub(crate) fn id_column(table: &Table, path: &Path, name: &str) -> Result<Vec<i64>> {
    read_column(table, path, name)?
        .iter()
        .enumerate()
        .map(|(row, v)| {
            as_i64(v).ok_or_else(|| invalid(path, format!("column `{name}` at row {row}: expected an integer, found {}", describe(v))))
        })
        .collect()
}

/// The windows of the data description rows in use, resolved against the selection.
pub(crate) fn read_windows(ms: &Path, selection: &MsSelection, used_dd: &[usize]) -> Result<Vec<Option<Window>>> {
    let dd_table = open_subtable(ms, "DATA_DESCRIPTION")?;
    let dd_path = ms.join("DATA_DESCRIPTION");
    let spw_of = id_column(&dd_table, &dd_path, "SPECTRAL_WINDOW_ID")?;
    let pol_of = id_column(&dd_table, &dd_path, "POLARIZATION_ID")?;
    let spw_table = open_subtable(ms, "SPECTRAL_WINDOW")?;
    let spw_path = ms.join("SPECTRAL_WINDOW");
    let freq_column = column_index(&spw_table, &spw_path, "CHAN_FREQ")?;
    let width_column = optional_column(&spw_table, "CHAN_WIDTH");
    let pol_table = open_subtable(ms, "POLARIZATION")?;
    let pol_path = ms.join("POLARIZATION");
    let corr_column = column_index(&pol_table, &pol_path, "CORR_TYPE")?;
    let nspw = spw_table.nrows() as usize;
    if let Some(wanted) = &selection.spw {
        if let Some(bad) = wanted.iter().find(|&&s| s >= nspw) {
            return Err(invalid(&spw_path, format!("spectral window {bad} does not exist (the MS has {nspw}: 0..{nspw})")));
        }
    }
    let mut windows = vec![None; spw_of.len()];
    for &dd in used_dd {
        let (Some(&spw), Some(&pol)) = (spw_of.get(dd), pol_of.get(dd)) else {
            return Err(invalid(
                ms,
                format!("column `DATA_DESC_ID` refers to row {dd}, but DATA_DESCRIPTION has {} rows", spw_of.len()),
            ));
        };
        let (Ok(spw), Ok(pol)) = (usize::try_from(spw), usize::try_from(pol)) else {
            return Err(invalid(&dd_path, format!("row {dd}: negative SPECTRAL_WINDOW_ID or POLARIZATION_ID")));
        };
        if selection.spw.as_ref().is_some_and(|s| !s.contains(&spw)) {
            continue;
        }
        if spw >= nspw {
            return Err(invalid(&dd_path, format!("row {dd} refers to spectral window {spw}; SPECTRAL_WINDOW has {nspw} rows")));
        }
        let cell = read_cells(&spw_table, &spw_path, freq_column, "CHAN_FREQ", spw as u64, 1)?;
        let (_, frequencies) = cell
            .first()
            .and_then(array_f64)
            .ok_or_else(|| invalid(&spw_path, format!("column `CHAN_FREQ` at row {spw}: expected an array of frequencies in Hz")))?;
        let nchan = frequencies.len();
        let channels = match selection.channels {
            None => 0..nchan,
            Some([start, end]) if start < end && end <= nchan => start..end,
            Some([start, end]) => {
                return Err(Error::parameter(
                    "channels",
                    format!("[{start}, {end}) is not a channel range of spectral window {spw}, which has {nchan} channels (0..{nchan})"),
                ))
            }
        };
        // Widths only describe the band (the bandwidth written as CDELT3): a missing or
        // unreadable column leaves it unknown rather than failing the read.
        let widths: Option<Vec<f64>> = width_column
            .and_then(|column| read_cells(&spw_table, &spw_path, column, "CHAN_WIDTH", spw as u64, 1).ok())
            .and_then(|cell| cell.first().and_then(array_f64).map(|(_, widths)| widths))
            .filter(|widths| widths.len() == nchan && widths[channels.clone()].iter().all(|w| w.is_finite() && *w != 0.0));
        let width_hz = widths.as_ref().and_then(|w| w[channels.clone()].iter().map(|w| w.abs()).reduce(f64::max));
        let edges_hz = widths.as_ref().and_then(|w| {
            channels.clone().map(|c| (frequencies[c] - 0.5 * w[c].abs(), frequencies[c] + 0.5 * w[c].abs())).reduce(|a, b| (a.0.min(b.0), a.1.max(b.1)))
        });
        if pol as u64 >= pol_table.nrows() {
            return Err(invalid(&dd_path, format!("row {dd} refers to polarization {pol}; POLARIZATION has {} rows", pol_table.nrows())));
        }
        let cell = read_cells(&pol_table, &pol_path, corr_column, "CORR_TYPE", pol as u64, 1)?;
        let codes: Vec<i64> = cell
            .first()
            .and_then(array_f64)
            .map(|(_, v)| v.iter().map(|&c| c as i64).collect())
            .ok_or_else(|| invalid(&pol_path, format!("column `CORR_TYPE` at row {pol}: expected an array of correlation codes")))?;
        let stokes = StokesI::from_codes(&codes).ok_or_else(|| {
            let names: Vec<String> = codes.iter().map(|&c| correlation_name(c)).collect();
            invalid(
                &pol_path,
                format!(
                    "column `CORR_TYPE` at row {pol} has correlations [{}]: no Stokes I can be formed (it needs I, XX and YY, or RR and LL)",
                    names.join(", ")
                ),
            )
        })?;
        windows[dd] = Some(Window { spw, channels, frequencies, width_hz, edges_hz, ncorr: codes.len(), stokes });
    }
    if let Some(group) = selection.channel_group {
        keep_channel_group(&mut windows, group, &spw_path)?;
    }
    Ok(windows)
}

/// Narrows `windows` to the channels of `group`: every window's selected channels (a window
/// that two data descriptions share counted once), in order of frequency, cut into
/// `group.count` runs as WSClean's `-channels-out` cuts them (run `k` holds channels
/// `k n / count .. (k + 1) n / count` of `n`). A window left with none is not read.
fn keep_channel_group(windows: &mut [Option<Window>], group: ChannelGroup, spw_path: &Path) -> Result<()> {
    let ChannelGroup { index, count } = group;
    let mut all: Vec<(f64, usize, usize)> = Vec::new();
    let mut seen = std::collections::BTreeSet::new();
    for window in windows.iter().flatten() {
        if seen.insert(window.spw) {
            all.extend(window.channels.clone().map(|c| (window.frequencies[c], window.spw, c)));
        }
    }
    let n = all.len();
    if count == 0 || index >= count {
        return Err(Error::parameter("channel_group", format!("expected group index < count (count >= 1), got {index} of {count}")));
    }
    if count > n {
        return Err(Error::parameter("channels_out", format!("{count} channel groups asked for, but the selection has {n} channels")));
    }
    all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let kept = &all[index * n / count..(index + 1) * n / count];
    for slot in windows.iter_mut() {
        let Some(window) = slot else { continue };
        let mine: Vec<usize> = kept.iter().filter(|k| k.1 == window.spw).map(|k| k.2).collect();
        match (mine.iter().min(), mine.iter().max()) {
            (Some(&lo), Some(&hi)) if hi - lo + 1 == mine.len() => {
                // The group's edges: its first and last channels' (the widths were read for
                // the whole selection).
                if let (Some(width), Some(_)) = (window.width_hz, window.edges_hz) {
                    let (f0, f1) = (window.frequencies[lo], window.frequencies[hi]);
                    window.edges_hz = Some((f0.min(f1) - 0.5 * width, f0.max(f1) + 0.5 * width));
                }
                window.channels = lo..hi + 1
            }
            (Some(_), Some(_)) => {
                return Err(invalid(
                    spw_path,
                    format!("spectral window {}: the channels of group {index} of {count} are not contiguous (CHAN_FREQ out of order?)", window.spw),
                ))
            }
            _ => *slot = None,
        }
    }
    Ok(())
}

/// Stokes I samples column by column, as the Parquet format has them (baselines in metres),
/// plus the MS ids `field` and `spw` (left empty by the Parquet-to-MS conversion).
#[derive(Default)]
pub(crate) struct SampleColumns {
    pub u: Vec<f64>,
    pub v: Vec<f64>,
    pub w: Vec<f64>,
    pub frequency: Vec<f64>,
    pub re: Vec<f64>,
    pub im: Vec<f64>,
    pub weight: Vec<f64>,
    pub flag: Vec<bool>,
    pub time: Vec<f64>,
    /// Integration time of each sample, seconds (NaN where unknown).
    pub interval: Vec<f64>,
    pub antenna1: Vec<i32>,
    pub antenna2: Vec<i32>,
    pub field: Vec<i32>,
    pub spw: Vec<i32>,
}

/// A directory being built beside its final place, removed when dropped (by then it is either
/// moved into place, or holds what it replaced, or a failed attempt).
pub(crate) struct TempDir {
    pub path: PathBuf,
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if self.path.exists() {
            let _ = std::fs::remove_dir_all(&self.path);
        }
    }
}

/// Where the `ms` source's jobs came from, carried in the job metadata (key [`ORIGIN_KEY`])
/// so that the writer can predict the model into the same MS rows.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
pub struct Origin {
    pub path: PathBuf,
    pub field_id: usize,
    pub selection: MsSelection,
    /// Set when the job is one part of a split (by time, channel or window), which a model
    /// column cannot be written for.
    #[serde(default)]
    pub split: Option<String>,
}

/// The metadata key holding the JSON [`Origin`] of a job read from an MS.
pub const ORIGIN_KEY: &str = "r2d2_ms_origin";

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ms::MsReader;

    #[test]
    fn a_damaged_table_is_a_table_error_keeping_casacores() {
        let dir = tempfile::tempdir().unwrap();
        let ms = dir.path().join("broken.ms");
        std::fs::create_dir(&ms).unwrap();
        std::fs::write(ms.join("table.dat"), b"this is not a casacore table header").unwrap();
        let err = MsReader::open(&ms, &MsSelection::default(), 1024).err().expect("a damaged table opened");
        let Error::Ms(MsError::Table { path, what, source }) = &err else { panic!("{err:?}") };
        assert_eq!((path, what.as_str()), (&ms, "cannot open the MeasurementSet's main table"));
        // Error -> MsError -> casacore's own error type.
        let module = std::error::Error::source(&err).expect("the MS error");
        let cause = module.source().expect("casacore's error");
        assert!(cause.downcast_ref::<casacure::table::TableDatError>().is_some(), "{cause:?}");
        let text = err.to_string();
        assert_eq!(text, format!("{}: cannot open the MeasurementSet's main table: {source}", ms.display()));
    }

    #[test]
    fn stokes_i_from_correlations() {
        assert_eq!(StokesI::from_codes(&[9, 10, 11, 12]), Some(StokesI::Mean(0, 3)));
        assert_eq!(StokesI::from_codes(&[5, 8]), Some(StokesI::Mean(0, 1)));
        assert_eq!(StokesI::from_codes(&[1]), Some(StokesI::Direct(0)));
        assert_eq!(StokesI::from_codes(&[9, 10]), None);
        assert_eq!(StokesI::from_codes(&[5, 12]), None);
        assert!(StokesI::Mean(0, 3).carries_i(3) && !StokesI::Mean(0, 3).carries_i(1));
    }

    #[test]
    fn weights_combine_as_the_inverse_variance_of_the_mean() {
        // Var((A + B) / 2) = (1/wA + 1/wB) / 4.
        assert_eq!(combine_weights(2.0, 2.0), 4.0);
        assert!((combine_weights(1.0, 3.0) - 3.0).abs() < 1e-15);
        assert_eq!(combine_weights(-1.0, 0.5), 0.0, "a negative hand must not give a positive weight");
        assert_eq!(combine_weights(0.0, 1.0), 0.0);
        assert!(combine_weights(f64::NAN, 1.0).is_nan());
    }

    #[test]
    fn field_selectors_parse_ids_and_names() {
        assert_eq!("3".parse::<FieldSelector>().unwrap(), FieldSelector::Id(3));
        assert_eq!("3C286".parse::<FieldSelector>().unwrap(), FieldSelector::Name("3C286".into()));
        assert_eq!(correlation_name(12), "YY");
        assert_eq!(correlation_name(40), "code 40");
    }
}

#[cfg(test)]
mod date_tests {
    use super::mjd_seconds_to_iso;

    #[test]
    fn mjd_seconds_become_iso_dates() {
        assert_eq!(mjd_seconds_to_iso(51544.5 * 86400.0).unwrap(), "2000-01-01T12:00:00.0");
        assert_eq!(mjd_seconds_to_iso(60000.0 * 86400.0 + 3723.46).unwrap(), "2023-02-25T01:02:03.5");
        assert_eq!(mjd_seconds_to_iso(51603.0 * 86400.0).unwrap(), "2000-02-29T00:00:00.0");
        assert!(mjd_seconds_to_iso(0.0).is_none() && mjd_seconds_to_iso(150.0).is_none() && mjd_seconds_to_iso(f64::NAN).is_none());
    }
}
