//! `kind: simulate`: simulated VLA observations of procedural skies (one job per seed), with
//! the true sky attached so the run reports SNR and logSNR.

use crate::nufft::NufftParams;
use crate::pipeline::config::ImageConfig;
use crate::pipeline::{Job, Source, StageParams};
use crate::simulate::observe::{frequency_channels, ObservationSpec};
use crate::simulate::{simulate, SimulationRequest, SkyModel};
use crate::weighting::{Weighting, WeightingScheme};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// `kind: simulate`: simulated VLA observations of procedural skies.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimulateParams {
    /// Number of jobs (seeds `seed`, `seed + 1`, ...); default 1.
    pub jobs: usize,
    /// Default 7.
    pub seed: u64,
    /// Of the procedural sky; default 1e4.
    pub dynamic_range: f64,
    /// VLA configurations; default `[a, c]`.
    pub configurations: Vec<char>,
    /// Hours per configuration; default `[6, 2]`.
    pub hours: Vec<f64>,
    /// Phase centre; default (180, 40) degrees.
    pub dec_deg: f64,
    pub ra_deg: f64,
    /// Seconds per sample; default 30.
    pub integration_s: f64,
    /// Frequency channels; default 1, at 1400 MHz.
    pub channels: usize,
    pub frequency_mhz: f64,
    /// Highest to lowest channel frequency; default 1.
    pub frequency_ratio: f64,
    /// Fraction of the samples flagged; default 0.
    pub flag_fraction: f64,
    /// Weighting the noise level is defined for; default Briggs, robust 0.
    pub noise_weighting: WeightingScheme,
    pub robust: f64,
}

impl Default for SimulateParams {
    fn default() -> Self {
        SimulateParams {
            jobs: 1,
            seed: 7,
            dynamic_range: 1e4,
            configurations: vec!['a', 'c'],
            hours: vec![6.0, 2.0],
            dec_deg: 40.0,
            ra_deg: 180.0,
            integration_s: 30.0,
            channels: 1,
            frequency_mhz: 1400.0,
            frequency_ratio: 1.0,
            flag_fraction: 0.0,
            noise_weighting: WeightingScheme::Briggs,
            robust: 0.0,
        }
    }
}

impl StageParams for SimulateParams {
    const KIND: &'static str = "simulate";
}

pub struct SimulateSource {
    config: SimulateParams,
    image: ImageConfig,
    weighting: Weighting,
    threads: usize,
}

impl SimulateSource {
    pub fn new(config: SimulateParams, image: &ImageConfig, threads: usize) -> Result<SimulateSource> {
        if config.configurations.len() != config.hours.len() {
            return Err(Error::parameter(
                "hours",
                format!("one observing time per configuration: {} configurations, {} times", config.configurations.len(), config.hours.len()),
            ));
        }
        crate::vis::check_phase_centre(config.ra_deg, config.dec_deg)?;
        if config.jobs == 0 {
            return Err(Error::parameter("jobs", "expected at least one job"));
        }
        let weighting = config.noise_weighting.with_robust(config.robust)?;
        frequency_channels(config.frequency_mhz * 1e6, config.channels, config.frequency_ratio)?;
        Ok(SimulateSource { config, image: image.clone(), weighting, threads })
    }
}

impl Source for SimulateSource {
    fn produce(&mut self, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()> {
        let c = &self.config;
        for k in 0..c.jobs as u64 {
            if cancelled() {
                break;
            }
            let seed = c.seed + k;
            let request = SimulationRequest {
                observation: ObservationSpec {
                    configurations: c.configurations.iter().copied().zip(c.hours.iter().copied()).collect(),
                    dec_deg: c.dec_deg,
                    integration_s: c.integration_s,
                    frequencies_hz: frequency_channels(c.frequency_mhz * 1e6, c.channels, c.frequency_ratio)?,
                    flag_fraction: c.flag_fraction,
                    random_rotation: true,
                    seed,
                },
                sky: SkyModel::Procedural { seed },
                size: self.image.size,
                pixel: self.image.pixel_scale(),
                dynamic_range: c.dynamic_range,
                noise_weighting: self.weighting,
                phase_centre_deg: (c.ra_deg, c.dec_deg),
                nufft: NufftParams::default(),
                threads: self.threads,
            };
            let out = simulate(&request)?;
            let id = format!("sim-{seed}");
            let (vis, stats) = out.table.to_visibilities(&id)?;
            log::info!("job {id}: simulated {stats}");
            let mut job = Job::new(id, out.meta, vis);
            job.truth_dynamic_range = crate::metrics::dynamic_range(&out.sky);
            job.truth = Some(out.sky);
            emit(job)?;
        }
        Ok(())
    }
}
