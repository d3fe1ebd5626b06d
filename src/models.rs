//! Network series on disk and the ONNX networks they hold: where series are looked up, what
//! is found there, which inference backend a build will use, and one network run the way a
//! step runs it (for checks against the framework that trained it).

use crate::steps::runtime::{self, Network};
use crate::{BackendChoice, Result};
use std::path::{Path, PathBuf};

pub use crate::steps::runtime::use_onnx_runtime;
pub use crate::steps::series::{add_model_dir, model_dirs};

/// A usable series found in the model directories.
#[derive(Clone, Debug)]
pub struct FoundSeries {
    pub name: String,
    /// Its folder.
    pub path: PathBuf,
    /// Networks per realisation.
    pub networks: usize,
    /// Image sizes it was trained at.
    pub image_sizes: Vec<usize>,
    /// The telescope its manifest names, if any.
    pub telescope: Option<String>,
    /// Its declared domain (the manifest's `validity`) as JSON, if any.
    pub domain_json: Option<String>,
}

/// The usable series in the model directories, in the order `auto` prefers them.
pub fn found_series() -> Result<Vec<FoundSeries>> {
    Ok(crate::steps::series::found_series()?
        .into_iter()
        .map(|(path, s)| {
            let manifest = s.manifest.as_ref();
            FoundSeries {
                networks: s.len(),
                telescope: manifest.map(|m| m.telescope.clone()).filter(|t| !t.is_empty()),
                domain_json: manifest.and_then(|m| m.validity.as_ref()).and_then(|v| serde_json::to_string(v).ok()),
                name: s.name,
                path,
                image_sizes: s.image_sizes,
            }
        })
        .collect())
}

/// The series `auto` takes for `size x size` images where nothing else of the job is known
/// (a wrapper reading a command line: no telescope, no weighting), and its trained size
/// nearest `size` where that is not `size`: a run off its trained size weighs on that trained
/// field's uv grid, as the weighting stage does.
pub fn auto_series_for_size(size: usize) -> Result<(String, Option<usize>)> {
    let (dir, _) = crate::steps::series::select_for(size, &crate::ImagingSetup::default())?;
    let series = crate::steps::series::Series::open(&dir)?;
    let trained = series.nearest_trained_size(size).filter(|t| *t != size);
    Ok((series.name, trained))
}

/// What `choice` resolves to on this machine (`auto`: native ONNX Runtime where it was
/// loaded, else tract), as the logs name it.
pub fn backend(choice: BackendChoice, threads: usize) -> Result<String> {
    Ok(runtime::Runtime::select(choice, threads)?.describe())
}

/// One ONNX network of a series, checked as a step checks it and loaded on a backend.
pub struct LoadedNetwork(Box<dyn Network>);

impl LoadedNetwork {
    /// Checks `path` for `size` x `size` images and loads it on `backend`.
    pub fn load(path: &Path, size: usize, backend: BackendChoice, threads: usize) -> Result<LoadedNetwork> {
        let signature = runtime::check_network(path, size)?;
        Ok(LoadedNetwork(runtime::Runtime::select(backend, threads)?.load(path, size, &signature)?))
    }

    /// The network's output for `input` (its two images, as the step stacks them).
    pub fn run(&mut self, input: &[f32]) -> Result<Vec<f32>> {
        self.0.run(input)
    }
}
