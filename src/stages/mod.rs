//! Stage kinds, registered by their YAML `kind`. Each kind is one module with a config
//! struct that rejects unknown keys, built by [`build_stage`].

mod arrow_ipc;
mod gridder;
#[cfg(feature = "ms")]
mod ms;
mod parquet;
mod residual;
mod simulate;
mod step;
mod weighting;
mod writer;

use crate::pipeline::config::{PipelineConfig, StageConfig};
use crate::pipeline::{Source, Stage};
use crate::Result;

/// What a stage does in the graph.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// Produces jobs (no input).
    Source,
    /// One job in, one job out.
    Transform,
    /// A network step of the imaging loop.
    Step,
    /// The residual update closing the loop (`to`: back to the step, `done`: out).
    Residual,
    /// Ends the pipeline (writers).
    Sink,
}

/// Every kind, with its role.
const REGISTRY: &[(&str, Role)] = &[
    ("simulate", Role::Source),
    ("parquet", Role::Source),
    ("arrow-ipc", Role::Source),
    ("ms", Role::Source),
    ("weighting", Role::Transform),
    ("gridder", Role::Transform),
    ("clean", Role::Step),
    ("onnx", Role::Step),
    ("native", Role::Step),
    ("residual", Role::Residual),
    ("writer", Role::Sink),
];

pub const KINDS: &[&str] = &["simulate", "parquet", "arrow-ipc", "ms", "weighting", "gridder", "clean", "onnx", "native", "residual", "writer"];
pub const SOURCE_KINDS: &[&str] = &["simulate", "parquet", "arrow-ipc", "ms"];

pub fn role(kind: &str) -> Option<Role> {
    REGISTRY.iter().find(|(k, _)| *k == kind).map(|(_, r)| *r)
}

/// A constructed stage, ready to run on its thread.
pub enum Built {
    Source(Box<dyn Source>),
    Stage(Box<dyn Stage>),
}

/// The job's imaging as a series' validity sees it: the super-resolution (unknown when the
/// pixel size is given in arcsec: it then depends on each job's longest baseline) and the
/// weighting of the pipeline's first weighting stage.
fn imaging_setup(config: &PipelineConfig) -> crate::steps::series::ImagingSetup {
    let weighting = config.stages.iter().find(|s| s.kind == "weighting").map(|s| &s.params);
    crate::steps::series::ImagingSetup {
        superresolution: config.image.pixel_arcsec.is_none().then(|| config.image.superresolution.unwrap_or(1.5)),
        weighting: weighting.and_then(|p| p.get("scheme")).and_then(serde_yaml::Value::as_str).map(str::to_string),
        robust: weighting.map(|p| p.get("robust").and_then(serde_yaml::Value::as_f64).unwrap_or(0.0)),
    }
}

/// Parse the stage's parameters and construct it (cheap: heavy work happens per job).
pub fn build_stage(config: &PipelineConfig, stage: &StageConfig) -> Result<Built> {
    let threads = config.threads;
    Ok(match stage.kind.as_str() {
        "simulate" => Built::Source(Box::new(simulate::SimulateSource::new(config.stage_params(stage)?, &config.image, threads)?)),
        "parquet" => Built::Source(Box::new(parquet::ParquetSource::new(config.stage_params(stage)?, config, stage)?)),
        "arrow-ipc" => Built::Source(Box::new(arrow_ipc::ArrowIpcSource::new(config.stage_params(stage)?, config, stage)?)),
        #[cfg(feature = "ms")]
        "ms" => Built::Source(Box::new(ms::MsSource::new(config.stage_params(stage)?, config, stage)?)),
        #[cfg(not(feature = "ms"))]
        "ms" => return Err(config.stage_error(&stage.name, Some("kind"), "kind 'ms': this r2d2 was built without the `ms` feature")),
        "weighting" => Built::Stage(Box::new(weighting::WeightingStage::new(config.stage_params(stage)?, &config.image)?)),
        "gridder" => {
            // Keep the operator for the residual update only if one of them needs it.
            let keep_operator = config.stages.iter().any(|s| s.kind == "residual" && residual::wants_nufft(&s.params));
            Built::Stage(Box::new(gridder::GridderStage::new(config.stage_params(stage)?, threads, keep_operator)?))
        }
        "clean" => Built::Stage(Box::new(step::StepStage::clean(config.stage_params(stage)?)?)),
        "onnx" => {
            // The series is checked against the pipeline (image size, network shapes): say where.
            let name = &stage.name;
            let step = step::StepStage::onnx(config.stage_params(stage)?, config.image.size, threads, &imaging_setup(config))
                .map_err(|e| config.stage_error(name, Some("series"), &format!("stages.{name}.series: {e}")))?;
            Built::Stage(Box::new(step))
        }
        "native" => Built::Stage(Box::new(step::StepStage::native(config.stage_params(stage)?, config.image.size, &stage.name)?)),
        "residual" => Built::Stage(Box::new(residual::ResidualStage::new(config.stage_params(stage)?)?)),
        "writer" => Built::Stage(Box::new(writer::WriterStage::new(config.stage_params(stage)?, config, stage)?)),
        other => {
            return Err(config.stage_error(
                &stage.name,
                Some("kind"),
                &format!("stages.{}.kind: unknown kind '{other}' (one of: {})", stage.name, KINDS.join(", ")),
            ));
        }
    })
}
