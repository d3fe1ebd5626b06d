//! `kind: residual`: `r = x_d - D x` after each network step, the per-iteration metrics, and
//! the loop exit (series finished or early stop).
//!
//! `method: toeplitz` (default) convolves with the 2N PSF: once gridding is done, memory no
//! longer grows with the number of visibilities. `method: nufft` is the exact round trip
//! through the kept visibilities (the reference's choice).

use crate::pipeline::registry::{BuildContext, Product};
use crate::pipeline::{Emit, Job, Port, Stage};
use crate::{Error, Result};
use serde::Deserialize;
use std::time::Instant;

#[derive(Deserialize, Clone, Copy, PartialEq, Debug, Default)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    #[default]
    Toeplitz,
    Nufft,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResidualConfig {
    #[serde(default)]
    method: Method,
    /// Stop early (reference v2 criterion) instead of running the whole series.
    #[serde(default)]
    early_stop: bool,
    /// Relative change of the residual ratio below which the loop stops (early_stop).
    #[serde(default = "tolerance")]
    tolerance: f64,
}

fn tolerance() -> f64 {
    1e-4
}

/// What the stage needs besides the imaging state: the NUFFT method runs the measurement
/// operator, which the gridder then keeps.
pub fn consumes(ctx: &BuildContext<'_>) -> Result<Vec<Product>> {
    let config: ResidualConfig = ctx.params()?;
    Ok(if config.method == Method::Nufft { vec![Product::Operator] } else { Vec::new() })
}

pub struct ResidualStage {
    config: ResidualConfig,
}

impl ResidualStage {
    pub fn new(config: ResidualConfig) -> Result<ResidualStage> {
        if !(config.tolerance > 0.0) {
            return Err(Error::parameter("tolerance", format!("expected a positive tolerance, got {}", config.tolerance)));
        }
        Ok(ResidualStage { config })
    }

    /// Reference v2: stop when the residual ratio changes by less than `tolerance` or has
    /// risen at two consecutive iterations.
    fn should_stop(&self, job: &Job) -> bool {
        let r: Vec<f64> = job.metrics.iter().map(|m| m.residual_ratio).collect();
        let n = r.len();
        if n >= 2 && ((r[n - 1] - r[n - 2]).abs() / r[n - 2] < self.config.tolerance) {
            return true;
        }
        n >= 3 && r[n - 1] > r[n - 2] && r[n - 2] > r[n - 3]
    }
}

impl Stage for ResidualStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let began = Instant::now();
        let method = self.config.method;
        let im = job.imaging_mut("residual")?;
        let d_x = match method {
            Method::Toeplitz => im.psf_convolution.apply(&im.model),
            Method::Nufft => match &im.operator {
                Some(op) => op.apply_normal(&im.model),
                None => return Err(Error::parameter("method", "nufft needs the visibilities, which the gridder released")),
            },
        };
        im.residual = im.dirty.iter().zip(&d_x).map(|(d, x)| d - x).collect();
        job.record_iteration(began.elapsed().as_secs_f64());
        if let Some(m) = job.metrics.last() {
            log::info!(
                "job {}: iteration {} residual ratio {:.4e}{}",
                job.id,
                m.iteration,
                m.residual_ratio,
                m.snr.map(|s| format!(", SNR {s:.2} dB")).unwrap_or_default()
            );
        }
        let finished = job.series_finished || (self.config.early_stop && self.should_stop(&job));
        emit(if finished { Port::Done } else { Port::Next }, job)
    }
}
