//! `kind: writer`: FITS products named like WSClean's (`<prefix>-dirty.fits`, `-psf.fits`,
//! `-model.fits`, `-residual.fits`, and `-image.fits` for CLEAN) with full WCS and beam, a
//! PNG preview beside each (`<prefix>-dirty.png`, ...; `previews: false` turns them off),
//! and the per-iteration metrics as `<prefix>-metrics.json` and `<prefix>-metrics.parquet`.
//! A job's products appear together or not at all: they are written into a staging
//! directory and moved into place only when all are complete (`crate::staging`).

use crate::fits::{write_image, BrightnessUnit, ImageWcs};
use crate::pipeline::config::{PipelineConfig, StageConfig};
use crate::pipeline::{Emit, Job, Stage};
use crate::preview::{write_png, PreviewScale};
use crate::staging::Staging;
use crate::{Error, Result};
use arrow::array::{ArrayRef, Float64Array, RecordBatch, UInt32Array};
use arrow::datatypes::{DataType, Field, Schema};
use parquet::arrow::ArrowWriter;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WriterConfig {
    /// Output prefix; `{job}` is replaced by the job id.
    #[serde(default = "prefix")]
    prefix: String,
    /// A PNG preview (log scale, colour bar) beside each FITS product.
    #[serde(default = "yes")]
    previews: bool,
    /// Decades shown by the previews' log scale; default: the dynamic range of the truth
    /// or of the simulated sky when known, else 1e3.
    #[serde(default)]
    preview_dynamic_range: Option<f64>,
    /// Predict the final model's visibilities into this column of the input MeasurementSet
    /// (`kind: ms` jobs), e.g. MODEL_DATA; created when missing.
    #[serde(default)]
    model_column: Option<String>,
}

/// What a writer prefix may contain besides text.
const PLACEHOLDERS: &[&str] = &["{job}"];

fn prefix() -> String {
    "{job}".into()
}

fn yes() -> bool {
    true
}

/// Previews' dynamic range when neither the configuration nor the data give one: deep enough
/// to show the PSF's first sidelobes and the brighter emission of typical images.
const DEFAULT_PREVIEW_DYNAMIC_RANGE: f64 = 1e3;

pub struct WriterStage {
    prefix: String,
    previews: bool,
    preview_dynamic_range: Option<f64>,
    model_column: Option<String>,
}

impl WriterStage {
    pub fn new(config: WriterConfig, pipeline: &PipelineConfig, stage: &StageConfig) -> Result<WriterStage> {
        let name = &stage.name;
        let prefix_error = |m: String| pipeline.stage_error(name, Some("prefix"), &format!("stages.{name}.prefix: {m}"));
        // Placeholders first: a typo would otherwise be written literally into file names.
        let mut rest = config.prefix.as_str();
        while let Some(open) = rest.find('{') {
            let placeholder = rest[open..].find('}').map_or(&rest[open..], |close| &rest[open..=open + close]);
            if !PLACEHOLDERS.contains(&placeholder) {
                return Err(prefix_error(format!("unknown placeholder {placeholder} in \"{}\" (known: {})", config.prefix, PLACEHOLDERS.join(", "))));
            }
            rest = &rest[open + placeholder.len()..];
        }
        crate::fits::check_output_prefix(&config.prefix).map_err(prefix_error)?;
        if let Some(dr) = config.preview_dynamic_range {
            if !(dr > 1.0 && dr.is_finite()) {
                return Err(Error::parameter("preview_dynamic_range", format!("expected a finite number above 1, got {dr}")));
            }
        }
        if config.model_column.as_deref().is_some_and(|c| c.trim().is_empty()) {
            return Err(Error::parameter("model_column", "expected a column name such as MODEL_DATA"));
        }
        Ok(WriterStage {
            prefix: config.prefix,
            previews: config.previews,
            preview_dynamic_range: config.preview_dynamic_range,
            model_column: config.model_column,
        })
    }

    fn preview_scale(&self, job: &Job) -> PreviewScale {
        let known = self.preview_dynamic_range.or(job.truth_dynamic_range).or(job.meta.dynamic_range);
        let dynamic_range = known.filter(|dr| *dr > 1.0 && dr.is_finite()).unwrap_or(DEFAULT_PREVIEW_DYNAMIC_RANGE);
        PreviewScale::Log { dynamic_range }
    }
}

/// Every product a writer makes for a prefix (`<prefix>-<suffix>`), to retire those of an
/// earlier run that this one does not make.
fn product_suffixes() -> Vec<String> {
    let images = ["dirty", "psf", "model", "residual", "image", "uncertainty"];
    let mut suffixes: Vec<String> = images.iter().flat_map(|i| [format!("{i}.fits"), format!("{i}.png")]).collect();
    suffixes.extend(["metrics.json".to_string(), "metrics.parquet".to_string()]);
    suffixes
}

impl Stage for WriterStage {
    fn process(&mut self, job: Job, _emit: &mut Emit<'_>) -> Result<()> {
        let im = job.imaging.as_ref().ok_or_else(|| Error::parameter("writer", "the job was never gridded: nothing to write"))?;
        let prefix = PathBuf::from(self.prefix.replace("{job}", &job.id));
        let dir = prefix.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")).to_path_buf();
        let stem = prefix.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| job.id.clone());
        let target = |suffix: &str| dir.join(format!("{stem}-{suffix}"));
        let mut staging = Staging::new(&dir)?;
        let n = im.geometry.size;
        let wcs = ImageWcs {
            ra_deg: job.meta.phase_centre_ra_deg,
            dec_deg: job.meta.phase_centre_dec_deg,
            pixel_deg: im.geometry.pixel_rad.to_degrees(),
            freq_hz: im.frequency_hz,
            bandwidth_hz: None,
        };
        let beam = im.beam.as_ref();
        let extra = [("TELESCOP", job.meta.telescope.clone()), ("R2D2ITER", job.iteration.to_string())];
        let mut products: Vec<(&str, &[f64], BrightnessUnit)> = vec![
            ("dirty", &im.dirty, BrightnessUnit::JyPerBeam),
            ("psf", &im.psf, BrightnessUnit::JyPerBeam),
        ];
        if job.iteration > 0 {
            products.push(("model", &im.model, BrightnessUnit::JyPerPixel));
            products.push(("residual", &im.residual, BrightnessUnit::JyPerBeam));
        }
        let restored;
        if job.step_kind.as_deref().is_some_and(|k| k.ends_with("+restore")) {
            if let Some(beam) = beam {
                let smooth = crate::deconv::restore(&im.model, n, beam, im.geometry.pixel_rad);
                restored = smooth.iter().zip(&im.residual).map(|(m, r)| m + r).collect::<Vec<f64>>();
                products.push(("image", &restored, BrightnessUnit::JyPerBeam));
            }
        }
        let scale = self.preview_scale(&job);
        let uncertainty = (!job.realisation_models.is_empty()).then(|| realisation_summary(&job, scale));
        if let Some((map, _)) = &uncertainty {
            products.push(("uncertainty", map, BrightnessUnit::Ratio));
        }
        for (name, data, unit) in &products {
            staging.write(target(&format!("{name}.fits")), |path| write_image(path, data, n, n, &wcs, *unit, beam, &extra))?;
            if self.previews {
                let (title, scale) = match unit {
                    BrightnessUnit::Ratio => (format!("{} {name} (std / mean)", job.id), PreviewScale::Linear),
                    _ => (format!("{} {name} ({})", job.id, unit.as_fits()), scale),
                };
                staging.write(target(&format!("{name}.png")), |path| write_png(path, data, n, n, scale, &title))?;
            }
        }
        let mut metrics = serde_json::json!({
            "job": job.id,
            "iterations": job.metrics,
            "stage_seconds": job.stage_seconds,
            "image_size": n,
            "pixel_arcsec": im.geometry.pixel_arcsec(),
        });
        if let Some((_, summary)) = uncertainty {
            metrics["realisations"] = summary;
        }
        let text = serde_json::to_string_pretty(&metrics).expect("metrics serialise");
        staging.write(target("metrics.json"), |path| std::fs::write(path, &text).map_err(|e| Error::io(path, e)))?;
        staging.write(target("metrics.parquet"), |path| write_metrics_parquet(path, &job, n, im.geometry.pixel_arcsec()))?;
        for suffix in product_suffixes() {
            let earlier = target(&suffix);
            if !staging.targets().any(|to| to == earlier) {
                staging.retire(earlier);
            }
        }
        let count = staging.targets().count();
        // Before the products move into place: a failed model write leaves neither.
        if let Some(column) = &self.model_column {
            write_model(&job, column)?;
        }
        for removed in staging.commit()? {
            log::info!("job {}: removed {}, which an earlier run made and this one does not", job.id, removed.display());
        }
        log::info!("job {}: wrote {count} files to {}-*", job.id, dir.join(&stem).display());
        Ok(())
    }
}

#[cfg(feature = "ms")]
fn write_model(job: &Job, column: &str) -> Result<()> {
    crate::ms::write_job_model(job, column).map(|_| ())
}

#[cfg(not(feature = "ms"))]
fn write_model(_job: &Job, _column: &str) -> Result<()> {
    Err(Error::parameter("model_column", "this r2d2 was built without the `ms` feature (MeasurementSets)"))
}

/// For a job imaged with several realisations: the uncertainty map (`metrics::std_over_mean`
/// of their final models, masked below the mean image's peak over the dynamic range the
/// previews use) and the figures of each realisation's final iteration, of the mean, and the
/// mean relative uncertainty.
fn realisation_summary(job: &Job, scale: PreviewScale) -> (Vec<f64>, serde_json::Value) {
    let dynamic_range = match scale {
        PreviewScale::Log { dynamic_range } => dynamic_range,
        PreviewScale::Linear => DEFAULT_PREVIEW_DYNAMIC_RANGE,
    };
    let mean = crate::metrics::pixel_mean(&job.realisation_models);
    let threshold = mean.iter().copied().fold(0.0f64, f64::max) / dynamic_range;
    let (map, mru) = crate::metrics::std_over_mean(&job.realisation_models, threshold);
    let last_of = |r: Option<usize>| job.metrics.iter().rev().find(|m| m.realisation == r).map(|m| serde_json::json!(m));
    let each: Vec<serde_json::Value> = (1..=job.realisation_models.len()).map(|r| last_of(Some(r)).unwrap_or_default()).collect();
    let summary = serde_json::json!({
        "count": job.realisation_models.len(),
        "final": each,
        "mean": last_of(None),
        "mean_relative_uncertainty": mru,
        "uncertainty_threshold": threshold,
        "uncertainty_dynamic_range": dynamic_range,
    });
    (map, summary)
}

/// `<prefix>-metrics.parquet`: one row per iteration (`iteration`, `residual_ratio`,
/// `step_seconds`, `residual_seconds`, and `snr`, `logsnr`, null without a truth); the job,
/// image size, pixel size and seconds per stage (a JSON object) as key-value metadata, since
/// they are one value per job rather than per iteration. Written into the staging directory,
/// which is what makes it appear whole or not at all.
fn write_metrics_parquet(path: &Path, job: &Job, size: usize, pixel_arcsec: f64) -> Result<()> {
    let rows = &job.metrics;
    let float = |values: Vec<Option<f64>>| Arc::new(Float64Array::from(values)) as ArrayRef;
    let column = |f: fn(&crate::pipeline::IterationMetrics) -> Option<f64>| float(rows.iter().map(f).collect());
    let iterations = Arc::new(UInt32Array::from(rows.iter().map(|m| m.iteration as u32).collect::<Vec<u32>>())) as ArrayRef;
    let fields = [
        Field::new("iteration", DataType::UInt32, false),
        Field::new("residual_ratio", DataType::Float64, false),
        Field::new("step_seconds", DataType::Float64, false),
        Field::new("residual_seconds", DataType::Float64, false),
        Field::new("snr", DataType::Float64, true),
        Field::new("logsnr", DataType::Float64, true),
    ];
    let columns = vec![
        iterations,
        column(|m| Some(m.residual_ratio)),
        column(|m| Some(m.step_seconds)),
        column(|m| Some(m.residual_seconds)),
        column(|m| m.snr),
        column(|m| m.logsnr),
    ];
    let io_error = |e: &dyn std::fmt::Display| Error::io(path, std::io::Error::other(format!("writing metrics Parquet: {e}")));
    let schema = Arc::new(Schema::new(fields.to_vec()));
    let batch = RecordBatch::try_new(schema.clone(), columns).map_err(|e| io_error(&e))?;
    let stage_seconds = serde_json::to_string(&job.stage_seconds).expect("stage seconds serialise");
    let metadata = [
        ("job", job.id.clone()),
        ("image_size", size.to_string()),
        ("pixel_arcsec", pixel_arcsec.to_string()),
        ("stage_seconds", stage_seconds),
    ];
    let properties = WriterProperties::builder()
        .set_key_value_metadata(Some(metadata.into_iter().map(|(k, v)| KeyValue::new(k.to_string(), v)).collect()))
        .build();
    let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    let mut writer = ArrowWriter::try_new(file, schema, Some(properties)).map_err(|e| io_error(&e))?;
    writer.write(&batch).map_err(|e| io_error(&e))?;
    writer.close().map_err(|e| io_error(&e))?;
    Ok(())
}
