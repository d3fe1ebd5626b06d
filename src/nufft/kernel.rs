//! The exponential-of-semicircle ("ES") gridding kernel of Barnett, Magland & af Klinteberg
//! (FINUFFT, 2019): `phi(z) = exp(beta * (sqrt(1 - z^2) - 1))` on `z in [-1, 1]`.
//!
//! Its support `w` (in grid cells) and shape `beta` follow from the requested accuracy and the
//! oversampling factor. Evaluating `exp` and `sqrt` for every cell of every visibility would
//! dominate the gridding time, so the kernel is tabulated once per plan as `w` polynomials (one
//! per covered cell) in the sub-cell offset, evaluated together by Horner's rule.

use crate::{Error, Result};

/// Largest kernel support the gridder is compiled for.
pub const MAX_SUPPORT: usize = 16;

/// Measured kernel tables: `(oversampling, [(beta / w, relative error) for w = 2 ..= 16])`.
/// Those up to 4 serve the uv grid's oversampling as asked; all of them the w direction of
/// w-gridding (see [`super::wgrid`]), where a finer plane spacing costs only more plane FFTs.
const KERNEL_TABLES: [(f64, [(f64, f64); 15]); 7] = [
    (
        1.25,
        [
            (1.30, 1.44e-1), (1.54, 3.19e-2), (1.70, 7.78e-3), (1.78, 2.11e-3), (1.78, 5.62e-4),
            (1.82, 1.42e-4), (1.82, 3.71e-5), (1.82, 1.10e-5), (1.82, 3.33e-6), (1.86, 6.67e-7),
            (1.86, 1.04e-7), (1.86, 1.90e-8), (1.86, 8.14e-9), (1.82, 2.28e-9), (1.82, 9.62e-10),
        ],
    ),
    (
        1.5,
        [
            (1.46, 8.94e-2), (1.82, 1.45e-2), (1.94, 2.42e-3), (1.98, 4.20e-4), (2.02, 7.31e-5),
            (2.02, 1.36e-5), (2.02, 2.61e-6), (2.06, 3.94e-7), (2.06, 5.73e-8), (2.06, 9.35e-9),
            (2.06, 1.81e-9), (2.02, 3.28e-10), (2.02, 6.31e-11), (2.06, 1.27e-11), (2.06, 1.91e-12),
        ],
    ),
    (
        2.0,
        [
            (2.18, 7.86e-2), (2.18, 7.20e-3), (2.22, 7.79e-4), (2.26, 8.94e-5), (2.29, 1.01e-5),
            (2.30, 1.16e-6), (2.31, 1.35e-7), (2.32, 1.50e-8), (2.32, 1.69e-9), (2.33, 1.76e-10),
            (2.33, 1.89e-11), (2.34, 2.10e-12), (2.34, 1.84e-13), (2.34, 2.16e-14), (2.34, 7.71e-15),
        ],
    ),
    (
        2.5,
        [
            (2.00, 4.76e-2), (2.28, 4.50e-3), (2.40, 4.20e-4), (2.44, 3.93e-5), (2.44, 3.73e-6),
            (2.48, 3.77e-7), (2.48, 3.22e-8), (2.48, 2.92e-9), (2.48, 2.69e-10), (2.48, 2.54e-11),
            (2.48, 2.35e-12), (2.48, 2.17e-13), (2.48, 2.11e-14), (2.48, 8.10e-15), (2.48, 7.83e-15),
        ],
    ),
    (
        3.0,
        [
            (2.16, 4.03e-2), (2.40, 3.44e-3), (2.48, 2.93e-4), (2.52, 2.53e-5), (2.56, 1.98e-6),
            (2.56, 1.68e-7), (2.56, 1.50e-8), (2.52, 1.19e-9), (2.56, 9.33e-11), (2.56, 6.93e-12),
            (2.60, 5.30e-13), (2.60, 4.05e-14), (2.60, 6.90e-15), (2.56, 6.17e-15), (2.48, 6.09e-15),
        ],
    ),
    (
        4.0,
        [
            (2.28, 3.23e-2), (2.56, 2.50e-3), (2.64, 1.93e-4), (2.68, 1.37e-5), (2.68, 9.91e-7),
            (2.72, 7.44e-8), (2.72, 4.77e-9), (2.72, 3.25e-10), (2.72, 2.32e-11), (2.72, 1.63e-12),
            (2.72, 1.11e-13), (2.72, 9.88e-15), (2.72, 6.55e-15), (2.56, 6.56e-15), (2.48, 6.52e-15),
        ],
    ),
    (
        6.0,
        [
            (2.40, 2.32e-2), (2.68, 2.08e-3), (2.76, 1.26e-4), (2.80, 8.40e-6), (2.84, 5.27e-7),
            (2.84, 3.12e-8), (2.84, 1.97e-9), (2.80, 1.20e-10), (2.84, 7.40e-12), (2.84, 4.30e-13),
            (2.84, 2.45e-14), (2.84, 6.12e-15), (2.76, 6.00e-15), (2.48, 5.99e-15), (2.48, 5.99e-15),
        ],
    ),
];

/// Shape parameters of the kernel for one accuracy / oversampling pair.
#[derive(Clone, Debug, PartialEq)]
pub struct KernelShape {
    /// Support in grid cells.
    pub support: usize,
    /// Exponent `beta` of the ES kernel.
    pub beta: f64,
}

impl KernelShape {
    /// The narrowest kernel whose measured error at oversampling `sigma` is at most `epsilon`.
    ///
    /// The table holds, per support `w`, the shape `beta / w` that minimised the relative L2
    /// error of both transform types against a direct DFT (random points, 64 x 48 image; the
    /// `r2d2 bench kernel-scan` reproduces it) and that error. FINUFFT's closed-form rule
    /// (`beta = 2.30 w`, `w = ceil(log10(10 / eps))`) lands at 1 to 2.5 eps; the table keeps
    /// the promise `error <= eps`. For an oversampling between tabulated ones the table of the
    /// next lower one is used: a kernel only gets more accurate on a finer grid.
    pub fn for_accuracy(epsilon: f64, sigma: f64) -> Result<KernelShape> {
        if !(1e-14..=0.1).contains(&epsilon) || !epsilon.is_finite() {
            return Err(Error::parameter(
                "epsilon",
                format!("expected a relative accuracy between 1e-14 and 0.1, got {epsilon}"),
            ));
        }
        if !(1.25..=4.0).contains(&sigma) {
            return Err(Error::parameter(
                "oversampling",
                format!("expected an oversampling factor between 1.25 and 4, got {sigma}"),
            ));
        }
        match Self::tabulated(epsilon, sigma) {
            Some(shape) => Ok(shape),
            None => {
                let needed = KERNEL_TABLES
                    .iter()
                    .filter(|(s, _)| *s <= 4.0)
                    .find(|(_, t)| t.last().expect("tables are not empty").1 <= epsilon)
                    .map(|(s, _)| format!("{s}"))
                    .unwrap_or_else(|| "more than 4".into());
                Err(Error::parameter(
                    "epsilon",
                    format!(
                        "an accuracy of {epsilon:e} needs a kernel wider than {MAX_SUPPORT} cells at \
                         oversampling {sigma}; use oversampling >= {needed} or relax epsilon"
                    ),
                ))
            }
        }
    }

    /// The narrowest tabulated kernel reaching `epsilon` at oversampling `sigma`, from the
    /// table of the highest tabulated oversampling not above `sigma`; `None` below the lowest
    /// table, or if no support up to [`MAX_SUPPORT`] reaches `epsilon`.
    pub(crate) fn tabulated(epsilon: f64, sigma: f64) -> Option<KernelShape> {
        let table = KERNEL_TABLES.iter().rev().find(|(s, _)| *s <= sigma + 1e-12).map(|(_, t)| t)?;
        let (i, (beta_over_w, _)) = table.iter().enumerate().find(|(_, (_, err))| *err <= epsilon)?;
        let support = i + 2;
        Some(KernelShape { support, beta: beta_over_w * support as f64 })
    }

    /// The oversamplings the kernel is tabulated for.
    pub(crate) fn tabulated_oversamplings() -> impl Iterator<Item = f64> {
        KERNEL_TABLES.iter().map(|(s, _)| *s)
    }

    /// The kernel at `z in [-1, 1]` (zero outside).
    pub fn eval(&self, z: f64) -> f64 {
        if z.abs() >= 1.0 {
            return 0.0;
        }
        (self.beta * ((1.0 - z * z).sqrt() - 1.0)).exp()
    }

    /// Fourier transform of the kernel at integer frequencies `k = 0 ..= kmax` on a grid of
    /// `n` cells: `psi(k) = integral over d of phi(2d/w) cos(2 pi k d / n)`, with d in cells.
    /// Gridding multiplies each mode by this factor; dividing it out ("grid correction") undoes
    /// that. Computed by Gauss-Legendre quadrature, which is exact to rounding for this
    /// smooth, compactly supported integrand with enough nodes.
    pub fn fourier_coefficients(&self, n: usize, kmax: usize) -> Vec<f64> {
        let half = self.support as f64 / 2.0;
        let (nodes, weights) = gauss_legendre(4 * self.support + 40);
        // Map [-1, 1] to [0, half]; the integrand is even in d.
        let d: Vec<f64> = nodes.iter().map(|&x| 0.5 * half * (x + 1.0)).collect();
        let f: Vec<f64> = d
            .iter()
            .zip(&weights)
            .map(|(&d, &wt)| wt * 0.5 * half * 2.0 * self.eval(d / half))
            .collect();
        (0..=kmax)
            .map(|k| {
                let omega = 2.0 * std::f64::consts::PI * k as f64 / n as f64;
                d.iter().zip(&f).map(|(&d, &f)| f * (omega * d).cos()).sum()
            })
            .collect()
    }
}

/// Nodes and weights of `q`-point Gauss-Legendre quadrature on [-1, 1] (Newton's method on
/// the Legendre polynomial from the Tricomi initial guesses).
pub fn gauss_legendre(q: usize) -> (Vec<f64>, Vec<f64>) {
    let mut nodes = vec![0.0; q];
    let mut weights = vec![0.0; q];
    for i in 0..q.div_ceil(2) {
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (q as f64 + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            // Legendre recurrence for P_q(x) and its derivative.
            let (mut p0, mut p1) = (1.0, x);
            for k in 2..=q {
                let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            let p = if q == 0 { 1.0 } else if q == 1 { x } else { p1 };
            let pm1 = if q == 1 { 1.0 } else { p0 };
            dp = q as f64 * (x * p - pm1) / (x * x - 1.0);
            let dx = p / dp;
            x -= dx;
            if dx.abs() < 1e-16 {
                break;
            }
        }
        nodes[i] = -x;
        nodes[q - 1 - i] = x;
        let wt = 2.0 / ((1.0 - x * x) * dp * dp);
        weights[i] = wt;
        weights[q - 1 - i] = wt;
    }
    (nodes, weights)
}

/// The kernel as `W` polynomials in the sub-cell position, for Horner evaluation.
///
/// A point at grid coordinate `t` touches cells `i0 .. i0 + W` with `i0 = ceil(t - W/2)`;
/// `frac = i0 - t + W/2 in [0, 1)` fixes all `W` kernel values. With `z = 2 frac - 1`,
/// cell `b` has value `p_b(z) = sum_d coeff[d][b] z^(D - d)`.
#[derive(Clone, Debug)]
pub struct PolynomialKernel<const W: usize> {
    /// Coefficients, highest degree first, so Horner runs front to back.
    pub coeffs: Vec<[f64; W]>,
}

impl<const W: usize> PolynomialKernel<W> {
    /// Fit the kernel to within `tolerance` (absolute; the kernel peak is 1) with the lowest
    /// degree that passes the check on a fine sample.
    /// The kernel's own jump of `exp(-beta)` at the support edge bounds what any polynomial
    /// can reach, so the tolerance is raised to twice that.
    pub fn fit(shape: &KernelShape, tolerance: f64) -> PolynomialKernel<W> {
        assert_eq!(shape.support, W, "kernel support and W disagree");
        let tolerance = tolerance.max(2.0 * (-shape.beta).exp());
        let mut best = None;
        for degree in 3..=(W + 12).min(24) {
            let kernel = Self::fit_degree(shape, degree);
            let err = kernel.max_error(shape);
            best = Some(kernel);
            if err <= tolerance {
                break;
            }
        }
        best.expect("at least one degree is tried")
    }

    fn fit_degree(shape: &KernelShape, degree: usize) -> PolynomialKernel<W> {
        let n = degree + 1;
        // Chebyshev interpolation at the n Chebyshev points, then conversion to monomials.
        let zs: Vec<f64> =
            (0..n).map(|k| (std::f64::consts::PI * (k as f64 + 0.5) / n as f64).cos()).collect();
        let mut mono = vec![[0.0f64; W]; n]; // mono[p][b]: coefficient of z^p
        for b in 0..W {
            let values: Vec<f64> = zs.iter().map(|&z| cell_value(shape, b, z)).collect();
            let cheb: Vec<f64> = (0..n)
                .map(|j| {
                    let s: f64 = values
                        .iter()
                        .enumerate()
                        .map(|(k, v)| v * (std::f64::consts::PI * j as f64 * (k as f64 + 0.5) / n as f64).cos())
                        .sum();
                    s * if j == 0 { 1.0 } else { 2.0 } / n as f64
                })
                .collect();
            // T_0 = 1, T_1 = z, T_{j+1} = 2 z T_j - T_{j-1}, as monomial coefficient vectors.
            let mut t_prev = vec![0.0; n];
            let mut t_cur = vec![0.0; n];
            t_prev[0] = 1.0;
            if n > 1 {
                t_cur[1] = 1.0;
            }
            for (j, c) in cheb.iter().enumerate() {
                let t = if j == 0 { &t_prev } else { &t_cur };
                for p in 0..n {
                    mono[p][b] += c * t[p];
                }
                if j >= 1 {
                    let mut next = vec![0.0; n];
                    for p in 0..n - 1 {
                        next[p + 1] += 2.0 * t_cur[p];
                    }
                    for p in 0..n {
                        next[p] -= t_prev[p];
                    }
                    t_prev = std::mem::replace(&mut t_cur, next);
                }
            }
        }
        mono.reverse();
        PolynomialKernel { coeffs: mono }
    }

    /// All `W` kernel values for the sub-cell variable `z in [-1, 1]`.
    #[inline(always)]
    pub fn eval(&self, z: f64) -> [f64; W] {
        let mut acc = self.coeffs[0];
        for c in &self.coeffs[1..] {
            for b in 0..W {
                acc[b] = acc[b] * z + c[b];
            }
        }
        acc
    }

    fn max_error(&self, shape: &KernelShape) -> f64 {
        let mut err: f64 = 0.0;
        for k in 0..=400 {
            let z = -1.0 + 2.0 * k as f64 / 400.0;
            let approx = self.eval(z);
            for b in 0..W {
                err = err.max((approx[b] - cell_value(shape, b, z)).abs());
            }
        }
        err
    }
}

/// The x and y kernels of a point evaluated together, using the kernel's symmetry.
///
/// Cell `W - 1 - b` at `-z` is cell `b` at `z`, so with `p_b(z) = E_b(z^2) + z O_b(z^2)`
/// the cells `b` and `W - 1 - b` are `E_b +- z O_b`: only the `H = ceil(W / 2)` first cells'
/// even and odd parts are evaluated, polynomials in `z^2` of half the degree. The `L = 4 H`
/// lanes `[E_x, E_y, O_x, O_y]` (H each) run through one Horner loop, a multiply-add over all
/// lanes per step, which vectorises without remainders or shuffles.
#[derive(Clone, Debug)]
pub struct SymKernel<const W: usize, const W2: usize, const L: usize> {
    /// Per Horner step (highest power first), the lanes' coefficients.
    coeffs: Vec<[f64; L]>,
}

impl<const W: usize, const W2: usize, const L: usize> SymKernel<W, W2, L> {
    pub fn new(kernel: &PolynomialKernel<W>) -> Self {
        assert_eq!(W2, 2 * W, "W2 must be 2 W");
        let h = W.div_ceil(2);
        assert_eq!(L, 4 * h, "L must be 4 ceil(W / 2)");
        let degree = kernel.coeffs.len() - 1;
        // mono(p, b): coefficient of z^p for cell b.
        let mono = |p: usize, b: usize| if p <= degree { kernel.coeffs[degree - p][b] } else { 0.0 };
        let steps = degree / 2 + 1;
        let coeffs = (0..steps)
            .map(|s| {
                let q = steps - 1 - s;
                let mut lanes = [0.0; L];
                for b in 0..h {
                    let even = mono(2 * q, b);
                    // The middle cell of an odd support is even in z: its odd part is zero.
                    let odd = if W % 2 == 1 && b == h - 1 { 0.0 } else { mono(2 * q + 1, b) };
                    lanes[b] = even;
                    lanes[h + b] = even;
                    lanes[2 * h + b] = odd;
                    lanes[3 * h + b] = odd;
                }
                lanes
            })
            .collect();
        SymKernel { coeffs }
    }

    /// `[phi_0(zx) .. phi_{W-1}(zx), phi_0(zy) .. phi_{W-1}(zy)]`.
    #[inline(always)]
    pub fn eval<const FMA: bool>(&self, zx: f64, zy: f64) -> [f64; W2] {
        let h = L / 4;
        let (x2, y2) = (zx * zx, zy * zy);
        let mut u = [x2; L];
        u[h..2 * h].fill(y2);
        u[3 * h..].fill(y2);
        let mut acc = self.coeffs[0];
        for c in &self.coeffs[1..] {
            for j in 0..L {
                acc[j] = super::simd::madd::<FMA>(acc[j], u[j], c[j]);
            }
        }
        let mut out = [0.0; W2];
        for b in 0..h {
            let (ex, ey) = (acc[b], acc[h + b]);
            let (ox, oy) = (zx * acc[2 * h + b], zy * acc[3 * h + b]);
            out[W - 1 - b] = ex - ox;
            out[b] = ex + ox;
            out[W + W - 1 - b] = ey - oy;
            out[W + b] = ey + oy;
        }
        out
    }
}

/// Exact kernel value of cell `b` for sub-cell variable `z` (see [`PolynomialKernel`]).
fn cell_value(shape: &KernelShape, b: usize, z: f64) -> f64 {
    let w = shape.support as f64;
    let frac = 0.5 * (z + 1.0);
    let d = frac - w / 2.0 + b as f64;
    shape.eval(2.0 * d / w)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gauss_legendre_integrates_polynomials_exactly() {
        let (x, w) = gauss_legendre(10);
        let integral: f64 = x.iter().zip(&w).map(|(x, w)| w * x.powi(18)).sum();
        assert!((integral - 2.0 / 19.0).abs() < 1e-14, "{integral}");
        let total: f64 = w.iter().sum();
        assert!((total - 2.0).abs() < 1e-14);
    }

    #[test]
    fn polynomial_kernel_matches_exact_kernel() {
        let shape = KernelShape::for_accuracy(1e-6, 2.0).unwrap();
        assert_eq!(shape.support, 8);
        // The exact kernel jumps by exp(-beta) ~ 1e-8 at the support edge, which bounds how
        // well any polynomial can follow it; far below the NUFFT's own error.
        let poly = PolynomialKernel::<8>::fit(&shape, 1e-12);
        assert!(poly.max_error(&shape) <= 2.0 * (-shape.beta).exp(), "{}", poly.max_error(&shape));
        assert!(poly.coeffs.len() <= 8 + 8, "degree {} is more than needed", poly.coeffs.len() - 1);
    }

    #[test]
    fn symmetric_evaluation_matches_plain_horner() {
        fn check<const W: usize, const W2: usize, const L: usize>(eps: f64) {
            let shape = KernelShape::for_accuracy(eps, 2.0).unwrap();
            assert_eq!(shape.support, W);
            let poly = PolynomialKernel::<W>::fit(&shape, eps / 20.0);
            let sym = SymKernel::<W, W2, L>::new(&poly);
            for k in 0..=50 {
                let zx = -1.0 + k as f64 / 25.0;
                let zy = 1.0 - k as f64 / 40.0;
                let both = sym.eval::<false>(zx, zy);
                let (px, py) = (poly.eval(zx), poly.eval(zy));
                for b in 0..W {
                    assert!((both[b] - px[b]).abs() < 1e-13, "W {W} x cell {b} at {zx}");
                    assert!((both[W + b] - py[b]).abs() < 1e-13, "W {W} y cell {b} at {zy}");
                }
            }
        }
        check::<7, 14, 16>(1e-5);
        check::<8, 16, 16>(1e-6);
        check::<3, 6, 8>(1e-2);
    }

    #[test]
    fn unreachable_accuracy_is_a_clear_error() {
        let err = KernelShape::for_accuracy(1e-12, 1.25).unwrap_err().to_string();
        assert!(err.contains("epsilon") && err.contains("oversampling"), "{err}");
    }

    #[test]
    fn fourier_coefficient_at_zero_is_kernel_integral() {
        let shape = KernelShape::for_accuracy(1e-4, 2.0).unwrap();
        // Direct trapezoid integral over d in [-w/2, w/2].
        let half = shape.support as f64 / 2.0;
        let m = 200_000;
        let h = 2.0 * half / m as f64;
        let direct: f64 = (0..=m)
            .map(|i| {
                let d = -half + i as f64 * h;
                let wgt = if i == 0 || i == m { 0.5 } else { 1.0 };
                wgt * shape.eval(d / half)
            })
            .sum::<f64>()
            * h;
        let psi = shape.fourier_coefficients(64, 0)[0];
        assert!((psi - direct).abs() < 1e-8 * direct, "{psi} vs {direct}");
    }
}
