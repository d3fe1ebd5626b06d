//! `kind: gridder`: dirty image, PSF (N and 2N), kappa and the restoring beam, with the w-term
//! where it matters (`w_term`). Releases the visibilities unless the residual update runs a
//! NUFFT round trip; keeps the operator where the w-term makes the PSF convolution inexact.

use super::params::GridderParams;
use crate::nufft::NufftParams;
use crate::operator::{doubled_psf, doubled_psf_of, normalise_by_psf_peak, ImageGeometry, MeasurementOperator, PsfConvolution, WTermMode};
use crate::operator::taylor::{self as w_taylor, WTaylor};
use crate::operator::toeplitz::{WToeplitz, WToeplitzBuilder, WToeplitzPlan};
use crate::weighting::WeightRule;
use crate::job::{Emit, Imaging, Job};
use crate::pipeline::{Port, Stage};
use crate::vis::{check_gridded_samples, chunk_weights, source_images, w_toeplitz_images, DataOperator, PartPass, StreamedOperator, VisSource};
use crate::{Error, Result};
use std::sync::Arc;

/// What an operator holds per sample (baselines, value, weight, its plan's sorting and
/// positions): what a streamed table costs when the residual update needs the operator.
const OPERATOR_BYTES_PER_SAMPLE: f64 = 100.0;

/// What a chunk of a streamed operator costs per sample: the samples as read, their weights
/// and the chunk's plan (measured at 1e8 samples: 140).
const STREAMED_BYTES_PER_SAMPLE: f64 = 150.0;

pub struct GridderStage {
    nufft: NufftParams,
    w_term: WTermMode,
    hold_bytes: f64,
    chunk_rows: usize,
    threads: usize,
    keep_operator: bool,
}

impl GridderStage {
    pub fn new(config: GridderParams, threads: usize, keep_operator: bool) -> Result<GridderStage> {
        let nufft = NufftParams { epsilon: config.epsilon, oversampling: config.oversampling };
        crate::nufft::kernel::KernelShape::for_accuracy(nufft.epsilon, nufft.oversampling)?;
        if !(config.hold_mb >= 0.0) || !config.hold_mb.is_finite() {
            return Err(Error::parameter("hold_mb", format!("expected a number of megabytes >= 0, got {}", config.hold_mb)));
        }
        if config.chunk_rows == 0 {
            return Err(Error::parameter("chunk_rows", "expected at least 1 sample per chunk"));
        }
        Ok(GridderStage { nufft, w_term: config.w_term, hold_bytes: config.hold_mb * 1e6, chunk_rows: config.chunk_rows, threads, keep_operator })
    }

    /// The builder of the w-aware Toeplitz form of `D` for a job whose samples reach `|w| <=
    /// max_abs_w` and `sqrt(u^2 + v^2) <= max_uv`, if one is accurate enough and fits in memory
    /// (otherwise the residual update is a Taylor series in w or runs through the operator, and
    /// the log says why).
    /// It is chosen where it takes at most `hold_mb`, or less than the samples would take held in
    /// the operator (reading them again at every update instead being the slow alternative).
    fn w_toeplitz_builder(&self, id: &str, geometry: ImageGeometry, max_abs_w: f64, max_uv: f64, samples: u64) -> Option<WToeplitzBuilder> {
        let Some(plan) = WToeplitzPlan::new(geometry, max_abs_w, self.nufft.epsilon) else {
            log::info!(
                "job {id}: no w-aware Toeplitz form of at most 24 taps reaches the accuracy {:e} for |w| up to {max_abs_w:e} on this field (or the field reaches the edge of the projection)",
                self.nufft.epsilon
            );
            return None;
        };
        let bytes = match WToeplitzBuilder::estimated_bytes(geometry, &plan, max_uv, self.nufft) {
            Ok(bytes) => bytes,
            Err(e) => {
                log::info!("job {id}: no w-aware Toeplitz form for the residual update: {e}");
                return None;
            }
        };
        let held = OPERATOR_BYTES_PER_SAMPLE * samples as f64;
        if bytes > self.hold_bytes && bytes > held {
            log::info!(
                "job {id}: no w-aware Toeplitz form for the residual update: its kernels ({} w-planes) would take {} while gridding, above the gridder's hold_mb {} and above the {} the samples take held",
                plan.planes,
                crate::limits::format_bytes(bytes),
                self.hold_bytes / 1e6,
                crate::limits::format_bytes(held)
            );
            return None;
        }
        WToeplitzBuilder::new(geometry, plan, max_uv, self.nufft, self.threads)
            .map_err(|e| log::info!("job {id}: no w-aware Toeplitz form for the residual update: {e}"))
            .ok()
    }

    /// The residual update's Taylor series in `w` of the PSF convolution (`crate::operator::taylor`),
    /// of the lowest order whose `D` of the dirty image agrees with the operator's
    /// (`reference`, made once the first order fits) to [`w_taylor::TOLERANCE`] times the
    /// NUFFT's accuracy, with that deviation; `kernel(m)` grids `R_m` from the samples, held
    /// or read again from their file. `None` where no order up to [`w_taylor::MAX_ORDER`] does
    /// within the gridder's hold_mb (the operator then runs at each update, and the log says why).
    fn w_taylor(
        &self,
        id: &str,
        geometry: ImageGeometry,
        psf_2n: &[f64],
        dirty: &[f64],
        reference: impl FnOnce() -> Result<Vec<f64>>,
        mut kernel: impl FnMut(usize) -> Result<Vec<f64>>,
    ) -> Result<Option<(WTaylor, f64)>> {
        let tolerance = w_taylor::TOLERANCE * self.nufft.epsilon;
        // Each order keeps one more complex 2N x 2N kernel, and applying it takes two more
        // such arrays per two orders.
        let kernel_bytes = (4 * geometry.pixels() * std::mem::size_of::<num_complex::Complex64>()) as f64;
        // The form so far and the operator's D of the dirty image, made at the first order
        // that fits.
        let mut made: Option<(WTaylor, Vec<f64>)> = None;
        let mut reference = Some(reference);
        let mut closest = None;
        // The order whose kernels would not fit in hold_mb, where that ended the search.
        let mut capped = None;
        for order in 1..=w_taylor::MAX_ORDER {
            let bytes = kernel_bytes * (order + 1 + 2 * (order + 1).div_ceil(2)) as f64;
            if bytes > self.hold_bytes {
                capped = Some(order);
                break;
            }
            let (form, reference) = match &mut made {
                Some(made) => made,
                None => {
                    let reference = reference.take().expect("taken once, with the first order")()?;
                    made.insert((WTaylor::new(geometry, &[psf_2n.to_vec()], self.threads)?, reference))
                }
            };
            form.push_kernel(&kernel(order)?)?;
            let deviation = form.deviation(dirty, reference);
            log::debug!("job {id}: a Taylor series in w of order {order} differs from the operator by {deviation:.2e} on the dirty image");
            if deviation <= tolerance {
                log::info!(
                    "job {id}: the residual update convolves with the kernels of a Taylor series in w of order {order} ({} kept): on the dirty image it differs from the operator by {deviation:.1e}, within {tolerance:.0e} (the written residual is the operator's)",
                    crate::limits::format_bytes(form.bytes() as f64)
                );
                let (form, _) = made.expect("made above");
                return Ok(Some((form, deviation)));
            }
            closest = Some((order, deviation));
        }
        let hold_mb = self.hold_bytes / 1e6;
        match (closest, capped) {
            (Some((order, deviation)), None) => log::info!(
                "job {id}: the residual update runs through the operator: no Taylor series in w up to order {order} comes within {tolerance:.0e} of it on the dirty image ({deviation:.1e}: the w-term is too large for it here)"
            ),
            (Some((order, deviation)), Some(next)) => log::info!(
                "job {id}: the residual update runs through the operator: a Taylor series in w of order {order} is {deviation:.1e} from it on the dirty image (above {tolerance:.0e}), and the kernels of order {next} would take more than the gridder's hold_mb {hold_mb}"
            ),
            (None, _) => log::info!("job {id}: the residual update runs through the operator: the kernels of a Taylor series in w would take more than the gridder's hold_mb {hold_mb}"),
        }
        Ok(None)
    }

    /// One pass over `source` for the dirty image and the kernels of `D`'s w-aware Toeplitz
    /// form, normalised: the samples are not needed again. `None` where the source's parts
    /// cannot add to one builder (they live in other processes).
    fn w_toeplitz_pass(&self, id: &str, source: &VisSource, rule: &WeightRule, mut builder: WToeplitzBuilder, pass: PartPass) -> Result<Option<ToeplitzImages>> {
        let geometry = pass.geometry()?;
        let (planes, taps, sigma) = (builder.planes(), builder.taps(), builder.sigma());
        let grid_bytes = builder.grid_bytes() as f64;
        // The chunks take what the hold limit leaves beside the kernels' grids.
        let room = (self.hold_bytes - grid_bytes).max(0.0);
        let pass = PartPass { chunk_rows: self.chunk_rows.max((room / STREAMED_BYTES_PER_SAMPLE) as usize), ..pass };
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
        Ok(Some(ToeplitzImages { dirty, psf, psf_2n, planes: images.planes, operator: op }))
    }
}

/// What [`GridderStage::w_toeplitz_pass`] makes.
struct ToeplitzImages {
    dirty: Vec<f64>,
    psf: Vec<f64>,
    psf_2n: Vec<f64>,
    /// The most w-planes of a chunk's operator (the dirty image's).
    planes: Option<usize>,
    operator: WToeplitz,
}

impl Stage<Job> for GridderStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        let (geometry, rule) = job.take_weights("gridder")?;
        let source = job.take_visibilities("gridder")?;
        let summary = source.summary();
        let (frequency_hz, bandwidth_hz) = summary.band().map_or((None, None), |(centre, width)| (Some(centre), width));
        let max_abs_w = summary.max_abs_w;
        let max_phase = crate::nufft::wgrid::max_w_phase(geometry.size, geometry.pixel_rad, max_abs_w);
        let w_term = self.w_term.includes(geometry, max_abs_w, self.nufft.epsilon);
        // With the w-term the PSF convolution is not D (the response depends on the position
        // in the field): the operator, which holds the samples, is kept for the residual
        // update. Otherwise the samples are gridded a chunk at a time as they are read, and
        // nothing the size of the table is ever held.
        let needs_operator = w_term || self.keep_operator;
        let in_parts = matches!(source, VisSource::Parts(_));
        if in_parts && self.keep_operator {
            return Err(Error::parameter(
                "method",
                format!("job '{}' is in parts gridded where they live, and the residual update's exact NUFFT round trip needs its samples in one process: use method: toeplitz", job.id),
            ));
        }
        let held_bytes = OPERATOR_BYTES_PER_SAMPLE * summary.samples as f64;
        let stream_operator = needs_operator && (in_parts || (source.is_streamed() && held_bytes > self.hold_bytes));
        let scheme = rule.scheme();
        let pass = |w_term: bool, chunk_rows: usize| PartPass::new(geometry, scheme, 0.0, w_term, self.nufft, self.threads, chunk_rows);
        // With the w-term and the convolution form of the residual update, one pass makes the
        // dirty image and the kernels of D's w-aware Toeplitz form: the samples are not needed
        // again, whatever their number.
        let builder = if w_term && !self.keep_operator { self.w_toeplitz_builder(&job.id, geometry, max_abs_w, summary.max_uv, summary.samples) } else { None };
        let toeplitz = match builder {
            Some(builder) => self.w_toeplitz_pass(&job.id, &source, &rule, builder, pass(true, self.chunk_rows))?,
            None => None,
        };
        let mut dirty_planes = None;
        let mut w_taylor = None;
        let (dirty, psf, psf_2n, operator, kept, w_toeplitz) = if let Some(images) = toeplitz {
            drop(source);
            dirty_planes = images.planes;
            (images.dirty, images.psf, images.psf_2n, None, None, Some(Arc::new(images.operator)))
        } else if stream_operator {
            let from = match &source {
                VisSource::Parts(parts) => {
                    log::info!("job {}: the operator applies to the {} samples where they live ({}) at each residual update", job.id, summary.samples, parts.passes.describe());
                    None
                }
                VisSource::Streamed(table) => Some(table.read_by_each_pass()),
                _ => Some("the file".into()),
            };
            // Chunks as large as the hold limit allows: each costs its w-planes' FFTs.
            let chunk_rows = self.chunk_rows.max((self.hold_bytes / STREAMED_BYTES_PER_SAMPLE) as usize);
            let g = StreamedOperator::grid(source, rule, pass(w_term, chunk_rows))?;
            if w_term && !self.keep_operator && !in_parts {
                // A pass over the samples per order, against one for every update after.
                let op = &g.operator;
                let kernel = |order| op.doubled_psf_of(|w| w_taylor::kernel_factor(w, order));
                w_taylor = self.w_taylor(&job.id, geometry, &g.psf_2n, &g.dirty, || op.apply_normal(&g.dirty), kernel)?;
            }
            if let Some(from) = from {
                let when = if w_taylor.is_some() { "for the final residual" } else { "at each residual update" };
                log::info!(
                    "job {}: the operator reads the {} samples again from {from} {when} (holding them would take about {}, above the gridder's hold_mb {})",
                    job.id,
                    summary.samples,
                    crate::limits::format_bytes(held_bytes),
                    self.hold_bytes / 1e6
                );
            }
            (g.dirty, g.psf, g.psf_2n, Some(Arc::new(DataOperator::Streamed(g.operator))), None, None)
        } else if needs_operator {
            if source.is_streamed() {
                crate::limits::check_memory(held_bytes, &format!("the {} samples of job '{}' held for the operator", summary.samples, job.id))
                    .map_err(|m| Error::parameter("gridder", format!("{m}: lower the gridder's hold_mb so that the samples are read from the file at each update instead")))?;
                log::info!("job {}: the operator holds the {} samples in memory (about {})", job.id, summary.samples, crate::limits::format_bytes(held_bytes));
            }
            let mut vis = source.into_held()?;
            let weight = chunk_weights(&vis.chunk(0..vis.len()), geometry, &rule)?;
            drop(rule);
            if !self.keep_operator {
                vis.frequency = Vec::new();
                vis.weight = Vec::new(); // natural weights: the total weights replace them
                vis.imaging_weight = Vec::new();
            }
            let operator = MeasurementOperator::for_mode(
                if w_term { WTermMode::On } else { WTermMode::Off },
                geometry,
                &vis.u,
                &vis.v,
                &vis.w,
                &weight,
                self.nufft,
                self.threads,
            )?;
            let (dirty, psf) = operator.dirty_image_and_psf(&vis.vis);
            let psf_2n = doubled_psf(geometry, &vis.u, &vis.v, &weight, operator.kappa(), self.nufft, self.threads)?;
            if w_term && !self.keep_operator {
                let (u, v, w, kappa) = (&vis.u, &vis.v, &vis.w, operator.kappa());
                let kernel = |order| doubled_psf_of(geometry, u, v, &weight, |k| w_taylor::kernel_factor(w[k], order), kappa, self.nufft, self.threads);
                w_taylor = self.w_taylor(&job.id, geometry, &psf_2n, &dirty, || Ok(operator.apply_normal(&dirty)), kernel)?;
            }
            if !self.keep_operator {
                vis.vis = Vec::new();
                vis.w = Vec::new();
            }
            let kept = self.keep_operator.then_some(vis);
            (dirty, psf, psf_2n, Some(Arc::new(DataOperator::Held(operator))), kept, None)
        } else {
            // Gridded a chunk at a time as read (or where its parts live), then released.
            let images = source_images(&source, &pass(false, self.chunk_rows), &rule)?.normalise(geometry.size)?;
            drop(source);
            (images.dirty, images.psf, images.psf_2n, None, None, None)
        };
        let planes = operator.as_ref().and_then(|op| op.w_planes()).or(dirty_planes);
        let toeplitz_inexact = w_term.then(|| {
            format!("the operator includes the w-term (phase up to {max_phase:.3} rad over the field), which a PSF convolution does not")
        });
        match (w_term, self.w_term) {
            (true, _) => log::info!(
                "job {}: the w-term is corrected by w-gridding ({} w-planes; |w| up to {max_abs_w:.4e} wavelengths turns the phase by up to {max_phase:.3} rad at the field's corners)",
                job.id,
                planes.unwrap_or(1)
            ),
            (false, WTermMode::Off) => {
                if let Some(warning) = (crate::imaging::WTerm { max_abs_w, max_phase_rad: max_phase }).warning(geometry) {
                    job.warn(format!("{warning} (w_term: off)"));
                }
            }
            (false, _) => log::info!("job {}: the w-term is left out: it turns no phase by more than {max_phase:.2e} rad over the field (below the NUFFT's accuracy)", job.id),
        }
        job.settings.insert(
            "w_term".into(),
            serde_json::json!({"mode": self.w_term.name(), "corrected": w_term, "planes": planes, "max_abs_w": max_abs_w, "max_phase_rad": max_phase,
                "toeplitz_planes": w_toeplitz.as_ref().map(|op| op.planes()),
                "taylor_order": w_taylor.as_ref().map(|(form, _): &(WTaylor, f64)| form.order()),
                "taylor_deviation": w_taylor.as_ref().map(|(_, deviation)| *deviation)}),
        );
        crate::sanity::check_image(&dirty, geometry.size, "dirty image", "the visibilities or weights hold values too large to image (check the data column and the weights)")?;
        let psf_convolution = PsfConvolution::new(geometry.size, &psf_2n)?;
        let beam = match crate::deconv::restoring_beam(&psf, geometry.size, geometry.pixel_rad) {
            Ok((b, warning)) => {
                if let Some(w) = warning {
                    job.warn(w);
                }
                Some(b)
            }
            Err(e) => {
                job.warn(format!("no restoring beam: {e}"));
                None
            }
        };
        let n = geometry.pixels();
        job.imaging = Some(Imaging {
            geometry,
            residual: dirty.clone(),
            dirty,
            psf,
            psf_convolution: Arc::new(psf_convolution),
            psf_2n: Arc::new(psf_2n),
            operator,
            toeplitz_inexact,
            w_toeplitz,
            w_taylor: w_taylor.map(|(form, _)| Arc::new(form)),
            nufft: self.nufft,
            w_term,
            model: vec![0.0; n],
            beam,
            frequency_hz,
            bandwidth_hz,
            best: None,
        });
        if let Some(vis) = kept {
            job.vis = Some(VisSource::Held(Arc::new(vis)));
        }
        emit(Port::Next, job)
    }
}
