//! The plan of a job's normal operator `D`: the form the residual update applies, why that
//! form and not another (its reasons, for the log), and the memory it is estimated to take,
//! decided from plain numbers about the samples ([`Samples`]) and the gridder's limits
//! ([`PlanParams`]); and the search for the order of `D`'s Taylor series in w. Building the
//! chosen form needs the samples, and is left to what holds them (`crate::vis`).
//!
//! The forms, first choice first where the w-term is included and no exact NUFFT round trip
//! is asked for: the w-aware Toeplitz form (`super::toeplitz`), its kernels built in the
//! gridding pass; else the operator, its samples held or read again at each update, with a
//! Taylor series in w (`super::taylor`) in its place at the updates where one agrees with it.
//! Without the w-term, `D` is the PSF convolution and no operator is kept unless asked for.
//! Where no stage applies `D` (only the dirty image and the PSFs are asked for: `r2d2 dirty`),
//! no form of it is made: the samples are gridded as read, through each chunk's own w-planes
//! where the w-term is included.

use super::geometry::ImageGeometry;
use super::measurement::WTermMode;
use super::taylor::{self, WTaylor};
use super::toeplitz::{WToeplitzBuilder, WToeplitzPlan};
use crate::nufft::wgrid::max_w_phase;
use crate::nufft::NufftParams;
use crate::Result;

/// What an operator kept with its samples holds per sample (baselines, value, weight, its
/// plan's sorting and positions): where the exact NUFFT round trip needs them later.
pub const OPERATOR_BYTES_PER_SAMPLE: f64 = 100.0;

/// What `D` alone holds per sample held (`crate::operator::NormalOperator`: grid position,
/// first w-plane and cell, weight) and the value each application passes between its two
/// directions.
pub const NORMAL_BYTES_PER_SAMPLE: f64 = 56.0;

/// What the samples take held: `D` alone, or the operator kept with them.
fn held_bytes_per_sample(params: &PlanParams) -> f64 {
    if params.keep_operator {
        OPERATOR_BYTES_PER_SAMPLE
    } else {
        NORMAL_BYTES_PER_SAMPLE
    }
}

/// What building an operator over samples costs per sample: the samples as read, their
/// weights, the plan with its sorting, and the values spread through it. A streamed chunk's
/// cost, and that of samples to be held while their operator is built.
pub const BUILD_BYTES_PER_SAMPLE: f64 = 150.0;

/// What the gridder asks of `D`.
#[derive(Clone, Copy, Debug)]
pub struct PlanParams {
    pub nufft: NufftParams,
    pub w_term: WTermMode,
    /// Bytes the samples may take held; beyond them they are read again at each application.
    pub hold_bytes: f64,
    /// Bytes the kernels of a convolution form of `D` (the w-aware Toeplitz form's while
    /// gridding, the Taylor series') may take.
    pub kernel_bytes: f64,
    /// The fewest samples a chunk reads.
    pub chunk_rows: usize,
    pub threads: usize,
    /// The residual update's exact NUFFT round trip: the operator is kept, with or without
    /// the w-term.
    pub keep_operator: bool,
    /// Only the images are asked for (no stage after the gridder applies `D`): no form of `D`
    /// is planned, and the samples are gridded a chunk at a time as read.
    pub images_only: bool,
    /// No oversampling was asked for: an operator that corrects the w-term, its samples held
    /// or read again at each update, chooses its own (`nufft::wgrid::operator_oversampling`);
    /// everything else uses `nufft`'s.
    pub operator_chooses_oversampling: bool,
}

/// The job's samples, as far as the plan needs to know them.
#[derive(Clone, Copy, Debug)]
pub struct Samples {
    pub count: u64,
    /// The largest `|w|`, wavelengths.
    pub max_abs_w: f64,
    /// The largest `sqrt(u^2 + v^2)`, wavelengths.
    pub max_uv: f64,
    /// Read again from their file at each pass, not held.
    pub streamed: bool,
    /// In parts gridded where they live.
    pub in_parts: bool,
}

/// A line of the plan's reasoning, for the log.
#[derive(Clone, Debug, PartialEq)]
pub struct Reason {
    pub level: log::Level,
    pub text: String,
}

impl Reason {
    fn info(text: String) -> Reason {
        Reason { level: log::Level::Info, text }
    }
}

/// The form of `D` where its w-aware Toeplitz form is not built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Form {
    /// The operator, its samples read again at each application: from their file a chunk of
    /// `chunk_rows` at a time, or where their parts live.
    Streamed { chunk_rows: usize },
    /// The operator, its samples held in memory.
    Held,
    /// No operator: the samples gridded a chunk at a time as read (with the w-term, through
    /// each chunk's own w-planes: images only), then released; `D` is the PSF convolution.
    Chunked,
}

/// The w-aware Toeplitz form's gridding pass: its builder, the samples a chunk reads beside
/// its grids, and the bytes it takes at most.
pub struct ToeplitzPass {
    pub builder: WToeplitzBuilder,
    pub chunk_rows: usize,
    pub bytes: f64,
}

/// The chosen form of `D` for a job, with its reasons and its estimated memory.
pub struct OperatorPlan {
    pub geometry: ImageGeometry,
    pub samples: Samples,
    pub params: PlanParams,
    /// Whether the operator includes the w-term.
    pub w_term: bool,
    /// The largest phase the w-term turns over the field (radians).
    pub max_phase_rad: f64,
    /// The first choice, where one is accurate and fits: its kernels built in the gridding
    /// pass, after which the samples are not needed.
    pub w_toeplitz: Option<ToeplitzPass>,
    /// The form otherwise, and where the parts cannot add to one Toeplitz builder.
    pub form: Form,
    /// Whether a Taylor series in w is sought to stand for the operator at the updates.
    pub taylor: bool,
    /// What the samples would take held in the operator.
    pub held_bytes: f64,
    /// What the chosen form is estimated to take: the Toeplitz form's builder, the samples
    /// held, or one chunk as read.
    pub bytes: f64,
    /// Why the forms before the chosen one were not.
    pub reasons: Vec<Reason>,
}

impl OperatorPlan {
    /// The form of `D` for samples described by `samples` on `geometry`, as `params` ask.
    pub fn new(geometry: ImageGeometry, samples: Samples, params: PlanParams) -> OperatorPlan {
        let w_term = params.w_term.includes(geometry, samples.max_abs_w, params.nufft.epsilon);
        // With the w-term the PSF convolution is not D (the response depends on the position in
        // the field): the operator, which holds the samples, is kept for the residual update.
        // Otherwise, and where no stage applies D (images only), the samples are gridded a chunk
        // at a time as they are read, and nothing the size of the table is ever held.
        let needs_operator = !params.images_only && (w_term || params.keep_operator);
        let held_bytes = held_bytes_per_sample(&params) * samples.count as f64;
        let form = if needs_operator && (samples.in_parts || (samples.streamed && held_bytes > params.hold_bytes)) {
            // Chunks as large as the hold limit allows: each costs its w-planes' FFTs.
            Form::Streamed { chunk_rows: params.chunk_rows.max((params.hold_bytes / BUILD_BYTES_PER_SAMPLE) as usize) }
        } else if needs_operator {
            Form::Held
        } else {
            Form::Chunked
        };
        let mut reasons = Vec::new();
        // With the w-term and the convolution form of the residual update, one pass makes the
        // dirty image and the kernels of D's w-aware Toeplitz form: the samples are not needed
        // again, whatever their number.
        let convolution_form = w_term && !params.keep_operator && !params.images_only;
        let w_toeplitz = convolution_form
            .then(|| toeplitz_pass(geometry, samples, params).map_err(|why| reasons.push(Reason::info(why))).ok())
            .flatten();
        let bytes = match (&w_toeplitz, form) {
            (Some(pass), _) => pass.bytes,
            (None, Form::Held) => held_bytes,
            (None, Form::Streamed { chunk_rows }) => chunk_rows as f64 * BUILD_BYTES_PER_SAMPLE,
            (None, Form::Chunked) => params.chunk_rows as f64 * BUILD_BYTES_PER_SAMPLE,
        };
        OperatorPlan {
            geometry,
            samples,
            params,
            w_term,
            max_phase_rad: max_w_phase(geometry.size, geometry.pixel_rad, samples.max_abs_w),
            w_toeplitz,
            form,
            // Parts elsewhere make no kernels of the series.
            taylor: convolution_form && !samples.in_parts,
            held_bytes,
            bytes,
            reasons,
        }
    }
}

/// The w-aware Toeplitz form's pass, or why there is none: none is accurate enough, or it
/// would take more than `kernel_bytes` and more than the samples held in the operator (reading
/// them again at every update instead being the slow alternative).
fn toeplitz_pass(geometry: ImageGeometry, samples: Samples, params: PlanParams) -> std::result::Result<ToeplitzPass, String> {
    let (epsilon, max_abs_w) = (params.nufft.epsilon, samples.max_abs_w);
    let Some(plan) = WToeplitzPlan::new(geometry, max_abs_w, epsilon) else {
        return Err(format!(
            "no w-aware Toeplitz form of at most 24 taps reaches the accuracy {epsilon:e} for |w| up to {max_abs_w:e} on this field (or the field reaches the edge of the projection)"
        ));
    };
    let no_form = |e: crate::Error| format!("no w-aware Toeplitz form for the residual update: {e}");
    let bytes = WToeplitzBuilder::estimated_bytes(geometry, &plan, samples.max_uv, params.nufft).map_err(no_form)?;
    let held = held_bytes_per_sample(&params) * samples.count as f64;
    if bytes > params.kernel_bytes && bytes > held {
        return Err(format!(
            "no w-aware Toeplitz form for the residual update: its kernels ({} w-planes) would take {} while gridding, above the gridder's kernel_mb {} and above the {} the samples take held",
            plan.planes,
            crate::limits::format_bytes(bytes),
            params.kernel_bytes / 1e6,
            crate::limits::format_bytes(held)
        ));
    }
    let builder = WToeplitzBuilder::new(geometry, plan, samples.max_uv, params.nufft, params.threads).map_err(no_form)?;
    // The chunks take what half the hold limit leaves beside the kernels' grids: they pass
    // (nothing of them is held after the pass), and beyond a few million samples a chunk's
    // fixed cost (its w-planes' FFTs for the dirty image) is small beside its spreading.
    let room = (0.5 * params.hold_bytes - builder.grid_bytes() as f64).max(0.0);
    let chunk_rows = params.chunk_rows.max((room / BUILD_BYTES_PER_SAMPLE) as usize);
    Ok(ToeplitzPass { builder, chunk_rows, bytes })
}

/// The residual update's Taylor series in `w` of the PSF convolution ([`super::taylor`]), of
/// the lowest order whose `D` of the dirty image agrees with the operator's (`reference`, made
/// once the first order fits) to [`taylor::TOLERANCE`] times the NUFFT's accuracy, with that
/// deviation; `kernel(m)` grids `R_m` from the samples, held or read again from their file.
/// `None` where no order up to [`taylor::MAX_ORDER`] does within `kernel_bytes` (the operator
/// then runs at each update). `note` is told each order's deviation and why the search ended.
pub fn taylor_series(
    geometry: ImageGeometry,
    params: PlanParams,
    psf_2n: &[f64],
    dirty: &[f64],
    reference: impl FnOnce() -> Result<Vec<f64>>,
    mut kernel: impl FnMut(usize) -> Result<Vec<f64>>,
    mut note: impl FnMut(Reason),
) -> Result<Option<(WTaylor, f64)>> {
    let tolerance = taylor::TOLERANCE * params.nufft.epsilon;
    // Each order keeps one more complex 2N x 2N kernel, and applying it takes two more such
    // arrays per two orders.
    let kernel_bytes = (4 * geometry.pixels() * std::mem::size_of::<num_complex::Complex64>()) as f64;
    // The form so far and the operator's D of the dirty image, made at the first order that fits.
    let mut made: Option<(WTaylor, Vec<f64>)> = None;
    let mut reference = Some(reference);
    let mut closest = None;
    // The order whose kernels would not fit in kernel_bytes, where that ended the search.
    let mut capped = None;
    for order in 1..=taylor::MAX_ORDER {
        let bytes = kernel_bytes * (order + 1 + 2 * (order + 1).div_ceil(2)) as f64;
        if bytes > params.kernel_bytes {
            capped = Some(order);
            break;
        }
        let (form, reference) = match &mut made {
            Some(made) => made,
            None => {
                let reference = reference.take().expect("taken once, with the first order")()?;
                made.insert((WTaylor::new(geometry, &[psf_2n.to_vec()], params.threads)?, reference))
            }
        };
        form.push_kernel(&kernel(order)?)?;
        let deviation = form.deviation(dirty, reference);
        note(Reason { level: log::Level::Debug, text: format!("a Taylor series in w of order {order} differs from the operator by {deviation:.2e} on the dirty image") });
        if deviation <= tolerance {
            note(Reason::info(format!(
                "the residual update convolves with the kernels of a Taylor series in w of order {order} ({} kept): on the dirty image it differs from the operator by {deviation:.1e}, within {tolerance:.0e} (the written residual is the operator's)",
                crate::limits::format_bytes(form.bytes() as f64)
            )));
            let (form, _) = made.expect("made above");
            return Ok(Some((form, deviation)));
        }
        closest = Some((order, deviation));
    }
    let kernel_mb = params.kernel_bytes / 1e6;
    note(Reason::info(match (closest, capped) {
        (Some((order, deviation)), None) => format!(
            "the residual update runs through the operator: no Taylor series in w up to order {order} comes within {tolerance:.0e} of it on the dirty image ({deviation:.1e}: the w-term is too large for it here)"
        ),
        (Some((order, deviation)), Some(next)) => format!(
            "the residual update runs through the operator: a Taylor series in w of order {order} is {deviation:.1e} from it on the dirty image (above {tolerance:.0e}), and the kernels of order {next} would take more than the gridder's kernel_mb {kernel_mb}"
        ),
        (None, _) => format!("the residual update runs through the operator: the kernels of a Taylor series in w would take more than the gridder's kernel_mb {kernel_mb}"),
    }));
    Ok(None)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The samples' and the kernels' budgets both `budget_mb`.
    fn params(w_term: WTermMode, budget_mb: f64, keep_operator: bool) -> PlanParams {
        PlanParams { nufft: NufftParams::default(), w_term, hold_bytes: budget_mb * 1e6, kernel_bytes: budget_mb * 1e6, chunk_rows: 1000, threads: 1, keep_operator, images_only: false, operator_chooses_oversampling: true }
    }

    fn samples(count: u64, streamed: bool, in_parts: bool) -> Samples {
        Samples { count, max_abs_w: 400.0, max_uv: 450.0, streamed, in_parts }
    }

    /// A field of about 4 degrees, on which the w-term of the samples above matters.
    fn field() -> ImageGeometry {
        ImageGeometry::new(64, 1e-3).unwrap()
    }

    #[test]
    fn without_the_w_term_the_samples_are_gridded_as_read_unless_the_operator_is_asked_for() {
        let p = OperatorPlan::new(field(), samples(1_000_000, true, false), params(WTermMode::Off, 1000.0, false));
        assert!(!p.w_term && !p.taylor && p.w_toeplitz.is_none() && p.reasons.is_empty());
        assert_eq!(p.form, Form::Chunked);
        // Asked for, it holds the samples where they fit in hold_mb, and reads them again where not.
        let held = OperatorPlan::new(field(), samples(1_000_000, true, false), params(WTermMode::Off, 1000.0, true));
        assert_eq!((held.form, held.bytes), (Form::Held, 1e8));
        let streamed = OperatorPlan::new(field(), samples(1_000_000, true, false), params(WTermMode::Off, 30.0, true));
        assert_eq!(streamed.form, Form::Streamed { chunk_rows: 200_000 });
        assert!(streamed.w_toeplitz.is_none() && !streamed.taylor);
        // Samples already held stay held.
        assert_eq!(OperatorPlan::new(field(), samples(1_000_000, false, false), params(WTermMode::Off, 30.0, true)).form, Form::Held);
        // With the w-term, D alone is held (not the operator kept with its samples): fewer
        // bytes per sample, so more samples fit in hold_mb.
        let normal = OperatorPlan::new(field(), samples(1_000_000, true, false), params(WTermMode::On, 60.0, false));
        assert_eq!((normal.form, normal.held_bytes), (Form::Held, 1e6 * NORMAL_BYTES_PER_SAMPLE));
        let kept = OperatorPlan::new(field(), samples(1_000_000, true, false), params(WTermMode::On, 60.0, true));
        assert_eq!((kept.held_bytes, matches!(kept.form, Form::Streamed { .. })), (1e6 * OPERATOR_BYTES_PER_SAMPLE, true));
    }

    #[test]
    fn with_the_w_term_the_toeplitz_form_comes_first_and_the_log_says_why_not() {
        let p = OperatorPlan::new(field(), samples(1_000_000, true, false), params(WTermMode::On, 1000.0, false));
        assert!(p.w_term && p.taylor && p.reasons.is_empty());
        let pass = p.w_toeplitz.as_ref().expect("a Toeplitz form");
        assert!(pass.chunk_rows >= 1000 && pass.bytes == p.bytes && p.bytes > 0.0);
        // Its kernels take more than kernel_mb 0 and than a hundred samples held: not chosen.
        let few = OperatorPlan::new(field(), samples(100, false, false), params(WTermMode::On, 0.0, false));
        assert!(few.w_toeplitz.is_none());
        assert_eq!(few.form, Form::Held);
        assert!(few.reasons.len() == 1 && few.reasons[0].text.contains("would take") && few.reasons[0].level == log::Level::Info, "{:?}", few.reasons);
        // In parts: the operator runs where they live, and the parts make no Taylor kernels.
        let parts = OperatorPlan::new(field(), samples(100, false, true), params(WTermMode::On, 0.0, false));
        assert_eq!(parts.form, Form::Streamed { chunk_rows: 1000 });
        assert!(!parts.taylor);
        // The exact round trip asked for: the operator, never a convolution form.
        let exact = OperatorPlan::new(field(), samples(100, false, false), params(WTermMode::On, 1000.0, true));
        assert!(exact.w_toeplitz.is_none() && !exact.taylor && exact.reasons.is_empty());
    }

    /// Images only (no stage applies `D`): whatever the w-term and the samples, no form of `D`
    /// is planned and the samples are gridded as read.
    #[test]
    fn images_only_plan_no_form_of_d() {
        for (w_term, streamed, in_parts) in [(WTermMode::On, true, false), (WTermMode::On, false, false), (WTermMode::On, false, true), (WTermMode::Off, true, false)] {
            let p = OperatorPlan::new(field(), samples(1_000_000, streamed, in_parts), PlanParams { images_only: true, ..params(w_term, 0.0, false) });
            assert_eq!(p.w_term, w_term == WTermMode::On);
            assert!(p.w_toeplitz.is_none() && !p.taylor && p.reasons.is_empty(), "{w_term:?}");
            assert_eq!((p.form, p.bytes), (Form::Chunked, 1000.0 * BUILD_BYTES_PER_SAMPLE));
        }
    }

    #[test]
    fn the_taylor_search_stops_before_kernels_beyond_kernel_mb() {
        let mut notes = Vec::new();
        let unused = || -> Result<Vec<f64>> { panic!("no reference where no order fits") };
        let found = taylor_series(field(), params(WTermMode::On, 0.0, false), &[], &[], unused, |_| panic!("no kernel"), |r| notes.push(r)).unwrap();
        assert!(found.is_none());
        assert_eq!(notes.len(), 1);
        assert!(notes[0].text.contains("would take more than the gridder's kernel_mb 0"), "{:?}", notes);
    }

    /// The two budgets are apart: samples held up to hold_mb do not let kernels grow past
    /// kernel_mb (a Toeplitz form slower than the Taylor series it would displace), and a
    /// kernel budget does not hold samples.
    #[test]
    fn samples_are_held_within_hold_mb_and_kernels_kept_within_kernel_mb() {
        let (few, many) = (samples(1000, true, false), samples(1_000_000, true, false));
        let both = |hold_mb: f64, kernel_mb: f64| PlanParams { hold_bytes: hold_mb * 1e6, kernel_bytes: kernel_mb * 1e6, ..params(WTermMode::On, 0.0, false) };
        let toeplitz_bytes = OperatorPlan::new(field(), many, both(1e6, 1e6)).w_toeplitz.expect("a Toeplitz form within any budget").bytes;
        // The samples fit in hold_mb; the kernels do not fit in kernel_mb: no Toeplitz form.
        let held = OperatorPlan::new(field(), few, both(1e6, 0.5 * toeplitz_bytes / 1e6));
        assert!(held.w_toeplitz.is_none() && held.taylor);
        assert_eq!(held.form, Form::Held);
        // Kernels within kernel_mb, samples above hold_mb: the Toeplitz form; were it refused,
        // the samples would be read again.
        let toeplitz = OperatorPlan::new(field(), many, both(1.0, 2.0 * toeplitz_bytes / 1e6));
        assert!(toeplitz.w_toeplitz.is_some());
        assert!(matches!(toeplitz.form, Form::Streamed { .. }));
    }
}
