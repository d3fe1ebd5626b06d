//! `r2d2_imaging._native`: the engine's Rust API for Python (the pure-Python half,
//! `python/r2d2_imaging/`, gives it its documented signatures).
//!
//! Every call that does engine work runs it on a thread of its own and waits for it with the
//! GIL released, taking the GIL back between short waits only to let Python run its signal
//! handlers: Ctrl-C (KeyboardInterrupt) cancels the run at the engine's next job boundary,
//! waits for the engine to stop, then raises. Engine errors become `R2D2Error` with the
//! engine's message (file, line, column, stage, job) and its causes; an error of a module that
//! has its own (FITS, model series, ONNX, native plugin, MeasurementSet) becomes the subclass
//! of `R2D2Error` for it, so Python can catch that kind alone.

mod arrow_in;
mod driven;
mod image;
mod logging;
mod parts;
mod products;

/// Large blocks on transparent huge pages, as in the `r2d2` binary (see the type).
#[global_allocator]
static ALLOCATOR: r2d2_imaging::LargeBlocksOnHugePages = r2d2_imaging::LargeBlocksOnHugePages;

use numpy::PyArray1;
use pyo3::create_exception;
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use r2d2_imaging::{Engine, EngineOptions, PipelineSpec};
use crossbeam_channel::{bounded, RecvTimeoutError};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

create_exception!(r2d2_imaging, R2D2Error, PyRuntimeError, "An error reported by the r2d2 engine; its message names the file, line, column, stage or job.");
create_exception!(r2d2_imaging, FitsError, R2D2Error, "A FITS image could not be read (cfitsio's report is in the message).");
create_exception!(r2d2_imaging, SeriesError, R2D2Error, "A model series could not be used: its directory, manifest or network files.");
create_exception!(r2d2_imaging, OnnxError, R2D2Error, "An ONNX network could not be checked, loaded or run.");
create_exception!(r2d2_imaging, PluginError, R2D2Error, "A native plugin could not be loaded, or failed.");
create_exception!(r2d2_imaging, MeasurementSetError, R2D2Error, "A MeasurementSet could not be read or written.");
create_exception!(r2d2_imaging, TableError, R2D2Error, "A visibility table (Parquet, Arrow) could not be read: not that format, a column missing or mistyped, bad metadata.");

/// How often a waiting call looks at Python's signals.
const SIGNAL_POLL: Duration = Duration::from_millis(50);

pub(crate) fn engine_error(e: r2d2_imaging::Error) -> PyErr {
    use r2d2_imaging::error as kinds;
    let message = e.report().to_string();
    // The module's error, also when a stage reported it on a job.
    let module = e.module_error();
    let is = |check: fn(&(dyn std::error::Error + 'static)) -> bool| module.is_some_and(check);
    if is(|m| m.is::<kinds::FitsError>()) {
        FitsError::new_err(message)
    } else if is(|m| m.is::<kinds::SeriesError>()) {
        SeriesError::new_err(message)
    } else if is(|m| m.is::<kinds::OnnxError>()) {
        OnnxError::new_err(message)
    } else if is(|m| m.is::<kinds::PluginError>()) {
        PluginError::new_err(message)
    } else if is(|m| m.is::<kinds::MsError>()) {
        MeasurementSetError::new_err(message)
    } else if is(|m| m.is::<kinds::TableError>()) {
        TableError::new_err(message)
    } else {
        R2D2Error::new_err(message)
    }
}

/// Runs `work` on a thread of its own with the GIL released, checking Python's signals while
/// it runs. On KeyboardInterrupt (or any exception a signal handler raises) the cancel flag
/// given to `work` is set, the engine is waited for (it stops at its next job boundary) and
/// the exception is raised.
pub(crate) fn run_released<T: Send + 'static>(
    py: Python<'_>,
    work: impl FnOnce(Arc<AtomicBool>) -> r2d2_imaging::Result<T> + Send + 'static,
) -> PyResult<T> {
    // Refused at once in a process forked after the engine ran in its parent (a
    // `multiprocessing` worker under Linux's default start method): its threads are not here.
    r2d2_imaging::claim_process().map_err(engine_error)?;
    logging::follow_level(py)?;
    let cancel = Arc::new(AtomicBool::new(false));
    let (tx, rx) = bounded(1);
    let flag = cancel.clone();
    let worker = std::thread::Builder::new()
        .name("r2d2-engine".into())
        .spawn(move || {
            // A panic is a bug; it must reach Python as an exception, not unwind through it.
            let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| work(flag)));
            let _ = tx.send(outcome);
        })
        .map_err(|e| R2D2Error::new_err(format!("cannot start the engine thread: {e}")))?;
    let outcome = loop {
        match py.allow_threads(|| rx.recv_timeout(SIGNAL_POLL)) {
            Ok(outcome) => break outcome,
            Err(RecvTimeoutError::Timeout) => {
                // Handing records to `logging` runs Python code, and with it a pending signal
                // handler: its KeyboardInterrupt comes back from the hand-over.
                if let Err(interrupt) = py.check_signals().and_then(|()| logging::hand_over(py)) {
                    cancel.store(true, Ordering::SeqCst);
                    py.allow_threads(|| {
                        let _ = rx.recv();
                    });
                    let _ = worker.join();
                    let _ = logging::hand_over(py);
                    return Err(interrupt);
                }
            }
            Err(RecvTimeoutError::Disconnected) => {
                return Err(R2D2Error::new_err("the engine thread ended without a result (this is a bug, please report it)"));
            }
        }
    };
    let _ = worker.join();
    logging::hand_over(py)?;
    match outcome {
        Ok(result) => result.map_err(engine_error),
        Err(payload) => Err(R2D2Error::new_err(format!(
            "the engine failed unexpectedly ({}); this is a bug, please report it",
            r2d2_imaging::error::panic_message(payload.as_ref())
        ))),
    }
}

/// An engine with the built-in stage kinds; the pipeline's own `threads` sizes its runs.
fn engine(onnx_runtime: Option<std::path::PathBuf>) -> r2d2_imaging::Result<Engine> {
    Engine::new(EngineOptions { threads: 0, onnx_runtime })
}

/// Parses a pipeline: `text` as read from `file_name` (named in errors), with `overrides`
/// (`stage.key=value`, as `r2d2 run --set`).
fn parse(engine: &Engine, text: &str, file_name: &str, overrides: Vec<String>) -> PyResult<PipelineSpec> {
    engine.load_yaml(text, file_name, &overrides).map_err(engine_error)
}

/// Checks a pipeline without running it (`r2d2 validate`); returns its stage names.
#[pyfunction]
#[pyo3(signature = (text, file_name, overrides))]
fn validate(py: Python<'_>, text: &str, file_name: &str, overrides: Vec<String>) -> PyResult<Vec<String>> {
    let engine = engine(None).map_err(engine_error)?;
    let spec = parse(&engine, text, file_name, overrides)?;
    let names = spec.stages.iter().map(|s| s.name.clone()).collect();
    // Building the stages reads model manifests and plugin libraries: no GIL needed.
    run_released(py, move |_| engine.validate(&spec))?;
    Ok(names)
}

/// Runs a pipeline (`r2d2 run`); returns the run's report as a dict: `jobs` (ids in completion
/// order), `seconds`, `stage_seconds`.
#[pyfunction]
#[pyo3(signature = (text, file_name, overrides, onnx_runtime=None))]
fn run<'py>(
    py: Python<'py>,
    text: &str,
    file_name: &str,
    overrides: Vec<String>,
    onnx_runtime: Option<std::path::PathBuf>,
) -> PyResult<Bound<'py, PyDict>> {
    let engine = engine(onnx_runtime).map_err(engine_error)?;
    let config = parse(&engine, text, file_name, overrides)?;
    let report = run_released(py, move |cancel| engine.run(&config, Vec::new(), None, cancel))?;
    // The metrics each job's writers committed (`<prefix>-metrics.json`), as the run reports them.
    let metrics_files = PyDict::new(py);
    for job in &report.jobs {
        let written = report.written.get(job).map(Vec::as_slice).unwrap_or_default();
        let files: Vec<String> =
            written.iter().filter(|p| p.to_string_lossy().ends_with("-metrics.json")).map(|p| p.display().to_string()).collect();
        metrics_files.set_item(job, files)?;
    }
    let out = PyDict::new(py);
    out.set_item("metrics_files", metrics_files)?;
    out.set_item("jobs", report.jobs)?;
    out.set_item("seconds", report.seconds)?;
    out.set_item("stage_seconds", report.stage_seconds)?;
    Ok(out)
}

/// The table rows of each job that `split_by: {column, window}` makes of `table` (anything
/// with `__arrow_c_stream__`, named `name` in messages), exactly as the engine's sources split
/// it: `([(suffix, rows)], longest_baseline)`, rows a uint64 array of the rows kept for
/// imaging, `longest_baseline` (wavelengths) what sets the pixel size the parts share.
#[pyfunction]
#[pyo3(signature = (table, name, column, window=None))]
fn split_rows<'py>(
    py: Python<'py>,
    table: &Bound<'py, PyAny>,
    name: &str,
    column: String,
    window: Option<f64>,
) -> PyResult<(Vec<(String, Bound<'py, PyArray1<u64>>)>, f64)> {
    let stream = arrow_in::stream_of(table)?;
    let split = r2d2_imaging::parts::SplitBy { column, window };
    split.check().map_err(|m| R2D2Error::new_err(format!("split_by.window: {m}")))?;
    let name = name.to_string();
    let parts = run_released(py, move |cancel| {
        let mut reader = r2d2_imaging::parts::memory_table(r2d2_imaging::MemoryInput::new(name.as_str(), stream), &name)?;
        r2d2_imaging::parts::split_rows(&mut reader, &split, "split_by", &|| cancel.load(Ordering::SeqCst))
    })?;
    let split = parts.ok_or_else(|| R2D2Error::new_err("interrupted while splitting"))?;
    // The row vectors become the arrays' buffers: moved, not copied.
    let parts = split.parts.into_iter().map(|(suffix, rows)| (suffix, PyArray1::from_vec(py, rows))).collect();
    Ok((parts, split.longest_baseline))
}

/// Add a directory of model series to look up after the engine's own places.
#[pyfunction]
fn add_model_dir(dir: std::path::PathBuf) {
    r2d2_imaging::models::add_model_dir(dir);
}

/// What this build and machine will use, as `r2d2 info` and `r2d2 models` say it: version,
/// gridder SIMD level, threads, the ONNX inference backend `auto` picks with `onnx_runtime`
/// (a library path or None), where series are looked up and the usable series found there
/// (in the order `auto` prefers them).
#[pyfunction]
#[pyo3(signature = (onnx_runtime=None))]
fn info(py: Python<'_>, onnx_runtime: Option<std::path::PathBuf>) -> PyResult<Bound<'_, PyDict>> {
    use r2d2_imaging::models::{backend, found_series, model_dirs, use_onnx_runtime};
    use r2d2_imaging::BackendChoice;
    let out = PyDict::new(py);
    out.set_item("version", env!("CARGO_PKG_VERSION"))?;
    out.set_item("gridder_simd", format!("{:?}", r2d2_imaging::SimdLevel::detect()))?;
    out.set_item("threads", std::thread::available_parallelism().map_or(1, |n| n.get()))?;
    let backend = run_released(py, move |_| {
        if let Some(lib) = &onnx_runtime {
            use_onnx_runtime(lib)?;
        }
        backend(BackendChoice::Auto, 0)
    })?;
    out.set_item("onnx_backend", backend)?;
    out.set_item("model_dirs", model_dirs().iter().map(|d| d.display().to_string()).collect::<Vec<_>>())?;
    let series = pyo3::types::PyList::empty(py);
    for s in found_series().map_err(engine_error)? {
        let entry = PyDict::new(py);
        entry.set_item("name", &s.name)?;
        entry.set_item("path", s.path.display().to_string())?;
        entry.set_item("networks", s.networks)?;
        entry.set_item("image_sizes", s.image_sizes.clone())?;
        entry.set_item("telescope", s.telescope.clone())?;
        entry.set_item("domain", s.domain_json.map(|d| py.import("json")?.call_method1("loads", (d,))).transpose()?)?;
        series.append(entry)?;
    }
    out.set_item("series", series)?;
    Ok(out)
}

/// The series `auto` takes for `size x size` images where nothing else of the job is known,
/// as `(name, trained size)`: the trained size nearest `size` where the series runs off it
/// (the job then weighs on that trained field's uv grid), else None.
#[pyfunction]
fn auto_series(size: usize) -> PyResult<(String, Option<usize>)> {
    r2d2_imaging::models::auto_series_for_size(size).map_err(engine_error)
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    logging::install();
    m.add("R2D2Error", m.py().get_type::<R2D2Error>())?;
    m.add("FitsError", m.py().get_type::<FitsError>())?;
    m.add("SeriesError", m.py().get_type::<SeriesError>())?;
    m.add("OnnxError", m.py().get_type::<OnnxError>())?;
    m.add("PluginError", m.py().get_type::<PluginError>())?;
    m.add("MeasurementSetError", m.py().get_type::<MeasurementSetError>())?;
    m.add("TableError", m.py().get_type::<TableError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(validate, m)?)?;
    m.add_function(wrap_pyfunction!(run, m)?)?;
    m.add_function(wrap_pyfunction!(split_rows, m)?)?;
    m.add_function(wrap_pyfunction!(info, m)?)?;
    m.add_function(wrap_pyfunction!(auto_series, m)?)?;
    m.add_function(wrap_pyfunction!(add_model_dir, m)?)?;
    m.add_function(wrap_pyfunction!(image::image, m)?)?;
    m.add_function(wrap_pyfunction!(image::image_options, m)?)?;
    m.add_function(wrap_pyfunction!(products::_products, m)?)?;
    m.add_class::<products::Products>()?;
    m.add_class::<parts::Parts>()?;
    m.add_class::<driven::DrivenSeries>()?;
    m.add_function(wrap_pyfunction!(driven::observation_domain, m)?)?;
    m.add_function(wrap_pyfunction!(parts::part_summary, m)?)?;
    m.add_function(wrap_pyfunction!(parts::part_density, m)?)?;
    m.add_function(wrap_pyfunction!(parts::part_images, m)?)?;
    m.add_function(wrap_pyfunction!(parts::part_w_toeplitz, m)?)?;
    m.add_function(wrap_pyfunction!(parts::part_apply_normal, m)?)?;
    Ok(())
}
