//! `kind: residual`: `r = x_d - D x` after each network step, the per-iteration metrics, and
//! the loop exit (series finished or early stop).
//!
//! `method: toeplitz` (default) convolves with the 2N PSF, or with the w-term with one kernel
//! per w-plane (`crate::operator::toeplitz`): once gridding is done, memory no longer grows with the
//! number of visibilities. `method: nufft` is the exact round trip
//! through the kept visibilities (the reference's choice).

use crate::job::{BuildContext, Built, Emit, Iterate, Job, KindFn, LoopStop, Product, StopReason, StopRule, DIVERGING_RISE};
use crate::pipeline::{Port, Role, Stage, StageParams};
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
    /// Stop early by the reference v2 criterion (the residual ratio changes by less than
    /// `tolerance`, or rises at two consecutive iterations) instead of running the whole
    /// series; default true.
    pub early_stop: bool,
    /// Relative change of the residual ratio below which the loop stops (`early_stop`);
    /// default 1e-4.
    pub tolerance: f64,
    /// Stop a series whose residual ratio rises above 1 (its model explains the data worse
    /// than an empty image) or rises at two consecutive iterations, keep the iterate of lowest
    /// residual ratio as the model (the empty model if none is below 1), and warn; default
    /// true.
    pub divergence_guard: bool,
}

impl Default for ResidualParams {
    fn default() -> Self {
        ResidualParams { method: ResidualMethod::Toeplitz, early_stop: true, tolerance: 1e-4, divergence_guard: true }
    }
}

impl StageParams for ResidualParams {
    const KIND: &'static str = "residual";
}

/// The kind, as registered.
pub(super) const KIND: KindFn = KindFn {
    name: ResidualParams::KIND,
    role: Role::Residual,
    consumes: &[Product::Imaging, Product::Model],
    produces: &[],
    consumes_also: Some(consumes),
    passes_on: false,
    build: |c| Ok(Built::Stage(Box::new(ResidualStage::new(c.params()?)?))),
};

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

    /// The loop's stop rule with this stage's settings.
    fn stop_rule(&self) -> StopRule {
        StopRule { early_stop: self.config.early_stop, tolerance: self.config.tolerance, divergence_guard: self.config.divergence_guard }
    }

    /// See [`StopRule::stop_reason`].
    fn stop_reason(&self, ratios: &[f64], finished: bool, early_stop_from: usize) -> Option<StopReason> {
        self.stop_rule().stop_reason(ratios, finished, early_stop_from)
    }
}

/// A CLEAN that stops above this residual ratio has explained less than half of the dirty
/// image: on any field with sources above its threshold it should do far better, so its
/// threshold is taken to be wrong for the data and the job warns.
const CLEAN_UNEXPLAINED: f64 = 0.5;

/// After the divergence guard stopped a job: its model and residual become the best iterate's
/// (the empty model when no iterate did better than ratio 1), and a warning says so.
fn fall_back(job: &mut Job, reason: StopReason) -> Result<()> {
    let iteration = job.iteration;
    let ratio = job.metrics.last().map_or(f64::NAN, |m| m.residual_ratio);
    let step = job.step_kind.clone().unwrap_or_else(|| "network".into());
    let im = job.imaging_mut("residual")?;
    let (kept, kept_ratio) = match im.best.take() {
        Some(best) => {
            im.model = best.model;
            im.residual = best.residual;
            (best.iteration, best.residual_ratio)
        }
        None => {
            im.model = vec![0.0; im.dirty.len()];
            im.residual = im.dirty.clone();
            (0, 1.0)
        }
    };
    let what = match reason {
        StopReason::Diverged => format!("residual ratio {ratio:.4} after iteration {iteration}, above 1: its model explains the data worse than an empty image"),
        _ => format!("residual ratio rose at two consecutive iterations by more than {:.0} %, to {ratio:.4} after iteration {iteration}", 100.0 * (DIVERGING_RISE - 1.0)),
    };
    let kept_what = if kept == 0 { "the empty model (residual ratio 1)".to_string() } else { format!("the model of iteration {kept} (residual ratio {kept_ratio:.4})") };
    // CLEAN has no training domain: what makes it diverge is a minor cycle run past what its
    // PSF describes.
    let advice = if step == "clean" {
        "CLEAN's minor cycles went further than its PSF describes the residual (a sparse uv-coverage, or the w-term over a wide field); a smaller `mgain`, a higher `auto_threshold` or fewer components per cycle keep each major cycle where the PSF holds"
    } else {
        "The data are probably outside what the series was trained for (see the domain warnings and `r2d2 models`)"
    };
    job.warn(format!("the {step} step diverged ({what}); stopped and kept {kept_what}. {advice}"));
    job.stop = Some(LoopStop { reason, after_iteration: iteration, kept_iteration: kept, kept_residual_ratio: kept_ratio });
    Ok(())
}

impl Stage<Job> for ResidualStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let began = Instant::now();
        let method = self.config.method;
        let iteration = job.iteration;
        let id = job.id.clone();
        let im = job.imaging_mut("residual")?;
        let d_x = match (method, &im.operator) {
            (ResidualMethod::Nufft, Some(op)) => op.apply_normal(&im.model)?,
            (ResidualMethod::Nufft, None) => return Err(Error::parameter("method", "nufft needs the visibilities, which the gridder released")),
            (ResidualMethod::Toeplitz, _) => {
                if let (1, None, false, Some(why), Some(_)) = (iteration, &im.w_toeplitz, im.updates_by_taylor(), &im.toeplitz_inexact, &im.operator) {
                    log::info!("job {id}: the residual update runs through the operator instead of the PSF convolution: {why}");
                }
                im.normal_at_updates(&im.model, "method")?
            }
        };
        im.residual = im.dirty.iter().zip(&d_x).map(|(d, x)| d - x).collect();
        let what = format!("residual after step {iteration}");
        crate::sanity::check_image(&im.residual, im.geometry.size, &what, "the model is too large for the residual update to stay finite")?;
        job.record_iteration(began.elapsed().as_secs_f64());
        if let Some(m) = job.metrics.last() {
            // "of N" where the step's series length is known: progress for a log reader (a
            // Python caller's `logging`) as the command line's bar shows it.
            let of = if job.series_length > 0 { format!(" of {}", job.series_length) } else { String::new() };
            log::info!(
                "job {}: iteration {}{of} residual ratio {:.4e}{}",
                job.id,
                m.iteration,
                m.residual_ratio,
                m.snr.map(|s| format!(", SNR {s:.2} dB")).unwrap_or_default()
            );
        }
        // Realisations run their whole series: the early stop would end the job (the ratios
        // of several realisations' iterations are not one sequence either). The guard still
        // watches each realisation's own sequence, and the mean's ratio: one realisation that
        // diverges spoils the mean, and its ratio can fall again while the model grows what
        // the data do not measure.
        let several = job.realisation > 0 || !job.realisation_models.is_empty();
        let ratios: Vec<f64> = job.metrics.iter().map(|m| m.residual_ratio).collect();
        let reason = if several {
            let current = job.metrics.last().and_then(|m| m.realisation);
            let own: Vec<f64> = job.metrics.iter().filter(|m| m.realisation == current).map(|m| m.residual_ratio).collect();
            // From no network on: the early stop never applies, the guard (where on) does.
            self.stop_reason(&own, job.series_finished || current.is_none(), usize::MAX)
        } else {
            self.stop_reason(&ratios, job.series_finished, job.early_stop_from)
        };
        if reason.is_some() && several {
            // The job ends here, as one model: the realisations' models are dropped.
            job.realisation_models.clear();
            job.realisation = 0;
        }
        match reason {
            Some(reason @ (StopReason::Diverged | StopReason::Rising)) if self.config.divergence_guard => fall_back(&mut job, reason)?,
            Some(reason) => {
                let ratio = ratios.last().copied().unwrap_or(f64::NAN);
                log::info!("job {}: stopped after iteration {iteration} ({reason:?}, residual ratio {ratio:.4e})", job.id);
                if reason == StopReason::Converged && ratio > CLEAN_UNEXPLAINED && job.step_kind.as_deref() == Some("clean") {
                    job.warn(format!(
                        "CLEAN stopped with a residual ratio of {ratio:.3}: its thresholds left most of the dirty image unexplained. Its noise threshold is in sigmas of the residual's robust spread, and on a sparse uv-coverage that spread is the sources' sidelobes, not noise: a lower `auto_threshold` (or a `threshold` in Jy/beam) cleans further"
                    ));
                }
                job.stop = Some(LoopStop { reason, after_iteration: iteration, kept_iteration: iteration, kept_residual_ratio: ratio });
            }
            None if self.config.divergence_guard && !several => {
                // Keep the best iterate for a later fall-back (the empty model has ratio 1).
                let ratio = ratios.last().copied().unwrap_or(f64::INFINITY);
                let im = job.imaging_mut("residual")?;
                if ratio < im.best.as_ref().map_or(1.0, |b| b.residual_ratio) {
                    im.best = Some(Iterate { iteration, residual_ratio: ratio, model: im.model.clone(), residual: im.residual.clone() });
                }
            }
            None => {}
        }
        let finished = job.series_finished || reason.is_some();
        let mut taylor_off = None;
        let mut exact_ratio = None;
        if finished {
            if let Some(im) = job.imaging.as_mut() {
                im.best = None;
                // The Taylor form agreed with the operator on the dirty image: the written
                // residual is the operator's all the same, and the log says how far the form
                // was from it on the final model.
                if method == ResidualMethod::Toeplitz {
                    if let Some((deviation, warning)) = im.residual_through_the_operator("the networks")? {
                        log::info!("job {id}: the final residual through the operator: the Taylor series in w was {deviation:.1e} of D x from it on the final model");
                        taylor_off = warning;
                        exact_ratio = Some(crate::metrics::residual_ratio(&im.residual, &im.dirty));
                    }
                }
            }
        }
        if let Some(ratio) = exact_ratio {
            // The figures of the model kept say the written residual's ratio: the stop's, and
            // the last iteration's where that is the model kept.
            let last_kept = job.stop.as_ref().is_none_or(|s| s.kept_iteration == s.after_iteration);
            if let Some(stop) = job.stop.as_mut() {
                stop.kept_residual_ratio = ratio;
            }
            if let Some(last) = job.metrics.last_mut().filter(|_| last_kept) {
                last.residual_ratio = ratio;
            }
        }
        if let Some(warning) = taylor_off {
            job.warn(warning);
        }
        emit(if finished { Port::Done } else { Port::Next }, job)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stage(early_stop: bool, divergence_guard: bool) -> ResidualStage {
        ResidualStage::new(ResidualParams { early_stop, divergence_guard, ..ResidualParams::default() }).unwrap()
    }

    #[test]
    fn the_guard_stops_above_one_and_on_a_second_rise_and_the_v2_rule_on_convergence_but_lets_a_first_overshoot_recover() {
        let guarded = stage(true, true);
        assert_eq!(guarded.stop_reason(&[0.5, 0.3], false, 1), None);
        assert_eq!(guarded.stop_reason(&[2.5], false, 1), Some(StopReason::Diverged));
        assert_eq!(guarded.stop_reason(&[0.5, 0.3, 1.01], false, 1), Some(StopReason::Diverged));
        // A first network's overshoot from the empty model may stand while the next ones
        // bring the ratio down (below the ceiling, for two iterations at most).
        assert_eq!(guarded.stop_reason(&[1.34], false, 1), None);
        assert_eq!(guarded.stop_reason(&[1.34, 1.06], false, 1), None);
        assert_eq!(guarded.stop_reason(&[1.34, 1.06, 0.36], false, 1), None);
        assert_eq!(guarded.stop_reason(&[1.34, 1.4], false, 1), Some(StopReason::Diverged));
        assert_eq!(guarded.stop_reason(&[1.34, 1.2, 1.1], false, 1), Some(StopReason::Diverged));
        assert_eq!(guarded.stop_reason(&[0.9, 1.2], false, 1), Some(StopReason::Diverged));
        // A series that ends on a tolerated overshoot diverged.
        assert_eq!(guarded.stop_reason(&[1.34], true, 1), Some(StopReason::Diverged));
        assert_eq!(guarded.stop_reason(&[1.34, 0.5], true, 1), None);
        // One rise is allowed (a network may trade residual for precision); two in a row by
        // more than half, above a ratio of 0.05, are divergence; others the v2 stop at the noise floor
        // (a held-out MeerKAT sky: 0.0019 -> 0.0021 -> 0.0023).
        assert_eq!(guarded.stop_reason(&[0.5, 0.3, 0.31], false, 1), None);
        assert_eq!(guarded.stop_reason(&[0.5, 0.3, 0.4, 0.46], false, 1), Some(StopReason::Rising));
        assert_eq!(guarded.stop_reason(&[0.5, 0.3, 0.32, 0.34], false, 1), Some(StopReason::Stalled));
        assert_eq!(guarded.stop_reason(&[0.0019, 0.0021, 0.0023], false, 1), Some(StopReason::Stalled));
        // Near the noise floor no rise is divergence; above the floor the same rise is.
        assert_eq!(guarded.stop_reason(&[0.0024, 0.004, 0.0057], false, 1), Some(StopReason::Stalled));
        assert_eq!(guarded.stop_reason(&[0.024, 0.04, 0.057], false, 1), Some(StopReason::Rising));
        assert_eq!(guarded.stop_reason(&[0.5, 0.3, 0.301, 0.302], false, 1), Some(StopReason::Stalled));
        assert_eq!(stage(false, true).stop_reason(&[0.5, 0.3, 0.301, 0.302], false, 1), None, "no v2 stop without early_stop");
        assert_eq!(guarded.stop_reason(&[0.5, 0.3, 0.3 * (1.0 + 5e-5)], false, 1), Some(StopReason::Converged));
        // Without the guard and the early stop, nothing stops the series.
        let plain = stage(false, false);
        assert_eq!(plain.stop_reason(&[3.0, 4.0, 5.0], false, 1), None);
        // The v2 rule alone stops a rising series too (and keeps the last iterate, as the
        // reference does), but not one above 1 that has not risen twice.
        let v2 = stage(true, false);
        assert_eq!(v2.stop_reason(&[3.0], false, 1), None);
        assert_eq!(v2.stop_reason(&[0.5, 0.6, 0.7], false, 1), Some(StopReason::Stalled));
    }

    #[test]
    fn a_series_early_stop_waits_for_its_first_network_to_stop_from_but_the_guard_does_not() {
        let guarded = stage(true, true);
        // Stalled at 12 and 13 of a series whose clean-up stage starts at 15: it runs on.
        let stalled = [0.5, 0.3, 0.2, 0.1, 0.05, 0.03, 0.02, 0.01, 0.008, 0.006, 0.005, 0.0052, 0.0054];
        assert_eq!(guarded.stop_reason(&stalled, false, 1), Some(StopReason::Stalled));
        assert_eq!(guarded.stop_reason(&stalled, false, 15), None);
        // From network 15 on, the rule applies again.
        let mut later = stalled.to_vec();
        later.extend([0.0049, 0.0051, 0.0053]);
        assert_eq!(guarded.stop_reason(&later[..15], false, 15), None);
        assert_eq!(guarded.stop_reason(&later, false, 15), Some(StopReason::Stalled));
        let converged = [0.5, 0.3, 0.3 * (1.0 + 5e-5)];
        assert_eq!(guarded.stop_reason(&converged, false, 4), None);
        // Divergence is stopped wherever it happens.
        assert_eq!(guarded.stop_reason(&[0.5, 0.3, 0.4, 0.46], false, 15), Some(StopReason::Rising));
        assert_eq!(guarded.stop_reason(&[0.5, 1.3], false, 15), Some(StopReason::Diverged));
    }

    #[test]
    fn the_defaults_are_the_v2_rule_and_the_guard() {
        let p = ResidualParams::default();
        assert!(p.early_stop && p.divergence_guard && p.tolerance == 1e-4);
    }
}
