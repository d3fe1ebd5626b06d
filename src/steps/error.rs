//! What goes wrong with network steps: model series on disk ([`SeriesError`]), ONNX networks
//! ([`OnnxError`]) and native plugins ([`PluginError`]), each keeping the error underneath as
//! its source.

pub use r2d2_plugin::host::LoadError;
use std::path::PathBuf;

/// What is wrong with a model series. Each variant names the file or directory; the cause,
/// where there is one (the YAML parser's error, the system's), is the
/// [`source`](std::error::Error::source).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SeriesError {
    /// No series of that name (or none for the image size) where series are looked up.
    #[error("{}: {message}", name.display())]
    NotFound { name: PathBuf, message: String },
    /// The manifest is not valid YAML for a manifest: `place` is the line, column and key.
    #[error("{}{}{place}", path.display(), if place.is_empty() { "" } else { ": " })]
    Manifest {
        path: PathBuf,
        place: String,
        #[source]
        source: serde_yaml::Error,
    },
    /// A network file the series lists is missing (the system's error is the source).
    #[error("{}: network file of series '{series}' is missing", path.display())]
    MissingNetwork {
        path: PathBuf,
        series: String,
        #[source]
        source: Option<std::io::Error>,
    },
    /// The series' directory, manifest or files are not a series this build runs (the message
    /// says what and what was expected).
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
}

/// What went wrong with an ONNX network or the runtime that runs it. Each variant names the
/// network file; the runtime's own error (ONNX Runtime's, tract's, the system's), where there is
/// one, is the [`source`](std::error::Error::source).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum OnnxError {
    /// Native ONNX Runtime was asked for (`backend: ort`) but cannot be used.
    #[error("invalid backend: ort: native ONNX Runtime is not available")]
    RuntimeUnavailable(#[source] RuntimeUnavailable),
    /// The network file could not be read, or its bytes are not an ONNX model.
    #[error("{}: {what}", path.display())]
    Unreadable {
        path: PathBuf,
        what: &'static str,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A side file holding the network's weights is missing.
    #[error("{}: the weights of {} are missing", path.display(), network.display())]
    MissingWeights {
        path: PathBuf,
        network: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The network is not one a step can run: its inputs, outputs, types or weights are not
    /// what an R2D2 network has (the message says what was expected).
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
    /// The runtime (`ONNX Runtime` or `tract`) could not load the network.
    #[error("{}: {runtime} could not load the network", path.display())]
    Load {
        path: PathBuf,
        runtime: &'static str,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// Running the network failed.
    #[error("{}: inference failed", path.display())]
    Inference {
        path: PathBuf,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The network's output is not what an R2D2 network gives (shape, finite values).
    #[error("{}: {message}", path.display())]
    Output { path: PathBuf, message: String },
}

/// Why native ONNX Runtime cannot be used.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RuntimeUnavailable {
    /// The embedding program (the command line) gave no library.
    #[error("no ONNX Runtime library given (EngineOptions::onnx_runtime)")]
    NotGiven,
    /// The library given could not be loaded or initialised (the loader's or ONNX Runtime's
    /// error: `ort::LoadDynamicError`, `ort::Error`).
    #[error("{}", library.display())]
    Load {
        library: PathBuf,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

/// What went wrong with a native plugin. Each variant names the library (and, while the step is
/// built, the YAML key `stages.<stage>.library`); the cause, where there is one, is the
/// [`source`](std::error::Error::source): what reading the file found ([`LibraryError`]), the
/// loader's error ([`LoadError`], in this process) or the host's ([`HostError`], isolated).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PluginError {
    /// The library file does not exist.
    #[error(
        "{}: stages.{stage}.library: no such plugin library (relative paths are relative to the working directory {cwd}; build the example plugins with `cargo build --release`)",
        path.display()
    )]
    NotFound { path: PathBuf, stage: String, cwd: String },
    /// The path is a directory, a FIFO, ...: `kind` says which.
    #[error("{}: stages.{stage}.library: {kind}, not a regular file (expected a plugin shared library)", path.display())]
    NotAFile { path: PathBuf, stage: String, kind: &'static str },
    /// The file is not a plugin library for this machine (found by reading it, not loading it).
    #[error("{}: stages.{stage}.library", path.display())]
    Library {
        path: PathBuf,
        stage: String,
        #[source]
        source: LibraryError,
    },
    /// Loading or creating the plugin in this process failed (`isolation: none`).
    #[error("{}: stages.{stage}.library", path.display())]
    Load {
        path: PathBuf,
        stage: String,
        #[source]
        source: LoadError,
    },
    /// Starting the plugin in its host process, or creating it there, failed.
    #[error("{}: stages.{stage}.library", path.display())]
    Host {
        path: PathBuf,
        stage: String,
        #[source]
        source: HostError,
    },
    /// The plugin host could not be found or started, or is not a plugin host: the library is
    /// not to blame (nothing of it ran).
    #[error("stages.{stage}: cannot start the plugin host (isolation: process)")]
    HostProgram {
        path: PathBuf,
        stage: String,
        #[source]
        source: HostError,
    },
    /// A step failed: the plugin's own message, or how its host process ended.
    #[error("{}: {message}", path.display())]
    Step { path: PathBuf, message: String },
    /// Tearing the plugin down failed: how its host process ended then.
    #[error("{}: {message}", path.display())]
    Teardown { path: PathBuf, message: String },
    /// A step returned an increment that is not finite everywhere.
    #[error(
        "{}: plugin step {iteration} returned a non-finite increment {value} at pixel (x {x}, y {y}) (every one of the {size} x {size} values must be written and finite)",
        path.display()
    )]
    NonFinite { path: PathBuf, iteration: usize, value: f64, x: usize, y: usize, size: usize },
    /// The job's image size is not the one the plugin was created for.
    #[error("{}: the plugin was created for {created} x {created} images, the job has {size} x {size}", path.display())]
    ImageSize { path: PathBuf, created: usize, size: usize },
}

/// What is wrong with a plugin library file, found by reading it (the caller names the file).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LibraryError {
    #[error("cannot read the plugin library")]
    Unreadable(#[source] std::io::Error),
    #[error("not a shared library: the file does not start with an ELF header")]
    NotElf,
    #[error("not a shared library for this machine: not a 64-bit little-endian ELF file")]
    NotElf64,
    #[error("not a shared library: ELF type {0} (a shared object is type 3)")]
    NotShared(u16),
    #[error("built for another machine (ELF machine {machine}), this r2d2 runs on {}", std::env::consts::ARCH)]
    OtherMachine { machine: u16 },
    #[error("not a valid shared library: {0}")]
    Damaged(&'static str),
    #[error("not an r2d2 plugin: it exports no symbols (no dynamic symbol table)")]
    NoSymbols,
    #[error("not an r2d2 plugin: missing symbol {0} (read from the file, not loaded)")]
    NotAPlugin(String),
    #[error("an r2d2 plugin missing symbol {0} (read from the file, not loaded)")]
    MissingSymbol(String),
}

/// Why a plugin could not be started in its host process (the caller names the library).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum HostError {
    /// The host executable was not found ([`find_host`] says where it looked).
    #[error("{0}")]
    NotFound(String),
    /// The system could not start the host (`host`: its path, or `R2D2_PLUGIN_HOST=PATH`).
    #[error("{host} could not be executed")]
    Spawn {
        host: String,
        #[source]
        source: std::io::Error,
    },
    /// The executable started is not a working plugin host: it ended, said something else or
    /// nothing before its greeting (`how`), with no plugin loaded yet.
    #[error("{host} is not an r2d2 plugin host: {how}")]
    Handshake { host: String, how: String },
    /// The system could not start the thread that reads the host's replies.
    #[error("cannot start a thread")]
    Thread(#[source] std::io::Error),
    /// The plugin (its creation) or its host process failed: the plugin's message, or how the
    /// process ended, as text (it crosses a process boundary).
    #[error("{0}")]
    Failed(String),
}
