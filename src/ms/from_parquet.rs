//! A Parquet visibility table as a MeasurementSet: `r2d2 convert OBS.parquet OBS.ms`.
//!
//! One MS row per (time, antenna1, antenna2) of the table, in order of first appearance; the
//! table's distinct frequencies are the channels of one spectral window; two correlations XX
//! and YY both holding the table's Stokes I, each with half its weight, so that the MS's I and
//! I weight (`(XX + YY) / 2`, `4 / (1/wA + 1/wB)`) are the table's. Channels a row lacks, and
//! samples the reader would exclude (flagged, non-finite, non-positive weight), are flagged.
//! The whole table is held in memory (rows are gathered from anywhere in it).
//!
//! The subtables are what a real observation's would be where the table's metadata say
//! (`r2d2 simulate` writes them): ANTENNA from the layouts of the configurations observed
//! (positions, dishes, station names), INTERVAL and EXPOSURE from the integration time (else
//! the most common step between times), a FEED (receptors X and Y) and a POINTING (tracking
//! the phase centre) row per antenna, OBSERVATION's time range. What is unknown is said in a
//! warning and written as before: antennas at the origin with 25 m dishes, an INTERVAL of 0.

use super::model::exchange;
use super::{invalid, MsError, SampleColumns, TempDir};
use crate::vis::{check_no_nulls, VisReader, CONFIGURATIONS_KEY, DEFAULT_BATCH_ROWS, INTEGRATION_KEY, ROTATION_KEY};
use crate::{Error, Result};
use arrow::array::{Array, BooleanArray, Float64Array, Int32Array, RecordBatch};
use arrow::datatypes::DataType;
use casacure::record::{ArrayData, ArrayValue, RecordValue};
use casacure::WritableTable;
use std::collections::HashMap;
use std::path::Path;

/// What names a conversion's MS while it is built: `.NAME.r2d2-convert-PID` beside it.
const CONVERT_INFIX: &str = ".r2d2-convert-";

/// A column of a batch cast to `to`; errors name the table and column.
fn cast(batch: &RecordBatch, name: &str, to: &DataType, source: &str, first_row: u64) -> Result<Option<arrow::array::ArrayRef>> {
    let Some(array) = batch.column_by_name(name) else { return Ok(None) };
    check_no_nulls(array.as_ref(), name, source, first_row)?;
    arrow::compute::cast(array, to)
        .map(Some)
        .map_err(|e| MsError::Arrow { path: source.into(), what: format!("column `{name}`: cannot read as {to}"), source: e }.into())
}

fn read_samples(parquet: &Path) -> Result<(SampleColumns, crate::vis::ObservationMeta)> {
    let extra = ["time", "antenna1", "antenna2"];
    let mut reader = VisReader::open_with_columns(parquet, DEFAULT_BATCH_ROWS, &extra)?;
    let source = parquet.display().to_string();
    for name in extra {
        if reader.schema().field_with_name(name).is_err() {
            return Err(invalid(
                parquet,
                format!("column `{name}` is missing; a MeasurementSet's rows need `time`, `antenna1` and `antenna2` (as `r2d2 simulate` writes them)"),
            ));
        }
    }
    let mut s = SampleColumns::default();
    let mut rows = 0u64;
    while let Some(batch) = reader.next_record_batch() {
        let batch = batch?;
        let f64s = |name: &str| -> Result<Option<Vec<f64>>> {
            Ok(cast(&batch, name, &DataType::Float64, &source, rows)?
                .map(|a| a.as_any().downcast_ref::<Float64Array>().expect("cast to Float64").values().to_vec()))
        };
        let required = |name: &str| -> Result<Vec<f64>> { f64s(name)?.ok_or_else(|| invalid(&source, format!("column `{name}` is missing"))) };
        let n = batch.num_rows();
        s.u.extend(required("u")?);
        s.v.extend(required("v")?);
        s.w.extend(required("w")?);
        s.frequency.extend(required("frequency")?);
        s.re.extend(required("vis_re")?);
        s.im.extend(required("vis_im")?);
        s.time.extend(required("time")?);
        s.weight.extend(f64s("weight")?.unwrap_or_else(|| vec![1.0; n]));
        match cast(&batch, "flag", &DataType::Boolean, &source, rows)? {
            Some(a) => s.flag.extend(a.as_any().downcast_ref::<BooleanArray>().expect("cast to Boolean").iter().map(|f| f.unwrap_or(true))),
            None => s.flag.extend(vec![false; n]),
        }
        for (name, out) in [("antenna1", &mut s.antenna1), ("antenna2", &mut s.antenna2)] {
            let a = cast(&batch, name, &DataType::Int32, &source, rows)?.ok_or_else(|| invalid(&source, format!("column `{name}` is missing")))?;
            out.extend(a.as_any().downcast_ref::<Int32Array>().expect("cast to Int32").values().iter());
        }
        rows += n as u64;
    }
    Ok((s, reader.meta().clone()))
}

/// Antenna ids a converted MS may hold (its ANTENNA table has a row for each id up to the
/// largest): far beyond any array's stations, far below what would exhaust memory.
const MAX_ANTENNA_ID: i32 = 1 << 16;

/// One row of an MS's ANTENNA table.
#[derive(Clone, Debug, PartialEq)]
pub struct AntennaRow {
    pub name: String,
    pub station: String,
    /// ITRF X, Y, Z, metres.
    pub position_m: [f64; 3],
    pub dish_diameter_m: f64,
}

/// The antennas a table's metadata say it was observed with, in the order of its antenna
/// ids; an error says what is unknown (the metadata lack them, name an unknown layout, ...).
pub type AntennaLayouts<'a> = &'a dyn Fn(&crate::vis::ObservationMeta) -> std::result::Result<Vec<AntennaRow>, String>;

/// The ANTENNA table of a conversion: `layouts` where they fit the antenna ids, else (with a
/// warning naming what is unknown) anonymous antennas at the origin with 25 m dishes.
fn antennas(parquet: &Path, meta: &crate::vis::ObservationMeta, ids: usize, layouts: AntennaLayouts<'_>) -> Vec<AntennaRow> {
    let known = layouts(meta).and_then(|rows| match rows.len() >= ids {
        true => Ok(rows),
        false => Err(format!("its antenna ids count {ids} antennas, its layouts (metadata `{CONFIGURATIONS_KEY}`, telescope `{}`) {}", meta.telescope, rows.len())),
    });
    known.unwrap_or_else(|why| {
        log::warn!("{}: antenna positions and dishes unknown ({why}): the MS's {ids} antennas are written at position 0 with 25 m dishes", parquet.display());
        (0..ids).map(|k| AntennaRow { name: format!("ANT{k:02}"), station: format!("ST{k:02}"), position_m: [0.0; 3], dish_diameter_m: 25.0 }).collect()
    })
}

/// A row's INTERVAL and EXPOSURE, seconds: the metadata's integration time, else the most
/// common step between successive times; 0 (with a warning) where neither says.
fn integration_s(parquet: &Path, meta: &crate::vis::ObservationMeta, times: &[f64]) -> f64 {
    let given = meta.extra.get(INTEGRATION_KEY).and_then(|v| v.trim().parse::<f64>().ok()).filter(|v| v.is_finite() && *v > 0.0);
    if let Some(seconds) = given {
        return seconds;
    }
    let mut observed = crate::vis::ObservedTimes::default();
    times.iter().for_each(|&t| observed.add_time(t));
    observed.integration_s().unwrap_or_else(|| {
        log::warn!("{}: integration time unknown (no positive `{INTEGRATION_KEY}` in its metadata, one time stamp): INTERVAL and EXPOSURE written as 0", parquet.display());
        0.0
    })
}

/// What the conversion made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ParquetToMs {
    pub samples: u64,
    pub rows: u64,
    pub channels: u64,
}

/// Writes the Parquet table at `parquet` as a MeasurementSet at `out` (built in a hidden
/// sibling directory and moved into place whole; an existing `out` is replaced). `layouts`
/// gives the antennas its metadata name (module doc).
pub fn convert_parquet_to_ms(parquet: &Path, out: &Path, layouts: AntennaLayouts<'_>) -> Result<ParquetToMs> {
    super::lock::check_conversion_output(parquet, out, true)?;
    let (s, meta) = read_samples(parquet)?;
    if s.u.is_empty() {
        return Err(invalid(parquet, "no samples: nothing to write"));
    }
    let mut channels: Vec<f64> = s.frequency.clone();
    channels.sort_by(f64::total_cmp);
    channels.dedup();
    if let Some(bad) = channels.iter().find(|f| !(f.is_finite() && **f > 0.0)) {
        return Err(invalid(parquet, format!("column `frequency` has {bad} Hz; frequencies must be positive")));
    }
    let nchan = channels.len();
    // What an MS cannot hold, refused by row before anything is sized by it (issue 56.12: a
    // NaN TIME and ANTENNA1 = -5 were written as they were; 56.3: one antenna id of 2e9 sized
    // an ANTENNA table until the machine ran out of memory).
    if let Some(i) = s.time.iter().position(|t| !t.is_finite()) {
        return Err(invalid(parquet, format!("row {i}: column `time` is {}; an MS's TIME must be a finite time (seconds)", s.time[i])));
    }
    for (name, ids) in [("antenna1", &s.antenna1), ("antenna2", &s.antenna2)] {
        if let Some(i) = ids.iter().position(|&a| !(0..MAX_ANTENNA_ID).contains(&a)) {
            return Err(invalid(parquet, format!("row {i}: column `{name}` is {}; antenna ids count from 0 and stay below {MAX_ANTENNA_ID}", ids[i])));
        }
    }

    // Rows: (time, antenna1, antenna2) in order of first appearance.
    let mut row_of_key: HashMap<(u64, i32, i32), usize> = HashMap::new();
    let mut first = Vec::new();
    let mut row_of = Vec::with_capacity(s.u.len());
    for i in 0..s.u.len() {
        let key = (s.time[i].to_bits(), s.antenna1[i], s.antenna2[i]);
        let row = *row_of_key.entry(key).or_insert_with(|| {
            first.push(i);
            first.len() - 1
        });
        row_of.push(row);
    }
    let nrow = first.len();
    // Each row holds every channel's cells over two hands: data (8 bytes), weight (4), flag
    // and whether seen (1 each); 30 000 rows of a frequency each asked 14 GB (issue 56.3).
    crate::limits::check_memory(nrow as f64 * nchan as f64 * 2.0 * 14.0, &format!("{} rows of {nchan} channels as MS cells", nrow))
        .map_err(|m| invalid(parquet, m))?;
    let mut data = vec![(0.0f32, 0.0f32); nrow * nchan * 2];
    let mut wspec = vec![0.0f32; nrow * nchan * 2];
    let mut flag = vec![true; nrow * nchan * 2];
    let mut seen = vec![false; nrow * nchan];
    for (i, &row) in row_of.iter().enumerate() {
        let channel = channels.binary_search_by(|f| f.total_cmp(&s.frequency[i])).expect("every frequency is a channel");
        let cell = row * nchan + channel;
        if std::mem::replace(&mut seen[cell], true) {
            return Err(invalid(
                parquet,
                format!("row {i}: a second sample for time {}, antennas {}-{}, {} Hz; an MS holds one per channel", s.time[i], s.antenna1[i], s.antenna2[i], s.frequency[i]),
            ));
        }
        let j = first[row];
        let same = |a: f64, b: f64| (a - b).abs() <= 1e-9 * (1.0 + a.abs().max(b.abs()));
        if !(same(s.u[i], s.u[j]) && same(s.v[i], s.v[j]) && same(s.w[i], s.w[j])) {
            return Err(invalid(parquet, format!("rows {j} and {i}: same time and antennas but different `u`, `v`, `w` (metres)")));
        }
        let finite = [s.re[i], s.im[i], s.weight[i]].iter().all(|x| x.is_finite());
        let excluded = s.flag[i] || !finite || s.weight[i] <= 0.0;
        for hand in 0..2 {
            data[cell * 2 + hand] = (s.re[i] as f32, s.im[i] as f32);
            wspec[cell * 2 + hand] = if excluded { 0.0 } else { (s.weight[i] / 2.0) as f32 };
            flag[cell * 2 + hand] = excluded;
        }
    }
    let out_name = out.file_name().ok_or_else(|| Error::parameter("output", format!("{}: expected a directory name", out.display())))?;
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    // What a conversion killed part-way left here (its process gone) goes first.
    let prefix = format!(".{}{CONVERT_INFIX}", out_name.to_string_lossy());
    super::lock::remove_left_by_dead_processes(parent, &prefix, "conversion");
    let building = TempDir { path: parent.join(format!("{prefix}{}", std::process::id())) };
    if building.path.exists() {
        std::fs::remove_dir_all(&building.path).map_err(|e| Error::io(&building.path, e))?;
    }
    let ids = s.antenna1.iter().chain(&s.antenna2).copied().max().unwrap_or(0).max(0) as usize + 1;
    if let Some(angle) = meta.extra.get(ROTATION_KEY).and_then(|a| a.trim().parse::<f64>().ok()).filter(|a| *a != 0.0) {
        log::info!("{}: its uv coverage was rotated by {angle} deg (the simulation's `random_rotation`): its UVW do not follow from the antenna positions and times", parquet.display());
    }
    let observed = Observed { antennas: antennas(parquet, &meta, ids, layouts), integration_s: integration_s(parquet, &meta, &s.time) };
    let table = MainTable { s: &s, first: &first, data, wspec, flag, nchan };
    write_ms(&building.path, &table, &channels, &meta, &observed).map_err(|e| match e {
        Error::Input { message, .. } => invalid(out, message),
        Error::Ms(mut e) => {
            *e.path_mut() = out.to_path_buf();
            Error::Ms(e)
        }
        other => other,
    })?;
    if out.exists() {
        // The MS being replaced is someone's: wait for another r2d2 writing it, refuse while
        // another program has it open (its files would vanish under it).
        // A link is replaced itself, and the MS it named is left as it is: no lock needed.
        let is_link = std::fs::symlink_metadata(out).is_ok_and(|m| m.file_type().is_symlink());
        let lock = if is_link { None } else { Some(super::lock::lock_for_replacement(out)?) };
        exchange(&building.path, out)?;
        drop(lock);
    } else {
        std::fs::rename(&building.path, out).map_err(|e| Error::io(out, e))?;
    }
    Ok(ParquetToMs { samples: s.u.len() as u64, rows: nrow as u64, channels: nchan as u64 })
}

struct MainTable<'a> {
    s: &'a SampleColumns,
    /// The first sample of each row.
    first: &'a [usize],
    /// `[row][channel][hand]`.
    data: Vec<(f32, f32)>,
    wspec: Vec<f32>,
    flag: Vec<bool>,
    nchan: usize,
}

/// What the subtables say of the observation beyond the table's columns.
struct Observed {
    antennas: Vec<AntennaRow>,
    integration_s: f64,
}

fn casacure_error<E: std::error::Error + Send + Sync + 'static>(path: &Path, what: &str, e: E) -> Error {
    MsError::Table { path: path.to_path_buf(), what: what.to_string(), source: Box::new(e) }.into()
}

/// Sets `values` (one per row, from row 0) into the column `name` of `table`.
fn put(table: &mut WritableTable, path: &Path, name: &str, values: impl IntoIterator<Item = RecordValue>) -> Result<()> {
    let column = table
        .desc()
        .columns
        .iter()
        .position(|c| c.name == name)
        .ok_or_else(|| invalid(path, format!("column `{name}` is missing from the MS schema")))?;
    for (row, value) in values.into_iter().enumerate() {
        table.putcell(column, row as u64, value).map_err(|e| casacure_error(path, &format!("column `{name}`"), e))?;
    }
    Ok(())
}

fn array(shape: &[u32], data: ArrayData) -> RecordValue {
    RecordValue::Array(ArrayValue { shape: shape.to_vec(), data })
}

/// Opens a (sub)table of the MS being built, adds `rows` rows, lets `fill` set its columns,
/// and flushes.
fn fill_table(path: &Path, rows: u64, fill: impl FnOnce(&mut WritableTable) -> Result<()>) -> Result<()> {
    let (_, mut table) = WritableTable::open_for_update(path).map_err(|e| casacure_error(path, "opening", e))?;
    table.addrows(rows);
    fill(&mut table)?;
    table.flush().map_err(|e| casacure_error(path, "writing", e))?;
    Ok(())
}

fn write_ms(path: &Path, table: &MainTable<'_>, channels: &[f64], meta: &crate::vis::ObservationMeta, observed: &Observed) -> Result<()> {
    let nchan = table.nchan;
    let column = |value_type: &str| {
        format!(
            r#"{{"valueType":"{value_type}","ndim":2,"shape":[{nchan},2],"option":4,"dataManagerType":"StandardStMan","dataManagerGroup":"StandardStMan","comment":"","keywords":{{}},"maxlen":0}}"#
        )
    };
    let extra = format!(r#"{{"DATA":{},"FLAG":{},"WEIGHT_SPECTRUM":{}}}"#, column("complex"), column("boolean"), column("float"));
    super::casacore(path, "creating the MeasurementSet", || casacure::ms::default_ms(path, Some(&extra), None))?;
    let s = table.s;
    let rows = table.first.len();
    let shape = [nchan as u32, 2];
    let cells = |i: usize| i * nchan * 2..(i + 1) * nchan * 2;
    fill_table(path, rows as u64, |t| {
        let scalar_f64 = |f: &dyn Fn(usize) -> f64| table.first.iter().map(move |&j| RecordValue::Double(f(j))).collect::<Vec<_>>();
        put(t, path, "TIME", scalar_f64(&|j| s.time[j]))?;
        put(t, path, "TIME_CENTROID", scalar_f64(&|j| s.time[j]))?;
        for name in ["INTERVAL", "EXPOSURE"] {
            put(t, path, name, (0..rows).map(|_| RecordValue::Double(observed.integration_s)))?;
        }
        put(t, path, "ANTENNA1", table.first.iter().map(|&j| RecordValue::Int(s.antenna1[j])))?;
        put(t, path, "ANTENNA2", table.first.iter().map(|&j| RecordValue::Int(s.antenna2[j])))?;
        put(t, path, "STATE_ID", (0..rows).map(|_| RecordValue::Int(-1)))?;
        put(t, path, "UVW", table.first.iter().map(|&j| array(&[3], ArrayData::Double(vec![s.u[j], s.v[j], s.w[j]]))))?;
        put(t, path, "DATA", (0..rows).map(|i| array(&shape, ArrayData::Complex(table.data[cells(i)].to_vec()))))?;
        put(t, path, "WEIGHT_SPECTRUM", (0..rows).map(|i| array(&shape, ArrayData::Float(table.wspec[cells(i)].to_vec()))))?;
        put(t, path, "FLAG", (0..rows).map(|i| array(&shape, ArrayData::Bool(table.flag[cells(i)].to_vec()))))?;
        put(t, path, "FLAG_ROW", (0..rows).map(|i| RecordValue::Bool(table.flag[cells(i)].iter().all(|&f| f))))?;
        // WEIGHT: each hand's mean weight over the row's unflagged channels; SIGMA from it.
        let row_weight: Vec<[f32; 2]> = (0..rows)
            .map(|i| {
                let mut mean = [0.0f32; 2];
                for (hand, m) in mean.iter_mut().enumerate() {
                    let kept: Vec<f32> = (0..nchan).map(|c| i * nchan * 2 + c * 2 + hand).filter(|&k| !table.flag[k]).map(|k| table.wspec[k]).collect();
                    *m = if kept.is_empty() { 0.0 } else { kept.iter().sum::<f32>() / kept.len() as f32 };
                }
                mean
            })
            .collect();
        put(t, path, "WEIGHT", row_weight.iter().map(|w| array(&[2], ArrayData::Float(w.to_vec()))))?;
        let sigma = |w: f32| if w > 0.0 { 1.0 / w.sqrt() } else { 0.0 };
        put(t, path, "SIGMA", row_weight.iter().map(|w| array(&[2], ArrayData::Float(vec![sigma(w[0]), sigma(w[1])]))))?;
        // casacore's MS checks (WSClean's among them) want FLAG_CATEGORY's CATEGORY keyword.
        let category = t.desc().columns.iter().position(|c| c.name == "FLAG_CATEGORY");
        if let Some(column) = category {
            t.putcolkeyword(column, "CATEGORY", array(&[0], ArrayData::String(Vec::new())))
                .map_err(|e| casacure_error(path, "column `FLAG_CATEGORY` keyword CATEGORY", e))?;
        }
        Ok(())
    })?;
    let widths: Vec<f64> = (0..nchan)
        .map(|c| match (c + 1 < nchan, c > 0) {
            (true, _) => channels[c + 1] - channels[c],
            (false, true) => channels[c] - channels[c - 1],
            _ => 1.0e6,
        })
        .collect();
    fill_table(&path.join("SPECTRAL_WINDOW"), 1, |t| {
        let p = path.join("SPECTRAL_WINDOW");
        put(t, &p, "NUM_CHAN", [RecordValue::Int(nchan as i32)])?;
        put(t, &p, "CHAN_FREQ", [array(&[nchan as u32], ArrayData::Double(channels.to_vec()))])?;
        for name in ["CHAN_WIDTH", "EFFECTIVE_BW", "RESOLUTION"] {
            put(t, &p, name, [array(&[nchan as u32], ArrayData::Double(widths.clone()))])?;
        }
        put(t, &p, "REF_FREQUENCY", [RecordValue::Double(channels[0])])?;
        put(t, &p, "TOTAL_BANDWIDTH", [RecordValue::Double(widths.iter().sum())])?;
        put(t, &p, "MEAS_FREQ_REF", [RecordValue::Int(5)])?; // TOPO
        put(t, &p, "NET_SIDEBAND", [RecordValue::Int(1)])?;
        put(t, &p, "NAME", [RecordValue::String("SPW0".into())])
    })?;
    fill_table(&path.join("POLARIZATION"), 1, |t| {
        let p = path.join("POLARIZATION");
        put(t, &p, "NUM_CORR", [RecordValue::Int(2)])?;
        put(t, &p, "CORR_TYPE", [array(&[2], ArrayData::Int(vec![9, 12]))])?; // XX, YY
        put(t, &p, "CORR_PRODUCT", [array(&[2, 2], ArrayData::Int(vec![0, 0, 1, 1]))])
    })?;
    fill_table(&path.join("DATA_DESCRIPTION"), 1, |_| Ok(()))?;
    // The observation spans its integrations, whole: from the first's start to the last's end.
    let (first_time, last_time) = s.time.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &t| (a.min(t), b.max(t)));
    let (t0, t1) = (first_time - observed.integration_s / 2.0, last_time + observed.integration_s / 2.0);
    let (middle, span) = ((t0 + t1) / 2.0, t1 - t0);
    // A direction column's cell: [2, n] in casacore's (Fortran) order, one polynomial term.
    let direction = || array(&[1, 2], ArrayData::Double(vec![meta.phase_centre_ra_deg.to_radians(), meta.phase_centre_dec_deg.to_radians()]));
    let field_name = meta.extra.get("ms_field").cloned().unwrap_or_else(|| "TARGET".into());
    fill_table(&path.join("FIELD"), 1, |t| {
        let p = path.join("FIELD");
        for name in ["PHASE_DIR", "DELAY_DIR", "REFERENCE_DIR"] {
            put(t, &p, name, [direction()])?;
        }
        put(t, &p, "NAME", [RecordValue::String(field_name.clone())])?;
        put(t, &p, "TIME", [RecordValue::Double(t0)])?;
        put(t, &p, "SOURCE_ID", [RecordValue::Int(-1)])
    })?;
    let simulated = meta.extra.get("simulation_seed");
    fill_table(&path.join("OBSERVATION"), 1, |t| {
        let p = path.join("OBSERVATION");
        put(t, &p, "TELESCOPE_NAME", [RecordValue::String(meta.telescope.clone())])?;
        put(t, &p, "TIME_RANGE", [array(&[2], ArrayData::Double(vec![t0, t1]))])?;
        let (observer, project) = match simulated {
            Some(seed) => ("r2d2 simulate".to_string(), format!("r2d2 simulation, seed {seed}")),
            None => ("r2d2 convert".to_string(), "r2d2 convert".to_string()),
        };
        put(t, &p, "OBSERVER", [RecordValue::String(observer)])?;
        put(t, &p, "PROJECT", [RecordValue::String(project)])
    })?;
    let antennas = &observed.antennas;
    let nant = antennas.len();
    fill_table(&path.join("ANTENNA"), nant as u64, |t| {
        let p = path.join("ANTENNA");
        put(t, &p, "NAME", antennas.iter().map(|a| RecordValue::String(a.name.clone())))?;
        put(t, &p, "STATION", antennas.iter().map(|a| RecordValue::String(a.station.clone())))?;
        put(t, &p, "TYPE", (0..nant).map(|_| RecordValue::String("GROUND-BASED".into())))?;
        put(t, &p, "MOUNT", (0..nant).map(|_| RecordValue::String("ALT-AZ".into())))?;
        put(t, &p, "POSITION", antennas.iter().map(|a| array(&[3], ArrayData::Double(a.position_m.to_vec()))))?;
        put(t, &p, "OFFSET", (0..nant).map(|_| array(&[3], ArrayData::Double(vec![0.0; 3]))))?;
        put(t, &p, "DISH_DIAMETER", antennas.iter().map(|a| RecordValue::Double(a.dish_diameter_m)))
    })?;
    // One feed per antenna, linear receptors X and Y (the correlations are XX and YY), valid
    // for the whole observation and every window.
    fill_table(&path.join("FEED"), nant as u64, |t| {
        let p = path.join("FEED");
        put(t, &p, "ANTENNA_ID", (0..nant).map(|k| RecordValue::Int(k as i32)))?;
        put(t, &p, "FEED_ID", (0..nant).map(|_| RecordValue::Int(0)))?;
        put(t, &p, "SPECTRAL_WINDOW_ID", (0..nant).map(|_| RecordValue::Int(-1)))?;
        put(t, &p, "TIME", (0..nant).map(|_| RecordValue::Double(middle)))?;
        put(t, &p, "INTERVAL", (0..nant).map(|_| RecordValue::Double(span)))?;
        put(t, &p, "NUM_RECEPTORS", (0..nant).map(|_| RecordValue::Int(2)))?;
        put(t, &p, "BEAM_ID", (0..nant).map(|_| RecordValue::Int(-1)))?;
        put(t, &p, "BEAM_OFFSET", (0..nant).map(|_| array(&[2, 2], ArrayData::Double(vec![0.0; 4]))))?;
        put(t, &p, "POLARIZATION_TYPE", (0..nant).map(|_| array(&[2], ArrayData::String(vec!["X".into(), "Y".into()]))))?;
        let identity = vec![(1.0, 0.0), (0.0, 0.0), (0.0, 0.0), (1.0, 0.0)];
        put(t, &p, "POL_RESPONSE", (0..nant).map(|_| array(&[2, 2], ArrayData::Complex(identity.clone()))))?;
        put(t, &p, "POSITION", (0..nant).map(|_| array(&[3], ArrayData::Double(vec![0.0; 3]))))?;
        put(t, &p, "RECEPTOR_ANGLE", (0..nant).map(|_| array(&[2], ArrayData::Double(vec![0.0, std::f64::consts::FRAC_PI_2]))))
    })?;
    // Every antenna tracks the phase centre throughout.
    fill_table(&path.join("POINTING"), nant as u64, |t| {
        let p = path.join("POINTING");
        put(t, &p, "ANTENNA_ID", (0..nant).map(|k| RecordValue::Int(k as i32)))?;
        put(t, &p, "TIME", (0..nant).map(|_| RecordValue::Double(middle)))?;
        put(t, &p, "INTERVAL", (0..nant).map(|_| RecordValue::Double(span)))?;
        put(t, &p, "TIME_ORIGIN", (0..nant).map(|_| RecordValue::Double(middle)))?;
        put(t, &p, "NAME", (0..nant).map(|_| RecordValue::String(field_name.clone())))?;
        put(t, &p, "NUM_POLY", (0..nant).map(|_| RecordValue::Int(0)))?;
        put(t, &p, "DIRECTION", (0..nant).map(|_| direction()))?;
        put(t, &p, "TARGET", (0..nant).map(|_| direction()))?;
        put(t, &p, "TRACKING", (0..nant).map(|_| RecordValue::Bool(true)))
    })
}
