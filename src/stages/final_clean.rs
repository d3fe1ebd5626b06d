//! `kind: final_clean`: CLEAN major cycles on what the imaging loop's model leaves in the
//! residual, after the loop (`crate::deconv::final_clean`), each major cycle's residual
//! `x_d - D x` with `D` as the loop's residual updates applied it (where that is the Taylor
//! series in `w`, the residual written is the operator's).

use crate::deconv::final_clean::{final_clean, peak_sigmas, CleanInput, CleanOutcome};
pub use crate::deconv::final_clean::FinalCleanParams;
use crate::job::{Built, Emit, Imaging, Job, KindFn, Product};
use crate::pipeline::{Port, Role, Stage, StageParams};
use crate::Result;

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
        Ok(FinalCleanStage { config: config.checked()? })
    }
}

impl Stage<Job> for FinalCleanStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        if self.config.major_cycles == 0 {
            return emit(Port::Next, job);
        }
        // Where the divergence guard rejected the step's model, the data are imaged by CLEAN
        // alone (the cycles from the empty model): the iterate a series kept on data outside
        // its domain holds artefacts no cycle takes out. The job still says the step was
        // rejected (its stop, its warning, the exit status); a pipeline that calibrates against
        // its model is not left with an empty or spoiled one.
        let rejected = job.stop.as_ref().is_some_and(|s| s.reason.is_rejection());
        let id = job.id.clone();
        let truth = job.truth.clone();
        let truth_dynamic_range = job.truth_dynamic_range;
        let user_mask = job.mask.clone();
        let im = job.imaging_mut("final_clean")?;
        let (model, residual) = match rejected {
            true => (vec![0.0; im.model.len()], im.dirty.clone()),
            false => (std::mem::take(&mut im.model), std::mem::take(&mut im.residual)),
        };
        let (flux_before, peak_before) = (model.iter().sum::<f64>(), peak_sigmas(&residual));
        let im: &Imaging = im;
        // The cycles apply D as the updates did (the Taylor series in w where it stands for the
        // operator: its D x agreed with the operator's on the dirty image, at a fraction of an
        // application's cost), and compare residual ratios in that one form: they start from
        // the series' residual of the step's model, not the operator's the loop ended with,
        // which is written back where the model does not change. Otherwise the residual
        // written is the operator's, below.
        let by_taylor = im.updates_by_taylor();
        let mut residual_of = |x: &[f64]| -> Result<Vec<f64>> { Ok(im.dirty.iter().zip(im.normal_at_updates(x, "final_clean")?).map(|(d, v)| d - v).collect()) };
        let (residual, step_residual) = match (by_taylor, rejected) {
            (true, false) => (residual_of(&model)?, Some(residual)),
            // The empty model's residual, the dirty image, in every form of D.
            (true, true) => (residual.clone(), Some(residual)),
            (false, _) => (residual, None),
        };
        let input = CleanInput { n: im.geometry.size, dirty: &im.dirty, psf: &im.psf, psf_2n: &im.psf_2n, mask: user_mask.as_deref().map(Vec::as_slice) };
        // Each kept cycle is an iteration of the job's metrics, after the loop's.
        let mut on_kept = |model: &[f64], residual: &[f64], seconds: f64| {
            crate::job::iteration_figures(model, residual, &im.dirty, truth.as_deref(), truth_dynamic_range, seconds)
        };
        let outcome = final_clean(&self.config, &input, model, residual, &mut residual_of, &mut on_kept)?;
        let CleanOutcome { model, residual, model_changed, cycles, components, mut ratio, mut kept, faint_islands, faint_flux, scale_steps, scale_flux } = outcome;
        let im = job.imaging_mut("final_clean")?;
        (im.model, im.residual) = (model, residual);
        let mut taylor_off = None;
        match (model_changed, step_residual) {
            (false, Some(step_residual)) => im.residual = step_residual,
            (true, Some(_)) => {
                if let Some((deviation, warning)) = im.residual_through_the_operator("the final CLEAN's cycles")? {
                    log::info!("job {id}: the final CLEAN's residual through the operator: the Taylor series in w was {deviation:.1e} of D x from it on its model");
                    taylor_off = warning;
                }
            }
            (_, None) => {}
        }
        if by_taylor {
            ratio = crate::metrics::residual_ratio(&im.residual, &im.dirty);
            if let Some(last) = kept.last_mut() {
                last.residual_ratio = ratio;
            }
        }
        if let Some(warning) = taylor_off {
            job.warn(warning);
        }
        let changed = !kept.is_empty();
        for figures in kept {
            job.iteration += 1;
            job.push_iteration(figures);
        }
        if let Some(stop) = job.stop.as_mut().filter(|_| changed || rejected) {
            // The model written is the last kept step's (a cycle, or the faint islands' removal),
            // or the empty one CLEAN alone started from.
            stop.kept_iteration = if changed { job.iteration } else { 0 };
            stop.kept_residual_ratio = ratio;
        }
        if rejected {
            let held = if changed { "its model" } else { "the empty model (no cycle was kept)" };
            job.warn(format!("the step's model being rejected, the final CLEAN imaged the data from the empty model (CLEAN alone): {cycles} major cycles, residual ratio {ratio:.4}; the products hold {held}, and the exit status still says the step was rejected"));
        }
        let im = job.imaging_mut("final_clean")?;
        let (flux_after, peak_after) = (im.model.iter().sum::<f64>(), peak_sigmas(&im.residual));
        log::info!(
            "job {id}: final CLEAN on the residual: components at {components} pixels in {cycles} major cycles; {scale_steps} smoothed-residual steps ({scale_flux:.3e} Jy); {faint_islands} faint islands ({faint_flux:.3e} Jy) left the model; model flux {flux_before:.4e} -> {flux_after:.4e} Jy; residual peak {peak_before:.1} -> {peak_after:.1} sigma"
        );
        job.settings.insert(
            "final_clean".into(),
            serde_json::json!({
                "major_cycles": cycles,
                "component_pixels": components,
                "scale_steps": scale_steps,
                "scale_flux_jy": scale_flux,
                "faint_islands": faint_islands,
                "faint_flux_jy": faint_flux,
                "model_flux_before_jy": flux_before,
                "model_flux_after_jy": flux_after,
                "residual_peak_sigma_before": peak_before,
                "residual_peak_sigma_after": peak_after,
                // The depths it cleaned to (`--auto-threshold` sets the masked one).
                "auto_mask_sigmas": self.config.auto_mask,
                "auto_threshold_sigmas": self.config.auto_threshold,
                "compact_threshold_sigmas": self.config.compact_threshold,
            }),
        );
        emit(Port::Next, job)
    }
}

