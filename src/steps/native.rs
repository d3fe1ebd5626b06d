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
//!   to: update
//! ```
//!
//! Everything that can be checked is checked when the pipeline is built, before any imaging:
//! the file, the ABI version, the symbols, and the plugin's own creation (its configuration).

use super::{NetworkStep, StepInput};
use crate::{Error, Result};
use libloading::Library;
use r2d2_plugin::{symbols, AbiVersionFn, CreateFn, DestroyFn, LastErrorFn, RawStepInput, StepFn, ABI_VERSION};
use serde::Deserialize;
use std::ffi::{c_char, c_void, CStr, CString};
use std::path::{Path, PathBuf};
use std::ptr::NonNull;

#[derive(Clone, Debug, Deserialize)]
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
}

fn yes() -> bool {
    true
}

/// A created plugin instance and the library it lives in.
struct Instance {
    handle: NonNull<c_void>,
    step: StepFn,
    last_error: LastErrorFn,
    destroy: DestroyFn,
    path: PathBuf,
    /// Declared last so it is dropped after `Drop::drop` has destroyed the handle: the
    /// library's code must stay mapped while the handle exists.
    _library: Library,
}

// SAFETY: the ABI (header, "Threads") requires that a handle may be used from any thread, one
// thread at a time; `Instance` is only used through `&mut self` (or dropped), so Rust's
// ownership rules already give one thread at a time. The function pointers are plain code.
unsafe impl Send for Instance {}

impl Drop for Instance {
    fn drop(&mut self) {
        // SAFETY: the handle came from this library's create, is destroyed exactly once here,
        // and the library (a later field) is still loaded.
        unsafe { (self.destroy)(self.handle.as_ptr()) };
    }
}

/// A message returned by the plugin (NUL-terminated UTF-8 owned by the plugin).
///
/// # Safety
/// `p` is NULL or points to a NUL-terminated string valid until the next call into the plugin.
unsafe fn plugin_message(p: *const c_char) -> String {
    if p.is_null() {
        return "(the plugin gave no message)".into();
    }
    // SAFETY: non-NULL and NUL-terminated by the caller's contract; copied out at once.
    let text = unsafe { CStr::from_ptr(p) }.to_string_lossy().trim().to_string();
    if text.is_empty() {
        "(the plugin gave an empty message)".into()
    } else {
        text
    }
}

impl Instance {
    fn load(path: &Path, config_json: &str, image_size: usize, iterations: usize) -> Result<Instance> {
        let fail = |message: String| Error::input(path, message);
        if !path.is_file() {
            let cwd = std::env::current_dir().map(|d| d.display().to_string()).unwrap_or_default();
            return Err(fail(format!(
                "no such plugin library (relative paths are relative to the working directory {cwd}; build the example plugins with `cargo build --release`)"
            )));
        }
        // SAFETY: loading a library runs its initialisers, arbitrary code the user chose to
        // trust by naming it in the pipeline; nothing more can be checked before loading.
        let library = unsafe { Library::new(path) }.map_err(|e| fail(format!("cannot load the plugin library: {e}")))?;
        let symbol_name = |s: &[u8]| String::from_utf8_lossy(&s[..s.len() - 1]).into_owned();
        // SAFETY (each `get`): the type is the header's signature for that symbol, which a
        // library exporting the symbol promises by the ABI version checked first. The copied
        // function pointers are only used while `library` stays loaded (it lives in `Instance`).
        let abi_version: AbiVersionFn = *unsafe { library.get::<AbiVersionFn>(symbols::ABI_VERSION) }.map_err(|e| {
            fail(format!("not an r2d2 plugin: missing symbol {} ({e})", symbol_name(symbols::ABI_VERSION)))
        })?;
        // SAFETY: takes no arguments and, by the ABI, cannot fail.
        let version = unsafe { abi_version() };
        if version != ABI_VERSION {
            return Err(fail(format!(
                "plugin ABI version {version}, but this r2d2 speaks version {ABI_VERSION}: rebuild the plugin against r2d2_plugin.h version {ABI_VERSION}"
            )));
        }
        fn get<T: Copy>(library: &Library, name: &[u8], path: &Path) -> Result<T> {
            // SAFETY: see above; T is the header's signature for `name`.
            unsafe { library.get::<T>(name) }.map(|s| *s).map_err(|e| {
                let shown = String::from_utf8_lossy(&name[..name.len() - 1]).into_owned();
                Error::input(path, format!("plugin ABI version {ABI_VERSION} but missing symbol {shown} ({e})"))
            })
        }
        let create: CreateFn = get(&library, symbols::CREATE, path)?;
        let step: StepFn = get(&library, symbols::STEP, path)?;
        let last_error: LastErrorFn = get(&library, symbols::LAST_ERROR, path)?;
        let destroy: DestroyFn = get(&library, symbols::DESTROY, path)?;
        let config = CString::new(config_json).map_err(|_| fail("the plugin configuration contains a NUL character".into()))?;
        let iterations = u32::try_from(iterations).map_err(|_| fail(format!("{iterations} iterations is too many")))?;
        // SAFETY: a NUL-terminated string that outlives the call, as create requires.
        let handle = unsafe { create(config.as_ptr(), image_size as u64, iterations) };
        let Some(handle) = NonNull::new(handle) else {
            // SAFETY: NULL asks for the calling thread's create error, read right after create.
            let message = unsafe { plugin_message(last_error(std::ptr::null())) };
            return Err(fail(format!("the plugin refused its configuration {config_json}: {message}")));
        };
        Ok(Instance { handle, step, last_error, destroy, path: path.to_path_buf(), _library: library })
    }
}

pub struct NativeStep {
    instance: Instance,
    iterations: usize,
    positivity: bool,
    size: usize,
    /// Host-side output buffer, refilled with NaN before each call.
    increment: Vec<f64>,
}

impl NativeStep {
    /// Load, check and create the plugin for N x N images. `stage` names the YAML keys in errors.
    pub fn new(config: NativeConfig, image_size: usize, stage: &str) -> Result<NativeStep> {
        if config.iterations == 0 {
            return Err(Error::parameter(format!("stages.{stage}.iterations"), "expected at least one iteration"));
        }
        let config_json = match &config.config {
            None | Some(serde_yaml::Value::Null) => "{}".to_string(),
            Some(value @ serde_yaml::Value::Mapping(_)) => serde_json::to_string(value).map_err(|e| {
                Error::parameter(format!("stages.{stage}.config"), format!("cannot be passed to the plugin as JSON: {e}"))
            })?,
            Some(_) => return Err(Error::parameter(format!("stages.{stage}.config"), "expected a mapping (key: value, ...)")),
        };
        let instance = Instance::load(&config.library, &config_json, image_size, config.iterations).map_err(|e| match e {
            Error::Input { path, message } => Error::Input { path, message: format!("stages.{stage}.library: {message}") },
            other => other,
        })?;
        Ok(NativeStep {
            instance,
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

    fn step(&mut self, iteration: usize, input: &StepInput<'_>) -> Result<Vec<f64>> {
        let n = input.size;
        let path = &self.instance.path;
        if n != self.size {
            return Err(Error::input(path, format!("the plugin was created for {0} x {0} images, the job has {n} x {n}", self.size)));
        }
        let pixels = n * n;
        let lengths = [input.residual.len(), input.model.len(), input.dirty.len()];
        if lengths.iter().any(|&l| l != pixels) || input.psf_2n.len() != 4 * pixels {
            return Err(Error::parameter("native step", format!("inconsistent image sizes for N = {n}")));
        }
        self.increment.clear();
        self.increment.resize(pixels, f64::NAN);
        let raw = RawStepInput {
            size: n as u64,
            iteration: iteration as u64,
            residual: input.residual.as_ptr(),
            model: input.model.as_ptr(),
            dirty: input.dirty.as_ptr(),
            psf_2n: input.psf_2n.as_ptr(),
        };
        // SAFETY: a live handle used by this thread only (`&mut self`); every input pointer
        // covers the lengths checked above and outlives the call; the output buffer has N x N
        // writable values and is a separate allocation, so it overlaps no input.
        let status = unsafe { (self.instance.step)(self.instance.handle.as_ptr(), &raw, self.increment.as_mut_ptr()) };
        if status != 0 {
            // SAFETY: the handle's message, valid until the next call, copied at once.
            let message = unsafe { plugin_message((self.instance.last_error)(self.instance.handle.as_ptr())) };
            return Err(Error::input(path, format!("plugin step {iteration} failed (status {status}): {message}")));
        }
        if let Some(k) = self.increment.iter().position(|v| !v.is_finite()) {
            return Err(Error::input(
                path,
                format!(
                    "plugin step {iteration} returned a non-finite increment {} at pixel (x {}, y {}) (every one of the {n} x {n} values must be written and finite)",
                    self.increment[k],
                    k % n,
                    k / n
                ),
            ));
        }
        let project = self.positivity;
        Ok(input
            .model
            .iter()
            .zip(&self.increment)
            .map(|(x, d)| if project { (x + d).max(0.0) } else { x + d })
            .collect())
    }
}
