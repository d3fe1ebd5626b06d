//! `r2d2 metrics`: SNR and logSNR of an estimate against the truth.

use crate::fits::read_image;
use crate::metrics::{dynamic_range, log_snr, snr};
use crate::{Error, Result};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Ground-truth image (FITS).
    #[arg(long)]
    truth: PathBuf,
    /// Estimated image (FITS), same size.
    #[arg(long)]
    estimate: PathBuf,
    /// Dynamic range for logSNR (default: the truth's peak over its faintest positive pixel).
    #[arg(long)]
    dr: Option<f64>,
}

pub fn run(args: Args) -> Result<()> {
    let truth = read_image(&args.truth)?;
    let estimate = read_image(&args.estimate)?;
    if (truth.nx, truth.ny) != (estimate.nx, estimate.ny) {
        return Err(Error::input(
            &args.estimate,
            format!("image is {} x {}, the truth {} is {} x {}", estimate.nx, estimate.ny, args.truth.display(), truth.nx, truth.ny),
        ));
    }
    let dr = match args.dr {
        Some(dr) if dr > 1.0 => dr,
        Some(dr) => return Err(Error::parameter("dr", format!("expected a dynamic range > 1, got {dr}"))),
        None => dynamic_range(&truth.data)
            .filter(|dr| *dr > 1.0)
            .ok_or_else(|| Error::input(&args.truth, "the truth has no positive emission below its peak; pass --dr"))?,
    };
    let report = serde_json::json!({
        "snr": snr(&estimate.data, &truth.data),
        "logsnr": log_snr(&estimate.data, &truth.data, dr),
        "dynamic_range": dr,
    });
    out!("{report}")?;
    Ok(())
}
