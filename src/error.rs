//! The one public error type, [`Error`], and the error types of the modules it wraps.
//!
//! Every message names what was wrong (a file, a column, a parameter) and what was expected, so
//! a user can fix the input without reading code.
//!
//! Modules that read and run things keep their own error enums, whose variants a program can
//! match on, and keep the error underneath (cfitsio's status, ONNX Runtime's or tract's error,
//! the dynamic loader's, casacore's, the system's) as the [`source`](std::error::Error::source)
//! instead of flattening it into text:
//!
//! - [`FitsError`] (`fits`): FITS images;
//! - [`SeriesError`] (`steps::series`): model series on disk (manifest, network files);
//! - [`OnnxError`] (`steps::runtime`): ONNX networks (checking, loading, inference);
//! - [`PluginError`] (`steps::native`): native plugins (the library, its loading, its host);
//! - [`TableError`] (`vis`): visibility tables (Parquet, Arrow IPC, in-memory Arrow): the
//!   decoder's error, a missing or mistyped column, bad metadata;
//! - `MsError` (`ms`, with the `ms` feature): MeasurementSets (casacore tables).
//!
//! [`Error`] wraps each in a variant of its own (`Error::Fits`, ...), whose `source()` is the
//! module's error. The module errors' own text says what failed and where, without their cause
//! (the usual rule: a cause is either a source or in the text, never both); `Error`'s text is
//! the whole message, causes included, so that `{}` of an `Error` (a log line, a Python
//! exception, another message) says everything. [`Report`] prints any error followed by the
//! causes its text does not already show: the command line prints errors through it.

use std::cell::{Cell, RefCell};
use std::fmt;
use std::path::PathBuf;
use std::sync::Once;

pub use crate::fits::FitsError;
#[cfg(feature = "ms")]
pub use crate::ms::MsError;
pub use crate::steps::native::PluginError;
pub use crate::steps::runtime::OnnxError;
pub use crate::steps::series::SeriesError;
pub use crate::vis::TableError;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A problem with an input file: unreadable, malformed, missing a column...
    #[error("{}: {message}", path.display())]
    Input { path: PathBuf, message: String },

    /// A problem at a place in a pipeline description (YAML): the file, line and column (both
    /// from 1), for an editor or a notebook to point at. `cause` is the error that the value
    /// there led to (a series that does not load), when there is one; `message` says it too.
    #[error("{}: line {line}, column {column}: {message}", file.display())]
    Located {
        file: PathBuf,
        line: usize,
        column: usize,
        message: String,
        #[source]
        cause: Option<Box<Error>>,
    },

    /// A parameter (command-line option or configuration value) out of its allowed range.
    #[error("invalid {name}: {message}")]
    Parameter { name: String, message: String },

    /// A pipeline stage failed on a job.
    #[error("stage '{stage}' ({kind}), job '{job}': {source}")]
    Stage {
        stage: String,
        kind: String,
        job: String,
        #[source]
        source: Box<Error>,
    },

    /// The machine could not give what the run needs (a thread, under an address-space
    /// limit): not the input's fault, so no file is named.
    #[error("out of memory: {0}")]
    OutOfMemory(String),

    /// The run was interrupted (Ctrl-C) before it finished.
    #[error("interrupted: {0}")]
    Interrupted(String),

    /// The engine was asked to run in a process forked from one where it had started its
    /// compute threads (`crate::parallel::claim_process`).
    #[error(
        "this process ({child}) was forked from process {parent} after the engine had started its compute threads there, and fork copies only the thread that forks: the engine cannot run here (it would wait for ever on threads that do not exist); start worker processes with the 'spawn' or 'forkserver' method (Python: multiprocessing.get_context(\"spawn\")), or fork before the engine's first use"
    )]
    Forked { parent: u32, child: u32 },

    /// A stage panicked: a bug, reported instead of bringing the process down.
    #[error("the stage failed unexpectedly ({0}); this is a bug, please report it")]
    Panic(String),

    /// An operating-system error while reading or writing a file.
    #[error("{}: {}", path.display(), Report(.source))]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// A FITS image could not be read (its own error says why and keeps cfitsio's).
    #[error("{}", Report(.0))]
    Fits(#[from] FitsError),

    /// A model series could not be used.
    #[error("{}", Report(.0))]
    Series(#[from] SeriesError),

    /// An ONNX network could not be checked, loaded or run.
    #[error("{}", Report(.0))]
    Onnx(#[from] OnnxError),

    /// A native plugin could not be loaded or failed.
    #[error("{}", Report(.0))]
    Plugin(#[from] PluginError),

    /// A visibility table could not be read or built.
    #[error("{}", Report(.0))]
    Table(#[from] TableError),

    /// A MeasurementSet could not be read or written.
    #[cfg(feature = "ms")]
    #[error("{}", Report(.0))]
    Ms(#[from] MsError),
}

/// An error followed by each cause in its [`source`](std::error::Error::source) chain that its
/// text does not already show, joined by `: ` (`{}`: one line, as the command line prints it).
pub struct Report<'a>(pub &'a (dyn std::error::Error + 'static));

impl fmt::Display for Report<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut text = self.0.to_string();
        let mut next = self.0.source();
        while let Some(cause) = next {
            let said = cause.to_string();
            // A wrapper that shows its cause (`Error::Stage`, `Error::Io`, third-party errors
            // that print theirs) would otherwise say it twice; text already there is not lost.
            if !said.is_empty() && !text.contains(&said) {
                text.push_str(": ");
                text.push_str(&said);
            }
            next = cause.source();
        }
        f.write_str(&text)
    }
}

impl Error {
    pub fn input(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Input { path: path.into(), message: message.into() }
    }
    pub fn parameter(name: impl Into<String>, message: impl Into<String>) -> Self {
        Error::Parameter { name: name.into(), message: message.into() }
    }
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), source }
    }

    /// This error and its causes on one line, each said once ([`Report`]).
    pub fn report(&self) -> Report<'_> {
        Report(self)
    }

    /// The error of the module that failed, through the stage that ran it: `Error::Fits` and
    /// the others, as such or inside `Error::Stage` (`None` for the generic variants).
    pub fn module_error(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Error::Fits(e) => Some(e),
            Error::Series(e) => Some(e),
            Error::Onnx(e) => Some(e),
            Error::Plugin(e) => Some(e),
            Error::Table(e) => Some(e),
            #[cfg(feature = "ms")]
            Error::Ms(e) => Some(e),
            Error::Stage { source, .. } => source.module_error(),
            Error::Located { cause: Some(cause), .. } => cause.module_error(),
            _ => None,
        }
    }

    /// Where in a pipeline file the error is (file, line, column), for this error or the one
    /// it wraps (a stage's).
    pub fn location(&self) -> Option<(&std::path::Path, usize, usize)> {
        match self {
            Error::Located { file, line, column, .. } => Some((file, *line, *column)),
            Error::Stage { source, .. } => source.location(),
            _ => None,
        }
    }

    /// The stage, its kind and the job an error happened in, when a stage failed on a job.
    pub fn stage(&self) -> Option<(&str, &str, &str)> {
        match self {
            Error::Stage { stage, kind, job, .. } => Some((stage, kind, job)),
            _ => None,
        }
    }
}

/// The message a panic was raised with (`panic!("...")` gives a `&str` or a `String`).
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "no message".to_string())
}

/// What a path that is not a regular file is, in words ("a directory", "a FIFO (named pipe)"),
/// from its metadata: the caller never opens it (a FIFO's open blocks until a writer comes).
pub(crate) fn file_kind(metadata: &std::fs::Metadata) -> &'static str {
    let kind = metadata.file_type();
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if kind.is_fifo() {
            return "a FIFO (named pipe)";
        }
        if kind.is_socket() {
            return "a socket";
        }
        if kind.is_char_device() || kind.is_block_device() {
            return "a device";
        }
    }
    if kind.is_dir() {
        "a directory"
    } else if kind.is_file() {
        "a regular file"
    } else {
        "not a regular file"
    }
}

thread_local! {
    /// Set while [`catch_quietly`] runs on this thread: the panic hook then keeps the panic's
    /// location for the error message instead of printing it.
    static QUIET: Cell<bool> = const { Cell::new(false) };
    static LOCATION: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Runs `work`, catching a panic without the panic hook printing "thread ... panicked at" (the
/// caller reports it as an error); `Err` holds the panic's message and location.
///
/// For decoders of untrusted bytes that panic on some inputs: such a panic is a property of the
/// input, reported with the file it came from. Panics elsewhere still print as usual.
pub(crate) fn catch_quietly<T>(work: impl FnOnce() -> T) -> std::result::Result<T, String> {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if QUIET.with(Cell::get) {
                let at = info.location().map(|l| format!("{}:{}", crate_relative(l.file()), l.line()));
                LOCATION.with(|slot| *slot.borrow_mut() = at);
            } else {
                previous(info);
            }
        }));
    });
    let was_quiet = QUIET.with(|q| q.replace(true));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(work));
    QUIET.with(|q| q.set(was_quiet));
    result.map_err(|payload| {
        let message = panic_message(payload.as_ref());
        match LOCATION.with(|slot| slot.borrow_mut().take()) {
            Some(at) => format!("{message}, at {at}"),
            None => message,
        }
    })
}

/// A dependency's source path from its crate directory (`parquet-55.2.0/src/...`), not from the
/// registry of the machine that built the binary.
fn crate_relative(file: &str) -> &str {
    file.split_once("/registry/src/").and_then(|(_, rest)| rest.split_once('/')).map_or(file, |(_, path)| path)
}

pub type Result<T> = std::result::Result<T, Error>;

#[cfg(test)]
mod tests {
    use super::*;

    /// A cause whose text its wrapper does not show.
    #[derive(Debug, thiserror::Error)]
    #[error("outer")]
    struct Outer(#[source] std::io::Error);

    /// Embedding programs move errors across threads and into `anyhow`/`Box<dyn Error>`.
    #[test]
    fn errors_are_send_sync_and_static() {
        fn check<T: std::error::Error + Send + Sync + 'static>() {}
        check::<Error>();
        check::<FitsError>();
        check::<SeriesError>();
        check::<OnnxError>();
        check::<PluginError>();
        check::<TableError>();
        #[cfg(feature = "ms")]
        check::<MsError>();
    }

    #[test]
    fn report_says_each_cause_once() {
        // Not shown by the wrapper: added.
        let outer = Outer(std::io::Error::other("disk on fire"));
        assert_eq!(Report(&outer).to_string(), "outer: disk on fire");
        // A stage's error, whose text shows its cause's: said once, and the module error is
        // found through the stage.
        let fits = FitsError::Invalid { path: "sky.fits".into(), message: "NAXIS3 = 2".into() };
        let e = Error::Stage { stage: "source".into(), kind: "parquet".into(), job: "obs".into(), source: Box::new(fits.into()) };
        let said = "stage 'source' (parquet), job 'obs': sky.fits: NAXIS3 = 2";
        assert_eq!((e.to_string().as_str(), e.report().to_string().as_str()), (said, said));
        assert!(e.module_error().and_then(|m| m.downcast_ref::<FitsError>()).is_some());
        assert_eq!(e.stage(), Some(("source", "parquet", "obs")));
        // An I/O error with a cause inside: the cause joins the text of `Error` itself.
        let io = Error::io("out.fits", std::io::Error::other(Outer(std::io::Error::other("quota"))));
        assert_eq!((io.to_string().as_str(), io.report().to_string().as_str()), ("out.fits: outer: quota", "out.fits: outer: quota"));
    }
}
