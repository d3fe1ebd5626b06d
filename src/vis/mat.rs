//! MATLAB `.mat` observations as the reference implementation (R2D2-RI) keeps them: `y`
//! (complex visibilities, raw), `u`, `v`, `w` (wavelengths, the MeasurementSet's signs; metres
//! when the file says `unit = 'm'`), `nW` (`1 / sigma`, one per sample or one for all),
//! `nWimag` (square roots of given imaging weights, or empty), `frequency` (Hz, one channel).
//! Both container versions occur: MAT v5 (scipy's `savemat`, MATLAB's default; compressed
//! elements included) and v7.3 (HDF5 with a MAT header as the user block, complex arrays as a
//! compound of `real` and `imag`).
//!
//! The file becomes a table of the Parquet format's columns (baselines in metres, `weight =
//! nW^2`) and, when `nWimag` holds values, `imaging_weight = nWimag^2`, which the `given`
//! weighting uses as the reference does. A .mat names no phase centre or telescope: they are
//! left unknown (RA 0, Dec 0, telescope `unknown`) and the log says so.

use super::error::TableError;
use super::reader::TableReader;
use super::{ObservationMeta, SPEED_OF_LIGHT};
use crate::{Error, Result};
use arrow::array::{ArrayRef, BooleanArray, Float64Array, RecordBatch};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};
use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The variables the reader uses; every other one is skipped unread.
const WANTED: [&str; 8] = ["y", "u", "v", "w", "nW", "nWimag", "frequency", "unit"];

/// Whether a file's first bytes are a MAT file's header (v5 or v7.3).
pub(crate) fn is_mat(head: &[u8]) -> bool {
    head.starts_with(b"MATLAB 5.0 MAT-file") || head.starts_with(b"MATLAB 7.3 MAT-file")
}

/// One variable as read: its dimensions and its values as f64 (the imaginary part when it is
/// complex), or its text.
#[derive(Debug, Default)]
struct Variable {
    dims: Vec<usize>,
    re: Vec<f64>,
    im: Option<Vec<f64>>,
    text: Option<String>,
}

impl Variable {
    fn len(&self) -> usize {
        self.re.len()
    }

    /// Whether it is a vector (N x 1, 1 x N) or a scalar, as every variable read here must be.
    fn is_vector(&self) -> bool {
        self.dims.iter().filter(|&&d| d > 1).count() <= 1
    }
}

/// A .mat observation as a visibility table: one record batch, handed out in slices.
pub struct MatReader {
    source: PathBuf,
    meta: ObservationMeta,
    batch: RecordBatch,
    next_row: usize,
    batch_rows: usize,
}

impl MatReader {
    pub fn open(path: &Path, batch_rows: usize) -> Result<MatReader> {
        let size = std::fs::metadata(path).map_err(|e| Error::io(path, e))?.len();
        let mut head = [0u8; 128];
        let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        file.read_exact(&mut head).map_err(|_| invalid(path, "shorter than a MAT file's 128-byte header"))?;
        let variables = if head.starts_with(b"MATLAB 7.3 MAT-file") {
            read_v73(path)?
        } else {
            // The whole file is read (elements are found by walking it): bounded by memory first.
            crate::limits::check_memory(size as f64, "the .mat file").map_err(|m| invalid(path, m))?;
            let mut bytes = Vec::new();
            std::fs::File::open(path).and_then(|mut f| f.read_to_end(&mut bytes)).map_err(|e| Error::io(path, e))?;
            read_v5(&bytes, path)?
        };
        let batch = to_batch(variables, path)?;
        log::info!(
            "{}: a MATLAB observation ({} samples); it names no phase centre or telescope: the images are placed at RA 0, Dec 0, telescope unknown",
            path.display(),
            batch.num_rows()
        );
        let mut meta = ObservationMeta::new(0.0, 0.0, crate::vis::UNKNOWN_TELESCOPE);
        meta.extra.insert("source_format".into(), "mat".into());
        Ok(MatReader { source: path.to_path_buf(), meta, batch, next_row: 0, batch_rows: batch_rows.max(1) })
    }
}

impl TableReader for MatReader {
    fn source(&self) -> &Path {
        &self.source
    }
    fn meta(&self) -> &ObservationMeta {
        &self.meta
    }
    fn schema(&self) -> SchemaRef {
        self.batch.schema()
    }
    fn next_batch(&mut self) -> Option<Result<RecordBatch>> {
        let rows = self.batch.num_rows();
        if self.next_row >= rows {
            return None;
        }
        let n = self.batch_rows.min(rows - self.next_row);
        let slice = self.batch.slice(self.next_row, n);
        self.next_row += n;
        Some(Ok(slice))
    }
}

fn invalid(path: &Path, message: impl Into<String>) -> Error {
    TableError::decode(path, "not a readable .mat observation", message.into()).into()
}

/// The table of a file's variables: checks names, lengths and units.
fn to_batch(mut vars: BTreeMap<String, Variable>, path: &Path) -> Result<RecordBatch> {
    if let Some((name, var)) = vars.iter().find(|(_, v)| !v.is_vector()) {
        return Err(invalid(path, format!("`{name}` is a {:?} array: expected a vector (N x 1 or 1 x N)", var.dims)));
    }
    // Each variable of its kind: text only for `unit`, complex values only for `y`.
    for (name, var) in &vars {
        let expected = match name.as_str() {
            "unit" => "text ('m', or none for wavelengths)",
            "y" => "numbers (complex visibilities)",
            "frequency" => "a real number (Hz)",
            _ => "real numbers",
        };
        let found = match (&var.text, &var.im) {
            (Some(text), _) if name != "unit" => format!("text ('{text}')"),
            (None, _) if name == "unit" && var.len() == 1 => format!("a number ({})", var.re[0]),
            (None, _) if name == "unit" && var.len() > 1 => format!("{} numbers", var.len()),
            (_, Some(_)) if name != "y" => format!("{} complex values", var.len()),
            _ => continue,
        };
        return Err(invalid(path, format!("`{name}` holds {found}: expected {expected}")));
    }
    let mut take = |name: &str| vars.remove(name);
    let need = |v: Option<Variable>, name: &str, what: &str| v.ok_or_else(|| invalid(path, format!("no variable `{name}` ({what})")));
    let y = need(take("y"), "y", "the visibilities")?;
    let u = need(take("u"), "u", "the baselines' u")?;
    let v = need(take("v"), "v", "the baselines' v")?;
    let w = take("w");
    let n = y.len();
    if n == 0 {
        return Err(invalid(path, "`y` holds no visibilities"));
    }
    let same = |var: &Variable, name: &str| -> Result<()> {
        if var.len() != n {
            return Err(invalid(path, format!("`{name}` holds {} values, `y` {n}: expected one real value per visibility", var.len())));
        }
        Ok(())
    };
    same(&u, "u")?;
    same(&v, "v")?;
    if let Some(w) = &w {
        same(w, "w")?;
    } else {
        log::warn!("{}: no variable `w`: taken as 0 (coplanar)", path.display());
    }
    let frequency = need(take("frequency"), "frequency", "the observing frequency in Hz")?;
    let f = match frequency.re.as_slice() {
        [f] if *f > 0.0 && f.is_finite() => *f,
        [_] => return Err(invalid(path, format!("`frequency` = {}: expected a positive frequency in Hz", frequency.re[0]))),
        values => {
            return Err(invalid(
                path,
                format!("`frequency` holds {} values: one channel per file is read (files of several channels, with `flag` and `nFreqs`, are not yet)", values.len()),
            ))
        }
    };
    let unit = take("unit").and_then(|u| u.text).unwrap_or_default(); // text, as checked above
    // u, v, w to metres, the table format's unit (the reader turns them back to wavelengths).
    let to_metres = match unit.trim() {
        "" | "lambda" | "wavelengths" => SPEED_OF_LIGHT / f,
        "m" => 1.0,
        other => return Err(invalid(path, format!("`unit` = '{other}': expected 'm' (metres) or none (wavelengths)"))),
    };
    let nw = match take("nW") {
        None => vec![1.0; n],
        Some(nw) if nw.len() == n => nw.re,
        Some(nw) if nw.len() == 1 => vec![nw.re[0]; n],
        Some(nw) => {
            return Err(invalid(
                path,
                format!("`nW` holds {} values for {n} visibilities: expected one per visibility or one for all (the per-block form with `tau_index` is not read)", nw.len()),
            ))
        }
    };
    if let Some(bad) = nw.iter().find(|x| !(x.is_finite() && **x >= 0.0)) {
        return Err(invalid(path, format!("`nW` holds {bad}: expected finite values >= 0 (1 / sigma)")));
    }
    let imaging = match take("nWimag") {
        Some(x) if x.len() == 0 => None,
        Some(x) if x.len() == n => Some(x.re),
        Some(x) => return Err(invalid(path, format!("`nWimag` holds {} values for {n} visibilities: expected one per visibility, or none", x.len()))),
        None => None,
    };
    if let Some(bad) = imaging.as_ref().and_then(|x| x.iter().find(|x| !(x.is_finite() && **x >= 0.0))) {
        return Err(invalid(path, format!("`nWimag` holds {bad}: expected finite values >= 0")));
    }
    let zeros = vec![0.0; n];
    let metres = |x: &[f64]| Arc::new(Float64Array::from_iter_values(x.iter().map(|x| x * to_metres))) as ArrayRef;
    let mut fields = vec![
        ("u", metres(&u.re)),
        ("v", metres(&v.re)),
        ("w", metres(w.as_ref().map_or(&zeros, |w| &w.re))),
        ("frequency", Arc::new(Float64Array::from(vec![f; n])) as ArrayRef),
        ("vis_re", Arc::new(Float64Array::from(y.re)) as ArrayRef),
        ("vis_im", Arc::new(Float64Array::from(y.im.unwrap_or(zeros.clone()))) as ArrayRef),
        ("weight", Arc::new(Float64Array::from_iter_values(nw.iter().map(|x| x * x))) as ArrayRef),
        ("flag", Arc::new(BooleanArray::from(vec![false; n])) as ArrayRef),
    ];
    if let Some(x) = imaging {
        fields.push(("imaging_weight", Arc::new(Float64Array::from_iter_values(x.iter().map(|x| x * x))) as ArrayRef));
    }
    let schema = Schema::new(
        fields.iter().map(|(name, a)| Field::new(*name, a.data_type().clone(), false)).collect::<Vec<_>>(),
    );
    debug_assert!(fields.iter().all(|(_, a)| matches!(a.data_type(), DataType::Float64 | DataType::Boolean)));
    RecordBatch::try_new(Arc::new(schema), fields.into_iter().map(|(_, a)| a).collect())
        .map_err(|e| TableError::Build { table: path.display().to_string(), source: e }.into())
}

// ---- MAT v5: a 128-byte header, then tagged data elements (8-byte aligned), some of them
// zlib-compressed elements holding one element each.

const MI_INT8: u32 = 1;
const MI_UINT8: u32 = 2;
const MI_INT16: u32 = 3;
const MI_UINT16: u32 = 4;
const MI_INT32: u32 = 5;
const MI_UINT32: u32 = 6;
const MI_SINGLE: u32 = 7;
const MI_DOUBLE: u32 = 9;
const MI_INT64: u32 = 12;
const MI_UINT64: u32 = 13;
const MI_MATRIX: u32 = 14;
const MI_COMPRESSED: u32 = 15;
const MI_UTF8: u32 = 16;
const MI_UTF16: u32 = 17;
/// `mxCHAR_CLASS`, and the numeric classes (double .. uint64).
const MX_CHAR: u32 = 4;
const MX_NUMERIC: std::ops::RangeInclusive<u32> = 6..=15;
const COMPLEX_FLAG: u32 = 0x0800;

/// Little- or big-endian reads, as the header's `IM`/`MI` says.
#[derive(Clone, Copy)]
struct Endian(bool);

impl Endian {
    fn u32(self, b: &[u8]) -> u32 {
        let a = [b[0], b[1], b[2], b[3]];
        if self.0 {
            u32::from_le_bytes(a)
        } else {
            u32::from_be_bytes(a)
        }
    }
}

/// One tagged element: its type and data.
struct Element<'a> {
    kind: u32,
    data: &'a [u8],
}

/// The next element of `bytes` at `*at`, moving `*at` past it (and its padding). Sizes are
/// checked against what is left before anything is read.
fn next_element<'a>(bytes: &'a [u8], at: &mut usize, e: Endian, path: &Path) -> Result<Element<'a>> {
    let tag = bytes.get(*at..*at + 8).ok_or_else(|| invalid(path, format!("a data element's tag runs past the end of the file (byte {})", *at)))?;
    let first = e.u32(&tag[0..4]);
    if first >> 16 != 0 {
        // Small element: size in the upper half, type in the lower, data in the tag's 4 bytes.
        let (kind, size) = (first & 0xffff, (first >> 16) as usize);
        if size > 4 {
            return Err(invalid(path, format!("a small data element declares {size} bytes (at most 4)")));
        }
        let data = &bytes[*at + 4..*at + 4 + size];
        *at += 8;
        return Ok(Element { kind, data });
    }
    let size = e.u32(&tag[4..8]) as usize;
    let start = *at + 8;
    let end = start.checked_add(size).filter(|&end| end <= bytes.len()).ok_or_else(|| {
        invalid(path, format!("a data element declares {size} bytes at byte {start}, past the end of the file ({} bytes)", bytes.len()))
    })?;
    // Compressed elements are not padded; the others are to 8 bytes.
    *at = if first == MI_COMPRESSED { end } else { (end + 7) & !7 };
    Ok(Element { kind: first, data: &bytes[start..end] })
}

fn read_v5(bytes: &[u8], path: &Path) -> Result<BTreeMap<String, Variable>> {
    if bytes.len() < 128 {
        return Err(invalid(path, "shorter than a MAT file's 128-byte header"));
    }
    let e = match &bytes[126..128] {
        b"IM" => Endian(true),
        b"MI" => Endian(false),
        other => return Err(invalid(path, format!("the header's endian indicator is {other:?}, expected \"IM\" or \"MI\""))),
    };
    let mut vars = BTreeMap::new();
    let mut at = 128;
    while at + 8 <= bytes.len() {
        let element = next_element(bytes, &mut at, e, path)?;
        let inflated;
        let matrix = match element.kind {
            MI_MATRIX => element.data,
            MI_COMPRESSED => {
                inflated = inflate(element.data, path)?;
                let mut inner = 0;
                let el = next_element(&inflated, &mut inner, e, path)?;
                if el.kind != MI_MATRIX {
                    continue;
                }
                // The inflated element's data, re-borrowed from `inflated`.
                let (s, n) = (el.data.as_ptr() as usize - inflated.as_ptr() as usize, el.data.len());
                &inflated[s..s + n]
            }
            _ => continue,
        };
        if let Some((name, var)) = read_matrix(matrix, e, path)? {
            vars.insert(name, var);
        }
    }
    Ok(vars)
}

/// Inflates a compressed element, bounded by the memory available.
fn inflate(data: &[u8], path: &Path) -> Result<Vec<u8>> {
    let budget = crate::limits::memory_budget().bytes as f64 / 2.0;
    let mut out = Vec::new();
    flate2::read::ZlibDecoder::new(data)
        .take(budget as u64 + 1)
        .read_to_end(&mut out)
        .map_err(|e| invalid(path, format!("a compressed element does not inflate: {e}")))?;
    if out.len() as f64 > budget {
        return Err(invalid(path, format!("a compressed element inflates to more than the memory available ({})", crate::limits::format_bytes(budget))));
    }
    Ok(out)
}

/// A matrix element's name and values, when it is one the reader uses.
fn read_matrix(data: &[u8], e: Endian, path: &Path) -> Result<Option<(String, Variable)>> {
    let mut at = 0;
    let flags = next_element(data, &mut at, e, path)?;
    if flags.data.len() < 8 {
        return Err(invalid(path, "a matrix's array flags are shorter than 8 bytes"));
    }
    let flag_word = e.u32(&flags.data[0..4]);
    let class = flag_word & 0xff;
    let dims_el = next_element(data, &mut at, e, path)?;
    let dims: Vec<usize> = numbers(&dims_el, e, path)?.into_iter().map(|d| d as usize).collect();
    let name_el = next_element(data, &mut at, e, path)?;
    let name = String::from_utf8_lossy(name_el.data).into_owned();
    if !WANTED.contains(&name.as_str()) {
        return Ok(None);
    }
    let count = dims.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).ok_or_else(|| invalid(path, format!("`{name}`: its dimensions {dims:?} overflow")))?;
    if class == MX_CHAR {
        let text_el = next_element(data, &mut at, e, path)?;
        let codes = numbers(&text_el, e, path)?;
        let text: String = codes.iter().filter_map(|&c| char::from_u32(c as u32)).collect();
        return Ok(Some((name, Variable { dims, text: Some(text), ..Variable::default() })));
    }
    if !MX_NUMERIC.contains(&class) {
        return Err(invalid(path, format!("`{name}` is of MATLAB class {class}: expected a numeric array")));
    }
    let re_el = next_element(data, &mut at, e, path)?;
    let re = numbers(&re_el, e, path)?;
    let im = if flag_word & COMPLEX_FLAG != 0 { Some(numbers(&next_element(data, &mut at, e, path)?, e, path)?) } else { None };
    if re.len() != count || im.as_ref().is_some_and(|im| im.len() != count) {
        return Err(invalid(path, format!("`{name}`: {} values for dimensions {dims:?}", re.len())));
    }
    Ok(Some((name, Variable { dims, re, im, text: None })))
}

/// An element's values as f64, whatever numeric type it is stored in (MATLAB stores a double
/// array in a smaller integer type when its values fit).
fn numbers(el: &Element<'_>, e: Endian, path: &Path) -> Result<Vec<f64>> {
    let d = el.data;
    macro_rules! each {
        ($n:expr, $conv:expr) => {{
            if d.len() % $n != 0 {
                return Err(invalid(path, format!("a data element of {} bytes is not a whole number of {}-byte values", d.len(), $n)));
            }
            d.chunks_exact($n).map(|c| {
                let mut a = [0u8; $n];
                a.copy_from_slice(c);
                if !e.0 {
                    a.reverse();
                }
                #[allow(clippy::redundant_closure_call)]
                ($conv)(a)
            }).collect()
        }};
    }
    Ok(match el.kind {
        MI_INT8 => d.iter().map(|&b| f64::from(b as i8)).collect(),
        MI_UINT8 | MI_UTF8 => d.iter().map(|&b| f64::from(b)).collect(),
        MI_INT16 => each!(2, |a| f64::from(i16::from_le_bytes(a))),
        MI_UINT16 | MI_UTF16 => each!(2, |a| f64::from(u16::from_le_bytes(a))),
        MI_INT32 => each!(4, |a| f64::from(i32::from_le_bytes(a))),
        MI_UINT32 => each!(4, |a| f64::from(u32::from_le_bytes(a))),
        MI_SINGLE => each!(4, |a| f64::from(f32::from_le_bytes(a))),
        MI_DOUBLE => each!(8, f64::from_le_bytes),
        MI_INT64 => each!(8, |a| i64::from_le_bytes(a) as f64),
        MI_UINT64 => each!(8, |a| u64::from_le_bytes(a) as f64),
        other => return Err(invalid(path, format!("a data element of type {other}: expected numbers"))),
    })
}

// ---- MAT v7.3: HDF5. Each variable is a dataset at the root with a `MATLAB_class`
// attribute; arrays are stored transposed (MATLAB is column-major), which leaves vectors as
// they are; complex arrays are compounds of `real` and `imag`; an empty array is its
// dimensions with `MATLAB_empty` set; text is UTF-16 code units.

fn read_v73(path: &Path) -> Result<BTreeMap<String, Variable>> {
    let h5 = |doing: &str, e: hdf5_reader::error::Error| -> Error { TableError::decode(path, &format!("reading the .mat file (HDF5): {doing}"), e).into() };
    // The HDF5 data start after MATLAB's 512-byte header (the user block), and its addresses
    // count from there. hdf5-reader finds such a superblock but takes the addresses from the
    // file's start, so it is handed the bytes from the superblock on.
    let size = std::fs::metadata(path).map_err(|e| Error::io(path, e))?.len();
    crate::limits::check_memory(size as f64, "the .mat file").map_err(|m| invalid(path, m))?;
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    const SIGNATURE: &[u8] = b"\x89HDF\r\n\x1a\n";
    let start = std::iter::once(0)
        .chain((0..).map(|k| 512usize << k))
        .take_while(|&at| at + SIGNATURE.len() <= bytes.len())
        .find(|&at| &bytes[at..at + SIGNATURE.len()] == SIGNATURE)
        .ok_or_else(|| invalid(path, "a MAT 7.3 header, but no HDF5 superblock after it"))?;
    let file = hdf5_reader::Hdf5File::from_vec(bytes[start..].to_vec()).map_err(|e| h5("opening it", e))?;
    let mut vars = BTreeMap::new();
    let root = file.root_group().map_err(|e| h5("opening its root group", e))?;
    // Each wanted variable by name: what else the root holds (groups, links) is never read.
    for name in WANTED {
        let ds = match root.dataset(name) {
            Ok(ds) => ds,
            Err(hdf5_reader::error::Error::DatasetNotFound(_)) => continue,
            Err(e) => {
                let what = format!("`{name}` is at the root but is no dataset it can read (expected a dataset, as MATLAB writes each variable; a soft or external link?)");
                return Err(h5(&what, e));
            }
        };
        let class = ds.attribute("MATLAB_class").ok().and_then(|a| a.read_string().ok()).unwrap_or_default();
        let empty = ds.attribute("MATLAB_empty").is_ok();
        let dims: Vec<usize> = ds.shape().iter().rev().map(|&d| d as usize).collect();
        if empty {
            vars.insert(name.to_string(), Variable { dims: vec![0, 0], ..Variable::default() });
            continue;
        }
        let count = ds.num_elements().map_err(|e| h5(name, e))? as usize;
        crate::limits::check_memory(count as f64 * 16.0, &format!("`{name}`")).map_err(|m| invalid(path, m))?;
        let var = match ds.dtype() {
            hdf5_reader::Datatype::Compound { size, fields } => {
                let part = |want: &str| fields.iter().find(|f| f.name == want);
                let (Some(re), Some(im)) = (part("real"), part("imag")) else {
                    return Err(invalid(path, format!("`{name}` is a compound without `real` and `imag`: not a MATLAB complex array")));
                };
                let bytes = ds.read_native_bytes().map_err(|e| h5(name, e))?;
                let size = *size as usize;
                let value = |field: &hdf5_reader::CompoundField, chunk: &[u8]| -> Result<f64> {
                    let o = field.byte_offset as usize;
                    match field.datatype {
                        hdf5_reader::Datatype::FloatingPoint { size: 8, .. } => Ok(f64::from_ne_bytes(chunk[o..o + 8].try_into().expect("8 bytes"))),
                        hdf5_reader::Datatype::FloatingPoint { size: 4, .. } => Ok(f64::from(f32::from_ne_bytes(chunk[o..o + 4].try_into().expect("4 bytes")))),
                        _ => Err(invalid(path, format!("`{name}`: complex parts that are not floating point"))),
                    }
                };
                if size == 0 || bytes.len() != count * size {
                    return Err(invalid(path, format!("`{name}`: {} bytes for {count} values of {size} bytes", bytes.len())));
                }
                let (mut r, mut i) = (Vec::with_capacity(count), Vec::with_capacity(count));
                for chunk in bytes.chunks_exact(size) {
                    r.push(value(re, chunk)?);
                    i.push(value(im, chunk)?);
                }
                Variable { dims, re: r, im: Some(i), text: None }
            }
            _ if class == "char" => {
                let codes = ds.read_array::<u16>().map_err(|e| h5(name, e))?;
                Variable { dims, text: Some(String::from_utf16_lossy(&codes.iter().copied().collect::<Vec<_>>())), ..Variable::default() }
            }
            hdf5_reader::Datatype::FloatingPoint { size: 4, .. } => {
                let values = ds.read_array::<f32>().map_err(|e| h5(name, e))?;
                Variable { dims, re: values.iter().map(|&x| f64::from(x)).collect(), im: None, text: None }
            }
            hdf5_reader::Datatype::FloatingPoint { .. } => {
                let values = ds.read_array::<f64>().map_err(|e| h5(name, e))?;
                Variable { dims, re: values.iter().copied().collect(), im: None, text: None }
            }
            other => return Err(invalid(path, format!("`{name}` is stored as {other:?}: expected floating-point numbers (MATLAB double or single)"))),
        };
        vars.insert(name.to_string(), var);
    }
    Ok(vars)
}
