//! What goes wrong with FITS files ([`FitsError`]), and cfitsio's own reports.

use fitsio::errors::Error as FitsioError;
use std::path::{Path, PathBuf};

/// What went wrong with a FITS file. Each variant names the file; cfitsio's own report, where
/// there is one, is the [`source`](std::error::Error::source) ([`Cfitsio`]).
///
/// Failures to write an image are [`Error::Io`] (as other write failures), whose `io::Error`
/// has the kind of the system's reason (`StorageFull`, `ReadOnlyFilesystem`, ...) when one is
/// found and carries a [`WriteFailure`] with cfitsio's report.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FitsError {
    /// cfitsio could not do what `doing` says (open the file, read its primary HDU, its pixels,
    /// a header keyword).
    #[error("{}: {doing}", path.display())]
    Cfitsio {
        path: PathBuf,
        doing: String,
        #[source]
        source: Cfitsio,
    },
    /// The file is FITS, but not an image this crate reads (the header or the pixels say why).
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
    /// A path cfitsio cannot be given (it parses file names), or that is not a regular file.
    #[error("{}: {message}", path.display())]
    Unusable { path: PathBuf, message: &'static str },
}

impl FitsError {
    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            FitsError::Cfitsio { path, .. } | FitsError::Invalid { path, .. } | FitsError::Unusable { path, .. } => path,
        }
    }
}

/// An error reported by cfitsio (through `fitsio`), readable: `fitsio`'s own text is a Debug
/// dump of a struct.
#[derive(Debug)]
pub struct Cfitsio(pub FitsioError);

impl Cfitsio {
    /// cfitsio's status code (104: cannot open the file, 202: no such keyword, ...), when the
    /// error came from cfitsio itself rather than from `fitsio`'s checks.
    pub fn status(&self) -> Option<i32> {
        match &self.0 {
            FitsioError::Fits(e) => Some(e.status),
            _ => None,
        }
    }
}

impl std::fmt::Display for Cfitsio {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.0 {
            FitsioError::Fits(e) => write!(f, "{} (cfitsio status {})", e.message, e.status),
            other => write!(f, "{other}"),
        }
    }
}

impl std::error::Error for Cfitsio {}

/// Why writing a FITS image failed: cfitsio's report (its status says nothing of the cause)
/// and, when the directory takes no more data, the system's reason as the source.
#[derive(Debug, thiserror::Error)]
#[error("writing FITS image: {cfitsio}{}", if disk.is_some() { ": the directory takes no more data" } else { "" })]
pub struct WriteFailure {
    pub cfitsio: Cfitsio,
    #[source]
    pub disk: Option<std::io::Error>,
}
