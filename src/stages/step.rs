//! Network-step stages (`kind: clean`, `onnx`, `native`): run the job's next step of
//! the series and pass it to the residual update.

use super::weighting::WeightingParams;
use crate::job::{BuildContext, Built, Emit, ImageContext, Job, KindFn, Product};
use crate::pipeline::{Port, Role, Stage, StageParams};
use crate::steps::clean::{CleanConfig, CleanStep};
use crate::steps::native::{Isolation, NativeConfig, NativeStep};
use crate::steps::onnx::runtime::{BackendChoice, GraphOptimization};
use crate::steps::onnx::{OnnxConfig, OnnxStep, ValidityMode};
use crate::steps::series::ImagingSetup;
use super::series_field::imaging_setup;
use crate::steps::{JobDomain, NetworkStep, StepInput};
use crate::{Error, Result};
use std::path::PathBuf;
use std::time::Instant;

// The steps' parameters are their configurations (`crate::steps`), re-exported as
// `params::CleanParams`, `OnnxParams`, `NativeParams`.

impl StageParams for CleanConfig {
    const KIND: &'static str = "clean";
}

impl StageParams for OnnxConfig {
    const KIND: &'static str = "onnx";
}

impl StageParams for NativeConfig {
    const KIND: &'static str = "native";
}

impl OnnxConfig {
    /// The series (a directory, a name `r2d2 models` lists, or `auto`: the one trained for the
    /// image size) with the defaults of the other keys.
    pub fn new(series: impl Into<PathBuf>) -> OnnxConfig {
        OnnxConfig {
            series: series.into(),
            backend: BackendChoice::default(),
            threads: 0,
            networks: None,
            prefetch: true,
            graph_optimization: GraphOptimization::default(),
            realisation: None,
            validity: ValidityMode::default(),
            fits_mask: None,
            auto_mask: None,
            tiles: Default::default(),
        }
    }
}

impl NativeConfig {
    /// The plugin library and the series length, with the defaults of the other keys.
    pub fn new(library: impl Into<PathBuf>, iterations: usize) -> NativeConfig {
        NativeConfig { library: library.into(), iterations, positivity: true, config: None, isolation: Isolation::default(), timeout: 600.0 }
    }
}

/// A network step kind: improves the model of a gridded job.
const fn step(name: &'static str, build: fn(&BuildContext<'_>) -> Result<Built>) -> KindFn {
    KindFn { name, role: Role::Step, consumes: &[Product::Imaging], produces: &[Product::Model], consumes_also: None, passes_on: false, build }
}

/// The kinds, as registered.
pub(super) const CLEAN: KindFn = step(CleanConfig::KIND, |c| {
    let config: CleanConfig = c.params()?;
    let mask = MaskFile::read(config.fits_mask.as_deref()).map_err(|e| c.error_caused("fits_mask", e))?;
    let auto_mask = config.auto_mask;
    let step = StepStage::clean(config.clone()).map_err(|e| c.at_field(&config, e))?;
    Ok(Built::Stage(Box::new(StepStage { mask, auto_mask, ..step })))
});

/// The series is checked against the pipeline (image size, network shapes): say where.
pub(super) const ONNX: KindFn = step(OnnxConfig::KIND, |c| {
    let config: OnnxConfig = c.params()?;
    let mask = MaskFile::read(config.fits_mask.as_deref()).map_err(|e| c.error_caused("fits_mask", e))?;
    config.given_auto_mask().map_err(|e| c.error_caused("auto_mask", e))?;
    let setup = upstream_imaging_setup(c, config.series.as_os_str() == crate::steps::series::AUTO_SERIES)?;
    let step = StepStage::onnx(config, c.image().size, c.threads, &setup).map_err(|e| c.error_caused("series", e))?;
    let auto_mask = step.step.auto_mask();
    Ok(Built::Stage(Box::new(StepStage { mask, auto_mask, ..step })))
});

pub(super) const NATIVE: KindFn = step(NativeConfig::KIND, |c| {
    let mut config: NativeConfig = c.params()?;
    // validate never loads a plugin into this process: its create check runs in a host
    // process even under `isolation: none` (unless no host can be found).
    if c.validating() && crate::steps::native_host::find_host().is_ok() {
        config.isolation = Isolation::Process;
    }
    Ok(Built::Stage(Box::new(StepStage::native(config, c.image().size, c.name())?)))
});

/// Whether a sink keeps its jobs' products until the run's end (its finish): a native plugin
/// before it is torn down only then, and a crash there (or a heap it corrupted, found then)
/// must fail the run before anything it computed is written or delivered.
pub(super) fn holds_until_finished(c: &BuildContext<'_>) -> bool {
    c.upstream_stages().iter().any(|&(_, kind)| kind == NativeConfig::KIND)
}

/// The jobs' imaging as a series' validity sees it ([`imaging_setup`]), with the weighting of
/// the weighting stage before the step (unknown if there are several that disagree, or none
/// of the built-in kind).
fn upstream_imaging_setup(ctx: &BuildContext<'_>, choosing: bool) -> Result<ImagingSetup> {
    let mut weightings = ctx.upstream_params::<WeightingParams>()?;
    weightings.dedup();
    let weighting = match weightings.as_slice() {
        [one] => Some((one.scheme.name(), one.robust)),
        _ => None,
    };
    imaging_setup(ctx, weighting, choosing)
}

pub struct StepStage {
    kind: &'static str,
    step: Box<dyn NetworkStep>,
    /// The step's `fits_mask`: each job's model is kept to it.
    mask: Option<MaskFile>,
    /// The `auto_mask` level (noise sigmas) CLEAN or a series applies, for the products' record.
    auto_mask: Option<f64>,
}

impl StepStage {
    pub fn clean(config: CleanConfig) -> Result<StepStage> {
        Ok(StepStage { kind: "clean", step: Box::new(CleanStep::new(config)?), mask: None, auto_mask: None })
    }

    /// An R2D2/R3D3 series for `size x size` images (checked now, before any job runs).
    pub fn onnx(config: OnnxConfig, size: usize, threads: usize, setup: &ImagingSetup) -> Result<StepStage> {
        Ok(StepStage { kind: "onnx", step: Box::new(OnnxStep::new(&config, size, threads, setup)?), mask: None, auto_mask: None })
    }

    /// Loads and creates the plugin now, so that every plugin error comes before imaging.
    pub fn native(config: NativeConfig, image_size: usize, stage: &str) -> Result<StepStage> {
        Ok(StepStage { kind: "native", step: Box::new(NativeStep::new(config, image_size, stage)?), mask: None, auto_mask: None })
    }
}

/// A mask file (`fits_mask`, WSClean's `-fits-mask`): read when the stage is built, checked
/// against each job's grid at its first step.
struct MaskFile {
    path: PathBuf,
    image: crate::fits::FitsImage,
}

impl MaskFile {
    /// The mask at `path` (none without one): a FITS image, any further axes of length 1, as
    /// WSClean's masks have them.
    fn read(path: Option<&std::path::Path>) -> Result<Option<MaskFile>> {
        let Some(path) = path else { return Ok(None) };
        let image = crate::fits::read_image(path)?;
        Ok(Some(MaskFile { path: path.to_path_buf(), image }))
    }

    /// The mask on `job`'s grid (true where the file is not zero), or an error naming the file,
    /// what it has and what the image has: a mask on another grid is refused, not reprojected.
    fn on_grid(&self, job: &Job, geometry: &crate::operator::ImageGeometry) -> Result<Vec<bool>> {
        let (image, n) = (&self.image, geometry.size);
        let mut problems = Vec::new();
        if (image.nx, image.ny) != (n, n) {
            problems.push(format!("it is {} x {} pixels, the image {n} x {n}", image.nx, image.ny));
        }
        match &image.wcs {
            Some(wcs) => problems.extend(job.grid_differences(wcs, geometry)),
            None if problems.is_empty() => {
                log::warn!("{}: the mask has no celestial coordinates; its pixels are taken to be the image's", self.path.display());
            }
            None => {}
        }
        if !problems.is_empty() {
            return Err(Error::parameter(
                "fits_mask",
                format!("{}: the mask is not on the image's grid ({}): make it on that grid (a mask is not reprojected)", self.path.display(), problems.join("; ")),
            ));
        }
        Ok(image.data.iter().map(|&v| v != 0.0).collect())
    }
}

impl StepStage {
    /// Before `iteration` of a step of several realisations: when the previous realisation has
    /// run its series, keep its final model and start the next from the dirty image (model 0,
    /// residual = dirty). True once every realisation is done.
    fn next_realisation(&self, job: &mut Job, iteration: usize, realisations: usize) -> Result<bool> {
        let per = self.step.series_length() / realisations;
        if iteration > 1 && (iteration - 1) % per == 0 {
            let im = job.imaging_mut(self.kind)?;
            let done = std::mem::replace(&mut im.model, vec![0.0; im.dirty.len()]);
            im.residual = im.dirty.clone();
            job.realisation_models.push(done);
        }
        job.realisation = (iteration - 1) / per + 1;
        Ok(job.realisation_models.len() == realisations)
    }
}

impl Stage<Job> for StepStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let began = Instant::now();
        let iteration = job.iteration + 1;
        let realisations = self.step.realisations();
        if realisations > 1 && self.next_realisation(&mut job, iteration, realisations)? {
            // Every realisation is done: the image is their mean, whose residual comes next.
            let mean = crate::metrics::pixel_mean(&job.realisation_models);
            job.imaging_mut(self.kind)?.model = mean;
            job.realisation = 0;
            job.iteration = iteration;
            job.series_finished = true;
            job.last_step_seconds = began.elapsed().as_secs_f64();
            return emit(Port::Next, job);
        }
        if iteration == 1 {
            // Before a job's first step: is it inside what the step was made for?
            let dirty_mean = job.imaging.as_ref().map(|im| im.dirty.iter().sum::<f64>() / im.dirty.len().max(1) as f64);
            let domain = JobDomain {
                telescope: &job.meta.telescope,
                superresolution: job.superresolution,
                track_hours: job.track_hours,
                integration_s: job.integration_s,
                dirty_mean,
                weighting_cells: job.weighting_cells,
            };
            for problem in self.step.domain_problems(&domain)? {
                job.warn(problem);
            }
            if let Some(described) = self.step.describe() {
                job.settings.insert("step".into(), described);
            }
            let geometry = job.imaging.as_ref().map(|im| im.geometry);
            if let (Some(mask), Some(geometry)) = (&self.mask, geometry) {
                let pixels = mask.on_grid(&job, &geometry)?;
                let inside = pixels.iter().filter(|&&p| p).count();
                if inside == 0 {
                    job.warn(format!("{}: the mask is zero everywhere: the model stays empty", mask.path.display()));
                }
                job.mask = Some(std::sync::Arc::new(pixels));
                job.inputs.push(mask.path.clone());
            }
            let mut record = serde_json::Map::new();
            if let Some(mask) = &self.mask {
                record.insert("fits_mask".into(), mask.path.display().to_string().into());
            }
            if let Some(sigmas) = self.auto_mask {
                record.insert("auto_mask".into(), sigmas.into());
            }
            if !record.is_empty() {
                job.settings.insert("mask".into(), record.into());
            }
        }
        let Job { id, imaging, mask, .. } = &mut job;
        let im = imaging.as_mut().ok_or_else(|| crate::job::missing(self.kind, id, crate::job::Product::Imaging))?;
        let input = StepInput {
            job: id,
            size: im.geometry.size,
            model: &im.model,
            residual: &im.residual,
            dirty: &im.dirty,
            psf: &im.psf,
            psf_2n: &im.psf_2n,
            psf_convolution: &im.psf_convolution,
            mask: mask.as_deref().map(Vec::as_slice),
        };
        let mut model = self.step.step(iteration, &input)?;
        // A step that knows no mask (a network) has its model kept to it: the pixels outside
        // are set to 0 after each step, and the residual update puts what they held back into
        // the residual.
        if let Some(mask) = mask.as_deref() {
            model.iter_mut().zip(mask.iter()).filter(|(_, inside)| !**inside).for_each(|(x, _)| *x = 0.0);
        }
        let cause = format!("the {} step made it from a finite residual: a diverging network or plugin", self.kind);
        crate::sanity::check_image(&model, im.geometry.size, &format!("model after step {iteration}"), &cause)?;
        im.model = model;
        job.iteration = iteration;
        job.series_finished = realisations == 1 && iteration >= self.step.series_length();
        job.series_length = self.step.series_length();
        job.early_stop_from = self.step.early_stop_from();
        job.step_kind = Some(self.kind.to_string());
        job.restores = self.step.restores();
        job.last_step_seconds = began.elapsed().as_secs_f64();
        emit(Port::Next, job)
    }

    fn finish(&mut self) -> Result<()> {
        self.step.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::job::RunContext;
    use crate::pipeline::graph::Graph;
    use crate::pipeline::runner::neighbours;
    use crate::pipeline::PipelineSpec;
    use std::path::Path;

    /// The imaging a series' validity is checked against, as the step at `stages[step]` of
    /// `text` sees it.
    fn setup_of(text: &str, step: usize) -> ImagingSetup {
        let spec = PipelineSpec::parse(text, Path::new("p.yaml"), &[]).unwrap();
        let registry = crate::stages::builtin();
        let graph = Graph::build(&registry, &spec).unwrap();
        let (upstream_stages, downstream_stages) = neighbours(&graph.reach(), step);
        let context = RunContext::new(&spec, Vec::new(), None).unwrap();
        let ctx = BuildContext {
            pipeline: &spec,
            stage: &spec.stages[step],
            threads: 1,
            downstream: Vec::new(),
            upstream_stages,
            downstream_stages,
            context: &context,
            registry: &registry,
            validating: false,
        };
        upstream_imaging_setup(&ctx, true).unwrap()
    }

    const PIPELINE: &str = "image: {size: 16, superresolution: 2}\nstages:\n  source: {kind: simulate, to: weights}\n  weights: {kind: weighting, scheme: robust, robust: -0.5, to: grid}\n  grid: {kind: gridder, to: step}\n  step: {kind: clean, to: update}\n  update: {kind: residual, to: step, done: write}\n  write: {kind: writer}\n";

    #[test]
    fn a_step_sees_the_weighting_of_the_stage_before_it() {
        let setup = setup_of(PIPELINE, 3);
        // `robust` is Briggs' other name: the series' manifest knows it as briggs.
        assert_eq!((setup.superresolution, setup.weighting.as_deref(), setup.robust), (Some(2.0), Some("briggs"), Some(-0.5)));
        let arcsec = setup_of(&PIPELINE.replace("superresolution: 2", "pixel_arcsec: 1"), 3);
        assert_eq!(arcsec.superresolution, None, "the super-resolution depends on each job's baselines");
    }

    #[test]
    fn a_weighting_stage_the_step_does_not_follow_is_not_its_weighting() {
        // A second weighting stage after the loop (before a writer), first in the file,
        // weights nothing the step sees.
        let after = PIPELINE
            .replace("done: write}", "done: again}")
            .replace("stages:\n", "stages:\n  again: {kind: weighting, scheme: natural, to: write}\n");
        assert_eq!(setup_of(&after, 4).weighting.as_deref(), Some("briggs"));
    }

    /// The telescope `auto` prefers a series for is the one the source before the step says,
    /// asked of the source kind (`SourceParams::telescope`): a simulation's, by its registry
    /// name; none where the source says none (a file that does not exist yet is not opened).
    #[test]
    fn a_step_sees_the_telescope_its_source_says() {
        assert_eq!(setup_of(PIPELINE, 3).telescope.as_deref(), Some("VLA"));
        let meerkat = PIPELINE.replace("{kind: simulate,", "{kind: simulate, telescope: mkat,");
        assert_eq!(setup_of(&meerkat, 3).telescope.as_deref(), Some("MeerKAT"), "an alias of the telescope data");
        let file = PIPELINE.replace("{kind: simulate,", "{kind: parquet, files: no-such.parquet,");
        assert_eq!(setup_of(&file, 3).telescope, None);
    }
}
