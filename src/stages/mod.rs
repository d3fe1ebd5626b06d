//! The built-in stage kinds, registered by their YAML `kind` in [`builtin`]. Each kind is one
//! module with its typed parameters (`params`: what the YAML holds, unknown keys refused); the
//! engine's contracts (`crate::pipeline::registry`) say what a kind declares and how it is built.

mod arrow_ipc;
mod final_clean;
mod gridder;
mod memory;
#[cfg(feature = "ms")]
mod ms;
pub mod params;
mod parquet;
mod products;
mod residual;
mod simulate;
mod step;
mod weighting;
mod writer;

use crate::job::{BuildContext, Built, ImageContext, KindFn, Product, Registry};
use crate::pipeline::Role;
use crate::Result;

const VISIBILITIES: &[Product] = &[Product::Visibilities];
const IMAGING: &[Product] = &[Product::Imaging];

/// A source kind: produces jobs with visibilities.
const fn source(name: &'static str, build: fn(&BuildContext<'_>) -> Result<Built>) -> KindFn {
    KindFn { name, role: Role::Source, consumes: &[], produces: VISIBILITIES, consumes_also: None, passes_on: false, build }
}

/// A network step kind: improves the model of a gridded job.
const fn step(name: &'static str, build: fn(&BuildContext<'_>) -> Result<Built>) -> KindFn {
    KindFn { name, role: Role::Step, consumes: IMAGING, produces: &[Product::Model], consumes_also: None, passes_on: false, build }
}

/// Source kinds that read no MeasurementSet: their jobs have no model column to write.
const FILE_SOURCES: &[&str] = &["simulate", "parquet", "arrow-ipc"];

/// Every built-in kind.
const BUILTIN: &[KindFn] = &[
    source("simulate", |c| {
        let source = simulate::SimulateSource::new(c.params()?, c.image(), c.threads).map_err(|e| at_key(c, SIMULATE_KEYS, e))?;
        Ok(Built::Source(Box::new(source)))
    }),
    source("parquet", |c| Ok(Built::Source(Box::new(parquet::ParquetSource::new(c.params()?, c.pipeline, c.stage, c.image().size)?)))),
    source("arrow-ipc", |c| Ok(Built::Source(Box::new(arrow_ipc::ArrowIpcSource::new(c.params()?, c.pipeline, c.stage, c.image().size)?)))),
    source("arrow", |c| Ok(Built::Source(Box::new(memory::MemorySource::new(c.params()?, c)?)))),
    #[cfg(feature = "ms")]
    source("ms", |c| {
        // A writer that predicts the model into the MS needs one job per field, checked now.
        let model_columns: Vec<String> = c.downstream_params::<params::WriterParams>()?.into_iter().filter_map(|w| w.model_column).collect();
        Ok(Built::Source(Box::new(ms::MsSource::new(c.params()?, c.pipeline, c.stage, c.image().size, &model_columns)?)))
    }),
    #[cfg(not(feature = "ms"))]
    source("ms", |c| Err(c.error(Some("kind"), "kind 'ms': this r2d2 was built without the `ms` feature"))),
    KindFn {
        name: "weighting",
        role: Role::Transform,
        consumes: VISIBILITIES,
        produces: &[Product::Weights],
        consumes_also: None,
        passes_on: false,
        build: |c| Ok(Built::Stage(Box::new(weighting::WeightingStage::new(c.params()?, c.image()).map_err(|e| at_key(c, &[("robust", "robust")], e))?))),
    },
    KindFn {
        name: "gridder",
        role: Role::Transform,
        consumes: &[Product::Visibilities, Product::Weights],
        produces: &[Product::Imaging, Product::Operator],
        consumes_also: None,
        passes_on: false,
        // The operator (and the visibilities) stay only if a stage downstream consumes them.
        build: |c| {
            let keep_operator = c.consumed_downstream(Product::Operator);
            Ok(Built::Stage(Box::new(gridder::GridderStage::new(c.params()?, c.threads, keep_operator)?)))
        },
    },
    step("clean", |c| Ok(Built::Stage(Box::new(step::StepStage::clean(c.params()?)?)))),
    // The series is checked against the pipeline (image size, network shapes): say where.
    step("onnx", |c| {
        let config: crate::steps::onnx::OnnxConfig = c.params()?;
        let setup = imaging_setup(c, config.series.as_os_str() == crate::steps::series::AUTO_SERIES)?;
        let step = step::StepStage::onnx(config, c.image().size, c.threads, &setup).map_err(|e| c.error_caused("series", e))?;
        Ok(Built::Stage(Box::new(step)))
    }),
    step("native", |c| {
        let mut config: crate::steps::native::NativeConfig = c.params()?;
        // validate never loads a plugin into this process: its create check runs in a host
        // process even under `isolation: none` (unless no host can be found).
        if c.validating() && crate::steps::native_host::find_host().is_ok() {
            config.isolation = crate::steps::native::Isolation::Process;
        }
        Ok(Built::Stage(Box::new(step::StepStage::native(config, c.image().size, c.name())?)))
    }),
    KindFn {
        name: "residual",
        role: Role::Residual,
        consumes: &[Product::Imaging, Product::Model],
        produces: &[],
        consumes_also: Some(residual::consumes),
        passes_on: false,
        build: |c| Ok(Built::Stage(Box::new(residual::ResidualStage::new(c.params()?)?))),
    },
    KindFn {
        name: "final_clean",
        role: Role::Transform,
        consumes: &[Product::Imaging, Product::Model],
        produces: &[],
        consumes_also: None,
        passes_on: false,
        build: |c| Ok(Built::Stage(Box::new(final_clean::FinalCleanStage::new(c.params()?)?))),
    },
    KindFn {
        name: "writer",
        role: Role::Sink,
        consumes: IMAGING,
        produces: &[],
        consumes_also: None,
        passes_on: false,
        build: |c| {
            let config: params::WriterParams = c.params()?;
            // A model column needs jobs read from an MS (`ms`, or in-memory batches that carry
            // an MS's origin): a file source has no column to write, known before imaging.
            if config.model_column.is_some() {
                if let Some((name, kind)) = c.upstream_stages().into_iter().find(|(_, k)| FILE_SOURCES.contains(k)) {
                    return Err(c.error(
                        Some("model_column"),
                        format!("the jobs come from stage '{name}' (kind '{kind}'), which reads no MeasurementSet: only an `ms` source has a column to write the model into"),
                    ));
                }
            }
            Ok(Built::Stage(Box::new(writer::WriterStage::new(config, c.pipeline, c.stage, several_jobs(c)?, holds_until_finished(c))?)))
        },
    },
    KindFn {
        name: "products",
        role: Role::Sink,
        consumes: IMAGING,
        produces: &[],
        consumes_also: None,
        passes_on: true,
        build: |c| Ok(Built::Stage(Box::new(products::ProductsStage::new(c.params()?, c, holds_until_finished(c))?))),
    },
];

/// The stage keys of the parameters the simulation's checks name.
const SIMULATE_KEYS: &[(&str, &str)] = &[
    ("configs", "configurations"),
    ("telescope configuration", "configurations"),
    ("observation time", "hours"),
    ("hours", "hours"),
    ("declination", "dec_deg"),
    ("integration time", "integration_s"),
    ("frequency", "frequency_mhz"),
    ("nfreq", "channels"),
    ("freq-ratio", "frequency_ratio"),
    ("flag-fraction", "flag_fraction"),
    ("robust", "robust"),
];

/// A stage constructor's parameter error at the line of the stage key it is about (`keys`:
/// the error's parameter name, the key), else as it is.
fn at_key(c: &BuildContext<'_>, keys: &[(&str, &str)], e: crate::Error) -> crate::Error {
    let key = match &e {
        crate::Error::Parameter { name, .. } => keys.iter().find(|(n, _)| n == name).map(|(_, key)| *key),
        _ => None,
    };
    match key {
        Some(key) => c.error_caused(key, e),
        None => e,
    }
}

/// Whether a sink keeps its jobs' products until the run's end (its finish): a native plugin
/// before it is torn down only then, and a crash there (or a heap it corrupted, found then)
/// must fail the run before anything it computed is written or delivered.
fn holds_until_finished(c: &BuildContext<'_>) -> bool {
    c.upstream_stages().iter().any(|&(_, kind)| kind == "native")
}

/// Why the sources before stage `c` may make several jobs (a list or pattern of files, a
/// `split_by`), if they may. Several sources feeding one writer are caught
/// by the writer at run time, when a second job reaches a prefix already written.
fn several_jobs(c: &BuildContext<'_>) -> Result<Option<String>> {
    let mut why = Vec::new();
    for p in c.upstream_params::<params::ParquetParams>()? {
        let files: Vec<&String> = match &p.files {
            params::Files::One(f) => vec![f],
            params::Files::Many(fs) => fs.iter().collect(),
        };
        if files.len() > 1 {
            why.push("a parquet source lists several files".to_string());
        } else if let Some(pattern) = files.iter().find(|f| f.contains(['*', '?', '['])) {
            why.push(format!("a parquet source's files are a pattern ({pattern})"));
        }
        why.extend(p.split_by.map(|_| "a parquet source has split_by".to_string()));
    }
    why.extend(c.upstream_params::<params::ArrowIpcParams>()?.into_iter().filter_map(|p| p.split_by).map(|_| "an arrow-ipc source has split_by".to_string()));
    why.extend(c.upstream_params::<params::ArrowParams>()?.into_iter().filter_map(|p| p.split_by).map(|_| "an arrow source has split_by".to_string()));
    #[cfg(feature = "ms")]
    why.extend(c.upstream_params::<params::MsParams>()?.into_iter().filter_map(|p| p.split_by).map(|_| "an ms source has split_by".to_string()));
    Ok((!why.is_empty()).then(|| why.join("; ")))
}

/// The jobs' imaging as a series' validity sees it: the super-resolution (unknown when the
/// pixel size is given in arcsec: it then depends on each job's longest baseline) and the
/// weighting of the weighting stage before the step (unknown if there are several that
/// disagree, or none of the built-in kind).
/// The telescope is looked up only for `auto` (`choosing`), whose choice it takes part in; a
/// named series meets each job's telescope at the job.
fn imaging_setup(ctx: &BuildContext<'_>, choosing: bool) -> Result<crate::steps::series::ImagingSetup> {
    let image = ctx.image();
    let mut weightings = ctx.upstream_params::<params::WeightingParams>()?;
    weightings.dedup();
    let weighting = match weightings.as_slice() {
        [one] => Some(one),
        _ => None,
    };
    Ok(crate::steps::series::ImagingSetup {
        superresolution: image.pixel_arcsec.is_none().then(|| image.superresolution.unwrap_or(1.5)),
        weighting: weighting.map(|w| w.scheme.name().to_string()),
        robust: weighting.map(|w| w.robust),
        telescope: if choosing { source_telescope(ctx)? } else { None },
        // Known once the data are read: each job's are checked at its first step.
        track_hours: None,
        integration_s: None,
    })
}

/// The telescope of the sources before the step (`auto` prefers a series trained for it): a
/// simulated source's, else the one the first named file says; none where none says.
fn source_telescope(ctx: &BuildContext<'_>) -> Result<Option<String>> {
    let mut paths: Vec<std::path::PathBuf> = Vec::new();
    for p in ctx.upstream_params::<params::ParquetParams>()? {
        match &p.files {
            params::Files::One(f) => paths.push(f.into()),
            params::Files::Many(fs) => paths.extend(fs.first().map(Into::into)),
        }
    }
    paths.extend(ctx.upstream_params::<params::ArrowIpcParams>()?.into_iter().map(|p| p.path.into()));
    #[cfg(feature = "ms")]
    paths.extend(ctx.upstream_params::<params::MsParams>()?.into_iter().map(|p| p.path));
    // A simulated source names its telescope.
    if let Some(p) = ctx.upstream_params::<params::SimulateParams>()?.first() {
        return Ok(Some(crate::simulate::telescope::telescope(&p.telescope)?.name.clone()));
    }
    // A glob pattern is not a file: it is not opened.
    Ok(paths.iter().filter(|p| !p.to_string_lossy().contains(['*', '?', '['])).find_map(|p| crate::vis::telescope_of(p)))
}

/// A registry holding the built-in kinds.
pub fn builtin() -> Registry {
    let mut registry = Registry::new();
    for kind in BUILTIN {
        registry.register(KindFn { ..*kind }).expect("built-in kinds have distinct names");
    }
    registry
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::graph::Graph;
    use crate::job::RunContext;
    use crate::pipeline::runner::neighbours;
    use crate::pipeline::PipelineSpec;
    use std::path::Path;

    /// The imaging a series' validity is checked against, as the step at `stages[step]` of
    /// `text` sees it.
    fn setup_of(text: &str, step: usize) -> crate::steps::series::ImagingSetup {
        let spec = PipelineSpec::parse(text, Path::new("p.yaml"), &[]).unwrap();
        let graph = Graph::build(&builtin(), &spec).unwrap();
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
            validating: false,
        };
        imaging_setup(&ctx, false).unwrap()
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
}
