//! `kind: simulate`: simulated observations of procedural skies (one job per seed), with
//! the true sky attached so the run reports SNR and logSNR.

use super::params::SimulateParams;
use crate::nufft::NufftParams;
use crate::imaging::ImageConfig;
use crate::job::Job;
use crate::pipeline::Source;
use crate::simulate::observe::{ObservationRequest, ObservationSpec};
use crate::simulate::{simulate, SimulationRequest, SkyModel};
use crate::weighting::Weighting;
use crate::{Error, Result};

pub struct SimulateSource {
    config: SimulateParams,
    /// The observation of every job but its seed: the options, else the telescope's preset.
    observation: ObservationSpec,
    image: ImageConfig,
    weighting: Weighting,
    threads: usize,
}

impl SimulateSource {
    pub fn new(config: SimulateParams, image: &ImageConfig, threads: usize) -> Result<SimulateSource> {
        let observation = observation(&config)?;
        crate::vis::check_phase_centre(config.ra_deg, observation.dec_deg)?;
        if config.jobs == 0 {
            return Err(Error::parameter("jobs", "expected at least one job"));
        }
        let weighting = config.noise_weighting.with_robust(config.robust)?;
        Ok(SimulateSource { config, observation, image: image.clone(), weighting, threads })
    }
}

/// The observation `c` asks for, the telescope's typical observation filling in what it does
/// not say (seed 0: each job sets its own).
fn observation(c: &SimulateParams) -> Result<ObservationSpec> {
    ObservationRequest {
        telescope: c.telescope.clone(),
        configurations: c.configurations.clone(),
        hours: c.hours.clone(),
        dec_deg: c.dec_deg,
        integration_s: c.integration_s,
        channels: c.channels,
        frequency_mhz: c.frequency_mhz,
        frequency_ratio: c.frequency_ratio,
        flag_fraction: c.flag_fraction,
        random_rotation: true,
        seed: 0,
    }
    .spec()
}

impl Source<Job> for SimulateSource {
    fn produce(&mut self, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()> {
        let c = &self.config;
        for k in 0..c.jobs as u64 {
            if cancelled() {
                break;
            }
            let seed = c.seed + k;
            let request = SimulationRequest {
                observation: ObservationSpec { seed, ..self.observation.clone() },
                sky: SkyModel::Procedural { seed },
                size: self.image.size,
                pixel: self.image.pixel_scale(),
                dynamic_range: c.dynamic_range,
                noise_weighting: self.weighting,
                phase_centre_deg: (c.ra_deg, self.observation.dec_deg),
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
