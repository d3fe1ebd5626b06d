//! Products staged beside their final place and committed all or nothing: the writer stage's
//! per-job products, and `r2d2 dirty`'s pair.

use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// Products of one job, staged in a directory beside their final place and committed together.
///
/// The directory has an unpredictable name and is created afresh (`mkdir`, mode 0700), so a
/// link planted where it would be is never followed; it is removed with what is left in it
/// however the job ends.
pub struct Staging {
    dir: tempfile::TempDir,
    /// (staged file, final place) per product made.
    moves: Vec<(PathBuf, PathBuf)>,
    /// Earlier products of the same prefix that this job does not make (`-image.fits` of an
    /// earlier CLEAN run): they would otherwise stand beside this run's as if they were its.
    retired: Vec<PathBuf>,
}

impl Staging {
    pub fn new(target_dir: &Path) -> Result<Staging> {
        std::fs::create_dir_all(target_dir).map_err(|e| Error::io(target_dir, e))?;
        let dir = tempfile::Builder::new().prefix(".r2d2-staging-").tempdir_in(target_dir).map_err(|e| Error::io(target_dir, e))?;
        Ok(Staging { dir, moves: Vec::new(), retired: Vec::new() })
    }

    /// A staged path for the final file `target`.
    pub fn file(&mut self, target: PathBuf) -> PathBuf {
        let staged = self.dir.path().join(target.file_name().expect("products have file names"));
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
        self.commit_with(&mut |from, to| std::fs::rename(from, to))
    }

    /// Commits with `rename` moving each file (a test injects failures through it).
    ///
    /// Every file that a product replaces, or that is retired, is first moved aside into the
    /// staging directory; then the products are moved in. If any step fails, the products
    /// moved in are removed and the files moved aside are put back, so the directory holds the
    /// earlier products exactly as before. The files moved aside go with the staging directory.
    pub(crate) fn commit_with(mut self, rename: &mut dyn FnMut(&Path, &Path) -> std::io::Result<()>) -> Result<Vec<PathBuf>> {
        let aside_dir = self.dir.path().join("earlier");
        std::fs::create_dir(&aside_dir).map_err(|e| Error::io(&aside_dir, e))?;
        let moves = std::mem::take(&mut self.moves);
        let mut aside: Vec<(PathBuf, PathBuf)> = Vec::new();
        let mut placed: Vec<&Path> = Vec::new();
        let mut attempt = || -> Result<()> {
            for target in moves.iter().map(|(_, to)| to).chain(&self.retired) {
                match std::fs::symlink_metadata(target) {
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                    Err(e) => return Err(Error::io(target, e)),
                    Ok(m) if m.is_dir() => return Err(Error::input(target, "is a directory where a product goes: not replacing it")),
                    Ok(_) => {}
                }
                let kept = aside_dir.join(format!("{}-{}", aside.len(), target.file_name().map(|n| n.to_string_lossy()).unwrap_or_default()));
                rename(target, &kept).map_err(|e| Error::io(target, e))?;
                aside.push((target.clone(), kept));
            }
            for (from, to) in &moves {
                rename(from, to).map_err(|e| Error::io(to, e))?;
                placed.push(to);
            }
            Ok(())
        };
        let Err(e) = attempt() else {
            let replaced: Vec<&PathBuf> = moves.iter().map(|(_, to)| to).collect();
            return Ok(aside.into_iter().map(|(target, _)| target).filter(|t| !replaced.contains(&t)).collect());
        };
        // Roll back with plain renames: these only undo renames that just worked.
        for path in placed.into_iter().rev() {
            let _ = std::fs::remove_file(path);
        }
        let mut lost = Vec::new();
        for (target, kept) in aside.into_iter().rev() {
            if std::fs::rename(&kept, &target).is_err() {
                lost.push(target.display().to_string());
            }
        }
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
            let result = staging.commit_with(&mut |from, to| {
                calls += 1;
                if calls == failing {
                    return Err(std::io::Error::other("injected failure"));
                }
                std::fs::rename(from, to)
            });
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
        let b = Staging::new(dir.path()).unwrap();
        assert_ne!(a.dir.path(), b.dir.path(), "two stagings share a directory name");
        drop((a, b));
        assert!(listing(dir.path()).is_empty(), "{:?}", listing(dir.path()));
    }
}
