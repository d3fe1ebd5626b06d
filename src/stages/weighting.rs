//! `kind: weighting`: image geometry (from the pipeline's `image`) and the total weight of
//! every visibility (natural x imaging: natural, uniform or Briggs).

use crate::imaging::{total_weights, DirtyParams};
use crate::pipeline::config::ImageConfig;
use crate::pipeline::{Emit, Job, Port, Stage};
use crate::weighting::{Weighting, WeightingScheme, DEFAULT_GRID_FACTOR};
use crate::{Error, Result};
use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WeightingConfig {
    /// natural, uniform or briggs.
    scheme: WeightingScheme,
    #[serde(default)]
    robust: f64,
    #[serde(default = "grid_factor")]
    grid_factor: f64,
}

fn grid_factor() -> f64 {
    DEFAULT_GRID_FACTOR
}

pub struct WeightingStage {
    weighting: Weighting,
    grid_factor: f64,
    image: ImageConfig,
}

impl WeightingStage {
    pub fn new(config: WeightingConfig, image: &ImageConfig) -> Result<WeightingStage> {
        Ok(WeightingStage {
            weighting: config.scheme.with_robust(config.robust)?,
            grid_factor: config.grid_factor,
            image: image.clone(),
        })
    }
}

impl Stage for WeightingStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let vis = job.vis.as_ref().ok_or_else(|| Error::parameter("visibilities", "already released by an earlier stage"))?;
        let params = DirtyParams { size: self.image.size, pixel: self.image.pixel_scale(), ..DirtyParams::default() };
        let geometry = params.geometry(vis)?;
        job.weight = Some(total_weights(vis, geometry, self.weighting, self.grid_factor)?);
        job.geometry = Some(geometry);
        emit(Port::Next, job)
    }
}
