//! `kind: residual`: `r = x_d - D x` after each network step, the per-iteration metrics, and
//! the loop exit (series finished or early stop).
//!
//! `method: toeplitz` (default) convolves with the 2N PSF: once gridding is done, memory no
//! longer grows with the number of visibilities. `method: nufft` is the exact round trip
//! through the kept visibilities (the reference's choice).

use crate::pipeline::registry::{BuildContext, Product};
use crate::pipeline::{Emit, Job, Port, Stage, StageParams};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// How the residual update computes `D x`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ResidualMethod {
    /// A convolution with the 2N PSF: memory no longer grows with the visibilities.
    #[default]
    Toeplitz,
    /// The exact NUFFT round trip through the visibilities, which the gridder then keeps.
    Nufft,
}

/// `kind: residual`: the residual update and the loop's exit.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct ResidualParams {
    /// Default `toeplitz`.
    pub method: ResidualMethod,
    /// Stop early (reference v2 criterion) instead of running the whole series.
    pub early_stop: bool,
    /// Relative change of the residual ratio below which the loop stops (`early_stop`);
    /// default 1e-4.
    pub tolerance: f64,
}

impl Default for ResidualParams {
    fn default() -> Self {
        ResidualParams { method: ResidualMethod::Toeplitz, early_stop: false, tolerance: 1e-4 }
    }
}

impl StageParams for ResidualParams {
    const KIND: &'static str = "residual";
}

/// What the stage needs besides the imaging state: the NUFFT method runs the measurement
/// operator, which the gridder then keeps.
pub fn consumes(ctx: &BuildContext<'_>) -> Result<Vec<Product>> {
    let config: ResidualParams = ctx.params()?;
    Ok(if config.method == ResidualMethod::Nufft { vec![Product::Operator] } else { Vec::new() })
}

pub struct ResidualStage {
    config: ResidualParams,
}

impl ResidualStage {
    pub fn new(config: ResidualParams) -> Result<ResidualStage> {
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
        let iteration = job.iteration;
        let im = job.imaging_mut("residual")?;
        let d_x = match method {
            ResidualMethod::Toeplitz => im.psf_convolution.apply(&im.model),
            ResidualMethod::Nufft => match &im.operator {
                Some(op) => op.apply_normal(&im.model),
                None => return Err(Error::parameter("method", "nufft needs the visibilities, which the gridder released")),
            },
        };
        im.residual = im.dirty.iter().zip(&d_x).map(|(d, x)| d - x).collect();
        let what = format!("residual after step {iteration}");
        crate::sanity::check_image(&im.residual, im.geometry.size, &what, "the model is too large for the residual update to stay finite")?;
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
        // Realisations run their whole series: stopping one early would end the job (the
        // ratios of several realisations' iterations are not one sequence either).
        let several = job.realisation > 0;
        let finished = job.series_finished || (self.config.early_stop && !several && self.should_stop(&job));
        emit(if finished { Port::Done } else { Port::Next }, job)
    }
}
