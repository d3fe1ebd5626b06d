//! The final CLEAN: major cycles of components of both signs, with the PSF, on what an
//! imaging loop's model leaves in the residual.
//!
//! A network series stops when its residual ratio stops changing, not when the residual is
//! noise: on compact sources its models come out too bright, with negative bowls in the
//! residual far above the noise. Components of both signs taken from that residual with the
//! PSF, each major cycle ending in the exact residual `x_d - D x`, give the model the fluxes
//! the data measure (the paper's data-fidelity criterion: a residual compatible with the
//! noise), while extended emission the series already explains leaves little above the
//! threshold to take. Who computes that exact residual is the caller's: the engine's `D` as
//! the residual updates apply it (`kind: final_clean`; where that is the Taylor series in `w`,
//! the residual written is the operator's), or an outside imager's major cycle
//! (`crate::steps::driven`).

use super::{hogbom, HogbomParams, DEFAULT_MAJOR_GAIN};
use crate::metrics::{residual_ratio, robust_sigma};
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
    /// After the cycles, islands of the model (connected positive pixels) whose flux is below
    /// this many times the noise of a flux measured over their area (the residual's robust
    /// noise times the square root of their area in beams, at least one) leave it, with the
    /// exact update, with the negative components beside them; default 3, 0 keeps every
    /// island. A series spreads faint positive specks where the data hold nothing it can
    /// measure, which a self-calibration would take as sky. The model's flux is what the
    /// cycles left of the data's, down to their thresholds, so the cut is the stricter in the
    /// data.
    pub faint_island_sigmas: f64,
    /// After the cycles, this many steps of the residual smoothed to `scale_beams` added to
    /// the model where it holds emission (pixels above the residual's robust noise and their
    /// eight neighbours), each scaled by the factor that best explains the data by the exact
    /// update; default 3, 0: none. Högbom's cycles stop where no pixel stands above their
    /// threshold, and leave emission spread below it over many beams (a series' extended
    /// sources' wings, faint sources' flux): a self-calibration takes the flux scale of a model
    /// that misses it, round after round.
    pub scale_steps: usize,
    /// The smoothing Gaussian's sigma in the PSF main lobe's FWHM; default 0.64 (a beam's
    /// wings, not its core).
    pub scale_beams: f64,
}

impl Default for FinalCleanParams {
    fn default() -> Self {
        FinalCleanParams {
            major_cycles: 20,
            gain: 0.1,
            major_gain: DEFAULT_MAJOR_GAIN,
            auto_mask: 5.0,
            auto_threshold: 2.0,
            components_per_cycle: 10_000,
            compact_beams: 4.0,
            compact_threshold: 1.0,
            faint_island_sigmas: 3.0,
            scale_steps: 3,
            scale_beams: 0.64,
        }
    }
}

impl FinalCleanParams {
    /// The parameters, or an error naming the first one out of range.
    pub fn checked(self) -> Result<FinalCleanParams> {
        let c = &self;
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
        if !(c.faint_island_sigmas >= 0.0 && c.faint_island_sigmas.is_finite()) {
            return Err(Error::parameter("faint_island_sigmas", format!("expected a number of noise sigmas, 0 or more, got {}", c.faint_island_sigmas)));
        }
        if !(c.scale_beams > 0.0 && c.scale_beams.is_finite()) {
            return Err(Error::parameter("scale_beams", format!("expected a positive number of PSF main-lobe FWHMs, got {}", c.scale_beams)));
        }
        if c.components_per_cycle == 0 {
            return Err(Error::parameter("components_per_cycle", "expected at least one component per cycle"));
        }
        Ok(self)
    }
}

/// The residual's peak in units of its robust noise.
pub fn peak_sigmas(residual: &[f64]) -> f64 {
    max_abs(residual) / robust_sigma(residual)
}

/// What the final CLEAN works on: the images a step's loop leaves, and the residual of any
/// model (`x_d - D x`) from whoever owns the data: the engine's `D` (as its residual updates
/// apply it), or an outside imager's major cycle (`crate::steps::driven`).
pub struct CleanInput<'a> {
    pub n: usize,
    pub dirty: &'a [f64],
    /// N x N, peak at (N/2, N/2): its main lobe sizes the compact islands.
    pub psf: &'a [f64],
    /// 2N x 2N, peak at (N, N): the minor cycles subtract it.
    pub psf_2n: &'a [f64],
    /// The user's mask (N x N, true inside), if any.
    pub mask: Option<&'a [bool]>,
}

/// The final CLEAN's result: the model, its exact residual, and what the cycles did. `kept`
/// holds what `on_kept` returned for each kept major cycle, in order (the cycles of a pass
/// that was undone are not in it), then for the faint islands' removal where there was one.
pub struct CleanOutcome<T> {
    pub model: Vec<f64>,
    pub residual: Vec<f64>,
    /// Whether the model differs from the one the final CLEAN was given (a kept cycle or step,
    /// or the compact islands' removal standing); where it does not, `residual` may still be
    /// one `residual_of` made of it again, not the one given.
    pub model_changed: bool,
    pub cycles: usize,
    pub components: usize,
    pub ratio: f64,
    pub kept: Vec<T>,
    /// The faint islands that left the model ([`FinalCleanParams::faint_island_sigmas`]) and
    /// their flux in all.
    pub faint_islands: usize,
    pub faint_flux: f64,
    /// The smoothed-residual steps kept ([`FinalCleanParams::scale_steps`]) and the flux they
    /// added in all.
    pub scale_steps: usize,
    pub scale_flux: f64,
}

/// The state of one run of the final CLEAN.
struct Cleaning<'a, 'b, T> {
    config: &'a FinalCleanParams,
    input: &'a CleanInput<'a>,
    model: Vec<f64>,
    residual: Vec<f64>,
    residual_of: &'b mut dyn FnMut(&[f64]) -> Result<Vec<f64>>,
    on_kept: &'b mut dyn FnMut(&[f64], &[f64], f64) -> T,
    kept: Vec<T>,
}

impl<T> Cleaning<'_, '_, T> {
    /// One major cycle: Hogbom on the residual (inside `mask` where there is one) down to
    /// `sigmas` times its noise, then the exact residual of the new model. Kept (model and
    /// residual updated, `ratio` lowered) where the residual ratio falls; the components
    /// taken, or `None` where nothing was kept.
    fn cycle(&mut self, ratio: &mut f64, mask: Option<&[bool]>, sigmas: f64, reach: Reach) -> Result<Option<Vec<f64>>> {
        let c = self.config;
        let n = self.input.n;
        let peak = peak_within(&self.residual, mask);
        let threshold = sigmas * robust_sigma(&self.residual);
        if peak <= reach.reached * threshold {
            log::debug!("final CLEAN: {} peak {peak:.3e} Jy/beam within {} of the threshold {threshold:.3e}: reached", if mask.is_some() { "masked" } else { "open" }, reach.reached);
            return Ok(None);
        }
        let level = ((1.0 - c.major_gain) * peak).max(reach.aim * threshold);
        let params = HogbomParams { gain: c.gain, threshold: level, max_components: c.components_per_cycle, positive_only: false, mask: mask.map(<[bool]>::to_vec) };
        let found = hogbom(&self.residual, self.input.psf_2n, n, &params);
        log::debug!("final CLEAN: {} cycle from peak {peak:.3e} to {level:.3e} Jy/beam: {} components, stopped at {:.3e}", if mask.is_some() { "masked" } else { "open" }, found.n_components, found.last_peak);
        if found.n_components == 0 {
            return Ok(None);
        }
        let model: Vec<f64> = self.model.iter().zip(&found.components).map(|(x, c)| x + c).collect();
        let residual = (self.residual_of)(&model)?;
        crate::sanity::check_image(&residual, n, "residual after a final CLEAN cycle", "the model is too large for the residual update to stay finite")?;
        let new_ratio = residual_ratio(&residual, self.input.dirty);
        // A cycle the data do not confirm is undone: no cycle explains them worse.
        if !(new_ratio < *ratio) {
            log::debug!("final CLEAN: a cycle would take the residual ratio from {ratio:.4e} to {new_ratio:.4e}; undone");
            return Ok(None);
        }
        *ratio = new_ratio;
        self.model = model;
        self.residual = residual;
        Ok(Some(found.components))
    }

    /// Major cycles over the whole image down to `auto_mask` sigmas, then inside the mask of
    /// what they took down to `auto_threshold`, then inside `compact` (a mask of the compact
    /// islands) down to `compact_threshold`, then, where the residual is left above `auto_mask`
    /// sigmas, strict open cycles ([`STRICT_REACH`]) and the masked phases again; each kept
    /// cycle handed to `on_kept`; every phase within the user's mask where there is one. The
    /// cycles kept, the pixels they put components at, and the residual ratio.
    fn cycles(&mut self, compact: Option<Vec<bool>>) -> Result<(usize, usize, f64)> {
        let c = self.config;
        let user = self.input.mask;
        let n = self.input.n;
        let mut ratio = residual_ratio(&self.residual, self.input.dirty);
        let (mut cycles, mut components) = (0, 0);
        // The mask starts from where the step found emission: pixels of the model above the
        // residual's noise (a source of a few sigma puts at least that in its brightest pixel).
        let sigma = robust_sigma(&self.residual);
        let mut taken: Vec<f64> = self.model.iter().map(|&x| if x > sigma { x } else { 0.0 }).collect();
        let mut phase = Phase::Open { strict: false };
        let (mut strict_done, mut masked_since_open) = (false, false);
        while cycles < c.major_cycles {
            let began = Instant::now();
            let (mask, sigmas, reach) = match &phase {
                Phase::Open { strict: false } => (user, c.auto_mask, WITHIN_REACH),
                Phase::Open { strict: true } => (user, c.auto_mask, STRICT_REACH),
                Phase::Masked(mask) => (Some(mask.as_slice()), c.auto_threshold, WITHIN_REACH),
                Phase::Compact(mask) => (Some(mask.as_slice()), c.compact_threshold, WITHIN_REACH),
            };
            let found = self.cycle(&mut ratio, mask, sigmas, reach)?;
            let Some(found) = found else {
                let next = match phase {
                    Phase::Open { .. } if taken.iter().any(|t| *t != 0.0) => Some(Phase::Masked(mask_of(&taken, n, user))),
                    Phase::Open { .. } | Phase::Masked(_) if c.compact_threshold < c.auto_threshold => compact.clone().map(Phase::Compact),
                    _ => None,
                };
                phase = match next {
                    Some(next) => next,
                    // The phases end within reach of their thresholds, and the masked ones clean
                    // inside their masks only: where the residual is left above the open
                    // threshold, the open cycles go again until it is under it (once, and
                    // again after masked cycles that may have raised it).
                    None if (!strict_done || masked_since_open) && peak_within(&self.residual, user) > c.auto_mask * robust_sigma(&self.residual) => {
                        (strict_done, masked_since_open) = (true, false);
                        Phase::Open { strict: true }
                    }
                    None => break,
                };
                continue;
            };
            match phase {
                Phase::Open { .. } => taken.iter_mut().zip(&found).for_each(|(t, f)| *t += f),
                Phase::Masked(_) | Phase::Compact(_) => masked_since_open = true,
            }
            cycles += 1;
            components += found.iter().filter(|c| **c != 0.0).count();
            let kept = (self.on_kept)(&self.model, &self.residual, began.elapsed().as_secs_f64());
            self.kept.push(kept);
        }
        Ok((cycles, components, ratio))
    }

    /// The smoothed-residual steps ([`FinalCleanParams::scale_steps`]), handed to `on_kept`
    /// together with the exact residual of their model; how many were kept and the flux they
    /// added. A step whose best factor is not positive (the smoothed residual explains nothing
    /// more) ends them.
    fn scale_steps(&mut self, ratio: &mut f64) -> Result<(usize, f64)> {
        let (c, n) = (self.config, self.input.n);
        if c.scale_steps == 0 {
            return Ok((0, 0.0));
        }
        let sigma_px = c.scale_beams * super::main_lobe_fwhm_px(self.input.psf, n);
        let noise = robust_sigma(&self.residual);
        let emission: Vec<f64> = self.model.iter().map(|&x| if x > noise { 1.0 } else { 0.0 }).collect();
        let mask = mask_of(&emission, n, self.input.mask);
        let (mut kept, mut flux) = (0, 0.0);
        let began = Instant::now();
        for _ in 0..c.scale_steps {
            let step: Vec<f64> = super::gaussian_blur(&self.residual, n, sigma_px, 3.0).into_iter().zip(&mask).map(|(v, &inside)| if inside { v } else { 0.0 }).collect();
            if step.iter().all(|v| *v == 0.0) {
                break;
            }
            // The residual is linear in the model: D step is what the step takes from it.
            let trial: Vec<f64> = self.model.iter().zip(&step).map(|(x, s)| x + s).collect();
            let taken: Vec<f64> = self.residual.iter().zip((self.residual_of)(&trial)?).map(|(r, t)| r - t).collect();
            let (along, norm) = self.residual.iter().zip(&taken).fold((0.0, 0.0), |(a, b), (r, t)| (a + r * t, b + t * t));
            let factor = along / norm;
            if !(factor > 0.0 && factor.is_finite()) {
                break;
            }
            self.model.iter_mut().zip(&step).for_each(|(x, s)| *x += factor * s);
            self.residual.iter_mut().zip(&taken).for_each(|(r, t)| *r -= factor * t);
            crate::sanity::check_image(&self.residual, n, "residual after a smoothed-residual step of the final CLEAN", "the model is too large for the residual update to stay finite")?;
            let added = factor * step.iter().sum::<f64>();
            *ratio = residual_ratio(&self.residual, self.input.dirty);
            log::debug!("final CLEAN: smoothed-residual step of factor {factor:.3e}: {added:.3e} Jy; residual ratio {ratio:.4e}");
            (kept, flux) = (kept + 1, flux + added);
        }
        if kept > 0 {
            // The steps' residuals were updated by linearity; the one written is the exact one.
            self.residual = (self.residual_of)(&self.model)?;
            *ratio = residual_ratio(&self.residual, self.input.dirty);
            let figures = (self.on_kept)(&self.model, &self.residual, began.elapsed().as_secs_f64());
            self.kept.push(figures);
        }
        Ok((kept, flux))
    }
}

/// The final CLEAN of `model` (with its exact residual `residual`): compact islands of the
/// model cleaned afresh where that explains the data better, then major cycles on what is left
/// (see [`FinalCleanParams`]), then the smoothed-residual steps, then the faint islands out.
/// `residual_of` gives the exact residual of a model; `on_kept` is told each kept major
/// cycle's model, residual and seconds, the smoothed-residual steps' and the faint islands'
/// removal's.
pub fn final_clean<T>(
    config: &FinalCleanParams,
    input: &CleanInput<'_>,
    model: Vec<f64>,
    residual: Vec<f64>,
    residual_of: &mut dyn FnMut(&[f64]) -> Result<Vec<f64>>,
    on_kept: &mut dyn FnMut(&[f64], &[f64], f64) -> T,
) -> Result<CleanOutcome<T>> {
    let n = input.n;
    let step_ratio = residual_ratio(&residual, input.dirty);
    let max_pixels = (config.compact_beams * main_lobe_pixels(input.psf, n) as f64) as usize;
    let compact = compact_island_pixels(&model, n, max_pixels, COMPACT_MIN_SIGMAS * robust_sigma(&residual));
    let mut run = Cleaning { config, input, model, residual, residual_of, on_kept, kept: Vec::new() };
    let (mut cycles, mut components, mut ratio) = (0, 0, step_ratio);
    let mut compact_left = false;
    if !compact.is_empty() {
        let step = (run.model.clone(), run.residual.clone());
        // Compact islands are cleaned afresh: their model leaves, its flux goes back to the
        // residual by the exact update.
        compact.iter().for_each(|&k| run.model[k] = 0.0);
        run.residual = (run.residual_of)(&run.model)?;
        let mut islands = vec![0.0; n * n];
        compact.iter().for_each(|&k| islands[k] = 1.0);
        let mask = mask_of(&islands, n, input.mask);
        (cycles, components, ratio) = run.cycles(Some(mask))?;
        if !(ratio < step_ratio) {
            // CLEAN explained the data worse than the step's compact islands did: they stay,
            // and the cycles build on them instead (their kept cycles forgotten).
            log::warn!("final CLEAN: the {} pixels of compact islands cleaned afresh left the residual ratio at {ratio:.4e}, above the step's {step_ratio:.4e}; the step's islands are kept", compact.len());
            (run.model, run.residual) = step;
            run.kept.clear();
            (cycles, components, ratio) = (0, 0, step_ratio);
        } else {
            compact_left = true;
        }
    }
    if cycles == 0 {
        (cycles, components, ratio) = run.cycles(None)?;
    }
    let (scale_steps, scale_flux) = run.scale_steps(&mut ratio)?;
    let (mut faint_islands, mut faint_flux) = (0, 0.0);
    if config.faint_island_sigmas > 0.0 {
        let began = Instant::now();
        let beam_pixels = main_lobe_pixels(input.psf, n) as f64 / std::f64::consts::LN_2;
        let sigma = robust_sigma(&run.residual);
        let faint = faint_islands_of(&run.model, n, beam_pixels, config.faint_island_sigmas * sigma);
        if !faint.is_empty() {
            // Faint islands explain no more than noise: where their removal leaves the
            // residual above the open cycles' threshold (and above its peak before), the
            // islands there held what the data measure, and they stay.
            let before = max_abs(&run.residual);
            let limit = before.max(config.auto_mask * sigma);
            let without = |islands: &[Vec<usize>]| {
                let mut model = run.model.clone();
                islands.iter().flatten().for_each(|&k| model[k] = 0.0);
                model
            };
            let mut faint = faint;
            let mut model = without(&faint);
            let mut residual = (run.residual_of)(&model)?;
            if max_abs(&residual) > limit {
                // Within two pixels of where the residual rose above the limit.
                let mut near = vec![false; n * n];
                for k in (0..n * n).filter(|&k| residual[k].abs() > limit) {
                    square(k, n, 2).for_each(|j| near[j] = true);
                }
                let count = faint.len();
                faint.retain(|island| !island.iter().any(|&k| near[k]));
                log::debug!("final CLEAN: {} of {count} faint islands stay: their removal left the residual above {:.1} sigma beside them", count - faint.len(), limit / sigma);
                if faint.len() == count {
                    // None lay near where it rose: what rose is not theirs to say.
                    faint.clear();
                }
                if !faint.is_empty() {
                    model = without(&faint);
                    residual = (run.residual_of)(&model)?;
                    if max_abs(&residual) > limit {
                        faint.clear();
                    }
                }
            }
            crate::sanity::check_image(&residual, n, "residual after the faint islands left the final CLEAN's model", "the model is too large for the residual update to stay finite")?;
            if faint.is_empty() {
                log::debug!("final CLEAN: the faint islands stay: their removal left the residual's peak above {:.1} sigma", limit / sigma);
            } else {
                // A negative pixel beside two faint islands is in both lists: counted once.
                let flux: f64 = run.model.iter().zip(&model).map(|(a, b)| a - b).sum();
                (faint_islands, faint_flux) = (faint.len(), flux);
                (run.model, run.residual) = (model, residual);
                // The ratio may rise a little: the islands explained some noise.
                ratio = residual_ratio(&run.residual, input.dirty);
                log::debug!("final CLEAN: {faint_islands} faint islands ({faint_flux:.3e} Jy) left the model; residual ratio {ratio:.4e}");
                let kept = (run.on_kept)(&run.model, &run.residual, began.elapsed().as_secs_f64());
                run.kept.push(kept);
            }
        }
    }
    let model_changed = compact_left || !run.kept.is_empty();
    Ok(CleanOutcome { model: run.model, residual: run.residual, model_changed, cycles, components, ratio, kept: run.kept, faint_islands, faint_flux, scale_steps, scale_flux })
}

/// The islands of `model` (8-connected positive pixels) whose flux is below `sigmas_flux`
/// (the threshold in sigmas times the residual's noise, Jy/beam) times the square root of
/// their area in beams of `beam_pixels`, at least one: a flux measured over an area of A
/// beams of a map whose noise is sigma has noise sigma sqrt(A). Each with the negative
/// pixels beside it and beside no island that stays: components the cycles took against it,
/// which would stay as a hole where no sky is. A negative pixel that also touches an island
/// that stays corrects that island too (the wing of a source the networks drew too wide), and
/// stays with it.
fn faint_islands_of(model: &[f64], n: usize, beam_pixels: f64, sigmas_flux: f64) -> Vec<Vec<usize>> {
    let mut seen = vec![false; n * n];
    let mut stays = vec![false; n * n];
    let mut faint = Vec::new();
    for k in 0..n * n {
        if !seen[k] && model[k] > 0.0 {
            let pixels = island(model, n, k, |v| v > 0.0, &mut seen);
            let flux: f64 = pixels.iter().map(|&j| model[j]).sum();
            if flux < sigmas_flux * (pixels.len() as f64 / beam_pixels).max(1.0).sqrt() {
                faint.push(pixels);
            } else {
                pixels.iter().for_each(|&j| stays[j] = true);
            }
        }
    }
    for pixels in &mut faint {
        // A negative pixel beside two of the island's is one component.
        let mut beside: Vec<usize> = pixels.iter().flat_map(|&j| block(j, n)).filter(|&j| model[j] < 0.0 && !block(j, n).any(|i| stays[i])).collect();
        beside.sort_unstable();
        beside.dedup();
        pixels.extend(beside);
    }
    faint
}

/// The 3 x 3 pixels centred on pixel `k` of an `n x n` image (`k` too), fewer at its edges:
/// an island's 8-connected reach, a component's mask, what lies beside an island.
fn block(k: usize, n: usize) -> impl Iterator<Item = usize> {
    square(k, n, 1)
}

/// The pixels within `radius` of pixel `k` of an `n x n` image along each axis (`k` too),
/// fewer at its edges.
fn square(k: usize, n: usize, radius: usize) -> impl Iterator<Item = usize> {
    let (x, y) = (k % n, k / n);
    (y.saturating_sub(radius)..(y + radius + 1).min(n)).flat_map(move |yy| (x.saturating_sub(radius)..(x + radius + 1).min(n)).map(move |xx| yy * n + xx))
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
        for j in block(k, n) {
            if !seen[j] && inside(image[j]) {
                seen[j] = true;
                pixels.push(j);
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

/// When a phase's threshold counts as reached, and where its minor cycles aim.
#[derive(Clone, Copy)]
struct Reach {
    /// The residual's peak within this factor of the threshold has reached it.
    reached: f64,
    /// The minor cycles clean down to this fraction of the threshold.
    aim: f64,
}

/// A peak within 5 % of its threshold has reached it (WSClean ends its cycles once a minor
/// loop reaches its threshold, without looking at the next residual): the noise, measured
/// afresh on each exact residual, falls a little with each cycle and the threshold with it,
/// and chasing it costs a major cycle for a handful of components, deeper in the noise.
const WITHIN_REACH: Reach = Reach { reached: 1.05, aim: 1.0 };

/// Where the phases leave the residual above the open threshold, the open cycles that follow
/// end only under it (the residual is then within `auto_mask` sigmas wherever cycles may
/// clean, unless `major_cycles` runs out or the data undo a cycle), and their minor cycles aim
/// a little below it, so that one major cycle gets there.
const STRICT_REACH: Reach = Reach { reached: 1.0, aim: 0.95 };

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
        for j in block(k, n) {
            mask[j] = within.is_none_or(|w| w[j]);
        }
    }
    mask
}

/// The residual's largest magnitude within `mask` (everywhere where there is none).
fn peak_within(residual: &[f64], mask: Option<&[bool]>) -> f64 {
    match mask {
        Some(mask) => residual.iter().zip(mask).filter(|(_, inside)| **inside).fold(0.0f64, |m, (v, _)| m.max(v.abs())),
        None => max_abs(residual),
    }
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

/// The stages of the final CLEAN's cycles: each goes on until a cycle takes nothing or its
/// residual's peak has reached its threshold ([`Reach`]).
enum Phase {
    /// The whole image, down to `auto_mask` sigmas; `strict`: under them, not within reach.
    Open { strict: bool },
    /// Around what the step's model and the open cycles found, down to `auto_threshold`.
    Masked(Vec<bool>),
    /// Around the compact islands, down to `compact_threshold`.
    Compact(Vec<bool>),
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

    /// A 32 x 32 field of unit Gaussian noise (seeded), a narrow Gaussian PSF and its 2N
    /// form, and the exact residual of a model on it (the dirty image minus the model
    /// convolved with the 2N PSF).
    struct NoiseField {
        n: usize,
        dirty: Vec<f64>,
        psf: Vec<f64>,
        psf_2n: Vec<f64>,
    }

    impl NoiseField {
        fn new(seed: u64) -> NoiseField {
            use rand::SeedableRng;
            use rand_distr::Distribution;
            let n = 32;
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let noise = rand_distr::Normal::new(0.0, 1.0).unwrap();
            let dirty: Vec<f64> = (0..n * n).map(|_| noise.sample(&mut rng)).collect();
            let gauss = |dx: f64, dy: f64| (-(dx * dx + dy * dy) / 2.0).exp();
            let psf: Vec<f64> = (0..n * n).map(|k| gauss((k % n) as f64 - 16.0, (k / n) as f64 - 16.0)).collect();
            let m = 2 * n;
            let psf_2n: Vec<f64> = (0..m * m).map(|k| gauss((k % m) as f64 - n as f64, (k / m) as f64 - n as f64)).collect();
            NoiseField { n, dirty, psf, psf_2n }
        }

        /// The noise and a point source of `flux` (sigmas) at pixel `source`.
        fn with_source(seed: u64, source: usize, flux: f64) -> NoiseField {
            let mut field = NoiseField::new(seed);
            let mut negative = vec![0.0; field.n * field.n];
            negative[source] = -flux;
            field.dirty = field.residual_of(&negative);
            field
        }

        fn input(&self) -> CleanInput<'_> {
            CleanInput { n: self.n, dirty: &self.dirty, psf: &self.psf, psf_2n: &self.psf_2n, mask: None }
        }

        fn residual_of(&self, x: &[f64]) -> Vec<f64> {
            let (n, m) = (self.n, 2 * self.n);
            let mut r = self.dirty.clone();
            for (j, &xj) in x.iter().enumerate().filter(|(_, v)| **v != 0.0) {
                let (sx, sy) = (j % n, j / n);
                for (k, v) in r.iter_mut().enumerate() {
                    *v -= xj * self.psf_2n[(k / n + n - sy) * m + (k % n + n - sx)];
                }
            }
            r
        }
    }

    /// Noise of robust sigma about 1 with one pixel at `peak` sigmas: the cycles the final
    /// CLEAN kept, how many exact residuals it asked for, and its residual's peak in robust
    /// sigmas.
    fn final_clean_of_a_peak_of(peak: f64) -> (usize, usize, f64) {
        let mut field = NoiseField::new(5);
        let n = field.n;
        let sigma = crate::metrics::robust_sigma(&field.dirty);
        field.dirty[16 * n + 16] = peak * sigma;
        let mut residuals = 0;
        let mut residual_of = |x: &[f64]| -> Result<Vec<f64>> {
            residuals += 1;
            Ok(field.residual_of(x))
        };
        let outcome = final_clean(&FinalCleanParams::default(), &field.input(), vec![0.0; n * n], field.dirty.clone(), &mut residual_of, &mut |_, _, _| ()).unwrap();
        let residual = field.residual_of(&outcome.model);
        (outcome.cycles, residuals, max_abs(&residual) / crate::metrics::robust_sigma(&residual))
    }

    /// The open phase cleans to `auto_mask` (5) sigmas: a peak under that costs no exact
    /// residual; one above it, even within reach of it, is cleaned, and the residual ends
    /// under the threshold.
    #[test]
    fn the_open_phase_ends_with_the_residual_under_its_threshold() {
        let (cycles, residuals, _) = final_clean_of_a_peak_of(5.0 * 0.97);
        assert_eq!((cycles, residuals), (0, 0));
        for over in [1.03, 1.5] {
            let (cycles, residuals, peak) = final_clean_of_a_peak_of(5.0 * over);
            assert!(cycles >= 1 && residuals >= 1, "a peak of {over} x 5 sigma: {cycles} cycles, {residuals} residuals");
            assert!(peak <= 5.0, "a peak of {over} x 5 sigma: the residual's peak ends at {peak:.2} sigma");
        }
    }

    #[test]
    fn faint_islands_are_those_below_the_noise_of_a_flux_over_their_area() {
        let n = 32;
        let mut model = vec![0.0; n * n];
        // Beams of 4 pixels, a threshold of 3 (Jy, over one beam): a 10 Jy point stays, a
        // 2 Jy speck goes, 100 pixels (25 beams: threshold 15) of 5 Jy in all go, of 20 stay.
        model[2 * n + 2] = 10.0;
        model[2 * n + 20] = 2.0;
        for y in 6..16 {
            for x in 2..12 {
                model[y * n + x] = 0.05;
                model[(y + 14) * n + x + 16] = 0.2;
            }
        }
        let faint = faint_islands_of(&model, n, 4.0, 3.0);
        let mut sizes: Vec<usize> = faint.iter().map(Vec::len).collect();
        sizes.sort();
        assert_eq!(sizes, vec![1, 100]);
        assert!(faint.iter().any(|i| i == &vec![2 * n + 20]));
        assert!(faint.iter().all(|i| !i.contains(&(2 * n + 2)) && !i.contains(&(20 * n + 20))));
    }

    /// A negative pixel beside a faint island leaves with it, unless it also touches an island
    /// that stays: then it corrects that island's wing and stays.
    #[test]
    fn negative_pixels_beside_a_faint_island_and_a_kept_one_stay() {
        let n = 16;
        let mut model = vec![0.0; n * n];
        // A 10 Jy source at (5, 5), a 0.5 Jy speck at (8, 5): the negative pixel at (7, 5)
        // touches only the speck, the one at (6, 6) both.
        model[5 * n + 5] = 10.0;
        model[5 * n + 8] = 0.5;
        model[5 * n + 7] = -0.1;
        model[6 * n + 6] = -0.2;
        // The speck's island holds (7, 6) too, beside the source's negative (6, 6).
        model[6 * n + 7] = 0.1;
        let faint = faint_islands_of(&model, n, 4.0, 3.0);
        assert_eq!(faint.len(), 1, "{faint:?}");
        let mut speck = faint[0].clone();
        speck.sort();
        assert_eq!(speck, vec![5 * n + 7, 5 * n + 8, 6 * n + 7]);
    }

    /// Data of noise and a 6 sigma point source; the step's model holds the source and a
    /// 1 sigma speck the data do not. The speck leaves the model (with the negative components
    /// the cycles took against it), the source stays, the residual is the exact one of what
    /// is left and the removal is handed on as a kept step; with `faint_island_sigmas` 0 the
    /// speck stays.
    #[test]
    fn a_faint_speck_leaves_the_model_with_the_exact_residual_and_a_source_stays() {
        let (n, source, speck) = (32, 20 * 32 + 20, 10 * 32 + 10);
        let field = NoiseField::with_source(7, source, 6.0);
        assert_eq!(field.n, n);
        let input = field.input();
        let residual_of = |x: &[f64]| -> Result<Vec<f64>> { Ok(field.residual_of(x)) };
        let mut model = vec![0.0; n * n];
        model[source] = 6.0;
        model[speck] = 1.0;
        let residual = residual_of(&model).unwrap();
        let mut handed = 0;
        let outcome = final_clean(&FinalCleanParams::default(), &input, model.clone(), residual.clone(), &mut |x| residual_of(x), &mut |_, _, _| handed += 1).unwrap();
        // (The masked cycles may take some of the speck's flux first: the residual dips there.)
        assert!(outcome.faint_islands >= 1 && outcome.faint_flux > 0.0 && outcome.faint_flux <= 1.0, "{} {}", outcome.faint_islands, outcome.faint_flux);
        assert!(block(speck, n).all(|k| outcome.model[k] == 0.0), "the speck and the components beside it left");
        assert!(outcome.model[source] > 5.0, "the source stays: {}", outcome.model[source]);
        assert_eq!(outcome.residual, residual_of(&outcome.model).unwrap());
        assert_eq!(handed, outcome.cycles + usize::from(outcome.scale_steps > 0) + 1);
        let keep = FinalCleanParams { faint_island_sigmas: 0.0, ..FinalCleanParams::default() };
        let outcome = final_clean(&keep, &input, model, residual, &mut |x| residual_of(x), &mut |_, _, _| ()).unwrap();
        assert_eq!(outcome.faint_islands, 0);
        assert!(outcome.model[speck] > 0.0);
        assert!(FinalCleanParams { faint_island_sigmas: -1.0, ..FinalCleanParams::default() }.checked().is_err());
    }

    /// A faint island that holds what the data measure (a source drawn with a wide, faint
    /// skirt: its flux is below the noise of a flux over its area) stays: its removal would
    /// leave the residual beside it above the open cycles' threshold.
    #[test]
    fn a_faint_island_whose_removal_the_data_refuse_stays() {
        let (n, source) = (32, 20 * 32 + 20);
        let field = NoiseField::with_source(7, source, 6.0);
        assert_eq!(field.n, n);
        let input = field.input();
        let residual_of = |x: &[f64]| -> Result<Vec<f64>> { Ok(field.residual_of(x)) };
        let mut model = vec![0.0; n * n];
        model[source] = 6.0;
        for y in 21..29 {
            for x in 5..31 {
                model[y * n + x] = 1e-3;
            }
        }
        let residual = residual_of(&model).unwrap();
        let beam = main_lobe_pixels(&field.psf, n) as f64 / std::f64::consts::LN_2;
        assert_eq!(faint_islands_of(&model, n, beam, 3.0 * robust_sigma(&residual)).len(), 1, "faint by its area");
        let outcome = final_clean(&FinalCleanParams::default(), &input, model, residual, &mut |x| residual_of(x), &mut |_, _, _| ()).unwrap();
        assert_eq!((outcome.faint_islands, outcome.faint_flux), (0, 0.0));
        assert!(outcome.model[source] > 5.0, "the source stays: {}", outcome.model[source]);
    }

    /// A Gaussian source a few PSFs wide that the step's model holds at 80 % of its flux, what
    /// is missing under the masked cycles' threshold (4 sigma here): the smoothed-residual
    /// steps give the model most of it, which the cycles alone leave in the residual; the
    /// residual handed on is the exact one, and with `scale_steps: 0` there are none.
    #[test]
    fn smoothed_residual_steps_give_the_model_the_flux_spread_below_the_threshold() {
        let n = 32;
        let mut field = NoiseField::new(11);
        let blob: Vec<f64> = (0..n * n).map(|k| {
            let (dx, dy) = ((k % n) as f64 - 16.0, (k / n) as f64 - 16.0);
            3.0 * (-(dx * dx + dy * dy) / (2.0 * 2.5 * 2.5)).exp()
        }).collect();
        let truth: f64 = blob.iter().sum();
        let negative: Vec<f64> = blob.iter().map(|v| -v).collect();
        field.dirty = field.residual_of(&negative);
        let input = field.input();
        let residual_of = |x: &[f64]| -> Result<Vec<f64>> { Ok(field.residual_of(x)) };
        let model: Vec<f64> = blob.iter().map(|v| 0.8 * v).collect();
        let residual = residual_of(&model).unwrap();
        let run = |params: &FinalCleanParams| final_clean(params, &input, model.clone(), residual.clone(), &mut |x| residual_of(x), &mut |_, _, _| ()).unwrap();
        let shallow = FinalCleanParams { auto_threshold: 4.0, ..FinalCleanParams::default() };
        let steps = run(&shallow);
        let none = run(&FinalCleanParams { scale_steps: 0, ..shallow.clone() });
        let missing = |o: &CleanOutcome<()>| (truth - o.model.iter().sum::<f64>()) / truth;
        assert_eq!((none.scale_steps, none.scale_flux), (0, 0.0));
        assert!(steps.scale_steps >= 1 && steps.scale_flux > 0.0, "{} steps, {} Jy", steps.scale_steps, steps.scale_flux);
        assert!(missing(&none) > 0.1, "the cycles alone leave {:.3} of the flux", missing(&none));
        assert!(missing(&steps).abs() < 0.5 * missing(&none), "with the steps {:.3} of the flux is missing, without {:.3}", missing(&steps), missing(&none));
        assert!(steps.ratio < none.ratio);
        assert_eq!(steps.residual, residual_of(&steps.model).unwrap());
        assert!(FinalCleanParams { scale_beams: 0.0, ..FinalCleanParams::default() }.checked().is_err());
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
