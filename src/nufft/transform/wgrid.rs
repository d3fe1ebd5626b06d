//! The measurement equation with the w-term, by w-gridding (the improved w-stacking of
//! Arras, Reinecke, Westermann & Enßlin 2021, as in ducc0's `wgridder`).
//!
//! On an `N x N` image of pixel `pixel_rad` (conventions of `crate::operator`: pixel
//! `x[iy * N + ix]` at `l = -pixel (ix - N/2)`, `m = pixel (iy - N/2)`):
//!
//! * forward (degridding, prediction), [`WGridPlan::forward`]:
//!   `V_k = sum_{ix, iy} f[iy * N + ix] exp(+2 pi i (u_k l + v_k m + w_k (n - 1)))`
//! * adjoint (gridding, dirty image), [`WGridPlan::adjoint`], its exact adjoint:
//!   `f[iy * N + ix] = sum_k c_k exp(-2 pi i (u_k l + v_k m + w_k (n - 1)))`
//!
//! with `n = sqrt(1 - l^2 - m^2)` and `u, v, w` in wavelengths. There is no `1 / n` factor:
//! whether the image is brightness or brightness over `n` is the caller's choice (a factor
//! per pixel it can apply itself), and without it the pair stays a plain Fourier sum whose
//! adjoint is the same expression conjugated.
//!
//! Algorithm. With `t = n - 1` in `[t_min, 0]` over the image, centred as `t = t0 + tc`
//! (`|tc| <= dt = -t_min / 2`), the factor `exp(-2 pi i w tc)` is written as a sum over
//! w-planes `w_p = w_first + p dw` of a kernel in `w` (the ES kernel `psi`, in plane units)
//! times the planes' phases, divided by the kernel's Fourier transform at `dw tc`:
//!
//! `exp(-2 pi i w tc) ~= sum_p psi((w - w_p) / dw) exp(-2 pi i w_p tc) / psi_hat(dw tc)`,
//!
//! exact up to aliasing terms `psi_hat(dw tc + j)`, `j != 0`, which the plane spacing
//! `dw = 1 / (2 sigma_w dt)` keeps as small as a kernel's aliasing on a grid oversampled by
//! `sigma_w`. Gridding therefore spreads each visibility (times `exp(-2 pi i w t0)`) onto
//! the `support` planes nearest its `w`, weighted by `psi`; each plane is a 2D NUFFT onto the
//! image, multiplied by its phase screen `exp(-2 pi i w_p tc)` and accumulated; the sum is
//! divided by `psi_hat(dw tc)` pixel by pixel. Degridding is the same steps transposed.
//!
//! For real images ([`WGridPlan::new_real`], as in imaging, where the sky is real) the
//! visibility at `-(u, v, w)` is the conjugate of that at `(u, v, w)`: points of negative `w`
//! are mirrored and conjugated, so the planes only span `|w|`.
//!
//! The uv kernel and the w-kernel are chosen for a slightly tighter accuracy than asked,
//! since three dimensions now contribute error. The uv grid's oversampling is the caller's;
//! the w direction's `sigma_w` is chosen by a cost model: a finer plane spacing (up to 6
//! times oversampled) narrows the w-kernel, so each point reaches fewer planes, for a few
//! more planes in all. Where the w-term
//! is too small to matter at the requested accuracy (all `w` equal, or a tiny field) the
//! plan uses a single plane at the mean `w` with no w-kernel: the 2D NUFFT and a phase
//! screen, exact up to the neglected `|2 pi (w - w_mean) tc|`.
//!
//! Points are sorted once, by uv tile and within a tile by the first plane they reach, so that
//! the points of a tile on a given plane are a contiguous run. Planes are processed one after the other, each
//! with all the plan's threads, so only one oversampled grid is held at a time. Results do
//! not depend on the number of threads or their scheduling: tiles are added to the grid row
//! by row in a fixed order.

use crate::nufft::kernel::{gauss_legendre, KernelShape, SymKernel};
use super::{
    fit_kernel, grid_position, interp_points, par_filled, spread_tile, spread_tile_pair, GridPosition, Nufft2d, NufftParams, Sink,
    Source, MAX_COORDINATE, TILE,
};
use crate::{Error, Result};
use num_complex::Complex64;
use rayon::prelude::*;
use std::f64::consts::PI;
use std::ops::Range;

/// Most w-planes a plan may use (each costs an FFT of the oversampled grid).
const MAX_PLANES: usize = 1 << 20;

/// Tile buffers spread per batch and thread before they are added to the grid: bounds the
/// buffer memory (`(TILE + support)^2` complex each) while giving every thread enough work.
const TILES_PER_THREAD: usize = 64;

/// Grid rows transformed and staged together in the gridding FFT ([`WGridPlan::grid_to_accumulator`]).
const ROW_BLOCK: usize = 16;

/// Planes whose phase screens are advanced by one multiplication each, between exact
/// evaluations (the rounding of repeated products stays near `1e-15`).
const PHASE_RESEED: usize = 16;

/// Chebyshev nodes of the interpolant of `psi_hat` over `|eta| <= 1 / (2 sigma)`: the
/// transform of a kernel of support 16 at most is entire of exponential type `16 pi`, and
/// 64 terms reach rounding on that interval.
const PSI_HAT_NODES: usize = 64;

/// `2 pi max|w| max|n - 1|` over an `size x size` image of pixel `pixel_rad`: the largest
/// phase (radians) the w-term adds to any visibility. Infinite when the image reaches the
/// edge of the sine projection (`l^2 + m^2 >= 1` at a corner), where `n` is not defined.
pub fn max_w_phase(size: usize, pixel_rad: f64, w_max_abs: f64) -> f64 {
    match t_min(size, pixel_rad) {
        Some(t) => 2.0 * PI * w_max_abs.abs() * (-t),
        None => f64::INFINITY,
    }
}

/// The oversampling (among the tabulated 1.25, 1.5 and 2) that a cost model puts fastest
/// for these data: spreading or interpolation costs about `support^2` per visibility and
/// plane it reaches (one footprint on each of the w-kernel's planes), each plane an FFT of
/// the oversampled grid (the w-kernel as [`WGridPlan`] chooses it). A lower oversampling
/// means fewer planes and smaller FFTs but a wider kernel; the
/// model's two constants were measured on this code (their ratio is what matters), and near
/// a tie either choice is about as fast. `real`: for a [`WGridPlan::new_real`] plan.
/// Falls back to 2 if nothing else reaches `epsilon` (or the field is not valid).
pub fn suggested_oversampling(size: usize, pixel_rad: f64, w: &[f64], real: bool, epsilon: f64) -> f64 {
    cheapest_oversampling(&[1.25, 1.5, 2.0], size, pixel_rad, w.len(), w_span(w, real), epsilon)
}

/// The oversampling of a real-image plan applied again and again (the imaging operator's
/// residual update with the w-term): the cheaper of 1.5 and 2 by the cost model of
/// [`suggested_oversampling`]. 1.25 is left out: its tabulated kernel errors are the least
/// regular, and on a 2048 x 2048 field asked for 1e-6 its gridding came out at 1.6e-6
/// (`r2d2 bench wgridder --size 2048 --fov 0.229 --epsilon 1e-6 --oversampling 1.25`).
pub fn operator_oversampling(size: usize, pixel_rad: f64, w: &[f64], epsilon: f64) -> f64 {
    cheapest_oversampling(&[1.5, 2.0], size, pixel_rad, w.len(), w_span(w, true), epsilon)
}

/// [`operator_oversampling`] for samples not at hand (read from their file at each update):
/// `points` of them, their `|w|` taken to span `0..=max_abs_w` (the shortest baselines'
/// |w| is near 0 on any observation).
pub fn operator_oversampling_of(size: usize, pixel_rad: f64, points: usize, max_abs_w: f64, epsilon: f64) -> f64 {
    cheapest_oversampling(&[1.5, 2.0], size, pixel_rad, points, max_abs_w.abs(), epsilon)
}

/// The range of `w` (of `|w|` for a real-image plan, which folds the two signs together).
fn w_span(w: &[f64], real: bool) -> f64 {
    let folded = |w: f64| if real { w.abs() } else { w };
    let (lo, hi) = w.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(folded(x)), b.max(folded(x))));
    if w.is_empty() {
        0.0
    } else {
        hi - lo
    }
}

fn cheapest_oversampling(candidates: &[f64], size: usize, pixel_rad: f64, points: usize, span: f64, epsilon: f64) -> f64 {
    let Some(t_min) = t_min(size, pixel_rad) else { return 2.0 };
    let dt = -0.5 * t_min;
    let single = negligible_w(span, dt, epsilon);
    let cost = |sigma: f64| -> Option<f64> {
        let eps = kernel_epsilon(single, epsilon);
        let shape = KernelShape::for_accuracy(eps, sigma).ok()?;
        let g = super::good_fft_size((size as f64 * sigma).ceil() as usize);
        if single {
            let g = g as f64;
            return Some(SPREAD_COST * points as f64 * (shape.support * shape.support) as f64 + FFT_COST * g * g * g.log2());
        }
        w_kernel_choice(eps, span, dt, points, shape.support, g).map(|c| c.cost(points, shape.support, g))
    };
    candidates
        .iter()
        .filter_map(|&sigma| cost(sigma).map(|c| (sigma, c)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map_or(2.0, |(sigma, _)| sigma)
}

/// Relative costs of the cost model: spreading one value onto one cell, and one FFT per
/// `g^2 log2 g` of an oversampled `g x g` grid (measured on this code; their ratio is what
/// matters).
const SPREAD_COST: f64 = 1.6;
const FFT_COST: f64 = 1.0;

/// A w-kernel: its shape at oversampling `sigma`, the plane spacing `dw = 1 / (2 sigma dt)`,
/// and the planes a w range needs with it.
struct WKernelChoice {
    shape: KernelShape,
    sigma: f64,
    dw: f64,
    planes: usize,
}

impl WKernelChoice {
    /// The tabulated kernel reaching `epsilon` at `sigma` for a w range `span` (`|tc| <=
    /// dt`); `None` if none does, or it would need more than [`MAX_PLANES`] planes.
    fn new(epsilon: f64, sigma: f64, span: f64, dt: f64) -> Option<WKernelChoice> {
        let shape = KernelShape::tabulated(epsilon, sigma)?;
        let dw = 1.0 / (2.0 * sigma * dt);
        let planes = (span / dw).ceil() + shape.support as f64;
        (planes <= MAX_PLANES as f64).then(|| WKernelChoice { shape, sigma, dw, planes: planes as usize })
    }

    /// The cost model's time for `points` visibilities with a uv kernel of support
    /// `uv_support` on a `g x g` grid: `uv_support^2` per point on each of the w-kernel's
    /// planes, and each plane an FFT.
    fn cost(&self, points: usize, uv_support: usize, g: usize) -> f64 {
        let g = g as f64;
        let spread = SPREAD_COST * points as f64 * (self.shape.support * uv_support * uv_support) as f64;
        spread + FFT_COST * self.planes as f64 * g * g * g.log2()
    }
}

/// Chooses the w-kernel the cost model puts fastest ([`WKernelChoice::cost`]). The w
/// direction need not share the uv grid's oversampling: a finer plane spacing narrows the
/// w-kernel (fewer planes per point) for a few more planes, which pays where the points
/// outnumber the grid's cells. `None` if no tabulated kernel reaches `epsilon` within
/// [`MAX_PLANES`].
fn w_kernel_choice(epsilon: f64, span: f64, dt: f64, points: usize, uv_support: usize, g: usize) -> Option<WKernelChoice> {
    KernelShape::tabulated_oversamplings()
        .filter_map(|sigma| WKernelChoice::new(epsilon, sigma, span, dt))
        .map(|choice| (choice.cost(points, uv_support, g), choice))
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, choice)| choice)
}

/// Whether the phase the single-plane reduction neglects, `2 pi (span / 2) dt` for a w
/// range `span` and `|tc| <= dt`, is negligible against the accuracy asked.
fn negligible_w(span: f64, dt: f64, epsilon: f64) -> bool {
    2.0 * PI * 0.5 * span * dt <= 0.05 * epsilon
}

/// The accuracy the kernel is chosen for: with w-planes, three dimensions' errors add up
/// where the kernel table measured two.
fn kernel_epsilon(single: bool, epsilon: f64) -> f64 {
    if single {
        epsilon
    } else {
        epsilon / 1.25
    }
}

/// `n - 1` at the image corner (the minimum over the image), if the corner is inside the
/// unit circle.
fn t_min(size: usize, pixel_rad: f64) -> Option<f64> {
    let half = (size / 2) as f64 * pixel_rad;
    let r2 = 2.0 * half * half;
    (r2 < 1.0).then(|| n_minus_one(r2))
}

/// `sqrt(1 - r2) - 1` without cancellation for small `r2 = l^2 + m^2`.
pub(crate) fn n_minus_one(r2: f64) -> f64 {
    -r2 / (1.0 + (1.0 - r2).sqrt())
}

/// The w-direction kernel: one polynomial per covered plane, as [`crate::nufft::kernel::PolynomialKernel`].
struct WKernel {
    support: usize,
    /// Coefficients per cell (`terms` each, highest degree first, an even number: a zero
    /// leads where the degree is even), cell after cell.
    by_cell: Vec<f64>,
    terms: usize,
}

impl WKernel {
    /// From the fit's `(degree + 1) * support` coefficients, degree-major, highest first.
    fn new(support: usize, coeffs: &[f64]) -> WKernel {
        let degrees = coeffs.len() / support;
        let terms = degrees + degrees % 2;
        let mut by_cell = vec![0.0; terms * support];
        for (d, row) in coeffs.chunks_exact(support).enumerate() {
            for (b, &c) in row.iter().enumerate() {
                by_cell[b * terms + (terms - degrees) + d] = c;
            }
        }
        WKernel { support, by_cell, terms }
    }

    /// The kernel value for cell `b` (plane `p0 + b`) at sub-cell variable `z`: Horner's rule
    /// in `z^2` over pairs of coefficients, whose own products do not wait on the sum (half
    /// the dependent steps of Horner in `z`; this runs once per point and plane).
    #[inline(always)]
    fn cell(&self, b: usize, z: f64) -> f64 {
        let z2 = z * z;
        self.by_cell[b * self.terms..][..self.terms].chunks_exact(2).fold(0.0, |acc, c| acc * z2 + (c[0] * z + c[1]))
    }
}

/// The points of one uv tile, in the plan's order (sorted by first plane inside the tile).
#[derive(Clone, Debug)]
struct TileSpan {
    tx: usize,
    ty: usize,
    points: Range<usize>,
}

/// A w-gridding plan: image geometry, the uv NUFFT machinery, the w-planes, and the points
/// sorted by tile and first plane.
pub struct WGridPlan {
    size: usize,
    /// The 2D NUFFT without points: kernel, grid, FFTs, corrections and thread pool.
    engine: Nufft2d,
    /// `None`: a single plane and no w-kernel (the w-term reduced to a phase screen).
    wkernel: Option<WKernel>,
    planes: usize,
    w_first: f64,
    dw: f64,
    /// Centre of `t = n - 1` over the image.
    t0: f64,
    positions: Vec<GridPosition>,
    /// `order[k]`: caller's index of plan point `k`; `rank` its inverse.
    order: Vec<u32>,
    rank: Vec<u32>,
    /// `w` of each point, and the first plane it reaches (see [`WGridPlan::first_plane_of`]),
    /// plan order.
    w: Vec<f64>,
    first_plane: Vec<u32>,
    /// The w-kernel's variable `z` in `[-1, 1]` of each point (plan order; empty without
    /// w-planes): worked out once, where each plane would otherwise divide by `dw` again.
    w_cell: Vec<f64>,
    /// A real-image plan ([`WGridPlan::new_real`]); `flip[k]`: plan point `k` is mirrored.
    real: bool,
    flip: Vec<bool>,
    /// Non-empty tiles in tile order; their point ranges cover the plan order.
    tiles: Vec<TileSpan>,
    /// Grid rows touched by some point's kernel.
    row_used: Vec<bool>,
    /// Per pixel of one quadrant, `[|jx| * (N/2 + 1) + |jy|]` (`j` from the centre; the
    /// image is symmetric in `l -> -l` and `m -> -m`): `tc`, and the w correction
    /// `1 / psi_hat(dw tc)` (1 without w-planes).
    tc: Vec<f64>,
    w_correction: Vec<f64>,
}

/// The normal operator `Re{Phi^H diag(weight) Phi}` of a w-gridding plan's points, holding
/// per point only its grid position, its w-planes' weights and its weight
/// ([`WGridPlan::into_normal`]).
pub struct WGridNormal {
    /// Without the caller's order: only [`WGridPlan::normal_real`] is called on it.
    plan: WGridPlan,
    /// In the plan's order.
    weight: Vec<f64>,
}

impl WGridNormal {
    /// `Re{Phi^H diag(weight) Phi x}`.
    pub fn apply(&self, x: &[f64]) -> Vec<f64> {
        self.plan.normal_real(x, &self.weight)
    }
    pub fn planes(&self) -> usize {
        self.plan.planes
    }
    pub fn len(&self) -> usize {
        self.weight.len()
    }
    pub fn is_empty(&self) -> bool {
        self.weight.is_empty()
    }
}

impl WGridPlan {
    /// Plan transforms between a `size x size` complex image of pixel `pixel_rad` (radians)
    /// and the visibilities at `(u[k], v[k], w[k])` (wavelengths), run on `threads` threads
    /// (0: all cores). `params.epsilon` is the requested relative accuracy of the whole
    /// transform; `params.oversampling` is used as given, and for wide fields a lower one
    /// than the 2D default is often faster (fewer, smaller plane FFTs; see
    /// [`suggested_oversampling`]).
    pub fn new(
        size: usize,
        pixel_rad: f64,
        u: &[f64],
        v: &[f64],
        w: &[f64],
        params: NufftParams,
        threads: usize,
    ) -> Result<WGridPlan> {
        Self::build(size, pixel_rad, u, v, w, params, threads, false, None)
    }

    /// A plan for real images only ([`WGridPlan::forward_real`], [`WGridPlan::adjoint_real`]):
    /// the visibility of a real image at `-(u, v, w)` is the conjugate of that at `(u, v,
    /// w)`, so points of negative `w` are mirrored to positive `w` and conjugated, which
    /// halves the w range (and the planes) of data with `w` of both signs.
    pub fn new_real(
        size: usize,
        pixel_rad: f64,
        u: &[f64],
        v: &[f64],
        w: &[f64],
        params: NufftParams,
        threads: usize,
    ) -> Result<WGridPlan> {
        Self::build(size, pixel_rad, u, v, w, params, threads, true, None)
    }

    #[allow(clippy::too_many_arguments)]
    fn build(
        size: usize,
        pixel_rad: f64,
        u: &[f64],
        v: &[f64],
        w: &[f64],
        params: NufftParams,
        threads: usize,
        real: bool,
        // The w direction's oversampling, a tabulated one (`None`: the cost model's choice).
        w_oversampling: Option<f64>,
    ) -> Result<WGridPlan> {
        if u.len() != v.len() || u.len() != w.len() {
            return Err(Error::parameter(
                "uvw",
                format!("u, v and w differ in length ({}, {}, {})", u.len(), v.len(), w.len()),
            ));
        }
        if u.len() > u32::MAX as usize {
            return Err(Error::parameter("uvw", "more than 2^32 visibilities in one plan"));
        }
        if size < 2 || !size.is_multiple_of(2) {
            return Err(Error::parameter("image size", format!("expected an even size >= 2, got {size}")));
        }
        if !(pixel_rad.is_finite() && pixel_rad > 0.0) {
            return Err(Error::parameter("pixel size", format!("expected a positive pixel size, got {pixel_rad} rad")));
        }
        let t_min = t_min(size, pixel_rad).ok_or_else(|| {
            Error::parameter(
                "pixel size",
                format!(
                    "a {size} x {size} image of {pixel_rad:e} rad pixels reaches beyond the sine projection \
                     (l^2 + m^2 >= 1 at its corners)"
                ),
            )
        })?;
        let limit = MAX_COORDINATE / (2.0 * PI * pixel_rad);
        if let Some(k) = (0..u.len()).find(|&k| !(u[k].abs() <= limit && v[k].abs() <= limit && w[k].is_finite())) {
            return Err(Error::parameter(
                "uvw",
                format!(
                    "visibility {k} has u, v, w = {}, {}, {}: expected finite values, |u| and |v| at most {limit:e}",
                    u[k], v[k], w[k]
                ),
            ));
        }

        // Mirrored points of a real-image plan.
        let flipped: Vec<bool> = w.iter().map(|&w| real && w < 0.0).collect();
        let mirror = |a: &[f64]| -> Vec<f64> { a.iter().zip(&flipped).map(|(&a, &f)| if f { -a } else { a }).collect() };
        let (u, v, w) = (&mirror(u)[..], &mirror(v)[..], &mirror(w)[..]);
        let (w_lo, w_hi) = w.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(x), b.max(x)));
        let (w_lo, w_hi) = if w.is_empty() { (0.0, 0.0) } else { (w_lo, w_hi) };
        let w_mid = 0.5 * (w_lo + w_hi);
        let t0 = 0.5 * t_min;
        let dt = -0.5 * t_min;
        // The phase the single-plane reduction would neglect, against the accuracy asked.
        let single = negligible_w(w_hi - w_lo, dt, params.epsilon);
        let uv_epsilon = kernel_epsilon(single, params.epsilon);
        let shape = KernelShape::for_accuracy(uv_epsilon, params.oversampling)?;
        let engine = Nufft2d::with_kernel(size, size, &[], &[], shape.clone(), NufftParams { epsilon: uv_epsilon, ..params }, threads)?;

        let (wkernel, planes, w_first, dw, w_shape) = if single {
            (None, 1, w_mid, 1.0, None)
        } else {
            let g = engine.grid_nx.max(engine.grid_ny);
            let choice = match w_oversampling {
                Some(sigma) => WKernelChoice::new(uv_epsilon, sigma, w_hi - w_lo, dt),
                None => w_kernel_choice(uv_epsilon, w_hi - w_lo, dt, u.len(), shape.support, g),
            }
            .ok_or_else(|| {
                Error::parameter(
                    "uvw",
                    format!(
                        "w from {w_lo} to {w_hi} needs more than {MAX_PLANES} w-planes on this field at an accuracy of {uv_epsilon:e}"
                    ),
                )
            })?;
            let (dw, planes) = (choice.dw, choice.planes);
            let w_first = w_mid - 0.5 * (planes - 1) as f64 * dw;
            let coeffs = fit_kernel(&choice.shape, uv_epsilon / 20.0);
            (Some(WKernel::new(choice.shape.support, &coeffs)), planes, w_first, dw, Some((choice.shape, choice.sigma)))
        };

        let h = size / 2 + 1;
        let mut tc = vec![0.0; h * h];
        for a in 0..h {
            for b in 0..h {
                let (l, m) = (a as f64 * pixel_rad, b as f64 * pixel_rad);
                tc[a * h + b] = n_minus_one(l * l + m * m) - t0;
            }
        }
        let w_correction = match &w_shape {
            None => vec![1.0; h * h],
            Some((w_shape, w_sigma)) => {
                let fit = Chebyshev::fit(|eta| psi_hat(w_shape, eta), 0.5 / w_sigma, PSI_HAT_NODES);
                tc.iter().map(|&t| 1.0 / fit.eval(dw * t)).collect()
            }
        };

        let mut plan = WGridPlan {
            size,
            engine,
            wkernel,
            planes,
            w_first,
            dw,
            t0,
            positions: Vec::new(),
            order: Vec::new(),
            rank: Vec::new(),
            w: Vec::new(),
            first_plane: Vec::new(),
            w_cell: Vec::new(),
            real,
            flip: Vec::new(),
            tiles: Vec::new(),
            row_used: Vec::new(),
            tc,
            w_correction,
        };
        let x: Vec<f64> = u.iter().map(|&u| -2.0 * PI * pixel_rad * u).collect();
        let y: Vec<f64> = v.iter().map(|&v| 2.0 * PI * pixel_rad * v).collect();
        let pool = plan.engine.pool.clone();
        pool.install(|| plan.sort_points(&x, &y, w));
        if real {
            plan.flip = plan.order.iter().map(|&k| flipped[k as usize]).collect();
        }
        Ok(plan)
    }

    /// Number of visibilities.
    pub fn len(&self) -> usize {
        self.positions.len()
    }
    /// Runs `f` in the plan's thread pool.
    pub fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.engine.install(f)
    }

    /// How many w-planes a transform runs (1 where the w-term is negligible).
    pub fn planes(&self) -> usize {
        self.planes
    }
    /// Support of the uv kernel, for logging.
    pub fn kernel_support(&self) -> usize {
        self.engine.shape.support
    }
    /// Support of the w-kernel (1 without w-planes): the planes each visibility reaches.
    #[cfg(test)]
    pub fn w_support(&self) -> usize {
        self.wkernel.as_ref().map_or(1, |wk| wk.support)
    }
    /// The oversampled grid's edges, for logging.
    pub fn grid_size(&self) -> (usize, usize) {
        self.engine.grid_size()
    }

    /// Sort the points by tile, and inside a tile by the first plane they reach (then caller
    /// index, so the order is reproducible); record each point's grid position.
    fn sort_points(&mut self, x: &[f64], y: &[f64], w: &[f64]) {
        let support = self.engine.shape.support;
        let (gx, gy) = (self.engine.grid_nx, self.engine.grid_ny);
        let tiles_x = (gx + 2 * support).div_ceil(TILE);
        let tiles_y = (gy + 2 * support).div_ceil(TILE);
        let (sx, sy) = (gx as f64 / (2.0 * PI), gy as f64 / (2.0 * PI));
        let (inv_gx, inv_gy) = (1.0 / gx as f64, 1.0 / gy as f64);
        let m = x.len();
        let positions: Vec<GridPosition> = x
            .par_iter()
            .zip(y.par_iter())
            .map(|(&xk, &yk)| GridPosition {
                x: grid_position(xk * sx, gx, inv_gx, support),
                y: grid_position(yk * sy, gy, inv_gy, support),
            })
            .collect();
        let tile_of = |p: &GridPosition| (p.py() / TILE) * tiles_x + p.px() / TILE;
        let mut starts = vec![0usize; tiles_x * tiles_y + 1];
        for p in &positions {
            starts[tile_of(p) + 1] += 1;
        }
        for t in 0..tiles_x * tiles_y {
            starts[t + 1] += starts[t];
        }
        let mut order = vec![0u32; m];
        let mut cursor = starts.clone();
        for (k, p) in positions.iter().enumerate() {
            let c = &mut cursor[tile_of(p)];
            order[*c] = k as u32;
            *c += 1;
        }
        let mut tiles = Vec::new();
        for t in 0..tiles_x * tiles_y {
            if starts[t + 1] > starts[t] {
                tiles.push(TileSpan { tx: t % tiles_x, ty: t / tiles_x, points: starts[t]..starts[t + 1] });
            }
        }
        // Inside each tile, by first plane: the keys `(first plane, caller index)` packed in
        // one integer, sorted where they lie in cache (comparing the points' `w` through
        // their indices reached all over the chunk's arrays).
        let first_plane: Vec<u32> = w.par_iter().map(|&w| self.first_plane_of(w) as u32).collect();
        let mut slices = Vec::with_capacity(tiles.len());
        let mut rest = order.as_mut_slice();
        for tile in &tiles {
            let (head, tail) = std::mem::take(&mut rest).split_at_mut(tile.points.len());
            slices.push(head);
            rest = tail;
        }
        slices.into_par_iter().for_each_init(Vec::new, |keys: &mut Vec<u64>, s| {
            keys.clear();
            keys.extend(s.iter().map(|&k| (u64::from(first_plane[k as usize]) << 32) | u64::from(k)));
            keys.sort_unstable();
            for (o, key) in s.iter_mut().zip(keys.iter()) {
                *o = *key as u32;
            }
        });

        self.positions = order.par_iter().map(|&k| positions[k as usize]).collect();
        self.w = order.par_iter().map(|&k| w[k as usize]).collect();
        self.first_plane = order.par_iter().map(|&k| first_plane[k as usize]).collect();
        if let Some(wk) = &self.wkernel {
            self.w_cell = self
                .w
                .par_iter()
                .zip(self.first_plane.par_iter())
                .map(|(&w, &p0)| 2.0 * (f64::from(p0) - self.plane_offset(wk, w)) - 1.0)
                .collect();
        }
        let mut rank = vec![0u32; m];
        for (i, &k) in order.iter().enumerate() {
            rank[k as usize] = i as u32;
        }
        let mut row_used = vec![false; gy];
        let padded_y = gy + 2 * support;
        for tile in &tiles {
            for q in tile.ty * TILE..((tile.ty + 1) * TILE + support).min(padded_y) {
                row_used[(q + gy - support) % gy] = true;
            }
        }
        self.order = order;
        self.rank = rank;
        self.tiles = tiles;
        self.row_used = row_used;
    }

    /// Where a point at `w` sits between the planes: `s - support / 2` with `s` its plane
    /// coordinate, so that it reaches planes `ceil` of that onwards.
    #[inline(always)]
    fn plane_offset(&self, wk: &WKernel, w: f64) -> f64 {
        (w - self.w_first) / self.dw - 0.5 * wk.support as f64
    }

    /// First plane `p0` a point at `w` reaches: it contributes to planes `p0 .. p0 +
    /// support`, with weights `psi` of cell `p - p0` (non-decreasing in `w`).
    fn first_plane_of(&self, w: f64) -> usize {
        match &self.wkernel {
            None => 0,
            Some(wk) => self.plane_offset(wk, w).ceil().clamp(0.0, (self.planes - wk.support) as f64) as usize,
        }
    }

    /// The tiles' point ranges on plane `p`, from those on plane `p - 1` (or, for plane 0,
    /// from empty ranges at the tiles' starts): points are sorted by first plane inside a
    /// tile, so both ends only move forward.
    fn advance_ranges(&self, ranges: &mut [Range<usize>], p: usize) {
        let Some(wk) = &self.wkernel else {
            ranges.iter_mut().zip(&self.tiles).for_each(|(r, t)| *r = t.points.clone());
            return;
        };
        let lo = (p + 1).saturating_sub(wk.support) as u32;
        let fp = &self.first_plane;
        ranges.par_iter_mut().zip(self.tiles.par_iter()).for_each(|(r, tile)| {
            while r.end < tile.points.end && fp[r.end] <= p as u32 {
                r.end += 1;
            }
            while r.start < r.end && fp[r.start] < lo {
                r.start += 1;
            }
        });
    }

    /// Weight of plan point `k` on plane `p`.
    #[inline(always)]
    fn weight(&self, k: usize, p: usize) -> f64 {
        match &self.wkernel {
            None => 1.0,
            Some(wk) => wk.cell(p - self.first_plane[k] as usize, self.w_cell[k]),
        }
    }

    /// Phase screens `exp(-2 pi i w_p tc)` over the quadrant, exactly, for plane `p`.
    fn phase_screen(&self, p: usize) -> Vec<Complex64> {
        let wp = self.w_first + p as f64 * self.dw;
        self.tc.par_iter().map(|&t| Complex64::from_polar(1.0, -2.0 * PI * wp * t)).collect()
    }

    /// The screen of plane `p + 1` from that of plane `p` (exactly every few planes).
    fn advance_screen(&self, screen: &mut Vec<Complex64>, step: &[Complex64], next: usize) {
        if next.is_multiple_of(PHASE_RESEED) {
            *screen = self.phase_screen(next);
        } else {
            screen.par_iter_mut().zip(step.par_iter()).for_each(|(s, d)| *s *= d);
        }
    }

    fn step_screen(&self) -> Vec<Complex64> {
        self.tc.par_iter().map(|&t| Complex64::from_polar(1.0, -2.0 * PI * self.dw * t)).collect()
    }

    /// Adjoint (gridding): the dirty image `f[iy * N + ix] = sum_k c_k exp(-2 pi i (u_k l +
    /// v_k m + w_k (n - 1)))`, visibilities in the caller's order.
    ///
    /// Panics on a real-image plan ([`WGridPlan::new_real`]), which only has
    /// [`WGridPlan::adjoint_real`].
    pub fn adjoint(&self, vis: &[Complex64]) -> Vec<Complex64> {
        assert!(!self.real, "a real-image plan (WGridPlan::new_real) has only adjoint_real");
        self.engine.install(|| self.grid(vis))
    }

    /// The real part of [`WGridPlan::adjoint`]: the adjoint of [`WGridPlan::forward_real`]
    /// (for the real inner product `Re <a, b>` on visibilities). Any plan.
    pub fn adjoint_real(&self, vis: &[Complex64]) -> Vec<f64> {
        self.engine.install(|| self.grid(vis).par_iter().map(|v| v.re).collect())
    }

    /// Forward (degridding): `V_k = sum f[iy * N + ix] exp(+2 pi i (u_k l + v_k m + w_k (n -
    /// 1)))`, visibilities in the caller's order.
    ///
    /// Panics on a real-image plan ([`WGridPlan::new_real`]), which only has
    /// [`WGridPlan::forward_real`].
    pub fn forward(&self, image: &[Complex64]) -> Vec<Complex64> {
        assert!(!self.real, "a real-image plan (WGridPlan::new_real) has only forward_real");
        assert_eq!(image.len(), self.size * self.size, "image size");
        self.engine.install(|| self.degrid(image))
    }

    /// [`WGridPlan::forward`] of a real image. Any plan.
    pub fn forward_real(&self, image: &[f64]) -> Vec<Complex64> {
        assert_eq!(image.len(), self.size * self.size, "image size");
        self.engine.install(|| {
            let image: Vec<Complex64> = image.par_iter().map(|&x| Complex64::new(x, 0.0)).collect();
            self.degrid(&image)
        })
    }

    /// `Re{Phi^H diag(weight) Phi x}` of the real image `x`, `weight` given per point in
    /// the plan's order ([`WGridPlan::to_plan_order`]). The values stay in the plan's order
    /// between the two directions: each point's phase `exp(+-2 pi i w t0)` and its mirroring
    /// (a conjugation) cancel there, so neither permutation is made.
    pub fn normal_real(&self, x: &[f64], weight: &[f64]) -> Vec<f64> {
        assert_eq!(x.len(), self.size * self.size, "image size");
        assert_eq!(weight.len(), self.len(), "one weight per point");
        self.engine.install(|| {
            let image: Vec<Complex64> = x.par_iter().map(|&v| Complex64::new(v, 0.0)).collect();
            let mut values = dispatch_support!(self.engine.shape.support, W, W2, L => self.forward_impl::<W, W2, L>(&image));
            drop(image);
            values.par_iter_mut().zip(weight.par_iter()).for_each(|(v, &q)| *v *= q);
            let mut images = dispatch_support!(self.engine.shape.support, W, W2, L => self.adjoint_impl::<W, W2, L>(&[&values]));
            drop(values);
            images.pop().expect("one image per set of values").par_iter().map(|v| v.re).collect()
        })
    }

    /// Per-point values from the caller's order into the plan's.
    pub fn to_plan_order(&self, values: &[f64]) -> Vec<f64> {
        assert_eq!(values.len(), self.len(), "one value per point");
        self.engine.install(|| self.order.par_iter().map(|&k| values[k as usize]).collect())
    }

    /// The normal operator `Re{Phi^H diag(weight) Phi}` of these points alone (`weight` in
    /// the caller's order): what only the caller's order needs (the order itself, the points'
    /// `w` and mirroring) is released, about half of what the plan holds per point.
    pub fn into_normal(mut self, weight: &[f64]) -> WGridNormal {
        let weight = self.to_plan_order(weight);
        self.order = Vec::new();
        self.rank = Vec::new();
        self.w = Vec::new();
        self.flip = Vec::new();
        WGridNormal { plan: self, weight }
    }

    /// Gridding of the visibilities (caller's order) with the per-point phase
    /// `exp(-2 pi i w t0)`, mirrored points conjugated (their real part is what counts).
    fn grid(&self, vis: &[Complex64]) -> Vec<Complex64> {
        assert_eq!(vis.len(), self.len(), "number of visibilities");
        let values = self.gridding_values(|k| vis[k]);
        let mut images = dispatch_support!(self.engine.shape.support, W, W2, L => self.adjoint_impl::<W, W2, L>(&[&values]));
        images.pop().expect("one image per set of values")
    }

    /// [`WGridPlan::adjoint_real`] of two sets of visibilities at once (a dirty image and
    /// its PSF), given as functions of the caller's index (no copy of them is made): the
    /// points' kernels and w-weights are evaluated once for both.
    pub fn adjoint_real_pair(
        &self,
        a: impl Fn(usize) -> Complex64 + Send + Sync,
        b: impl Fn(usize) -> Complex64 + Send + Sync,
    ) -> (Vec<f64>, Vec<f64>) {
        self.engine.install(|| {
            let (va, vb) = (self.gridding_values(a), self.gridding_values(b));
            let images = dispatch_support!(self.engine.shape.support, W, W2, L => self.adjoint_impl::<W, W2, L>(&[&va, &vb]));
            let mut real = images.into_iter().map(|img| img.par_iter().map(|v| v.re).collect::<Vec<f64>>());
            (real.next().expect("two images"), real.next().expect("two images"))
        })
    }

    /// The values gridding spreads, from the visibility of each caller's index: in plan
    /// order, times `exp(-2 pi i w t0)`, mirrored points conjugated.
    fn gridding_values(&self, vis: impl Fn(usize) -> Complex64 + Sync) -> Vec<Complex64> {
        (0..self.len())
            .into_par_iter()
            .map(|i| {
                let c = vis(self.order[i] as usize);
                let c = if self.flip.get(i) == Some(&true) { c.conj() } else { c };
                c * Complex64::from_polar(1.0, -2.0 * PI * self.w[i] * self.t0)
            })
            .collect()
    }

    /// Degridding to the caller's order, with the per-point phase `exp(+2 pi i w t0)`,
    /// mirrored points conjugated.
    fn degrid(&self, image: &[Complex64]) -> Vec<Complex64> {
        let sorted = dispatch_support!(self.engine.shape.support, W, W2, L => self.forward_impl::<W, W2, L>(image));
        self.rank
            .par_iter()
            .map(|&i| {
                let i = i as usize;
                let v = sorted[i] * Complex64::from_polar(1.0, 2.0 * PI * self.w[i] * self.t0);
                if self.flip.get(i) == Some(&true) {
                    v.conj()
                } else {
                    v
                }
            })
            .collect()
    }

    /// The per-pixel factor both directions apply once: the uv grid correction times the
    /// w correction, in the column-major layout `[ix * N + iy]`.
    fn total_correction(&self, ix: usize, iy: usize) -> f64 {
        let (n, h) = (self.size, self.size / 2 + 1);
        let (a, b) = (ix.abs_diff(n / 2), iy.abs_diff(n / 2));
        self.engine.correction_x[ix] * self.engine.correction_y[iy] * self.w_correction[a * h + b]
    }

    /// The images of one or two sets of values (plan order), spread together plane by plane.
    fn adjoint_impl<const W: usize, const W2: usize, const L: usize>(&self, sets: &[&[Complex64]]) -> Vec<Vec<Complex64>> {
        assert!(matches!(sets.len(), 1 | 2), "one or two sets of values");
        let n = self.size;
        let (gx, gy) = (self.engine.grid_nx, self.engine.grid_ny);
        let kernel = self.engine.kernel::<W, W2, L>();
        let mut grids: Vec<Vec<Complex64>> = sets.iter().map(|_| par_filled(Complex64::default(), gx * gy)).collect();
        // Column-major accumulators: acc[ix * n + iy].
        let mut accs: Vec<Vec<Complex64>> = sets.iter().map(|_| par_filled(Complex64::default(), n * n)).collect();
        let mut staging = par_filled(Complex64::default(), gy.div_ceil(ROW_BLOCK) * ROW_BLOCK * n);
        let mut screen = self.phase_screen(0);
        let step = if self.planes > 1 { self.step_screen() } else { Vec::new() };
        let mut ranges: Vec<Range<usize>> = self.tiles.iter().map(|t| t.points.start..t.points.start).collect();
        for p in 0..self.planes {
            self.advance_ranges(&mut ranges, p);
            let spans: Vec<(usize, Range<usize>)> =
                ranges.iter().enumerate().filter(|(_, r)| !r.is_empty()).map(|(i, r)| (i, r.clone())).collect();
            if !spans.is_empty() {
                self.spread_plane::<W, W2, L>(&kernel, p, &spans, sets, &mut grids);
                for (grid, acc) in grids.iter_mut().zip(accs.iter_mut()) {
                    self.grid_to_accumulator(grid, &mut staging, &screen, acc);
                }
            }
            if p + 1 < self.planes {
                self.advance_screen(&mut screen, &step, p + 1);
            }
        }
        drop(grids);
        accs.into_iter()
            .map(|mut acc| {
                acc.par_chunks_mut(n).enumerate().for_each(|(ix, col)| {
                    for (iy, v) in col.iter_mut().enumerate() {
                        *v *= self.total_correction(ix, iy);
                    }
                });
                let mut out = par_filled(Complex64::default(), n * n);
                crate::fft2::transpose(&acc, &mut out, n, n);
                out
            })
            .collect()
    }

    /// Spread the points of plane `p` (`spans`: tile index and plan-order range, in tile
    /// order) onto the zeroed grids, one per set of values, weighted by the w-kernel: tiles go
    /// into private buffers a batch at a time, then the buffers are added to the grids row by
    /// row in parallel, each grid row taking its buffers in tile order.
    fn spread_plane<const W: usize, const W2: usize, const L: usize>(
        &self,
        kernel: &SymKernel<W, W2, L>,
        p: usize,
        spans: &[(usize, Range<usize>)],
        sets: &[&[Complex64]],
        grids: &mut [Vec<Complex64>],
    ) {
        let (gx, gy) = (self.engine.grid_nx, self.engine.grid_ny);
        let bw = TILE + W;
        let bw2 = 2 * bw;
        let padded_y = gy + 2 * W;
        let batch = TILES_PER_THREAD * rayon::current_num_threads().max(1);
        let spare = std::sync::Mutex::new(Vec::<Vec<f64>>::new());
        let fresh = || {
            let mut buf = spare.lock().expect("no task panics holding the buffers").pop().unwrap_or_default();
            buf.clear();
            buf.resize(bw * bw2, 0.0);
            buf
        };
        for chunk in spans.chunks(batch) {
            // Per tile, one buffer per set.
            let buffers: Vec<Vec<Vec<f64>>> = chunk
                .par_iter()
                .map_init(
                    || (Vec::new(), Vec::new(), Vec::new()),
                    |(weights, wa, wb): &mut (Vec<f64>, Vec<Complex64>, Vec<Complex64>), (i, range)| {
                        let tile = &self.tiles[*i];
                        let origin = ((tile.tx * TILE) as u32, (tile.ty * TILE) as u32);
                        let positions = &self.positions[range.clone()];
                        weights.clear();
                        weights.extend(range.clone().map(|k| self.weight(k, p)));
                        let weighted = |set: &[Complex64], out: &mut Vec<Complex64>| {
                            out.clear();
                            out.extend(set[range.clone()].iter().zip(weights.iter()).map(|(v, &q)| v * q));
                        };
                        weighted(sets[0], wa);
                        let mut first = fresh();
                        if let Some(second_set) = sets.get(1) {
                            weighted(second_set, wb);
                            let mut second = fresh();
                            spread_tile_pair::<W, W2, L>(self.engine.simd, kernel, positions, wa, wb, &mut first, &mut second, bw2, origin);
                            vec![first, second]
                        } else {
                            let mut source = Source::Sorted(&wa[..]);
                            spread_tile::<W, W2, L>(self.engine.simd, kernel, positions, &mut source, 0..wa.len(), &[], 0, &mut first, bw2, origin);
                            vec![first]
                        }
                    },
                )
                .collect();
            let tys: Vec<usize> = chunk.iter().map(|(i, _)| self.tiles[*i].ty).collect();
            let (q_lo, q_hi) = (tys[0] * TILE, (tys[tys.len() - 1] * TILE + bw).min(padded_y));
            for (s, grid) in grids.iter_mut().enumerate() {
                grid.par_chunks_mut(gx).enumerate().for_each(|(r, row)| {
                    // Padded rows that wrap onto grid row r.
                    for q in [r + W + gy, r + W, (r + W).wrapping_sub(gy)] {
                        if q < q_lo || q >= q_hi {
                            continue;
                        }
                        // Tiles whose buffer rows cover q: ty * TILE <= q < ty * TILE + bw.
                        let first = tys.partition_point(|&ty| ty * TILE + bw <= q);
                        let last = tys.partition_point(|&ty| ty * TILE <= q);
                        for j in first..last {
                            let tile = &self.tiles[chunk[j].0];
                            let src = &buffers[j][s][(q - tile.ty * TILE) * bw2..][..bw2];
                            let start = (tile.tx * TILE + gx - W) % gx;
                            if start + bw <= gx {
                                for (d, s) in row[start..start + bw].iter_mut().zip(src.chunks_exact(2)) {
                                    *d += Complex64::new(s[0], s[1]);
                                }
                            } else {
                                for (c, s) in src.chunks_exact(2).enumerate() {
                                    row[(start + c) % gx] += Complex64::new(s[0], s[1]);
                                }
                            }
                        }
                    }
                });
            }
            spare.lock().expect("no task panics holding the buffers").extend(buffers.into_iter().flatten());
        }
    }

    /// FFT the plane's grid to image modes, multiply by the plane's phase screen and add to
    /// the column-major accumulator; leave the grid zeroed for the next plane.
    ///
    /// Rows are transformed a block of [`ROW_BLOCK`] at a time, and while they are in cache
    /// the image columns of the block are copied to `staging` (`[block][ix][row in block]`)
    /// and the rows zeroed; the column transforms then read whole `ROW_BLOCK`-long runs of
    /// consecutive columns, rather than a few values from every grid row.
    fn grid_to_accumulator(&self, grid: &mut [Complex64], staging: &mut [Complex64], screen: &[Complex64], acc: &mut [Complex64]) {
        const RB: usize = ROW_BLOCK;
        let e = &self.engine;
        let (gx, gy, n) = (e.grid_nx, e.grid_ny, self.size);
        let (h, half) = (n / 2 + 1, n / 2);
        // Image column ix sits at grid column gcol[ix]: the upper half of the image at the
        // start of the grid, the lower half at its end.
        let gcol: Vec<usize> = (0..n).map(|ix| if ix < half { gx - half + ix } else { ix - half }).collect();
        grid.par_chunks_mut(gx * RB).zip(staging.par_chunks_mut(n * RB)).enumerate().for_each_init(
            || vec![Complex64::default(); e.fft_x.get_inplace_scratch_len()],
            |scratch, (rb, (rows, stage))| {
                for (j, row) in rows.chunks_exact_mut(gx).enumerate() {
                    if !self.row_used[rb * RB + j] {
                        for ix in 0..n {
                            stage[ix * RB + j] = Complex64::default();
                        }
                        continue;
                    }
                    e.fft_x.process_with_scratch(row, scratch);
                    for (ix, &g) in gcol.iter().enumerate() {
                        stage[ix * RB + j] = row[g];
                    }
                    row.fill(Complex64::default());
                }
            },
        );
        const B: usize = 16;
        let staging: &[Complex64] = staging;
        acc.par_chunks_mut(n * B).enumerate().for_each_init(
            || (vec![Complex64::default(); gy * B], vec![Complex64::default(); e.fft_y.get_inplace_scratch_len()]),
            |(block, scratch), (bi, dst)| {
                let ncols = dst.len() / n;
                for (rb, stage) in staging.chunks_exact(n * RB).enumerate() {
                    let nr = RB.min(gy - rb * RB);
                    for c in 0..ncols {
                        let run = &stage[(bi * B + c) * RB..][..nr];
                        block[c * gy + rb * RB..][..nr].copy_from_slice(run);
                    }
                }
                for c in 0..ncols {
                    let col = &mut block[c * gy..(c + 1) * gy];
                    e.fft_y.process_with_scratch(col, scratch);
                    let ix = bi * B + c;
                    let ph = &screen[ix.abs_diff(half) * h..][..h];
                    let (lower, upper) = dst[c * n..(c + 1) * n].split_at_mut(half);
                    // iy = j < n/2 at grid row gy - n/2 + j, |jy| = n/2 - j; iy = n/2 + j at row j.
                    for (j, o) in lower.iter_mut().enumerate() {
                        *o += col[gy - half + j] * ph[half - j];
                    }
                    for ((o, v), q) in upper.iter_mut().zip(&col[..half]).zip(&ph[..half]) {
                        *o += v * q;
                    }
                }
            },
        );
    }

    fn forward_impl<const W: usize, const W2: usize, const L: usize>(&self, image: &[Complex64]) -> Vec<Complex64> {
        let e = &self.engine;
        let n = self.size;
        let (gx, gy) = (e.grid_nx, e.grid_ny);
        let kernel = e.kernel::<W, W2, L>();
        // Corrected image, column-major: f[ix * n + iy].
        let mut f = par_filled(Complex64::default(), n * n);
        f.par_chunks_mut(n).enumerate().for_each(|(ix, col)| {
            for (iy, v) in col.iter_mut().enumerate() {
                *v = image[iy * n + ix] * self.total_correction(ix, iy);
            }
        });
        let mut cols = par_filled(Complex64::default(), n * gy);
        let (pw, ph) = (gx + 2 * W, gy + 2 * W);
        let mut padded = par_filled(0.0f64, 2 * pw * ph);
        let mut out = par_filled(Complex64::default(), self.len());
        let mut tile_out = Vec::with_capacity(self.tiles.len());
        {
            let mut rest = out.as_mut_slice();
            for tile in &self.tiles {
                let (head, tail) = std::mem::take(&mut rest).split_at_mut(tile.points.len());
                tile_out.push(head);
                rest = tail;
            }
        }
        let mut screen = self.phase_screen(0);
        let step = if self.planes > 1 { self.step_screen() } else { Vec::new() };
        let pw2 = 2 * pw;
        let mut rows = par_filled(Complex64::default(), n * gy);
        let mut ranges: Vec<Range<usize>> = self.tiles.iter().map(|t| t.points.start..t.points.start).collect();
        for p in 0..self.planes {
            self.advance_ranges(&mut ranges, p);
            if ranges.iter().any(|r| !r.is_empty()) {
                self.image_to_padded(&f, &screen, &mut cols, &mut rows, &mut padded);
                tile_out.par_iter_mut().zip(ranges.par_iter()).zip(self.tiles.par_iter()).for_each_init(
                    Vec::new,
                    |interp, ((dst, range), tile)| {
                        if range.is_empty() {
                            return;
                        }
                        interp.clear();
                        interp.resize(range.len(), Complex64::default());
                        {
                            let mut sink = Sink::Sorted(&mut interp[..]);
                            interp_points::<W, W2, L>(e.simd, &kernel, &self.positions[range.clone()], &padded, pw2, &mut sink, &[], 0);
                        }
                        let local = range.start - tile.points.start;
                        for (j, v) in interp.iter().enumerate() {
                            dst[local + j] += v * self.weight(range.start + j, p);
                        }
                    },
                );
            }
            if p + 1 < self.planes {
                self.advance_screen(&mut screen, &step, p + 1);
            }
        }
        out
    }

    /// The plane's image (corrected image `f` times the conjugate phase screen) onto the
    /// padded grid: inverse FFT the image columns, then the rows used, each written with
    /// periodic margins of width `support` (see [`Nufft2d`]'s forward transform).
    ///
    /// `cols` (`n x gy`) and `rows` (`gy x n`) are scratch space.
    fn image_to_padded(
        &self,
        f: &[Complex64],
        screen: &[Complex64],
        cols: &mut [Complex64],
        rows: &mut [Complex64],
        padded: &mut [f64],
    ) {
        let e = &self.engine;
        let (gx, gy, n) = (e.grid_nx, e.grid_ny, self.size);
        let w = e.shape.support;
        let (h, half) = (n / 2 + 1, n / 2);
        cols.par_chunks_mut(gy).enumerate().for_each_init(
            || vec![Complex64::default(); e.ifft_y.get_inplace_scratch_len()],
            |scratch, (ix, col)| {
                let ph = &screen[ix.abs_diff(half) * h..][..h];
                let (lower, upper) = f[ix * n..(ix + 1) * n].split_at(half);
                // iy = n/2 + j at grid row j, iy = j < n/2 at row gy - n/2 + j (|jy| = n/2 - j).
                for ((c, v), q) in col[..half].iter_mut().zip(upper).zip(&ph[..half]) {
                    *c = v * q.conj();
                }
                col[half..gy - half].fill(Complex64::default());
                for (j, (c, v)) in col[gy - half..].iter_mut().zip(lower).enumerate() {
                    *c = v * ph[half - j].conj();
                }
                e.ifft_y.process_with_scratch(col, scratch);
            },
        );
        // Grid rows, contiguous (the columns' transpose), then the row transforms.
        crate::fft2::transpose(cols, rows, n, gy);
        let rows: &[Complex64] = rows;
        let pw = gx + 2 * w;
        padded.par_chunks_mut(2 * pw).enumerate().for_each_init(
            || (vec![Complex64::default(); gx], vec![Complex64::default(); e.ifft_x.get_inplace_scratch_len()]),
            |(row, scratch), (q, dst)| {
                let r = (q + gy - w) % gy;
                if !self.row_used[r] {
                    return;
                }
                let src = &rows[r * n..(r + 1) * n];
                row[..half].copy_from_slice(&src[half..]);
                row[half..gx - half].fill(Complex64::default());
                row[gx - half..].copy_from_slice(&src[..half]);
                e.ifft_x.process_with_scratch(row, scratch);
                // Padded column i holds grid column (i - w) mod gx.
                let wrapped = row[gx - w..].iter().chain(row.iter()).chain(&row[..w]);
                for (d, v) in dst.chunks_exact_mut(2).zip(wrapped) {
                    d[0] = v.re;
                    d[1] = v.im;
                }
            },
        );
    }
}

/// Fourier transform of the kernel in plane units, `psi_hat(eta) = integral over s in
/// [-support/2, support/2] of phi(2 s / support) cos(2 pi s eta)`, by Gauss-Legendre
/// quadrature as [`KernelShape::fourier_coefficients`] (which is this at `eta = k / n`).
pub(crate) fn psi_hat(shape: &KernelShape, eta: f64) -> f64 {
    let half = shape.support as f64 / 2.0;
    let (nodes, weights) = gauss_legendre(4 * shape.support + 40);
    nodes
        .iter()
        .zip(&weights)
        .map(|(&x, &wt)| {
            let d = 0.5 * half * (x + 1.0);
            wt * half * shape.eval(d / half) * (2.0 * PI * eta * d).cos()
        })
        .sum()
}

/// Chebyshev interpolant of a smooth function on `[-a, a]`.
struct Chebyshev {
    a: f64,
    coeffs: Vec<f64>,
}

impl Chebyshev {
    fn fit(f: impl Fn(f64) -> f64, a: f64, nodes: usize) -> Chebyshev {
        let x: Vec<f64> = (0..nodes).map(|k| (PI * (k as f64 + 0.5) / nodes as f64).cos()).collect();
        let fx: Vec<f64> = x.iter().map(|&x| f(a * x)).collect();
        let coeffs = (0..nodes)
            .map(|j| {
                let s: f64 = fx
                    .iter()
                    .enumerate()
                    .map(|(k, v)| v * (PI * j as f64 * (k as f64 + 0.5) / nodes as f64).cos())
                    .sum();
                s * if j == 0 { 1.0 } else { 2.0 } / nodes as f64
            })
            .collect();
        Chebyshev { a, coeffs }
    }

    /// Clenshaw's recurrence at `t in [-a, a]`.
    fn eval(&self, t: f64) -> f64 {
        let x = t / self.a;
        let (mut b1, mut b2) = (0.0, 0.0);
        for &c in self.coeffs[1..].iter().rev() {
            let b0 = 2.0 * x * b1 - b2 + c;
            b2 = b1;
            b1 = b0;
        }
        x * b1 - b2 + self.coeffs[0]
    }
}

#[cfg(test)]
mod tests;
