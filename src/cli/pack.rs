//! `r2d2 pack`: move the weights of a series' networks into side files that ONNX Runtime maps
//! instead of copying (`steps::pack`).

use r2d2_imaging::steps::pack::{pack_file, MIN_EXTERNAL_BYTES};
use r2d2_imaging::steps::runtime::weight_layout;
use r2d2_imaging::steps::series::{resolve, Series};
use r2d2_imaging::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Series directories, series names (looked up like `--step`), or single .onnx files.
    #[arg(required = true)]
    targets: Vec<PathBuf>,
    /// Move weights of at least this many bytes; smaller ones (biases, norm scales) stay inline.
    #[arg(long, default_value_t = MIN_EXTERNAL_BYTES)]
    min_bytes: usize,
}

pub fn run(args: Args) -> Result<()> {
    for target in &args.targets {
        let files: Vec<PathBuf> = if target.is_file() {
            vec![target.clone()]
        } else {
            Series::open(&resolve(target)?)?.files.into_iter().flatten().collect()
        };
        for file in files {
            let started = std::time::Instant::now();
            let packed = pack_file(&file, args.min_bytes)?;
            // Read back what was written: the side file holds every weight the model names.
            let (external, model) = weight_layout(&file)?;
            let mb = |b: u64| b as f64 / (1 << 20) as f64;
            match packed.data_file {
                Some(data) => println!(
                    "{}: {} weights ({:.1} MiB) moved to {} in {:.2} s; the model file is now {:.2} MiB",
                    file.display(),
                    packed.tensors,
                    mb(packed.bytes),
                    data.display(),
                    started.elapsed().as_secs_f64(),
                    mb(model)
                ),
                None => println!("{}: nothing to move ({:.1} MiB of weights already in side files, {:.2} MiB inline)", file.display(), mb(external), mb(model)),
            }
        }
    }
    Ok(())
}
