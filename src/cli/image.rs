//! `r2d2 image`: the default imaging pipeline (`pipelines/image.yaml`, compiled in) on one
//! Parquet file, without writing YAML.

use super::ImageOptions;
use r2d2_imaging::pipeline::config::PipelineConfig;
use r2d2_imaging::{Error, Result};
use std::path::{Path, PathBuf};

const IMAGE_PIPELINE: &str = include_str!("../../pipelines/image.yaml");

#[derive(clap::Args)]
pub struct Args {
    /// Visibilities (Parquet).
    input: PathBuf,
    #[command(flatten)]
    image: ImageOptions,
    /// Network step: `clean` (built in).
    #[arg(long, default_value = "clean")]
    step: String,
    /// Iterations of the step (CLEAN major cycles).
    #[arg(long, default_value_t = 5)]
    iterations: usize,
    /// Ground truth (FITS) for SNR/logSNR per iteration.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Output prefix (WSClean's -name).
    #[arg(long, default_value = "r2d2")]
    name: String,
}

pub fn run(args: Args) -> Result<()> {
    if args.step != "clean" {
        return Err(Error::parameter("step", format!("expected clean (the built-in step), got '{}'", args.step)));
    }
    let quote = |p: &Path| serde_json::to_string(&p.to_string_lossy()).expect("strings serialise");
    let mut set = vec![
        format!("read.files={}", quote(&args.input)),
        format!("image.size={}", args.image.size),
        format!("weights.scheme={}", args.image.weighting),
        format!("weights.robust={}", args.image.robust),
        format!("weights.grid_factor={}", args.image.weighting_grid_factor),
        format!("grid.epsilon={}", args.image.epsilon),
        format!("grid.oversampling={}", args.image.oversampling),
        format!("step.major_cycles={}", args.iterations),
        format!("write.prefix={}", quote(Path::new(&args.name))),
        format!("threads={}", args.image.threads),
    ];
    match args.image.pixel_arcsec {
        Some(p) => set.push(format!("image.pixel_arcsec={p}")),
        None => set.push(format!("image.superresolution={}", args.image.superresolution)),
    }
    if let Some(t) = &args.truth {
        set.push(format!("read.truth={}", quote(t)));
    }
    let config = PipelineConfig::parse(IMAGE_PIPELINE, Path::new("pipelines/image.yaml"), &set)?;
    super::run::run_pipeline(&config)
}
