//! `_native.DrivenSeries`: a series whose major cycles an outside imager runs (WSClean's
//! `-python-deconvolution` hook, `r2d2_imaging.wsclean`), over `r2d2_imaging::DrivenSeries`.

use crate::run_released;
use numpy::{PyArray1, PyReadonlyArray1};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use r2d2_imaging::params::{FinalCleanParams, OnnxParams, ResidualParams};
use r2d2_imaging::{Cycle, DrivenConfig, DrivenOutcome, Engine, EngineOptions, ImagingSetup, StopRule};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

#[pyclass(module = "r2d2_imaging._native")]
pub struct DrivenSeries {
    inner: Arc<Mutex<r2d2_imaging::DrivenSeries>>,
    warnings: Vec<String>,
    networks: usize,
    name: String,
    trained_size: Option<usize>,
}

fn outcome_dict<'py>(py: Python<'py>, o: &DrivenOutcome) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("networks_run", o.networks_run)?;
    d.set_item("kept_network", o.kept_network)?;
    d.set_item("stop", o.stop.map(|s| format!("{s:?}").to_lowercase()))?;
    d.set_item("ratios", o.ratios.clone())?;
    d.set_item("final_clean_cycles", o.final_clean_cycles)?;
    d.set_item("residual_ratio", o.ratio)?;
    Ok(d)
}

#[pymethods]
impl DrivenSeries {
    /// Opens the series (`auto`: chosen as `r2d2 image` chooses, by size and the job), checks
    /// the job against its domain and starts: `dirty` and `psf` are the N x N images
    /// (flattened, row-major; the PSF's peak 1 at (N/2, N/2)).
    #[new]
    #[pyo3(signature = (series, size, dirty, psf, telescope=None, superresolution=None, weighting=None, robust=None, track_hours=None, integration_s=None, final_clean=true, early_stop=true, divergence_guard=true, onnx_runtime=None, threads=0))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        series: PathBuf,
        size: usize,
        dirty: PyReadonlyArray1<'_, f64>,
        psf: PyReadonlyArray1<'_, f64>,
        telescope: Option<String>,
        superresolution: Option<f64>,
        weighting: Option<String>,
        robust: Option<f64>,
        track_hours: Option<f64>,
        integration_s: Option<f64>,
        final_clean: bool,
        early_stop: bool,
        divergence_guard: bool,
        onnx_runtime: Option<PathBuf>,
        threads: usize,
    ) -> PyResult<DrivenSeries> {
        let (dirty, psf) = (dirty.as_slice()?.to_vec(), psf.as_slice()?.to_vec());
        let mut step = OnnxParams::new(series);
        step.threads = threads;
        let config = DrivenConfig {
            step,
            size,
            setup: ImagingSetup { superresolution, weighting, robust, telescope, track_hours, integration_s },
            stop: StopRule { early_stop, tolerance: ResidualParams::default().tolerance, divergence_guard },
            final_clean: final_clean.then(FinalCleanParams::default),
        };
        let inner = run_released(py, move |_| {
            // Makes the ONNX Runtime library given (if any) the networks' backend.
            Engine::new(EngineOptions { threads: 0, onnx_runtime })?;
            r2d2_imaging::DrivenSeries::start(config, dirty, psf)
        })?;
        Ok(DrivenSeries { warnings: inner.warnings().to_vec(), networks: inner.networks(), name: inner.series_name().to_string(), trained_size: inner.trained_size(), inner: Arc::new(Mutex::new(inner)) })
    }

    /// What the domain check found, one sentence each.
    #[getter]
    fn warnings(&self) -> Vec<String> {
        self.warnings.clone()
    }

    #[getter]
    fn networks(&self) -> usize {
        self.networks
    }

    #[getter]
    fn series(&self) -> String {
        self.name.clone()
    }

    /// The series' trained image size nearest the image's (None where it names none).
    #[getter]
    fn trained_size(&self) -> Option<usize> {
        self.trained_size
    }

    /// The next model and whether it is the result: `(model, None)` asks for its residual at
    /// the next call; `(model, outcome)` ends imaging (`outcome`: what ran and why it stopped).
    /// `residual` is that of the model last given (none at the first call).
    #[pyo3(signature = (residual=None))]
    fn next<'py>(&self, py: Python<'py>, residual: Option<PyReadonlyArray1<'py, f64>>) -> PyResult<(Bound<'py, PyArray1<f64>>, Option<Bound<'py, PyDict>>)> {
        let residual = residual.map(|r| r.as_slice().map(<[f64]>::to_vec)).transpose()?;
        let inner = self.inner.clone();
        let cycle = run_released(py, move |_| inner.lock().unwrap_or_else(|e| e.into_inner()).next(residual))?;
        match cycle {
            Cycle::Evaluate(model) => Ok((PyArray1::from_vec(py, model), None)),
            Cycle::Done(outcome) => {
                let d = outcome_dict(py, &outcome)?;
                Ok((PyArray1::from_vec(py, outcome.model), Some(d)))
            }
        }
    }
}

/// What a series' domain check needs of an observation (an MS, a Parquet or Arrow table), read
/// once: `{"telescope", "max_uv" (wavelengths), "track_hours", "integration_s"}`, the last
/// three None where the data do not tell.
#[pyfunction]
pub fn observation_domain(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, PyDict>> {
    let (telescope, summary) = run_released(py, move |_| {
        let (meta, source) = r2d2_imaging::parts::open_source(&path, &r2d2_imaging::vis::OpenOptions::default())?;
        Ok((meta.telescope.clone(), source.summary()))
    })?;
    let d = PyDict::new(py);
    d.set_item("telescope", (!telescope.trim().is_empty()).then_some(telescope))?;
    d.set_item("max_uv", (summary.max_uv > 0.0).then_some(summary.max_uv))?;
    d.set_item("track_hours", summary.times.track_hours())?;
    d.set_item("integration_s", summary.times.integration_s())?;
    Ok(d)
}
