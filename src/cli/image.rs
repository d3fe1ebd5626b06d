//! `r2d2 image`: the default imaging pipeline (the one `pipelines/image.yaml` writes out) on
//! one observation, through `Engine::image`; its options are the library's `ImageRequest`.

use crate::{ImageRequest, Result};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Visibilities (Parquet) or a MeasurementSet.
    input: PathBuf,
    #[command(flatten)]
    request: ImageRequest,
}

/// Runs `r2d2 image`; true where the products were written but the divergence guard rejected
/// the step's model (the job kept an earlier iterate or the empty model, or after a series
/// the final CLEAN imaged the data from the empty model): the command then
/// exits with [`super::EXIT_MODEL_REJECTED`], so that a pipeline step can tell.
pub fn run(args: Args) -> Result<bool> {
    let mut request = args.request;
    request.name.get_or_insert_with(|| super::DEFAULT_NAME.to_string());
    let onnx = request.step.runs_a_series() && request.step.backend != crate::BackendChoice::Tract;
    let (engine, _bar) = super::engine::engine(request.grid.threads, onnx)?;
    let engine = engine.with_cancel(super::run::cancel_on_ctrl_c());
    let rejected = |p: &crate::JobProducts| p.stop.as_ref().is_some_and(|s| s.reason.is_rejection());
    if request.ms.channels_out.is_some_and(|n| n > 1) {
        let groups = engine.image_channels(args.input.as_path(), &request)?;
        return Ok(groups.channels.iter().chain(&groups.mfs).any(rejected));
    }
    let products = engine.image(args.input.as_path(), &request)?;
    Ok(rejected(&products))
}
