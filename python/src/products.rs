//! A finished job's products for Python: the images as float32 numpy arrays `(N, N)` in FITS
//! orientation (row 0 at the bottom, as astropy reads the files), whose buffers are the
//! engine's own (moved into numpy, not copied); `metrics`, `header`, and `write(prefix)`
//! writing exactly what `r2d2 image --name PREFIX` writes. Products pickle (Dask sends them
//! from its workers): the arrays as numpy pickles them, the rest field by field.

use crate::run_released;
use numpy::{PyArray1, PyArray2, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use r2d2_imaging::fits::{Beam, ImageWcs};
use r2d2_imaging::IterationMetrics;
use r2d2_imaging::{JobProducts, WriteOptions};
use std::collections::BTreeMap;

/// The image products a job may have, in the order they pickle.
const IMAGES: [&str; 6] = ["dirty", "psf", "model", "residual", "image", "uncertainty"];

#[pyclass(module = "r2d2_imaging", name = "Products", frozen)]
pub struct Products {
    /// Everything but the images (whose vectors are empty here: numpy owns them).
    job: JobProducts,
    /// dirty, psf, model, residual, image, uncertainty.
    images: [Option<Py<PyArray2<f32>>>; 6],
}

/// A vector of `size * size` values as an `(N, N)` numpy array owning the vector's buffer.
fn square<'py>(py: Python<'py>, data: Vec<f32>, size: usize) -> PyResult<Bound<'py, PyArray2<f32>>> {
    PyArray1::from_vec(py, data).reshape([size, size])
}

impl Products {
    pub fn new(py: Python<'_>, mut job: JobProducts) -> PyResult<Products> {
        let size = job.size;
        let take = |v: Option<Vec<f32>>| -> PyResult<Option<Py<PyArray2<f32>>>> {
            v.map(|data| square(py, data, size).map(Bound::unbind)).transpose()
        };
        let images = [
            take(Some(std::mem::take(&mut job.dirty)))?,
            take(Some(std::mem::take(&mut job.psf)))?,
            take(job.model.take())?,
            take(job.residual.take())?,
            take(job.image.take())?,
            take(job.uncertainty.take())?,
        ];
        Ok(Products { job, images })
    }

    /// The complete products, images copied back from the arrays (for writing).
    fn to_job(&self, py: Python<'_>) -> PyResult<JobProducts> {
        let mut job = self.job.clone();
        let copy = |i: usize| -> PyResult<Option<Vec<f32>>> {
            self.images[i].as_ref().map(|a| a.bind(py).to_vec().map_err(|e| PyValueError::new_err(e.to_string()))).transpose()
        };
        job.dirty = copy(0)?.unwrap_or_default();
        job.psf = copy(1)?.unwrap_or_default();
        job.model = copy(2)?;
        job.residual = copy(3)?;
        job.image = copy(4)?;
        job.uncertainty = copy(5)?;
        Ok(job)
    }

    fn array(&self, py: Python<'_>, i: usize) -> Option<Py<PyArray2<f32>>> {
        self.images[i].as_ref().map(|a| a.clone_ref(py))
    }
}

fn metrics_row<'py>(py: Python<'py>, m: &IterationMetrics) -> PyResult<Bound<'py, PyDict>> {
    let row = PyDict::new(py);
    row.set_item("iteration", m.iteration)?;
    row.set_item("residual_ratio", m.residual_ratio)?;
    row.set_item("step_seconds", m.step_seconds)?;
    row.set_item("residual_seconds", m.residual_seconds)?;
    row.set_item("snr", m.snr)?;
    row.set_item("logsnr", m.logsnr)?;
    if let Some(r) = m.realisation {
        row.set_item("realisation", r)?;
    }
    Ok(row)
}

fn metrics_from_row(row: &Bound<'_, PyDict>) -> PyResult<IterationMetrics> {
    let get = |k: &str| -> PyResult<Bound<'_, PyAny>> { row.get_item(k)?.ok_or_else(|| PyValueError::new_err(format!("metrics row without `{k}`"))) };
    Ok(IterationMetrics {
        iteration: get("iteration")?.extract()?,
        residual_ratio: get("residual_ratio")?.extract()?,
        step_seconds: get("step_seconds")?.extract()?,
        residual_seconds: get("residual_seconds")?.extract()?,
        snr: get("snr")?.extract()?,
        logsnr: get("logsnr")?.extract()?,
        realisation: row.get_item("realisation")?.map(|r| r.extract()).transpose()?,
    })
}

/// A FITS header value as Python reads it: an integer, a float, a bool, or text without its
/// quotes.
fn header_value(py: Python<'_>, text: &str) -> PyObject {
    let t = text.trim();
    if let Ok(i) = t.parse::<i64>() {
        return i.into_pyobject(py).expect("ints convert").into_any().unbind();
    }
    if let Ok(f) = t.parse::<f64>() {
        return f.into_pyobject(py).expect("floats convert").into_any().unbind();
    }
    match t {
        "T" => return true.into_pyobject(py).expect("bools convert").to_owned().into_any().unbind(),
        "F" => return false.into_pyobject(py).expect("bools convert").to_owned().into_any().unbind(),
        _ => {}
    }
    let unquoted = t.strip_prefix('\'').and_then(|s| s.strip_suffix('\'')).map_or(t, |s| s.trim_end());
    unquoted.replace("''", "'").into_pyobject(py).expect("strings convert").into_any().unbind()
}

#[pymethods]
impl Products {
    #[getter]
    fn id(&self) -> &str {
        &self.job.id
    }
    #[getter]
    fn size(&self) -> usize {
        self.job.size
    }
    #[getter]
    fn dirty(&self, py: Python<'_>) -> Option<Py<PyArray2<f32>>> {
        self.array(py, 0)
    }
    #[getter]
    fn psf(&self, py: Python<'_>) -> Option<Py<PyArray2<f32>>> {
        self.array(py, 1)
    }
    /// The estimate (Jy/pixel); None when no step ran.
    #[getter]
    fn model(&self, py: Python<'_>) -> Option<Py<PyArray2<f32>>> {
        self.array(py, 2)
    }
    #[getter]
    fn residual(&self, py: Python<'_>) -> Option<Py<PyArray2<f32>>> {
        self.array(py, 3)
    }
    /// The restored image (the model convolved with the fitted beam plus the residual,
    /// Jy/beam); None where no step ran (a dirty image) or no beam could be fitted.
    #[getter]
    fn image(&self, py: Python<'_>) -> Option<Py<PyArray2<f32>>> {
        self.array(py, 4)
    }
    /// For a series of several realisations: the pixel-wise standard deviation over their
    /// mean (the model), as `-uncertainty.fits`; None otherwise.
    #[getter]
    fn uncertainty(&self, py: Python<'_>) -> Option<Py<PyArray2<f32>>> {
        self.array(py, 5)
    }
    /// The FITS keywords every product carries (WCS, frequency, beam, telescope ...), with
    /// values as astropy reads them.
    #[getter]
    fn header<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let header = PyDict::new(py);
        for (key, value) in &self.job.header {
            header.set_item(key, header_value(py, value))?;
        }
        Ok(header)
    }
    /// As `<prefix>-metrics.json`: `job`, `image_size`, `pixel_arcsec`, `iterations` (one
    /// dict per iteration: residual ratio, SNR, logSNR, seconds), `stage_seconds`, `settings`
    /// (weighting, step and series, data column), `warnings`, `stop`, `telescope`, `object`,
    /// `date_obs` and `residual_noise_jy_per_beam` where known.
    #[getter]
    fn metrics<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let mut metrics = self.job.metrics_json();
        // Every row has `snr` and `logsnr` here (None without a truth); the file leaves them out.
        if let Some(rows) = metrics.get_mut("iterations").and_then(|r| r.as_array_mut()) {
            for row in rows.iter_mut().filter_map(|r| r.as_object_mut()) {
                for key in ["snr", "logsnr"] {
                    row.entry(key).or_insert(serde_json::Value::Null);
                }
            }
        }
        py.import("json")?.call_method1("loads", (metrics.to_string(),))
    }

    /// Writes the products as `r2d2 image --name PREFIX` does (FITS, PNG previews unless
    /// `previews=False`, metrics JSON and Parquet), all or nothing.
    #[pyo3(signature = (prefix, previews=true))]
    fn write(&self, py: Python<'_>, prefix: std::path::PathBuf, previews: bool) -> PyResult<()> {
        let job = self.to_job(py)?;
        let options = WriteOptions { previews, ..WriteOptions::default() };
        run_released(py, move |_| job.write_with(&prefix, &options))
    }

    fn __repr__(&self) -> String {
        let made: Vec<&str> = IMAGES.iter().zip(&self.images).filter(|(_, a)| a.is_some()).map(|(n, _)| *n).collect();
        format!("<r2d2_imaging.Products job '{}', {} x {}, {} iteration(s): {}>", self.job.id, self.job.size, self.job.size, self.job.metrics.len(), made.join(", "))
    }

    /// Pickling (Dask moves products between processes): a state tuple for `_products`.
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<(PyObject, Bound<'py, PyTuple>)> {
        let j = &self.job;
        let metrics = PyList::empty(py);
        for m in &j.metrics {
            metrics.append(metrics_row(py, m)?)?;
        }
        let images = PyTuple::new(py, self.images.iter().map(|a| a.as_ref().map(|a| a.clone_ref(py))))?;
        let wcs = (j.wcs.ra_deg, j.wcs.dec_deg, j.wcs.pixel_deg, j.wcs.freq_hz, j.wcs.bandwidth_hz);
        let beam = j.beam.as_ref().map(|b| (b.major_deg, b.minor_deg, b.pa_deg));
        let state = (
            (j.id.clone(), j.size, images, j.header.clone(), metrics, j.stage_seconds.clone()),
            (j.iterations, j.pixel_arcsec, wcs, beam, j.telescope.clone(), j.dynamic_range, j.realisations.as_ref().map(|v| v.to_string())),
            serde_json::json!({"warnings": j.warnings, "stop": j.stop, "settings": j.settings, "object": j.object, "date_obs": j.date_obs, "residual_noise": j.residual_noise}).to_string(),
        );
        let restore = py.import("r2d2_imaging._native")?.getattr("_products")?.unbind();
        Ok((restore, PyTuple::new(py, [state.into_pyobject(py)?.into_any()])?))
    }
}

type Wcs = (f64, f64, f64, Option<f64>, Option<f64>);
type State<'py> = (
    (String, usize, Vec<Option<Bound<'py, PyArray2<f32>>>>, Vec<(String, String)>, Vec<Bound<'py, PyDict>>, BTreeMap<String, f64>),
    (usize, f64, Wcs, Option<(f64, f64, f64)>, String, Option<f64>, Option<String>),
    String,
);

/// The job's notes in the pickled state (a JSON object: warnings, stop, settings, object,
/// date, residual noise).
#[derive(serde::Deserialize)]
struct Notes {
    warnings: Vec<String>,
    stop: Option<r2d2_imaging::LoopStop>,
    settings: BTreeMap<String, serde_json::Value>,
    #[serde(default)]
    object: Option<String>,
    #[serde(default)]
    date_obs: Option<String>,
    #[serde(default)]
    residual_noise: Option<f64>,
}

/// Products from their pickled state.
#[pyfunction]
pub fn _products(state: State<'_>) -> PyResult<Products> {
    let ((id, size, images, header, metrics, stage_seconds), (iterations, pixel_arcsec, wcs, beam, telescope, dynamic_range, realisations), notes) = state;
    let notes: Notes = serde_json::from_str(&notes).map_err(|e| PyValueError::new_err(format!("products state: notes: {e}")))?;
    if images.len() != IMAGES.len() {
        return Err(PyValueError::new_err("products state with the wrong number of images"));
    }
    let mut slots: [Option<Py<PyArray2<f32>>>; 6] = Default::default();
    for (slot, image) in slots.iter_mut().zip(images) {
        if let Some(a) = &image {
            if a.shape() != [size, size] {
                return Err(PyValueError::new_err(format!("products state: an image of shape {:?}, expected ({size}, {size})", a.shape())));
            }
        }
        *slot = image.map(Bound::unbind);
    }
    let job = JobProducts {
        id,
        size,
        dirty: Vec::new(),
        psf: Vec::new(),
        model: None,
        residual: None,
        image: None,
        uncertainty: None,
        realisations: realisations.map(|text| serde_json::from_str(&text)).transpose().map_err(|e| PyValueError::new_err(format!("products state: realisations: {e}")))?,
        header,
        metrics: metrics.iter().map(metrics_from_row).collect::<PyResult<_>>()?,
        stage_seconds,
        iterations,
        pixel_arcsec,
        wcs: ImageWcs { ra_deg: wcs.0, dec_deg: wcs.1, pixel_deg: wcs.2, freq_hz: wcs.3, bandwidth_hz: wcs.4 },
        beam: beam.map(|(major_deg, minor_deg, pa_deg)| Beam { major_deg, minor_deg, pa_deg }),
        telescope,
        object: notes.object,
        date_obs: notes.date_obs,
        residual_noise: notes.residual_noise,
        dynamic_range,
        warnings: notes.warnings,
        stop: notes.stop,
        settings: notes.settings,
        inputs: Vec::new(),
    };
    Ok(Products { job, images: slots })
}
