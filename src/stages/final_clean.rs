//! `kind: final_clean`: CLEAN major cycles on what the imaging loop's model leaves in the
//! residual, after the loop.
//!
//! A network series stops when its residual ratio stops changing, not when the residual is
//! noise: on compact sources its models come out too bright, with negative bowls in the
//! residual far above the noise. Components of both signs taken from that residual with the
//! PSF, each major cycle ending in the exact residual `x_d - D x`, give the model the fluxes
//! the data measure (the paper's data-fidelity criterion: a residual compatible with the
//! noise), while extended emission the series already explains leaves little above the
//! threshold to take.

use crate::deconv::{hogbom, HogbomParams};
use crate::job::{Built, Emit, Imaging, Job, KindFn, Product};
use crate::metrics::{residual_ratio, robust_sigma};
use crate::pipeline::{Port, Role, Stage, StageParams};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// `kind: final_clean`: after the imaging loop, CLEAN major cycles on what the step's model
/// leaves in the residual (components of both signs, with the PSF, each major cycle's residual
/// the exact `x_d - D x`), so that the model's fluxes are what the data say: a network series
/// leaves its compact sources too bright, with negative bowls in the residual, that the
/// stopping rule does not see. A cycle that does not lower the residual is undone.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct FinalCleanParams {
    /// Most major cycles; default 20. 0 turns the stage into a pass-through.
    pub major_cycles: usize,
    /// Minor-cycle loop gain; default 0.1.
    pub gain: f64,
    /// Fraction of the residual's peak each major cycle cleans away (WSClean's `-mgain`);
    /// default 0.8.
    pub major_gain: f64,
    /// Clean the whole image down to this many times the residual's robust noise, then only
    /// where components were taken (WSClean's `-auto-mask`); default 5.
    pub auto_mask: f64,
    /// Inside that mask, stop at this many times the residual's robust noise (WSClean's
    /// `-auto-threshold`); default 2. Noise peaks elsewhere stay in the residual, where they
    /// belong, instead of becoming model components.
    pub auto_threshold: f64,
    /// Most components per major cycle; default 10 000.
    pub components_per_cycle: usize,
    /// Islands of the step's model (connected positive pixels) no larger than this many PSF
    /// main lobes are taken out of the model before the cycles and cleaned afresh; default 4,
    /// 0 keeps every island. A network series draws a point source as a blob wider than
    /// the PSF, which components added on top correct in flux only with a ring of negative
    /// ones around it; CLEAN's own components give a point source a point.
    pub compact_beams: f64,
    /// Around those islands, stop at this many times the residual's robust noise; default 1.
    /// A point source's flux is then what the data measure to a fraction of the noise, while
    /// extended emission keeps `auto_threshold` (deeper there, noise becomes model).
    pub compact_threshold: f64,
}

impl Default for FinalCleanParams {
    fn default() -> Self {
        FinalCleanParams {
            major_cycles: 20,
            gain: 0.1,
            major_gain: crate::steps::clean::DEFAULT_MAJOR_GAIN,
            auto_mask: 5.0,
            auto_threshold: 2.0,
            components_per_cycle: 10_000,
            compact_beams: 4.0,
            compact_threshold: 1.0,
        }
    }
}

impl StageParams for FinalCleanParams {
    const KIND: &'static str = "final_clean";
}

/// The kind, as registered.
pub(super) const KIND: KindFn = KindFn {
    name: FinalCleanParams::KIND,
    role: Role::Transform,
    consumes: &[Product::Imaging, Product::Model],
    produces: &[],
    consumes_also: None,
    passes_on: false,
    build: |c| Ok(Built::Stage(Box::new(FinalCleanStage::new(c.params()?)?))),
};

pub struct FinalCleanStage {
    config: FinalCleanParams,
}

impl FinalCleanStage {
    pub fn new(config: FinalCleanParams) -> Result<FinalCleanStage> {
        let c = &config;
        if !(c.gain > 0.0 && c.gain <= 1.0) {
            return Err(Error::parameter("gain", format!("expected a loop gain in (0, 1], got {}", c.gain)));
        }
        if !(c.major_gain > 0.0 && c.major_gain <= 1.0) {
            return Err(Error::parameter("major_gain", format!("expected a major-cycle gain in (0, 1], got {}", c.major_gain)));
        }
        if !(c.auto_threshold > 0.0 && c.auto_threshold.is_finite()) {
            return Err(Error::parameter("auto_threshold", format!("expected a positive number of noise sigmas, got {}", c.auto_threshold)));
        }
        if !(c.compact_threshold > 0.0 && c.compact_threshold.is_finite()) {
            return Err(Error::parameter("compact_threshold", format!("expected a positive number of noise sigmas, got {}", c.compact_threshold)));
        }
        if !(c.auto_mask >= c.auto_threshold && c.auto_mask.is_finite()) {
            return Err(Error::parameter("auto_mask", format!("expected a number of noise sigmas of auto_threshold ({}) or more, got {}", c.auto_threshold, c.auto_mask)));
        }
        if !(c.compact_beams >= 0.0 && c.compact_beams.is_finite()) {
            return Err(Error::parameter("compact_beams", format!("expected a number of PSF main lobes, 0 or more, got {}", c.compact_beams)));
        }
        if c.components_per_cycle == 0 {
            return Err(Error::parameter("components_per_cycle", "expected at least one component per cycle"));
        }
        Ok(FinalCleanStage { config })
    }
}

/// `D x` by the most exact form the gridder left: the w-Toeplitz kernels, the operator (the
/// samples), the Taylor series in `w`, or the PSF convolution where it is exact.
fn normal(im: &Imaging, x: &[f64]) -> Result<Vec<f64>> {
    if let Some(w_toeplitz) = &im.w_toeplitz {
        return Ok(w_toeplitz.apply(x));
    }
    if let Some(op) = &im.operator {
        return op.apply_normal(x);
    }
    if let Some(w_taylor) = &im.w_taylor {
        return Ok(w_taylor.apply(x));
    }
    match &im.toeplitz_inexact {
        Some(why) => Err(Error::parameter("final_clean", format!("the PSF convolution is not exact here ({why}) and the gridder kept no operator"))),
        None => Ok(im.psf_convolution.apply(x)),
    }
}

impl FinalCleanStage {
    /// One major cycle on `im`: Hogbom on the residual (inside `mask` where there is one) down
    /// to `sigmas` times its noise, then the exact residual of the new model. Kept (model and residual updated, `ratio`
    /// lowered) where the residual ratio falls; the components taken, or `None` where nothing
    /// was kept.
    fn cycle(&self, im: &mut Imaging, ratio: &mut f64, mask: Option<&[bool]>, sigmas: f64) -> Result<Option<Vec<f64>>> {
        let c = &self.config;
        let n = im.geometry.size;
        let peak = match mask {
            Some(mask) => im.residual.iter().zip(mask).filter(|(_, inside)| **inside).fold(0.0f64, |m, (v, _)| m.max(v.abs())),
            None => max_abs(&im.residual),
        };
        let level = ((1.0 - c.major_gain) * peak).max(sigmas * robust_sigma(&im.residual));
        let params = HogbomParams { gain: c.gain, threshold: level, max_components: c.components_per_cycle, positive_only: false, mask: mask.map(<[bool]>::to_vec) };
        let found = hogbom(&im.residual, &im.psf_2n, n, &params);
        log::debug!("final CLEAN: {} cycle from peak {peak:.3e} to {level:.3e} Jy/beam: {} components, stopped at {:.3e}", if mask.is_some() { "masked" } else { "open" }, found.n_components, found.last_peak);
        if found.n_components == 0 {
            return Ok(None);
        }
        let model: Vec<f64> = im.model.iter().zip(&found.components).map(|(x, c)| x + c).collect();
        let d_x = normal(im, &model)?;
        let residual: Vec<f64> = im.dirty.iter().zip(&d_x).map(|(d, x)| d - x).collect();
        crate::sanity::check_image(&residual, n, "residual after a final CLEAN cycle", "the model is too large for the residual update to stay finite")?;
        let new_ratio = residual_ratio(&residual, &im.dirty);
        // A cycle the data do not confirm is undone: the model never explains them worse.
        if !(new_ratio < *ratio) {
            log::debug!("final CLEAN: a cycle would take the residual ratio from {ratio:.4e} to {new_ratio:.4e}; undone");
            return Ok(None);
        }
        *ratio = new_ratio;
        im.model = model;
        im.residual = residual;
        Ok(Some(found.components))
    }
}

/// The pixels of the PSF's main lobe: those at half its peak or above, connected to it.
fn main_lobe_pixels(psf: &[f64], n: usize) -> usize {
    let peak = psf.iter().copied().enumerate().fold((0, f64::MIN), |b, (k, v)| if v > b.1 { (k, v) } else { b });
    island(psf, n, peak.0, |v| v >= 0.5 * peak.1, &mut vec![false; n * n]).len()
}

/// The 8-connected pixels where `inside` holds, from `start`; `seen` marks them.
fn island(image: &[f64], n: usize, start: usize, inside: impl Fn(f64) -> bool, seen: &mut [bool]) -> Vec<usize> {
    let mut pixels = vec![start];
    seen[start] = true;
    let mut next = 0;
    while next < pixels.len() {
        let k = pixels[next];
        next += 1;
        let (x, y) = (k % n, k / n);
        for yy in y.saturating_sub(1)..(y + 2).min(n) {
            for xx in x.saturating_sub(1)..(x + 2).min(n) {
                let j = yy * n + xx;
                if !seen[j] && inside(image[j]) {
                    seen[j] = true;
                    pixels.push(j);
                }
            }
        }
    }
    pixels
}

/// The pixels of the islands of `model` (8-connected positive pixels) of at most
/// `max_pixels` pixels and at least `min_flux` in all.
fn compact_island_pixels(model: &[f64], n: usize, max_pixels: usize, min_flux: f64) -> Vec<usize> {
    let mut seen = vec![false; n * n];
    let mut compact = Vec::new();
    for k in 0..n * n {
        if !seen[k] && model[k] > 0.0 {
            let pixels = island(model, n, k, |v| v > 0.0, &mut seen);
            if pixels.len() <= max_pixels && pixels.iter().map(|&j| model[j]).sum::<f64>() >= min_flux {
                compact.extend(pixels);
            }
        }
    }
    compact
}

/// Islands fainter than this many times the residual's noise (in Jy, the flux of a point
/// source of that peak) are left as the step drew them: noise alone makes their fluxes
/// uncertain by a tenth or more, and cleaning them deeper turns noise into model.
const COMPACT_MIN_SIGMAS: f64 = 10.0;

/// The pixels of `components` that are not zero, and their eight neighbours, within `within`
/// (the user's mask) where there is one: where the masked cycles may take more (a source's
/// flux spreads over the pixels around its peak).
fn mask_of(components: &[f64], n: usize, within: Option<&[bool]>) -> Vec<bool> {
    let mut mask = vec![false; n * n];
    for (k, _) in components.iter().enumerate().filter(|(_, c)| **c != 0.0) {
        let (x, y) = (k % n, k / n);
        for yy in y.saturating_sub(1)..(y + 2).min(n) {
            for xx in x.saturating_sub(1)..(x + 2).min(n) {
                mask[yy * n + xx] = within.is_none_or(|w| w[yy * n + xx]);
            }
        }
    }
    mask
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

/// The residual's peak in units of its robust noise.
fn peak_sigmas(residual: &[f64]) -> f64 {
    max_abs(residual) / robust_sigma(residual)
}

impl FinalCleanStage {
    /// Major cycles over the whole image down to `auto_mask` sigmas, then inside the mask of
    /// what they took down to `auto_threshold`, then inside `compact` (a mask of the compact
    /// islands) down to `compact_threshold`; each kept cycle an iteration of the job's
    /// metrics; every phase within the job's mask where it has one. The cycles kept, the
    /// pixels they put components at, and the residual ratio.
    fn cycles(&self, job: &mut Job, compact: Option<Vec<bool>>) -> Result<(usize, usize, f64)> {
        let c = &self.config;
        let user = job.mask.clone();
        let user = user.as_deref().map(Vec::as_slice);
        let im = job.imaging_mut("final_clean")?;
        let n = im.geometry.size;
        let mut ratio = residual_ratio(&im.residual, &im.dirty);
        let (mut cycles, mut components) = (0, 0);
        // The mask starts from where the step found emission: pixels of the model above the
        // residual's noise (a source of a few sigma puts at least that in its brightest pixel).
        let sigma = robust_sigma(&im.residual);
        let mut taken: Vec<f64> = im.model.iter().map(|&x| if x > sigma { x } else { 0.0 }).collect();
        let mut phase = Phase::Open;
        while cycles < c.major_cycles {
            let began = Instant::now();
            let (mask, sigmas) = match &phase {
                Phase::Open => (user, c.auto_mask),
                Phase::Masked(mask) => (Some(mask.as_slice()), c.auto_threshold),
                Phase::Compact(mask) => (Some(mask.as_slice()), c.compact_threshold),
            };
            let found = self.cycle(job.imaging_mut("final_clean")?, &mut ratio, mask, sigmas)?;
            let Some(found) = found else {
                phase = match phase {
                    Phase::Open if taken.iter().any(|t| *t != 0.0) => Phase::Masked(mask_of(&taken, n, user)),
                    Phase::Open | Phase::Masked(_) if c.compact_threshold < c.auto_threshold => match &compact {
                        Some(mask) => Phase::Compact(mask.clone()),
                        None => break,
                    },
                    _ => break,
                };
                continue;
            };
            if matches!(phase, Phase::Open) {
                taken.iter_mut().zip(&found).for_each(|(t, f)| *t += f);
            }
            cycles += 1;
            components += found.iter().filter(|c| **c != 0.0).count();
            // Each kept cycle is an iteration of the job's metrics, after the loop's.
            job.iteration += 1;
            job.last_step_seconds = began.elapsed().as_secs_f64();
            job.record_iteration(0.0);
        }
        Ok((cycles, components, ratio))
    }
}

/// The stages of the final CLEAN's cycles: each goes on until a cycle takes nothing.
enum Phase {
    /// The whole image, down to `auto_mask` sigmas.
    Open,
    /// Around what the step's model and the open cycles found, down to `auto_threshold`.
    Masked(Vec<bool>),
    /// Around the compact islands, down to `compact_threshold`.
    Compact(Vec<bool>),
}

impl Stage<Job> for FinalCleanStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        // A model the divergence guard rejected is not built on: the products say what it kept.
        let rejected = job.stop.as_ref().is_some_and(|s| s.reason.is_rejection());
        if self.config.major_cycles == 0 || rejected {
            return emit(Port::Next, job);
        }
        let id = job.id.clone();
        let im = job.imaging_mut("final_clean")?;
        let (flux_before, peak_before) = (im.model.iter().sum::<f64>(), peak_sigmas(&im.residual));
        let step_ratio = residual_ratio(&im.residual, &im.dirty);
        let n = im.geometry.size;
        let max_pixels = (self.config.compact_beams * main_lobe_pixels(&im.psf, n) as f64) as usize;
        let compact = compact_island_pixels(&im.model, n, max_pixels, COMPACT_MIN_SIGMAS * robust_sigma(&im.residual));
        let (mut cycles, mut components, mut ratio) = (0, 0, step_ratio);
        if !compact.is_empty() {
            let step = (im.model.clone(), im.residual.clone(), job.iteration, job.metrics.len());
            let im = job.imaging_mut("final_clean")?;
            // Compact islands are cleaned afresh: their model leaves, its flux goes back to
            // the residual by the exact update.
            compact.iter().for_each(|&k| im.model[k] = 0.0);
            let d_x = normal(im, &im.model)?;
            im.residual = im.dirty.iter().zip(&d_x).map(|(d, x)| d - x).collect();
            let mut islands = vec![0.0; n * n];
            compact.iter().for_each(|&k| islands[k] = 1.0);
            let mask = mask_of(&islands, n, job.mask.as_deref().map(Vec::as_slice));
            (cycles, components, ratio) = self.cycles(&mut job, Some(mask))?;
            if !(ratio < step_ratio) {
                // CLEAN explained the data worse than the step's compact islands did: they
                // stay, and the cycles build on them instead (their iterations forgotten).
                log::warn!("job {id}: final CLEAN: the {} pixels of compact islands cleaned afresh left the residual ratio at {ratio:.4e}, above the step's {step_ratio:.4e}; the step's islands are kept", compact.len());
                let im = job.imaging_mut("final_clean")?;
                (im.model, im.residual, job.iteration) = (step.0, step.1, step.2);
                job.metrics.truncate(step.3);
                (cycles, components, ratio) = (0, 0, step_ratio);
            }
        }
        if cycles == 0 {
            (cycles, components, ratio) = self.cycles(&mut job, None)?;
        }
        if let Some(stop) = job.stop.as_mut().filter(|_| cycles > 0) {
            // The model written is the last cycle's.
            stop.kept_iteration = job.iteration;
            stop.kept_residual_ratio = ratio;
        }
        let im = job.imaging_mut("final_clean")?;
        let (flux_after, peak_after) = (im.model.iter().sum::<f64>(), peak_sigmas(&im.residual));
        log::info!(
            "job {id}: final CLEAN on the residual: components at {components} pixels in {cycles} major cycles; model flux {flux_before:.4e} -> {flux_after:.4e} Jy; residual peak {peak_before:.1} -> {peak_after:.1} sigma"
        );
        job.settings.insert(
            "final_clean".into(),
            serde_json::json!({
                "major_cycles": cycles,
                "component_pixels": components,
                "model_flux_before_jy": flux_before,
                "model_flux_after_jy": flux_after,
                "residual_peak_sigma_before": peak_before,
                "residual_peak_sigma_after": peak_after,
            }),
        );
        emit(Port::Next, job)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compact_islands_are_the_small_bright_ones() {
        let n = 32;
        let mut model = vec![0.0; n * n];
        // A 3 x 3 blob of 9 in all, a faint 2-pixel island, and a 10 x 10 patch.
        for y in 2..5 {
            for x in 2..5 {
                model[y * n + x] = 1.0;
            }
        }
        model[10 * n + 2] = 0.1;
        model[10 * n + 3] = 0.1;
        for y in 15..25 {
            for x in 15..25 {
                model[y * n + x] = 1.0;
            }
        }
        let mut compact = compact_island_pixels(&model, n, 20, 1.0);
        compact.sort();
        let blob: Vec<usize> = (2..5).flat_map(|y| (2..5).map(move |x| y * n + x)).collect();
        assert_eq!(compact, blob);
        // Diagonal neighbours belong to the same island.
        model[5 * n + 5] = 1.0;
        assert!(compact_island_pixels(&model, n, 9, 1.0).is_empty());
        assert_eq!(compact_island_pixels(&model, n, 10, 1.0).len(), 10);
    }

    #[test]
    fn the_main_lobe_is_the_connected_half_power_region() {
        let n = 16;
        let mut psf = vec![0.0; n * n];
        psf[8 * n + 8] = 1.0;
        psf[8 * n + 9] = 0.6;
        psf[9 * n + 9] = 0.5;
        // A sidelobe at half power, not connected to the peak, is not part of it.
        psf[2 * n + 2] = 0.7;
        assert_eq!(main_lobe_pixels(&psf, n), 3);
    }
}
