//! One table into several jobs' worth of visibilities, by a column (time windows, frequency
//! channels), read batch by batch through the reader contract.

use super::reader::TableReader;
use super::{check_no_nulls, record_batch_to_visibilities, record_batch_to_visibilities_keeping_rows, IngestStats, Visibilities};
use crate::{Error, Result};
use arrow::array::{Array, Float64Array, RecordBatch};
use arrow::datatypes::{DataType, Schema};
use serde::{Deserialize, Serialize};

/// How to split one table into jobs.
///
/// `{column: time, window: 600}`: windows of `window` (in the column's unit: seconds for
/// `time`) counted from the column's smallest value, one job per window holding samples;
/// `{column: frequency}`: one job per distinct value (one per channel). Job ids are the
/// table's id, then `-t003` (time), `-ch01` (frequency) or `-<column>NN`, numbered from 0
/// by window (so an empty window leaves a gap) or by rank of the value among all rows'
/// (flagged ones included, so a channel keeps its number when another is fully flagged).
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
/// turned true. A table with no sample left to image is an error naming it.
pub fn read_parts(
    reader: &mut dyn TableReader,
    split: Option<&SplitBy>,
    split_key: &str,
    cancelled: &dyn Fn() -> bool,
) -> Result<Option<(Vec<Part>, IngestStats)>> {
    let Some(scan) = scan(reader, split, split_key, cancelled)? else { return Ok(None) };
    if scan.stats.kept() == 0 {
        // Here, before an image geometry is made of no baselines (which blamed the uv coverage).
        return Err(Error::input(reader.source(), nothing_to_image(&scan.stats)));
    }
    let Some(split) = split else {
        return Ok(Some((vec![Part { suffix: None, vis: scan.vis }], scan.stats)));
    };
    let grouping = grouping(&scan, split, split_key, &reader.source().display().to_string())?;
    let mut parts = scan.vis.partition(&grouping.group, grouping.suffixes.len());
    if split.column == super::TIME_COLUMN {
        // A window of the observation is a track of its own: its times are its samples'.
        let whole = parts.first().map(|p| p.times.without_tracks()).unwrap_or_default();
        parts.iter_mut().for_each(|p| p.times = whole.clone());
        for (&g, &time) in grouping.group.iter().zip(&scan.keys) {
            parts[g].times.add_time(time);
        }
    }
    let parts = parts
        .into_iter()
        .zip(grouping.suffixes)
        .filter(|(vis, _)| !vis.is_empty())
        .map(|(vis, suffix)| Part { suffix: Some(suffix), vis })
        .collect();
    Ok(Some((parts, scan.stats)))
}

/// Why a table whose samples were all excluded cannot be imaged, with what excluded them.
pub fn nothing_to_image(stats: &IngestStats) -> String {
    if stats.rows == 0 {
        return "the table holds no samples: nothing to image".into();
    }
    let reasons: Vec<String> = [
        (stats.flagged, "flagged"),
        (stats.nonpositive_weight, "with zero (or negative) weight"),
        (stats.non_finite, "non-finite"),
        (stats.impossible, "physically impossible"),
    ]
    .iter()
    .filter(|(n, _)| *n > 0)
    .map(|(n, why)| format!("{n} {why}"))
    .collect();
    let what = if stats.non_finite + stats.impossible == 0 { "are flagged or have zero weight" } else { "are excluded" };
    format!("no usable visibilities: all {} samples {what} ({}): nothing to image", stats.rows, reasons.join(", "))
}

/// The jobs of a split as table rows ([`split_rows`]).
pub struct SplitRows {
    /// Each job's id suffix and rows (0-based, over the whole table).
    pub parts: Vec<(String, Vec<u64>)>,
    /// The longest baseline (wavelengths) of all the parts: their shared pixel size is set by
    /// it, as the engine's own split sets it (`image.longest_baseline` for a part imaged apart).
    pub longest_baseline: f64,
}

/// The rows (0-based, over the whole table) of each job `split` makes of the table, as
/// [`read_parts`] splits it: only rows kept for imaging, each part's in table order, parts in
/// group order with their id suffixes. For a caller that ships each part elsewhere as a table
/// of its own (the Python package's Dask fan-out), which then images exactly as the part.
pub fn split_rows(reader: &mut dyn TableReader, split: &SplitBy, split_key: &str, cancelled: &dyn Fn() -> bool) -> Result<Option<SplitRows>> {
    let Some(scan) = scan(reader, Some(split), split_key, cancelled)? else { return Ok(None) };
    let grouping = grouping(&scan, split, split_key, &reader.source().display().to_string())?;
    let mut rows: Vec<Vec<u64>> = vec![Vec::new(); grouping.suffixes.len()];
    for (&g, &row) in grouping.group.iter().zip(&scan.kept_rows) {
        rows[g].push(row);
    }
    let parts = grouping.suffixes.into_iter().zip(rows).filter(|(_, rows)| !rows.is_empty()).collect();
    Ok(Some(SplitRows { parts, longest_baseline: scan.vis.max_uv() }))
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
    /// Without a window: the split column's distinct finite values over all rows, flagged ones
    /// included, in `total_cmp` order; at most [`MAX_SPLIT_PARTS`] + 1 (more is refused).
    distinct: Vec<f64>,
}

fn scan(reader: &mut dyn TableReader, split: Option<&SplitBy>, split_key: &str, cancelled: &dyn Fn() -> bool) -> Result<Option<Scan>> {
    let source = reader.source().display().to_string();
    if let Some(split) = split {
        split.check_schema(&reader.schema()).map_err(|m| Error::parameter(format!("{split_key}.column"), format!("{source}: {m}")))?;
    }
    let mut scan = Scan { vis: Visibilities::default(), stats: IngestStats::default(), keys: Vec::new(), kept_rows: Vec::new(), smallest: f64::INFINITY, distinct: Vec::new() };
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
        if split.window.is_none() {
            add_distinct(&mut scan.distinct, values.values());
        }
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

/// Merges the finite values of `values` into the sorted, deduplicated `distinct`, which stops
/// growing past [`MAX_SPLIT_PARTS`] + 1 (enough to refuse the split, bounded whatever the table).
fn add_distinct(distinct: &mut Vec<f64>, values: &[f64]) {
    if distinct.len() > MAX_SPLIT_PARTS {
        return;
    }
    let mut batch: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    batch.sort_by(f64::total_cmp);
    batch.dedup_by(|a, b| a.total_cmp(b).is_eq());
    distinct.extend(batch);
    distinct.sort_by(f64::total_cmp);
    distinct.dedup_by(|a, b| a.total_cmp(b).is_eq());
    distinct.truncate(MAX_SPLIT_PARTS + 1);
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
            // Ranked among every row's values, not only the kept ones: a fully flagged channel
            // must not hand its number to the next.
            let distinct = &scan.distinct;
            if distinct.len() > MAX_SPLIT_PARTS {
                return Err(too_many("column", format!("column `{}` has more than {MAX_SPLIT_PARTS} distinct values", split.column)));
            }
            let rank = |k: &f64| distinct.binary_search_by(|d| d.total_cmp(k)).expect("a kept row's value is among all rows' values");
            (keys.iter().map(rank).collect(), 2)
        }
    };
    let groups = match split.window {
        Some(_) => group.iter().max().map_or(0, |g| g + 1),
        None => scan.distinct.len(),
    };
    let width = (groups.saturating_sub(1)).to_string().len().max(min_width);
    let suffixes: Vec<String> = (0..groups).map(|g| format!("{}{g:0width$}", split.label())).collect();
    if split.window.is_none() {
        warn_of_values_left_without_samples(&group, &suffixes, &scan.distinct, &split.column, source);
    }
    Ok(Grouping { group, suffixes })
}

/// A value of the split column that rows hold but none of them kept for imaging (a channel
/// flagged throughout) makes no job: an image of no samples would be zeros that read as an
/// empty sky, so the job is left out and its number with it, and said here. (A time window
/// without samples is only a gap in the observation and passes without a word.)
fn warn_of_values_left_without_samples(group: &[usize], suffixes: &[String], distinct: &[f64], column: &str, source: &str) {
    let mut has_samples = vec![false; suffixes.len()];
    for &g in group {
        has_samples[g] = true;
    }
    for ((suffix, value), _) in suffixes.iter().zip(distinct).zip(&has_samples).filter(|(_, &has)| !has) {
        log::warn!("{source}: {suffix} (`{column}` {value}) has no sample left to image (all flagged, zero weight or excluded): no job for it, and the others keep their numbers");
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vis::{ObservationMeta, VisReader};

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
        // Each window is a track of its own: 10 integrations of 10 s.
        for part in &parts {
            assert_eq!(part.vis.times.track_hours(), Some(100.0 / 3600.0));
        }
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
        // A channel's samples are of the whole track: 400 s from the first integration's start.
        assert!(parts.iter().all(|p| p.vis.times.track_hours() == Some(400.0 / 3600.0)));
        assert_eq!(parts.len(), 2);
        assert_eq!(parts[0].suffix.as_deref(), Some("ch00"));
        assert!(parts[0].vis.frequency.iter().all(|&f| f == 1.2e9));
        assert!(parts[1].vis.frequency.iter().all(|&f| f == 1.4e9));
        assert_eq!(rows(&parts[1]), [0, 2, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30, 32, 34, 36, 38]);
        // u is converted to wavelengths at each sample's own frequency, as without a split.
        assert_eq!(parts[0].vis.u[0], 101.0 * (1.2e9 / crate::vis::SPEED_OF_LIGHT));
    }

    /// A channel whose every row is flagged makes no job, and the channels after it keep their
    /// numbers (ranked among all rows' values, not the kept ones'); `split_rows` the same.
    #[test]
    fn a_fully_flagged_channel_leaves_a_gap_and_the_others_keep_their_numbers() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("obs.parquet");
        let mut t = table();
        // Three channels in turn, the middle one (1.3 GHz) flagged throughout.
        t.frequency = (0..40).map(|i| [1.2e9, 1.3e9, 1.4e9][i % 3]).collect();
        t.flag = (0..40).map(|i| i % 3 == 1).collect();
        write_parquet(&path, &t, &meta()).unwrap();
        let split = SplitBy { column: "frequency".into(), window: None };
        let mut reader = VisReader::open_with_columns(&path, 7, &["frequency"]).unwrap();
        let (parts, _) = read_parts(&mut reader, Some(&split), "split_by", &|| false).unwrap().unwrap();
        let suffixes: Vec<_> = parts.iter().map(|p| p.suffix.clone().unwrap()).collect();
        assert_eq!(suffixes, ["ch00", "ch02"]);
        assert!(parts[1].vis.frequency.iter().all(|&f| f == 1.4e9));
        let mut reader = VisReader::open_with_columns(&path, 7, &["frequency"]).unwrap();
        let rows = split_rows(&mut reader, &split, "split_by", &|| false).unwrap().unwrap().parts;
        assert_eq!(rows.iter().map(|(s, _)| s.as_str()).collect::<Vec<_>>(), ["ch00", "ch02"]);
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
            assert_eq!(split_rows.longest_baseline, parts.iter().map(|p| p.vis.max_uv()).fold(0.0, f64::max));
            let split_rows = split_rows.parts;
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
