//! The normal operator `D x = kappa Re{Phi^H diag(omega) Phi x}` with the w-term, as a short
//! sum of convolutions: once one pass over the samples has built its kernels, applying it
//! costs a few FFTs per w-plane, whatever the number of samples (the coplanar case is
//! [`PsfConvolution`](crate::operator::PsfConvolution), one kernel).
//!
//! Conventions are `crate::nufft::wgrid`'s: `D x (p) = Re sum_k omega_k sum_q x_q
//! exp(-2 pi i (u_k (l_p - l_q) + v_k (m_p - m_q) + w_k (t_p - t_q)))`, `t = n - 1`. The image
//! being real, a sample at `-(u, v, w)` adds the same as one at `(u, v, w)`: every `w` is
//! taken `>= 0`. Over the image `|t_p - t_q| <= T = max(-t)`; write
//!
//! `exp(-2 pi i w dt) ~= sum_j a_j(w) exp(-2 pi i w_j dt)` for `|dt| <= T`,
//!
//! with planes `w_j = j delta` and real coefficients `a_j(w)`, non-zero on the `taps` planes
//! nearest `w` ([`WTaps`]: least squares over the band, which `delta = 1 / (2 sigma T)`
//! makes a fraction `1 / sigma` of the period). The sum separates in `p` and `q`:
//!
//! `D x (p) = Re sum_j exp(-2 pi i w_j t_p) [P_j * (exp(+2 pi i w_j t) x)] (p)`,
//! `P_j (dl, dm) = sum_k omega_k a_j(w_k) exp(-2 pi i (u_k dl + v_k dm))`,
//!
//! a linear convolution with each plane's kernel `P_j` over the `2N x 2N` offsets, which is
//! the 2N PSF of the weights `omega_k a_j(w_k)`: one gridding pass makes them all
//! ([`WToeplitzBuilder`]). The coefficients carry no correction factor (it would depend on `dt`,
//! which does not separate), so their accuracy is the least-squares fit's; the taps are as many
//! as that fit needs to meet the NUFFT's accuracy.

use crate::fft2::Fft2;
use crate::nufft::wgrid::n_minus_one;
use crate::nufft::{ChunkedAdjoint, NufftParams};
use super::geometry::ImageGeometry;
use crate::{Error, Result};
use num_complex::Complex64;
use rayon::prelude::*;
use rustfft::FftDirection;
use std::f64::consts::PI;
use std::sync::Arc;

/// Most taps a fit may take.
const MAX_TAPS: usize = 24;

/// Oversamplings of the period the band may have (the plane spacing's `sigma`).
const SIGMAS: [f64; 6] = [1.5, 2.0, 3.0, 4.0, 6.0, 8.0];

/// Largest `max |w| / delta` a plan is made for.
const MAX_PLANE_SPAN: f64 = (1u64 << 32) as f64;

/// Intervals of the coefficient table over a plane spacing (cubic interpolation: its error is
/// far below any accuracy asked, see [`WTaps::new`]).
const TABLE_STEPS: usize = 256;

/// Least-squares coefficients `a_m(f)`, `m = 1 - taps/2 ..= taps/2`, of
/// `exp(-2 pi i f s) ~= sum_m a_m(f) exp(-2 pi i m s)` over `|s| <= 1 / (2 sigma)`, for a
/// plane offset `f` in `[0, 1]`, tabulated.
pub struct WTaps {
    sigma: f64,
    taps: usize,
    /// `table[(i + 1) * taps + m]`: the coefficients at `f = i / TABLE_STEPS`, `i = -1 ..=
    /// TABLE_STEPS + 1`.
    table: Vec<f64>,
    /// Largest error of the fit measured over the band.
    error: f64,
}

impl WTaps {
    /// The fit of `taps` (even) coefficients over the band of `sigma`.
    pub fn new(sigma: f64, taps: usize) -> Result<WTaps> {
        if taps < 2 || taps % 2 != 0 || taps > MAX_TAPS || !(sigma > 1.0 && sigma.is_finite()) {
            return Err(Error::parameter("w taps", format!("expected an even number of taps in 2..={MAX_TAPS} and an oversampling above 1, got {taps} and {sigma}")));
        }
        let fit = LeastSquares::new(sigma, taps);
        let table = (0..TABLE_STEPS + 3).flat_map(|i| fit.solve((i as f64 - 1.0) / TABLE_STEPS as f64)).collect();
        let mut w = WTaps { sigma, taps, table, error: 0.0 };
        w.error = w.measured_error();
        Ok(w)
    }

    /// The fewest taps over the band of `sigma` whose fit is within `epsilon`, if any is.
    pub fn for_accuracy(sigma: f64, epsilon: f64) -> Option<WTaps> {
        Self::for_accuracy_within(sigma, epsilon, MAX_TAPS)
    }

    /// As [`WTaps::for_accuracy`], trying no more than `most` taps.
    fn for_accuracy_within(sigma: f64, epsilon: f64, most: usize) -> Option<WTaps> {
        (1..=most.min(MAX_TAPS) / 2).map(|h| 2 * h).filter_map(|taps| WTaps::new(sigma, taps).ok()).find(|w| w.error <= epsilon)
    }

    pub fn sigma(&self) -> f64 {
        self.sigma
    }
    pub fn taps(&self) -> usize {
        self.taps
    }
    /// Largest error of the fit (tabulated and interpolated) measured over the band.
    pub fn error(&self) -> f64 {
        self.error
    }

    /// Tap `m` (`0 .. taps`, for plane offset `m + 1 - taps/2`) at plane offset `f` in `[0, 1)`.
    pub fn coefficient(&self, f: f64, m: usize) -> f64 {
        self.interpolated(&self.interpolation(f, 1.0), m)
    }

    /// Where offset `f` falls in the table and its cubic Lagrange weights (times `scale`).
    #[inline]
    fn interpolation(&self, f: f64, scale: f64) -> TapInterpolation {
        let u = f * TABLE_STEPS as f64;
        let i = (u.floor().max(0.0) as usize).min(TABLE_STEPS - 1);
        let r = u - i as f64;
        // On nodes i - 1 ..= i + 2 (stored at i ..= i + 3).
        let (a, b, c, d) = ((r + 1.0), r, (r - 1.0), (r - 2.0));
        let l = [-b * c * d / 6.0, a * c * d / 2.0, -a * b * d / 2.0, a * b * c / 6.0];
        TapInterpolation { row: (i * self.taps) as u32, base: 0, weights: l.map(|l| l * scale) }
    }

    #[inline]
    fn interpolated(&self, p: &TapInterpolation, m: usize) -> f64 {
        let (t, row) = (self.taps, p.row as usize + m);
        p.weights[0] * self.table[row] + p.weights[1] * self.table[row + t] + p.weights[2] * self.table[row + 2 * t] + p.weights[3] * self.table[row + 3 * t]
    }

    /// Largest `|sum_m a_m(f) exp(-2 pi i m s) - exp(-2 pi i f s)|` over offsets `f` between
    /// the table's nodes and a fine grid of the band.
    fn measured_error(&self) -> f64 {
        let half = 0.5 / self.sigma;
        let points = 64 * self.taps + 1;
        let band = |i: usize| -half + 2.0 * half * i as f64 / (points - 1) as f64;
        // The taps' phasors at each band point do not depend on the offset: made once (the
        // trigonometry was most of a plan's making).
        let phasors: Vec<Complex64> = (0..points).flat_map(|i| (0..self.taps).map(move |m| (i, m))).map(|(i, m)| Complex64::cis(-2.0 * PI * self.offset(m) as f64 * band(i))).collect();
        let mut worst = 0.0f64;
        // The fit at f and 1 - f are mirror images: half the offsets suffice.
        for step in 0..=40 {
            let f = (step as f64 + 0.37) / 80.0;
            let a: Vec<f64> = (0..self.taps).map(|m| self.coefficient(f, m)).collect();
            for (i, taps) in phasors.chunks_exact(self.taps).enumerate() {
                let approx: Complex64 = a.iter().zip(taps).map(|(&a, &p)| a * p).sum();
                worst = worst.max((approx - Complex64::cis(-2.0 * PI * f * band(i))).norm());
            }
        }
        worst
    }

    /// The plane offset of tap `m`.
    fn offset(&self, m: usize) -> i64 {
        m as i64 + 1 - (self.taps / 2) as i64
    }
}

/// One sample's taps: its row of the table, its first plane, and the interpolation weights
/// (times its weight).
#[derive(Clone, Copy, Default)]
struct TapInterpolation {
    row: u32,
    base: i32,
    weights: [f64; 4],
}

/// The real least-squares problem of [`WTaps`] on a grid of the band, factored once
/// (Householder QR: the condition of the fit, not its square) and solved for each offset.
struct LeastSquares {
    /// Band points `s_i`.
    s: Vec<f64>,
    /// Householder vector `k`, over rows `k..` (scaled so that reflecting is `b -= v (v . b)`).
    reflectors: Vec<Vec<f64>>,
    /// `R`, row-major `taps x taps`.
    r: Vec<f64>,
}

impl LeastSquares {
    fn new(sigma: f64, taps: usize) -> LeastSquares {
        let half = 0.5 / sigma;
        let npoints = 16 * taps + 1;
        let s: Vec<f64> = (0..npoints).map(|i| -half + 2.0 * half * i as f64 / (npoints - 1) as f64).collect();
        // Columns (one per tap): the real parts, then the imaginary parts, of exp(-2 pi i m s_i).
        let mut columns: Vec<Vec<f64>> = (0..taps)
            .map(|m| {
                let o = (m as i64 + 1 - (taps / 2) as i64) as f64;
                s.iter().map(|&si| (2.0 * PI * o * si).cos()).chain(s.iter().map(|&si| -(2.0 * PI * o * si).sin())).collect()
            })
            .collect();
        let mut reflectors = Vec::with_capacity(taps);
        let mut r = vec![0.0; taps * taps];
        for k in 0..taps {
            let x = &columns[k][k..];
            let norm = x.iter().map(|a| a * a).sum::<f64>().sqrt();
            let alpha = if x[0] > 0.0 { -norm } else { norm };
            let mut v = x.to_vec();
            v[0] -= alpha;
            let vn = v.iter().map(|a| a * a).sum::<f64>().sqrt();
            if vn > 0.0 {
                // |v|^2 = 2: the reflection I - v v^T.
                v.iter_mut().for_each(|a| *a *= std::f64::consts::SQRT_2 / vn);
            }
            r[k * taps + k] = alpha;
            for j in k + 1..taps {
                let c = &mut columns[j][k..];
                let dot: f64 = v.iter().zip(c.iter()).map(|(a, b)| a * b).sum();
                c.iter_mut().zip(&v).for_each(|(c, a)| *c -= dot * a);
                r[k * taps + j] = c[0];
            }
            reflectors.push(v);
        }
        LeastSquares { s, reflectors, r }
    }

    /// The coefficients for offset `f`.
    fn solve(&self, f: f64) -> Vec<f64> {
        let taps = self.reflectors.len();
        let mut b: Vec<f64> = self.s.iter().map(|&si| (2.0 * PI * f * si).cos()).chain(self.s.iter().map(|&si| -(2.0 * PI * f * si).sin())).collect();
        for (k, v) in self.reflectors.iter().enumerate() {
            let dot: f64 = v.iter().zip(&b[k..]).map(|(a, b)| a * b).sum();
            b[k..].iter_mut().zip(v).for_each(|(b, a)| *b -= dot * a);
        }
        let mut a = vec![0.0; taps];
        for k in (0..taps).rev() {
            let sum: f64 = (k + 1..taps).map(|j| self.r[k * taps + j] * a[j]).sum();
            a[k] = (b[k] - sum) / self.r[k * taps + k];
        }
        a
    }
}

/// The planes of a w-aware Toeplitz form for an image and a `|w|` range: their spacing, the
/// first one's index and their number, and the fit of the coefficients. Cheap to make: the
/// memory it will take is known before anything is gridded.
pub struct WToeplitzPlan {
    pub taps: WTaps,
    /// Plane spacing (wavelengths).
    pub delta: f64,
    /// Index `j` of the first plane (`w_j = j delta`).
    pub first: i64,
    pub planes: usize,
    /// The `|w|` bound it was made for.
    pub max_abs_w: f64,
    size: usize,
}

impl WToeplitzPlan {
    /// The plan of fewest planes for `geometry` and samples of `|w| <= max_abs_w` at relative
    /// accuracy `epsilon`; `None` where no fit of at most [`MAX_TAPS`] taps is accurate
    /// enough, or the image reaches the edge of the projection.
    pub fn new(geometry: ImageGeometry, max_abs_w: f64, epsilon: f64) -> Option<WToeplitzPlan> {
        let span = max_t_difference(geometry)?;
        if !(max_abs_w.is_finite() && max_abs_w >= 0.0) {
            return None;
        }
        // The plan of fewest planes, then fewest taps, then the first oversampling of SIGMAS.
        // A plan has floor(max |w| / delta) + taps planes: the oversamplings are tried from the
        // largest (the fewest taps, the cheapest fits) and each is fitted only up to the taps
        // that could still beat the best plan so far (the fits are most of a plan's cost).
        let mut best: Option<((usize, usize, usize), WToeplitzPlan)> = None;
        for (index, &sigma) in SIGMAS.iter().enumerate().rev() {
            let delta = 1.0 / (2.0 * sigma * span);
            // Beyond this many planes no plan fits in any memory (and the casts stay exact).
            if max_abs_w / delta > MAX_PLANE_SPAN {
                continue;
            }
            let base = (max_abs_w / delta).floor() as usize;
            let beats = |taps: usize| best.as_ref().map_or(true, |(key, _)| (base + taps, taps, index) < *key);
            let most = (2..=MAX_TAPS).step_by(2).take_while(|&t| beats(t)).last().unwrap_or(0);
            let Some(taps) = WTaps::for_accuracy_within(sigma, epsilon / 2.0, most) else { continue };
            let first = 1 - (taps.taps() / 2) as i64;
            let planes = base + taps.taps();
            best = Some(((planes, taps.taps(), index), WToeplitzPlan { taps, delta, first, planes, max_abs_w, size: geometry.size }));
        }
        best.map(|(_, plan)| plan)
    }

    /// What makes two plans the same (kernels of parts built in other processes are summed
    /// only where their plans' keys agree).
    pub fn key(&self) -> String {
        format!("{} planes from {} spaced {:e}, {} taps at oversampling {}, {} pixels", self.planes, self.first, self.delta, self.taps.taps(), self.taps.sigma(), self.size)
    }

    /// Bytes the applied operator keeps: a real `2N x 2N` kernel per plane.
    pub fn kept_bytes(&self) -> f64 {
        let m = 2.0 * self.size as f64;
        self.planes as f64 * m * m * 8.0
    }
}

/// The largest coordinate (radians per pixel) of samples up to `max_uv` on `geometry`.
fn max_phase(geometry: ImageGeometry, max_uv: f64) -> f64 {
    2.0 * PI * geometry.pixel_rad * max_uv * (1.0 + 1e-12)
}

/// Largest `|t_p - t_q|` over the image: `-t` at the farthest corner (`t = 0` at the centre).
fn max_t_difference(geometry: ImageGeometry) -> Option<f64> {
    let half = geometry.size as f64 / 2.0 * geometry.pixel_rad;
    let r2 = 2.0 * half * half;
    (r2 < 1.0).then(|| -n_minus_one(r2))
}

/// Builds the kernels of [`WToeplitz`] from samples given a chunk at a time: each sample's
/// weight, times each of its taps, gridded on the `2N` image of its plane; two planes share
/// one complex grid (the kernels' Fourier transforms are real, so plane `2i` is the real part
/// and `2i + 1` the imaginary part of the pair's), and the grids hold only the window of the
/// uv-plane the samples reach.
pub struct WToeplitzBuilder {
    geometry: ImageGeometry,
    plan: WToeplitzPlan,
    /// Made at the first samples (a builder that only sums kernels finished elsewhere, as
    /// where parts live in other processes, needs no grids).
    adjoint: Option<ChunkedAdjoint>,
    nufft: NufftParams,
    threads: usize,
    /// The uv radius it grids up to.
    max_uv: f64,
    /// Bytes its grids take once made.
    grid_bytes: f64,
    /// Kernels (planes after one another) and coplanar 2N PSF finished elsewhere (parts built
    /// in other processes), added to these at the end.
    finished: Option<(Vec<f64>, Vec<f64>)>,
}

impl WToeplitzBuilder {
    /// Bytes a builder for samples up to `max_uv` would take at most: its grids while gridding
    /// beside the kernels and the transforms' work space when it finishes, allocating nothing.
    pub fn estimated_bytes(geometry: ImageGeometry, plan: &WToeplitzPlan, max_uv: f64, nufft: NufftParams) -> Result<f64> {
        Ok(Self::sizes(geometry, plan, max_uv, nufft)?.1)
    }

    /// (bytes of the grids once made, bytes of the whole builder at most).
    fn sizes(geometry: ImageGeometry, plan: &WToeplitzPlan, max_uv: f64, nufft: NufftParams) -> Result<(f64, f64)> {
        let doubled = geometry.doubled();
        let (grids, full) = ChunkedAdjoint::windowed_grid_bytes(doubled.size, doubled.size, plan.planes.div_ceil(2), max_phase(geometry, max_uv), nufft)?;
        // Finishing: the grids, one full grid and an image pair in work, the kernels, and
        // (summing parts) as much again.
        let m = 2.0 * geometry.size as f64;
        Ok((grids, grids + full + 4.0 * m * m * 16.0 + 2.0 * plan.kept_bytes()))
    }

    /// For samples of `sqrt(u^2 + v^2) <= max_uv` (beyond it they are refused where the grids
    /// are a window of the uv-plane). An error where the memory it would take is beyond the
    /// machine's budget (checked before anything is allocated).
    pub fn new(geometry: ImageGeometry, plan: WToeplitzPlan, max_uv: f64, nufft: NufftParams, threads: usize) -> Result<WToeplitzBuilder> {
        if plan.size != geometry.size {
            return Err(Error::parameter("w-Toeplitz plan", format!("planned for {} pixels a side, the image has {}", plan.size, geometry.size)));
        }
        let (grid_bytes, bytes) = Self::sizes(geometry, &plan, max_uv, nufft)?;
        crate::limits::check_memory(bytes, &format!("the {} w-planes of a w-aware Toeplitz form", plan.planes)).map_err(|m| Error::parameter("w-Toeplitz plan", m))?;
        Ok(WToeplitzBuilder { geometry, plan, adjoint: None, nufft, threads, max_uv, finished: None, grid_bytes })
    }

    fn adjoint(&mut self) -> Result<&mut ChunkedAdjoint> {
        if self.adjoint.is_none() {
            let doubled = self.geometry.doubled();
            let phase = max_phase(self.geometry, self.max_uv);
            self.adjoint = Some(ChunkedAdjoint::windowed(doubled.size, doubled.size, self.plan.planes.div_ceil(2), phase, self.nufft, self.threads)?);
        }
        Ok(self.adjoint.as_mut().expect("made above"))
    }

    pub fn planes(&self) -> usize {
        self.plan.planes
    }
    /// Its plan's [`key`](WToeplitzPlan::key).
    pub fn plan_key(&self) -> String {
        self.plan.key()
    }

    /// The `|w|` and uv radius bounds it was made for: a builder of a part in another process
    /// made for the same (and the same image and accuracy) has the same planes.
    pub fn bounds(&self) -> (f64, f64) {
        (self.plan.max_abs_w, self.max_uv)
    }

    /// Adds the kernels (`planes x (2N)^2`, planes after one another, as
    /// [`WToeplitz::kernels`]) and coplanar 2N PSF of samples built by another builder of the
    /// same plan (a part in another process).
    pub fn add_finished(&mut self, kernels: Vec<f64>, psf_2n: Vec<f64>) -> Result<()> {
        let m = 2 * self.geometry.size;
        if kernels.len() != self.plan.planes * m * m || psf_2n.len() != m * m {
            return Err(Error::parameter(
                "w-Toeplitz kernels",
                format!("expected {} planes of {m} x {m} and a {m} x {m} PSF, got {} and {} values", self.plan.planes, kernels.len(), psf_2n.len()),
            ));
        }
        match &mut self.finished {
            Some((k, p)) => {
                k.iter_mut().zip(&kernels).for_each(|(a, b)| *a += b);
                p.iter_mut().zip(&psf_2n).for_each(|(a, b)| *a += b);
            }
            None => self.finished = Some((kernels, psf_2n)),
        }
        Ok(())
    }
    pub fn taps(&self) -> usize {
        self.plan.taps.taps()
    }
    /// The band's oversampling of the plane spacing.
    pub fn sigma(&self) -> f64 {
        self.plan.taps.sigma()
    }

    /// Bytes of the grids it builds (made at the first samples).
    pub fn grid_bytes(&self) -> usize {
        self.grid_bytes as usize
    }

    /// Adds samples at `(u, v, w)` (wavelengths) with total weights `weight`.
    pub fn add(&mut self, u: &[f64], v: &[f64], w: &[f64], weight: &[f64]) -> Result<()> {
        let n = u.len();
        if v.len() != n || w.len() != n || weight.len() != n {
            return Err(Error::parameter("visibilities", "u, v, w and weight arrays differ in length"));
        }
        self.adjoint()?;
        let (geometry, plan, adjoint) = (self.geometry, &self.plan, self.adjoint.as_mut().expect("made above"));
        let taps = plan.taps.taps();
        let half = (taps / 2) as i64;
        // Mirrored to w >= 0: its uv coordinates, and its first plane (`None`: outside the
        // planes planned).
        let first_plane = |k: usize| -> Option<(i64, f64)> {
            let z = w[k].abs() / plan.delta;
            if !(z <= MAX_PLANE_SPAN) {
                return None;
            }
            let j0 = z.floor();
            let base = j0 as i64 + 1 - half - plan.first;
            (base >= 0 && base as usize + taps <= plan.planes).then_some((base, z - j0))
        };
        if let Some(k) = (0..n).find(|&k| first_plane(k).is_none()) {
            return Err(Error::parameter("w", format!("w = {} wavelengths lies outside the planes planned for |w| up to {}", w[k], plan.max_abs_w)));
        }
        let (x, y): (Vec<f64>, Vec<f64>) = (0..n)
            .map(|k| {
                let sign = if w[k] < 0.0 { -1.0 } else { 1.0 };
                geometry.uv_to_phase(sign * u[k], sign * v[k])
            })
            .unzip();
        // Each sample's taps, gathered in the gridder's order once for all the grids.
        let prepare = |order: &[u32]| -> Vec<TapInterpolation> {
            order
                .par_iter()
                .map(|&k| {
                    let k = k as usize;
                    let (base, frac) = first_plane(k).expect("checked");
                    TapInterpolation { base: base as i32, ..plan.taps.interpolation(frac, weight[k]) }
                })
                .collect()
        };
        let tap = |p: &TapInterpolation, j: usize| -> f64 {
            let m = j as i64 - i64::from(p.base);
            if m >= 0 && (m as usize) < taps {
                plan.taps.interpolated(p, m as usize)
            } else {
                0.0
            }
        };
        adjoint.add_in_order(&x, &y, prepare, |points, t, i| Complex64::new(tap(&points[i], 2 * t), tap(&points[i], 2 * t + 1)))?;
        Ok(())
    }

    /// The operator (not normalised: `kappa` 1) and the coplanar 2N PSF of the weights (as
    /// [`doubled_psf`](crate::operator::doubled_psf), unscaled; its row and column 0, offsets
    /// `-N` that no `N x N` image reaches, are zero).
    pub fn finish(self) -> Result<(WToeplitz, Vec<f64>)> {
        let WToeplitzBuilder { geometry, plan, adjoint, threads, finished, .. } = self;
        let (n, m) = (geometry.size, 2 * geometry.size);
        let pool = crate::parallel::shared_pool(threads)?;
        let forward = Fft2::new(m, m, FftDirection::Forward);
        let inverse = Fft2::new(m, m, FftDirection::Inverse);
        let (kernels, psf_2n) = match adjoint {
            // Kernels finished elsewhere only (or none at all).
            None => {
                let (other, psf_2n) = finished.unwrap_or_else(|| (vec![0.0; plan.planes * m * m], vec![0.0; m * m]));
                (other.chunks_exact(m * m).map(<[f64]>::to_vec).collect(), psf_2n)
            }
            Some(adjoint) => {
                let scale = 1.0 / (m * m) as f64;
                let mut kernels: Vec<Vec<f64>> = Vec::with_capacity(plan.planes);
                let mut coplanar = vec![0.0; m * m];
                adjoint.finish_each(|_, mut pair| {
                    pool.install(|| {
                        // Offsets -N (row and column 0) have no partner at +N in a 2N grid, and no
                        // N x N image needs them: zero, the pair's transforms are exactly real.
                        pair[..m].iter_mut().for_each(|c| *c = Complex64::default());
                        pair.iter_mut().step_by(m).for_each(|c| *c = Complex64::default());
                        forward.process(&mut pair);
                        let re: Vec<f64> = pair.par_iter().map(|c| c.re * scale).collect();
                        coplanar.par_iter_mut().zip(&re).for_each(|(s, k)| *s += k);
                        kernels.push(re);
                        if kernels.len() < plan.planes {
                            let im: Vec<f64> = pair.par_iter().map(|c| c.im * scale).collect();
                            coplanar.par_iter_mut().zip(&im).for_each(|(s, k)| *s += k);
                            kernels.push(im);
                        }
                    })
                });
                let mut psf_2n: Vec<Complex64> = coplanar.into_iter().map(|k| Complex64::new(k, 0.0)).collect();
                pool.install(|| inverse.process(&mut psf_2n));
                let mut psf_2n: Vec<f64> = psf_2n.into_iter().map(|c| c.re).collect();
                if let Some((other, other_psf)) = finished {
                    for (kernel, other) in kernels.iter_mut().zip(other.chunks_exact(m * m)) {
                        kernel.iter_mut().zip(other).for_each(|(a, b)| *a += b);
                    }
                    psf_2n.iter_mut().zip(&other_psf).for_each(|(a, b)| *a += b);
                }
                (kernels, psf_2n)
            }
        };
        // Transposed as the images' spectra are (`Fft2::process_from_rows_transposed`).
        let planes = kernels
            .into_iter()
            .enumerate()
            .map(|(j, kernel)| {
                let mut kernel_hat = vec![0.0; m * m];
                crate::fft2::transpose(&kernel, &mut kernel_hat, m, m);
                WPlane { w: (plan.first + j as i64) as f64 * plan.delta, kernel_hat }
            })
            .collect();
        let t = pixel_t(geometry);
        Ok((WToeplitz { size: n, planes, t, forward, inverse, pool, taps: plan.taps.taps(), sigma: plan.taps.sigma() }, psf_2n))
    }
}

/// `t = n - 1` of each pixel of `geometry`'s image.
pub(crate) fn pixel_t(geometry: ImageGeometry) -> Vec<f64> {
    let n = geometry.size;
    let half = n as f64 / 2.0;
    (0..n * n)
        .map(|p| {
            let (l, m) = ((p % n) as f64 - half, (p / n) as f64 - half);
            n_minus_one((l * l + m * m) * geometry.pixel_rad * geometry.pixel_rad)
        })
        .collect()
}

/// One plane of [`WToeplitz`]: its `w` and the FFT of its kernel (real; divided by `(2N)^2`
/// for the unnormalised inverse FFT; transposed as the images' spectra are).
struct WPlane {
    w: f64,
    kernel_hat: Vec<f64>,
}

/// `D` with the w-term as a sum of convolutions (see the module's documentation).
pub struct WToeplitz {
    size: usize,
    planes: Vec<WPlane>,
    /// `t = n - 1` per pixel.
    t: Vec<f64>,
    forward: Fft2,
    inverse: Fft2,
    pool: Arc<rayon::ThreadPool>,
    taps: usize,
    sigma: f64,
}

impl WToeplitz {
    pub fn size(&self) -> usize {
        self.size
    }
    pub fn planes(&self) -> usize {
        self.planes.len()
    }
    pub fn taps(&self) -> usize {
        self.taps
    }
    /// The band's oversampling of the plane spacing.
    pub fn sigma(&self) -> f64 {
        self.sigma
    }
    /// Bytes of its kernels.
    pub fn bytes(&self) -> usize {
        self.planes.iter().map(|p| p.kernel_hat.len() * 8).sum()
    }

    /// The kernels' FFTs, row-major, planes after one another (what
    /// [`WToeplitzBuilder::add_finished`] takes).
    pub fn kernels(&self) -> Vec<f64> {
        let m = 2 * self.size;
        let mut out = vec![0.0; self.planes.len() * m * m];
        for (plane, kernel) in self.planes.iter().zip(out.chunks_exact_mut(m * m)) {
            crate::fft2::transpose(&plane.kernel_hat, kernel, m, m);
        }
        out
    }

    /// Multiplies the operator by `kappa`.
    pub fn scale(&mut self, kappa: f64) {
        self.pool.install(|| self.planes.par_iter_mut().for_each(|p| p.kernel_hat.iter_mut().for_each(|k| *k *= kappa)));
    }

    /// `D x` for an `N x N` image.
    pub fn apply(&self, x: &[f64]) -> Vec<f64> {
        let (n, m) = (self.size, 2 * self.size);
        assert_eq!(x.len(), n * n, "image size");
        let mut out = vec![0.0; n * n];
        self.pool.install(|| {
            let mut z = vec![Complex64::default(); m * m];
            let mut scratch = vec![Complex64::default(); m * m];
            for plane in &self.planes {
                let turn = 2.0 * PI * plane.w;
                z.par_chunks_mut(m).enumerate().for_each(|(iy, row)| {
                    row.iter_mut().for_each(|c| *c = Complex64::default());
                    if iy < n {
                        for ix in 0..n {
                            let p = iy * n + ix;
                            row[ix] = Complex64::cis(turn * self.t[p]) * x[p];
                        }
                    }
                });
                self.forward.process_from_rows_transposed(&mut z, n, &mut scratch);
                z.par_iter_mut().zip(&plane.kernel_hat).for_each(|(c, k)| *c *= k);
                self.inverse.process_transposed_to_rows(&mut z, n, &mut scratch);
                // The linear convolution with a kernel centred at (N, N): pixel p is at p + N.
                out.par_chunks_mut(n).enumerate().for_each(|(iy, row)| {
                    let src = &z[(iy + n) * m + n..][..n];
                    for (ix, o) in row.iter_mut().enumerate() {
                        *o += (Complex64::cis(-turn * self.t[iy * n + ix]) * src[ix]).re;
                    }
                });
            }
        });
        out
    }

    /// The PSF `D delta` with the delta at `(N/2, N/2)` (peak at the centre).
    pub fn psf(&self) -> Vec<f64> {
        let n = self.size;
        let mut delta = vec![0.0; n * n];
        delta[(n / 2) * n + n / 2] = 1.0;
        self.apply(&delta)
    }
}

/// A field of `degrees` over `n` pixels with samples in the uv disc of half the Nyquist radius,
/// `|w|` up to `w_fraction` of the disc's radius in both signs and weights in 0.5..1.5
/// (`u, v, w, weight`): the w-term's forms are tested on it.
#[cfg(test)]
pub(crate) fn test_field(n: usize, degrees: f64, w_fraction: f64, samples: usize, seed: u64) -> (ImageGeometry, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
    let geometry = ImageGeometry::new(n, (degrees / n as f64).to_radians()).unwrap();
    let radius = 0.25 / geometry.pixel_rad;
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let (mut u, mut v, mut w, mut weight) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for _ in 0..samples {
        let (r, a) = (radius * next().sqrt(), 2.0 * PI * next());
        u.push(r * a.cos());
        v.push(r * a.sin());
        w.push(w_fraction * radius * (2.0 * next() - 1.0));
        weight.push(0.5 + next());
    }
    (geometry, u, v, w, weight)
}

/// `||a - b|| / ||b||`.
#[cfg(test)]
pub(crate) fn relative(a: &[f64], b: &[f64]) -> f64 {
    let d: f64 = a.iter().zip(b).map(|(a, b)| (a - b) * (a - b)).sum();
    let r: f64 = b.iter().map(|b| b * b).sum();
    (d / r).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nufft::direct;
    use crate::operator::{doubled_psf, MeasurementOperator};

    /// A wide field (30 degrees: the w-term turns phases by radians) with samples in the uv
    /// disc of half the Nyquist radius and |w| up to the disc's radius, in both signs.
    fn wide_field(n: usize, samples: usize, seed: u64) -> (ImageGeometry, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
        test_field(n, 30.0, 1.0, samples, seed)
    }

    #[test]
    fn the_tap_fit_meets_its_accuracy_at_offsets_and_points_it_was_not_measured_on() {
        for (sigma, epsilon) in [(2.0, 1e-4), (4.0, 1e-7), (6.0, 1e-9)] {
            let taps = WTaps::for_accuracy(sigma, epsilon).expect("a fit");
            assert!(taps.error() <= epsilon, "{sigma} {epsilon}: {}", taps.error());
            // Fewer taps would not do.
            assert!(WTaps::new(sigma, taps.taps() - 2).unwrap().error() > epsilon);
            let half = 0.5 / sigma;
            let mut worst = 0.0f64;
            for i in 0..97 {
                let f = (i as f64 * 0.618_034).fract();
                let s = half * ((i as f64 * 0.414_214).fract() * 2.0 - 1.0);
                let approx: Complex64 = (0..taps.taps()).map(|m| taps.coefficient(f, m) * Complex64::cis(-2.0 * PI * taps.offset(m) as f64 * s)).sum();
                worst = worst.max((approx - Complex64::cis(-2.0 * PI * f * s)).norm());
            }
            assert!(worst <= 1.5 * epsilon, "{sigma}: {worst:e} against {epsilon:e}");
        }
        assert!(WTaps::new(4.0, 3).is_err() && WTaps::new(1.0, 4).is_err());
    }

    #[test]
    fn a_plan_is_the_one_of_fewest_planes_then_taps_of_every_fit_over_every_oversampling() {
        // The plan fits each oversampling only up to the taps that could beat the best so far;
        // it must be the plan a fit of every oversampling would choose.
        let geometry = ImageGeometry::new(512, (1.0f64 / 3600.0 * 0.2).to_radians()).unwrap();
        let wide = ImageGeometry::new(256, (20.0f64 / 256.0).to_radians()).unwrap();
        let span_of = |g| max_t_difference(g).unwrap();
        for (g, max_abs_w, epsilon) in [(geometry, 1.4e5, 1e-5), (geometry, 1.4e5, 1e-7), (wide, 0.0, 1e-5), (wide, 40.0, 1e-6), (wide, 900.0, 1e-4), (wide, 900.0, 1e-9)] {
            let span = span_of(g);
            let all = SIGMAS
                .iter()
                .filter_map(|&sigma| {
                    let taps = WTaps::for_accuracy(sigma, epsilon / 2.0)?;
                    let delta = 1.0 / (2.0 * sigma * span);
                    let planes = (max_abs_w / delta).floor() as usize + taps.taps();
                    Some((planes, taps.taps(), sigma))
                })
                .min_by(|a, b| (a.0, a.1).cmp(&(b.0, b.1)));
            let plan = WToeplitzPlan::new(g, max_abs_w, epsilon);
            assert_eq!(plan.as_ref().map(|p| (p.planes, p.taps.taps(), p.taps.sigma())), all, "|w| {max_abs_w}, epsilon {epsilon}");
            if let Some(p) = plan {
                assert_eq!(p.first, 1 - (p.taps.taps() / 2) as i64);
                assert!((p.delta - 1.0 / (2.0 * p.taps.sigma() * span)).abs() <= 1e-15 * p.delta);
            }
        }
    }

    #[test]
    fn the_w_toeplitz_form_is_the_normal_operator_of_the_direct_sums() {
        let (geometry, u, v, w, weight) = wide_field(32, 300, 3);
        let (n, pixel) = (geometry.size, geometry.pixel_rad);
        let max_uv = u.iter().zip(&v).map(|(u, v)| u.hypot(*v)).fold(0.0, f64::max);
        let max_w = w.iter().fold(0.0f64, |m, w| m.max(w.abs()));
        assert!(2.0 * PI * max_w * max_t_difference(geometry).unwrap() > 2.0, "the w-term must matter here");
        let x: Vec<f64> = (0..n * n).map(|p| ((p as f64 * 0.37).sin() + 1.2) * if p % 7 == 0 { 3.0 } else { 1.0 }).collect();
        let xc: Vec<Complex64> = x.iter().map(|&a| Complex64::new(a, 0.0)).collect();
        let vis = direct::forward_w(n, pixel, &u, &v, &w, &xc);
        let weighted: Vec<Complex64> = vis.iter().zip(&weight).map(|(v, w)| v * w).collect();
        let truth: Vec<f64> = direct::adjoint_w(n, pixel, &u, &v, &w, &weighted).into_iter().map(|c| c.re).collect();
        for epsilon in [1e-4, 1e-7] {
            let nufft = NufftParams { epsilon, oversampling: 2.0 };
            let plan = WToeplitzPlan::new(geometry, max_w, epsilon).unwrap();
            let mut builder = WToeplitzBuilder::new(geometry, plan, max_uv, nufft, 2).unwrap();
            // In two chunks, as read.
            builder.add(&u[..120], &v[..120], &w[..120], &weight[..120]).unwrap();
            builder.add(&u[120..], &v[120..], &w[120..], &weight[120..]).unwrap();
            let (op, psf_2n) = builder.finish().unwrap();
            let error = relative(&op.apply(&x), &truth);
            // Its kernels as exported to another process's builder give the same operator.
            let mut other = WToeplitzBuilder::new(geometry, WToeplitzPlan::new(geometry, max_w, epsilon).unwrap(), max_uv, nufft, 2).unwrap();
            other.add_finished(op.kernels(), psf_2n.clone()).unwrap();
            assert_eq!(other.finish().unwrap().0.apply(&x), op.apply(&x), "epsilon {epsilon:e}: the exported kernels");
            assert!(error < 3.0 * epsilon, "epsilon {epsilon:e}: {error:e} ({} planes, {} taps)", op.planes(), op.taps());
            // The PSF is D of a delta; the 2N PSF the coplanar one.
            let ones: Vec<Complex64> = weight.iter().map(|&w| Complex64::new(w, 0.0)).collect();
            let psf_truth: Vec<f64> = direct::adjoint_w(n, pixel, &u, &v, &w, &ones).into_iter().map(|c| c.re).collect();
            assert!(relative(&op.psf(), &psf_truth) < 3.0 * epsilon);
            let mut coplanar = doubled_psf(geometry, &u, &v, &weight, 1.0, nufft, 2).unwrap();
            let m = 2 * n;
            for i in 0..m {
                coplanar[i] = 0.0;
                coplanar[i * m] = 0.0;
            }
            assert!(relative(&psf_2n, &coplanar) < 3.0 * epsilon);
            // The w-gridded operator agrees as well.
            let wgridded = MeasurementOperator::part_for_mode(true, geometry, &u, &v, &w, &weight, nufft, 2).unwrap();
            assert!(relative(&op.apply(&x), &wgridded.apply_normal(&x)) < 4.0 * epsilon);
        }
    }

    #[test]
    fn a_sample_outside_the_planned_range_is_refused() {
        let (geometry, u, v, w, weight) = wide_field(32, 50, 5);
        let max_uv = u.iter().zip(&v).map(|(u, v)| u.hypot(*v)).fold(0.0, f64::max);
        let plan = WToeplitzPlan::new(geometry, 1.0, 1e-6).unwrap();
        let mut builder = WToeplitzBuilder::new(geometry, plan, max_uv, NufftParams::default(), 1).unwrap();
        let e = builder.add(&u, &v, &w, &weight).unwrap_err().to_string();
        assert!(e.contains("outside the planes"), "{e}");
        // Beyond memory: refused before anything is allocated.
        let plan = WToeplitzPlan::new(geometry, 1e8, 1e-6).unwrap();
        let e = WToeplitzBuilder::new(geometry, plan, max_uv, NufftParams::default(), 1).err().unwrap().to_string();
        assert!(e.contains("w-planes"), "{e}");
        // A |w| no plan could span (a corrupt value): no plan, no overflow.
        assert!(WToeplitzPlan::new(geometry, 1e300, 1e-6).is_none() && WToeplitzPlan::new(geometry, f64::INFINITY, 1e-6).is_none());
        let plan = WToeplitzPlan::new(geometry, 100.0, 1e-6).unwrap();
        let mut builder = WToeplitzBuilder::new(geometry, plan, max_uv, NufftParams::default(), 1).unwrap();
        let e = builder.add(&u[..1], &v[..1], &[1e300], &weight[..1]).unwrap_err().to_string();
        assert!(e.contains("outside the planes"), "{e}");
        let plan = WToeplitzPlan::new(geometry, 1e3, 1e-6).unwrap();
        let mut builder = WToeplitzBuilder::new(geometry, plan, max_uv / 2.0, NufftParams::default(), 1).unwrap();
        let e = builder.add(&u, &v, &w, &weight).unwrap_err().to_string();
        assert!(e.contains("beyond the coordinate bound"), "{e}");
    }
}
