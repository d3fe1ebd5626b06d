//! The built-in `clean` step: one Hogbom minor cycle per loop iteration (a major cycle), the
//! residual update in between being the pipeline's own.
//!
//! The stopping controls mean what WSClean's do: `max_components` (`-niter`, components over
//! all major cycles), `gain` (`-gain`), `major_gain` (`-mgain`: each minor cycle cleans the
//! peak down by this fraction of its value at the cycle's start), `auto_threshold`
//! (`-auto-threshold`: stop at this many times the residual's robust noise, measured at each
//! major cycle) and `threshold` (`-threshold`, Jy/beam). A minor cycle that has nothing left
//! to clean leaves the model as it is, and the residual update's convergence rule ends the
//! loop.
//!
//! The defaults are WSClean's usual command (`-mgain 0.8 -auto-threshold 3`), not its bare
//! defaults: a minor cycle that runs far below what its shift-invariant PSF describes
//! diverges once the w-term makes each position's response its own (measured on DP3's,
//! OSKAR's and Birli's public MSs, where WSClean without a threshold diverges as well).
//! `major_gain: 1` and `auto_threshold: 0` switch either off.
//!
//! Masks mean what WSClean's do. `fits_mask` (read by the step stage, which hands each job's
//! mask in [`StepInput::mask`]): components are taken inside it only. `auto_mask`
//! (`-auto-mask`): the major cycles clean without a mask of their own down to this many times
//! the residual's robust noise; from the cycle that reaches that level, only the pixels that
//! already hold components are cleaned, down to `auto_threshold` (WSClean's Högbom auto-mask:
//! the components' own pixels, no scales and no dilation).

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
    /// Components over all major cycles of a job (WSClean's `-niter`); none: no total limit.
    #[serde(default)]
    pub max_components: Option<usize>,
    /// Fraction of the peak each minor cycle cleans away (WSClean's `-mgain`); 1 (or none):
    /// only `components_per_cycle` and the thresholds end a minor cycle.
    #[serde(default = "major_gain")]
    pub major_gain: Option<f64>,
    /// Stop at this many times the residual's robust noise (WSClean's `-auto-threshold`); 0
    /// (or none): no noise threshold.
    #[serde(default = "auto_threshold")]
    pub auto_threshold: Option<f64>,
    /// Clean without a mask down to this many times the residual's robust noise, then only
    /// where components were taken, down to `auto_threshold` (WSClean's `-auto-mask`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auto_mask: Option<f64>,
    /// A FITS image on the image's grid: components only where it is not zero (WSClean's
    /// `-fits-mask`). Read and checked against each job's grid by the step stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fits_mask: Option<std::path::PathBuf>,
    /// Why CLEAN runs where a series was asked for (`auto` found none trained for the data's
    /// telescope): every job carries it as a warning. Set by the engine.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chosen_because: Option<String>,
}

impl Default for CleanConfig {
    fn default() -> Self {
        CleanConfig {
            gain: gain(),
            threshold: 0.0,
            components_per_cycle: components(),
            major_cycles: cycles(),
            positive_only: false,
            max_components: None,
            major_gain: major_gain(),
            auto_threshold: auto_threshold(),
            auto_mask: None,
            fits_mask: None,
            chosen_because: None,
        }
    }
}

pub use crate::deconv::DEFAULT_MAJOR_GAIN;
/// WSClean's usual `-auto-threshold`.
pub const DEFAULT_AUTO_THRESHOLD: f64 = 3.0;

fn major_gain() -> Option<f64> {
    Some(DEFAULT_MAJOR_GAIN)
}
fn auto_threshold() -> Option<f64> {
    Some(DEFAULT_AUTO_THRESHOLD)
}

fn gain() -> f64 {
    0.1
}
fn components() -> usize {
    1000
}
/// WSClean's `-nmiter` default: enough major cycles for the thresholds to end the loop on
/// most fields (it stops early where a cycle takes nothing).
fn cycles() -> usize {
    20
}

pub struct CleanStep {
    config: CleanConfig,
    /// Components taken so far per job (for `max_components`).
    taken: std::collections::HashMap<String, usize>,
    /// Per job, under `auto_mask`, once its cycles have reached that level: the pixels that
    /// held components then, the only ones cleaned from there on.
    auto_masks: std::collections::HashMap<String, Vec<bool>>,
}

impl CleanStep {
    pub fn new(config: CleanConfig) -> Result<CleanStep> {
        if !(config.gain > 0.0 && config.gain <= 1.0) {
            return Err(Error::parameter("gain", format!("expected a loop gain in (0, 1], got {}", config.gain)));
        }
        if config.major_cycles == 0 {
            return Err(Error::parameter("major_cycles", "expected at least one major cycle"));
        }
        if !(config.threshold >= 0.0 && config.threshold.is_finite()) {
            return Err(Error::parameter("threshold", format!("expected a threshold of 0 Jy/beam or more, got {}", config.threshold)));
        }
        if let Some(m) = config.major_gain.filter(|m| !(*m > 0.0 && *m <= 1.0)) {
            return Err(Error::parameter("major_gain", format!("expected a major-cycle gain in (0, 1], got {m}")));
        }
        if let Some(s) = config.auto_threshold.filter(|s| !(*s >= 0.0 && s.is_finite())) {
            return Err(Error::parameter("auto_threshold", format!("expected a number of noise sigmas of 0 or more, got {s}")));
        }
        if let Some(s) = config.auto_mask.filter(|s| !(*s > 0.0 && s.is_finite())) {
            return Err(Error::parameter("auto_mask", format!("expected a positive number of noise sigmas, got {s}")));
        }
        Ok(CleanStep { config, taken: std::collections::HashMap::new(), auto_masks: std::collections::HashMap::new() })
    }
}

impl NetworkStep for CleanStep {
    fn series_length(&self) -> usize {
        self.config.major_cycles
    }

    fn domain_problems(&self, _job: &super::JobDomain<'_>) -> Result<Vec<String>> {
        Ok(self.config.chosen_because.iter().cloned().collect())
    }

    fn describe(&self) -> Option<serde_json::Value> {
        let c = &self.config;
        Some(serde_json::json!({"kind": "clean", "gain": c.gain, "major_gain": c.major_gain, "auto_threshold": c.auto_threshold, "threshold": c.threshold, "max_components": c.max_components}))
    }

    fn step(&mut self, iteration: usize, input: &StepInput<'_>) -> Result<Vec<f64>> {
        let c = &self.config;
        if iteration == 1 {
            self.taken.remove(input.job);
            self.auto_masks.remove(input.job);
        }
        let taken = self.taken.get(input.job).copied().unwrap_or(0);
        let budget = c.max_components.map_or(c.components_per_cycle, |total| c.components_per_cycle.min(total.saturating_sub(taken)));
        if budget == 0 {
            return Ok(input.model.to_vec());
        }
        let sigma = crate::metrics::robust_sigma(input.residual);
        let score = |r: f64| if c.positive_only { r } else { r.abs() };
        let peak_within = |mask: Option<&[bool]>| input.residual.iter().enumerate().filter(|(k, _)| mask.is_none_or(|m| m[*k])).map(|(_, &r)| score(r)).fold(0.0, f64::max);
        // Under auto_mask, a job whose residual is already below that level inside the user's
        // mask goes on inside the auto mask at once (an open cycle would take nothing, and a
        // model left as it was ends the loop).
        if let Some(sigmas) = c.auto_mask {
            if !self.auto_masks.contains_key(input.job) && !(peak_within(input.mask) >= sigmas * sigma) {
                self.auto_masks.insert(input.job.to_string(), input.model.iter().map(|&x| x != 0.0).collect());
            }
        }
        let auto_mask = self.auto_masks.get(input.job);
        let mask = auto_mask.map(Vec::as_slice).or(input.mask);
        let mut level = c.threshold;
        if let Some(m) = c.major_gain {
            level = level.max((1.0 - m) * peak_within(mask));
        }
        if let Some(sigmas) = c.auto_threshold {
            level = level.max(sigmas * sigma);
        }
        let open = c.auto_mask.filter(|_| auto_mask.is_none());
        if let Some(sigmas) = open {
            level = level.max(sigmas * sigma);
        }
        let params = HogbomParams { gain: c.gain, threshold: level, max_components: budget, positive_only: c.positive_only, mask: mask.map(<[bool]>::to_vec) };
        let result = hogbom(input.residual, input.psf_2n, input.size, &params);
        *self.taken.entry(input.job.to_string()).or_insert(0) += result.n_components;
        let phase = match (auto_mask, input.mask) {
            (Some(_), _) => "in the auto mask",
            (None, Some(_)) => "in the mask",
            (None, None) => "open",
        };
        log::debug!("job {}: major cycle {iteration} ({phase}): {} components down to {:.3e} Jy/beam (stop level {level:.3e})", input.job, result.n_components, result.last_peak);
        let model: Vec<f64> = input.model.iter().zip(&result.components).map(|(x, c)| x + c).collect();
        // The cycle that cleaned down to the auto-mask level makes the mask the next ones
        // keep to: every pixel that holds a component.
        if let Some(sigmas) = open {
            if !(score(result.last_peak) >= sigmas * sigma) {
                log::debug!("job {}: reached the auto-mask level ({sigmas} sigma) at major cycle {iteration}: cleaning on in the mask of the components", input.job);
                self.auto_masks.insert(input.job.to_string(), model.iter().map(|&x| x != 0.0).collect());
            }
        }
        Ok(model)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::operator::PsfConvolution;

    const N: usize = 32;

    /// A Gaussian 2N PSF (peak 1 at (N, N)), and the dirty image of point sources through it.
    fn problem() -> (Vec<f64>, Vec<f64>, PsfConvolution) {
        let m = 2 * N;
        let psf_2n: Vec<f64> = (0..m * m)
            .map(|k| {
                let (x, y) = ((k % m) as f64 - N as f64, (k / m) as f64 - N as f64);
                (-(x * x + y * y) / (2.0 * 1.5f64.powi(2))).exp()
            })
            .collect();
        let convolution = PsfConvolution::new(N, &psf_2n).unwrap();
        let mut sky = vec![0.0; N * N];
        for (x, y, s) in [(10, 12, 1.0), (20, 8, 0.5), (16, 24, 0.25), (5, 27, 0.1)] {
            sky[y * N + x] = s;
        }
        let dirty = convolution.apply(&sky);
        (psf_2n, dirty, convolution)
    }

    fn cycle(step: &mut CleanStep, iteration: usize, model: &[f64], residual: &[f64], psf_2n: &[f64], convolution: &PsfConvolution) -> Vec<f64> {
        let psf = vec![0.0; N * N];
        let input = StepInput { job: "job", size: N, model, residual, dirty: residual, psf: &psf, psf_2n, psf_convolution: convolution, mask: None };
        step.step(iteration, &input).unwrap()
    }

    fn peak(v: &[f64]) -> f64 {
        v.iter().fold(0.0, |m: f64, x| m.max(x.abs()))
    }

    /// `-niter` bounds the components over all major cycles of a job; `-mgain` ends each
    /// minor cycle once the peak is down by that fraction; `-auto-threshold` stops at that
    /// many noise sigmas; `-threshold` at an absolute level; a new job starts afresh.
    #[test]
    fn the_controls_mean_what_wsclean_means() {
        let (psf_2n, dirty, convolution) = problem();
        let config = |c: CleanConfig| CleanStep::new(c).unwrap();
        // Each control alone: the others off.
        let bare = CleanConfig { major_gain: None, auto_threshold: None, ..CleanConfig::default() };
        let components = |model: &[f64], before: &[f64]| model.iter().zip(before).filter(|(a, b)| a != b).count();

        // -niter 7 with 5 per cycle: 5 components, then 2, then none.
        let mut step = config(CleanConfig { max_components: Some(7), components_per_cycle: 5, gain: 0.1, ..bare.clone() });
        let m1 = cycle(&mut step, 1, &vec![0.0; N * N], &dirty, &psf_2n, &convolution);
        assert_eq!(*step.taken.get("job").unwrap(), 5);
        let r1: Vec<f64> = dirty.iter().zip(convolution.apply(&m1)).map(|(d, x)| d - x).collect();
        let m2 = cycle(&mut step, 2, &m1, &r1, &psf_2n, &convolution);
        assert_eq!(*step.taken.get("job").unwrap(), 7);
        let r2: Vec<f64> = dirty.iter().zip(convolution.apply(&m2)).map(|(d, x)| d - x).collect();
        assert_eq!(cycle(&mut step, 3, &m2, &r2, &psf_2n, &convolution), m2, "the budget is spent: the model stays");
        assert!(components(&m2, &vec![0.0; N * N]) >= 1);
        // Iteration 1 of the job again: a fresh budget.
        cycle(&mut step, 1, &vec![0.0; N * N], &dirty, &psf_2n, &convolution);
        assert_eq!(*step.taken.get("job").unwrap(), 5);

        // -mgain 0.8: the minor cycle stops with the residual peak at about 0.2 of the start.
        let mut step = config(CleanConfig { major_gain: Some(0.8), components_per_cycle: 100_000, gain: 0.1, ..bare.clone() });
        let m = cycle(&mut step, 1, &vec![0.0; N * N], &dirty, &psf_2n, &convolution);
        let r: Vec<f64> = dirty.iter().zip(convolution.apply(&m)).map(|(d, x)| d - x).collect();
        let ratio = peak(&r) / peak(&dirty);
        assert!(ratio <= 0.2 + 1e-9 && ratio > 0.15, "peak down to {ratio} of the start");

        // -auto-threshold 3 on a residual with noise: nothing below 3 sigma is cleaned.
        let noisy: Vec<f64> = dirty.iter().enumerate().map(|(k, d)| d + 0.01 * ((k * 7919 % 1000) as f64 / 500.0 - 1.0)).collect();
        let sigma = crate::metrics::robust_sigma(&noisy);
        let mut step = config(CleanConfig { auto_threshold: Some(3.0), components_per_cycle: 100_000, gain: 0.1, ..bare.clone() });
        let m = cycle(&mut step, 1, &vec![0.0; N * N], &noisy, &psf_2n, &convolution);
        let r: Vec<f64> = noisy.iter().zip(convolution.apply(&m)).map(|(d, x)| d - x).collect();
        assert!(peak(&r) < 3.0 * sigma * 1.001 && peak(&r) > 2.0 * sigma, "residual peak {} against 3 sigma {}", peak(&r), 3.0 * sigma);

        // -threshold 0.3 Jy/beam: the peak is cleaned to just below it, and no further.
        let mut step = config(CleanConfig { threshold: 0.3, components_per_cycle: 100_000, gain: 0.1, ..bare.clone() });
        let m = cycle(&mut step, 1, &vec![0.0; N * N], &dirty, &psf_2n, &convolution);
        let r: Vec<f64> = dirty.iter().zip(convolution.apply(&m)).map(|(d, x)| d - x).collect();
        assert!(peak(&r) < 0.3 && peak(&r) > 0.2, "{}", peak(&r));

        // The defaults are WSClean's usual command.
        assert_eq!((CleanConfig::default().major_gain, CleanConfig::default().auto_threshold), (Some(0.8), Some(3.0)));
        let parsed: CleanConfig = serde_yaml::from_str("{gain: 0.1}").unwrap();
        assert_eq!(parsed, CleanConfig::default());

        for bad in [
            CleanConfig { major_gain: Some(0.0), ..CleanConfig::default() },
            CleanConfig { auto_threshold: Some(-1.0), ..CleanConfig::default() },
            CleanConfig { threshold: f64::NAN, ..CleanConfig::default() },
            CleanConfig { auto_mask: Some(0.0), ..CleanConfig::default() },
        ] {
            assert!(CleanStep::new(bad).is_err());
        }
    }

    /// `-auto-mask 5 -auto-threshold 1`: the open cycles stop at 5 sigma, the mask is the
    /// pixels holding components then, and the cycles after it take components there only,
    /// down to 1 sigma; the loop ends with the model unchanged (converged).
    #[test]
    fn auto_mask_cleans_deeper_inside_the_components_it_found() {
        let (psf_2n, dirty, convolution) = problem();
        let noisy: Vec<f64> = dirty.iter().enumerate().map(|(k, d)| d + 0.004 * ((k * 7919 % 1000) as f64 / 500.0 - 1.0)).collect();
        let config = CleanConfig { auto_mask: Some(5.0), auto_threshold: Some(1.0), components_per_cycle: 100_000, major_cycles: 50, ..CleanConfig::default() };
        let mut step = CleanStep::new(config).unwrap();
        let mut model = vec![0.0; N * N];
        let mut residual = noisy.clone();
        let mut mask_at_switch = None;
        let mut converged = false;
        for iteration in 1..=50 {
            let next = cycle(&mut step, iteration, &model, &residual, &psf_2n, &convolution);
            if let (None, Some(mask)) = (&mask_at_switch, step.auto_masks.get("job")) {
                // The mask is made from the cycle that reached 5 sigma: its components, and
                // only those.
                assert_eq!(*mask, next.iter().map(|&x| x != 0.0).collect::<Vec<_>>());
                mask_at_switch = Some(mask.clone());
            }
            if next == model {
                converged = true;
                break;
            }
            model = next;
            residual = noisy.iter().zip(convolution.apply(&model)).map(|(d, x)| d - x).collect();
        }
        assert!(converged, "the loop did not converge");
        let mask = mask_at_switch.expect("the cycles reached the auto-mask level");
        let outside: Vec<usize> = (0..N * N).filter(|&k| model[k] != 0.0 && !mask[k]).collect();
        assert!(outside.is_empty(), "components outside the auto mask at {outside:?}");
        // Deeper than 5 sigma inside the mask; noise peaks outside it untouched.
        let sigma = crate::metrics::robust_sigma(&residual);
        let inside_peak = (0..N * N).filter(|&k| mask[k]).fold(0.0f64, |m, k| m.max(residual[k].abs()));
        assert!(inside_peak < 1.5 * sigma, "inside the mask: peak {inside_peak} against sigma {sigma}");
        for (x, y, s) in [(10, 12, 1.0), (20, 8, 0.5), (16, 24, 0.25)] {
            let near: f64 = (0..N * N).filter(|&k| (k % N).abs_diff(x) <= 2 && (k / N).abs_diff(y) <= 2).map(|k| model[k]).sum();
            assert!((near - s).abs() < 0.1 * s, "source at ({x}, {y}): {near} against {s}");
        }
    }
}
