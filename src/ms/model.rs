//! The writer's `model_column`: the final model's visibilities, predicted with the imaging
//! operator's degridder, into a column of the MS the job was read from.
//!
//! Atomicity: the MS is copied to a hidden sibling directory (`.NAME.r2d2-model-PID`; reflinked
//! where the file system can), the column is written and flushed there, the copy's files are
//! synced, and the two directories are exchanged in one `renameat2(RENAME_EXCHANGE)` (Linux;
//! elsewhere two renames, with a moment in which the MS path is absent). So at every instant
//! the MS path holds either the untouched MS or the complete new one; a failure or an
//! interruption before the exchange leaves the original as it was (and at most the hidden copy,
//! removed on failure; after a kill, by the next model write to the same MS). The price: free disk
//! space for one copy of the MS while writing. A linked MS is updated where it lies (the link
//! stays a link), its directories keep their modes, what the write leaves unchanged keeps its
//! links, hard links and times (`copy.rs`), and other writers of the MS are waited for or
//! refused (`lock.rs`).

use super::{invalid, open_table, MsError, MsReader, Origin, TempDir, Window};
use crate::nufft::NufftParams;
use crate::operator::{predict, ImageGeometry, WTermMode};
use crate::vis::{DEFAULT_BATCH_ROWS, SPEED_OF_LIGHT};
use crate::{Error, Result};
use casacure::record::{ArrayData, ArrayValue, DataType, RecordValue};
use casacure::WritableTable;
use num_complex::Complex64;
use std::path::{Path, PathBuf};

/// What to predict and where.
pub struct ModelTarget<'a> {
    /// The column to write (`MODEL_DATA`), created when missing.
    pub column: &'a str,
    pub geometry: ImageGeometry,
    /// The model image, Jy/pixel, row-major `N x N`.
    pub model: &'a [f64],
    pub nufft: NufftParams,
    /// Whether the prediction includes the w-term (as the images it came from did).
    pub w_term: WTermMode,
    pub threads: usize,
}

/// What was written: samples predicted, and samples left zero because their baseline lies
/// beyond the image's Nyquist limit (only flagged samples can: kept ones were imaged).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ModelReport {
    pub rows: u64,
    pub samples: u64,
    pub beyond_nyquist: u64,
}

/// `.NAME.r2d2-model-` beside the MS: the prefix of its staging copies.
fn staging_prefix(ms: &Path) -> Result<(PathBuf, String)> {
    let name = ms.file_name().ok_or_else(|| invalid(ms, "a MeasurementSet path must name a directory"))?;
    let parent = ms.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    Ok((parent.to_path_buf(), format!(".{}{}", name.to_string_lossy(), super::lock::COPY_INFIX)))
}

fn staging_path(ms: &Path) -> Result<PathBuf> {
    let (parent, prefix) = staging_prefix(ms)?;
    Ok(parent.join(format!("{prefix}{}", std::process::id())))
}

/// Removes staging copies left by killed writers (their process no longer runs), so a kill
/// costs disk space only until the next model write to the same MS.
fn remove_stale_staging(ms: &Path) {
    let Ok((parent, prefix)) = staging_prefix(ms) else { return };
    super::lock::remove_left_by_dead_processes(&parent, &prefix, "model write");
}

/// Gives the directories of the copy the modes of the original's (files keep theirs through
/// the copy), so that a rewritten MS is shared as the original was.
fn copy_modes(from: &Path, to: &Path) -> Result<()> {
    for entry in std::fs::read_dir(from).map_err(|e| Error::io(from, e))? {
        let entry = entry.map_err(|e| Error::io(from, e))?;
        if entry.file_type().map_err(|e| Error::io(entry.path(), e))?.is_dir() && to.join(entry.file_name()).is_dir() {
            copy_modes(&entry.path(), &to.join(entry.file_name()))?;
        }
    }
    let mode = std::fs::metadata(from).map_err(|e| Error::io(from, e))?.permissions();
    std::fs::set_permissions(to, mode).map_err(|e| Error::io(to, e))
}

/// fsync of every file and directory of a tree, so the exchange publishes complete data.
/// Links are not followed: what they name is not part of the copy (and may hold it).
fn sync_tree(dir: &Path) -> Result<()> {
    for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        let (path, kind) = (entry.path(), entry.file_type().map_err(|e| Error::io(entry.path(), e))?);
        if kind.is_dir() {
            sync_tree(&path)?;
        } else if kind.is_file() {
            std::fs::File::open(&path).and_then(|f| f.sync_all()).map_err(|e| Error::io(&path, e))?;
        }
    }
    std::fs::File::open(dir).and_then(|f| f.sync_all()).map_err(|e| Error::io(dir, e))
}

/// Swaps two directories: atomically on Linux, else by two renames.
pub(super) fn exchange(a: &Path, b: &Path) -> Result<()> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use std::ffi::CString;
        use std::os::unix::ffi::OsStrExt;
        let c = |p: &Path| CString::new(p.as_os_str().as_bytes()).map_err(|_| invalid(p, "path contains a NUL byte"));
        let (ca, cb) = (c(a)?, c(b)?);
        // SAFETY: both pointers are valid NUL-terminated strings that outlive the call, and
        // AT_FDCWD resolves relative paths against the working directory, as std does.
        let rc = unsafe { libc::renameat2(libc::AT_FDCWD, ca.as_ptr(), libc::AT_FDCWD, cb.as_ptr(), libc::RENAME_EXCHANGE) };
        if rc == 0 {
            return Ok(());
        }
        let e = std::io::Error::last_os_error();
        // File systems without RENAME_EXCHANGE answer EINVAL; fall back to renames.
        if e.raw_os_error() != Some(libc::EINVAL) && e.raw_os_error() != Some(libc::ENOSYS) {
            return Err(Error::io(a, e));
        }
    }
    let aside = a.with_extension("r2d2-old");
    std::fs::rename(b, &aside).map_err(|e| Error::io(b, e))?;
    std::fs::rename(a, b).map_err(|e| Error::io(a, e))?;
    std::fs::rename(&aside, a).map_err(|e| Error::io(&aside, e))
}

/// Predicts `target.model` into `target.column` of the MS `origin` names, for the rows and
/// channels of its selection (other rows keep their contents; a new column has zeros there,
/// in every row).
/// Correlations that carry Stokes I (XX and YY, RR and LL, or I) get the model's visibility,
/// the others zero: the model is unpolarised.
pub fn write_model_column(origin: &Origin, target: &ModelTarget<'_>) -> Result<ModelReport> {
    let ms = origin.path.as_path();
    if let Some(split) = &origin.split {
        return Err(Error::parameter(
            "model_column",
            format!(
                "{}: the job is one part of the MS split by `{split}`; a model column holds one model per MS field, so split by `field` or not at all",
                ms.display()
            ),
        ));
    }
    if target.model.len() != target.geometry.pixels() {
        return Err(Error::parameter("model", format!("{} pixels for a {} x {} image", target.model.len(), target.geometry.size, target.geometry.size)));
    }
    super::lock::check_model_column_name(ms, target.column, &origin.selection.data_column)?;
    // From here until the exchange, no other writer of this MS starts (or the write is refused).
    let lock = super::lock::lock_for_model_write(ms, target.column)?;
    let real = lock.ms.as_path();
    remove_stale_staging(real);
    let staging = TempDir { path: staging_path(real)? };
    if staging.path.exists() {
        std::fs::remove_dir_all(&staging.path).map_err(|e| Error::io(&staging.path, e))?;
    }
    let started = std::time::SystemTime::now();
    super::copy::copy_tree(real, &staging.path)?;
    let report = predict_into(&staging.path, origin, target).map_err(|e| retarget(e, &staging.path, ms))?;
    // The write is done: what it left unchanged becomes the original's again (files linked,
    // links made links, times kept).
    super::copy::restore(real, &staging.path, started);
    copy_modes(real, &staging.path)?;
    sync_tree(&staging.path)?;
    // Checks the written copy opens as a table before it replaces the original.
    open_table(&staging.path, "the MeasurementSet with the new model column").map_err(|e| retarget(e, &staging.path, ms))?;
    if std::env::var_os(crate::staging::KILL_BEFORE_MS_EXCHANGE).is_some() {
        crate::staging::kill_this_process();
    }
    exchange(&staging.path, real)?;
    drop(lock);
    // `staging` now names the old MS: dropping it removes that.
    Ok(report)
}

/// Errors about the staging copy name the MS the user gave.
fn retarget(error: Error, staging: &Path, ms: &Path) -> Error {
    match error {
        Error::Input { path, message } => Error::Input { path: swap_prefix(&path, staging, ms), message },
        Error::Io { path, source } => Error::Io { path: swap_prefix(&path, staging, ms), source },
        Error::Ms(mut e) => {
            let path = e.path_mut();
            *path = swap_prefix(path, staging, ms);
            Error::Ms(e)
        }
        other => other,
    }
}

fn swap_prefix(path: &Path, from: &Path, to: &Path) -> PathBuf {
    path.strip_prefix(from).map(|rest| to.join(rest)).unwrap_or_else(|_| path.to_path_buf())
}

fn write_error<E: std::error::Error + Send + Sync + 'static>(ms: &Path, column: &str, e: E) -> Error {
    MsError::Table { path: ms.to_path_buf(), what: format!("column `{column}`: writing"), source: Box::new(e) }.into()
}

fn predict_into(ms: &Path, origin: &Origin, target: &ModelTarget<'_>) -> Result<ModelReport> {
    let mut selection = origin.selection.clone();
    selection.field = Some(super::FieldSelector::Id(origin.field_id));
    let reader = MsReader::open(ms, &selection, DEFAULT_BATCH_ROWS)?;
    let layout = reader.layout.clone();
    drop(reader);
    let column = target.column;
    let (table, mut writable) = super::casacore(ms, "cannot open the MeasurementSet for writing", || {
        WritableTable::open_for_update(ms)
    })?;
    let names = table.colnames();
    let uvw_col = super::column_index(&table, ms, "UVW")?;
    let field_col = super::column_index(&table, ms, "FIELD_ID")?;
    let dd_col = super::column_index(&table, ms, "DATA_DESC_ID")?;
    let data_col = super::column_index(&table, ms, &selection.data_column)?;
    let desc = &table.dat.desc.columns;
    let (model_col, existed) = match names.iter().position(|c| c == column) {
        Some(i) => {
            super::lock::check_takes_a_model(ms, &desc[i])?;
            (i, true)
        }
        None => {
            // Checked before the imaging too; an MS changed since then fails here, naming why.
            let new = super::lock::new_model_column(&desc[data_col], column);
            if let Some(why) = super::casacore(ms, &format!("column `{column}`: adding"), || casacure::table::add_column_obstacle(ms, &new))? {
                return Err(invalid(ms, format!("cannot write `{column}`: {why}")));
            }
            writable.addcol(new);
            (names.len(), false)
        }
    };
    let double = existed && matches!(desc[model_col].data_type, DataType::DComplex);
    let nrows = table.nrows();
    let mut report = ModelReport::default();
    let chunk = 1u64 << 14;
    for start in (0..nrows).step_by(chunk as usize) {
        let n = chunk.min(nrows - start);
        let cells = |col: usize, name: &str| super::read_cells(&table, ms, col, name, start, n);
        let uvw = cells(uvw_col, "UVW")?;
        let field = cells(field_col, "FIELD_ID")?;
        let dd = cells(dd_col, "DATA_DESC_ID")?;
        let old = if existed { Some(cells(model_col, column)?) } else { None };
        // A new column gets every row's cell, zeros outside the selection, shaped as the
        // data column's there: readers (casacore's getcol, WSClean, DP3) take a row without
        // a full cell for a broken column.
        let new_column = !existed;
        // The selected rows of the chunk, their window, and their samples' (u, v, w).
        let mut rows: Vec<(u64, &Window)> = Vec::new();
        let (mut us, mut vs, mut ws, mut inside) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for r in 0..n as usize {
            let window = super::as_i64(&dd[r])
                .and_then(|d| usize::try_from(d).ok())
                .and_then(|d| layout.windows.get(d))
                .and_then(Option::as_ref)
                .filter(|_| super::as_i64(&field[r]) == Some(layout.field_id as i64));
            let Some(window) = window else {
                if new_column {
                    // One row's data cell at a time: only its shape is needed, and a chunk of
                    // wide-band rows would be gigabytes.
                    let row = start + r as u64;
                    let data = super::read_cells(&table, ms, data_col, &selection.data_column, row, 1)?;
                    match data.first() {
                        // An undefined data cell (no shape) stays undefined in the model too.
                        Some(RecordValue::Array(a)) if !a.shape.is_empty() => {
                            let zeros = ArrayData::Complex(vec![(0.0f32, 0.0f32); a.shape.iter().map(|&d| d as usize).product()]);
                            writable.putcell(model_col, row, RecordValue::Array(ArrayValue { shape: a.shape.clone(), data: zeros })).map_err(|e| write_error(ms, column, e))?;
                        }
                        Some(RecordValue::Array(_)) => {}
                        _ => return Err(invalid(ms, format!("column `{}` at row {row}: expected an array cell", selection.data_column))),
                    }
                }
                continue;
            };
            let [u, v, w] = super::array_f64(&uvw[r])
                .and_then(|(_, values)| <[f64; 3]>::try_from(values).ok())
                .ok_or_else(|| invalid(ms, format!("column `UVW` at row {}: expected 3 numbers", start + r as u64)))?;
            for channel in window.channels.clone() {
                let per_metre = window.frequencies[channel] / SPEED_OF_LIGHT;
                let (u, v) = (u * per_metre, v * per_metre);
                let limit = 0.5 / target.geometry.pixel_rad;
                let ok = u.abs() < limit && v.abs() < limit && u.is_finite() && v.is_finite() && w.is_finite();
                inside.push(ok);
                if ok {
                    us.push(u);
                    vs.push(v);
                    ws.push(w * per_metre);
                } else {
                    report.beyond_nyquist += 1;
                }
            }
            rows.push((start + r as u64, window));
        }
        let predicted = predict(target.geometry, &us, &vs, &ws, target.model, target.w_term, target.nufft, target.threads)?;
        let mut next = predicted.into_iter();
        let mut flags = inside.into_iter();
        for (row, window) in rows {
            let shape = [window.frequencies.len() as u32, window.ncorr as u32];
            let mut cell = vec![(0.0f64, 0.0f64); window.frequencies.len() * window.ncorr];
            if let Some(old) = &old {
                // Channels outside the selection keep what the column held.
                match &old[(row - start) as usize] {
                    RecordValue::Array(a) if a.shape == shape => match &a.data {
                        ArrayData::Complex(v) => cell = v.iter().map(|&(re, im)| (f64::from(re), f64::from(im))).collect(),
                        ArrayData::DComplex(v) => cell.clone_from(v),
                        _ => {}
                    },
                    _ => {}
                }
            }
            for channel in window.channels.clone() {
                let value = if flags.next().unwrap_or(false) { next.next().unwrap_or_default() } else { Complex64::default() };
                for k in 0..window.ncorr {
                    cell[channel * window.ncorr + k] = if window.stokes.carries_i(k) { (value.re, value.im) } else { (0.0, 0.0) };
                }
                report.samples += 1;
            }
            let data = if double {
                ArrayData::DComplex(cell)
            } else {
                ArrayData::Complex(cell.into_iter().map(|(re, im)| (re as f32, im as f32)).collect())
            };
            let value = RecordValue::Array(ArrayValue { shape: shape.to_vec(), data });
            writable.putcell(model_col, row, value).map_err(|e| write_error(ms, column, e))?;
            report.rows += 1;
        }
        // One flush per chunk keeps the write buffer at a chunk, not the column.
        super::casacore(ms, &format!("column `{column}`: writing"), || writable.flush())?;
    }
    if report.rows == 0 {
        return Err(invalid(ms, format!("no rows of field {} in the selected windows: nothing to write to `{column}`", layout.field_id)));
    }
    Ok(report)
}

