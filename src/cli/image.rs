//! `r2d2 image`: the default imaging pipeline (`pipelines/image.yaml`, compiled in) on one
//! Parquet file, without writing YAML.

use super::ImageOptions;
use r2d2_imaging::pipeline::config::PipelineConfig;
use r2d2_imaging::steps::series::{resolve, AUTO_SERIES};
use r2d2_imaging::{Error, Result};
use std::path::{Path, PathBuf};

const IMAGE_PIPELINE: &str = include_str!("../../pipelines/image.yaml");

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
    /// ONNX Runtime graph optimisation: extended (least memory) or all (faster inference:
    /// weights copied into a blocked layout, larger activations).
    #[arg(long, default_value = "extended", value_parser = ["extended", "all"])]
    graph_optimization: String,
    /// Ground truth (FITS) for SNR/logSNR per iteration.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Output prefix (WSClean's -name).
    #[arg(long, default_value = "r2d2")]
    name: String,
}

/// The `step` stage of the image pipeline for `--step`.
fn step_stage(args: &Args) -> Result<serde_yaml::Value> {
    let yaml = |s: &str| serde_yaml::from_str::<serde_yaml::Value>(s).expect("literal YAML");
    let path = Path::new(&args.step);
    let is_library = matches!(path.extension().and_then(|e| e.to_str()), Some("so" | "dylib" | "dll"));
    if args.plugin_config.is_some() && !is_library {
        return Err(Error::parameter("plugin-config", format!("only a native plugin takes a configuration; --step is '{}'", args.step)));
    }
    if args.step == "clean" {
        let cycles = args.iterations.unwrap_or(5);
        return Ok(yaml(&format!("{{kind: clean, major_cycles: {cycles}, to: update}}")));
    }
    if !is_library {
        // `auto` is resolved by the step, which knows the image size.
        let series = if args.step == AUTO_SERIES { path.to_path_buf() } else { resolve(path)? };
        let mut stage = yaml("{kind: onnx, to: update}");
        stage["series"] = serde_yaml::Value::String(series.to_string_lossy().into_owned());
        stage["backend"] = serde_yaml::Value::String(args.backend.clone());
        if let Some(n) = args.iterations {
            stage["networks"] = n.into();
        }
        if args.no_prefetch {
            stage["prefetch"] = false.into();
        }
        stage["graph_optimization"] = serde_yaml::Value::String(args.graph_optimization.clone());
        return Ok(stage);
    }
    let mut stage = yaml("{kind: native, to: update}");
    stage["library"] = serde_yaml::Value::String(path.to_string_lossy().into_owned());
    stage["iterations"] = args.iterations.unwrap_or(10).into();
    if let Some(text) = &args.plugin_config {
        let config: serde_yaml::Value =
            serde_yaml::from_str(text).map_err(|e| Error::parameter("plugin-config", format!("expected a YAML or JSON mapping: {e}")))?;
        stage["config"] = config;
    }
    Ok(stage)
}

/// The `read` stage for a MeasurementSet input: `kind: ms` with the MS options.
fn ms_read_stage(args: &Args) -> Result<serde_yaml::Value> {
    #[cfg(feature = "ms")]
    {
        let mut stage = serde_yaml::from_str::<serde_yaml::Value>("{kind: ms, path: obs.ms, to: weights}").expect("literal YAML");
        args.ms.stage_keys(&mut stage);
        Ok(stage)
    }
    #[cfg(not(feature = "ms"))]
    Err(Error::input(&args.input, "a MeasurementSet, but this r2d2 was built without the `ms` feature"))
}

pub fn run(args: Args) -> Result<()> {
    let mut pipeline: serde_yaml::Value = serde_yaml::from_str(IMAGE_PIPELINE).expect("the compiled-in pipeline is valid YAML");
    pipeline["stages"]["step"] = step_stage(&args)?;
    let ms_input = super::convert::is_ms(&args.input);
    if ms_input {
        pipeline["stages"]["read"] = ms_read_stage(&args)?;
    } else if args.model_column.is_some() {
        return Err(Error::parameter("model-column", format!("{}: only a MeasurementSet input has a column to write the model into", args.input.display())));
    }
    let text = serde_yaml::to_string(&pipeline).expect("YAML serialises");
    let quote = |p: &Path| serde_json::to_string(&p.to_string_lossy()).expect("strings serialise");
    let mut set = vec![
        format!("read.{}={}", if ms_input { "path" } else { "files" }, quote(&args.input)),
        format!("image.size={}", args.image.size),
        format!("weights.scheme={}", args.image.weighting),
        format!("weights.robust={}", args.image.robust),
        format!("weights.grid_factor={}", args.image.weighting_grid_factor),
        format!("grid.epsilon={}", args.image.epsilon),
        format!("grid.oversampling={}", args.image.oversampling),
        format!("write.prefix={}", quote(Path::new(&args.name))),
        format!("threads={}", args.image.threads),
    ];
    match args.image.pixel_arcsec {
        Some(p) => set.push(format!("image.pixel_arcsec={p}")),
        None => set.push(format!("image.superresolution={}", args.image.superresolution)),
    }
    if let Some(column) = &args.model_column {
        set.push(format!("write.model_column={}", serde_json::to_string(column).expect("strings serialise")));
    }
    if let Some(t) = &args.truth {
        set.push(format!("read.truth={}", quote(t)));
    }
    let config = PipelineConfig::parse(&text, Path::new("pipelines/image.yaml"), &set)?;
    super::run::run_pipeline(&config)
}
