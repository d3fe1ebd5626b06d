//! `image(obs, options)`: one observation through `r2d2 image`'s pipeline ([`Engine::image`]),
//! its options parsed by the engine's own request ([`ImageRequest::from_named`]).

use crate::arrow_in;
use crate::products::Products;
use crate::run_released;
use pyo3::prelude::*;
use r2d2_imaging::NamedValue;
use r2d2_imaging::{Engine, EngineOptions, ImageRequest, MemoryInput, Observation};
use std::path::PathBuf;

/// An option's value as the Python wrapper passes it: a switch, or its words.
#[derive(FromPyObject)]
pub enum OptionValue {
    Switch(bool),
    Words(Vec<String>),
}

/// Images `obs` (a path, an object with `__arrow_c_stream__`, or [`Parts`](crate::parts::Parts))
/// as `r2d2 image` does, with `options` named as the request's fields are; see the Python
/// wrapper `r2d2_imaging.image`.
#[pyfunction]
#[pyo3(signature = (obs, options, *, id=None, onnx_runtime=None))]
pub fn image(py: Python<'_>, obs: &Bound<'_, PyAny>, options: Vec<(String, OptionValue)>, id: Option<String>, onnx_runtime: Option<PathBuf>) -> PyResult<Vec<Products>> {
    let named = options.into_iter().map(|(name, value)| {
        let value = match value {
            OptionValue::Switch(on) => NamedValue::Switch(on),
            OptionValue::Words(words) => NamedValue::Words(words),
        };
        (name, value)
    });
    let request = ImageRequest::from_named(named).map_err(crate::engine_error)?;
    let observation = if let Ok(parts) = obs.downcast::<crate::parts::Parts>() {
        Observation::Parts(parts.borrow().take()?)
    } else if let Ok(path) = obs.extract::<PathBuf>() {
        Observation::Path(path)
    } else {
        let stream = arrow_in::stream_of(obs)?;
        Observation::Batches(MemoryInput::new(id.clone().unwrap_or_else(|| "table".into()), stream))
    };
    let threads = request.grid.threads;
    // Several channel groups: every group's products, then the whole band's (join_channels).
    let groups = request.ms.channels_out.is_some_and(|n| n > 1);
    let products = run_released(py, move |cancel| {
        let engine = Engine::new(EngineOptions { threads, onnx_runtime })?.with_cancel(cancel);
        match groups {
            true => engine.image_channels(observation, &request).map(|all| all.channels.into_iter().chain(all.mfs).collect::<Vec<_>>()),
            false => engine.image(observation, &request).map(|one| vec![one]),
        }
    })?;
    products
        .into_iter()
        .map(|mut job| {
            if let Some(id) = id.as_ref().filter(|_| !groups) {
                job.id = id.clone();
            }
            Products::new(py, job)
        })
        .collect()
}

/// The options `image()` takes (every option of `r2d2 image`, named as the request's fields).
#[pyfunction]
pub fn image_options() -> Vec<String> {
    ImageRequest::option_names()
}
