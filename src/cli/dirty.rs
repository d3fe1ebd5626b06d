//! `r2d2 dirty`: dirty image and PSF, named like WSClean's products.

use crate::fits::{header_text, write_image, BrightnessUnit, ImageWcs};
use crate::imaging::dirty_image;
use crate::staging::Staging;
use crate::Result;
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct Args {
    /// Visibilities (Parquet, one row per sample) or a MeasurementSet.
    input: PathBuf,
    #[command(flatten)]
    image: crate::GridOptions,
    #[command(flatten)]
    ms: crate::MsOptions,
    /// Output prefix: writes PREFIX-dirty.fits and PREFIX-psf.fits.
    #[arg(long, default_value = "r2d2")]
    name: String,
}

pub fn run(args: Args) -> Result<()> {
    crate::fits::check_output_prefix(&args.name).map_err(|m| crate::Error::parameter("--name", m))?;
    // Refused before any work: a product that would replace the input, or land inside an
    // input MeasurementSet, as `r2d2 image` refuses.
    for suffix in ["dirty", "psf"] {
        let target = PathBuf::from(format!("{}-{suffix}.fits", args.name));
        if let Some(input) = crate::staging::destroys_input(&target, &[args.input.as_path()]) {
            return Err(crate::Error::parameter(
                "--name",
                format!("the product {} would replace or lie inside the input {}: choose another output name", target.display(), input.display()),
            ));
        }
    }
    let params = args.image.dirty_params()?;
    let (vis, meta, stats) = super::convert::read_input(&args.input, &args.ms)?;
    stats.log(&args.input);
    let products = dirty_image(&vis, &params)?;
    let geometry = products.operator.geometry();
    let w_term = crate::imaging::WTerm::of(&vis, geometry);
    match products.operator.w_planes() {
        Some(planes) => log::info!(
            "{}: the w-term is corrected by w-gridding ({planes} w-planes; up to {:.3} rad at the field's corners)",
            args.input.display(),
            w_term.max_phase_rad
        ),
        None => {
            if let Some(warning) = w_term.warning(geometry) {
                log::warn!("{}: {warning} (--w-term off)", args.input.display());
            }
        }
    }
    log::info!(
        "{} x {} image, {:.4} arcsec pixels, {} weighting",
        geometry.size,
        geometry.size,
        geometry.pixel_arcsec(),
        params.weighting
    );
    let wcs = ImageWcs {
        ra_deg: meta.phase_centre_ra_deg,
        dec_deg: meta.phase_centre_dec_deg,
        pixel_deg: geometry.pixel_rad.to_degrees(),
        freq_hz: vis.band().map(|(centre, _)| centre),
        bandwidth_hz: vis.band().and_then(|(_, width)| width),
    };
    let n = geometry.size;
    let (telescope, changed) = header_text(&meta.telescope);
    if let Some(note) = changed {
        log::warn!("{}: TELESCOP: {note}", args.input.display());
    }
    // Both products or neither, in a directory made if need be (as the writer stage does).
    let prefix = PathBuf::from(&args.name);
    let dir = prefix.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let mut staging = Staging::new(dir)?;
    for (suffix, image) in [("dirty", &products.dirty), ("psf", &products.psf)] {
        let path = PathBuf::from(format!("{}-{suffix}.fits", args.name));
        let extra = [("TELESCOP", telescope.clone())];
        staging.write(path, |staged| write_image(staged, image, n, n, &wcs, BrightnessUnit::JyPerBeam, None, &extra))?;
    }
    let written: Vec<String> = staging.targets().map(|p| p.display().to_string()).collect();
    staging.commit()?;
    log::info!("wrote {}", written.join(", "));
    Ok(())
}
