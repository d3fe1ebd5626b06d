//! The built-in `clean` step: one Hogbom minor cycle per loop iteration (a major cycle), the
//! residual update in between being the pipeline's own.

use super::{NetworkStep, StepInput};
use crate::deconv::{hogbom, HogbomParams};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CleanConfig {
    /// Loop gain.
    #[serde(default = "gain")]
    pub gain: f64,
    /// Stop a minor cycle when the residual peak falls below this (Jy/beam).
    #[serde(default)]
    pub threshold: f64,
    /// Components per major cycle.
    #[serde(default = "components")]
    pub components_per_cycle: usize,
    /// Major cycles (loop iterations).
    #[serde(default = "cycles")]
    pub major_cycles: usize,
    /// Only positive components (intensity).
    #[serde(default)]
    pub positive_only: bool,
}

impl Default for CleanConfig {
    fn default() -> Self {
        CleanConfig { gain: gain(), threshold: 0.0, components_per_cycle: components(), major_cycles: cycles(), positive_only: false }
    }
}

fn gain() -> f64 {
    0.1
}
fn components() -> usize {
    1000
}
fn cycles() -> usize {
    5
}

pub struct CleanStep {
    config: CleanConfig,
}

impl CleanStep {
    pub fn new(config: CleanConfig) -> Result<CleanStep> {
        if !(config.gain > 0.0 && config.gain <= 1.0) {
            return Err(Error::parameter("gain", format!("expected a loop gain in (0, 1], got {}", config.gain)));
        }
        if config.major_cycles == 0 {
            return Err(Error::parameter("major_cycles", "expected at least one major cycle"));
        }
        Ok(CleanStep { config })
    }
}

impl NetworkStep for CleanStep {
    fn series_length(&self) -> usize {
        self.config.major_cycles
    }

    fn step(&mut self, _iteration: usize, input: &StepInput<'_>) -> Result<Vec<f64>> {
        let params = HogbomParams {
            gain: self.config.gain,
            threshold: self.config.threshold,
            max_components: self.config.components_per_cycle,
            positive_only: self.config.positive_only,
        };
        let result = hogbom(input.residual, input.psf_2n, input.size, &params);
        Ok(input.model.iter().zip(&result.components).map(|(x, c)| x + c).collect())
    }

}
