//! The engine embedded in a Rust program: observations handed in as Arrow record batches,
//! products handed back as arrays, no file read or written for either; stage kinds of the
//! program's own; the products it writes are those the file pipeline writes.

use r2d2_imaging::imaging::{dirty_image, DirtyParams, PixelScale};
use r2d2_imaging::NufftParams;
use r2d2_imaging::simulate::ObservationSpec;
use r2d2_imaging::simulate::{simulate, SimulationOutput, SimulationRequest, SkyModel};
use r2d2_imaging::vis::to_record_batches;
use r2d2_imaging::{
    BuildContext, Built, DirtyRequest, Emit, Engine, EngineOptions, ImageRequest, Job, JobProducts, MemoryInput, Product, Role, Stage,
    StageKind, Weighting,
};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

const SIZE: usize = 64;

fn observation(seed: u64) -> SimulationOutput {
    simulate(&SimulationRequest {
        observation: ObservationSpec {
            telescope: "vla".into(),
            configurations: vec![("c".into(), 1.0)],
            dec_deg: 40.0,
            integration_s: 120.0,
            frequencies_hz: vec![1.4e9],
            flag_fraction: 0.0,
            random_rotation: false,
            seed,
        },
        sky: SkyModel::Procedural { seed },
        size: SIZE,
        pixel: PixelScale::SuperResolution(1.5),
        dynamic_range: 1e3,
        noise_weighting: Weighting::Briggs { robust: 0.0 },
        phase_centre_deg: (150.0, 40.0),
        nufft: NufftParams::default(),
        threads: 2,
    })
    .unwrap()
}

/// The observation as an in-memory input, in batches of 1000 rows.
fn input(id: &str, obs: &SimulationOutput) -> MemoryInput {
    let (schema, batches) = to_record_batches(&obs.table, &obs.meta, 1000).unwrap();
    assert!(batches.len() > 1, "the test should stream several batches");
    MemoryInput::from_batches(id, schema, batches)
}

fn clean_params() -> ImageRequest {
    let mut request = ImageRequest::default();
    (request.grid.size, request.step.step, request.step.iterations) = (SIZE, "clean".into(), Some(2));
    request
}

fn engine() -> Engine {
    Engine::new(EngineOptions { threads: 2, onnx_runtime: None }).unwrap()
}

#[test]
fn image_from_record_batches_returns_the_products_as_arrays() {
    let obs = observation(3);
    let products = engine().image(input("obs", &obs), &clean_params()).unwrap();
    assert_eq!(products.id, "obs");
    assert_eq!(products.size, SIZE);
    // The dirty image is the library's, made from the same visibilities directly, to the
    // NUFFT's accuracy: with the w-term the job grids it beside the kernels of the w-aware
    // Toeplitz form, and its PSF (whose peak normalises it) is that form's.
    let (vis, _) = obs.table.to_visibilities("table").unwrap();
    let reference = dirty_image(&vis, &DirtyParams { size: SIZE, threads: 2, ..DirtyParams::default() }).unwrap();
    let peak = reference.dirty.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let worst = products.dirty.iter().zip(&reference.dirty).fold(0.0f64, |m, (a, b)| m.max((f64::from(*a) - b).abs()));
    assert!(worst <= 1e-5 * peak, "{worst:e} of {peak}");
    assert_eq!(products.psf.len(), SIZE * SIZE);
    let peak = products.psf[SIZE / 2 * SIZE + SIZE / 2];
    assert!((peak - 1.0).abs() < 1e-5, "PSF peak {peak}");
    // Two CLEAN major cycles: model, residual, restored image and two metrics rows.
    assert_eq!(products.iterations, 2);
    assert_eq!(products.metrics.len(), 2);
    let model = products.model.as_ref().expect("a model");
    assert!(model.iter().any(|&v| v > 0.0));
    assert!(products.residual.is_some() && products.image.is_some());
    // The WCS keywords the FITS files carry, with the observation's phase centre.
    let key = |k: &str| products.header.iter().find(|(name, _)| name == k).map(|(_, v)| v.clone());
    assert_eq!(key("CTYPE1").as_deref(), Some("RA---SIN"));
    assert_eq!(key("CRVAL1").and_then(|v| v.parse::<f64>().ok()), Some(150.0));
    assert_eq!(key("CRPIX2").as_deref(), Some(&*format!("{}", SIZE / 2 + 1)));
    assert_eq!(key("TELESCOP").as_deref(), Some("VLA"));
}

#[test]
fn memory_and_parquet_inputs_give_the_same_products_and_files() {
    let obs = observation(5);
    let engine = engine();
    let from_memory = engine.image(input("obs", &obs), &clean_params()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let parquet = dir.path().join("obs.parquet");
    r2d2_imaging::vis::write_parquet(&parquet, &obs.table, &obs.meta).unwrap();
    // The file path, writing its products as `r2d2 image --name` does.
    let prefix = dir.path().join("file").to_string_lossy().into_owned();
    let from_file = engine.image(parquet.as_path(), &ImageRequest { name: Some(prefix), ..clean_params() }).unwrap();
    assert_eq!(from_memory.dirty, from_file.dirty);
    assert_eq!(from_memory.model, from_file.model);
    assert_eq!(from_memory.header, from_file.header);
    // JobProducts::write makes the files the writer stage made, pixel for pixel.
    let written = dir.path().join("memory");
    from_memory.write(&written).unwrap();
    for product in ["dirty", "psf", "model", "residual", "image"] {
        let read = |prefix: &str| r2d2_imaging::fits::read_image(&dir.path().join(format!("{prefix}-{product}.fits"))).unwrap();
        let (a, b) = (read("memory"), read("file"));
        assert_eq!(a.data, b.data, "{product}");
        assert_eq!(a.wcs, b.wcs, "{product}");
        assert!(dir.path().join(format!("memory-{product}.png")).is_file());
    }
    let model = r2d2_imaging::fits::read_image(&dir.path().join("memory-model.fits")).unwrap();
    let expected: Vec<f64> = from_memory.model.as_ref().unwrap().iter().map(|&v| f64::from(v)).collect();
    assert_eq!(model.data, expected);
    for suffix in ["metrics.json", "metrics.parquet"] {
        assert!(dir.path().join(format!("memory-{suffix}")).is_file(), "{suffix}");
    }
}

/// `Engine::dirty` (`r2d2 dirty`) runs the stages `image` runs, with no step: its images are
/// those the library's `imaging::dirty_image` makes of the same samples in one operator, which
/// `r2d2 dirty` called before, to the NUFFT's accuracy (the gridder stage grids them as read,
/// with the w-term each chunk through its own w-planes), the same from record batches as from
/// the file; there is no model, residual or metrics, and with a name only the dirty image and
/// the PSF are written, as the products hold them.
#[test]
fn dirty_is_the_library_dirty_image_through_the_image_stages() {
    use r2d2_imaging::imaging::WTermMode;
    let obs = observation(9);
    let engine = engine();
    let (vis, _) = obs.table.to_visibilities("table").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let parquet = dir.path().join("obs.parquet");
    r2d2_imaging::vis::write_parquet(&parquet, &obs.table, &obs.meta).unwrap();
    let mut names = vec!["obs.parquet".to_string()];
    // Off: coplanar; auto includes the w-term on this field (as the image test above says).
    for (w_term, tolerance) in [("off", 1e-6), ("auto", 1e-5)] {
        let mut request = DirtyRequest::default();
        (request.grid.size, request.grid.threads, request.grid.w_term) = (SIZE, 2, WTermMode::from_name(w_term).unwrap());
        let reference = dirty_image(&vis, &request.grid.dirty_params().unwrap()).unwrap();
        let from_memory = engine.dirty(input("obs", &obs), &request).unwrap();
        let prefix = dir.path().join(format!("d-{w_term}")).to_string_lossy().into_owned();
        let from_file = engine.dirty(parquet.as_path(), &DirtyRequest { name: Some(prefix.clone()), ..request.clone() }).unwrap();
        assert_eq!((&from_memory.dirty, &from_memory.psf, &from_memory.header), (&from_file.dirty, &from_file.psf, &from_file.header), "{w_term}");
        assert!(from_memory.model.is_none() && from_memory.residual.is_none() && from_memory.image.is_none(), "{w_term}");
        assert!(from_memory.iterations == 0 && from_memory.metrics.is_empty(), "{w_term}");
        for (product, ours, theirs) in [("dirty", &from_file.dirty, &reference.dirty), ("psf", &from_file.psf, &reference.psf)] {
            let peak = theirs.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let worst = ours.iter().zip(theirs.iter()).fold(0.0f64, |m, (a, b)| m.max((f64::from(*a) - b).abs()));
            eprintln!("w_term {w_term}, {product}: Engine::dirty vs imaging::dirty_image: {:e} of the peak", worst / peak);
            assert!(worst <= tolerance * peak, "w_term {w_term}, {product}: {worst:e} of {peak}");
            let written = r2d2_imaging::fits::read_image(std::path::Path::new(&format!("{prefix}-{product}.fits"))).unwrap();
            assert_eq!(written.data, ours.iter().map(|&v| f64::from(v)).collect::<Vec<_>>(), "{w_term} {product}");
            names.push(format!("d-{w_term}-{product}.fits"));
        }
        let key = |k: &str| from_file.header.iter().find(|(name, _)| name == k).map(|(_, v)| v.clone());
        assert_eq!((key("TELESCOP").as_deref(), key("WEIGHT").as_deref(), key("CTYPE1").as_deref()), (Some("VLA"), Some("briggs 0"), Some("RA---SIN")));
    }
    let mut written: Vec<String> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    written.sort();
    names.sort();
    assert_eq!(written, names, "the dirty images and PSFs only");
}

const PIPELINE: &str = "\
image: {size: 64}
stages:
  read: {kind: arrow, to: weights}
  weights: {kind: weighting, scheme: natural, to: grid}
  grid: {kind: gridder, to: step}
  step: {kind: clean, major_cycles: 1, to: update}
  update: {kind: residual, to: step, done: deliver}
  deliver: {kind: products}
";

#[test]
fn a_yaml_pipeline_runs_on_several_inputs_and_delivers_each_job() {
    let engine = engine();
    let spec = engine.load_yaml(PIPELINE, "embedded.yaml", &[]).unwrap();
    engine.validate(&spec).unwrap();
    let received: Arc<Mutex<Vec<JobProducts>>> = Arc::default();
    let into = received.clone();
    let sink = move |p: JobProducts| {
        into.lock().unwrap().push(p);
        Ok(())
    };
    let inputs = vec![input("a", &observation(1)), input("b", &observation(2))];
    let report = engine.run(&spec, inputs, Some(Box::new(sink)), Arc::new(AtomicBool::new(false))).unwrap();
    let mut ids: Vec<String> = received.lock().unwrap().iter().map(|p| p.id.clone()).collect();
    ids.sort();
    assert_eq!(ids, ["a", "b"]);
    assert_eq!(report.jobs.len(), 2);
}

/// The run's report names the files each job's writer committed (Python's `run` reads each
/// job's metrics from them), whatever the writer's prefix.
#[test]
fn the_run_report_lists_the_files_each_jobs_writer_wrote() {
    let engine = engine();
    let dir = tempfile::tempdir().unwrap();
    let prefix = dir.path().join("out").join("{job}-x");
    let yaml = PIPELINE.replace("done: deliver}\n  deliver: {kind: products}", &format!("done: write}}\n  write: {{kind: writer, prefix: '{}', previews: false}}", prefix.display()));
    let spec = engine.load_yaml(&yaml, "written.yaml", &[]).unwrap();
    let report = engine.run(&spec, vec![input("a", &observation(1)), input("b", &observation(2))], None, Arc::default()).unwrap();
    assert_eq!(report.written.keys().collect::<Vec<_>>(), ["a", "b"]);
    for (job, files) in &report.written {
        let names: std::collections::BTreeSet<String> = files.iter().map(|f| f.file_name().unwrap().to_string_lossy().into_owned()).collect();
        for product in ["dirty.fits", "psf.fits", "model.fits", "residual.fits", "image.fits", "metrics.json", "metrics.parquet"] {
            assert!(names.contains(&format!("{job}-x-{product}")), "{job}: {names:?}");
        }
        assert!(files.iter().all(|f| f.starts_with(dir.path().join("out")) && f.is_file()), "{files:?}");
    }
}

/// Runs `spec` on one input and returns the job's products.
fn run_one(engine: &Engine, spec: &r2d2_imaging::PipelineSpec, input: MemoryInput) -> JobProducts {
    let received: Arc<Mutex<Vec<JobProducts>>> = Arc::default();
    let into = received.clone();
    let sink = move |p: JobProducts| {
        into.lock().unwrap().push(p);
        Ok(())
    };
    engine.run(spec, vec![input], Some(Box::new(sink)), Arc::default()).unwrap();
    let mut received = received.lock().unwrap();
    assert_eq!(received.len(), 1);
    received.remove(0)
}

/// PIPELINE written with the typed parameters instead of YAML text: the same products.
#[test]
fn a_pipeline_of_typed_parameters_is_its_yaml() {
    use r2d2_imaging::params::{ArrowParams, CleanParams, GridderParams, ProductsParams, ResidualParams, WeightingParams, WeightingScheme};
    use r2d2_imaging::{ImageConfig, PipelineSpec, StageSpec};
    let engine = engine();
    let stages = vec![
        StageSpec::typed("read", &ArrowParams::default()).unwrap().to("weights"),
        StageSpec::typed("weights", &WeightingParams { scheme: WeightingScheme::Natural, ..Default::default() }).unwrap().to("grid"),
        StageSpec::typed("grid", &GridderParams::default()).unwrap().to("step"),
        StageSpec::typed("step", &CleanParams { major_cycles: 1, ..Default::default() }).unwrap().to("update"),
        StageSpec::typed("update", &ResidualParams::default()).unwrap().to("step").done("deliver"),
        StageSpec::typed("deliver", &ProductsParams::default()).unwrap(),
    ];
    let typed = PipelineSpec::new("typed", &ImageConfig { size: SIZE, superresolution: None, pixel_arcsec: None, longest_baseline: None }, stages).unwrap();
    let yaml = engine.load_yaml(PIPELINE, "embedded.yaml", &[]).unwrap();
    let obs = observation(3);
    let (a, b) = (run_one(&engine, &typed, input("a", &obs)), run_one(&engine, &yaml, input("a", &obs)));
    assert_eq!((a.iterations, &a.dirty, &a.model), (b.iterations, &b.dirty, &b.model));
    // Typed parameters the kind refuses are still refused when the stage is built, naming it.
    let bad = StageSpec::typed("weights", &WeightingParams { robust: f64::NAN, ..Default::default() }).unwrap().to("grid");
    let mut stages = typed.stages.clone();
    stages[1] = bad;
    let spec = PipelineSpec::new("typed", &typed.image, stages).unwrap();
    let err = engine.validate(&spec).unwrap_err().to_string();
    assert!(err.contains("robust"), "{err}");
}

#[test]
fn errors_name_the_file_line_and_stage() {
    let engine = engine();
    // No weighting stage: found when the graph is checked, before anything runs.
    let text = PIPELINE.replace("read: {kind: arrow, to: weights}", "read: {kind: arrow, to: grid}").replace("  weights: {kind: weighting, scheme: natural, to: grid}\n", "");
    let spec = engine.load_yaml(&text, "embedded.yaml", &[]).unwrap();
    let err = engine.validate(&spec).unwrap_err();
    let (file, line, _) = err.location().expect("a located error");
    assert_eq!((file, line), (std::path::Path::new("embedded.yaml"), 4));
    let err = err.to_string();
    assert!(err.contains("embedded.yaml") && err.contains("line 4") && err.contains("weighting stage"), "{err}");
    // A misspelt key of a stage, at its line and column.
    let err = engine.load_yaml(&PIPELINE.replace("scheme: natural", "schme: natural"), "embedded.yaml", &[]).and_then(|s| engine.validate(&s));
    let err = err.unwrap_err().to_string();
    assert!(err.contains("embedded.yaml") && err.contains("line 4") && err.contains("schme"), "{err}");
    // A run without inputs for its memory source says so.
    let spec = engine.load_yaml(PIPELINE, "embedded.yaml", &[]).unwrap();
    let err = engine.run(&spec, Vec::new(), Some(Box::new(|_: JobProducts| Ok(()))), Arc::default()).unwrap_err().to_string();
    assert!(err.contains("in-memory inputs"), "{err}");
    // Batches without the observation metadata are refused, naming the input.
    let obs = observation(4);
    let (schema, batches) = to_record_batches(&obs.table, &obs.meta, 1000).unwrap();
    let bare = Arc::new(schema.as_ref().clone().with_metadata(Default::default()));
    let batches = batches.into_iter().map(|b| arrow::array::RecordBatch::try_new(bare.clone(), b.columns().to_vec()).unwrap()).collect();
    let err = engine.image(MemoryInput::from_batches("bare", bare, batches), &clean_params()).unwrap_err().to_string();
    assert!(err.contains("in-memory input 'bare'") && err.contains("phase_centre"), "{err}");
}

/// Counts the jobs it receives: a sink of the embedding program's own.
struct Count(Arc<AtomicUsize>);

impl Stage<Job> for Count {
    fn process(&mut self, job: Job, _emit: &mut Emit<'_>) -> r2d2_imaging::Result<()> {
        assert!(job.imaging.is_some());
        self.0.fetch_add(1, Ordering::SeqCst);
        Ok(())
    }
}

/// The kind building [`Count`] stages, all adding to one counter.
struct CountKind(Arc<AtomicUsize>);

impl StageKind<Job> for CountKind {
    fn name(&self) -> &str {
        "count"
    }
    fn role(&self) -> Role {
        Role::Sink
    }
    fn consumes(&self, _: &BuildContext<'_>) -> r2d2_imaging::Result<Vec<Product>> {
        Ok(vec![Product::Imaging])
    }
    fn build(&self, _: &BuildContext<'_>) -> r2d2_imaging::Result<Built> {
        Ok(Built::Stage(Box::new(Count(self.0.clone()))))
    }
}

#[test]
fn a_program_registers_a_stage_kind_of_its_own() {
    let mut engine = engine();
    let counted = Arc::new(AtomicUsize::new(0));
    engine.registry_mut().register(CountKind(counted.clone())).unwrap();
    let spec = engine.load_yaml(&PIPELINE.replace("kind: products", "kind: count"), "custom.yaml", &[]).unwrap();
    let inputs = vec![input("a", &observation(6)), input("b", &observation(7))];
    engine.run(&spec, inputs, None, Arc::default()).unwrap();
    assert_eq!(counted.load(Ordering::SeqCst), 2);
    // A name taken already is refused.
    assert!(engine.registry_mut().register(CountKind(counted)).is_err());
}

/// Fails every job, as a stage of the program's own with a bug might.
struct Fails;

impl Stage<Job> for Fails {
    fn process(&mut self, _: Job, _: &mut Emit<'_>) -> r2d2_imaging::Result<()> {
        Err(r2d2_imaging::Error::parameter("fails", "failing on purpose"))
    }
}

struct FailsKind;

impl StageKind<Job> for FailsKind {
    fn name(&self) -> &str {
        "fails"
    }
    fn role(&self) -> Role {
        Role::Sink
    }
    fn consumes(&self, _: &BuildContext<'_>) -> r2d2_imaging::Result<Vec<Product>> {
        Ok(vec![Product::Imaging])
    }
    fn build(&self, _: &BuildContext<'_>) -> r2d2_imaging::Result<Built> {
        Ok(Built::Stage(Box::new(Fails)))
    }
}

#[test]
fn a_failed_or_cancelled_run_leaves_the_engine_ready_for_the_next() {
    let mut engine = engine();
    engine.registry_mut().register(FailsKind).unwrap();
    let cancel = engine.cancel_flag();
    // A stage failing stops that run only: the caller's flag (which `image` uses) stays clear.
    let failing = engine.load_yaml(&PIPELINE.replace("kind: products", "kind: fails"), "fails.yaml", &[]).unwrap();
    let err = engine.run(&failing, vec![input("a", &observation(8))], None, cancel.clone()).unwrap_err().to_string();
    assert!(err.contains("failing on purpose"), "{err}");
    assert!(!cancel.load(Ordering::SeqCst), "a failed run set the engine's cancel flag: every later image() would stop at once");
    engine.image(input("after-failure", &observation(9)), &clean_params()).unwrap();

    // Cancelled by the caller once the first job is delivered: an interruption, not every job.
    let spec = engine.load_yaml(PIPELINE, "embedded.yaml", &[]).unwrap();
    let delivered = Arc::new(AtomicUsize::new(0));
    let sink = |delivered: &Arc<AtomicUsize>, cancel: Option<Arc<AtomicBool>>| {
        let (delivered, cancel) = (delivered.clone(), cancel);
        move |_: JobProducts| {
            delivered.fetch_add(1, Ordering::SeqCst);
            if let Some(cancel) = &cancel {
                cancel.store(true, Ordering::SeqCst);
            }
            Ok(())
        }
    };
    let inputs = |ids: &[&str]| ids.iter().enumerate().map(|(k, id)| input(id, &observation(10 + k as u64))).collect::<Vec<_>>();
    let err = engine.run(&spec, inputs(&["a", "b", "c", "d"]), Some(Box::new(sink(&delivered, Some(cancel.clone())))), cancel.clone()).unwrap_err();
    assert!(matches!(err, r2d2_imaging::Error::Interrupted(_)), "{err}");
    let first = delivered.load(Ordering::SeqCst);
    assert!((1..4).contains(&first), "{first} of 4 jobs delivered after a cancel at the first");

    // The same engine, its flag cleared by the caller, runs again in full.
    cancel.store(false, Ordering::SeqCst);
    let again = Arc::new(AtomicUsize::new(0));
    let report = engine.run(&spec, inputs(&["e", "f"]), Some(Box::new(sink(&again, None))), cancel.clone()).unwrap();
    assert_eq!((report.jobs.len(), again.load(Ordering::SeqCst)), (2, 2));
    engine.image(input("after-cancel", &observation(12)), &clean_params()).unwrap();
}

/// A series that does not load fails validation at the YAML line of `series`, and a caller can
/// still match on the series error beneath it (`Error::module_error`, `source()`).
#[test]
fn a_series_error_keeps_its_yaml_line_and_its_kind() {
    let d = tempfile::tempdir().unwrap();
    let missing = d.path().join("no-such-series");
    let yaml = format!(
        "image: {{size: 64}}\nstages:\n  source: {{kind: simulate, to: weights}}\n  weights: {{kind: weighting, scheme: natural, to: grid}}\n  grid: {{kind: gridder, to: step}}\n  step:\n    kind: onnx\n    series: '{}'\n    to: update\n  update: {{kind: residual, to: step, done: write}}\n  write: {{kind: writer, prefix: 'out/{{job}}'}}\n",
        missing.display()
    );
    let engine = engine();
    let spec = engine.load_yaml(&yaml, "series.yaml", &[]).unwrap();
    let error = engine.validate(&spec).unwrap_err();
    let (file, line, _) = error.location().expect("a located error");
    assert_eq!((file.to_str(), line), (Some("series.yaml"), 8), "{error}");
    let module = error.module_error().expect("the series error beneath");
    assert!(module.downcast_ref::<r2d2_imaging::error::SeriesError>().is_some(), "{module:?}");
    assert!(std::error::Error::source(&error).is_some(), "the cause is the located error's source");
    assert!(error.to_string().contains("no-such-series"), "{error}");
}

/// A source kind of the program's own, in one place as a built-in source kind is in its file
/// (`src/stages/*.rs`): its parameters, what it says of its jobs (`SourceParams`) and its
/// source. Registering it is one line; nothing else names it.
mod toy {
    use r2d2_imaging::{Job, Reads, Source, SourceKind, SourceParams, StageParams};
    use serde::{Deserialize, Serialize};

    /// `kind: toy`: a simulated observation per seed, one job each.
    #[derive(Clone, Debug, Deserialize, Serialize)]
    #[serde(deny_unknown_fields)]
    pub struct ToyParams {
        pub seeds: Vec<u64>,
    }

    impl StageParams for ToyParams {
        const KIND: &'static str = "toy";
    }

    impl SourceParams for ToyParams {
        fn reads(&self) -> Reads {
            Reads::Nothing
        }
        fn several_jobs(&self) -> Option<String> {
            (self.seeds.len() > 1).then(|| format!("a toy source makes {} jobs", self.seeds.len()))
        }
    }

    struct ToySource(Vec<u64>);

    impl Source<Job> for ToySource {
        fn produce(&mut self, emit: &mut dyn FnMut(Job) -> r2d2_imaging::Result<()>, _cancelled: &dyn Fn() -> bool) -> r2d2_imaging::Result<()> {
            for &seed in &self.0 {
                let obs = super::observation(seed);
                let id = format!("toy-{seed}");
                let (vis, _) = obs.table.to_visibilities(&id)?;
                emit(Job::new(id, obs.meta, vis))?;
            }
            Ok(())
        }
    }

    /// The kind, as the program registers it.
    pub const KIND: SourceKind<ToyParams> = SourceKind::new(|params, _ctx| Ok(Box::new(ToySource(params.seeds))));
}

#[test]
fn a_program_adds_a_source_kind_in_one_place() {
    let mut engine = engine();
    engine.registry_mut().register(toy::KIND).unwrap();
    let toy = |seeds: &str| PIPELINE.replace("{kind: arrow,", &format!("{{kind: toy, seeds: {seeds},"));
    let spec = engine.load_yaml(&toy("[3, 4]"), "toy.yaml", &[]).unwrap();
    let received: Arc<Mutex<Vec<String>>> = Arc::default();
    let into = received.clone();
    let sink = move |p: JobProducts| {
        into.lock().unwrap().push(p.id);
        Ok(())
    };
    engine.run(&spec, Vec::new(), Some(Box::new(sink)), Arc::default()).unwrap();
    let mut ids = received.lock().unwrap().clone();
    ids.sort();
    assert_eq!(ids, ["toy-3", "toy-4"]);
    // Its parameters are checked as a built-in kind's are, at their line.
    let err = engine.load_yaml(&toy("[3]").replace("seeds:", "sedes:"), "toy.yaml", &[]).and_then(|s| engine.validate(&s)).unwrap_err().to_string();
    assert!(err.contains("line 3") && err.contains("stages.read.sedes (toy stage)"), "{err}");
    // What it says of its jobs is what the stages after it check, before anything runs: a
    // writer's prefix without {job} where it makes several, a model column where it reads no
    // MeasurementSet.
    let writer = |seeds: &str, writer: &str| toy(seeds).replace("deliver: {kind: products}", &format!("deliver: {{kind: writer, {writer}}}"));
    let validate = |text: &str| engine.load_yaml(text, "toy.yaml", &[]).and_then(|s| engine.validate(&s)).map_err(|e| e.to_string());
    let err = validate(&writer("[3, 4]", "prefix: out/all")).unwrap_err();
    assert!(err.contains("stages.deliver.prefix") && err.contains("a toy source makes 2 jobs"), "{err}");
    validate(&writer("[3]", "prefix: out/all")).unwrap();
    let err = validate(&writer("[3]", "model_column: MODEL_DATA")).unwrap_err();
    assert!(err.contains("stages.deliver.model_column") && err.contains("kind 'toy'") && err.contains("reads no MeasurementSet"), "{err}");
}
