//! The copy of an MS that a model write works in (`model.rs`), made so that what the write
//! does not change comes back as it was.
//!
//! - Files are copied with their modification and access times.
//! - A link to a file or directory outside the MS is copied as what it names, so that the
//!   write never writes through it into the original before the exchange. A link to nothing,
//!   to a place inside the MS, or to a directory holding the MS (whose copy would hold the MS
//!   again) is copied as the link it is.
//! - Anything else (a FIFO, a socket, a device) is refused, before imaging by
//!   [`check_entries`]: copying would open it, and opening a FIFO waits for a writer for ever.
//!
//! After the write, [`restore`] compares the copy with the original. A file the write left
//! unchanged becomes a hard link to the original file again, so it keeps its inode, its other
//! links, its times and its owner (the write is over by then: nothing writes through the link,
//! and the exchange then retires the original's directory entries only). A copied outside link
//! whose copy is unchanged becomes the link again. A directory whose entries are all unchanged
//! takes back its modification time. What the write changed stays a copy, and a link it changed
//! is reported.

use super::invalid;
use crate::{Error, Result};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

/// How an entry of the MS is copied.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    File,
    Dir,
    /// A link copied as the link it is (to nothing, inside the MS, or to a directory holding a
    /// directory being copied).
    Link,
    /// A link to a file or directory outside the MS: the copy holds what it names.
    LinkedFile,
    LinkedDir,
}

/// How `path` is copied: `root` is the MS (canonical), `copying` the canonical directories
/// being copied around it (a link to one of them or to a directory holding one is kept as a
/// link: following it would copy for ever). Anything but files, directories and links to them
/// is an error naming it.
fn kind_of(root: &Path, copying: &[PathBuf], path: &Path) -> Result<Kind> {
    let meta = std::fs::symlink_metadata(path).map_err(|e| Error::io(path, e))?;
    let kind = meta.file_type();
    if kind.is_dir() {
        return Ok(Kind::Dir);
    }
    if kind.is_file() {
        return Ok(Kind::File);
    }
    if !kind.is_symlink() {
        return Err(not_copied(root, path, &kind, None));
    }
    // A link to nothing (or a loop of links) is no file to copy.
    let Ok(target) = path.canonicalize() else { return Ok(Kind::Link) };
    if target.starts_with(root) || copying.iter().any(|dir| dir.starts_with(&target)) {
        return Ok(Kind::Link);
    }
    let meta = std::fs::metadata(&target).map_err(|e| Error::io(path, e))?;
    match meta.file_type() {
        t if t.is_dir() => Ok(Kind::LinkedDir),
        t if t.is_file() => Ok(Kind::LinkedFile),
        t => Err(not_copied(root, path, &t, Some(&target))),
    }
}

/// The error for an entry that is neither a file, a directory nor a link to one.
fn not_copied(root: &Path, path: &Path, kind: &std::fs::FileType, target: Option<&Path>) -> Error {
    #[cfg(unix)]
    let what = {
        use std::os::unix::fs::FileTypeExt;
        if kind.is_fifo() {
            "a FIFO (named pipe)"
        } else if kind.is_socket() {
            "a socket"
        } else if kind.is_block_device() || kind.is_char_device() {
            "a device"
        } else {
            "neither a file nor a directory"
        }
    };
    #[cfg(not(unix))]
    let what = {
        let _ = kind;
        "neither a file nor a directory"
    };
    let via = target.map(|t| format!(" (through a link to {})", t.display())).unwrap_or_default();
    invalid(
        path,
        format!(
            "{what}{via} inside the MeasurementSet {}: an MS holds files, directories and links to them, and a model write copies the MS but cannot copy this (nor open it: a FIFO waits for a writer for ever); move it out of the MS",
            root.display()
        ),
    )
}

/// Calls `visit` on every entry under `dir` (its path and its path relative to the MS),
/// a directory before what it holds, going into directories and linked outside directories.
fn walk(root: &Path, copying: &mut Vec<PathBuf>, dir: &Path, rel: &Path, visit: &mut dyn FnMut(&Path, &Path, Kind) -> Result<()>) -> Result<()> {
    let mut entries: Vec<_> = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.collect::<std::io::Result<_>>().map_err(|e| Error::io(dir, e))?;
    entries.sort_by_key(|e| e.file_name());
    for entry in entries {
        let (path, rel) = (entry.path(), rel.join(entry.file_name()));
        let kind = kind_of(root, copying, &path)?;
        visit(&path, &rel, kind)?;
        if matches!(kind, Kind::Dir | Kind::LinkedDir) {
            copying.push(path.canonicalize().map_err(|e| Error::io(&path, e))?);
            walk(root, copying, &path, &rel, visit)?;
            copying.pop();
        }
    }
    Ok(())
}

/// Refuses, before any work, an MS a model write could not copy: one holding (or linking to)
/// a FIFO, a socket or a device. `ms` is the MS, links resolved.
pub(super) fn check_entries(ms: &Path) -> Result<()> {
    let root = ms.canonicalize().map_err(|e| Error::io(ms, e))?;
    walk(&root, &mut vec![root.clone()], &root, Path::new(""), &mut |_, _, _| Ok(()))
}

/// Copies the MS `from` (links resolved) to the new directory `to` as the module
/// documentation says.
pub(super) fn copy_tree(from: &Path, to: &Path) -> Result<()> {
    let root = from.canonicalize().map_err(|e| Error::io(from, e))?;
    std::fs::create_dir(to).map_err(|e| Error::io(to, e))?;
    walk(&root, &mut vec![root.clone()], &root, Path::new(""), &mut |path, rel, kind| {
        let target = to.join(rel);
        match kind {
            Kind::Dir | Kind::LinkedDir => std::fs::create_dir(&target).map_err(|e| Error::io(&target, e)),
            Kind::File | Kind::LinkedFile => copy_file(path, &target),
            Kind::Link => copy_link(path, &target),
        }
    })
}

/// Copies a file (through a link: the file it names) with its times.
fn copy_file(from: &Path, to: &Path) -> Result<()> {
    std::fs::copy(from, to).map_err(|e| Error::io(from, e))?;
    let meta = std::fs::metadata(from).map_err(|e| Error::io(from, e))?;
    let mut times = std::fs::FileTimes::new();
    if let Ok(t) = meta.modified() {
        times = times.set_modified(t);
    }
    if let Ok(t) = meta.accessed() {
        times = times.set_accessed(t);
    }
    // Setting given times needs ownership, not write access: the copy may be read-only.
    std::fs::File::open(to).and_then(|f| f.set_times(times)).map_err(|e| Error::io(to, e))
}

/// Makes `to` a link with the same target text as the link `from`.
fn copy_link(from: &Path, to: &Path) -> Result<()> {
    let target = std::fs::read_link(from).map_err(|e| Error::io(from, e))?;
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(&target, to).map_err(|e| Error::io(to, e))
    }
    #[cfg(not(unix))]
    {
        let _ = target;
        copy_file(from, to)
    }
}

/// How long before the copy began a file must have been last modified for an equal
/// modification time in the copy to show that the write did not touch it: a write sets the
/// time to now, and some file systems keep times to a second or two only. Files modified more
/// recently are compared byte for byte.
const TIME_RESOLUTION: Duration = Duration::from_secs(2);

/// After the write into `copy`: puts back what it left unchanged of `original`, as the module
/// documentation says; `started` is when the copy began. Best effort: where something cannot
/// be put back, the copy (a complete, correct MS) keeps its own file.
pub(super) fn restore(original: &Path, copy: &Path, started: SystemTime) {
    let Ok(root) = original.canonicalize() else { return };
    let before = started.checked_sub(TIME_RESOLUTION).unwrap_or(SystemTime::UNIX_EPOCH);
    restore_dir(&root, &mut vec![root.clone()], &root, copy, before, true);
}

/// Compares (and with `apply`, restores) the directory `copy` against `original`; whether
/// every entry of it is unchanged.
fn restore_dir(root: &Path, copying: &mut Vec<PathBuf>, original: &Path, copy: &Path, before: SystemTime, apply: bool) -> bool {
    let Ok(entries) = std::fs::read_dir(original).and_then(|d| d.collect::<std::io::Result<Vec<_>>>()) else { return false };
    let in_copy = std::fs::read_dir(copy).map(|d| d.count()).unwrap_or(0);
    let mut unchanged = in_copy == entries.len();
    for entry in entries {
        let (path, copied) = (entry.path(), copy.join(entry.file_name()));
        let Ok(kind) = kind_of(root, copying, &path) else {
            unchanged = false;
            continue;
        };
        let same = match kind {
            Kind::Link => std::fs::read_link(&path).ok().is_some_and(|t| std::fs::read_link(&copied).ok() == Some(t)),
            Kind::File | Kind::LinkedFile => same_file_content(&path, &copied, before),
            Kind::Dir | Kind::LinkedDir => {
                let Ok(canonical) = path.canonicalize() else {
                    unchanged = false;
                    continue;
                };
                copying.push(canonical);
                // A copied outside directory becomes the link again only if all of it is
                // unchanged; otherwise what is unchanged inside it is put back.
                let same = restore_dir(root, copying, &path, &copied, before, apply && kind == Kind::Dir);
                if !same && apply && kind == Kind::LinkedDir {
                    restore_dir(root, copying, &path, &copied, before, true);
                }
                copying.pop();
                if same && apply && kind == Kind::Dir {
                    set_modified(&path, &copied);
                }
                same
            }
        };
        unchanged &= same;
        if !apply {
            continue;
        }
        match kind {
            Kind::File if same => relink(&path, &copied),
            Kind::LinkedFile | Kind::LinkedDir if same => link_again(&path, &copied),
            Kind::LinkedFile | Kind::LinkedDir => log::warn!(
                "{}: a link to {}, which the model write changed: the MeasurementSet now holds its own copy there (the linked {} is left as it was)",
                path.display(),
                std::fs::read_link(&path).map(|t| t.display().to_string()).unwrap_or_default(),
                if kind == Kind::LinkedDir { "directory" } else { "file" },
            ),
            _ => {}
        }
    }
    unchanged
}

/// Whether the copy `copy` of the file `original` (links followed) still holds what the
/// original does: the same length and, for a file last modified before `before`, the same
/// modification time (a write would have set it to now); for a more recent one, the same bytes.
fn same_file_content(original: &Path, copy: &Path, before: SystemTime) -> bool {
    let (Ok(a), Ok(b)) = (std::fs::metadata(original), std::fs::symlink_metadata(copy)) else { return false };
    if !a.is_file() || !b.is_file() || a.len() != b.len() {
        return false;
    }
    match (a.modified(), b.modified()) {
        (Ok(ta), Ok(tb)) if ta < before => ta == tb,
        _ => same_bytes(original, copy).unwrap_or(false),
    }
}

fn same_bytes(a: &Path, b: &Path) -> std::io::Result<bool> {
    let (mut a, mut b) = (std::fs::File::open(a)?, std::fs::File::open(b)?);
    let (mut x, mut y) = (vec![0u8; 1 << 16], vec![0u8; 1 << 16]);
    loop {
        let n = a.read(&mut x)?;
        if n == 0 {
            return Ok(b.read(&mut y[..1])? == 0);
        }
        b.read_exact(&mut y[..n])?;
        if x[..n] != y[..n] {
            return Ok(false);
        }
    }
}

/// Replaces the unchanged copy `copy` by a hard link to `original` (a new name, then renamed
/// over the copy: the copy is never without a file). Where the file system refuses (another
/// device, a file of another user under `protected_hardlinks`), the copy stays, with the
/// original's times.
fn relink(original: &Path, copy: &Path) {
    let Some(aside) = sibling(copy, "r2d2-link") else { return };
    let linked = std::fs::hard_link(original, &aside).and_then(|()| std::fs::rename(&aside, copy));
    if let Err(e) = linked {
        let _ = std::fs::remove_file(&aside);
        log::debug!("{}: kept as a copy, not linked to the original ({e})", copy.display());
    }
}

/// Replaces the unchanged copy `copy` of what the link `original` names by the link again.
fn link_again(original: &Path, copy: &Path) {
    let Some(aside) = sibling(copy, "r2d2-link") else { return };
    let replaced = copy_link(original, &aside).map_err(|e| e.to_string()).and_then(|()| {
        if copy.is_dir() {
            std::fs::remove_dir_all(copy).map_err(|e| e.to_string())?;
        }
        std::fs::rename(&aside, copy).map_err(|e| e.to_string())
    });
    if let Err(e) = replaced {
        let _ = std::fs::remove_file(&aside);
        log::warn!("{}: a link the model write left unchanged, but it could not be made a link again ({e}): the MeasurementSet holds a copy of what it names", original.display());
    }
}

/// `.NAME.<what>` beside `path`.
fn sibling(path: &Path, what: &str) -> Option<PathBuf> {
    Some(path.with_file_name(format!(".{}.{what}", path.file_name()?.to_string_lossy())))
}

/// Gives the directory `copy` the modification time of `original` (best effort).
fn set_modified(original: &Path, copy: &Path) {
    if let Ok(time) = std::fs::metadata(original).and_then(|m| m.modified()) {
        let _ = std::fs::File::open(copy).and_then(|d| d.set_times(std::fs::FileTimes::new().set_modified(time)));
    }
}
