//! Products staged beside their final place and committed all or nothing: the writer stage's
//! per-job products, and `r2d2 dirty`'s pair.
//!
//! A job's products are written into a staging directory (`.r2d2-staging-*`, beside them),
//! then moved into place by renames: first every earlier file they replace (or that is
//! retired) is moved aside into the staging directory, then the new files are moved in. A
//! failure part-way undoes the renames made. So that a process killed part-way (SIGKILL, power
//! loss) cannot leave a mixed set either, the commit keeps a journal:
//!
//! - `journal.json` lists the files' names; it is written and synced (file and directory)
//!   before the first rename, and a `committed` marker after the last one.
//! - Whoever next stages products in the same directory first looks at the staging
//!   directories left there ([`recover`]): one without a journal (killed before the commit
//!   began) or with the marker is removed; one whose journal is not marked committed is rolled
//!   forward if every new file was moved in, else rolled back (new files removed, earlier files
//!   put back). What it did is logged as a warning. A process looks once per directory (the
//!   first time it stages there): a run of many jobs does not list its output directory again
//!   for each.
//! - Concurrent processes: each staging directory is held under an exclusive `flock` for its
//!   whole life (released by the kernel however the process ends), and recovery skips any it
//!   cannot lock, so it never touches a commit in flight. The target directory is itself
//!   locked while a staging directory is created and locked and while leftovers are recovered,
//!   so that a directory just made and not yet locked is never taken for a leftover.

use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::path::{Path, PathBuf};

/// Whether two paths name the same file or directory (links followed); false when either
/// does not exist.
pub fn same_file(a: &Path, b: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (std::fs::metadata(a), std::fs::metadata(b)) {
            (Ok(x), Ok(y)) => x.dev() == y.dev() && x.ino() == y.ino(),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

/// Whether writing (or replacing) `output` would destroy one of `inputs`: the same file, an
/// input inside it (an output directory holding the input), or it inside an input (a file
/// written into an input MeasurementSet). Returns the input it would destroy.
pub fn destroys_input<'a>(output: &Path, inputs: &[&'a Path]) -> Option<&'a Path> {
    let canonical = |p: &Path| p.canonicalize().ok();
    // The output may not exist yet: its parent's canonical path and its name.
    let out = canonical(output).or_else(|| {
        let parent = output.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        Some(canonical(parent)?.join(output.file_name()?))
    });
    inputs.iter().copied().find(|input| {
        same_file(output, input)
            || match (&out, canonical(input)) {
                (Some(out), Some(input)) => input.starts_with(out) || out.starts_with(&input),
                _ => false,
            }
    })
}

/// Name prefix of staging directories.
const PREFIX: &str = ".r2d2-staging-";
/// What follows `<prefix>-` in the name of every product staged here (`job::products` and
/// `r2d2 dirty` write no others): a journal naming anything else was not written by a commit.
pub const PRODUCT_SUFFIXES: &[&str] = &[
    "dirty.fits", "dirty.png", "psf.fits", "psf.png", "model.fits", "model.png", "residual.fits", "residual.png", "image.fits", "image.png",
    "uncertainty.fits", "uncertainty.png", "metrics.json", "metrics.parquet", "pb.fits", "image-pb.fits", "model-pb.fits",
];
/// The commit journal, and the name it is written under before being renamed into place.
const JOURNAL: &str = "journal.json";
const JOURNAL_PART: &str = "journal.part";
/// Present once every rename of a commit is done.
const COMMITTED: &str = "committed";
/// Subdirectories: the staged products, and the earlier files moved aside.
const NEW: &str = "new";
const EARLIER: &str = "earlier";
/// Bytes a staged file's path adds to its target directory's absolute path (tempfile makes
/// the staging directory's absolute): `/.r2d2-staging-XXXXXX/new/`, with tempfile's 6 random
/// characters (files moved aside under `earlier/` take numbers, not their names).
pub const STAGED_PATH_EXTRA: usize = 1 + PREFIX.len() + 6 + 1 + NEW.len() + 1;
/// Test hook only (tests/faults.rs): the process kills itself (SIGKILL) once this many renames
/// of a commit are done (0: right after the journal is written), as a power cut would stop it.
pub const KILL_AFTER_RENAMES: &str = "R2D2_TEST_KILL_AFTER_RENAMES";
/// Test hook only (tests/ms.rs): the process kills itself when a model column is written and
/// synced in the MS's copy, just before the copy replaces the MS.
pub const KILL_BEFORE_MS_EXCHANGE: &str = "R2D2_TEST_KILL_BEFORE_MS_EXCHANGE";

/// Products of one job, staged in a directory beside their final place and committed together.
///
/// The directory has an unpredictable name and is created afresh (`mkdir`, mode 0700), so a
/// link planted where it would be is never followed; it is removed with what is left in it
/// however the job ends (and by the next [`Staging::new`] in the same place after a kill).
pub struct Staging {
    dir: tempfile::TempDir,
    /// The directory the products go to.
    target_dir: PathBuf,
    /// (staged file, final place) per product made.
    moves: Vec<(PathBuf, PathBuf)>,
    /// Earlier products of the same prefix that this job does not make (`-image.fits` of an
    /// earlier CLEAN run): they would otherwise stand beside this run's as if they were its.
    retired: Vec<PathBuf>,
    /// An open handle on `dir`, exclusively locked while this staging lives: recovery in
    /// another process (or thread) leaves the directory alone.
    _lock: File,
}

/// A file name as the journal stores it: text, or bytes when it is not UTF-8.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(untagged)]
enum Name {
    Text(String),
    Bytes(Vec<u8>),
}

impl Name {
    fn bytes(&self) -> &[u8] {
        match self {
            Name::Text(text) => text.as_bytes(),
            Name::Bytes(bytes) => bytes,
        }
    }

    fn of(path: &Path) -> Name {
        let name = path.file_name().expect("products have file names");
        match name.to_str() {
            Some(text) => Name::Text(text.to_string()),
            None => Name::Bytes(name.as_encoded_bytes().to_vec()),
        }
    }

    fn to_path(&self) -> PathBuf {
        match self {
            Name::Text(text) => PathBuf::from(text),
            #[cfg(unix)]
            Name::Bytes(bytes) => PathBuf::from(<std::ffi::OsStr as std::os::unix::ffi::OsStrExt>::from_bytes(bytes)),
            #[cfg(not(unix))]
            Name::Bytes(bytes) => PathBuf::from(String::from_utf8_lossy(bytes).into_owned()),
        }
    }
}

/// What a commit does, by file name in the target directory: entry `k` of `products` is
/// staged as `new/<name>`; the earlier file of entry `k` of `products` followed by `retired`
/// (if there is one) is moved aside to `earlier/<k>`.
#[derive(Serialize, Deserialize, Debug)]
struct Journal {
    version: u32,
    products: Vec<Name>,
    retired: Vec<Name>,
}

impl Journal {
    /// Refuses names a commit never writes: anything but plain file names (no separator, not
    /// `.` or `..`, no NUL) of one prefix's products (`obs-dirty.fits`, `obs-psf.fits`, ...),
    /// each once. Recovery acts on a journal only when it passes, so a journal planted in a
    /// shared output directory cannot have files elsewhere, or other files here, removed or
    /// overwritten. The message names the first offending name.
    fn check_names(&self) -> std::result::Result<(), String> {
        // The prefixes the names so far can all be products of (`a-image-pb.fits` is prefix
        // `a`'s `image-pb.fits` or prefix `a-image`'s `pb.fits`).
        let mut stems: Option<Vec<&[u8]>> = None;
        let mut seen = std::collections::BTreeSet::new();
        for name in self.products.iter().chain(&self.retired) {
            let bytes = name.bytes();
            let shown = String::from_utf8_lossy(bytes);
            let plain = !bytes.is_empty()
                && bytes != b"."
                && bytes != b".."
                && !bytes.contains(&0)
                && !bytes.iter().any(|&b| b < 0x80 && std::path::is_separator(b as char));
            if !plain {
                return Err(format!("{shown:?} is not a plain file name (it holds a separator or NUL, or is empty, `.` or `..`)"));
            }
            let own: Vec<&[u8]> = PRODUCT_SUFFIXES
                .iter()
                .filter_map(|suffix| bytes.strip_suffix(suffix.as_bytes())?.strip_suffix(b"-"))
                .filter(|own| !own.is_empty())
                // Channel groups' products are one prefix's too: `<prefix>-0000-dirty.fits`,
                // `<prefix>-MFS-...`, `<prefix>-cube-...`.
                .map(group_base)
                .collect();
            if own.is_empty() {
                return Err(format!("{shown:?} is not the name of a product (<prefix>-dirty.fits, <prefix>-psf.fits, ...)"));
            }
            let common: Vec<&[u8]> = match stems.take() {
                None => own,
                Some(earlier) => earlier.into_iter().filter(|s| own.contains(s)).collect(),
            };
            if common.is_empty() {
                return Err(format!("{shown:?} is a product of another prefix than the journal's first name"));
            }
            stems = Some(common);
            if !seen.insert(bytes) {
                return Err(format!("{shown:?} is named twice"));
            }
        }
        Ok(())
    }
}

/// `prefix` less a channel group's label (`-0000`, `-MFS`, `-cube`), where it ends with one.
fn group_base(prefix: &[u8]) -> &[u8] {
    let Some(dash) = prefix.iter().rposition(|&b| b == b'-') else { return prefix };
    let label = &prefix[dash + 1..];
    let is_group = (label.len() == 4 && label.iter().all(u8::is_ascii_digit)) || label == b"MFS" || label == b"cube";
    if is_group && dash > 0 {
        &prefix[..dash]
    } else {
        prefix
    }
}

/// The places a journal's renames involve, resolved against the directories.
struct Plan {
    /// (target, staged) per product.
    products: Vec<(PathBuf, PathBuf)>,
    /// (target, where it goes aside) per product, then per retired file.
    aside: Vec<(PathBuf, PathBuf)>,
}

impl Plan {
    fn new(journal: &Journal, target_dir: &Path, staging: &Path) -> Plan {
        let products = journal.products.iter().map(|n| (target_dir.join(n.to_path()), staging.join(NEW).join(n.to_path()))).collect();
        let aside =
            journal.products.iter().chain(&journal.retired).enumerate().map(|(k, n)| (target_dir.join(n.to_path()), staging.join(EARLIER).join(k.to_string()))).collect();
        Plan { products, aside }
    }

    /// Whether every product has been moved in (its staged file is gone).
    fn all_moved_in(&self) -> bool {
        self.products.iter().all(|(_, staged)| !exists(staged))
    }

    /// Undoes whatever renames of the commit were made, judging each by which files exist:
    /// a product whose staged file is gone was moved in (the earlier files were all moved
    /// aside before any was), so it is removed; an earlier file found aside is put back.
    /// Safe to repeat. Returns the files that could not be put back, with why.
    fn roll_back(&self) -> Vec<String> {
        let mut lost = Vec::new();
        for (target, staged) in self.products.iter().rev() {
            if !exists(staged) && exists(target) {
                if let Err(e) = std::fs::remove_file(target) {
                    lost.push(format!("{} (the new file could not be removed: {e})", target.display()));
                }
            }
        }
        for (target, kept) in self.aside.iter().rev() {
            if exists(kept) {
                if let Err(e) = std::fs::rename(kept, target) {
                    lost.push(format!("{} ({e})", target.display()));
                }
            }
        }
        lost
    }
}

fn exists(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok()
}

/// Flushes a directory's entries (the renames and creations in it) to the disk.
fn sync_dir(dir: &Path) -> Result<()> {
    File::open(dir).and_then(|d| d.sync_all()).map_err(|e| Error::io(dir, e))
}

/// Why `dir` cannot be made where a part of its path exists and is no directory: a link that
/// leads round a loop of links (the system says only "File exists"), or a file. `None` where
/// no part is such.
fn not_a_directory(dir: &Path) -> Option<Error> {
    let mut parts: Vec<&Path> = dir.ancestors().filter(|p| !p.as_os_str().is_empty()).collect();
    parts.reverse();
    parts.into_iter().find_map(|part| {
        let own = std::fs::symlink_metadata(part).ok()?;
        match std::fs::metadata(part) {
            Ok(m) if m.is_dir() => None,
            Ok(m) => Some(Error::input(part, format!("is {}, not a directory: the products cannot go under it", crate::error::file_kind(&m)))),
            Err(e) if own.file_type().is_symlink() && e.raw_os_error() == Some(libc::ELOOP) => Some(Error::input(
                part,
                format!("a symbolic link that leads round a loop of links (to {}), not a directory: the products cannot go under it", target_of(part)),
            )),
            Err(e) if own.file_type().is_symlink() => Some(Error::input(part, format!("a symbolic link that leads nowhere (to {}: {e}), not a directory: the products cannot go under it", target_of(part)))),
            Err(_) => None,
        }
    })
}

/// The target a link names, as text.
fn target_of(link: &Path) -> String {
    std::fs::read_link(link).map_or_else(|e| format!("an unreadable target: {e}"), |t| t.display().to_string())
}

/// Locks `dir` (an open handle on it) exclusively, waiting for the lock.
fn lock_dir(dir: &Path) -> Result<File> {
    let handle = File::open(dir).map_err(|e| Error::io(dir, e))?;
    handle.lock().map_err(|e| Error::io(dir, e))?;
    Ok(handle)
}

impl Staging {
    pub fn new(target_dir: &Path) -> Result<Staging> {
        std::fs::create_dir_all(target_dir).map_err(|e| not_a_directory(target_dir).unwrap_or_else(|| Error::io(target_dir, e)))?;
        let held = lock_dir(target_dir)?;
        let place = std::fs::canonicalize(target_dir).unwrap_or_else(|_| target_dir.to_path_buf());
        let mut looked = LOOKED.lock().unwrap_or_else(|e| e.into_inner());
        if !looked.contains(&place) {
            recover_locked(target_dir)?;
            looked.insert(place);
        }
        drop(looked);
        let dir = tempfile::Builder::new().prefix(PREFIX).tempdir_in(target_dir).map_err(|e| Error::io(target_dir, e))?;
        let lock = lock_dir(dir.path())?;
        drop(held);
        std::fs::create_dir(dir.path().join(NEW)).map_err(|e| Error::io(dir.path(), e))?;
        Ok(Staging { dir, target_dir: target_dir.to_path_buf(), moves: Vec::new(), retired: Vec::new(), _lock: lock })
    }

    /// A staged path for the final file `target` (a file of the target directory).
    pub fn file(&mut self, target: PathBuf) -> PathBuf {
        let staged = self.dir.path().join(NEW).join(target.file_name().expect("products have file names"));
        self.moves.push((staged.clone(), target));
        staged
    }

    /// Writes the product for `target` with `write`, given its staged path; errors name
    /// `target`, the file the user asked for, not the staging directory.
    pub fn write(&mut self, target: PathBuf, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
        let staged = self.file(target.clone());
        write(&staged).map_err(|e| match e {
            Error::Io { path, source } if path == staged => Error::Io { path: target, source },
            Error::Input { path, message } if path == staged => Error::Input { path: target, message },
            other => other,
        })
    }

    /// The final places of the products staged so far.
    pub fn targets(&self) -> impl Iterator<Item = &Path> {
        self.moves.iter().map(|(_, to)| to.as_path())
    }

    /// Removes `earlier` (if it exists) when the job's products are committed.
    pub fn retire(&mut self, earlier: PathBuf) {
        self.retired.push(earlier);
    }

    /// Moves the products into place, all or none; the earlier products removed.
    pub fn commit(self) -> Result<Vec<PathBuf>> {
        let kill_after: Option<usize> = std::env::var(KILL_AFTER_RENAMES).ok().and_then(|v| v.parse().ok());
        self.commit_with(&mut |from, to| std::fs::rename(from, to), &mut |renames| {
            if kill_after == Some(renames) {
                kill_this_process();
            }
        })
    }

    /// Commits with `rename` moving each file (a test injects failures through it); `done`
    /// hears how many renames are done, after the journal is written and after each rename.
    ///
    /// Every file that a product replaces, or that is retired, is first moved aside into the
    /// staging directory; then the products are moved in. If any step fails, the products
    /// moved in are removed and the files moved aside are put back, so the directory holds the
    /// earlier products exactly as before. The files moved aside go with the staging directory.
    pub(crate) fn commit_with(
        mut self,
        rename: &mut dyn FnMut(&Path, &Path) -> std::io::Result<()>,
        done: &mut dyn FnMut(usize),
    ) -> Result<Vec<PathBuf>> {
        let moves = std::mem::take(&mut self.moves);
        let staging = self.dir.path().to_path_buf();
        let journal = Journal {
            version: 1,
            products: moves.iter().map(|(_, to)| Name::of(to)).collect(),
            retired: self.retired.iter().map(|t| Name::of(t)).collect(),
        };
        // A journal recovery would not act on is never written (only products are staged).
        journal.check_names().map_err(|e| Error::input(&self.target_dir, format!("cannot commit these products: {e}")))?;
        let mut plan = Plan::new(&journal, &self.target_dir, &staging);
        // The caller's spelling of the targets (the same files), so that errors name them as
        // the caller did.
        for ((target, _), (_, to)) in plan.products.iter_mut().zip(&moves) {
            *target = to.clone();
        }
        for ((target, _), to) in plan.aside.iter_mut().zip(moves.iter().map(|(_, to)| to).chain(&self.retired)) {
            *target = to.clone();
        }
        for (target, _) in &plan.aside {
            match std::fs::symlink_metadata(target) {
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(Error::io(target, e)),
                Ok(m) if m.is_dir() => return Err(Error::input(target, "is a directory where a product goes: not replacing it")),
                Ok(_) => {}
            }
        }
        // The staged files reach the disk before anything refers to them.
        for (_, staged) in &plan.products {
            File::open(staged).and_then(|f| f.sync_all()).map_err(|e| Error::io(staged, e))?;
        }
        std::fs::create_dir(staging.join(EARLIER)).map_err(|e| Error::io(&staging, e))?;
        sync_dir(&staging.join(NEW))?;
        write_journal(&staging, &journal)?;
        done(0);
        let mut renames = 0;
        let mut attempt = || -> Result<()> {
            for (target, kept) in &plan.aside {
                if exists(target) {
                    rename(target, kept).map_err(|e| Error::io(target, e))?;
                    renames += 1;
                    done(renames);
                }
            }
            for (to, from) in &plan.products {
                rename(from, to).map_err(|e| Error::io(to, e))?;
                renames += 1;
                done(renames);
            }
            sync_dir(&self.target_dir)?;
            File::create(staging.join(COMMITTED)).map_err(|e| Error::io(&staging, e))?;
            sync_dir(&staging)
        };
        let Err(e) = attempt() else {
            let products = plan.products.len();
            return Ok(plan.aside[products..].iter().filter(|(_, kept)| exists(kept)).map(|(target, _)| target.clone()).collect());
        };
        let lost = plan.roll_back();
        if lost.is_empty() {
            return Err(e);
        }
        // Keep what could not be put back where the user can find it.
        let kept = self.dir.keep();
        Err(Error::io(
            kept.clone(),
            std::io::Error::other(format!("{e}; and while undoing, {} could not be put back: the earlier files are in {}", lost.join(", "), kept.display())),
        ))
    }
}

/// Writes the journal whole or not at all: written aside, synced, renamed into place, synced.
fn write_journal(staging: &Path, journal: &Journal) -> Result<()> {
    let part = staging.join(JOURNAL_PART);
    let text = serde_json::to_vec_pretty(journal).expect("journals serialise");
    let write = || -> std::io::Result<()> {
        let mut file = File::create(&part)?;
        std::io::Write::write_all(&mut file, &text)?;
        file.sync_all()?;
        std::fs::rename(&part, staging.join(JOURNAL))
    };
    write().map_err(|e| Error::io(&part, e))?;
    sync_dir(staging)
}

/// The test hooks' kill: no destructor, no cleanup, as SIGKILL from outside.
pub(crate) fn kill_this_process() -> ! {
    #[cfg(unix)]
    // SAFETY: kill(2) and getpid(2) take and return plain integers and touch no memory.
    unsafe {
        libc::kill(libc::getpid(), libc::SIGKILL);
    }
    std::process::abort()
}

/// Directories this process has recovered leftovers in (canonical paths).
static LOOKED: std::sync::Mutex<std::collections::BTreeSet<PathBuf>> = std::sync::Mutex::new(std::collections::BTreeSet::new());

/// Finishes or undoes the commits that killed processes left in `dir` (see the module
/// documentation); staging directories in use by a live process are left alone.
#[cfg(test)]
pub fn recover(dir: &Path) -> Result<()> {
    let _held = lock_dir(dir)?;
    recover_locked(dir)
}

/// [`recover`] with `dir` already locked.
fn recover_locked(dir: &Path) -> Result<()> {
    for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        if !entry.file_name().to_string_lossy().starts_with(PREFIX) || !entry.file_type().is_ok_and(|t| t.is_dir()) {
            continue;
        }
        let staging = entry.path();
        let Ok(handle) = File::open(&staging) else { continue };
        match handle.try_lock() {
            Ok(()) => recover_one(dir, &staging),
            // In use: its commit is in flight (or it is being written).
            Err(std::fs::TryLockError::WouldBlock) => {}
            Err(std::fs::TryLockError::Error(e)) => log::warn!("{}: cannot lock ({e}); left as it is", staging.display()),
        }
    }
    Ok(())
}

/// Recovers one leftover staging directory (locked by the caller) and removes it.
fn recover_one(dir: &Path, staging: &Path) {
    let journal_path = staging.join(JOURNAL);
    let remove = |what: &str| match std::fs::remove_dir_all(staging) {
        Ok(()) => log::debug!("removed {} ({what})", staging.display()),
        Err(e) => log::warn!("{}: cannot remove it ({what}): {e}", staging.display()),
    };
    if exists(&staging.join(COMMITTED)) {
        return remove("a commit that completed");
    }
    if !exists(&journal_path) {
        return remove("products staged by a run that ended before committing them");
    }
    let journal: Journal = match std::fs::read(&journal_path).map_err(|e| e.to_string()).and_then(|b| serde_json::from_slice(&b).map_err(|e| e.to_string())) {
        Ok(journal) => journal,
        Err(e) => {
            log::warn!("{}: an interrupted commit whose journal cannot be read ({e}); left as it is: the earlier files are in its earlier/", staging.display());
            return;
        }
    };
    if let Err(e) = journal.check_names() {
        log::warn!("{}: the journal of an interrupted commit names files no commit writes ({e}); left as it is, nothing moved", staging.display());
        return;
    }
    let plan = Plan::new(&journal, dir, staging);
    let names = |paths: &mut dyn Iterator<Item = &PathBuf>| paths.map(|p| p.file_name().unwrap_or_default().to_string_lossy().into_owned()).collect::<Vec<_>>().join(", ");
    if plan.all_moved_in() {
        log::warn!(
            "{}: a run was stopped after moving its products into place but before recording it: rolled forward ({} are its products)",
            dir.display(),
            names(&mut plan.products.iter().map(|(t, _)| t))
        );
        return remove("a commit rolled forward");
    }
    // Rolling back removes and replaces files of `dir`: only for a staging directory this
    // user's runs made, whose files aside are files it moved there.
    if let Err(e) = own_leftover(staging, &plan) {
        log::warn!("{}: an interrupted commit, not rolled back: {e}; left as it is, nothing moved", staging.display());
        return;
    }
    let restored = names(&mut plan.aside.iter().filter(|(_, kept)| exists(kept)).map(|(t, _)| t));
    let removed = names(&mut plan.products.iter().filter(|(t, staged)| !exists(staged) && exists(t)).map(|(t, _)| t));
    let lost = plan.roll_back();
    if !lost.is_empty() {
        log::warn!(
            "{}: rolling back a run stopped while committing its products, {} could not be put back; the earlier files stay in {}",
            dir.display(),
            lost.join(", "),
            staging.join(EARLIER).display()
        );
        return;
    }
    log::warn!(
        "{}: a run was stopped while committing its products: rolled back (earlier files put back: {}; new files removed: {})",
        dir.display(),
        if restored.is_empty() { "none" } else { &restored },
        if removed.is_empty() { "none" } else { &removed },
    );
    remove("a commit rolled back");
}

/// Whether a leftover staging directory is one a commit of this user left: owned by this
/// user (staging directories are made with mode 0700), its `new/` and `earlier/` directories
/// (not links to others), and each file aside a plain file, not a link or a directory.
fn own_leftover(staging: &Path, plan: &Plan) -> std::result::Result<(), String> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let owner = std::fs::symlink_metadata(staging).map_err(|e| e.to_string())?.uid();
        // SAFETY: geteuid(2) takes nothing and cannot fail.
        let me = unsafe { libc::geteuid() };
        if owner != me {
            return Err(format!("it belongs to another user (uid {owner}, this process runs as uid {me})"));
        }
    }
    for sub in [NEW, EARLIER] {
        match std::fs::symlink_metadata(staging.join(sub)) {
            Ok(m) if !m.is_dir() => return Err(format!("its {sub} is not a directory")),
            _ => {}
        }
    }
    for (_, kept) in &plan.aside {
        match std::fs::symlink_metadata(kept) {
            Ok(m) if !m.is_file() => return Err(format!("{} is not a plain file", kept.display())),
            _ => {}
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The files in `dir` and their contents, sorted.
    fn listing(dir: &Path) -> Vec<(String, String)> {
        let mut files: Vec<(String, String)> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read_to_string(&p).unwrap_or_else(|_| "<dir>".into())))
            .collect();
        files.sort();
        files
    }

    /// Earlier products `x-dirty.fits`, `x-psf.fits`; new ones staged for `x-dirty.fits`,
    /// `x-psf.fits` and `x-metrics.json`.
    fn staged_over_earlier(dir: &Path) -> Staging {
        for name in ["x-dirty.fits", "x-psf.fits"] {
            std::fs::write(dir.join(name), format!("earlier {name}")).unwrap();
        }
        let mut staging = Staging::new(dir).unwrap();
        for name in ["x-dirty.fits", "x-psf.fits", "x-metrics.json"] {
            std::fs::write(staging.file(dir.join(name)), format!("new {name}")).unwrap();
        }
        staging
    }

    #[test]
    fn a_commit_failing_part_way_puts_the_earlier_products_back() {
        // Every rename in turn fails; until one does, they are real.
        for failing in 1..=8 {
            let dir = tempfile::tempdir().unwrap();
            let staging = staged_over_earlier(dir.path());
            let before: Vec<_> = listing(dir.path()).into_iter().filter(|(n, _)| !n.starts_with(".r2d2-staging")).collect();
            let mut calls = 0;
            let result = staging.commit_with(
                &mut |from, to| {
                    calls += 1;
                    if calls == failing {
                        return Err(std::io::Error::other("injected failure"));
                    }
                    std::fs::rename(from, to)
                },
                &mut |_| {},
            );
            match result {
                Err(e) => assert!(e.to_string().contains("injected failure"), "{e}"),
                // Fewer renames than `failing`: all went through.
                Ok(_) => continue,
            }
            assert_eq!(listing(dir.path()), before, "rename {failing} failed: the earlier products are not all back");
        }
    }

    #[test]
    fn a_commit_replaces_the_product_set_and_retires_earlier_products() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("x-image.fits"), "earlier CLEAN image").unwrap();
        let mut staging = staged_over_earlier(dir.path());
        staging.retire(dir.path().join("x-image.fits"));
        staging.retire(dir.path().join("x-model.fits"));
        let removed = staging.commit().unwrap();
        assert_eq!(removed, [dir.path().join("x-image.fits")]);
        let names = ["x-dirty.fits", "x-metrics.json", "x-psf.fits"];
        let expected: Vec<(String, String)> = names.iter().map(|n| (n.to_string(), format!("new {n}"))).collect();
        assert_eq!(listing(dir.path()), expected);
    }

    #[test]
    fn staging_directories_have_unpredictable_names_and_go_away() {
        let dir = tempfile::tempdir().unwrap();
        let a = Staging::new(dir.path()).unwrap();
        let mut b = Staging::new(dir.path()).unwrap();
        assert_ne!(a.dir.path(), b.dir.path(), "two stagings share a directory name");
        // What the output-name checks allow for (`fits::check_output_prefix`).
        let staged = b.file(dir.path().join("x"));
        assert!(staged.is_absolute());
        assert_eq!(staged.as_os_str().len(), dir.path().as_os_str().len() + STAGED_PATH_EXTRA + 1, "{}", staged.display());
        drop((a, b));
        assert!(listing(dir.path()).is_empty(), "{:?}", listing(dir.path()));
    }

    /// Copies the tree at `from` to `to` (files and directories).
    fn copy_tree(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for entry in std::fs::read_dir(from).unwrap().flatten() {
            if entry.file_type().unwrap().is_dir() {
                copy_tree(&entry.path(), &to.join(entry.file_name()));
            } else {
                std::fs::copy(entry.path(), to.join(entry.file_name())).unwrap();
            }
        }
    }

    #[test]
    fn a_commit_stopped_after_any_rename_is_rolled_back_or_forward_by_the_next_staging() {
        // The directory as a kill after `renames` renames would leave it (a copy taken then,
        // whose staging directory no process holds), recovered by a later staging there.
        let before = {
            let dir = tempfile::tempdir().unwrap();
            drop(staged_over_earlier(dir.path()));
            listing(dir.path())
        };
        let mut after = Vec::new();
        let mut renames_in_all = 0;
        for renames in 0.. {
            let dir = tempfile::tempdir().unwrap();
            let killed = tempfile::tempdir().unwrap();
            let mut staging = staged_over_earlier(dir.path());
            staging.retire(dir.path().join("x-image.fits"));
            std::fs::write(dir.path().join("x-image.fits"), "earlier x-image.fits").unwrap();
            staging.commit_with(&mut |from, to| std::fs::rename(from, to), &mut |done| {
                if done == renames {
                    copy_tree(dir.path(), killed.path());
                }
                renames_in_all = done;
            })
            .unwrap();
            after = listing(dir.path());
            if renames > renames_in_all {
                break;
            }
            let mixed = listing(killed.path());
            drop(Staging::new(killed.path()).unwrap());
            let recovered = listing(killed.path());
            let mut earlier = before.clone();
            earlier.push(("x-image.fits".into(), "earlier x-image.fits".into()));
            earlier.sort();
            let expected = if renames == renames_in_all { &after } else { &earlier };
            assert_eq!(&recovered, expected, "killed after {renames} of {renames_in_all} renames (left: {mixed:?})");
        }
        // 2 earlier products and the retired image aside, 3 products in.
        assert_eq!(renames_in_all, 6);
        assert!(!after.iter().any(|(n, _)| n == "x-image.fits"));
    }

    #[test]
    fn recovery_leaves_a_commit_in_flight_alone() {
        let dir = tempfile::tempdir().unwrap();
        let staging = staged_over_earlier(dir.path());
        let mut calls = 0;
        staging
            .commit_with(
                &mut |from, to| {
                    calls += 1;
                    if calls == 3 {
                        // Half-way: another writer in the same directory recovers leftovers.
                        let other = Staging::new(dir.path()).unwrap();
                        drop(other);
                        recover(dir.path()).unwrap();
                    }
                    std::fs::rename(from, to)
                },
                &mut |_| {},
            )
            .unwrap();
        let names = ["x-dirty.fits", "x-metrics.json", "x-psf.fits"];
        let expected: Vec<(String, String)> = names.iter().map(|n| (n.to_string(), format!("new {n}"))).collect();
        assert_eq!(listing(dir.path()), expected);
    }

    /// Every file under `dir` (recursively, links not followed) and its contents, sorted.
    fn tree(dir: &Path) -> Vec<(PathBuf, String)> {
        let mut files = Vec::new();
        for entry in std::fs::read_dir(dir).unwrap().flatten() {
            let kind = entry.file_type().unwrap();
            if kind.is_dir() {
                files.extend(tree(&entry.path()));
            } else if kind.is_symlink() {
                files.push((entry.path(), format!("-> {}", std::fs::read_link(entry.path()).unwrap().display())));
            } else {
                files.push((entry.path(), std::fs::read_to_string(entry.path()).unwrap()));
            }
        }
        files.sort();
        files
    }

    #[cfg(unix)]
    #[test]
    fn a_planted_journal_moves_nothing_unless_it_names_one_prefixs_products_here() {
        // Issue 56: names joined onto the output directory unchecked deleted and overwrote
        // files anywhere; plain names overwrote any file of the directory.
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("out");
        for (path, text) in [("victimdir/precious.txt", "precious"), ("precious2.txt", "precious2"), ("abs.txt", "abs"), ("elsewhere/0", "elsewhere")] {
            std::fs::create_dir_all(root.path().join(path).parent().unwrap()).unwrap();
            std::fs::write(root.path().join(path), text).unwrap();
        }
        std::fs::create_dir(&out).unwrap();
        for name in ["notes.txt", "x-psf.fits", "y-psf.fits"] {
            std::fs::write(out.join(name), format!("earlier {name}")).unwrap();
        }
        let absolute = root.path().join("abs.txt").display().to_string();
        let cases: Vec<(Vec<&str>, Vec<&str>)> = vec![
            (vec!["x-dirty.fits", "../victimdir/precious.txt"], vec!["../precious2.txt", &absolute]),
            (vec!["x-dirty.fits"], vec!["x-psf.fits", "notes.txt"]),
            (vec!["x-dirty.fits", "y-psf.fits"], vec![]),
            // Channel groups: one prefix's, but not another's (`y-0000`).
            (vec!["x-0000-dirty.fits", "y-0000-psf.fits"], vec![]),
            (vec!["x-MFS-dirty.fits", "y-psf.fits"], vec![]),
            (vec!["x-dirty.fits", "x-psf.fits", "x-psf.fits"], vec![]),
            (vec!["x-dirty.fits", "x-psf.fits\u{0}"], vec![]),
            (vec!["x-dirty.fits", "."], vec![]),
            (vec!["-psf.fits"], vec![]),
        ];
        let before = tree(root.path());
        for (k, (products, retired)) in cases.iter().enumerate() {
            let planted = out.join(".r2d2-staging-planted");
            std::fs::create_dir_all(planted.join("new")).unwrap();
            std::fs::create_dir_all(planted.join("earlier")).unwrap();
            std::fs::write(planted.join("new/x-dirty.fits"), "planted").unwrap();
            for i in 0..4 {
                std::fs::write(planted.join(format!("earlier/{i}")), format!("planted {i}")).unwrap();
            }
            let journal = serde_json::json!({"version": 1, "products": products, "retired": retired});
            std::fs::write(planted.join(JOURNAL), journal.to_string()).unwrap();
            let planted_tree = tree(&planted);
            recover(&out).unwrap();
            let after: Vec<_> = tree(root.path()).into_iter().filter(|(p, _)| !p.starts_with(&planted)).collect();
            assert_eq!(after, before, "case {k} ({journal}): files outside the staging directory changed");
            assert_eq!(tree(&planted), planted_tree, "case {k}: the planted directory is left as it is");
            std::fs::remove_dir_all(&planted).unwrap();
        }
        // Good names, but `earlier/` a link to another directory: its files are not put back.
        let planted = out.join(".r2d2-staging-linked");
        std::fs::create_dir_all(planted.join("new")).unwrap();
        std::fs::write(planted.join("new/x-dirty.fits"), "planted").unwrap();
        std::os::unix::fs::symlink(root.path().join("elsewhere"), planted.join("earlier")).unwrap();
        std::fs::write(planted.join(JOURNAL), r#"{"version": 1, "products": ["x-dirty.fits"], "retired": []}"#).unwrap();
        recover(&out).unwrap();
        let after: Vec<_> = tree(root.path()).into_iter().filter(|(p, _)| !p.starts_with(&planted)).collect();
        assert_eq!(after, before, "a file of the directory `earlier` links to was moved");
    }

    #[test]
    fn a_channel_groups_products_are_one_prefixs() {
        let journal = |names: &[&str]| Journal { version: 1, products: names.iter().map(|n| Name::of(std::path::Path::new(n))).collect(), retired: Vec::new() };
        assert!(journal(&["x-0000-dirty.fits", "x-0001-dirty.fits", "x-MFS-psf.fits", "x-cube-image.fits", "x-dirty.fits"]).check_names().is_ok());
        for names in [&["x-0000-dirty.fits", "y-0001-dirty.fits"][..], &["x-00001-dirty.fits", "x-dirty.fits"][..], &["x-mfs-dirty.fits", "x-dirty.fits"][..]] {
            assert!(journal(names).check_names().is_err(), "{names:?}");
        }
    }

    #[test]
    fn a_commit_writes_only_journals_that_recovery_acts_on() {
        let dir = tempfile::tempdir().unwrap();
        let mut staging = Staging::new(dir.path()).unwrap();
        std::fs::write(staging.file(dir.path().join("notes.txt")), "new").unwrap();
        let e = staging.commit().unwrap_err().to_string();
        assert!(e.contains("notes.txt") && e.contains("not the name of a product"), "{e}");
        assert!(listing(dir.path()).is_empty(), "{:?}", listing(dir.path()));
    }

    #[test]
    fn leftover_staging_without_a_journal_is_removed() {
        let dir = tempfile::tempdir().unwrap();
        let staging = staged_over_earlier(dir.path());
        // As a kill before the commit would leave it: the directory stays, unlocked.
        let kept = staging.dir.path().to_path_buf();
        std::mem::forget(staging);
        let leftover = dir.path().join(".r2d2-staging-leftover");
        std::fs::rename(&kept, &leftover).unwrap();
        // The forgotten handle still locks the directory (same open file): a kill closes it.
        // Here a fresh copy stands in for the killed process's directory.
        let copy = dir.path().join(".r2d2-staging-copy");
        copy_tree(&leftover, &copy);
        recover(dir.path()).unwrap();
        let names: Vec<String> = listing(dir.path()).into_iter().map(|(n, _)| n).collect();
        assert!(names.contains(&".r2d2-staging-leftover".to_string()), "a locked staging directory was removed: {names:?}");
        assert!(!names.contains(&".r2d2-staging-copy".to_string()), "{names:?}");
        assert_eq!(std::fs::read_to_string(dir.path().join("x-dirty.fits")).unwrap(), "earlier x-dirty.fits");
    }
}
