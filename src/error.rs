//! The one public error type. Every message names what was wrong (a file, a column, a
//! parameter) and what was expected, so a user can fix the input without reading code.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A problem with an input file: unreadable, malformed, missing a column...
    #[error("{}: {message}", path.display())]
    Input { path: PathBuf, message: String },

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
}

/// The message a panic was raised with (`panic!("...")` gives a `&str` or a `String`).
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "no message".to_string())
}

pub type Result<T> = std::result::Result<T, Error>;
