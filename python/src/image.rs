//! `image(obs, ...)`: one observation through `r2d2 image`'s pipeline ([`Engine::image`]).

use crate::arrow_in;
use crate::products::Products;
use crate::{run_released, R2D2Error};
use pyo3::prelude::*;
use r2d2_imaging::{BackendChoice, Engine, EngineOptions, ImageParams, Observation, StepChoice};
use r2d2_imaging::MemoryInput;
use r2d2_imaging::Weighting;
use std::path::PathBuf;

fn parameter(name: &str, message: impl std::fmt::Display) -> PyErr {
    R2D2Error::new_err(format!("invalid {name}: {message}"))
}

/// `step` as `r2d2 image --step` reads it: `auto`, `clean`, a plugin library, or a series.
fn step_choice(step: &str, plugin_config: Option<&str>) -> PyResult<StepChoice> {
    let path = PathBuf::from(step);
    let is_library = matches!(path.extension().and_then(|e| e.to_str()), Some("so" | "dylib" | "dll"));
    if plugin_config.is_some() && !is_library {
        return Err(parameter("plugin_config", format!("only a native plugin takes a configuration; step is '{step}'")));
    }
    Ok(match step {
        "auto" => StepChoice::Auto,
        "clean" => StepChoice::Clean,
        _ if is_library => StepChoice::Native {
            library: path,
            config: plugin_config
                .map(|text| serde_yaml::from_str(text).map_err(|e| parameter("plugin_config", format!("expected a YAML or JSON mapping: {e}"))))
                .transpose()?,
        },
        _ => StepChoice::Series(path),
    })
}

fn backend_choice(backend: &str) -> PyResult<BackendChoice> {
    match backend {
        "auto" => Ok(BackendChoice::Auto),
        "ort" => Ok(BackendChoice::Ort),
        "tract" => Ok(BackendChoice::Tract),
        other => Err(parameter("backend", format!("expected auto, ort or tract, got '{other}'"))),
    }
}

/// Images `obs` (a path, or an object with `__arrow_c_stream__`) as `r2d2 image` does; see the
/// Python wrapper `r2d2_imaging.image` for the parameters.
#[pyfunction]
#[pyo3(signature = (obs, *, id, size, step, weighting, robust, superresolution, pixel_arcsec, truth, iterations, threads,
                    backend, prefetch, plugin_config, epsilon, oversampling, weighting_grid_factor, onnx_runtime, w_term))]
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
) -> PyResult<Products> {
    let observation = match obs.extract::<PathBuf>() {
        Ok(path) => Observation::Path(path),
        Err(_) => {
            let stream = arrow_in::stream_of(obs)?;
            Observation::Batches(MemoryInput::new(id.clone().unwrap_or_else(|| "table".into()), stream))
        }
    };
    let params = ImageParams {
        size,
        superresolution,
        pixel_arcsec,
        weighting: Weighting::from_options(weighting, robust).map_err(crate::engine_error)?,
        weighting_grid_factor,
        epsilon,
        oversampling,
        w_term: r2d2_imaging::operator::WTermMode::from_name(w_term).map_err(crate::engine_error)?,
        step: step_choice(step, plugin_config)?,
        iterations,
        backend: backend_choice(backend)?,
        prefetch,
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
