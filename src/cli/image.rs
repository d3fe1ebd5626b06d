//! `r2d2 image`: the default imaging pipeline (the one `pipelines/image.yaml` writes out) on
//! one observation, through `Engine::image`.

use super::ImageOptions;
use r2d2_imaging::steps::series::AUTO_SERIES;
use r2d2_imaging::{BackendChoice, CleanControls, Error, ImageParams, Result, StepChoice};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Visibilities (Parquet) or a MeasurementSet.
    input: PathBuf,
    #[command(flatten)]
    image: ImageOptions,
    #[command(flatten)]
    ms: super::convert::MsOptions,
    /// MS input: predict the final model's visibilities into this column of the MS (e.g.
    /// MODEL_DATA; created when missing).
    #[arg(long)]
    model_column: Option<String>,
    /// Network step: `auto` (the series trained for the image size, see `r2d2 models`), a model
    /// series (a name from `r2d2 models`, or its directory), `clean` (the built-in Hogbom
    /// CLEAN), or a native plugin library (`.so`, `.dylib`, `.dll`).
    #[arg(long, default_value = AUTO_SERIES)]
    step: String,
    /// Iterations of the step: CLEAN major cycles (default 5), the first networks of a series
    /// (default: all), or the steps of a native plugin (default 10).
    #[arg(long)]
    iterations: Option<usize>,
    /// CLEAN (--step clean): most components over all major cycles, as WSClean's -niter
    /// (with it, up to 20 major cycles unless --iterations says otherwise).
    #[arg(long)]
    niter: Option<usize>,
    /// CLEAN: minor-cycle loop gain, as WSClean's -gain (default 0.1).
    #[arg(long)]
    gain: Option<f64>,
    /// CLEAN: the fraction of the peak each major cycle cleans away, as WSClean's -mgain (default 0.8; 1: no limit).
    #[arg(long)]
    mgain: Option<f64>,
    /// CLEAN: stop at this many times the residual's noise, as WSClean's -auto-threshold (default 3; 0: none).
    #[arg(long)]
    auto_threshold: Option<f64>,
    /// CLEAN: stop below this residual peak in Jy/beam, as WSClean's -threshold.
    #[arg(long)]
    threshold: Option<f64>,
    /// Configuration of a native plugin, a YAML/JSON mapping (e.g. '{gain: 0.1}').
    #[arg(long)]
    plugin_config: Option<String>,
    /// ONNX inference backend for a series: auto (native ONNX Runtime if found), ort, tract.
    #[arg(long, default_value = "auto")]
    backend: String,
    /// Load each network of a series only when it runs, not while the previous one infers
    /// (one network resident instead of two; loading then adds to the wall time).
    #[arg(long)]
    no_prefetch: bool,
    /// A series' model as the networks leave it: no final CLEAN cycles on its residual (which
    /// otherwise give compact sources the fluxes the data measure).
    #[arg(long)]
    no_final_clean: bool,
    /// ONNX Runtime graph optimisation: auto (all for small networks, extended for large
    /// ones), extended (least memory) or all (faster inference: weights copied into a blocked
    /// layout, larger activations).
    #[arg(long, default_value = "auto", value_parser = ["auto", "extended", "all"])]
    graph_optimization: String,
    /// Ground truth (FITS) for SNR/logSNR per iteration.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Output prefix (WSClean's -name).
    #[arg(long, default_value = "r2d2")]
    name: String,
    /// Most memory (MB) the samples may take held in memory where the residual update needs
    /// them (the w-term); above it they are read again from the file at each update (or only
    /// for the kernels and the final residual where a Taylor series in w replaces the operator).
    #[arg(long, default_value_t = r2d2_imaging::params::DEFAULT_HOLD_MB)]
    hold_mb: f64,
}

/// `r2d2 image`'s options as the engine's parameters.
fn image_params(args: &Args) -> Result<ImageParams> {
    let image = &args.image;
    Ok(ImageParams {
        size: image.size,
        superresolution: image.superresolution,
        pixel_arcsec: image.pixel_arcsec,
        longest_baseline: None,
        weighting: image.weighting()?,
        weighting_grid_factor: image.weighting_grid_factor,
        epsilon: image.epsilon,
        oversampling: image.oversampling,
        w_term: image.w_term,
        hold_mb: args.hold_mb,
        step: StepChoice::parse(&args.step, args.plugin_config.as_deref())?,
        iterations: args.iterations,
        clean: CleanControls { niter: args.niter, gain: args.gain, mgain: args.mgain, auto_threshold: args.auto_threshold, threshold: args.threshold },
        backend: args.backend.parse()?,
        prefetch: !args.no_prefetch,
        final_clean: !args.no_final_clean,
        graph_optimization: args.graph_optimization.parse()?,
        truth: args.truth.clone(),
        write: Some(args.name.clone()),
        model_column: args.model_column.clone(),
        #[cfg(feature = "ms")]
        ms: Some(args.ms.selection()),
    })
}

/// Runs `r2d2 image`; true where the products were written but the divergence guard rejected
/// the step's model (the job kept an earlier iterate or the empty model): the command then
/// exits with [`super::EXIT_MODEL_REJECTED`], so that a pipeline step can tell.
pub fn run(args: Args) -> Result<bool> {
    let params = image_params(&args)?;
    let onnx = matches!(params.step, StepChoice::Auto | StepChoice::Series(_)) && params.backend != BackendChoice::Tract;
    let (engine, _bar) = super::engine::engine(image_threads(&args)?, onnx)?;
    let engine = engine.with_cancel(super::run::cancel_on_ctrl_c());
    let products = engine.image(args.input.as_path(), &params)?;
    Ok(products.stop.as_ref().is_some_and(|s| s.reason.is_rejection()))
}

/// `--threads`, checked.
fn image_threads(args: &Args) -> Result<usize> {
    r2d2_imaging::limits::check_threads(args.image.threads).map_err(|m| Error::parameter("threads", m))?;
    Ok(args.image.threads)
}
