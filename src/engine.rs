//! The embedding API: an [`Engine`] holds the stage registry and the run-wide settings (the
//! thread pool's size, the ONNX Runtime library), loads and checks pipeline specs, and runs
//! them with in-memory inputs and a product sink as well as with files. [`Engine::image`] is
//! the one-call path `r2d2 image` itself takes, [`Engine::dirty`] that of `r2d2 dirty`.
//!
#![doc = include_str!("../docs/embedding.md")]

use crate::job::{ProductSink, Registry, RunContext};
use crate::pipeline::{runner, PipelineSpec, Progress, RunReport, StageSpec};
use crate::vis::{MemoryInput, PartedObservation, TableFormat};
#[cfg(feature = "ms")]
use crate::params::MsParams;
use crate::params::{
    ArrowIpcParams, ArrowParams, CleanParams, FinalCleanParams, Files, GridderParams, NativeParams, OnnxParams, ParquetParams, ProductsParams, ResidualParams,
    WeightingParams, WriterParams,
};
use crate::params::MatParams;
use crate::job::{ChannelProducts, JobProducts, ProductSet, WriteOptions};
use crate::request::{DirtyRequest, ImageRequest, StepChoice};
use crate::weighting::Weighting;
use crate::{Error, Result};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};

/// Run-wide settings, fixed when the engine is made.
#[derive(Clone, Debug, Default)]
pub struct EngineOptions {
    /// Threads of the shared pool that numerical work runs on (0: all cores). A pipeline's
    /// own `threads` key takes precedence for its run.
    pub threads: usize,
    /// The native ONNX Runtime library (`libonnxruntime.so.*`) for `onnx` steps; without one
    /// they run on tract (pure Rust). The library is loaded once per process.
    pub onnx_runtime: Option<PathBuf>,
}

/// Observer of a run's progress (the CLI draws its progress bar from it).
pub type ProgressObserver = dyn Fn(&Progress) + Send + Sync;

/// The imaging engine.
pub struct Engine {
    registry: Registry,
    options: EngineOptions,
    progress: Option<Box<ProgressObserver>>,
    cancel: Arc<AtomicBool>,
}

impl Engine {
    /// An engine with the built-in stage kinds.
    pub fn new(options: EngineOptions) -> Result<Engine> {
        crate::limits::check_threads(options.threads).map_err(|m| Error::parameter("threads", m))?;
        crate::parallel::size_shared_pool(options.threads)?;
        if let Some(library) = &options.onnx_runtime {
            crate::steps::runtime::use_onnx_runtime(library)?;
        }
        Ok(Engine { registry: crate::stages::builtin(), options, progress: None, cancel: Arc::new(AtomicBool::new(false)) })
    }

    pub fn options(&self) -> &EngineOptions {
        &self.options
    }

    pub fn registry(&self) -> &Registry {
        &self.registry
    }

    /// To register stage kinds of the embedding program's own.
    pub fn registry_mut(&mut self) -> &mut Registry {
        &mut self.registry
    }

    /// Reports each run's progress to `observer`.
    pub fn with_progress(mut self, observer: impl Fn(&Progress) + Send + Sync + 'static) -> Engine {
        self.progress = Some(Box::new(observer));
        self
    }

    /// Stops [`Engine::image`] at the next job boundary when `cancel` turns true. Runs only
    /// read the flag (a failed run leaves it clear); after a cancel, clear it to image again.
    pub fn with_cancel(mut self, cancel: Arc<AtomicBool>) -> Engine {
        self.cancel = cancel;
        self
    }

    /// The flag that stops [`Engine::image`] (and runs given it) at the next job boundary.
    pub fn cancel_flag(&self) -> Arc<AtomicBool> {
        self.cancel.clone()
    }

    /// Parses a pipeline written in YAML; `file` names it in errors (which carry line and
    /// column), `overrides` are `stage.key=value` settings as `r2d2 run --set` takes them.
    pub fn load_yaml(&self, text: &str, file: impl AsRef<Path>, overrides: &[String]) -> Result<PipelineSpec> {
        PipelineSpec::parse(text, file.as_ref(), overrides)
    }

    /// Reads and parses a pipeline file.
    pub fn load_file(&self, path: impl AsRef<Path>, overrides: &[String]) -> Result<PipelineSpec> {
        PipelineSpec::load(path.as_ref(), overrides)
    }

    /// Checks the graph and builds every stage without running anything.
    pub fn validate(&self, spec: &PipelineSpec) -> Result<()> {
        let spec = self.with_threads(spec);
        runner::validate(&self.registry, &spec, &RunContext::new(&spec, Vec::new(), None)?).map(|_| ())
    }

    /// Runs `spec` to completion (or until `cancel` turns true; the run only reads it, and
    /// stops its plugin hosts when it does). An `arrow` source reads
    /// `inputs`; a `products` stage delivers each finished job to `sink`.
    pub fn run(
        &self,
        spec: &PipelineSpec,
        inputs: Vec<MemoryInput>,
        sink: Option<Box<dyn ProductSink>>,
        cancel: Arc<AtomicBool>,
    ) -> Result<RunReport> {
        self.run_with_parts(spec, inputs, Vec::new(), sink, cancel)
    }

    /// [`run`](Self::run), the `arrow` source also reading observations in parts.
    fn run_with_parts(
        &self,
        spec: &PipelineSpec,
        inputs: Vec<MemoryInput>,
        parted: Vec<PartedObservation>,
        sink: Option<Box<dyn ProductSink>>,
        cancel: Arc<AtomicBool>,
    ) -> Result<RunReport> {
        let spec = self.with_threads(spec);
        let progress: &(dyn Fn(&Progress) + Sync) = match &self.progress {
            Some(observer) => observer.as_ref(),
            None => &|_| {},
        };
        let context = RunContext::new(&spec, inputs, sink)?.with_parted(parted);
        let mut report = runner::run(&self.registry, &spec, &context, cancel, progress)?;
        report.written = context.files_written();
        Ok(report)
    }

    /// The spec with the engine's thread count where it sets none.
    fn with_threads(&self, spec: &PipelineSpec) -> PipelineSpec {
        let mut spec = spec.clone();
        if spec.threads == 0 {
            spec.threads = self.options.threads;
        }
        spec
    }

    /// Images one observation with the default pipeline (weighting, gridder, the step, the
    /// residual update) and returns its products; with the request's `name`, also writes them
    /// as `r2d2 image` does.
    pub fn image(&self, obs: impl Into<Observation>, request: &ImageRequest) -> Result<JobProducts> {
        one_group(request.ms.channels_out, "image_channels")?;
        self.run_plan(obs.into(), &ImagePlan::of(request)?)
    }

    /// Images a MeasurementSet in `request.ms.channels_out` groups of its channels, one after
    /// another on one grid (the pixel of the whole band's longest baseline), and with
    /// `join_channels` the whole band on it too; with the request's `name`, writes every
    /// group's products as WSClean names them (`<name>-0000-image.fits`, ...,
    /// `<name>-MFS-image.fits`) and a cube of each image product (`<name>-cube-image.fits`),
    /// all together or none.
    pub fn image_channels(&self, obs: impl Into<Observation>, request: &ImageRequest) -> Result<ChannelProducts> {
        self.run_channels(obs.into(), ImagePlan::of(request)?)
    }

    /// [`image_channels`](Self::image_channels)' dirty images and PSFs only (`r2d2 dirty
    /// --channels-out N`).
    pub fn dirty_channels(&self, obs: impl Into<Observation>, request: &DirtyRequest) -> Result<ChannelProducts> {
        self.run_channels(obs.into(), ImagePlan::of_dirty(request)?)
    }

    fn run_channels(&self, obs: Observation, mut plan: ImagePlan) -> Result<ChannelProducts> {
        let count = plan.ms.channels_out.unwrap_or(1);
        let path = match &obs {
            Observation::Path(path) if crate::vis::format_of(path)? == TableFormat::MeasurementSet => path.clone(),
            _ => return Err(Error::parameter("channels_out", "channel groups are made of a MeasurementSet's channels, and the observation is not one (a table splits by frequency with a pipeline's split_by)")),
        };
        if count == 0 {
            return Err(Error::parameter("channels_out", "expected at least 1 channel group"));
        }
        if plan.model_column.is_some() {
            return Err(Error::parameter("model_column", "channel groups are not predicted into the MS: image the band as one (without channels_out) to predict its model"));
        }
        let id = crate::job::stem_id(&path);
        if let Some(prefix) = &plan.write {
            let mut inputs = vec![path.as_path()];
            inputs.extend(plan.truth.as_deref());
            ChannelProducts::check_spares_inputs(prefix, &id, count, &inputs, plan.products).map_err(|e| match e {
                Error::Parameter { message, .. } => Error::parameter("name", message),
                other => other,
            })?;
        }
        // One pipeline: the source reads every group (and the whole band) as a job of its
        // own, all on the grid of the whole band's longest baseline.
        let write = plan.write.take();
        let groups = ImagePlan { channel_groups: true, ..plan.clone() };
        let mut channels = self.run_plan_jobs(Observation::Path(path.clone()), &groups)?;
        let mfs = match plan.ms.join_channels {
            true => channels.pop(),
            false => None,
        };
        let expected = |k: usize| format!("{id}-{}", crate::job::group_label(k));
        if channels.len() != count || channels.iter().enumerate().any(|(k, p)| p.id != expected(k)) || mfs.as_ref().is_some_and(|p| p.id != format!("{id}-{}", crate::job::MFS_LABEL)) {
            let made: Vec<&str> = channels.iter().chain(&mfs).map(|p| p.id.as_str()).collect();
            return Err(Error::parameter("channels_out", format!("expected {count} channel groups' jobs in order, made {}", made.join(", "))));
        }
        let all = ChannelProducts { channels, mfs };
        if let Some(prefix) = write {
            let options = WriteOptions { previews: plan.products == ProductSet::All, ..WriteOptions::default() };
            let (_, no_cubes) = all.write(&prefix, &options, plan.products)?;
            if let Some(why) = no_cubes {
                log::warn!("{id}: no cubes written: {why}");
            }
        }
        Ok(all)
    }

    /// The dirty image and PSF of one observation (what `r2d2 dirty` makes): read, weighted
    /// and gridded by the stages [`image`](Self::image) runs (the samples read in passes, not
    /// held), with no step; with the request's `name`, also writes `<name>-dirty.fits` and
    /// `<name>-psf.fits`, both or neither, and nothing else.
    pub fn dirty(&self, obs: impl Into<Observation>, request: &DirtyRequest) -> Result<JobProducts> {
        one_group(request.ms.channels_out, "dirty_channels")?;
        self.run_plan(obs.into(), &ImagePlan::of_dirty(request)?)
    }

    /// Runs the pipeline of `params` on `obs` and returns its one job's products.
    fn run_plan(&self, obs: Observation, params: &ImagePlan) -> Result<JobProducts> {
        if let (Observation::Path(path), Some(prefix)) = (&obs, &params.write) {
            // Before imaging: products that would replace the observation or the truth.
            let mut inputs = vec![path.as_path()];
            inputs.extend(params.truth.as_deref());
            crate::job::check_spares_inputs(prefix, &crate::job::stem_id(path), &inputs, params.products).map_err(|e| match e {
                // The prefix is the request's `name`.
                Error::Parameter { message, .. } => Error::parameter("name", message),
                other => other,
            })?;
        }
        let mut delivered = self.run_plan_jobs(obs, params)?;
        match delivered.len() {
            1 => Ok(delivered.remove(0)),
            n => Err(Error::parameter("observation", format!("made {n} jobs where one was expected"))),
        }
    }

    /// Runs the pipeline of `params` on `obs` and returns every job's products, in the order
    /// the jobs were made.
    fn run_plan_jobs(&self, obs: Observation, params: &ImagePlan) -> Result<Vec<JobProducts>> {
        let (spec, inputs, parted) = image_spec(obs, params)?;
        let delivered: Arc<Mutex<Vec<JobProducts>>> = Arc::default();
        let into = delivered.clone();
        let sink = move |products: JobProducts| -> Result<()> {
            into.lock().expect("products").push(products);
            Ok(())
        };
        self.run_with_parts(&spec, inputs, parted, Some(Box::new(sink)), self.cancel.clone())?;
        let delivered = std::mem::take(&mut *delivered.lock().expect("products"));
        Ok(delivered)
    }
}

/// Refuses several channel groups where one job's products are returned (`instead` returns
/// them all).
fn one_group(channels_out: Option<usize>, instead: &str) -> Result<()> {
    match channels_out {
        Some(n) if n > 1 => Err(Error::parameter("channels_out", format!("{n} channel groups make {n} jobs' products: Engine::{instead} returns them"))),
        _ => Ok(()),
    }
}

/// An observation for [`Engine::image`] and [`Engine::dirty`]: a file (Parquet, Arrow IPC, a .mat observation, a MeasurementSet),
/// record batches in memory, or parts gridded where they live (a cluster's workers).
pub enum Observation {
    Path(PathBuf),
    Batches(MemoryInput),
    Parts(PartedObservation),
}

impl From<PartedObservation> for Observation {
    fn from(parts: PartedObservation) -> Self {
        Observation::Parts(parts)
    }
}

impl From<PathBuf> for Observation {
    fn from(path: PathBuf) -> Self {
        Observation::Path(path)
    }
}

impl From<&Path> for Observation {
    fn from(path: &Path) -> Self {
        Observation::Path(path.to_path_buf())
    }
}

impl From<MemoryInput> for Observation {
    fn from(input: MemoryInput) -> Self {
        Observation::Batches(input)
    }
}

/// CLEAN's stopping controls as WSClean names them; `None` keeps the step's default.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct CleanControls {
    /// Components over all major cycles (`-niter`).
    niter: Option<usize>,
    /// Minor-cycle loop gain (`-gain`, default 0.1).
    gain: Option<f64>,
    /// Fraction of the peak each major cycle's minor cycle cleans away (`-mgain`).
    mgain: Option<f64>,
    /// Stop at this many times the residual's noise (`-auto-threshold`).
    auto_threshold: Option<f64>,
    /// Stop below this residual peak, Jy/beam (`-threshold`).
    threshold: Option<f64>,
    /// Clean without a mask to this many noise sigmas, then in the components' mask
    /// (`-auto-mask`).
    auto_mask: Option<f64>,
}

impl CleanControls {
    fn any(&self) -> bool {
        *self != CleanControls::default()
    }

    /// The controls only the step clean takes: a network series takes `auto_mask` (its model
    /// kept to where the data show emission) and `auto_threshold` (its final CLEAN's depth).
    fn for_clean_only(&self) -> CleanControls {
        CleanControls { auto_mask: None, auto_threshold: None, ..*self }
    }
}

pub use crate::steps::runtime::{BackendChoice, GraphOptimization};

/// An [`ImageRequest`] resolved into what the pipeline is built from: typed choices, each
/// checked, its errors naming the request's field.
#[derive(Clone, Debug)]
struct ImagePlan {
    size: usize,
    /// `None`: the series' own (its manifest's `superresolution`) for a series step, else the
    /// default.
    superresolution: Option<f64>,
    pixel_arcsec: Option<f64>,
    longest_baseline: Option<f64>,
    /// `None`: the series' own (its manifest's `weighting`) for a series step, else the default.
    weighting: Option<Weighting>,
    /// `None`: a series' trained field's grid where a series runs off its trained size, else
    /// the default.
    weighting_grid_factor: Option<f64>,
    uv: crate::weighting::UvControls,
    restoring_beam: crate::params::RestoringBeam,
    epsilon: f64,
    oversampling: Option<f64>,
    w_term: crate::operator::WTermMode,
    hold_mb: f64,
    kernel_mb: f64,
    threads: usize,
    step: StepChoice,
    iterations: Option<usize>,
    clean: CleanControls,
    /// The step's mask file (`-fits-mask`).
    fits_mask: Option<PathBuf>,
    final_clean: bool,
    backend: BackendChoice,
    prefetch: bool,
    graph_optimization: GraphOptimization,
    truth: Option<PathBuf>,
    write: Option<String>,
    model_column: Option<String>,
    /// With `--apply-primary-beam`: the beam level below which the corrected images are blank.
    primary_beam: Option<f64>,
    ms: crate::request::MsOptions,
    /// `All`: the imaging loop and every product; `Dirty`: the dirty image and the PSF, no step.
    products: ProductSet,
    /// Whether the MS is read as `ms.channels_out` channel groups (and with `join_channels`
    /// the whole band), each a job; else as one job of every selected channel.
    #[cfg_attr(not(feature = "ms"), allow(dead_code))]
    channel_groups: bool,
}

impl ImagePlan {
    fn of(request: &ImageRequest) -> Result<ImagePlan> {
        let (grid, step) = (&request.grid, &request.step);
        crate::limits::check_image_size(grid.size).map_err(|m| Error::parameter("size", m))?;
        crate::limits::check_threads(grid.threads).map_err(|m| Error::parameter("threads", m))?;
        if let Some(factor) = grid.weighting_grid_factor.filter(|f| !(*f > 0.0 && f.is_finite())) {
            return Err(Error::parameter("weighting_grid_factor", format!("expected a positive number, got {factor}")));
        }
        if let Some(name) = &request.name {
            crate::fits::check_output_prefix(name).map_err(|m| Error::parameter("name", m))?;
        }
        Ok(ImagePlan {
            size: grid.size,
            superresolution: grid.superresolution,
            pixel_arcsec: grid.pixel_arcsec,
            longest_baseline: grid.longest_baseline,
            weighting: grid.weighting()?,
            weighting_grid_factor: grid.weighting_grid_factor,
            uv: grid.uv()?,
            restoring_beam: grid.restoring_beam()?,
            epsilon: grid.epsilon,
            oversampling: grid.oversampling,
            w_term: grid.w_term,
            hold_mb: request.hold_mb,
            kernel_mb: request.kernel_mb,
            threads: grid.threads,
            step: StepChoice::parse(&step.step, step.plugin_config.as_deref())?,
            iterations: step.iterations,
            clean: CleanControls { niter: step.niter, gain: step.gain, mgain: step.mgain, auto_threshold: step.auto_threshold, threshold: step.threshold, auto_mask: step.auto_mask },
            fits_mask: step.fits_mask.clone(),
            final_clean: step.final_clean,
            backend: step.backend,
            prefetch: step.prefetch,
            graph_optimization: step.graph_optimization,
            truth: request.truth.clone(),
            write: request.name.clone(),
            model_column: request.model_column.clone(),
            primary_beam: match request.apply_primary_beam {
                true => {
                    crate::primary_beam::check_limit(request.primary_beam_limit).map_err(|m| Error::parameter("primary_beam_limit", m))?;
                    Some(request.primary_beam_limit)
                }
                false if request.primary_beam_limit != crate::primary_beam::DEFAULT_LIMIT => {
                    return Err(Error::parameter("primary_beam_limit", "blanks the primary-beam corrected images: give apply_primary_beam as well"));
                }
                false => None,
            },
            ms: request.ms.clone(),
            products: ProductSet::All,
            channel_groups: false,
        })
    }

    /// The plan of a dirty image: `request`'s grid, MS selection and name, every other choice
    /// at its default (and none of a series': no step runs).
    fn of_dirty(request: &DirtyRequest) -> Result<ImagePlan> {
        let image = ImageRequest { grid: request.grid.clone(), ms: request.ms.clone(), name: request.name.clone(), ..ImageRequest::default() };
        Ok(ImagePlan { products: ProductSet::Dirty, ..ImagePlan::of(&image)? })
    }
}

/// The `r2d2 image` pipeline for `obs` and `params`, and the in-memory inputs it reads.
fn image_spec(obs: Observation, params: &ImagePlan) -> Result<(PipelineSpec, Vec<MemoryInput>, Vec<PartedObservation>)> {
    let (resolved, clean_because) = match params.products {
        ProductSet::All => resolve_auto(params, || observation_telescope(&obs))?,
        ProductSet::Dirty => (params.clone(), None),
    };
    let params = &resolved;
    // A telescope without a beam model is refused before imaging, not after.
    if params.primary_beam.is_some() {
        crate::job::beam_telescope(observation_telescope(&obs).as_deref().unwrap_or(""))?;
    }
    let (mut inputs, mut parted) = (Vec::new(), Vec::new());
    let truth = params.truth.clone();
    let reads_ms = matches!(&obs, Observation::Path(path) if is_ms(path));
    let read = match obs {
        Observation::Batches(input) => {
            inputs.push(input);
            StageSpec::typed("read", &ArrowParams { truth, ..ArrowParams::default() })?
        }
        Observation::Parts(parts) => {
            if params.model_column.is_some() {
                return Err(Error::parameter("model_column", format!("job '{}' is in parts: only a MeasurementSet input has a column to write the model into", parts.id)));
            }
            parted.push(parts);
            StageSpec::typed("read", &ArrowParams { truth, ..ArrowParams::default() })?
        }
        Observation::Path(path) => {
            let format = crate::vis::format_of(&path)?;
            if format == TableFormat::MeasurementSet {
                ms_read(&path, params)?
            } else {
                if params.model_column.is_some() {
                    return Err(Error::parameter("model_column", format!("{}: only a MeasurementSet input has a column to write the model into", path.display())));
                }
                let text = path.to_string_lossy().into_owned();
                match format {
                    TableFormat::ArrowIpc => StageSpec::typed("read", &ArrowIpcParams { truth, ..ArrowIpcParams::new(text) })?,
                    TableFormat::Mat => StageSpec::typed("read", &MatParams(ParquetParams { truth, ..ParquetParams::new(Files::One(text)) }))?,
                    // Parquet (a MeasurementSet is read above).
                    _ => StageSpec::typed("read", &ParquetParams { truth, ..ParquetParams::new(Files::One(text)) })?,
                }
            }
        }
    };
    if !reads_ms {
        if let Some(option) = params.ms.given() {
            return Err(Error::parameter(option, "only a MeasurementSet input has it; the observation is not one"));
        }
    }
    let (weighting, superresolution) = imaging_setting(params)?;
    let weights = WeightingParams { grid_factor: params.weighting_grid_factor, ..WeightingParams::new(weighting).with_uv(params.uv) };
    let grid = GridderParams { epsilon: params.epsilon, oversampling: params.oversampling, w_term: params.w_term, hold_mb: params.hold_mb, kernel_mb: params.kernel_mb, restoring_beam: params.restoring_beam, ..GridderParams::default() };
    let mut stages = vec![read.to("weights"), StageSpec::typed("weights", &weights)?.to("grid")];
    match params.products {
        // The gridded job's images are its products: no step, and no form of D is made.
        ProductSet::Dirty => stages.push(StageSpec::typed("grid", &grid)?.to("products")),
        ProductSet::All => {
            stages.push(StageSpec::typed("grid", &grid)?.to("step"));
            stages.push(step_stage(params, clean_because)?.to("update"));
            // A network series' model gets CLEAN's final cycles on its residual; CLEAN's and a
            // plugin's end where they end.
            if params.final_clean && matches!(params.step, StepChoice::Auto | StepChoice::Series(_)) {
                stages.push(StageSpec::typed("update", &ResidualParams::default())?.to("step").done("final"));
                stages.push(StageSpec::typed("final", &final_clean_params(params.clean.auto_threshold))?.to("products"));
            } else {
                stages.push(StageSpec::typed("update", &ResidualParams::default())?.to("step").done("products"));
            }
        }
    }
    let products = StageSpec::typed("products", &ProductsParams::default())?;
    match &params.write {
        Some(prefix) => {
            stages.push(products.to("write"));
            // A dirty image's FITS files only, as `r2d2 dirty` (and WSClean's `-niter 0`) writes
            // them: no previews, no metrics, nothing else at the prefix touched.
            let dirty = params.products == ProductSet::Dirty;
            let write = WriterParams {
                prefix: prefix.clone(),
                model_column: params.model_column.clone(),
                products: params.products,
                previews: !dirty,
                apply_primary_beam: params.primary_beam.is_some(),
                primary_beam_limit: params.primary_beam.unwrap_or(crate::primary_beam::DEFAULT_LIMIT),
                ..WriterParams::default()
            };
            stages.push(StageSpec::typed("write", &write)?);
        }
        None => stages.push(products),
    }
    let image = crate::imaging::ImageConfig {
        size: params.size,
        superresolution: params.pixel_arcsec.is_none().then_some(superresolution),
        pixel_arcsec: params.pixel_arcsec,
        longest_baseline: params.longest_baseline,
    };
    let name = match params.products {
        ProductSet::All => "image",
        ProductSet::Dirty => "dirty",
    };
    let mut spec = PipelineSpec::new(name, &image, stages)?;
    spec.threads = params.threads;
    Ok((spec, inputs, parted))
}

/// Weighting and super-resolution of an image: what `params` asks for; where it asks for none,
/// a series step's own (its manifest's, as it was trained), else Briggs 0 and SR 1.5 (a dirty
/// image's, which no step follows). The log says when the series' setting is used. (The
/// weighting grid of a series run off its trained size is the weighting stage's to choose.)
fn imaging_setting(params: &ImagePlan) -> Result<(Weighting, f64)> {
    const DEFAULT: (Weighting, f64) = (crate::weighting::DEFAULT_WEIGHTING, crate::imaging::DEFAULT_SUPERRESOLUTION);
    let needs_series = params.weighting.is_none() || (params.superresolution.is_none() && params.pixel_arcsec.is_none());
    let own = match &params.step {
        StepChoice::Auto | StepChoice::Series(_) if needs_series && params.products == ProductSet::All => {
            // A series that does not resolve or open is reported by the step itself, as is
            // `auto`'s off-size warning (not repeated here).
            let dir = match &params.step {
                StepChoice::Series(path) => crate::steps::series::resolve(path).ok(),
                _ => {
                    // What the options fix takes part in `auto`'s choice (a series trained for
                    // it); the chosen series' own setting fills in the rest.
                    crate::steps::series::select_for(params.size, &fixed_setup(params, None)).ok().map(|(dir, _)| dir)
                }
            };
            dir.and_then(|d| crate::steps::series::Series::open(&d).ok()).and_then(|s| s.manifest.map(|m| (s.name, m)))
        }
        _ => None,
    };
    let own_weighting = own.as_ref().and_then(|(_, m)| {
        let scheme = m.weighting.get("scheme")?.as_str()?;
        let robust = m.weighting.get("robust").and_then(serde_yaml::Value::as_f64).unwrap_or(0.0);
        Weighting::from_name(scheme, robust).ok()
    });
    let own_superresolution = own.as_ref().and_then(|(_, m)| m.superresolution);
    let weighting = params.weighting.or(own_weighting).unwrap_or(DEFAULT.0);
    let superresolution = params.superresolution.or(own_superresolution).unwrap_or(DEFAULT.1);
    if let Some((name, _)) = &own {
        let mut used = Vec::new();
        if params.weighting.is_none() && own_weighting.is_some() {
            used.push(format!("weighting {weighting}"));
        }
        if params.superresolution.is_none() && params.pixel_arcsec.is_none() && own_superresolution.is_some() {
            used.push(format!("super-resolution {superresolution}"));
        }
        if !used.is_empty() {
            log::info!("imaging with series '{name}''s own setting: {} (the options set none)", used.join(", "));
        }
    }
    Ok((weighting, superresolution))
}

/// The telescope an observation says its data come from, read without its samples (none
/// where it names none, or is standard input, which can be read once only).
fn observation_telescope(obs: &Observation) -> Option<String> {
    match obs {
        Observation::Path(path) => crate::vis::telescope_of(path),
        Observation::Batches(input) => input.batches.schema().metadata().get("telescope").and_then(|t| crate::vis::named_telescope(t)),
        Observation::Parts(parts) => crate::vis::named_telescope(&parts.meta.telescope),
    }
}

/// Components the CLEAN that `auto` falls back to may take: its stopping rule is the
/// auto-threshold, as in WSClean's usual command (`-auto-threshold 3 -mgain 0.8`).
const FALLBACK_CLEAN: CleanControls = CleanControls { niter: Some(1_000_000), gain: None, mgain: Some(crate::steps::clean::DEFAULT_MAJOR_GAIN), auto_threshold: Some(crate::steps::clean::DEFAULT_AUTO_THRESHOLD), threshold: None, auto_mask: None };

/// `auto` where the data's telescope is known: among the series trained for the image size,
/// one trained for that telescope (and the setting, where one is); where no series was
/// trained for the telescope at any size, the built-in CLEAN with WSClean's usual stopping
/// rule, and the reason every job carries as a warning (a series trained on another
/// telescope's PSFs gives a confident image that nothing vouches for; CLEAN's is the one
/// the user knows how to judge).
/// The telescope is read (`telescope()`) only when `auto` is asked for.
fn resolve_auto(params: &ImagePlan, telescope: impl FnOnce() -> Option<String>) -> Result<(ImagePlan, Option<String>)> {
    // CLEAN's own controls with `auto` are refused by the step stage, whatever the telescope.
    if params.step != StepChoice::Auto || params.clean.for_clean_only().any() {
        return Ok((params.clone(), None));
    }
    let Some(telescope) = telescope() else { return Ok((params.clone(), None)) };
    let telescope = telescope.as_str();
    let found = crate::steps::series::found_series()?;
    if found.is_empty() || found.iter().any(|(_, s)| s.trained_for_telescope(telescope)) {
        // The series `auto` prefers for this telescope, named from here on so that the
        // imaging setting comes from the series that runs. Off its trained size the step
        // also says so in each job's metrics.
        let (dir, off_size) = crate::steps::series::select_for(params.size, &fixed_setup(params, Some(telescope)))?;
        if let Some(warning) = off_size {
            log::warn!("{warning}");
        }
        return Ok((ImagePlan { step: StepChoice::Series(dir), ..params.clone() }, None));
    }
    let known: Vec<String> = found.iter().map(|(_, s)| s.name_with_telescopes()).collect();
    let reason = format!(
        "no series was trained for the telescope '{telescope}' the data come from (series: {}): imaged with the built-in CLEAN (auto-threshold 3, mgain 0.8); `step` set to a series' name runs it anyway, outside what it was trained for",
        known.join(", ")
    );
    Ok((ImagePlan { step: StepChoice::Clean, clean: FALLBACK_CLEAN, ..params.clone() }, Some(reason)))
}

/// What the options fix of a series' domain (a series is chosen for it).
fn fixed_setup(params: &ImagePlan, telescope: Option<&str>) -> crate::steps::series::ImagingSetup {
    crate::steps::series::ImagingSetup {
        superresolution: params.superresolution,
        weighting: params.weighting.map(|w| w.scheme().name().to_string()),
        robust: params.weighting.and_then(|w| w.robust()),
        telescope: telescope.map(str::to_string),
        ..Default::default()
    }
}

/// The final CLEAN after a network series: its defaults, with `auto_threshold` (the user's
/// `--auto-threshold`, WSClean's meaning) as the depth of its masked cycles, and the open
/// cycles' level raised to it where it is above theirs.
fn final_clean_params(auto_threshold: Option<f64>) -> FinalCleanParams {
    let defaults = FinalCleanParams::default();
    match auto_threshold {
        Some(sigmas) => FinalCleanParams { auto_threshold: sigmas, auto_mask: defaults.auto_mask.max(sigmas), ..defaults },
        None => defaults,
    }
}

/// The step stage for `params.step` (`clean_because`: why CLEAN runs where `auto` was asked).
fn step_stage(params: &ImagePlan, clean_because: Option<String>) -> Result<StageSpec> {
    // auto_mask also keeps a series' model to where the data show emission.
    let series_step = matches!(params.step, StepChoice::Auto | StepChoice::Series(_));
    let clean_only = if series_step { params.clean.for_clean_only() } else { params.clean };
    if clean_only.any() && params.step != StepChoice::Clean {
        return Err(Error::parameter(
            "step",
            "the CLEAN controls (niter, gain, mgain, threshold) are for the step clean (auto_mask and auto_threshold for it and a network series); the default step is a network series, which needs none",
        ));
    }
    if series_step && params.clean.auto_threshold.is_some() && !params.final_clean {
        return Err(Error::parameter("auto_threshold", "with a network series it is the depth of its final CLEAN, which is off (no_final_clean)"));
    }
    if params.fits_mask.is_some() && matches!(params.step, StepChoice::Native { .. }) {
        return Err(Error::parameter("fits_mask", "a mask is for the step clean and for a network series; a native plugin's model is its own"));
    }
    match &params.step {
        StepChoice::Clean => {
            let c = params.clean;
            let defaults = CleanParams::default();
            let cycles = params.iterations.unwrap_or(defaults.major_cycles);
            StageSpec::typed(
                "step",
                &CleanParams {
                    major_cycles: cycles,
                    gain: c.gain.unwrap_or(defaults.gain),
                    threshold: c.threshold.unwrap_or(defaults.threshold),
                    max_components: c.niter,
                    major_gain: c.mgain.or(defaults.major_gain),
                    auto_threshold: c.auto_threshold.or(defaults.auto_threshold),
                    auto_mask: c.auto_mask,
                    fits_mask: params.fits_mask.clone(),
                    chosen_because: clean_because,
                    ..defaults
                },
            )
        }
        StepChoice::Auto | StepChoice::Series(_) => {
            // `auto` is resolved by the step, which knows the image size.
            let series = match &params.step {
                StepChoice::Series(path) => crate::steps::series::resolve(path)?,
                _ => PathBuf::from(crate::steps::series::AUTO_SERIES),
            };
            let onnx = OnnxParams {
                backend: params.backend,
                graph_optimization: params.graph_optimization,
                networks: params.iterations,
                prefetch: params.prefetch,
                fits_mask: params.fits_mask.clone(),
                auto_mask: params.clean.auto_mask,
                ..OnnxParams::new(series)
            };
            StageSpec::typed("step", &onnx)
        }
        StepChoice::Native { library, config } => {
            StageSpec::typed("step", &NativeParams { config: config.clone(), ..NativeParams::new(library, params.iterations.unwrap_or(crate::request::DEFAULT_PLUGIN_STEPS)) })
        }
    }
}

/// Whether `path` is a MeasurementSet (a directory with a table), else a file.
pub fn is_ms(path: &Path) -> bool {
    crate::vis::format_of(path).is_ok_and(|f| f == TableFormat::MeasurementSet)
}

#[cfg(feature = "ms")]
fn ms_read(path: &Path, params: &ImagePlan) -> Result<StageSpec> {
    let (channels_out, join_channels) = match params.channel_groups {
        true => (params.ms.channels_out, params.ms.join_channels),
        false => (None, false),
    };
    StageSpec::typed("read", &MsParams { truth: params.truth.clone(), selection: params.ms.selection()?, channels_out, join_channels, ..MsParams::new(path) })
}

#[cfg(not(feature = "ms"))]
fn ms_read(path: &Path, _params: &ImagePlan) -> Result<StageSpec> {
    Err(Error::input(path, "a MeasurementSet, but this r2d2 was built without the `ms` feature"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::*;
    use crate::pipeline::StageParams;

    /// Whether stages `a` of `ya` and `b` of `yb` (both of `kind`) have the same parameters once
    /// read as the kind's typed parameters (so defaults written out or left out compare equal).
    fn same_params(kind: &str, (ya, a): (&PipelineSpec, &StageSpec), (yb, b): (&PipelineSpec, &StageSpec)) -> bool {
        fn same<P: StageParams + PartialEq + std::fmt::Debug>(ya: &PipelineSpec, a: &StageSpec, yb: &PipelineSpec, b: &StageSpec) -> bool {
            let (pa, pb) = (ya.stage_params::<P>(a).unwrap(), yb.stage_params::<P>(b).unwrap());
            if pa != pb {
                eprintln!("stage '{}': {pa:?}\n  differs from {pb:?}", a.name);
            }
            pa == pb
        }
        match kind {
            "parquet" => same::<ParquetParams>(ya, a, yb, b),
            "weighting" => same::<WeightingParams>(ya, a, yb, b),
            "gridder" => same::<GridderParams>(ya, a, yb, b),
            "onnx" => same::<OnnxParams>(ya, a, yb, b),
            "residual" => same::<ResidualParams>(ya, a, yb, b),
            "final_clean" => same::<FinalCleanParams>(ya, a, yb, b),
            "writer" => same::<WriterParams>(ya, a, yb, b),
            other => panic!("the test has no typed parameters for kind '{other}'"),
        }
    }

    /// The spec without its `products` stages, what pointed at one pointing where it led.
    fn without_products(spec: &PipelineSpec) -> Vec<StageSpec> {
        let next = |target: &Option<String>| -> Option<String> {
            let mut target = target.clone();
            while let Some(s) = target.as_deref().and_then(|t| spec.stage(t)).filter(|s| s.kind == ProductsParams::KIND) {
                target = s.to.clone();
            }
            target
        };
        spec.stages
            .iter()
            .filter(|s| s.kind != ProductsParams::KIND)
            .map(|s| {
                let mut s = s.clone();
                (s.to, s.done) = (next(&s.to), next(&s.done));
                s
            })
            .collect()
    }

    /// A file named `name` in a fresh directory that starts as a table of its format does
    /// (`image_spec` tells formats by content).
    fn table_file(name: &str, head: &[u8]) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("r2d2-engine-test-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, head).unwrap();
        path
    }

    fn plan(request: ImageRequest) -> ImagePlan {
        ImagePlan::of(&request).unwrap()
    }

    /// MS options for an input that is not an MS are refused, naming the option.
    #[test]
    fn ms_options_for_another_input_are_refused_by_name() {
        let mut request = ImageRequest::default();
        request.ms.field = Some("3".into());
        let e = image_spec(Observation::Path(table_file("f.parquet", b"PAR1")), &plan(request)).err().expect("refused").to_string();
        assert!(e.contains("field") && e.contains("MeasurementSet"), "{e}");
    }

    /// pipelines/image.yaml says it is the pipeline `r2d2 image OBS.parquet` runs: it is
    /// `Engine::image`'s with every option at its default, for `obs.parquet` written at the
    /// YAML's prefix (`{job}`: `r2d2 image` takes it from `--name`). `Engine::image` adds a
    /// `products` stage handing the products to its caller, which `r2d2 run` has not.
    #[test]
    fn pipelines_image_yaml_is_the_pipeline_of_engine_image() {
        let yaml = PipelineSpec::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/image.yaml"), &[]).unwrap();
        let params = plan(ImageRequest { name: Some("{job}".into()), ..ImageRequest::default() });
        let (mut code, inputs, _) = image_spec(Observation::Path(table_file("obs.parquet", b"PAR1")), &params).unwrap();
        assert!(inputs.is_empty());
        // The YAML names the observation as the command line would: by its name.
        code.stages[0].set_param("files", "obs.parquet").unwrap();
        assert_eq!((&yaml.name, &yaml.image, yaml.threads, yaml.channel_capacity), (&code.name, &code.image, code.threads, code.channel_capacity));
        let code_stages = without_products(&code);
        let shape = |stages: &[StageSpec]| stages.iter().map(|s| (s.name.clone(), s.kind.clone(), s.to.clone(), s.done.clone())).collect::<Vec<_>>();
        assert_eq!(shape(&yaml.stages), shape(&code_stages), "stages, kinds and routing");
        for (a, b) in yaml.stages.iter().zip(&code_stages) {
            assert!(same_params(&a.kind, (&yaml, a), (&code, b)), "stage '{}': the YAML's parameters differ from Engine::image's", a.name);
        }
        assert!(code.stages.iter().any(|s| s.kind == ProductsParams::KIND));
    }

    /// `Engine::dirty`'s pipeline is `Engine::image`'s source and gridder, the weighting at its
    /// default (no series is consulted), then the products stage and a writer of the dirty image
    /// and the PSF only, without previews; a name that cannot be a prefix is refused by name.
    #[test]
    fn engine_dirty_is_the_image_pipeline_without_the_step() {
        let request = DirtyRequest { name: Some("out/{job}".into()), ..DirtyRequest::default() };
        let obs = table_file("d.parquet", b"PAR1");
        let (dirty, inputs, _) = image_spec(Observation::Path(obs.clone()), &ImagePlan::of_dirty(&request).unwrap()).unwrap();
        assert!(inputs.is_empty());
        let (image, _, _) = image_spec(Observation::Path(obs), &plan(ImageRequest { name: request.name.clone(), ..ImageRequest::default() })).unwrap();
        let shape: Vec<(&str, &str, Option<&str>)> = dirty.stages.iter().map(|s| (s.name.as_str(), s.kind.as_str(), s.to.as_deref())).collect();
        assert_eq!(
            shape,
            [("read", "parquet", Some("weights")), ("weights", "weighting", Some("grid")), ("grid", "gridder", Some("products")), ("products", "products", Some("write")), ("write", "writer", None)]
        );
        for (stage, kind) in [("read", "parquet"), ("grid", "gridder")] {
            assert!(same_params(kind, (&dirty, dirty.stage(stage).unwrap()), (&image, image.stage(stage).unwrap())), "{stage}");
        }
        assert_eq!(dirty.stage_params::<WeightingParams>(dirty.stage("weights").unwrap()).unwrap(), WeightingParams::default());
        let image_config: crate::imaging::ImageConfig = serde_yaml::from_value(dirty.image.clone()).unwrap();
        assert_eq!(image_config.pixel_scale(), crate::imaging::PixelScale::SuperResolution(crate::imaging::DEFAULT_SUPERRESOLUTION));
        let write = dirty.stage_params::<WriterParams>(dirty.stage("write").unwrap()).unwrap();
        assert_eq!((write.products, write.previews, write.prefix.as_str()), (ProductSet::Dirty, false, "out/{job}"));
        let e = ImagePlan::of_dirty(&DirtyRequest { name: Some("out/".into()), ..DirtyRequest::default() }).err().expect("refused").to_string();
        assert!(e.contains("name") && e.contains("names a directory"), "{e}");
    }

    /// Each choice of `Engine::image` reaches its stage's parameters (read back typed).
    #[test]
    fn engine_image_pipelines_read_back_as_typed_parameters() {
        let mut clean = ImageRequest { name: Some("out/{job}".into()), ..ImageRequest::default() };
        (clean.step.step, clean.step.iterations, clean.grid.weighting) = ("clean".into(), Some(3), Some("uniform".into()));
        (clean.grid.minuv_l, clean.grid.maxuv_l, clean.grid.taper_gaussian, clean.grid.taper_tukey) = (Some(10.0), Some(1e5), Some(2.0), Some(1e3));
        let clean = plan(clean);
        let arrows = table_file("a.arrows", &[0xff; 8]);
        let (spec, _, _) = image_spec(Observation::Path(arrows.clone()), &clean).unwrap();
        assert_eq!(spec.stage_params::<CleanParams>(spec.stage("step").unwrap()).unwrap().major_cycles, 3);
        let weights = spec.stage_params::<WeightingParams>(spec.stage("weights").unwrap()).unwrap();
        assert_eq!(weights.scheme, WeightingScheme::Uniform);
        assert_eq!(weights.uv(), crate::weighting::UvControls { minuv_l: Some(10.0), maxuv_l: Some(1e5), taper_gaussian: Some(2.0), taper_tukey: Some(1e3) });
        // A bad value is refused before anything is read, naming the request's field.
        let mut bad = ImageRequest::default();
        bad.grid.taper_tukey = Some(5.0);
        let e = ImagePlan::of(&bad).err().expect("refused").to_string();
        assert!(e.contains("taper_tukey") && e.contains("maxuv_l"), "{e}");
        assert_eq!(spec.stage_params::<ArrowIpcParams>(spec.stage("read").unwrap()).unwrap().path, arrows.to_string_lossy());
        let mut native = ImageRequest::default();
        (native.step.step, native.step.plugin_config) = ("p.so".into(), Some("{gain: 1}".into()));
        let native = plan(native);
        let (spec, _, _) = image_spec(Observation::Path(table_file("a.parquet", b"PAR1")), &native).unwrap();
        let step = spec.stage_params::<NativeParams>(spec.stage("step").unwrap()).unwrap();
        assert_eq!((step.iterations, step.config.unwrap()["gain"].as_f64()), (10, Some(1.0)));
        let mut onnx = ImageRequest::default();
        (onnx.step.iterations, onnx.step.prefetch, onnx.step.backend) = (Some(2), false, BackendChoice::Tract);
        let onnx = plan(onnx);
        let (spec, _, _) = image_spec(Observation::Path(table_file("a.parquet", b"PAR1")), &onnx).unwrap();
        let step = spec.stage_params::<OnnxParams>(spec.stage("step").unwrap()).unwrap();
        assert_eq!((step.networks, step.prefetch, step.backend), (Some(2), false, BackendChoice::Tract));
        // A series' final CLEAN takes its depth from auto_threshold (and its open cycles' level
        // rises to a depth above theirs); without it, its defaults.
        let final_of = |auto_threshold: Option<f64>| {
            let mut request = ImageRequest::default();
            request.step.auto_threshold = auto_threshold;
            let (spec, _, _) = image_spec(Observation::Path(table_file("a.parquet", b"PAR1")), &plan(request)).unwrap();
            let params = spec.stage_params::<FinalCleanParams>(spec.stage("final").unwrap()).unwrap();
            (params.auto_threshold, params.auto_mask)
        };
        let defaults = FinalCleanParams::default();
        assert_eq!(final_of(None), (defaults.auto_threshold, defaults.auto_mask));
        assert_eq!(final_of(Some(1.0)), (1.0, defaults.auto_mask));
        assert_eq!(final_of(Some(7.0)), (7.0, 7.0));
    }
}
