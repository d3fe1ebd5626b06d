//! `r2d2 run` and `r2d2 validate`: a pipeline described in YAML.

use crate::{PipelineSpec, Result};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[derive(clap::Args)]
pub struct RunArgs {
    /// Pipeline description (YAML).
    pipeline: PathBuf,
    /// Override a value: stage.key=value (also image.size=N, threads=N).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
}

#[derive(clap::Args)]
pub struct ValidateArgs {
    pipeline: PathBuf,
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
}

/// Ctrl-C, SIGTERM and SIGHUP set the flag; the run given it stops its stages at the next job
/// boundary and kills its plugin hosts, and fails cleanly (a job being written is written
/// whole; nothing half-made stays behind).
pub fn cancel_on_ctrl_c() -> Arc<AtomicBool> {
    let cancel = Arc::new(AtomicBool::new(false));
    let flag = cancel.clone();
    let handler = move || flag.store(true, Ordering::SeqCst);
    if let Err(e) = ctrlc::set_handler(handler) {
        log::warn!("Ctrl-C will not stop the pipeline cleanly: {e}");
    }
    cancel
}

/// Whether a stage of `spec` may run native ONNX Runtime.
fn uses_onnx(spec: &PipelineSpec) -> bool {
    spec.stages.iter().any(|s| s.kind == "onnx" && s.params().get("backend").and_then(|b| b.as_str()) != Some("tract"))
}

pub fn run_pipeline(spec: &PipelineSpec) -> Result<()> {
    let (engine, _bar) = super::engine::engine(spec.threads, uses_onnx(spec))?;
    let report = engine.run(spec, Vec::new(), None, cancel_on_ctrl_c())?;
    let split: Vec<String> = report.stage_seconds.iter().map(|(k, v)| format!("{k} {v:.2}s")).collect();
    log::info!("{} job(s) in {:.2} s ({})", report.jobs.len(), report.seconds, split.join(", "));
    Ok(())
}

pub fn run(args: RunArgs) -> Result<()> {
    run_pipeline(&PipelineSpec::load(&args.pipeline, &args.set)?)
}

pub fn validate(args: ValidateArgs) -> Result<()> {
    let spec = PipelineSpec::load(&args.pipeline, &args.set)?;
    let (engine, _bar) = super::engine::engine(spec.threads, uses_onnx(&spec))?;
    engine.validate(&spec)?;
    out!("{}: valid ({} stages)", args.pipeline.display(), spec.stages.len())?;
    Ok(())
}
