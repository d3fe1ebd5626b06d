//! A finished job's products as arrays ([`JobProducts`]): what the product sink hands an
//! embedding program, and what the writer stage writes (FITS named like WSClean's, a PNG
//! preview beside each, the per-iteration metrics as JSON and Parquet; or only the dirty
//! image and the PSF, [`ProductSet`]), all or nothing.

use crate::fits::{write_image, Beam, BrightnessUnit, ImageWcs, Pixels};
use crate::primary_beam::{BeamTelescope, PrimaryBeam};
use super::state::{IterationMetrics, Job, LoopStop};
use crate::preview::{write_png_on_sky, PreviewScale, SkyFrame};
use crate::staging::Staging;
use crate::{Error, Result};
use arrow::array::{ArrayRef, Float64Array, RecordBatch, UInt32Array};
use arrow::datatypes::{DataType, Field, Schema};
use parquet::arrow::ArrowWriter;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// One finished job's images and figures. Images are `size x size` float32, row-major in FITS
/// storage order (`data[y * size + x]`, row 0 at the bottom: as astropy reads the FITS files).
#[derive(Clone, Debug)]
pub struct JobProducts {
    pub id: String,
    pub size: usize,
    /// Dirty image (Jy/beam) and PSF (peak 1).
    pub dirty: Vec<f32>,
    pub psf: Vec<f32>,
    /// Final estimate (Jy/pixel) and its residual dirty image (Jy/beam); `None` when no
    /// network step ran.
    pub model: Option<Vec<f32>>,
    pub residual: Option<Vec<f32>>,
    /// Restored image (model convolved with the beam, plus residual), for steps that
    /// restore (CLEAN) when a beam could be fitted.
    pub image: Option<Vec<f32>>,
    /// For a series of several realisations (whose mean is the model): the pixel-wise
    /// standard deviation over the mean, 0 below the masking threshold.
    pub uncertainty: Option<Vec<f32>>,
    /// For several realisations: each one's final figures, the mean's, the mean relative
    /// uncertainty and the masking threshold (the metrics file's `realisations`).
    pub realisations: Option<serde_json::Value>,
    /// The FITS header keywords every product shares (celestial WCS, frequency axis, beam,
    /// telescope, iterations), as key/value text; each file adds its BUNIT.
    pub header: Vec<(String, String)>,
    /// Figures per iteration (residual ratio, seconds, SNR/logSNR with a truth).
    pub metrics: Vec<IterationMetrics>,
    /// Seconds spent per stage on this job.
    pub stage_seconds: BTreeMap<String, f64>,
    /// Network steps run.
    pub iterations: usize,
    pub pixel_arcsec: f64,
    pub wcs: ImageWcs,
    pub beam: Option<Beam>,
    pub telescope: String,
    /// What was observed and when it began (FITS `OBJECT`, `DATE-OBS`), where the data say.
    pub object: Option<String>,
    pub date_obs: Option<String>,
    /// The final residual's noise, Jy/beam ([`crate::metrics::robust_sigma`]).
    pub residual_noise: Option<f64>,
    /// Dynamic range of the truth or of the simulated sky, when known (previews' scale).
    pub dynamic_range: Option<f64>,
    /// Warnings raised about the job (outside a series' domain, a diverging series).
    pub warnings: Vec<String>,
    /// Where the imaging loop stopped before the end of its series, and what it kept.
    pub stop: Option<LoopStop>,
    /// The settings the job was imaged with (weighting, pixel, series) and their origin.
    pub settings: BTreeMap<String, serde_json::Value>,
    /// The files the job was read from: writing refuses a prefix whose products would replace
    /// (or retire) one of them.
    pub inputs: Vec<PathBuf>,
}

/// How [`JobProducts::write_with`] writes.
#[derive(Clone, Debug)]
pub struct WriteOptions {
    /// A PNG preview (log scale, colour bar) beside each FITS product.
    pub previews: bool,
    /// Decades the previews show; default: the job's known dynamic range, else 1e3.
    pub preview_dynamic_range: Option<f64>,
    /// With `Some(limit)`: also the primary beam (`<prefix>-pb.fits`) and the restored image
    /// and the model divided by it (`-image-pb.fits`, `-model-pb.fits`), blank (NaN) where the
    /// beam is below `limit`, as WSClean's `-apply-primary-beam`; no previews of these.
    pub primary_beam: Option<f64>,
}

impl Default for WriteOptions {
    fn default() -> Self {
        WriteOptions { previews: true, preview_dynamic_range: None, primary_beam: None }
    }
}

/// Which of a job's products a writer writes at its prefix.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ProductSet {
    /// Every product the job has (`r2d2 image`'s): its images, a preview beside each, the
    /// metrics; products of an earlier run at the prefix that this one does not make are
    /// removed.
    #[default]
    All,
    /// The dirty image and the PSF (`r2d2 dirty`'s, as WSClean's `-niter 0`), with a preview
    /// beside each where previews are asked for; every other file at the prefix is left as it is.
    Dirty,
}

impl ProductSet {
    /// The names (`<prefix>-<suffix>`) the set may write, or retire.
    fn suffixes(self) -> Vec<String> {
        match self {
            ProductSet::All => product_suffixes(),
            ProductSet::Dirty => ["dirty.fits", "dirty.png", "psf.fits", "psf.png"].map(str::to_string).to_vec(),
        }
    }
}

/// Previews' dynamic range when neither the options nor the data give one: deep enough to
/// show the PSF's first sidelobes and the brighter emission of typical images.
const DEFAULT_PREVIEW_DYNAMIC_RANGE: f64 = 1e3;

/// Products staged for a prefix, not yet in place.
pub(crate) struct Staged {
    staging: Staging,
    pub count: usize,
    /// The prefix's directory and file-name part.
    pub dir: PathBuf,
    pub stem: String,
}

impl Staged {
    /// Moves every product into place (returns their paths); earlier products this run does
    /// not make are removed.
    pub fn commit(self, id: &str) -> Result<Vec<PathBuf>> {
        let written: Vec<PathBuf> = self.staging.targets().map(|p| p.to_path_buf()).collect();
        for removed in self.staging.commit()? {
            log::info!("job {id}: removed {}, which an earlier run made and this one does not", removed.display());
        }
        log::info!("job {id}: wrote {} files to {}-*", self.count, self.dir.join(&self.stem).display());
        Ok(written)
    }
}

/// The command line of this process, recorded in the products' HISTORY ([`record_command_line`]).
static COMMAND_LINE: std::sync::OnceLock<String> = std::sync::OnceLock::new();

/// Record the command that runs this process (the CLI's `r2d2 image ...`), for the HISTORY of
/// the products it writes; the first call counts.
pub fn record_command_line(command: String) {
    let _ = COMMAND_LINE.set(command);
}

fn command_line() -> Option<String> {
    COMMAND_LINE.get().cloned()
}

/// Printable ASCII only (HISTORY text), at most the HISTORY limit of the FITS writer.
fn fits_safe(text: &str) -> String {
    text.chars().map(|c| if (' '..='~').contains(&c) { c } else { '?' }).take(2000).collect()
}

impl JobProducts {
    /// The products of a gridded job; `dynamic_range` (else the job's known one, else the
    /// previews' default) sets where the uncertainty map is masked. A header text FITS cannot
    /// hold as it is (a telescope name in other than ASCII) becomes a warning of the job, once
    /// however many stages make its products.
    pub(crate) fn from_job(job: &mut Job, dynamic_range: Option<f64>) -> Result<JobProducts> {
        let im = job.imaging.as_ref().ok_or_else(|| Error::parameter("writer", "the job was never gridded: nothing to write"))?;
        let n = im.geometry.size;
        let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let stepped = job.iteration > 0;
        let image = match (&im.beam, job.restores) {
            (Some(_), true) if job.restored.is_some() => job.restored.clone(),
            (Some(beam), true) => {
                let smooth = crate::deconv::restore(&im.model, n, beam, im.geometry.pixel_rad);
                Some(smooth.iter().zip(&im.residual).map(|(m, r)| (m + r) as f32).collect())
            }
            _ => None,
        };
        let wcs = ImageWcs {
            ra_deg: job.meta.phase_centre_ra_deg,
            dec_deg: job.meta.phase_centre_dec_deg,
            pixel_deg: im.geometry.pixel_rad.to_degrees(),
            freq_hz: im.frequency_hz,
            bandwidth_hz: im.bandwidth_hz,
        };
        let dynamic_range_known = job.truth_dynamic_range.or(job.meta.dynamic_range);
        let (uncertainty, realisations) = match job.realisation_models.is_empty() {
            true => (None, None),
            false => {
                let (map, summary) = realisation_summary(job, preview_dynamic_range(dynamic_range.or(dynamic_range_known)));
                (Some(f32s(&map)), Some(summary))
            }
        };
        let mut products = JobProducts {
            id: job.id.clone(),
            size: n,
            dirty: f32s(&im.dirty),
            psf: f32s(&im.psf),
            model: stepped.then(|| f32s(&im.model)),
            residual: stepped.then(|| f32s(&im.residual)),
            image,
            uncertainty,
            realisations,
            header: Vec::new(),
            metrics: job.metrics.clone(),
            stage_seconds: job.stage_seconds.clone(),
            iterations: job.iteration,
            pixel_arcsec: im.geometry.pixel_arcsec(),
            wcs,
            beam: im.beam,
            telescope: job.meta.telescope.clone(),
            object: job.meta.extra.get(crate::vis::OBJECT_KEY).cloned(),
            date_obs: job.meta.extra.get(crate::vis::DATE_OBS_KEY).cloned(),
            residual_noise: stepped.then(|| crate::metrics::robust_sigma(&im.residual)),
            dynamic_range: dynamic_range_known,
            warnings: job.warnings.clone(),
            stop: job.stop.clone(),
            settings: {
                let mut settings = job.settings.clone();
                if let Some(column) = job.meta.extra.get("ms_data_column") {
                    settings.insert("data_column".into(), serde_json::json!(column));
                }
                settings
            },
            inputs: job.inputs.clone(),
        };
        for (keyword, value) in products.text_keywords() {
            let Some(note) = crate::fits::header_text(&value).1 else { continue };
            let warning = format!("{keyword}: {note}");
            if !products.warnings.contains(&warning) {
                job.warn(warning.clone());
                products.warnings.push(warning);
            }
        }
        products.header = products.header_cards();
        Ok(products)
    }

    /// The keywords written into every product's header, as text.
    fn header_cards(&self) -> Vec<(String, String)> {
        let w = &self.wcs;
        let mut cards: Vec<(&str, String)> = vec![
            ("CTYPE1", "RA---SIN".into()),
            ("CRPIX1", (self.size / 2 + 1).to_string()),
            ("CRVAL1", w.ra_deg.to_string()),
            ("CDELT1", (-w.pixel_deg).to_string()),
            ("CUNIT1", "deg".into()),
            ("CTYPE2", "DEC--SIN".into()),
            ("CRPIX2", (self.size / 2 + 1).to_string()),
            ("CRVAL2", w.dec_deg.to_string()),
            ("CDELT2", w.pixel_deg.to_string()),
            ("CUNIT2", "deg".into()),
            ("EQUINOX", "2000".into()),
            ("RADESYS", "FK5".into()),
        ];
        if let Some(freq) = w.freq_hz {
            cards.extend([("CTYPE3", "FREQ".into()), ("CRPIX3", "1".into()), ("CRVAL3", freq.to_string()), ("CUNIT3", "Hz".into())]);
            if let Some(bandwidth) = w.bandwidth_hz {
                cards.push(("CDELT3", bandwidth.to_string()));
            }
        }
        if let Some(beam) = &self.beam {
            cards.extend([("BMAJ", beam.major_deg.to_string()), ("BMIN", beam.minor_deg.to_string()), ("BPA", beam.pa_deg.to_string())]);
        }
        cards.extend(self.extra_keywords());
        cards.into_iter().map(|(k, v)| (k.to_string(), v)).collect()
    }

    /// The keywords beside the WCS that every product carries, as WSClean records them where
    /// the meaning is shared: telescope, object, date, the MS column imaged, the weighting, and
    /// what made the model (the series and its networks run, or the step).
    pub(crate) fn extra_keywords(&self) -> Vec<(&'static str, String)> {
        let mut cards: Vec<(&'static str, String)> = self.text_keywords().into_iter().map(|(k, v)| (k, crate::fits::header_text(&v).0)).collect();
        cards.push(("R2D2ITER", self.iterations.to_string()));
        cards
    }

    /// The text keywords of [`Self::extra_keywords`] as the job has them, before they are made
    /// what a header card holds (names from the data may be any Unicode, of any length).
    fn text_keywords(&self) -> Vec<(&'static str, String)> {
        let mut cards = vec![("TELESCOP", self.telescope.clone())];
        if let Some(object) = self.object.as_deref().filter(|o| !o.trim().is_empty()) {
            cards.push(("OBJECT", object.to_string()));
        }
        if let Some(date) = &self.date_obs {
            cards.push(("DATE-OBS", date.clone()));
        }
        if let Some(column) = self.settings.get("data_column").and_then(|c| c.as_str()) {
            cards.push(("DATACOL", column.to_string()));
        }
        if let Some(weighting) = self.settings.get("weighting") {
            let scheme = weighting.get("scheme").and_then(|s| s.as_str()).unwrap_or_default();
            let text = match weighting.get("robust").and_then(|r| r.as_f64()) {
                Some(robust) if scheme == "briggs" => format!("briggs {robust}"),
                _ => scheme.to_string(),
            };
            if !text.is_empty() {
                cards.push(("WEIGHT", text));
            }
            // The uv cuts and tapers, by the request's field names (values in wavelengths, the
            // Gaussian's FWHM in arcsec).
            let uv: Vec<String> = ["minuv_l", "maxuv_l", "taper_gaussian", "taper_tukey"]
                .into_iter()
                .filter_map(|name| weighting.get(name).and_then(|v| v.as_f64()).map(|v| format!("{name}={v}")))
                .collect();
            if !uv.is_empty() {
                cards.push(("WEIGHTUV", uv.join(" ")));
            }
        }
        // What made the model: `clean`, `series NAME` or `plugin FILE` (and the series alone,
        // as earlier products carry it).
        if let Some(step) = self.settings.get("step") {
            let text = |key: &str| step.get(key).and_then(|s| s.as_str());
            let what = match text("kind") {
                Some("series") => text("series").map(|name| format!("series {name}")),
                Some("plugin") => Some(format!("plugin {}", text("library").unwrap_or("?"))),
                other => other.map(str::to_string),
            };
            cards.extend(what.map(|w| ("R2D2STEP", w)));
            cards.extend(text("series").map(|series| ("R2D2SER", series.to_string())));
        }
        cards
    }

    /// HISTORY records of the files: what wrote them and, for a command-line run, its command.
    fn history(&self) -> Vec<(&'static str, String)> {
        let mut lines = vec![("HISTORY", format!("r2d2-imaging {} imaged job '{}'", env!("CARGO_PKG_VERSION"), fits_safe(&self.id)))];
        if let Some(command) = command_line() {
            lines.push(("HISTORY", format!("command: {}", fits_safe(&command))));
        }
        // Beams chosen differently differ for the same PSF (fitted ones by several per cent in
        // area between imagers): the header says how this one was.
        if let Some(how) = self.beam.and(self.settings.get("restoring_beam")).and_then(|b| b.get("how")).and_then(|h| h.as_str()) {
            lines.push(("HISTORY", fits_safe(how)));
        }
        // The mask the model was kept to, by the request's field names (any command).
        if let Some(mask) = self.settings.get("mask").and_then(|m| m.as_object()) {
            let said: Vec<String> = mask.iter().map(|(k, v)| format!("{k}={}", v.as_str().map_or_else(|| v.to_string(), str::to_string))).collect();
            lines.push(("HISTORY", format!("mask: {}", fits_safe(&said.join(" ")))));
        }
        lines
    }

    /// The figures of the model written: the last iteration's, or where the divergence guard
    /// stopped the loop, the kept iterate's (the empty model's: ratio 1, SNR and logSNR 0 dB),
    /// which `iterations` (every iteration run) does not end with.
    fn final_figures(&self) -> Option<serde_json::Value> {
        let last = self.metrics.last()?;
        let kept = self.stop.as_ref().map_or(last.iteration, |s| s.kept_iteration);
        if kept == 0 {
            return Some(serde_json::json!({"iteration": 0, "residual_ratio": 1.0, "snr": last.snr.map(|_| 0.0), "logsnr": last.logsnr.map(|_| 0.0)}));
        }
        let m = self.metrics.iter().rev().find(|m| m.iteration == kept && m.realisation.is_none()).unwrap_or(last);
        Some(serde_json::json!({"iteration": m.iteration, "residual_ratio": m.residual_ratio, "snr": m.snr, "logsnr": m.logsnr}))
    }

    /// `<prefix>-metrics.json`: the job, its per-iteration figures, seconds per stage, image
    /// and pixel size, the settings (weighting, step and series, data column), warnings, how
    /// the loop stopped, the figures of the model written (`final`), what was observed and
    /// when, and the residual's noise.
    pub fn metrics_json(&self) -> serde_json::Value {
        let mut metrics = serde_json::json!({
            "job": self.id,
            "iterations": self.metrics,
            "stage_seconds": self.stage_seconds,
            "image_size": self.size,
            "pixel_arcsec": self.pixel_arcsec,
            "settings": self.settings,
            "warnings": self.warnings,
        });
        if let Some(noise) = self.residual_noise {
            metrics["residual_noise_jy_per_beam"] = serde_json::json!(noise);
        }
        for (key, value) in [("telescope", Some(&self.telescope)), ("object", self.object.as_ref()), ("date_obs", self.date_obs.as_ref())] {
            if let Some(value) = value.filter(|v| !v.is_empty()) {
                metrics[key] = serde_json::json!(value);
            }
        }
        if let Some(stop) = &self.stop {
            metrics["stop"] = serde_json::json!(stop);
        }
        if let Some(last) = self.final_figures() {
            metrics["final"] = last;
        }
        if let Some(summary) = &self.realisations {
            metrics["realisations"] = summary.clone();
        }
        metrics
    }

    /// Writes the products as `r2d2 image` does (`<prefix>-dirty.fits`, `-psf`, `-model`,
    /// `-residual`, `-image` and a PNG preview of each, `-metrics.json`, `-metrics.parquet`),
    /// all appearing together or not at all; products of an earlier run at this prefix that
    /// this one does not make are removed. `{job}` in `prefix` is replaced by the job id.
    pub fn write(&self, prefix: impl AsRef<Path>) -> Result<()> {
        self.write_with(prefix, &WriteOptions::default())
    }

    pub fn write_with(&self, prefix: impl AsRef<Path>, options: &WriteOptions) -> Result<()> {
        let prefix = prefix.as_ref().to_string_lossy().into_owned();
        crate::fits::check_output_prefix(&prefix).map_err(|m| Error::parameter("prefix", m))?;
        self.stage(&prefix, options, ProductSet::All)?.commit(&self.id).map(|_| ())
    }

    /// Writes the products of `set` into a staging directory beside the prefix.
    pub(crate) fn stage(&self, prefix: &str, options: &WriteOptions, set: ProductSet) -> Result<Staged> {
        // The prefix was checked with `{job}` in it; a long job id can still make the names too long.
        if prefix.contains("{job}") {
            crate::fits::check_output_prefix(&prefix.replace("{job}", &self.id)).map_err(|m| Error::parameter("prefix", format!("job '{}': {m}", self.id)))?;
        }
        let inputs: Vec<&Path> = self.inputs.iter().map(PathBuf::as_path).collect();
        check_spares_inputs(prefix, &self.id, &inputs, set)?;
        let (dir, stem) = prefix_parts(prefix, &self.id);
        let mut staging = Staging::new(&dir)?;
        self.stage_into(&mut staging, &dir, &stem, options, set)?;
        let count = staging.targets().count();
        Ok(Staged { staging, count, dir, stem })
    }

    /// Writes the products of `set` into `staging`, named `<dir>/<stem>-<product>`.
    pub(crate) fn stage_into(&self, staging: &mut Staging, dir: &Path, stem: &str, options: &WriteOptions, set: ProductSet) -> Result<()> {
        let target = |suffix: &str| dir.join(format!("{stem}-{suffix}"));
        let n = self.size;
        let mut extra = self.extra_keywords();
        extra.extend(self.history());
        let mut images: Vec<(&str, &[f32], BrightnessUnit)> =
            vec![("dirty", &self.dirty, BrightnessUnit::JyPerBeam), ("psf", &self.psf, BrightnessUnit::JyPerBeam)];
        if set == ProductSet::All {
            if let (Some(model), Some(residual)) = (&self.model, &self.residual) {
                images.push(("model", model, BrightnessUnit::JyPerPixel));
                images.push(("residual", residual, BrightnessUnit::JyPerBeam));
            }
            if let Some(image) = &self.image {
                images.push(("image", image, BrightnessUnit::JyPerBeam));
            }
            if let Some(uncertainty) = &self.uncertainty {
                images.push(("uncertainty", uncertainty, BrightnessUnit::Ratio));
            }
        }
        let scale = PreviewScale::Log { dynamic_range: preview_dynamic_range(options.preview_dynamic_range.or(self.dynamic_range)) };
        for (name, pixels, unit) in &images {
            let data: Vec<f64> = pixels.iter().map(|&v| f64::from(v)).collect();
            staging.write(target(&format!("{name}.fits")), |path| write_image(path, &data, n, n, &self.wcs, *unit, self.beam.as_ref(), &extra))?;
            if options.previews {
                // The model is positive (log scale over the dynamic range); the others carry
                // meaningful negative pixels (sidelobes, noise) and get the signed stretch,
                // linear within their noise.
                let (title, scale) = match (unit, *name) {
                    (BrightnessUnit::Ratio, _) => (format!("{} {name} (std / mean)", self.id), PreviewScale::Linear),
                    (_, "model") => (format!("{} {name} ({})", self.id, unit.as_fits()), scale),
                    _ => {
                        let softening = crate::metrics::robust_sigma(pixels);
                        (format!("{} {name} ({}, asinh)", self.id, unit.as_fits()), PreviewScale::Signed { softening })
                    }
                };
                let sky = SkyFrame {
                    pixel_arcsec: self.pixel_arcsec,
                    beam: self.beam.map(|b| (b.major_deg * 3600.0, b.minor_deg * 3600.0, b.pa_deg)),
                };
                staging.write(target(&format!("{name}.png")), |path| write_png_on_sky(path, &data, n, n, scale, &title, Some(&sky)))?;
            }
        }
        if let (ProductSet::All, Some(limit)) = (set, options.primary_beam) {
            let (beam, model) = self.primary_beam()?;
            let description = model.description();
            let mut extra = extra.clone();
            extra.push(("PBMODEL", description.clone()));
            extra.push(("PBLIMIT", limit.to_string()));
            extra.push(("HISTORY", format!("primary beam: {description}, about the phase centre (taken as the pointing centre); blank where below {limit}")));
            staging.write(target("pb.fits"), |path| write_image(path, &beam, n, n, &self.wcs, BrightnessUnit::Ratio, self.beam.as_ref(), &extra))?;
            let corrected = [("image-pb.fits", &self.image, BrightnessUnit::JyPerBeam), ("model-pb.fits", &self.model, BrightnessUnit::JyPerPixel)];
            for (suffix, pixels, unit) in corrected {
                let Some(pixels) = pixels else { continue };
                let data: Vec<f64> = pixels.iter().map(|&v| f64::from(v)).collect();
                let data = crate::primary_beam::correct(&data, &beam, limit);
                staging.write(target(suffix), |path| write_image(path, Pixels::blanked(&data), n, n, &self.wcs, unit, self.beam.as_ref(), &extra))?;
            }
        }
        if set == ProductSet::All {
            let metrics = self.metrics_json();
            let text = serde_json::to_string_pretty(&metrics).expect("metrics serialise");
            staging.write(target("metrics.json"), |path| std::fs::write(path, &text).map_err(|e| Error::io(path, e)))?;
            staging.write(target("metrics.parquet"), |path| self.write_metrics_parquet(path))?;
            for suffix in product_suffixes() {
                let earlier = target(&suffix);
                if !staging.targets().any(|to| to == earlier) {
                    staging.retire(earlier);
                }
            }
        }
        Ok(())
    }

    /// The primary beam on the products' grid: the published model of the job's telescope at
    /// the centre frequency (`CRVAL3`), centred on the phase centre.
    fn primary_beam(&self) -> Result<(Vec<f64>, PrimaryBeam)> {
        let telescope = beam_telescope(&self.telescope)?;
        let frequency = self.wcs.freq_hz.ok_or_else(|| Error::parameter("apply_primary_beam", format!("job '{}': its frequency is unknown, and the beam depends on it", self.id)))?;
        let beam = PrimaryBeam::new(telescope, frequency).map_err(|m| Error::parameter("apply_primary_beam", format!("job '{}': {m}", self.id)))?;
        Ok((beam.image(self.size, self.wcs.pixel_deg.to_radians()), beam))
    }

    /// `<prefix>-metrics.parquet`: one row per iteration (`iteration`, `residual_ratio`,
    /// `step_seconds`, `residual_seconds`, and `snr`, `logsnr`, null without a truth); the job,
    /// image size, pixel size and seconds per stage (a JSON object) as key-value metadata,
    /// since they are one value per job rather than per iteration.
    fn write_metrics_parquet(&self, path: &Path) -> Result<()> {
        let rows = &self.metrics;
        let float = |values: Vec<Option<f64>>| Arc::new(Float64Array::from(values)) as ArrayRef;
        let column = |f: fn(&IterationMetrics) -> Option<f64>| float(rows.iter().map(f).collect());
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
        let stage_seconds = serde_json::to_string(&self.stage_seconds).expect("stage seconds serialise");
        let metadata = [
            ("job", self.id.clone()),
            ("image_size", self.size.to_string()),
            ("pixel_arcsec", self.pixel_arcsec.to_string()),
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
}

/// The telescope `name` (as data name it: `EVLA`, `MeerKAT`, ...) as the primary-beam models
/// know it; an error, naming `apply_primary_beam`, where there is no model for it.
pub(crate) fn beam_telescope(name: &str) -> Result<BeamTelescope> {
    // Found by the registry's names and aliases (CASA writes `EVLA` for the VLA).
    let found = match crate::simulate::telescope::telescope(name).ok().map(|t| t.key.as_str()) {
        Some("vla") => Some(BeamTelescope::Vla),
        Some("meerkat") => Some(BeamTelescope::MeerKat),
        _ => None,
    };
    found.ok_or_else(|| {
        let supported: Vec<&str> = BeamTelescope::ALL.iter().map(|t| t.name()).collect();
        let which = match crate::vis::named_telescope(name) {
            Some(named) => format!("telescope '{named}'"),
            None => "an observation that names no telescope".to_string(),
        };
        Error::parameter("apply_primary_beam", format!("there is no primary-beam model for {which}; the telescopes with one: {}", supported.join(", ")))
    })
}

/// The directory and file-name part of job `id`'s products at `prefix` (`{job}` replaced).
pub(crate) fn prefix_parts(prefix: &str, id: &str) -> (PathBuf, String) {
    let prefix = PathBuf::from(prefix.replace("{job}", id));
    let dir = prefix.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")).to_path_buf();
    let stem = prefix.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| id.to_string());
    (dir, stem)
}

/// Refuses a prefix at which the products of job `id` (any of `set` the writer makes or
/// retires) would replace one of `inputs` (its visibilities, truth, MeasurementSet), or lie
/// inside one (a MeasurementSet's directory).
pub fn check_spares_inputs(prefix: &str, id: &str, inputs: &[&Path], set: ProductSet) -> Result<()> {
    let (dir, stem) = prefix_parts(prefix, id);
    for suffix in set.suffixes() {
        let target = dir.join(format!("{stem}-{suffix}"));
        if let Some(input) = crate::staging::destroys_input(&target, inputs) {
            // Inside: the nearest existing directory above the product is the input or in it.
            let existing = target.ancestors().skip(1).find_map(|a| if a.as_os_str().is_empty() { Path::new(".") } else { a }.canonicalize().ok());
            let inside = existing.zip(input.canonicalize().ok()).is_some_and(|(dir, input)| dir.starts_with(input));
            let what = if inside { "lie inside" } else { "replace" };
            // Named as the prefix names it (`out/x-dirty.fits`, `x-dirty.fits`).
            let product = format!("{}-{suffix}", prefix.replace("{job}", id));
            return Err(Error::parameter(
                "prefix",
                format!("job '{id}': the product {product} would {what} the input {}: choose another output name (the request's `name`, the writer's `prefix`)", input.display()),
            ));
        }
    }
    Ok(())
}

/// Every product a writer makes for a prefix (`<prefix>-<suffix>`), to retire those of an
/// earlier run that this one does not make. The staging journal's recovery acts on these
/// names only, so the list lives there.
fn product_suffixes() -> Vec<String> {
    crate::staging::PRODUCT_SUFFIXES.iter().map(|s| s.to_string()).collect()
}

/// The previews' dynamic range: the one given or known when it means something, else the
/// default.
fn preview_dynamic_range(known: Option<f64>) -> f64 {
    known.filter(|dr| *dr > 1.0 && dr.is_finite()).unwrap_or(DEFAULT_PREVIEW_DYNAMIC_RANGE)
}

/// For a job imaged with several realisations: the uncertainty map (`metrics::std_over_mean`
/// of their final models, masked below the mean image's peak over `dynamic_range`, the one
/// the previews use) and the figures of each realisation's final iteration, of the mean, and
/// the mean relative uncertainty.
fn realisation_summary(job: &Job, dynamic_range: f64) -> (Vec<f64>, serde_json::Value) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_output_name_checks_know_the_longest_product_name() {
        let longest = product_suffixes().into_iter().map(|s| s.len() + 1).max().unwrap();
        assert_eq!(longest, crate::fits::LONGEST_PRODUCT_SUFFIX.len());
    }

    #[test]
    fn metrics_floats_read_back_from_json_to_the_bit() {
        // A residual noise whose shortest decimal serde_json's fast parser read back one ulp
        // off (a pickled Products then differed from its original); and a sweep of others.
        let mut values = vec![0.006_479_778_501_561_288_4_f64];
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        for _ in 0..20_000 {
            state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            let x = f64::from_bits((state >> 2) | 0x3000_0000_0000_0000);
            values.push(if x.is_finite() { x } else { 1.0 });
        }
        for x in values {
            let text = serde_json::json!({ "x": x }).to_string();
            let back: serde_json::Value = serde_json::from_str(&text).unwrap();
            assert_eq!(back["x"].as_f64().unwrap().to_bits(), x.to_bits(), "{text}");
        }
    }
}
