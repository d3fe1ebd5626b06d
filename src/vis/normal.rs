//! The gridding pass of a job's samples for the form of `D` its plan chose
//! ([`OperatorPlan`]): the dirty image, the PSFs, and what the residual update applies
//! thereafter, from samples held, read from their file or in parts.

use super::data::Visibilities;
use super::operator::{check_gridded_samples, source_images, DataOperator, StreamedOperator};
use super::parted::PartPass;
use super::parts::{chunk_weights, w_toeplitz_images};
use super::stream::VisSource;
use crate::operator::plan::{self, Form, OperatorPlan, Reason, ToeplitzPass};
use crate::operator::taylor::{kernel_factor, WTaylor};
use crate::operator::{doubled_psf, doubled_psf_of, normalise_by_psf_peak, MeasurementOperator, WToeplitz, WTermMode};
use crate::weighting::WeightRule;
use crate::{Error, Result};
use std::sync::Arc;

/// What the gridding pass makes: the images, normalised, and `D`'s form.
pub struct GriddedForm {
    pub dirty: Vec<f64>,
    pub psf: Vec<f64>,
    pub psf_2n: Vec<f64>,
    /// The operator, where the residual update (or the final residual) runs through it.
    pub operator: Option<Arc<DataOperator>>,
    /// The samples, where the residual update's exact NUFFT round trip needs them later.
    pub kept: Option<Visibilities>,
    pub w_toeplitz: Option<Arc<WToeplitz>>,
    /// The Taylor series in w standing for the operator at the updates, with its deviation.
    pub w_taylor: Option<(WTaylor, f64)>,
    /// The operator's w-planes (the most of a chunk's where streamed); `None` for coplanar.
    pub planes: Option<usize>,
}

fn log_reason(id: &str, reason: Reason) {
    log::log!(reason.level, "job {id}: {}", reason.text);
}

/// Grids job `id`'s samples (`source`, weighted by `rule`) as `plan` chose, and logs why.
pub fn grid_planned(id: &str, source: VisSource, rule: WeightRule, mut plan: OperatorPlan) -> Result<GriddedForm> {
    std::mem::take(&mut plan.reasons).into_iter().for_each(|r| log_reason(id, r));
    log::debug!("job {id}: the normal operator's form is estimated to take {}", crate::limits::format_bytes(plan.bytes));
    if let Some(toeplitz) = plan.w_toeplitz.take() {
        let pass = pass(&plan, &rule, true, toeplitz.chunk_rows);
        if let Some(gridded) = toeplitz_pass(id, &source, &rule, toeplitz, pass)? {
            return Ok(gridded);
        }
    }
    let mut planes = None;
    let (dirty, psf, psf_2n, operator, kept, w_taylor) = match plan.form {
        Form::Streamed { chunk_rows } => streamed(id, source, rule, &plan, chunk_rows)?,
        Form::Held => held(id, source, rule, &plan)?,
        Form::Chunked => {
            // Gridded a chunk at a time as read (or where its parts live), then released: with
            // the w-term (images only), through each chunk's own w-planes.
            let images = source_images(&source, &pass(&plan, &rule, plan.w_term, plan.params.chunk_rows), &rule)?.normalise(plan.geometry.size)?;
            planes = images.planes;
            (images.dirty, images.psf, images.psf_2n, None, None, None)
        }
    };
    let planes = planes.or_else(|| operator.as_ref().and_then(|op| op.w_planes()));
    Ok(GriddedForm { dirty, psf, psf_2n, operator, kept, w_toeplitz: None, w_taylor, planes })
}

/// The images and `D`'s form of a branch that builds no w-aware Toeplitz form.
type Branch = (Vec<f64>, Vec<f64>, Vec<f64>, Option<Arc<DataOperator>>, Option<Visibilities>, Option<(WTaylor, f64)>);

fn pass(plan: &OperatorPlan, rule: &WeightRule, w_term: bool, chunk_rows: usize) -> PartPass {
    PartPass { uv: rule.uv(), ..PartPass::new(plan.geometry, rule.scheme(), 0.0, w_term, plan.params.nufft, plan.params.threads, chunk_rows) }
}

/// One pass over `source` for the dirty image and the kernels of `D`'s w-aware Toeplitz form,
/// normalised: the samples are not needed again. `None` where the source's parts cannot add
/// to one builder (they live in other processes).
fn toeplitz_pass(id: &str, source: &VisSource, rule: &WeightRule, toeplitz: ToeplitzPass, pass: PartPass) -> Result<Option<GriddedForm>> {
    let mut builder = toeplitz.builder;
    let geometry = pass.geometry()?;
    let (planes, taps, sigma) = (builder.planes(), builder.taps(), builder.sigma());
    let grid_bytes = builder.grid_bytes() as f64;
    let images = match source {
        VisSource::Parts(parts) => match parts.passes.w_toeplitz_images(&pass, rule, &mut builder)? {
            Some(images) => images,
            None => {
                log::info!("job {id}: the parts ({}) cannot add to one w-aware Toeplitz form: the residual update runs through the operator", parts.passes.describe());
                return Ok(None);
            }
        },
        _ => w_toeplitz_images(source, &pass, rule, &mut builder)?,
    };
    check_gridded_samples(source, images.samples)?;
    let (mut op, mut psf_2n) = builder.finish()?;
    let mut dirty = images.dirty;
    let mut psf = op.psf();
    let kappa = normalise_by_psf_peak(geometry.size, &mut dirty, &mut psf)?;
    psf_2n.iter_mut().for_each(|p| *p *= kappa);
    op.scale(kappa);
    log::info!(
        "job {id}: the residual update convolves with the kernels of {planes} w-planes ({taps} taps at oversampling {sigma}; {} kept, {} of grids while gridding), built in the gridding pass: the samples are read once",
        crate::limits::format_bytes(op.bytes() as f64),
        crate::limits::format_bytes(grid_bytes)
    );
    let w_toeplitz = Some(Arc::new(op));
    Ok(Some(GriddedForm { dirty, psf, psf_2n, operator: None, kept: None, w_toeplitz, w_taylor: None, planes: images.planes }))
}

/// The operator reading the samples again at each application: from their file, or where
/// their parts live.
fn streamed(id: &str, source: VisSource, rule: WeightRule, plan: &OperatorPlan, chunk_rows: usize) -> Result<Branch> {
    let samples = plan.samples.count;
    let from = match &source {
        VisSource::Parts(parts) => {
            log::info!("job {id}: the operator applies to the {samples} samples where they live ({}) at each residual update", parts.passes.describe());
            None
        }
        VisSource::Streamed(table) => Some(table.read_by_each_pass()),
        _ => Some("the file".into()),
    };
    let mut pass = pass(plan, &rule, plan.w_term, chunk_rows);
    if plan.w_term && plan.params.operator_chooses_oversampling {
        // As for samples held (below), from what is known of samples not at hand.
        let (geometry, samples) = (plan.geometry, plan.samples);
        pass.oversampling = crate::nufft::wgrid::operator_oversampling_of(geometry.size, geometry.pixel_rad, samples.count as usize, samples.max_abs_w, pass.epsilon);
        log::debug!("job {id}: the w-term operator grids at oversampling {}", pass.oversampling);
    }
    let g = StreamedOperator::grid(source, rule, pass)?;
    let mut w_taylor = None;
    if plan.taylor {
        // A pass over the samples per order, against one for every update after.
        let op = &g.operator;
        let kernel = |order| op.doubled_psf_of(|w| kernel_factor(w, order));
        w_taylor = plan::taylor_series(plan.geometry, plan.params, &g.psf_2n, &g.dirty, || op.apply_normal(&g.dirty), kernel, |r| log_reason(id, r))?;
    }
    if let Some(from) = from {
        let when = if w_taylor.is_some() { "for the final residual" } else { "at each residual update" };
        log::info!(
            "job {id}: the operator reads the {samples} samples again from {from} {when} (holding them would take about {}, above the gridder's hold_mb {})",
            crate::limits::format_bytes(plan.held_bytes),
            plan.params.hold_bytes / 1e6
        );
    }
    Ok((g.dirty, g.psf, g.psf_2n, Some(Arc::new(DataOperator::Streamed(g.operator))), None, w_taylor))
}

/// The operator holding the samples in memory (kept with them where the exact NUFFT round
/// trip needs them later; otherwise all but their baselines are released).
fn held(id: &str, source: VisSource, rule: WeightRule, plan: &OperatorPlan) -> Result<Branch> {
    let (geometry, params, samples) = (plan.geometry, plan.params, plan.samples.count);
    if plan.samples.streamed {
        // Above what stays held (`plan.held_bytes`), for the build.
        let building = samples as f64 * crate::operator::plan::BUILD_BYTES_PER_SAMPLE;
        crate::limits::check_memory(building, &format!("the {samples} samples of job '{id}' held for the operator (while it is built)"))
            .map_err(|m| Error::parameter("gridder", format!("{m}: lower the gridder's hold_mb so that the samples are read from the file at each update instead")))?;
        log::info!(
            "job {id}: the operator holds the {samples} samples in memory (about {}; about {} while it is built)",
            crate::limits::format_bytes(plan.held_bytes),
            crate::limits::format_bytes(building)
        );
    }
    let mut vis = source.into_held()?;
    let weight = chunk_weights(&vis.chunk(0..vis.len()), geometry, &rule)?;
    drop(rule);
    let keep = params.keep_operator;
    if !keep {
        vis.frequency = Vec::new();
        vis.weight = Vec::new(); // natural weights: the total weights replace them
        vis.imaging_weight = Vec::new();
    }
    let mode = if plan.w_term { WTermMode::On } else { WTermMode::Off };
    // Applied at every update, its grids' FFTs are what the w-term costs: with few samples a
    // smaller grid and a wider kernel are cheaper, and take less memory.
    let mut nufft = params.nufft;
    if plan.w_term && params.operator_chooses_oversampling {
        nufft.oversampling = crate::nufft::wgrid::operator_oversampling(geometry.size, geometry.pixel_rad, &vis.w, nufft.epsilon);
        log::debug!("job {id}: the w-term operator grids at oversampling {}", nufft.oversampling);
    }
    let operator = MeasurementOperator::for_mode(mode, geometry, &vis.u, &vis.v, &vis.w, &weight, nufft, params.threads)?;
    let (dirty, psf) = operator.dirty_image_and_psf(&vis.vis);
    // The doubled PSF's grid (twice the field's) is the largest the job makes: at the same
    // oversampling.
    let psf_2n = doubled_psf(geometry, &vis.u, &vis.v, &weight, operator.kappa(), nufft, params.threads)?;
    let mut w_taylor = None;
    if plan.taylor {
        let (u, v, w, kappa) = (&vis.u, &vis.v, &vis.w, operator.kappa());
        let kernel = |order| doubled_psf_of(geometry, u, v, &weight, |k| kernel_factor(w[k], order), kappa, nufft, params.threads);
        w_taylor = plan::taylor_series(geometry, params, &psf_2n, &dirty, || Ok(operator.apply_normal(&dirty)), kernel, |r| log_reason(id, r))?;
    }
    if !keep {
        vis.vis = Vec::new();
        vis.w = Vec::new();
    }
    let kept = keep.then_some(vis);
    Ok((dirty, psf, psf_2n, Some(Arc::new(DataOperator::Held(operator.into_normal()))), kept, w_taylor))
}
