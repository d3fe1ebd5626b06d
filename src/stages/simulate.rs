//! `kind: simulate`: simulated observations of procedural skies (one job per seed), with
//! the true sky attached so the run reports SNR and logSNR.

use crate::imaging::ImageConfig;
use crate::job::{ImageContext, Job, Reads, SourceKind, SourceParams};
use crate::nufft::NufftParams;
use crate::pipeline::{Source, StageParams};
use crate::simulate::observe::{ObservationRequest, ObservationSpec};
use crate::simulate::{simulate, SimulationRequest, SkyModel};
use crate::weighting::{Weighting, WeightingScheme};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// `kind: simulate`: simulated observations of procedural skies.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimulateParams {
    /// Number of jobs (seeds `seed`, `seed + 1`, ...); default 1.
    pub jobs: usize,
    /// Default 7.
    pub seed: u64,
    /// Of the procedural sky; default 1e4.
    pub dynamic_range: f64,
    /// A telescope of `data/telescopes/telescopes.yaml`; default `vla`.
    pub telescope: String,
    /// Its configurations; default its typical observation's (`[a, c]` for the VLA).
    pub configurations: Option<Vec<String>>,
    /// Hours per configuration; default its typical observation's (`[6, 2]` for the VLA).
    pub hours: Option<Vec<f64>>,
    /// Declination of the phase centre; default the telescope's typical observation's (40
    /// degrees for the VLA, -30 for MeerKAT).
    pub dec_deg: Option<f64>,
    /// Default 180 degrees.
    pub ra_deg: f64,
    /// Seconds per sample; default the typical observation's (VLA 30, MeerKAT 8).
    pub integration_s: Option<f64>,
    /// Frequency channels and the lowest frequency; default the typical observation's (VLA
    /// 1 at 1400 MHz, MeerKAT 4 from 856 MHz).
    pub channels: Option<usize>,
    pub frequency_mhz: Option<f64>,
    /// Highest to lowest channel frequency; default the typical observation's (VLA 1, MeerKAT 2).
    pub frequency_ratio: Option<f64>,
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
            telescope: "vla".into(),
            configurations: None,
            hours: None,
            dec_deg: None,
            ra_deg: 180.0,
            integration_s: None,
            channels: None,
            frequency_mhz: None,
            frequency_ratio: None,
            flag_fraction: 0.0,
            noise_weighting: WeightingScheme::Briggs,
            robust: 0.0,
        }
    }
}

impl StageParams for SimulateParams {
    const KIND: &'static str = "simulate";
}

impl SourceParams for SimulateParams {
    fn reads(&self) -> Reads {
        Reads::Nothing
    }
    fn several_jobs(&self) -> Option<String> {
        (self.jobs > 1).then(|| format!("a simulate source makes {} jobs", self.jobs))
    }
    /// The telescope it simulates (its registry name).
    fn telescope(&self) -> Result<Option<String>> {
        Ok(Some(crate::simulate::telescope::telescope(&self.telescope)?.name.clone()))
    }
}

/// The kind, as registered. The simulation's errors name its parameters' fields, the stage's
/// keys: they are reported at the key's line.
pub(super) const KIND: SourceKind<SimulateParams> =
    SourceKind::new(|params, c| Ok(Box::new(SimulateSource::new(params.clone(), c.image(), c.threads).map_err(|e| c.at_field(&params, e))?)));

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
        crate::vis::check_phase_centre(config.ra_deg, observation.dec_deg, ["ra_deg", "dec_deg"])?;
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
