//! The built-in stage kinds, registered by their YAML `kind` in [`builtin`]. Each kind is one
//! module with a config struct that rejects unknown keys; the engine's contracts
//! (`crate::pipeline::registry`) say what a kind declares and how it is built.

mod arrow_ipc;
mod gridder;
pub mod ingest;
mod memory;
#[cfg(feature = "ms")]
mod ms;
mod parquet;
mod products;
mod residual;
mod simulate;
mod step;
mod weighting;
mod writer;

use crate::pipeline::config::PipelineSpec;
use crate::pipeline::registry::{BuildContext, Built, KindFn, Product, Registry, Role};
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

/// Every built-in kind.
const BUILTIN: &[KindFn] = &[
    source("simulate", |c| Ok(Built::Source(Box::new(simulate::SimulateSource::new(c.params()?, c.image(), c.threads)?)))),
    source("parquet", |c| Ok(Built::Source(Box::new(parquet::ParquetSource::new(c.params()?, c.pipeline, c.stage)?)))),
    source("arrow-ipc", |c| Ok(Built::Source(Box::new(arrow_ipc::ArrowIpcSource::new(c.params()?, c.pipeline, c.stage)?)))),
    source("arrow", |c| Ok(Built::Source(Box::new(memory::MemorySource::new(c.params()?, c)?)))),
    #[cfg(feature = "ms")]
    source("ms", |c| Ok(Built::Source(Box::new(ms::MsSource::new(c.params()?, c.pipeline, c.stage)?)))),
    #[cfg(not(feature = "ms"))]
    source("ms", |c| Err(c.error(Some("kind"), "kind 'ms': this r2d2 was built without the `ms` feature"))),
    KindFn {
        name: "weighting",
        role: Role::Transform,
        consumes: VISIBILITIES,
        produces: &[Product::Weights],
        consumes_also: None,
        passes_on: false,
        build: |c| Ok(Built::Stage(Box::new(weighting::WeightingStage::new(c.params()?, c.image())?))),
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
        let step = step::StepStage::onnx(c.params()?, c.image().size, c.threads, &imaging_setup(c.pipeline)).map_err(|e| c.error(Some("series"), e))?;
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
        name: "writer",
        role: Role::Sink,
        consumes: IMAGING,
        produces: &[],
        consumes_also: None,
        passes_on: false,
        build: |c| Ok(Built::Stage(Box::new(writer::WriterStage::new(c.params()?, c.pipeline, c.stage)?))),
    },
    KindFn {
        name: "products",
        role: Role::Sink,
        consumes: IMAGING,
        produces: &[],
        consumes_also: None,
        passes_on: true,
        build: |c| Ok(Built::Stage(Box::new(products::ProductsStage::new(c.params()?, c)?))),
    },
];

/// The job's imaging as a series' validity sees it: the super-resolution (unknown when the
/// pixel size is given in arcsec: it then depends on each job's longest baseline) and the
/// weighting of the pipeline's first weighting stage.
fn imaging_setup(pipeline: &PipelineSpec) -> crate::steps::series::ImagingSetup {
    let weighting = pipeline.stages.iter().find(|s| s.kind == "weighting").map(|s| &s.params);
    crate::steps::series::ImagingSetup {
        superresolution: pipeline.image.pixel_arcsec.is_none().then(|| pipeline.image.superresolution.unwrap_or(1.5)),
        weighting: weighting.and_then(|p| p.get("scheme")).and_then(serde_yaml::Value::as_str).map(str::to_string),
        robust: weighting.map(|p| p.get("robust").and_then(serde_yaml::Value::as_f64).unwrap_or(0.0)),
    }
}

/// A registry holding the built-in kinds.
pub fn builtin() -> Registry {
    let mut registry = Registry::new();
    for kind in BUILTIN {
        registry.register(KindFn { ..*kind }).expect("built-in kinds have distinct names");
    }
    registry
}
