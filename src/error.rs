//! The one public error type. Every message names what was wrong (a file, a column, a
//! parameter) and what was expected, so a user can fix the input without reading code.

use std::cell::{Cell, RefCell};
use std::path::PathBuf;
use std::sync::Once;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A problem with an input file: unreadable, malformed, missing a column...
    #[error("{}: {message}", path.display())]
    Input { path: PathBuf, message: String },

    /// A problem at a place in a pipeline description (YAML): the file, line and column (both
    /// from 1), for an editor or a notebook to point at.
    #[error("{}: line {line}, column {column}: {message}", file.display())]
    Located { file: PathBuf, line: usize, column: usize, message: String },

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

    /// The run was interrupted (Ctrl-C) before it finished.
    #[error("interrupted: {0}")]
    Interrupted(String),

    /// A stage panicked: a bug, reported instead of bringing the process down.
    #[error("the stage failed unexpectedly ({0}); this is a bug, please report it")]
    Panic(String),

    /// An operating-system error while reading or writing a file.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
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
pub fn catch_quietly<T>(work: impl FnOnce() -> T) -> std::result::Result<T, String> {
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
