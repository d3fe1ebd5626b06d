//! Sharing a MeasurementSet with other programs while a model column is written into it.
//!
//! The model write replaces the MS directory by an updated copy (`model.rs`), so two guards
//! keep what others hold:
//!
//! - r2d2's own writers of one MS take turns on an exclusive `flock` of a sibling file
//!   `.NAME.r2d2-lock` (a lock inside the MS would not outlive the exchange of directories),
//!   and each copies the MS only once it has its turn, so it starts from the other's result;
//! - other casacore programs (CASA, python-casacore, DP3, WSClean) announce an open table by
//!   `fcntl` locks on its `table.lock`. While one holds any, the table is in use and a rewrite
//!   would be lost when that program writes its view back: the write is refused, naming the
//!   process. For the length of the write r2d2 holds a write lock there itself (an
//!   open-file-description lock, which casacore's locks see and which the copy's own reading
//!   of the file does not release), so they wait for it in turn.
//!
//! Which column may take a model is decided here too: never the data the image was made from
//! nor the observed or calibrated data.

use super::invalid;
use crate::{Error, Result};
use std::fs::File;
use std::path::{Path, PathBuf};

/// Columns that hold what was observed or calibrated: a model must never replace them.
const DATA_COLUMNS: [&str; 2] = ["DATA", "CORRECTED_DATA"];

/// Held while an MS is rewritten (a model column written, or the MS replaced by a
/// conversion): r2d2's turn on the MS and a write lock on its `table.lock`. Dropping it
/// releases both.
pub struct MsWriteLock {
    /// The MS itself, links resolved: the directory that is exchanged.
    pub ms: PathBuf,
    // Field order is drop order: the table lock goes first, then the turn (its file removed).
    _table_lock: Option<File>,
    _turn: Turn,
}

/// The directory an MS path names, links resolved: a model write replaces that directory,
/// not the link to it.
pub fn real_path(ms: &Path) -> Result<PathBuf> {
    ms.canonicalize().map_err(|e| Error::io(ms, e))
}

/// Whether `column` may receive a model of an MS imaged from `data_column`.
pub fn check_model_column_name(ms: &Path, column: &str, data_column: &str) -> Result<()> {
    let upper = column.trim().to_ascii_uppercase();
    if upper == data_column.trim().to_ascii_uppercase() {
        return Err(invalid(ms, format!("cannot write the model into `{column}`: it is the data column the image is made from (choose MODEL_DATA)")));
    }
    if DATA_COLUMNS.contains(&upper.as_str()) {
        return Err(invalid(ms, format!("cannot write the model into `{column}`: it holds observed or calibrated visibilities, which the model would replace (choose MODEL_DATA)")));
    }
    // A name other programs can use: casacore's TaQL, CASA and DP3 take letters, digits and
    // underscores, starting with a letter or an underscore.
    let plain = column.chars().next().is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && column.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        && column.len() <= MAX_COLUMN_NAME;
    if !plain {
        return Err(invalid(
            ms,
            format!("cannot write the model into `{column}`: expected a column name of letters, digits and underscores, starting with a letter, at most {MAX_COLUMN_NAME} characters (such as MODEL_DATA)"),
        ));
    }
    Ok(())
}

/// The longest model column name taken (casacore has no limit; no MS column comes near it).
const MAX_COLUMN_NAME: usize = 64;

/// Removes the directories `<prefix><pid>` in `parent` that a process of this user left when
/// it was killed part-way (`left_by`: "model write", "conversion"), so that a kill costs disk
/// space only until the next such run beside the same MS. One whose process still runs
/// (perhaps another r2d2 at its work), of another user, or not a directory is left alone.
pub(super) fn remove_left_by_dead_processes(parent: &Path, prefix: &str, left_by: &str) {
    let Ok(entries) = std::fs::read_dir(parent) else { return };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = name.strip_prefix(prefix).and_then(|p| p.parse::<u32>().ok()) else { continue };
        let Ok(metadata) = std::fs::symlink_metadata(entry.path()) else { continue };
        if pid == std::process::id() || !metadata.is_dir() || !owned_by_this_user(&metadata) || process_runs(pid) {
            continue;
        }
        log::info!("removing {} left by an interrupted {left_by}", entry.path().display());
        let _ = std::fs::remove_dir_all(entry.path());
    }
}

#[cfg(unix)]
fn owned_by_this_user(metadata: &std::fs::Metadata) -> bool {
    use std::os::unix::fs::MetadataExt;
    // SAFETY: geteuid(2) takes nothing and cannot fail.
    metadata.uid() == unsafe { libc::geteuid() }
}

#[cfg(not(unix))]
fn owned_by_this_user(_metadata: &std::fs::Metadata) -> bool {
    false
}

/// Whether process `pid` runs (where that cannot be told, it is taken to).
#[cfg(unix)]
fn process_runs(pid: u32) -> bool {
    let Some(pid) = libc::pid_t::try_from(pid).ok().filter(|&p| p > 0) else { return true };
    // SAFETY: kill(2) with signal 0 sends nothing, only checks; it takes and returns integers.
    let checked = unsafe { libc::kill(pid, 0) };
    // EPERM: the process runs, as another user.
    checked == 0 || std::io::Error::last_os_error().raw_os_error() != Some(libc::ESRCH)
}

#[cfg(not(unix))]
fn process_runs(_pid: u32) -> bool {
    true
}

/// Bytes in one file name (NAME_MAX of Linux's and macOS's file systems).
const NAME_MAX: usize = 255;
/// What names the model write's copy of `NAME`: `.NAME.r2d2-model-PID` beside it.
pub(super) const COPY_INFIX: &str = ".r2d2-model-";
/// Digits of the longest pid: Linux's PID_MAX_LIMIT (4194304), elsewhere a u32's.
const PID_DIGITS: usize = if cfg!(target_os = "linux") { 7 } else { 10 };
/// Bytes the copy's name adds to the MS's: the dot, the infix and the longest pid.
const COPY_NAME_EXTRA: usize = 1 + COPY_INFIX.len() + PID_DIGITS;
/// What names r2d2's turn on `NAME`: `.NAME.r2d2-lock` beside it.
const TURN_SUFFIX: &str = ".r2d2-lock";

/// Refuses an MS whose name leaves no room for the files r2d2 makes beside it (`extra` bytes
/// more than its name): found before any work, not when the lock or the copy is made.
fn check_name_room(ms: &Path, real: &Path, doing: &str, extra: usize) -> Result<()> {
    let name = real.file_name().map_or(0, |n| n.len());
    if name + extra <= NAME_MAX {
        return Ok(());
    }
    let linked = std::fs::symlink_metadata(ms).is_ok_and(|m| m.file_type().is_symlink());
    let shown = if linked { format!(" (the MeasurementSet it links to, {})", real.display()) } else { String::new() };
    Err(invalid(
        ms,
        format!(
            "cannot {doing}: the MeasurementSet's name{shown} has {name} bytes, more than the {} allowed: the write works beside it in `.NAME{COPY_INFIX}PID` and `.NAME{TURN_SUFFIX}`, whose names must fit the file system's {NAME_MAX} bytes; rename the MeasurementSet",
            NAME_MAX - extra
        ),
    ))
}

/// Everything about a model write that can be checked before imaging: the column, that the MS
/// and the directory holding it are writable, that its name leaves room for the copy beside
/// it, that it holds nothing the copy cannot copy (a FIFO), and that no other program has the
/// MS open.
pub fn check_model_write(ms: &Path, column: &str, data_column: &str) -> Result<()> {
    check_model_column_name(ms, column, data_column)?;
    let real = real_path(ms)?;
    check_name_room(ms, &real, &format!("write `{column}`"), COPY_NAME_EXTRA)?;
    super::copy::check_entries(&real).map_err(|e| match e {
        // Named as the user named the MS, not by its resolved path.
        Error::Ms(super::MsError::Invalid { path, message }) => {
            let shown = path.strip_prefix(&real).map(|rest| ms.join(rest)).unwrap_or(path);
            invalid(shown, format!("cannot write `{column}`: {}", message.replace(&real.display().to_string(), &ms.display().to_string())))
        }
        other => other,
    })?;
    let parent = real.parent().unwrap_or(Path::new("/"));
    for dir in [real.as_path(), parent] {
        if !writable(dir) {
            let role = if dir == real { "the MeasurementSet" } else { "the directory holding the MeasurementSet (the updated copy is made there)" };
            return Err(invalid(ms, format!("cannot write `{column}`: {role} ({}) is not writable", dir.display())));
        }
    }
    if let Some(pid) = foreign_lock(&real)? {
        return Err(in_use(ms, &format!("write `{column}`"), pid));
    }
    check_column_can_be_written(ms, column, data_column)
}

/// An existing column of that name must be a complex array column that casacure can write; a
/// new one must be one the table can add. A layout casacure cannot write is refused here, not
/// after the imaging.
fn check_column_can_be_written(ms: &Path, column: &str, data_column: &str) -> Result<()> {
    let table = super::open_table(ms, "the MeasurementSet's main table")?;
    let columns = &table.dat.desc.columns;
    let obstacle = match columns.iter().find(|c| c.name == column) {
        Some(desc) => {
            check_takes_a_model(ms, desc)?;
            super::casacore(ms, &format!("cannot check that `{column}` can be written"), || casacure::table::write_array_column_obstacle(ms, column))?
        }
        None => {
            // Without the data column the imaging fails first, naming it.
            let Some(data) = columns.iter().find(|c| c.name == data_column) else { return Ok(()) };
            let new = new_model_column(data, column);
            super::casacore(ms, &format!("cannot check that `{column}` can be added"), || casacure::table::add_column_obstacle(ms, &new))?
        }
    };
    match obstacle {
        Some(why) => Err(invalid(ms, format!("cannot write `{column}`: {why}"))),
        None => Ok(()),
    }
}

/// The description of a new model column: shaped as the data column, complex, in a storage
/// manager of its own so the existing data files are not rewritten.
pub(super) fn new_model_column(data: &casacure::tabledesc::ColumnDesc, column: &str) -> casacure::tabledesc::ColumnDesc {
    let mut new = data.clone();
    new.name = column.to_string();
    new.comment = "model visibilities predicted by r2d2".into();
    new.data_type = casacure::record::DataType::Complex;
    new.data_manager_type = "StandardStMan".into();
    new.data_manager_group = format!("R2D2_{column}");
    new
}

/// An existing column takes a model only if it is a complex array column (checked before
/// imaging and again by the write itself).
pub(super) fn check_takes_a_model(ms: &Path, desc: &casacure::tabledesc::ColumnDesc) -> Result<()> {
    use casacure::record::DataType;
    use casacure::tabledesc::ColumnKind;
    if matches!(desc.kind, ColumnKind::Array) && matches!(desc.data_type, DataType::Complex | DataType::DComplex) {
        return Ok(());
    }
    Err(invalid(ms, format!("column `{}` exists but is not a complex array column; cannot write a model into it", desc.name)))
}

/// Takes r2d2's turn on the MS (waiting for another r2d2 writing it), then the write lock on
/// its `table.lock` (refused while another program holds a lock there).
pub fn lock_for_model_write(ms: &Path, column: &str) -> Result<MsWriteLock> {
    lock_for_write(ms, &format!("write `{column}`"))
}

/// The same turn and lock for replacing the whole MS (`r2d2 convert` onto an existing MS):
/// another r2d2 writing it is waited for, another program holding it open refuses.
pub fn lock_for_replacement(ms: &Path) -> Result<MsWriteLock> {
    lock_for_write(ms, "replace it")
}

/// `doing` completes "cannot ..." in the refusal.
fn lock_for_write(ms: &Path, doing: &str) -> Result<MsWriteLock> {
    let real = real_path(ms)?;
    let name = real.file_name().ok_or_else(|| invalid(ms, "a MeasurementSet path must name a directory"))?;
    check_name_room(ms, &real, doing, 1 + TURN_SUFFIX.len())?;
    let turn_path = real.with_file_name(format!(".{}{TURN_SUFFIX}", name.to_string_lossy()));
    // The turn file is removed by its holder when done (no litter beside the MS): a waiter
    // that wakes holding a removed file's lock tries again on the current one.
    let turn = loop {
        let turn = File::options().create(true).truncate(false).read(true).write(true).open(&turn_path).map_err(|e| Error::io(&turn_path, e))?;
        if !flock(&turn, false).map_err(|e| Error::io(&turn_path, e))? {
            log::info!("{}: another r2d2 is writing this MeasurementSet; waiting for it", ms.display());
            flock(&turn, true).map_err(|e| Error::io(&turn_path, e))?;
        }
        if same_open_file(&turn, &turn_path) {
            break turn;
        }
    };
    let turn = Turn { file: turn, path: turn_path };
    let table_lock = lock_table(&real).map_err(|e| match e {
        LockRefused::Held(pid) => in_use(ms, doing, pid),
        LockRefused::Io(path, e) => Error::io(path, e),
    })?;
    Ok(MsWriteLock { ms: real, _table_lock: table_lock, _turn: turn })
}

/// r2d2's turn on an MS: the locked turn file, removed (before the lock goes) when done.
struct Turn {
    file: File,
    path: PathBuf,
}

impl Drop for Turn {
    fn drop(&mut self) {
        if same_open_file(&self.file, &self.path) {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

/// Whether `path` still names the open `file`.
#[cfg(unix)]
fn same_open_file(file: &File, path: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (file.metadata(), std::fs::metadata(path)) {
        (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
        _ => false,
    }
}

#[cfg(not(unix))]
fn same_open_file(_file: &File, path: &Path) -> bool {
    path.exists()
}

fn in_use(ms: &Path, doing: &str, pid: i32) -> Error {
    let who = if pid > 0 { format!("process {pid}") } else { "another program".to_string() };
    invalid(
        ms,
        format!("cannot {doing}: the MeasurementSet is open in {who} (it holds a lock on table.lock, as CASA, python-casacore and DP3 do while a table is open); close it there and run again"),
    )
}

/// What a conversion may replace at `out`: nothing that is an input, and only what it would
/// write itself (an MS for an MS, a file for a file), so that a directory or another kind of
/// file given by mistake is never deleted.
pub fn check_conversion_output(input: &Path, out: &Path, writes_ms: bool) -> Result<()> {
    if let Some(input) = crate::staging::destroys_input(out, &[input]) {
        return Err(invalid(out, format!("the output would replace or lie inside the input {}: choose another output path", input.display())));
    }
    let Ok(meta) = std::fs::symlink_metadata(out) else { return Ok(()) };
    let is_ms = super::is_measurement_set(out);
    let what = if meta.is_dir() { "a directory" } else if meta.file_type().is_symlink() { "a link" } else { "a file" };
    let inside = |name: &str| if meta.is_dir() { format!(", such as {}", out.join(name).display()) } else { String::new() };
    match (writes_ms, is_ms, meta.is_file()) {
        // Refused before the work while another program has it open (checked again, under
        // the lock, when it is replaced); a link is replaced itself, its MS left alone.
        (true, true, _) if meta.file_type().is_symlink() => Ok(()),
        (true, true, _) => match foreign_lock(&real_path(out)?)? {
            Some(pid) => Err(in_use(out, "replace it", pid)),
            None => Ok(()),
        },
        (false, _, true) => Ok(()),
        (true, false, _) => Err(invalid(out, format!("exists and is {what}, not a MeasurementSet: converting replaces only a MeasurementSet (give a new path{})", inside("obs.ms")))),
        (false, _, false) => Err(invalid(out, format!("exists and is {what}: the Parquet table is written as a file, replacing only a file (give a new path{})", inside("obs.parquet")))),
    }
}

#[cfg(unix)]
fn writable(dir: &Path) -> bool {
    use std::os::unix::ffi::OsStrExt;
    let Ok(c) = std::ffi::CString::new(dir.as_os_str().as_bytes()) else { return false };
    // SAFETY: `c` is a valid NUL-terminated path that outlives the call.
    unsafe { libc::access(c.as_ptr(), libc::W_OK) == 0 }
}

#[cfg(not(unix))]
fn writable(dir: &Path) -> bool {
    std::fs::metadata(dir).is_ok_and(|m| !m.permissions().readonly())
}

/// An exclusive `flock`: `Ok(false)` when not waiting and another holds it.
#[cfg(unix)]
fn flock(file: &File, wait: bool) -> std::io::Result<bool> {
    use std::os::fd::AsRawFd;
    let op = libc::LOCK_EX | if wait { 0 } else { libc::LOCK_NB };
    // SAFETY: the descriptor is open for the call's duration (borrowed from `file`).
    let rc = unsafe { libc::flock(file.as_raw_fd(), op) };
    if rc == 0 {
        return Ok(true);
    }
    let e = std::io::Error::last_os_error();
    if !wait && e.raw_os_error() == Some(libc::EWOULDBLOCK) {
        return Ok(false);
    }
    Err(e)
}

#[cfg(not(unix))]
fn flock(_file: &File, _wait: bool) -> std::io::Result<bool> {
    Ok(true)
}

enum LockRefused {
    /// Another process holds a lock on `table.lock` (its pid, or -1 for an open-file lock).
    Held(i32),
    Io(PathBuf, std::io::Error),
}

/// A `struct flock` over the whole file.
#[cfg(target_os = "linux")]
fn whole_file(kind: i32) -> libc::flock {
    // SAFETY: `flock` is plain old data; all-zero is a valid value before the fields are set.
    let mut l: libc::flock = unsafe { std::mem::zeroed() };
    l.l_type = kind as libc::c_short;
    l.l_whence = libc::SEEK_SET as libc::c_short;
    l.l_start = 0;
    l.l_len = 0;
    l
}

/// The process holding a lock on the MS's `table.lock` that a write lock would conflict
/// with, if any (`None` also when the table has no lock file: nobody ever locked it).
#[cfg(target_os = "linux")]
pub fn foreign_lock(ms: &Path) -> Result<Option<i32>> {
    use std::os::fd::AsRawFd;
    let path = ms.join("table.lock");
    let file = match File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(Error::io(&path, e)),
    };
    let mut l = whole_file(libc::F_WRLCK);
    // SAFETY: valid descriptor and a valid, exclusively borrowed `flock` for F_OFD_GETLK.
    let rc = unsafe { libc::fcntl(file.as_raw_fd(), libc::F_OFD_GETLK, &mut l) };
    if rc != 0 {
        return Err(Error::io(&path, std::io::Error::last_os_error()));
    }
    Ok((l.l_type != libc::F_UNLCK as libc::c_short).then_some(l.l_pid))
}

#[cfg(not(target_os = "linux"))]
pub fn foreign_lock(_ms: &Path) -> Result<Option<i32>> {
    Ok(None)
}

/// A write lock over the whole `table.lock` (created when missing, as casacore does), held
/// by the returned file's open description.
#[cfg(target_os = "linux")]
fn lock_table(ms: &Path) -> std::result::Result<Option<File>, LockRefused> {
    use std::os::fd::AsRawFd;
    let path = ms.join("table.lock");
    let file = File::options().create(true).truncate(false).read(true).write(true).open(&path).map_err(|e| LockRefused::Io(path.clone(), e))?;
    let mut l = whole_file(libc::F_WRLCK);
    // SAFETY: valid descriptor and a valid `flock` for F_OFD_SETLK.
    let rc = unsafe { libc::fcntl(file.as_raw_fd(), libc::F_OFD_SETLK, &l) };
    if rc == 0 {
        return Ok(Some(file));
    }
    let e = std::io::Error::last_os_error();
    if matches!(e.raw_os_error(), Some(libc::EAGAIN) | Some(libc::EACCES)) {
        // SAFETY: as above, F_OFD_GETLK fills `l` with the conflicting lock.
        let _ = unsafe { libc::fcntl(file.as_raw_fd(), libc::F_OFD_GETLK, &mut l) };
        return Err(LockRefused::Held(l.l_pid));
    }
    Err(LockRefused::Io(path, e))
}

#[cfg(not(target_os = "linux"))]
fn lock_table(_ms: &Path) -> std::result::Result<Option<File>, LockRefused> {
    Ok(None)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn data_columns_never_take_a_model() {
        let ms = Path::new("obs.ms");
        for (column, data) in [("DATA", "DATA"), ("data", "DATA"), ("CORRECTED_DATA", "DATA"), ("MY_DATA", "my_data")] {
            let e = check_model_column_name(ms, column, data).unwrap_err().to_string();
            assert!(e.contains("cannot write the model") && e.contains("MODEL_DATA"), "{column}: {e}");
        }
        check_model_column_name(ms, "MODEL_DATA", "DATA").unwrap();
        check_model_column_name(ms, "MODEL_DATA", "CORRECTED_DATA").unwrap();
    }

    #[test]
    fn ms_names_leave_room_for_what_a_model_write_makes_beside_them() {
        let most = NAME_MAX - COPY_NAME_EXTRA;
        let ms = |n: usize| PathBuf::from(format!("data/{}", "a".repeat(n)));
        check_name_room(&ms(most), &ms(most), "write `M`", COPY_NAME_EXTRA).unwrap();
        let e = check_name_room(&ms(most + 1), &ms(most + 1), "write `M`", COPY_NAME_EXTRA).unwrap_err().to_string();
        assert!(e.contains(&format!("has {} bytes, more than the {most} allowed", most + 1)) && e.contains("cannot write `M`"), "{e}");
        // The copy's name with the longest pid, and the turn's, fit at the limit.
        assert!(format!(".{}{COPY_INFIX}{}", "a".repeat(most), "9".repeat(PID_DIGITS)).len() <= NAME_MAX);
        assert!(format!(".{}{TURN_SUFFIX}", "a".repeat(most)).len() <= NAME_MAX);
    }

    #[test]
    fn a_lock_held_elsewhere_on_table_lock_is_seen_and_refuses_the_write() {
        let dir = tempfile::tempdir().unwrap();
        let ms = dir.path().join("t.ms");
        std::fs::create_dir(&ms).unwrap();
        assert_eq!(foreign_lock(&ms).unwrap(), None, "no table.lock: nobody holds it");
        let held = lock_for_model_write(&ms, "MODEL_DATA").unwrap();
        // Another open description (as another process would have) sees the write lock.
        assert!(foreign_lock(&ms).unwrap().is_some());
        let e = lock_table(&ms).err().expect("a second write lock is refused");
        assert!(matches!(e, LockRefused::Held(_)));
        drop(held);
        assert_eq!(foreign_lock(&ms).unwrap(), None);
    }
}
