//! `kind: simulate`: simulated observations of procedural skies (one job per seed), with
//! the true sky attached so the run reports SNR and logSNR.

use super::params::SimulateParams;
use crate::nufft::NufftParams;
use crate::imaging::ImageConfig;
use crate::job::Job;
use crate::pipeline::Source;
use crate::simulate::observe::{frequency_channels, ObservationSpec};
use crate::simulate::{simulate, SimulationRequest, SkyModel};
use crate::weighting::Weighting;
use crate::{Error, Result};

pub struct SimulateSource {
    config: SimulateParams,
    image: ImageConfig,
    weighting: Weighting,
    threads: usize,
}

impl SimulateSource {
    pub fn new(config: SimulateParams, image: &ImageConfig, threads: usize) -> Result<SimulateSource> {
        let (configurations, hours) = tracks(&config)?;
        if configurations.len() != hours.len() {
            return Err(Error::parameter(
                "hours",
                format!("one observing time per configuration: {} configurations, {} times", configurations.len(), hours.len()),
            ));
        }
        crate::vis::check_phase_centre(config.ra_deg, config.dec_deg)?;
        if config.jobs == 0 {
            return Err(Error::parameter("jobs", "expected at least one job"));
        }
        let weighting = config.noise_weighting.with_robust(config.robust)?;
        // Before any job: what the observation of every seed would refuse.
        observation(&config, config.seed)?.validate()?;
        Ok(SimulateSource { config, image: image.clone(), weighting, threads })
    }
}

/// The configurations and hours asked for, else the telescope's typical observation's.
fn tracks(c: &SimulateParams) -> Result<(Vec<String>, Vec<f64>)> {
    let preset = &crate::simulate::telescope::telescope(&c.telescope)?.observation;
    Ok((c.configurations.clone().unwrap_or_else(|| preset.configurations.clone()), c.hours.clone().unwrap_or_else(|| preset.hours.clone())))
}

/// The observation of the job of `seed`.
fn observation(c: &SimulateParams, seed: u64) -> Result<ObservationSpec> {
    let (configurations, hours) = tracks(c)?;
    Ok(ObservationSpec {
        telescope: c.telescope.clone(),
        configurations: configurations.into_iter().zip(hours).collect(),
        dec_deg: c.dec_deg,
        integration_s: c.integration_s,
        frequencies_hz: frequency_channels(c.frequency_mhz * 1e6, c.channels, c.frequency_ratio)?,
        flag_fraction: c.flag_fraction,
        random_rotation: true,
        seed,
    })
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
                observation: observation(c, seed)?,
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
