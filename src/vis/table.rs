//! The visibility table format (the columns below), and tables written as Parquet files or
//! Arrow record batches ([`VisTable`]). Reading is in `parquet.rs` (files), `convert.rs`
//! (record batches to imaging input) and `guard.rs` (decoder panics contained).
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
//! | `time` (optional)      | float64            | seconds: the track (domain check)   |
//! | `interval` (optional)  | float64            | integration time, seconds (likewise)|
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

use super::data::{ObservationMeta, Visibilities};
use super::convert::{record_batch_to_visibilities, IngestStats};
use super::error::TableError;
use std::fs::File;
use std::ops::Range;
use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, BooleanArray, Float64Array, Int32Array, RecordBatch};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};
use num_complex::Complex64;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use parquet::schema::types::ColumnPath;

use crate::fits::TempSibling;
use crate::{Error, Result};

/// Rows per Parquet row group written: about 50 MB uncompressed, big enough for good
/// compression and cheap footers, small enough for readers to stream.
const ROW_GROUP_ROWS: usize = 1 << 20;

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
pub(crate) mod tests {
    use super::*;
    use crate::vis::{contain_panics, read_parquet, VisReader, PARQUET};
    use arrow::array::Float32Array;
    use num_complex::{Complex32, Complex64};
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
    pub(crate) fn test_table(n: usize) -> VisTable {
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
