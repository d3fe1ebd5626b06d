//! `kind: native`: a network step in a shared library, through the versioned C ABI of
//! `plugins/r2d2-plugin/include/r2d2_plugin.h` (docs/plugins.md).
//!
//! ```yaml
//! step:
//!   kind: native
//!   library: target/release/libr2d2_landweber.so   # relative to the working directory
//!   iterations: 10                                 # series length
//!   positivity: true                               # x_i = max(0, x_{i-1} + increment)
//!   config: {gain: 1.0}                            # passed to the plugin as JSON
//!   isolation: process                             # default; `none` loads it into r2d2
//!   timeout: 600                                   # seconds per call (isolated plugins)
//!   to: update
//! ```
//!
//! Everything that can be checked is checked when the pipeline is built, before any imaging:
//! the file, the ABI version, the symbols, and the plugin's own creation (its configuration).
//! By default the plugin runs in a supervised child process (`native_host`), so that a crash,
//! an exit or a hang is an error of the run instead of the end of the engine.

use super::native_host::HostedInstance;
use super::{NetworkStep, StepInput};
use crate::{Error, Result};
use r2d2_plugin::host::Instance;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::time::Duration;

pub use super::error::{HostError, PluginError};

#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct NativeConfig {
    /// The shared library; a relative path is relative to the working directory, like every
    /// other path in a pipeline (parquet `files`, writer `prefix`).
    pub library: PathBuf,
    /// Series length: the number of steps the loop runs.
    pub iterations: usize,
    /// Project each new estimate on the positive orthant, as R2D2 does.
    #[serde(default = "yes")]
    pub positivity: bool,
    /// Plugin configuration, any mapping; the plugin receives it as a JSON object.
    #[serde(default)]
    pub config: Option<serde_yaml::Value>,
    /// Where the plugin runs: in a supervised child process (default) or in this one.
    #[serde(default)]
    pub isolation: Isolation,
    /// Seconds one call into an isolated plugin (its creation, each step) may take.
    #[serde(default = "default_timeout")]
    pub timeout: f64,
}

#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Isolation {
    /// In `r2d2-plugin-host`, a child process: a crash, exit or hang is an error of the run.
    #[default]
    Process,
    /// Loaded into this process: no copy per step, but a crashing plugin ends the engine.
    None,
}

fn yes() -> bool {
    true
}

fn default_timeout() -> f64 {
    600.0
}

/// Where the plugin instance lives.
enum Backend {
    InProcess(Instance),
    Isolated(HostedInstance),
    /// Destroyed by [`NetworkStep::finish`].
    TornDown,
}

pub struct NativeStep {
    backend: Backend,
    library: PathBuf,
    iterations: usize,
    positivity: bool,
    size: usize,
    /// Output buffer of the in-process backend, refilled with NaN before each call.
    increment: Vec<f64>,
}

impl NativeStep {
    /// Load, check and create the plugin for N x N images. `stage` names the YAML keys in errors.
    pub fn new(config: NativeConfig, image_size: usize, stage: &str) -> Result<NativeStep> {
        if config.iterations == 0 {
            return Err(Error::parameter(format!("stages.{stage}.iterations"), "expected at least one iteration"));
        }
        if !(config.timeout.is_finite() && config.timeout > 0.0 && config.timeout <= 1e9) {
            return Err(Error::parameter(format!("stages.{stage}.timeout"), format!("expected seconds > 0, got {}", config.timeout)));
        }
        let config_json = match &config.config {
            None | Some(serde_yaml::Value::Null) => "{}".to_string(),
            Some(value @ serde_yaml::Value::Mapping(_)) => serde_json::to_string(value).map_err(|e| {
                Error::parameter(format!("stages.{stage}.config"), format!("cannot be passed to the plugin as JSON: {e}"))
            })?,
            Some(_) => return Err(Error::parameter(format!("stages.{stage}.config"), "expected a mapping (key: value, ...)")),
        };
        let path = &config.library;
        let (named, key) = (|| path.clone(), || stage.to_string());
        // From the metadata, never by opening: a FIFO's open would block.
        match std::fs::metadata(path) {
            Ok(m) if m.is_file() => {}
            Ok(m) => return Err(PluginError::NotAFile { path: named(), stage: key(), kind: crate::error::file_kind(&m) }.into()),
            Err(_) => {
                let cwd = std::env::current_dir().map(|d| d.display().to_string()).unwrap_or_default();
                return Err(PluginError::NotFound { path: named(), stage: key(), cwd }.into());
            }
        }
        super::native_file::check(path).map_err(|source| PluginError::Library { path: named(), stage: key(), source })?;
        let backend = match config.isolation {
            Isolation::None => Backend::InProcess(
                Instance::load(path, &config_json, image_size, config.iterations)
                    .map_err(|source| PluginError::Load { path: named(), stage: key(), source })?,
            ),
            Isolation::Process => Backend::Isolated(
                HostedInstance::start(path, &config_json, image_size, config.iterations, Duration::from_secs_f64(config.timeout))
                    .map_err(|source| match source {
                        HostError::NotFound(_) | HostError::Spawn { .. } | HostError::Handshake { .. } => {
                            PluginError::HostProgram { path: named(), stage: key(), source }
                        }
                        _ => PluginError::Host { path: named(), stage: key(), source },
                    })?,
            ),
        };
        Ok(NativeStep {
            backend,
            library: config.library,
            iterations: config.iterations,
            positivity: config.positivity,
            size: image_size,
            increment: Vec::new(),
        })
    }
}

impl NetworkStep for NativeStep {
    fn series_length(&self) -> usize {
        self.iterations
    }

    fn describe(&self) -> Option<serde_json::Value> {
        // The library's file name: where it lay is the machine's, not the product's.
        let name = self.library.file_name().map(|n| n.to_string_lossy().into_owned());
        Some(serde_json::json!({"kind": "plugin", "library": name}))
    }

    fn step(&mut self, iteration: usize, input: &StepInput<'_>) -> Result<Vec<f64>> {
        let n = input.size;
        let path = &self.library;
        if n != self.size {
            return Err(PluginError::ImageSize { path: path.clone(), created: self.size, size: n }.into());
        }
        let (residual, model, dirty, psf_2n) = (input.residual, input.model, input.dirty, input.psf_2n);
        match &mut self.backend {
            Backend::InProcess(instance) => {
                self.increment.resize(n * n, f64::NAN);
                instance.step(iteration, residual, model, dirty, psf_2n, &mut self.increment)
            }
            Backend::Isolated(hosted) => hosted.step(iteration, residual, model, dirty, psf_2n).map(|d| self.increment = d),
            Backend::TornDown => Err(format!("step {iteration} asked of a plugin already torn down")),
        }
        .map_err(|message| PluginError::Step { path: path.clone(), message })?;
        if let Some(k) = self.increment.iter().position(|v| !v.is_finite()) {
            let (value, x, y) = (self.increment[k], k % n, k / n);
            return Err(PluginError::NonFinite { path: path.clone(), iteration, value, x, y, size: n }.into());
        }
        let project = self.positivity;
        Ok(input
            .model
            .iter()
            .zip(&self.increment)
            .map(|(x, d)| if project { (x + d).max(0.0) } else { x + d })
            .collect())
    }

    fn finish(&mut self) -> Result<()> {
        match std::mem::replace(&mut self.backend, Backend::TornDown) {
            // A crash in the plugin's destroy or the library's unloading ends this process
            // here, before anything is committed; what runs at its exit is not watched.
            Backend::InProcess(instance) => drop(instance),
            Backend::Isolated(mut hosted) => {
                hosted.finish().map_err(|message| PluginError::Teardown { path: self.library.clone(), message })?;
            }
            Backend::TornDown => {}
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::steps::error::{LibraryError, LoadError};
    use super::*;

    fn config(library: PathBuf, isolation: Isolation) -> NativeConfig {
        NativeConfig { library, iterations: 1, positivity: true, config: None, isolation, timeout: 10.0 }
    }

    #[test]
    fn a_library_that_is_not_elf_is_named_with_what_reading_it_found() {
        let dir = tempfile::tempdir().unwrap();
        let library = dir.path().join("libnotes.so");
        std::fs::write(&library, "not a library\n").unwrap();
        for isolation in [Isolation::None, Isolation::Process] {
            let err = NativeStep::new(config(library.clone(), isolation), 16, "step").err().expect("a text file accepted as a plugin");
            let Error::Plugin(PluginError::Library { path, stage, source }) = &err else { panic!("{err:?}") };
            assert_eq!((path, stage.as_str()), (&library, "step"));
            assert!(matches!(source, LibraryError::NotElf), "{source:?}");
            // Error -> PluginError -> LibraryError.
            let module = std::error::Error::source(&err).expect("the plugin error");
            assert!(matches!(module.source().and_then(|c| c.downcast_ref::<LibraryError>()), Some(LibraryError::NotElf)));
            assert_eq!(
                err.to_string(),
                format!("{}: stages.step.library: not a shared library: the file does not start with an ELF header", library.display())
            );
        }
    }

    #[test]
    fn the_loader_error_is_kept_under_the_load_error() {
        // Past the file check (which the step runs first), the loader's own error is the cause.
        let dir = tempfile::tempdir().unwrap();
        let library = dir.path().join("libnotes.so");
        std::fs::write(&library, "not a library\n").unwrap();
        let err = Instance::load(&library, "{}", 16, 1).err().expect("a text file loaded");
        // The kind holds libloading's error, which is also the source.
        let LoadError::Library(loader) = &err else { panic!("{err:?}") };
        let source = std::error::Error::source(&err).expect("the loader's error");
        assert!(std::ptr::addr_eq(source, loader as &dyn std::error::Error));
        let text = crate::error::Report(&err).to_string();
        assert_eq!(text, format!("cannot load the plugin library: {}", crate::error::Report(loader)));
        assert!(text.contains("libnotes.so"), "the loader names the file: {text}");
    }
}
