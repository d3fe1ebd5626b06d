//! Synthetic data for training and testing: procedural ground-truth skies (`sky`) and
//! Earth-rotation uv coverage from real antenna layouts (`telescope`).
//!
//! Like the other numerical modules these know nothing of files or configuration: the
//! antenna tables are compiled into the binary, and every random choice comes from a
//! caller-supplied seed so a data set can be regenerated bit for bit.

pub(crate) mod epoch;
pub(crate) mod extended;
pub(crate) mod observe;
pub(crate) mod sky;
pub(crate) mod telescope;
pub(crate) mod trainset;

pub use observe::{frequency_channels, sample_coverage, ObservationSpec};

use crate::imaging::PixelScale;
use crate::nufft::NufftParams;
use crate::operator::{ImageGeometry, WTermMode};
use crate::vis::{ObservationMeta, VisTable, CONFIGURATIONS_KEY, INTEGRATION_KEY, ROTATION_KEY};
use crate::weighting::Weighting;
use crate::{metrics, Error, Result};
use observe::{simulate_visibilities, NoiseModel};
use std::collections::BTreeMap;

/// The sky of a simulation.
#[derive(Clone, Debug)]
pub enum SkyModel {
    /// A procedural radio sky of the requested size and dynamic range, from a seed.
    Procedural { seed: u64 },
    /// A given image (Jy/pixel), square, with its pixel size if it has one.
    Image { data: Vec<f64>, size: usize, pixel_rad: Option<f64>, exponentiate: bool },
}

/// Everything a simulated observation depends on.
#[derive(Clone, Debug)]
pub struct SimulationRequest {
    pub observation: ObservationSpec,
    pub sky: SkyModel,
    /// Size of a procedural sky.
    pub size: usize,
    /// Pixel scale when the sky image does not fix it.
    pub pixel: PixelScale,
    pub dynamic_range: f64,
    /// Weighting the noise level is defined for (eta).
    pub noise_weighting: Weighting,
    pub phase_centre_deg: (f64, f64),
    pub nufft: NufftParams,
    pub threads: usize,
}

/// A simulated data set and the sky it came from.
pub struct SimulationOutput {
    pub table: VisTable,
    pub meta: ObservationMeta,
    pub sky: Vec<f64>,
    pub geometry: ImageGeometry,
}

/// Simulate the observation: coverage, sky on its pixel grid, visibilities with noise. The
/// table's times are dated as a real observation's (MJD seconds, UTC; [`epoch`]: configuration
/// `k` on day `k` after 2025-06-01, centred on transit), its metadata name the configurations
/// and integration time (`r2d2 convert` writes the antennas and INTERVAL from them) and the
/// coverage's random rotation.
pub fn simulate(req: &SimulationRequest) -> Result<SimulationOutput> {
    crate::vis::check_phase_centre(req.phase_centre_deg.0, req.phase_centre_deg.1, ["phase_centre_deg", "phase_centre_deg"])?;
    crate::limits::check_image_size(req.size).map_err(|m| Error::parameter("size", m))?;
    crate::limits::check_threads(req.threads).map_err(|m| Error::parameter("threads", m))?;
    let coverage = sample_coverage(&req.observation)?;
    let geometry_for = |size: usize| req.pixel.geometry(size, coverage.max_uv());
    let (sky, geometry) = match &req.sky {
        SkyModel::Procedural { seed } => {
            (sky::procedural_sky(&sky::SkyParams::new(req.size, req.dynamic_range, *seed))?, geometry_for(req.size)?)
        }
        SkyModel::Image { data, size, pixel_rad, exponentiate } => {
            if data.iter().any(|&p| p < 0.0) {
                return Err(Error::parameter("sky", "a sky model must be non-negative (intensity)"));
            }
            let geometry = match (req.pixel, pixel_rad) {
                (PixelScale::Arcsec(_), _) | (_, None) => geometry_for(*size)?,
                (_, Some(p)) => ImageGeometry::new(*size, *p)?,
            };
            let mut sky = data.clone();
            if *exponentiate {
                let source_dr = metrics::dynamic_range(&sky)
                    .ok_or_else(|| Error::parameter("sky", "no positive emission to exponentiate"))?;
                sky::exponentiate(&mut sky, source_dr, req.dynamic_range)?;
            }
            (sky, geometry)
        }
    };
    let model = NoiseModel {
        dynamic_range: req.dynamic_range,
        weighting: req.noise_weighting,
        grid_factor: crate::weighting::DEFAULT_GRID_FACTOR,
    };
    let seed = req.observation.seed;
    let sim = simulate_visibilities(&sky, geometry, &coverage, &model, WTermMode::Auto, req.nufft, req.threads, seed)?;
    log::debug!("noise sigma {:.4e} Jy per visibility (eta {:.4})", sim.noise_sigma, sim.eta);
    let weight = 1.0 / (sim.noise_sigma * sim.noise_sigma);
    let n = coverage.len();
    let time = coverage.utc_times(req.phase_centre_deg.0);
    let configurations: Vec<&str> = coverage.tracks.iter().map(|t| t.configuration.as_str()).collect();
    let mut extra = BTreeMap::new();
    extra.insert(CONFIGURATIONS_KEY.into(), configurations.join(","));
    extra.insert(INTEGRATION_KEY.into(), req.observation.integration_s.to_string());
    extra.insert(ROTATION_KEY.into(), coverage.rotation_rad.to_degrees().to_string());
    let table = VisTable {
        u_m: coverage.u_m,
        v_m: coverage.v_m,
        w_m: coverage.w_m,
        frequency: coverage.frequency_hz,
        vis: sim.vis,
        weight: vec![weight; n],
        flag: coverage.flag,
        time,
        antenna1: coverage.antenna1,
        antenna2: coverage.antenna2,
    };
    extra.insert("simulation_seed".into(), seed.to_string());
    extra.insert("sky_pixel_arcsec".into(), format!("{}", geometry.pixel_arcsec()));
    extra.insert("sky_size".into(), geometry.size.to_string());
    extra.insert("noise_weighting".into(), model.weighting.to_string());
    let meta = ObservationMeta {
        phase_centre_ra_deg: req.phase_centre_deg.0,
        phase_centre_dec_deg: req.phase_centre_deg.1,
        telescope: telescope::telescope(&req.observation.telescope)?.name.clone(),
        noise_sigma: Some(sim.noise_sigma),
        dynamic_range: Some(req.dynamic_range),
        extra,
    };
    Ok(SimulationOutput { table, meta, sky, geometry })
}
