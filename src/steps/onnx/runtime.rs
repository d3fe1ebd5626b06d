//! ONNX inference backends, chosen at run time: native ONNX Runtime (through `ort`, the library
//! loaded dynamically: no download at build time) when its shared library is found, else tract
//! (pure Rust, always available, slower).
//!
//! tract is used directly rather than through `ort-tract` because the R2D2 U-Nets need their
//! input shape pinned before optimisation (tract cannot type a transposed convolution over
//! symbolic H and W), which `ort`'s session API has no way to say.

pub use crate::steps::error::{OnnxError, RuntimeUnavailable};
use super::check::invalid;
// The file check by its former path (the tests and the command line name it so).
pub use super::check::{check_network, Signature};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendChoice {
    /// Native ONNX Runtime if found, else tract.
    #[default]
    Auto,
    /// Native ONNX Runtime, or an error saying where it was looked for.
    Ort,
    /// tract, even when ONNX Runtime is available.
    Tract,
}

impl std::str::FromStr for BackendChoice {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "auto" => Ok(BackendChoice::Auto),
            "ort" => Ok(BackendChoice::Ort),
            "tract" => Ok(BackendChoice::Tract),
            other => Err(Error::parameter("backend", format!("expected auto, ort or tract, got '{other}'"))),
        }
    }
}

/// How far ONNX Runtime rewrites a network's graph before running it. Measured on the reference
/// U-Net (31 M parameters, 512^2, 2 threads, weights mapped from the file): `all` infers 12 % faster (1.80 s
/// against 2.03 s) but copies every weight into its blocked layout at load (0.31 s against
/// 0.03 s; 136 MB resident against 21 MB before the first run) and needs 130 MB more at the
/// inference peak (528 MB against 396 MB). On the shipped series' small U-Nets (16 channels,
/// 2 MB) the copy costs nothing worth saving and `all` with the CPU arena is about a third
/// faster than `extended` without it: `auto` chooses by the network's weight bytes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum GraphOptimization {
    /// `all` with the CPU arena for networks of at most [`SMALL_NETWORK_BYTES`] of weights,
    /// `extended` for larger ones.
    #[default]
    Auto,
    /// Node fusions, no layout change: weights stay as they are in the file (mapped). The
    /// least memory.
    Extended,
    /// Also the layout optimisations (convolutions in ONNX Runtime's blocked NCHWc layout).
    All,
}

/// Networks with at most this many bytes of weights count as small for
/// [`GraphOptimization::Auto`]: copying their weights into the blocked layout and keeping an
/// arena for one inference's activations costs tens of MB, against hundreds for the
/// reference U-Net (118 MB of weights), where the arena added 200 MB for a 4 % gain.
pub const SMALL_NETWORK_BYTES: u64 = 16 << 20;

impl std::str::FromStr for GraphOptimization {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "auto" => Ok(GraphOptimization::Auto),
            "extended" => Ok(GraphOptimization::Extended),
            "all" => Ok(GraphOptimization::All),
            other => Err(Error::parameter("graph_optimization", format!("expected auto, extended or all, got '{other}'"))),
        }
    }
}

impl GraphOptimization {
    /// The level and whether ONNX Runtime's CPU arena is used, for a network with
    /// `weight_bytes` of weights. The arena reuses freed activation buffers within a run
    /// instead of mapping fresh pages for each (the allocator policy unmaps large blocks at
    /// once); it only pays where the activations are small beside the work on them.
    fn resolve(self, weight_bytes: u64) -> (GraphOptimization, bool) {
        let small = weight_bytes <= SMALL_NETWORK_BYTES;
        let level = match self {
            GraphOptimization::Auto if small => GraphOptimization::All,
            GraphOptimization::Auto => GraphOptimization::Extended,
            explicit => explicit,
        };
        (level, small && level == GraphOptimization::All)
    }
}

/// An ONNX network with one `[1, 2, N, N]` input and one `[1, 1, N, N]` output (float32).
pub trait Network: Send {
    fn run(&mut self, input: &[f32]) -> Result<Vec<f32>>;
}

/// The backend a run uses, with the ONNX Runtime library when native.
#[derive(Clone, Debug)]
pub enum Runtime {
    Ort { library: PathBuf, version: String, threads: usize, optimization: GraphOptimization },
    Tract,
}

/// The ONNX Runtime environment: the library can be loaded only once per process.
static ORT_ENV: OnceLock<(PathBuf, ort::environment::Environment)> = OnceLock::new();
/// Held while ONNX Runtime is being loaded: only a success is kept, so a run before the library
/// was given (which falls back to tract, or fails) does not stop a later one from loading it.
static ORT_LOADING: Mutex<()> = Mutex::new(());

impl Runtime {
    /// Pick the backend. `threads` = intra-op threads for ONNX Runtime (0: its default).
    pub fn select(choice: BackendChoice, threads: usize) -> Result<Runtime> {
        if choice == BackendChoice::Tract {
            return Ok(Runtime::Tract);
        }
        match ort_environment() {
            Ok((library, _)) => Ok(Runtime::Ort { version: ort_version(library), library: library.clone(), threads, optimization: GraphOptimization::default() }),
            Err(why) if choice == BackendChoice::Auto => {
                log::info!("native ONNX Runtime not used ({}); using tract", crate::error::Report(&why));
                Ok(Runtime::Tract)
            }
            Err(why) => Err(OnnxError::RuntimeUnavailable(why).into()),
        }
    }

    /// The graph optimisation level ONNX Runtime sessions use (tract has its own, fixed).
    pub fn with_graph_optimization(self, level: GraphOptimization) -> Runtime {
        match self {
            Runtime::Ort { library, version, threads, .. } => Runtime::Ort { library, version, threads, optimization: level },
            Runtime::Tract => Runtime::Tract,
        }
    }

    pub fn describe(&self) -> String {
        match self {
            Runtime::Ort { library, version, .. } => format!("ONNX Runtime {version} (native, {})", library.display()),
            Runtime::Tract => format!("tract {} (pure Rust)", tract_version()),
        }
    }

    /// Load a network for `size x size` images (`signature`: from [`check_network`]).
    pub fn load(&self, path: &Path, size: usize, signature: &Signature) -> Result<Box<dyn Network>> {
        match self {
            Runtime::Ort { threads, optimization, .. } => Ok(Box::new(OrtNetwork::load(path, size, *threads, *optimization, signature, true)?)),
            Runtime::Tract => Ok(Box::new(TractNetwork::load(path, size)?)),
        }
    }
}

/// The ONNX Runtime library the embedding program chose (`EngineOptions::onnx_runtime`).
static ORT_LIBRARY: Mutex<Option<PathBuf>> = Mutex::new(None);

/// Sets the native ONNX Runtime library `onnx` steps load. A process loads one: another
/// library after the first was loaded is refused.
pub fn use_onnx_runtime(library: &Path) -> Result<()> {
    if let Some((loaded, _)) = ORT_ENV.get() {
        if loaded != library {
            return Err(Error::parameter(
                "onnx_runtime",
                format!("{}: this process loaded {} already, and ONNX Runtime cannot be loaded twice", library.display(), loaded.display()),
            ));
        }
    }
    if !library.is_file() {
        return Err(Error::input(library, "the ONNX Runtime library is not a file"));
    }
    *ORT_LIBRARY.lock().expect("ONNX Runtime library") = Some(library.to_path_buf());
    Ok(())
}

fn ort_environment() -> std::result::Result<&'static (PathBuf, ort::environment::Environment), RuntimeUnavailable> {
    if let Some(env) = ORT_ENV.get() {
        return Ok(env);
    }
    let _loading = ORT_LOADING.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    if let Some(env) = ORT_ENV.get() {
        return Ok(env);
    }
    let chosen = ORT_LIBRARY.lock().expect("ONNX Runtime library").clone();
    // The library does not search the machine for one: that is the caller's policy (the
    // command line looks in the usual places and passes what it finds).
    let library = chosen.ok_or(RuntimeUnavailable::NotGiven)?;
    let failed = |source| RuntimeUnavailable::Load { library: library.clone(), source };
    let builder = ort::init_from(&library).map_err(|e| failed(e.into()))?;
    let env = builder.with_name("r2d2").build().map_err(|e| failed(e.into()))?;
    match register_shared_cpu_arena(&env) {
        Ok(()) => SHARED_CPU_ARENA.store(true, std::sync::atomic::Ordering::Relaxed),
        Err(why) => log::debug!("no shared CPU arena in ONNX Runtime ({why}); each small network keeps its own"),
    }
    Ok(ORT_ENV.get_or_init(|| (library, env)))
}

/// Whether the environment holds the CPU arena small networks share.
static SHARED_CPU_ARENA: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Registers one CPU arena with the environment, which the sessions of small networks use
/// (`session.use_env_allocators`) instead of an arena each. A series runs its networks one
/// after the other, each a session of its own: with an arena per session every network
/// faulted its activations in afresh (the allocator policy unmaps large blocks when the
/// session goes), and those page faults were a sizeable part of a series' time on 2 cores.
/// The shared arena keeps one small network's activations resident between networks.
fn register_shared_cpu_arena(env: &ort::environment::Environment) -> std::result::Result<(), String> {
    use ort::memory::{AllocationDevice, AllocatorType, MemoryInfo, MemoryType};
    use ort::AsPointer;
    let info = MemoryInfo::new(AllocationDevice::CPU, 0, AllocatorType::Arena, MemoryType::Default).map_err(|e| e.to_string())?;
    let api = ort::api();
    // SAFETY: `env` and `info` are live handles of the loaded library for the whole call (the
    // environment lives in a static once built; ONNX Runtime copies what it needs of `info`).
    // A null arena configuration asks for ONNX Runtime's defaults. The returned status is
    // either null (success) or owned by us: its message is copied before it is released once.
    unsafe {
        let status = (api.CreateAndRegisterAllocator)(env.ptr().cast_mut(), info.ptr(), std::ptr::null());
        if status.0.is_null() {
            return Ok(());
        }
        let message = std::ffi::CStr::from_ptr((api.GetErrorMessage)(status.0)).to_string_lossy().into_owned();
        (api.ReleaseStatus)(status.0);
        Err(message)
    }
}

/// The version from the library's file name (`libonnxruntime.so.1.31.1`); ONNX Runtime's build
/// string carries a git branch, not always a version.
fn ort_version(library: &Path) -> String {
    let name = library.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    name.split_once(".so.").map_or_else(|| "(version unknown)".to_string(), |(_, v)| v.to_string())
}

fn tract_version() -> &'static str {
    env!("R2D2_TRACT_VERSION")
}

struct OrtNetwork {
    session: ort::session::Session,
    path: PathBuf,
    size: usize,
}

impl OrtNetwork {
    /// `map_weights`: load the skeleton so the weights are mapped from the file (the default;
    /// false only to compare with ONNX Runtime's own loading).
    fn load(path: &Path, size: usize, threads: usize, optimization: GraphOptimization, signature: &Signature, map_weights: bool) -> Result<OrtNetwork> {
        let (_, env) = ort_environment().map_err(OnnxError::RuntimeUnavailable)?;
        let fail = |e: ort::Error| OnnxError::Load { path: path.to_path_buf(), runtime: "ONNX Runtime", source: e.into() };
        // The weights the level and the arena are chosen by: the file (inline weights) and
        // its external-data side files.
        let weight_bytes = std::fs::metadata(path).map_or(0, |m| m.len()) + signature.external_bytes;
        let (level, arena) = optimization.resolve(weight_bytes);
        log::debug!("{}: {} MB of weights, graph optimisation {level:?}, CPU arena {}", path.display(), weight_bytes >> 20, if arena { "on" } else { "off" });
        // No CPU arena for large networks: an arena keeps the peak activation memory of every
        // resident session allocated between runs (measured with the reference U-Net at 512^2:
        // 1.95 GB peak with it). Freed buffers go back to the system instead; inference time
        // is barely changed there.
        let cpu = ort::ep::CPU::default().with_arena_allocator(arena).build();
        // Extended graph optimisations (level 2) keep the weights as they are; the layout
        // ones rewrite every convolution to a blocked NCHWc layout, which copies every weight
        // and adds reorder buffers to the activations (see GraphOptimization for the trade).
        // No memory pattern: it kept one inference's peak allocated between runs (+110 MB).
        use ort::session::builder::GraphOptimizationLevel as Level;
        let level = match level {
            GraphOptimization::All => Level::All,
            _ => Level::Level2,
        };
        let mut builder = ort::session::Session::builder(env)
            .map_err(|e| fail(e.into()))?
            .with_execution_providers([cpu])
            .map_err(|e| fail(e.into()))?
            .with_optimization_level(level)
            .map_err(|e| fail(e.into()))?
            .with_memory_pattern(false)
            .map_err(|e| fail(e.into()))?
            // Idle intra-op threads sleep instead of spinning: between two inferences the
            // engine grids and updates the residual on the same cores, and spinning threads
            // slowed both (by a sixth on 2 cores).
            .with_config_entry("session.intra_op.allow_spinning", "0")
            .map_err(|e| fail(e.into()))?;
        if arena {
            // The environment's shared CPU arena where one was registered (else ONNX Runtime
            // falls back to the session's own).
            builder = builder.with_env_allocators().map_err(|e| fail(e.into()))?;
        }
        // Symbolic dimensions take the one shape this pipeline feeds: static shapes let ONNX
        // Runtime plan and reuse activation buffers.
        let shape = [1, 2, size as i64, size as i64];
        for (name, value) in signature.input_params.iter().zip(shape) {
            if let Some(name) = name {
                builder = builder.with_dimension_override(name, value).map_err(|e| fail(e.into()))?;
            }
        }
        if threads > 0 {
            builder = builder.with_intra_threads(threads).map_err(|e| fail(e.into()))?;
        }
        let session = match signature.mapped.as_ref().filter(|_| map_weights) {
            Some(mapped) => {
                // The skeleton's references are offsets into the file as it was checked.
                if mapped.is_stale(path) {
                    return Err(invalid(path, "the network file changed after it was checked; restart the run"));
                }
                // External data is looked up in the model's directory (a model from memory has
                // no directory of its own).
                let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
                builder = builder
                    .with_config_entry("session.model_external_initializers_file_folder_path", dir.to_str().unwrap_or("."))
                    .map_err(|e| fail(e.into()))?;
                match builder.commit_from_memory(&mapped.skeleton) {
                    Ok(session) => session,
                    // An ONNX Runtime without that option (older than this one) looks for the
                    // weights elsewhere: let it read the file whole rather than fail.
                    Err(e) => {
                        log::info!("{}: ONNX Runtime could not map the weights from the file ({e}); reading it whole", path.display());
                        builder.commit_from_file(path).map_err(|e| fail(e.into()))?
                    }
                }
            }
            None => builder.commit_from_file(path).map_err(|e| fail(e.into()))?,
        };
        Ok(OrtNetwork { session, path: path.to_path_buf(), size })
    }
}

impl Network for OrtNetwork {
    fn run(&mut self, input: &[f32]) -> Result<Vec<f32>> {
        let n = self.size;
        let fail = |e: ort::Error| OnnxError::Inference { path: self.path.clone(), source: e.into() };
        let tensor = ort::value::Tensor::from_array(([1usize, 2, n, n], input.to_vec())).map_err(|e| fail(e.into()))?;
        let outputs = self.session.run(ort::inputs![tensor]).map_err(|e| fail(e.into()))?;
        let (shape, data) = outputs[0].try_extract_tensor::<f32>().map_err(|e| fail(e.into()))?;
        let dims: Vec<i64> = shape.iter().copied().collect();
        if dims != [1, 1, n as i64, n as i64] {
            return Err(OnnxError::Output { path: self.path.clone(), message: format!("expected an output of shape [1, 1, {n}, {n}], got {dims:?}") }.into());
        }
        Ok(data.to_vec())
    }
}

struct TractNetwork {
    plan: std::sync::Arc<tract_onnx::prelude::TypedRunnableModel>,
    path: PathBuf,
    size: usize,
}

impl TractNetwork {
    fn load(path: &Path, size: usize) -> Result<TractNetwork> {
        use tract_onnx::prelude::*;
        let fail = |source: Box<dyn std::error::Error + Send + Sync>| OnnxError::Load { path: path.to_path_buf(), runtime: "tract", source };
        // tract panics on some damaged files (a node naming a value no node makes): an error
        // naming the file, without the panic's text on the terminal.
        let plan = crate::error::catch_quietly(|| {
            tract_onnx::onnx()
                .model_for_path(path)
                .and_then(|m| m.with_input_fact(0, f32::fact([1, 2, size, size]).into()))
                .and_then(|m| m.into_optimized())
                .and_then(|m| m.into_runnable())
        })
        .map_err(|panic| fail(format!("{panic} (a damaged file?)").into()))?
        .map_err(|e: TractError| fail(e.into()))?;
        Ok(TractNetwork { plan, path: path.to_path_buf(), size })
    }
}

impl Network for TractNetwork {
    fn run(&mut self, input: &[f32]) -> Result<Vec<f32>> {
        use tract_onnx::prelude::*;
        let n = self.size;
        let fail = |e: TractError| OnnxError::Inference { path: self.path.clone(), source: e.into() };
        let tensor = Tensor::from_shape(&[1, 2, n, n], input).map_err(|e| fail(e.into()))?;
        let out = self.plan.run(tvec!(tensor.into_tvalue())).map_err(|e| fail(e.into()))?;
        let view = out[0].to_plain_array_view::<f32>().map_err(|e| fail(e.into()))?;
        if view.shape() != [1, 1, n, n] {
            return Err(OnnxError::Output { path: self.path.clone(), message: format!("expected an output of shape [1, 1, {n}, {n}], got {:?}", view.shape()) }.into());
        }
        Ok(view.iter().copied().collect())
    }
}

/// The command line's lookup, for the tests that need native ONNX Runtime.
#[cfg(test)]
#[path = "../../cli/onnx_runtime.rs"]
mod lookup;

/// Injects the ONNX Runtime library the command line would find (tests only).
#[cfg(test)]
pub(crate) fn use_onnx_runtime_for_tests() {
    let library = lookup::find_onnxruntime().expect("native ONNX Runtime (pip install onnxruntime)");
    use_onnx_runtime(&library).expect("the library loads");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_graph_optimisation_takes_the_layout_and_arena_for_small_networks_only() {
        use GraphOptimization::*;
        assert_eq!(Auto.resolve(2 << 20), (All, true));
        assert_eq!(Auto.resolve(SMALL_NETWORK_BYTES), (All, true));
        assert_eq!(Auto.resolve(SMALL_NETWORK_BYTES + 1), (Extended, false));
        // An explicit level is kept; `extended` (the least memory) never takes the arena.
        assert_eq!(Extended.resolve(2 << 20), (Extended, false));
        assert_eq!(All.resolve(2 << 20), (All, true));
        assert_eq!(All.resolve(118 << 20), (All, false));
        assert_eq!("auto".parse::<GraphOptimization>().unwrap(), Auto);
        let e = "fast".parse::<GraphOptimization>().unwrap_err().to_string();
        assert!(e.contains("graph_optimization") && e.contains("'fast'"), "{e}");
    }

    #[test]
    fn a_file_that_is_not_onnx_is_unreadable_keeping_the_decoder_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("net.onnx");
        std::fs::write(&path, [0xffu8; 64]).unwrap();
        let err = check_network(&path, 64).unwrap_err();
        let Error::Onnx(OnnxError::Unreadable { path: named, what, source }) = &err else { panic!("{err:?}") };
        assert_eq!((named.as_path(), *what), (path.as_path(), "not a readable ONNX model"));
        let text = err.to_string();
        assert!(text.starts_with(&format!("{}: not a readable ONNX model: ", path.display())), "{text}");
        assert_eq!(text.matches(&source.to_string()).count(), 1, "{text}");
        // tract is told the same file: its error chain is kept whole, each part said once.
        let err = match TractNetwork::load(&path, 64) {
            Err(e) => e,
            Ok(_) => panic!("tract loaded 64 bytes of 0xff"),
        };
        let Error::Onnx(OnnxError::Load { runtime: "tract", source, .. }) = &err else { panic!("{err:?}") };
        let text = err.to_string();
        assert!(text.contains("tract could not load the network: ") && text.contains(&source.to_string()), "{text}");
        let mut cause = std::error::Error::source(&err);
        while let Some(c) = cause {
            assert_eq!(text.matches(&c.to_string()).count(), 1, "'{c}' in {text}");
            cause = c.source();
        }
    }

    #[test]
    fn onnx_runtime_maps_inline_weights_from_the_file_and_infers_the_same() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mapped-unet.onnx");
        std::fs::copy(super::super::tests::test_models().join("unet.onnx"), &path).unwrap();
        let signature = check_network(&path, 64).unwrap();
        let mapped = signature.mapped.as_ref().expect("the test U-Net has weights over 4 KiB");
        assert!(mapped.weights >= 3 && mapped.bytes > 20_000, "{mapped:?}");
        assert!((mapped.skeleton.len() as u64) < std::fs::metadata(&path).unwrap().len() - mapped.bytes + 1024);
        let input = super::super::tests::unet_input();
        { use_onnx_runtime_for_tests(); Runtime::select(BackendChoice::Ort, 1) }.expect("native ONNX Runtime (pip install onnxruntime)");
        // `extended`: the level that keeps the weights where they are (`all` copies them).
        let opt = GraphOptimization::Extended;
        let mut copied = OrtNetwork::load(&path, 64, 1, opt, &signature, false).unwrap();
        let mut from_file = OrtNetwork::load(&path, 64, 1, opt, &signature, true).unwrap();
        assert_eq!(from_file.run(&input).unwrap(), copied.run(&input).unwrap(), "mapping changes no output value");
        // ONNX Runtime mapped the model file itself (its own loading reads it and closes it).
        #[cfg(target_os = "linux")]
        {
            let maps = std::fs::read_to_string("/proc/self/maps").unwrap();
            assert!(maps.contains("mapped-unet.onnx"), "the model file is not mapped:\n{maps}");
        }
        drop(from_file);
        // When ONNX Runtime cannot resolve the skeleton's references (as an older one without
        // the folder option would not), the file is read whole instead: same output.
        let file = std::fs::File::open(&path).unwrap();
        let len = file.metadata().unwrap().len();
        let elsewhere = super::super::mapped_weights::skeleton(file, len, "no-such-file.onnx", super::super::mapped_weights::MIN_MAPPED_BYTES).unwrap();
        let mut unresolvable = signature.clone();
        unresolvable.mapped.as_mut().unwrap().skeleton = std::sync::Arc::new(elsewhere.bytes);
        let mut fallback = OrtNetwork::load(&path, 64, 1, opt, &unresolvable, true).unwrap();
        assert_eq!(fallback.run(&input).unwrap(), copied.run(&input).unwrap(), "the fallback gives the same output");
        // A file changed after the check is refused, not read at stale offsets.
        let mut bytes = std::fs::read(&path).unwrap();
        bytes.push(0);
        std::fs::write(&path, bytes).unwrap();
        let e = OrtNetwork::load(&path, 64, 1, opt, &signature, true).err().expect("stale skeleton refused").to_string();
        assert!(e.contains("mapped-unet.onnx") && e.contains("changed"), "{e}");
    }

    #[test]
    fn small_networks_share_the_environment_arena_one_after_the_other_with_the_same_output() {
        let path = super::super::tests::test_models().join("unet.onnx");
        let signature = check_network(&path, 64).unwrap();
        let input = super::super::tests::unet_input();
        { use_onnx_runtime_for_tests(); Runtime::select(BackendChoice::Ort, 1) }.expect("native ONNX Runtime (pip install onnxruntime)");
        assert!(SHARED_CPU_ARENA.load(std::sync::atomic::Ordering::Relaxed), "the environment has no shared CPU arena");
        assert_eq!(GraphOptimization::Auto.resolve(std::fs::metadata(&path).unwrap().len()), (GraphOptimization::All, true));
        // As a series runs: each network a session of its own, the previous one dropped, the
        // arena's buffers handed from one to the next.
        let first = OrtNetwork::load(&path, 64, 1, GraphOptimization::Auto, &signature, true).unwrap().run(&input).unwrap();
        let second = OrtNetwork::load(&path, 64, 1, GraphOptimization::Auto, &signature, true).unwrap().run(&input).unwrap();
        assert_eq!(first, second, "a session on the shared arena infers what the one before it did");
        // Against a session with no arena at all (`extended`): the same network, up to rounding.
        let own = OrtNetwork::load(&path, 64, 1, GraphOptimization::Extended, &signature, true).unwrap().run(&input).unwrap();
        let scale = own.iter().fold(0f32, |m, v| m.max(v.abs()));
        let worst = first.iter().zip(&own).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(scale > 0.0 && worst <= 1e-5 * scale, "shared-arena output differs by {worst} (scale {scale})");
    }
}
