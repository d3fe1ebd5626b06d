//! `kind: weighting`: image geometry (from the pipeline's `image`) and the total weight of
//! every visibility (natural x imaging: natural, uniform or Briggs, with WSClean's uv cuts and
//! tapers).

use crate::vis::weight_rule;
use crate::imaging::ImageConfig;
use crate::job::{Built, Emit, ImageContext, Job, KindFn, Product};
use crate::pipeline::{Port, Role, Stage, StageParams};
use crate::weighting::{UvControls, UvCounts, Weighting, WeightingScheme, DEFAULT_GRID_FACTOR};
use crate::Result;
use serde::{Deserialize, Serialize};

/// `kind: weighting`: how each visibility is weighted. `scheme` has no default in YAML (a
/// pipeline says which it uses); `WeightingParams::default()` is `r2d2 image`'s, Briggs with
/// robust 0.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct WeightingParams {
    /// natural, uniform or briggs.
    pub scheme: WeightingScheme,
    /// Briggs robustness (-2: close to uniform, 2: close to natural); default 0.
    #[serde(default)]
    pub robust: f64,
    /// Uniform and Briggs weights count the visibilities in a uv grid of `grid_factor x size`
    /// cells per axis (the uv cuts and tapers are evaluated on it too, as WSClean does).
    /// Default: 2; where the jobs go on to a network series run off its trained size, its
    /// trained field's grid (`2 x trained size / size`: the uv cell, so the PSF, it was trained
    /// on; WSClean's `-super-weight` does the same).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grid_factor: Option<f64>,
    /// Leave out samples nearer the uv origin than this (wavelengths), as WSClean's minimum uv
    /// distance.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub minuv_l: Option<f64>,
    /// Leave out samples farther from the uv origin than this (wavelengths).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub maxuv_l: Option<f64>,
    /// A Gaussian taper of the imaging weights whose image-plane FWHM is this (arcsec), as
    /// WSClean's Gaussian taper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub taper_gaussian: Option<f64>,
    /// A Tukey transition this wide (wavelengths) inside `maxuv_l`, as WSClean's Tukey taper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub taper_tukey: Option<f64>,
}

impl StageParams for WeightingParams {
    const KIND: &'static str = "weighting";
}

impl Default for WeightingParams {
    fn default() -> Self {
        WeightingParams::new(Weighting::Briggs { robust: 0.0 })
    }
}

impl WeightingParams {
    /// The stage for `weighting`, with the default grid factor (the series' field's off its size).
    pub fn new(weighting: Weighting) -> WeightingParams {
        let (scheme, robust) = match weighting {
            Weighting::Natural => (WeightingScheme::Natural, 0.0),
            Weighting::Uniform => (WeightingScheme::Uniform, 0.0),
            Weighting::Briggs { robust } => (WeightingScheme::Briggs, robust),
            Weighting::Given => (WeightingScheme::Given, 0.0),
        };
        WeightingParams { scheme, robust, grid_factor: None, minuv_l: None, maxuv_l: None, taper_gaussian: None, taper_tukey: None }
    }

    /// The stage with the uv cuts and tapers `uv`.
    pub fn with_uv(self, uv: UvControls) -> WeightingParams {
        WeightingParams { minuv_l: uv.minuv_l, maxuv_l: uv.maxuv_l, taper_gaussian: uv.taper_gaussian, taper_tukey: uv.taper_tukey, ..self }
    }

    /// The uv cuts and tapers asked for.
    pub fn uv(&self) -> UvControls {
        UvControls { minuv_l: self.minuv_l, maxuv_l: self.maxuv_l, taper_gaussian: self.taper_gaussian, taper_tukey: self.taper_tukey }
    }
}


/// The kind, as registered.
pub(super) const KIND: KindFn = KindFn {
    name: WeightingParams::KIND,
    role: Role::Transform,
    consumes: &[Product::Visibilities],
    produces: &[Product::Weights],
    consumes_also: None,
    passes_on: false,
    build: |c| {
        let params: WeightingParams = c.params()?;
        let grid_factor = grid_factor_of(c, &params).map_err(|e| c.at_field(&params, e))?;
        Ok(Built::Stage(Box::new(WeightingStage::new(params.clone(), grid_factor, c.image()).map_err(|e| c.at_field(&params, e))?)))
    },
};

/// The stage's weighting grid factor: the one given, else the trained field's of the series the
/// jobs go on to where it runs off its trained size (uniform and Briggs weights, so the PSF,
/// depend on the grid's cell: a 512 series at 1024 x 1024 on that image's own grid diverged at
/// its first network), else the default.
fn grid_factor_of(c: &crate::job::BuildContext<'_>, params: &WeightingParams) -> Result<f64> {
    if let Some(factor) = params.grid_factor {
        return Ok(factor);
    }
    if !params.scheme.with_robust(params.robust)?.needs_density() {
        return Ok(DEFAULT_GRID_FACTOR);
    }
    let size = c.image().size;
    Ok(match super::series_field::series_field_off_size(c, (params.scheme.name(), params.robust))? {
        Some((name, trained)) => {
            let factor = crate::weighting::grid_factor_of_trained_field(trained, size);
            log::info!(
                "weighting on the uv grid of series '{name}''s trained {trained} x {trained} field at {size} x {size} ({} cells across, grid factor {factor}, as WSClean's -super-weight): the PSF it was trained on",
                crate::weighting::cells_of(factor, size)
            );
            factor
        }
        None => DEFAULT_GRID_FACTOR,
    })
}

/// Where the truth's FITS grid is not the job's (another pixel size or centre), what differs:
/// its SNR and logSNR would compare images of different skies.
fn truth_grid_problem(job: &Job, geometry: crate::operator::ImageGeometry) -> Option<String> {
    let problems = job.grid_differences(job.truth_wcs.as_ref()?, &geometry);
    (!problems.is_empty()).then(|| format!("the truth is on another grid than the image ({}): its SNR and logSNR compare different pixels", problems.join("; ")))
}

/// A weighting as the metrics file records it, with its uv cuts and tapers (and how many
/// samples they left out, where counted).
fn weighting_json(weighting: Weighting, grid_factor: f64, uv: &UvControls, counts: Option<&UvCounts>) -> serde_json::Value {
    let mut json = match weighting {
        Weighting::Natural => serde_json::json!({"scheme": "natural"}),
        Weighting::Uniform => serde_json::json!({"scheme": "uniform", "grid_factor": grid_factor}),
        Weighting::Briggs { robust } => serde_json::json!({"scheme": "briggs", "robust": robust, "grid_factor": grid_factor}),
        Weighting::Given => serde_json::json!({"scheme": "given"}),
    };
    if let (Some(map), Ok(serde_json::Value::Object(controls))) = (json.as_object_mut(), serde_json::to_value(uv)) {
        map.extend(controls.into_iter().filter(|(_, v)| !v.is_null()));
        if !uv.is_empty() {
            map.insert("grid_factor".into(), serde_json::json!(grid_factor));
        }
        if let Some(c) = counts.filter(|c| c.kept() < c.samples) {
            map.insert("left_out".into(), serde_json::json!({"samples": c.samples, "minuv_l": c.below_min, "maxuv_l": c.above_max, "beyond_nyquist": c.beyond}));
        }
    }
    json
}

pub struct WeightingStage {
    weighting: Weighting,
    grid_factor: f64,
    uv: UvControls,
    image: ImageConfig,
}

impl WeightingStage {
    pub fn new(config: WeightingParams, grid_factor: f64, image: &ImageConfig) -> Result<WeightingStage> {
        // Before any data are read (and in `validate`): a grid this machine cannot hold, a cut
        // or taper out of range.
        let uv = config.uv();
        uv.check()?;
        if !matches!(config.scheme, WeightingScheme::Natural) || !uv.is_empty() {
            crate::weighting::check_grid(grid_factor, image.size)?;
        }
        Ok(WeightingStage {
            weighting: config.scheme.with_robust(config.robust)?,
            grid_factor,
            uv,
            image: image.clone(),
        })
    }
}

impl Stage<Job> for WeightingStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let vis = job.visibilities("weighting")?;
        let summary = vis.summary();
        // A job of a split is imaged on the grid of the whole split (or of the baseline the
        // image section gives); its super-resolution below is its own data's. Either is of the
        // baselines `maxuv_l` keeps.
        let max_uv = self.uv.longest_kept(summary.max_uv);
        let longest_baseline = self.image.longest_baseline.unwrap_or_else(|| self.uv.longest_kept(job.split_max_uv.unwrap_or(summary.max_uv)));
        let geometry = self.image.pixel_scale().geometry(self.image.size, longest_baseline)?;
        let given_unused = summary.imaging_weights && self.weighting != Weighting::Given;
        if vis.is_streamed() && self.weighting.needs_density() {
            log::info!("job {}: {} weighting reads the table once more for the density of its uv-coverage", job.id, self.weighting);
        }
        let (rule, counts) = weight_rule(vis, &summary, geometry, self.weighting, self.grid_factor, &self.uv)?;
        job.weight = Some(rule);
        let limit_l = 0.5 / geometry.pixel_rad;
        if let Some(counts) = &counts {
            counts.check_kept(limit_l, geometry.pixel_arcsec())?;
            if let Some(text) = counts.describe(limit_l, geometry.pixel_arcsec()) {
                log::info!("job {}: {text}", job.id);
            }
        }
        if !self.uv.is_empty() {
            log::info!("job {}: uv cuts and tapers as WSClean applies them: {}", job.id, self.uv.describe());
        }
        if given_unused {
            // As the reference's current imager: weights given with the data are used when asked.
            log::info!("job {}: the data carry imaging weights (`imaging_weight`, a .mat file's `nWimag`), not used: the weighting is {} (`given` uses them)", job.id, self.weighting);
        }
        job.geometry = Some(geometry);
        job.weighting_cells = self.weighting.needs_density().then(|| crate::weighting::cells_of(self.grid_factor, self.image.size));
        job.superresolution = geometry.superresolution(max_uv);
        job.theoretic_beam_rad = (max_uv > 0.0).then(|| self.uv.theoretic_beam_rad(summary.max_uv));
        (job.track_hours, job.integration_s) = (summary.times.track_hours(), summary.times.integration_s());
        if let Some(problem) = truth_grid_problem(&job, geometry) {
            job.warn(problem);
        }
        job.settings.insert("weighting".into(), weighting_json(self.weighting, self.grid_factor, &self.uv, counts.as_ref()));
        job.settings.insert("pixel_arcsec".into(), serde_json::json!(geometry.pixel_arcsec()));
        if let Some(sr) = job.superresolution {
            job.settings.insert("superresolution".into(), serde_json::json!(sr));
        }
        if let Some(hours) = job.track_hours {
            job.settings.insert("track_hours".into(), serde_json::json!(hours));
        }
        if let Some(seconds) = job.integration_s {
            job.settings.insert("integration_s".into(), serde_json::json!(seconds));
        }
        emit(Port::Next, job)
    }
}
