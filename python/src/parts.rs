//! One observation in parts gridded where they live (`r2d2_imaging.dask.image_parts`): the
//! part's side (`part_summary`, `part_density`, `part_images`, `part_apply_normal`, run by a
//! worker on a part it can read) and the job's side ([`Parts`], handed to `image` in place of
//! an observation: its passes are made by a Python object, which sends them to the workers
//! and sums what they give).

use crate::run_released;
use numpy::{PyArray1, PyReadonlyArray1};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use r2d2_imaging::parts::{self, open_pass, open_source, PartCheck, PartImages, PartPass, PartPasses, PartedObservation, VisSummary};
use r2d2_imaging::vis::{ObservationMeta, OpenOptions};
use r2d2_imaging::parts::{WToeplitzBuilder, WToeplitzPlan};
use r2d2_imaging::parts::{DensityGrid, WeightRule};
use r2d2_imaging::{Error, Result};
use std::path::PathBuf;
use std::sync::Mutex;

fn summary_dict<'py>(py: Python<'py>, s: &VisSummary) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("samples", s.samples)?;
    d.set_item("max_uv", s.max_uv)?;
    d.set_item("max_abs_w", s.max_abs_w)?;
    d.set_item("lowest_hz", s.lowest_hz)?;
    d.set_item("highest_hz", s.highest_hz)?;
    d.set_item("imaging_weights", s.imaging_weights)?;
    Ok(d)
}

fn summary_of(d: &Bound<'_, PyDict>) -> PyResult<VisSummary> {
    let get = |key: &str| -> PyResult<Bound<'_, PyAny>> {
        d.get_item(key)?.ok_or_else(|| {
            pyo3::exceptions::PyKeyError::new_err(format!("a part's summary without '{key}'"))
        })
    };
    Ok(VisSummary {
        samples: get("samples")?.extract()?,
        max_uv: get("max_uv")?.extract()?,
        max_abs_w: get("max_abs_w")?.extract()?,
        lowest_hz: get("lowest_hz")?.extract()?,
        highest_hz: get("highest_hz")?.extract()?,
        imaging_weights: get("imaging_weights")?.extract()?,
        // Not sent by the workers: a job in parts is not checked against a series' tracks.
        times: Default::default(),
    })
}

/// What imaging must know of a part before the first pass: `(metadata pairs, summary dict)`.
/// Reads the part once (on the worker that holds it). The summary's `check` (what this
/// reading found) goes with every later pass over the part, which fails where it finds other
/// samples.
#[pyfunction]
pub fn part_summary(
    py: Python<'_>,
    path: PathBuf,
) -> PyResult<(Vec<(String, String)>, Bound<'_, PyDict>)> {
    let (meta, summary, check) = run_released(py, move |_| {
        let (meta, source) = open_source(&path, &OpenOptions::default())?;
        Ok((meta.to_pairs()?, source.summary(), source.part_check().map(|c| c.to_text())))
    })?;
    let summary = summary_dict(py, &summary)?;
    summary.set_item("check", check)?;
    Ok((meta, summary))
}

/// A part opened for one pass, checked against its first reading's `check` (from its summary).
fn open_checked(path: &std::path::Path, check: Option<&str>) -> Result<parts::VisSource> {
    let check = check.map(PartCheck::from_text).transpose()?;
    open_pass(path, &OpenOptions::default(), check.as_ref())
}

/// The uv density of a part on the weighting grid: `(density, sum of natural weights)`.
#[pyfunction]
pub fn part_density(
    py: Python<'_>,
    path: PathBuf,
    check: Option<String>,
    pass: String,
) -> PyResult<(Bound<'_, PyArray1<f64>>, f64)> {
    let (density, sum_w) = run_released(py, move |_| {
        let pass = PartPass::from_json(&pass)?;
        let source = open_checked(&path, check.as_deref())?;
        let grid = parts::part_density(&source, &pass)?;
        let (density, sum_w) = grid.raw();
        Ok((density.to_vec(), sum_w))
    })?;
    Ok((PyArray1::from_vec(py, density), sum_w))
}

/// What a worker's pass over a part needs: the pass, the job's weighting rule and the part.
fn part_inputs(path: &std::path::Path, check: Option<&str>, pass: &str, density: Vec<f64>, f2: f64) -> Result<(PartPass, WeightRule, parts::VisSource)> {
    let pass = PartPass::from_json(pass)?;
    let rule = pass.rule(density, f2)?;
    Ok((pass, rule, open_checked(path, check)?))
}

/// A part's images, not normalised: `(dirty, psf, psf_2n, samples, planes)`, the images
/// flattened row-major.
#[pyfunction]
#[allow(clippy::type_complexity)]
pub fn part_images<'py>(
    py: Python<'py>,
    path: PathBuf,
    check: Option<String>,
    pass: String,
    density: PyReadonlyArray1<'py, f64>,
    f2: f64,
) -> PyResult<(
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f64>>,
    u64,
    Option<usize>,
)> {
    let density = density.as_slice()?.to_vec();
    let images = run_released(py, move |_| {
        let (pass, rule, source) = part_inputs(&path, check.as_deref(), &pass, density, f2)?;
        parts::part_images(&source, &pass, &rule)
    })?;
    Ok((
        PyArray1::from_vec(py, images.dirty),
        PyArray1::from_vec(py, images.psf),
        PyArray1::from_vec(py, images.psf_2n),
        images.samples,
        images.planes,
    ))
}

/// A part's dirty image with the kernels of its w-aware Toeplitz form, for the job's bounds
/// `max_abs_w` and `max_uv`, not normalised: `(dirty, samples, planes, kernels, psf_2n,
/// plan_key)`, flattened row-major (the kernels plane after plane); `None` where no such form
/// can be built here (no fit reaches the accuracy, or it would not fit in this worker's memory).
#[pyfunction]
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
pub fn part_w_toeplitz<'py>(
    py: Python<'py>,
    path: PathBuf,
    check: Option<String>,
    pass: String,
    density: PyReadonlyArray1<'py, f64>,
    f2: f64,
    max_abs_w: f64,
    max_uv: f64,
) -> PyResult<Option<(Bound<'py, PyArray1<f64>>, u64, Option<usize>, Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>, String)>> {
    let density = density.as_slice()?.to_vec();
    let built = run_released(py, move |_| {
        let (pass, rule, source) = part_inputs(&path, check.as_deref(), &pass, density, f2)?;
        let geometry = pass.geometry()?;
        let Some(plan) = WToeplitzPlan::new(geometry, max_abs_w, pass.epsilon) else {
            return Ok(None);
        };
        let Ok(mut builder) = WToeplitzBuilder::new(geometry, plan, max_uv, pass.nufft(), pass.threads) else {
            return Ok(None);
        };
        let key = builder.plan_key();
        let images = parts::w_toeplitz_images(&source, &pass, &rule, &mut builder)?;
        let (op, psf_2n) = builder.finish()?;
        Ok(Some((images, op.kernels(), psf_2n, key)))
    })?;
    Ok(built.map(|(images, kernels, psf_2n, key)| {
        (PyArray1::from_vec(py, images.dirty), images.samples, images.planes, PyArray1::from_vec(py, kernels), PyArray1::from_vec(py, psf_2n), key)
    }))
}

/// `Re{Phi^H Phi x}` over a part's samples (`x` flattened row-major), not scaled.
#[pyfunction]
pub fn part_apply_normal<'py>(
    py: Python<'py>,
    path: PathBuf,
    check: Option<String>,
    pass: String,
    density: PyReadonlyArray1<'py, f64>,
    f2: f64,
    x: PyReadonlyArray1<'py, f64>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let density = density.as_slice()?.to_vec();
    let x = x.as_slice()?.to_vec();
    let out = run_released(py, move |_| {
        let (pass, rule, source) = part_inputs(&path, check.as_deref(), &pass, density, f2)?;
        parts::part_apply_normal(&source, &pass, &rule, &x)
    })?;
    Ok(PyArray1::from_vec(py, out))
}

/// Passes made by a Python object (`describe()`, `density(pass)`, `images(pass, density, f2)`,
/// `apply_normal(pass, density, f2, x)`, each summing over the parts), called from the engine's
/// thread with the GIL taken for the call.
struct PythonPasses {
    passes: Py<PyAny>,
    description: String,
}

/// A Python exception raised by the passes object, as an engine error.
fn python_error(py: Python<'_>, what: &str, e: PyErr) -> Error {
    let text = e.value(py).to_string();
    let kind = e
        .get_type(py)
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "exception".into());
    Error::parameter("parts", format!("{what} failed: {kind}: {text}"))
}

impl PartPasses for PythonPasses {
    fn describe(&self) -> String {
        self.description.clone()
    }

    fn density(&self, pass: &PartPass) -> Result<DensityGrid> {
        let (density, sum_w) = Python::with_gil(|py| -> PyResult<(Vec<f64>, f64)> {
            let (density, sum_w): (PyReadonlyArray1<f64>, f64) = self
                .passes
                .call_method1(py, "density", (pass.to_json(),))?
                .extract(py)?;
            Ok((density.as_slice()?.to_vec(), sum_w))
        })
        .map_err(|e| Python::with_gil(|py| python_error(py, "the parts' density pass", e)))?;
        DensityGrid::from_raw(
            pass.weighting()?,
            pass.size,
            pass.grid_factor,
            density,
            sum_w,
        )
    }

    fn images(&self, pass: &PartPass, rule: &WeightRule) -> Result<PartImages> {
        let (density, f2) = rule.raw();
        Python::with_gil(|py| -> PyResult<PartImages> {
            let density = PyArray1::from_slice(py, density);
            let out = self
                .passes
                .call_method1(py, "images", (pass.to_json(), density, f2))?;
            let (dirty, psf, psf_2n, samples, planes): (
                PyReadonlyArray1<f64>,
                PyReadonlyArray1<f64>,
                PyReadonlyArray1<f64>,
                u64,
                Option<usize>,
            ) = out.extract(py)?;
            Ok(PartImages {
                dirty: dirty.as_slice()?.to_vec(),
                psf: psf.as_slice()?.to_vec(),
                psf_2n: psf_2n.as_slice()?.to_vec(),
                samples,
                planes,
            })
        })
        .map_err(|e| Python::with_gil(|py| python_error(py, "the parts' gridding pass", e)))
        .and_then(|images| check_sizes(pass, images))
    }

    fn w_toeplitz_images(&self, pass: &PartPass, rule: &WeightRule, builder: &mut WToeplitzBuilder) -> Result<Option<PartImages>> {
        let (density, f2) = rule.raw();
        let (max_abs_w, max_uv) = builder.bounds();
        type Built = (PartImages, Vec<f64>, Vec<f64>, String);
        let built = Python::with_gil(|py| -> PyResult<Option<Built>> {
            let density = PyArray1::from_slice(py, density);
            let out = self.passes.call_method1(py, "w_toeplitz_images", (pass.to_json(), density, f2, max_abs_w, max_uv))?;
            let out: Option<(PyReadonlyArray1<f64>, u64, Option<usize>, PyReadonlyArray1<f64>, PyReadonlyArray1<f64>, String)> = out.extract(py)?;
            let Some((dirty, samples, planes, kernels, psf_2n, key)) = out else {
                return Ok(None);
            };
            let images = PartImages { dirty: dirty.as_slice()?.to_vec(), psf: Vec::new(), psf_2n: Vec::new(), samples, planes };
            Ok(Some((images, kernels.as_slice()?.to_vec(), psf_2n.as_slice()?.to_vec(), key)))
        })
        .map_err(|e| Python::with_gil(|py| python_error(py, "the parts' gridding pass", e)))?;
        let Some((images, kernels, psf_2n, key)) = built else {
            return Ok(None);
        };
        if images.dirty.len() != pass.size * pass.size {
            return Err(Error::parameter("parts", format!("the parts' gridding pass gave a dirty image of {} pixels where {} were expected", images.dirty.len(), pass.size * pass.size)));
        }
        if key != builder.plan_key() {
            return Err(Error::parameter("parts", format!("the parts built their w-Toeplitz kernels on {key}, this process on {}: another version of the engine on the workers?", builder.plan_key())));
        }
        builder.add_finished(kernels, psf_2n)?;
        Ok(Some(images))
    }

    fn apply_normal(&self, pass: &PartPass, rule: &WeightRule, x: &[f64]) -> Result<Vec<f64>> {
        let (density, f2) = rule.raw();
        let out = Python::with_gil(|py| -> PyResult<Vec<f64>> {
            let (density, x) = (
                PyArray1::from_slice(py, density),
                PyArray1::from_slice(py, x),
            );
            let out: PyReadonlyArray1<f64> = self
                .passes
                .call_method1(py, "apply_normal", (pass.to_json(), density, f2, x))?
                .extract(py)?;
            Ok(out.as_slice()?.to_vec())
        })
        .map_err(|e| Python::with_gil(|py| python_error(py, "the parts' operator pass", e)))?;
        if out.len() != x.len() {
            return Err(Error::parameter(
                "parts",
                format!(
                    "the parts' operator pass gave {} pixels where {} were expected",
                    out.len(),
                    x.len()
                ),
            ));
        }
        Ok(out)
    }
}

/// Images of the sizes of `pass`'s grid, or an error (a passes object that summed wrongly).
fn check_sizes(pass: &PartPass, images: PartImages) -> Result<PartImages> {
    let n = pass.size * pass.size;
    if images.dirty.len() != n || images.psf.len() != n || images.psf_2n.len() != 4 * n {
        return Err(Error::parameter(
            "parts",
            format!("the parts' gridding pass gave images of {}, {} and {} pixels where {n}, {n} and {} were expected", images.dirty.len(), images.psf.len(), images.psf_2n.len(), 4 * n),
        ));
    }
    Ok(images)
}

/// One observation in parts, for `image` in place of an observation: made of each part's
/// name, metadata pairs and summary (from `part_summary`) and the object that makes the passes.
/// Imaged once: the engine takes it.
#[pyclass(module = "r2d2_imaging._native")]
pub struct Parts {
    pub(crate) observation: Mutex<Option<PartedObservation>>,
}

#[pymethods]
impl Parts {
    #[new]
    #[pyo3(signature = (id, parts, passes, description))]
    fn new(
        id: String,
        parts: Vec<(String, Vec<(String, String)>, Bound<'_, PyDict>)>,
        passes: Py<PyAny>,
        description: String,
    ) -> PyResult<Parts> {
        let mut described = Vec::with_capacity(parts.len());
        for (name, pairs, summary) in parts {
            let meta = ObservationMeta::from_pairs(
                pairs.iter().map(|(k, v)| (k.as_str(), Some(v.as_str()))),
                &name,
            )
            .map_err(crate::engine_error)?;
            described.push((name, meta, summary_of(&summary)?));
        }
        let observation = PartedObservation::new(
            id,
            &described,
            Box::new(PythonPasses {
                passes,
                description,
            }),
        )
        .map_err(crate::engine_error)?;
        Ok(Parts {
            observation: Mutex::new(Some(observation)),
        })
    }

    /// The number of unflagged samples with weight over all parts.
    #[getter]
    fn samples(&self) -> u64 {
        self.observation
            .lock()
            .expect("parts")
            .as_ref()
            .map_or(0, |o| o.summary.samples)
    }
}

impl Parts {
    /// The observation, taken (an error the second time).
    pub(crate) fn take(&self) -> PyResult<PartedObservation> {
        self.observation
            .lock()
            .expect("parts")
            .take()
            .ok_or_else(|| {
                crate::R2D2Error::new_err(
                    "these parts were imaged already: make a new Parts for another run",
                )
            })
    }
}
