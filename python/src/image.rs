//! `image(obs, ...)`: one observation through `r2d2 image`'s pipeline ([`Engine::image`]).

use crate::arrow_in;
use crate::products::Products;
use crate::run_released;
use pyo3::prelude::*;
use r2d2_imaging::{BackendChoice, CleanControls, Engine, EngineOptions, ImageParams, Observation, StepChoice};
use r2d2_imaging::MemoryInput;
use r2d2_imaging::Weighting;
use std::path::PathBuf;



/// Images `obs` (a path, an object with `__arrow_c_stream__`, or [`Parts`](crate::parts::Parts)) as `r2d2 image` does; see the
/// Python wrapper `r2d2_imaging.image` for the parameters.
#[pyfunction]
#[pyo3(signature = (obs, *, id, size, step, weighting, robust, superresolution, pixel_arcsec, truth, iterations, threads,
                    backend, prefetch, plugin_config, epsilon, oversampling, weighting_grid_factor, onnx_runtime, w_term,
                    niter=None, gain=None, mgain=None, auto_threshold=None, threshold=None, final_clean=true, longest_baseline=None))]
#[allow(clippy::too_many_arguments)]
pub fn image(
    py: Python<'_>,
    obs: &Bound<'_, PyAny>,
    id: Option<String>,
    size: usize,
    step: &str,
    weighting: Option<&str>,
    robust: Option<f64>,
    superresolution: Option<f64>,
    pixel_arcsec: Option<f64>,
    truth: Option<PathBuf>,
    iterations: Option<usize>,
    threads: usize,
    backend: &str,
    prefetch: bool,
    plugin_config: Option<&str>,
    epsilon: f64,
    oversampling: f64,
    weighting_grid_factor: f64,
    onnx_runtime: Option<PathBuf>,
    w_term: &str,
    niter: Option<usize>,
    gain: Option<f64>,
    mgain: Option<f64>,
    auto_threshold: Option<f64>,
    threshold: Option<f64>,
    final_clean: bool,
    longest_baseline: Option<f64>,
) -> PyResult<Products> {
    let observation = if let Ok(parts) = obs.downcast::<crate::parts::Parts>() {
        Observation::Parts(parts.borrow().take()?)
    } else if let Ok(path) = obs.extract::<PathBuf>() {
        Observation::Path(path)
    } else {
        let stream = arrow_in::stream_of(obs)?;
        Observation::Batches(MemoryInput::new(id.clone().unwrap_or_else(|| "table".into()), stream))
    };
    let params = ImageParams {
        size,
        superresolution,
        pixel_arcsec,
        longest_baseline,
        weighting: Weighting::from_options(weighting, robust).map_err(crate::engine_error)?,
        weighting_grid_factor,
        epsilon,
        oversampling,
        w_term: r2d2_imaging::operator::WTermMode::from_name(w_term).map_err(crate::engine_error)?,
        step: StepChoice::parse(step, plugin_config).map_err(crate::engine_error)?,
        iterations,
        clean: CleanControls { niter, gain, mgain, auto_threshold, threshold },
        backend: backend.parse::<BackendChoice>().map_err(crate::engine_error)?,
        prefetch,
        final_clean,
        truth,
        ..ImageParams::default()
    };
    let mut products = run_released(py, move |cancel| {
        let engine = Engine::new(EngineOptions { threads, onnx_runtime })?.with_cancel(cancel);
        engine.image(observation, &params)
    })?;
    if let Some(id) = id {
        products.id = id;
    }
    Products::new(py, products)
}
