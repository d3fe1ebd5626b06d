//! `r2d2 simulate`: an observation of a sky by a telescope of the registry (FITS or procedural) into a Parquet table.
//! Its `time` column is MJD seconds (UTC): configuration k observed on day k after
//! 2025-06-01, centred on the phase centre's transit (`simulate::epoch`).

use crate::fits::{read_image, write_image, BrightnessUnit, ImageWcs};
use crate::nufft::NufftParams;
use crate::imaging::PixelScale;
use crate::simulate::observe::ObservationRequest;
use crate::simulate::{simulate, SimulationOutput, SimulationRequest, SkyModel};
use crate::vis::write_parquet;
use crate::weighting::Weighting;
use crate::{Error, Result};
use std::path::PathBuf;

// The fields are named as the library's request names them (`frequency_ratio`), each with the
// option's own spelling (`--freq-ratio`): the library's errors name the field, which the
// command line then spells as the option (`spelled_as_options`).
#[derive(clap::Args)]
pub struct Args {
    /// Sky model: a FITS image (Jy/pixel), or `procedural[:SEED]` for a generated radio sky.
    #[arg(long, default_value = "procedural")]
    sky: String,
    /// Telescope (`data/telescopes/telescopes.yaml`: vla, meerkat, ska-mid). Its typical
    /// observation fills in every option of the observation not given.
    #[arg(long, default_value = "vla")]
    telescope: String,
    /// Array configurations, comma separated (vla: a, b, c, d; default a,c).
    #[arg(long = "configs", value_name = "CONFIGS", value_delimiter = ',')]
    configurations: Option<Vec<String>>,
    /// Observing time per configuration in hours, comma separated, one per configuration
    /// (vla: 6,2; meerkat: 8).
    #[arg(long, value_delimiter = ',')]
    hours: Option<Vec<f64>>,
    /// Declination of the phase centre, degrees (vla: 40; meerkat: -30).
    #[arg(long = "dec", value_name = "DEC", allow_hyphen_values = true)]
    dec_deg: Option<f64>,
    /// Right ascension of the phase centre, degrees.
    #[arg(long, default_value_t = 180.0)]
    ra: f64,
    /// Target dynamic range: fixes the noise level (reference formula).
    #[arg(long = "dr", value_name = "DR", default_value_t = 1e4)]
    dynamic_range: f64,
    /// Number of frequency channels (vla: 1; meerkat: 4).
    #[arg(long = "nfreq", value_name = "NFREQ")]
    channels: Option<usize>,
    /// Lowest frequency, MHz (vla: 1400; meerkat: 856).
    #[arg(long = "freq-mhz", value_name = "FREQ_MHZ")]
    frequency_mhz: Option<f64>,
    /// Highest over lowest frequency (vla: 1; meerkat: 2, L band 856..1712 MHz).
    #[arg(long = "freq-ratio", value_name = "FREQ_RATIO")]
    frequency_ratio: Option<f64>,
    /// Fraction of samples flagged at random.
    #[arg(long, default_value_t = 0.0)]
    flag_fraction: f64,
    /// Integration time, seconds (vla: 30; meerkat: 8).
    #[arg(long)]
    integration_s: Option<f64>,
    /// Do not rotate the uv coverage by a random angle. By default it is rotated (varying
    /// the PSF, as training does): the UVW then no longer follow from the antenna positions
    /// and times that `r2d2 convert` writes into an MS (the metadata's `uv_rotation_deg` says
    /// by how much), which matters to tools that recompute UVW; give --no-rotation for
    /// geometrically consistent data.
    #[arg(long)]
    no_rotation: bool,
    /// Raise a FITS sky's dynamic range to --dr by exponentiation (Terris et al. 2022).
    #[arg(long)]
    exponentiate: bool,
    /// Image size of a procedural sky, pixels.
    #[arg(long, default_value_t = 512)]
    size: usize,
    /// Super-resolution factor fixing the sky's pixel (unless the FITS sky has a pixel size
    /// or --pixel-arcsec is given).
    #[arg(long, default_value_t = 1.5)]
    superresolution: f64,
    /// Pixel size of the sky, arcsec.
    #[arg(long)]
    pixel_arcsec: Option<f64>,
    /// Weighting the noise level is computed for (natural, uniform, briggs).
    #[arg(long, default_value = "briggs")]
    weighting: String,
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    robust: f64,
    /// NUFFT accuracy.
    #[arg(long, default_value_t = 1e-6)]
    epsilon: f64,
    /// Random seed: the same seed gives the same file.
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Threads (0: all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Output Parquet file. Its `time` column is MJD seconds (UTC): configuration k is
    /// observed on day k after 2025-06-01, its track centred on the phase centre's transit.
    #[arg(long)]
    out: PathBuf,
}

enum SkySource {
    Procedural(u64),
    File(PathBuf),
}

fn parse_sky(text: &str, seed: u64) -> Result<SkySource> {
    match text.split_once(':') {
        _ if text == "procedural" => Ok(SkySource::Procedural(seed)),
        Some(("procedural", s)) => s
            .parse()
            .map(SkySource::Procedural)
            .map_err(|_| Error::parameter("sky", format!("expected procedural:SEED with an integer seed, got '{text}'"))),
        _ => Ok(SkySource::File(PathBuf::from(text))),
    }
}

pub fn run(args: Args) -> Result<()> {
    // The output and the observation before any work (reading the sky, simulating).
    crate::fits::check_output_file(&args.out, false).map_err(|m| Error::parameter("--out", m))?;
    let spec = ObservationRequest {
        telescope: args.telescope.clone(),
        configurations: args.configurations.clone(),
        hours: args.hours.clone(),
        dec_deg: args.dec_deg,
        integration_s: args.integration_s,
        channels: args.channels,
        frequency_mhz: args.frequency_mhz,
        frequency_ratio: args.frequency_ratio,
        flag_fraction: args.flag_fraction,
        random_rotation: !args.no_rotation,
        seed: args.seed,
    }
    .spec()?;
    let dec = spec.dec_deg;
    let noise_weighting = Weighting::from_name(&args.weighting, args.robust)?;
    let source = parse_sky(&args.sky, args.seed)?;
    if let SkySource::Procedural(_) = source {
        crate::fits::check_output_file(&sky_path(&args.out), true).map_err(|m| Error::parameter("--out", format!("the sky model beside it: {m}")))?;
    }
    let sky = match &source {
        SkySource::Procedural(seed) => SkyModel::Procedural { seed: *seed },
        SkySource::File(path) => {
            let image = read_image(path)?;
            if image.nx != image.ny {
                return Err(Error::input(path, format!("expected a square sky image, got {} x {}", image.nx, image.ny)));
            }
            SkyModel::Image {
                data: image.data,
                size: image.nx,
                pixel_rad: image.wcs.map(|w| w.pixel_deg.to_radians()),
                exponentiate: args.exponentiate,
            }
        }
    };
    crate::vis::check_phase_centre(args.ra, dec, ["ra", "dec_deg"])?;
    let request = SimulationRequest {
        observation: spec.clone(),
        sky,
        size: args.size,
        pixel: match args.pixel_arcsec {
            Some(p) => PixelScale::Arcsec(p),
            None => PixelScale::SuperResolution(args.superresolution),
        },
        dynamic_range: args.dynamic_range,
        noise_weighting,
        phase_centre_deg: (args.ra, dec),
        nufft: NufftParams { epsilon: args.epsilon, oversampling: 2.0 },
        threads: args.threads,
    };
    let SimulationOutput { table, meta, sky, geometry } = simulate(&request)?;
    log::info!(
        "{} visibilities ({} configurations x {} channels), {} x {} sky at {:.4} arcsec, noise sigma {:.4e} Jy",
        table.len(),
        spec.configurations.len(),
        spec.frequencies_hz.len(),
        geometry.size,
        geometry.size,
        geometry.pixel_arcsec(),
        meta.noise_sigma.unwrap_or(0.0)
    );
    write_parquet(&args.out, &table, &meta)?;
    log::info!("wrote {}", args.out.display());

    if let SkySource::Procedural(_) = source {
        let sky_path = sky_path(&args.out);
        let wcs = ImageWcs {
            ra_deg: args.ra,
            dec_deg: dec,
            pixel_deg: geometry.pixel_rad.to_degrees(),
            freq_hz: Some(spec.frequencies_hz.iter().sum::<f64>() / spec.frequencies_hz.len() as f64),
            bandwidth_hz: None,
        };
        write_image(&sky_path, &sky, geometry.size, geometry.size, &wcs, BrightnessUnit::JyPerPixel, None, &[])?;
        log::info!("wrote the sky model to {}", sky_path.display());
    }
    Ok(())
}

/// Where a procedural sky is written: beside the table, `obs.parquet` -> `obs.sky.fits`.
fn sky_path(out: &std::path::Path) -> PathBuf {
    out.with_extension("sky.fits")
}
