//! The normal operator `D` with a small w-term, as a Taylor series in `w` about the coplanar
//! PSF convolution: where the w-term turns phases by a fraction of a radian over the field
//! (a VLA field of a few arcminutes), a few more kernels of the PSF convolution's kind make
//! `D` to the NUFFT's accuracy at the cost of one to three pairs of FFTs, where the operator
//! grids and degrids every sample on its w-planes at each residual update.
//!
//! Conventions are `crate::operator::toeplitz`'s: `D x (p) = Re sum_k omega_k sum_q x_q exp(-2 pi i
//! (u_k (l_p - l_q) + v_k (m_p - m_q) + w_k (t_p - t_q)))`, `t = n - 1`. Expanding
//! `exp(-2 pi i w (t_p - t_q))` to order `M` and `(t_p - t_q)^m` by the binomial theorem
//! separates `p` and `q`:
//!
//! `D x (p) ~= sum_a t_p^a sum_b (-1)^b / (a! b!) [R_{a+b} * (t^b x)] (p)`, `a + b <= M`,
//! `R_m (dl, dm) = Re sum_k omega_k (-2 pi i w_k)^m exp(-2 pi i (u_k dl + v_k dm))`,
//!
//! real linear convolutions over the `2N x 2N` offsets (`R_0` is the 2N PSF). Every image
//! convolved and every result is real, so two go through one complex FFT: order `M` takes
//! `ceil((M + 1) / 2)` FFTs each way, order 1 as many as the PSF convolution.
//!
//! The truncation is bounded by `|2 pi w (t_p - t_q)|^(M+1) / (M+1)!` per sample and pixel
//! pair, a bound far above what a sky's flux, spread over the field and weighted by samples
//! of every `|w|`, meets. So the form is not trusted from the bound: [`WTaylor::deviation`]
//! measures it against the operator on an image of the job's own sky (its dirty image), and
//! the gridder uses it only where the two agree to the NUFFT's accuracy.

use crate::fft2::Fft2;
use super::geometry::ImageGeometry;
use super::toeplitz::pixel_t;
use crate::{Error, Result};
use num_complex::Complex64;
use rayon::prelude::*;
use rustfft::FftDirection;
use std::f64::consts::PI;
use std::sync::{Arc, Mutex};

/// Highest order tried: its six terms fill three complex FFTs each way, still fewer than the
/// operator's w-planes where an order this high is needed (a MeerKAT field of 1-2 rad).
pub const MAX_ORDER: usize = 5;

/// How far, in units of the NUFFT's accuracy, the series may be from the operator on the dirty
/// image. Its error reaches only the networks' input (the residual written at the end is the
/// operator's): at the default accuracy, `1e-5` of `D x`, about a hundredth of the residual a
/// series leaves at its noise floor. Ten times more on the final model is worth a warning.
pub const TOLERANCE: f64 = 10.0;

/// `D` as a Taylor series in `w` of the PSF convolution (see the module's documentation).
pub struct WTaylor {
    size: usize,
    /// FFTs of `R_0 ..= R_order`, each divided by `(2N)^2` for the unnormalised inverse FFT,
    /// transposed as the images' spectra are (`Fft2::process_from_rows_transposed`).
    kernel_hats: Vec<Vec<Complex64>>,
    /// `t = n - 1` per pixel.
    t: Vec<f64>,
    forward: Fft2,
    inverse: Fft2,
    pool: Arc<rayon::ThreadPool>,
    /// The transforms' arrays, kept from one update to the next: made afresh, their pages were
    /// mapped and zeroed at every update.
    buffers: Mutex<Buffers>,
}

/// Arrays of `(2N)^2` an application works in.
#[derive(Default)]
struct Buffers {
    spectra: Vec<Vec<Complex64>>,
    sums: Vec<Vec<Complex64>>,
    scratch: Vec<Complex64>,
}

/// The value each sample adds to `R_m` (`m >= 1`), beside its weight: `(-2 pi i w)^m`, real
/// for even `m` and imaginary for odd.
pub fn kernel_factor(w: f64, m: usize) -> Complex64 {
    Complex64::new(0.0, -2.0 * PI * w).powu(m as u32)
}

impl WTaylor {
    /// The form of order `kernels.len() - 1` from its kernels `R_0, R_1, ...` (each `2N x 2N`,
    /// centre at `(N, N)`, scaled alike: `R_0` the 2N PSF as the PSF convolution takes it).
    pub fn new(geometry: ImageGeometry, kernels: &[Vec<f64>], threads: usize) -> Result<WTaylor> {
        let (n, m) = (geometry.size, 2 * geometry.size);
        let Some((first, next)) = kernels.split_first().filter(|_| kernels.len() <= MAX_ORDER + 1) else {
            return Err(Error::parameter("w_taylor", format!("expected 1 to {} kernels, got {}", MAX_ORDER + 1, kernels.len())));
        };
        let pool = crate::parallel::shared_pool(threads)?;
        let forward = Fft2::new(m, m, FftDirection::Forward);
        let inverse = Fft2::new(m, m, FftDirection::Inverse);
        let mut form = WTaylor { size: n, kernel_hats: Vec::new(), t: pixel_t(geometry), forward, inverse, pool, buffers: Mutex::new(Buffers::default()) };
        for kernel in std::iter::once(first).chain(next) {
            form.push_kernel(kernel)?;
        }
        Ok(form)
    }

    /// Raises the order by one with the next kernel `R_{order + 1}` (as [`WTaylor::new`] takes
    /// them): the kernels it has are kept as transformed.
    pub fn push_kernel(&mut self, kernel: &[f64]) -> Result<()> {
        let (n, m) = (self.size, 2 * self.size);
        if self.kernel_hats.len() > MAX_ORDER {
            return Err(Error::parameter("w_taylor", format!("expected 1 to {} kernels, got {}", MAX_ORDER + 1, self.kernel_hats.len() + 1)));
        }
        if kernel.len() != m * m {
            return Err(Error::parameter("w_taylor", format!("expected {m} x {m} kernels for a {n} x {n} image, got {} pixels", kernel.len())));
        }
        let scale = 1.0 / (m * m) as f64;
        let hat = self.pool.install(|| {
            let mut hat: Vec<Complex64> = kernel.par_iter().map(|&k| Complex64::new(k * scale, 0.0)).collect();
            self.forward.process_from_rows_transposed(&mut hat, m, &mut vec![Complex64::default(); m * m]);
            hat
        });
        self.kernel_hats.push(hat);
        Ok(())
    }

    pub fn order(&self) -> usize {
        self.kernel_hats.len() - 1
    }

    /// Bytes of its kernels.
    pub fn bytes(&self) -> usize {
        self.kernel_hats.iter().map(|k| k.len() * std::mem::size_of::<Complex64>()).sum()
    }

    /// `D x` for an `N x N` image.
    pub fn apply(&self, x: &[f64]) -> Vec<f64> {
        let (n, m) = (self.size, 2 * self.size);
        assert_eq!(x.len(), n * n, "image size");
        let terms = self.order() + 1;
        let pairs = terms.div_ceil(2);
        let t = &self.t;
        let power = |p: usize, e: usize| t[p].powi(e as i32);
        // A poisoned lock only means an earlier application panicked: its arrays are rewritten here.
        let mut buffers = self.buffers.lock().unwrap_or_else(|e| e.into_inner());
        let Buffers { spectra, sums, scratch } = &mut *buffers;
        for arrays in [&mut *spectra, &mut *sums] {
            arrays.resize_with(pairs, || vec![Complex64::default(); m * m]);
        }
        scratch.resize(m * m, Complex64::default());
        self.pool.install(|| {
            // z_j = pad(t^{2j} x) + i pad(t^{2j+1} x), transformed.
            for (j, z) in spectra.iter_mut().enumerate() {
                let (re, im) = (2 * j, 2 * j + 1);
                z.par_chunks_mut(m).enumerate().for_each(|(iy, row)| {
                    if iy >= n {
                        row.fill(Complex64::default());
                        return;
                    }
                    row[n..].fill(Complex64::default());
                    for ix in 0..n {
                        let p = iy * n + ix;
                        let b = if im < terms { x[p] * power(p, im) } else { 0.0 };
                        row[ix] = Complex64::new(x[p] * power(p, re), b);
                    }
                });
                self.forward.process_from_rows_transposed(z, n, scratch);
            }
            let spectra = &*spectra;
            // Per frequency: the spectra Y_b of the real images t^b x (from z at the frequency
            // and at its mirror), the sums S_a = sum_b (-1)^b / (a! b!) R_{a+b} Y_b, packed two
            // to an array for the inverse transforms (each S_a is the spectrum of a real image).
            // The spectra are transposed (rows of kx); the mirror of (kx, ky) is found alike.
            let coefficient = |a: usize, b: usize| {
                let sign = if b % 2 == 0 { 1.0 } else { -1.0 };
                sign / (factorial(a) * factorial(b))
            };
            let mut rows: Vec<Vec<&mut [Complex64]>> = (0..m).map(|_| Vec::with_capacity(pairs)).collect();
            for sum in sums.iter_mut() {
                for (row, chunk) in rows.iter_mut().zip(sum.chunks_mut(m)) {
                    row.push(chunk);
                }
            }
            rows.par_iter_mut().enumerate().for_each(|(kx, out)| {
                let mirror_x = (m - kx) % m;
                let mut y = [Complex64::default(); MAX_ORDER + 1];
                for ky in 0..m {
                    let (i, j) = (kx * m + ky, mirror_x * m + (m - ky) % m);
                    for (pair, z) in spectra.iter().enumerate() {
                        let (zi, zj) = (z[i], z[j].conj());
                        y[2 * pair] = 0.5 * (zi + zj);
                        if 2 * pair + 1 < terms {
                            y[2 * pair + 1] = Complex64::new(0.0, -0.5) * (zi - zj);
                        }
                    }
                    for (pair, row) in out.iter_mut().enumerate() {
                        let mut packed = Complex64::default();
                        for (a, unit) in [(2 * pair, Complex64::new(1.0, 0.0)), (2 * pair + 1, Complex64::new(0.0, 1.0))] {
                            if a >= terms {
                                continue;
                            }
                            let s: Complex64 = (0..terms - a).map(|b| coefficient(a, b) * self.kernel_hats[a + b][i] * y[b]).sum();
                            packed += unit * s;
                        }
                        row[ky] = packed;
                    }
                }
            });
            drop(rows);
            let mut result = vec![0.0; n * n];
            for (pair, s) in sums.iter_mut().enumerate() {
                self.inverse.process_transposed_to_rows(s, n, scratch);
                let (re, im) = (2 * pair, 2 * pair + 1);
                // The linear convolution with kernels centred at (N, N): pixel p is at p + N.
                result.par_chunks_mut(n).enumerate().for_each(|(iy, row)| {
                    let src = &s[(iy + n) * m + n..][..n];
                    for (ix, o) in row.iter_mut().enumerate() {
                        let p = iy * n + ix;
                        *o += power(p, re) * src[ix].re;
                        if im < terms {
                            *o += power(p, im) * src[ix].im;
                        }
                    }
                });
            }
            result
        })
    }

    /// [`relative_deviation`] of `apply(x)` from `reference`: the form against `D x` computed
    /// otherwise (the operator's), on an image `x` of the sky it will image.
    pub fn deviation(&self, x: &[f64], reference: &[f64]) -> f64 {
        relative_deviation(&self.apply(x), reference)
    }
}

/// `|| ours - reference || / || reference ||` (0 where both are 0, infinite where only the
/// reference is).
pub fn relative_deviation(ours: &[f64], reference: &[f64]) -> f64 {
    let d: f64 = ours.iter().zip(reference).map(|(a, b)| (a - b) * (a - b)).sum();
    let r: f64 = reference.iter().map(|b| b * b).sum();
    if r > 0.0 {
        (d / r).sqrt()
    } else if d > 0.0 {
        f64::INFINITY
    } else {
        0.0
    }
}

/// How far the form's `D x` of the final model (`by_form`) is from the operator's (`exact`),
/// and a warning where that is ten times what the dirty image was allowed ([`TOLERANCE`] times
/// the NUFFT's accuracy `epsilon`): `seen_by` (the networks, the final CLEAN's cycles) then saw
/// residuals that far off.
pub fn final_deviation(by_form: &[f64], exact: &[f64], epsilon: f64, seen_by: &str) -> (f64, Option<String>) {
    let deviation = relative_deviation(by_form, exact);
    let limit = 10.0 * TOLERANCE * epsilon;
    let warning = (deviation > limit).then(|| {
        format!(
            "the residual update's Taylor series in w was {deviation:.1e} of D x from the operator on the final model (above {limit:.0e}): {seen_by} saw residuals that far off (the written residual is the operator's); the residual stage's `method: nufft` updates through the operator at every iteration"
        )
    });
    (deviation, warning)
}

fn factorial(k: usize) -> f64 {
    (1..=k).map(|i| i as f64).product()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nufft::{direct, NufftParams};
    use crate::operator::{doubled_psf_of, PsfConvolution};
    use crate::operator::toeplitz::{relative, test_field as field};

    fn kernels(geometry: ImageGeometry, u: &[f64], v: &[f64], w: &[f64], weight: &[f64], order: usize, nufft: NufftParams) -> Vec<Vec<f64>> {
        (0..=order)
            .map(|m| doubled_psf_of(geometry, u, v, weight, |k| kernel_factor(w[k], m), 1.0, nufft, 2).unwrap())
            .collect()
    }

    #[test]
    fn each_order_comes_closer_to_the_direct_sums_with_the_w_term_and_order_1_beats_the_psf_convolution() {
        // 8 degrees at 64 pixels, |w| up to a tenth of the uv radius: phases up to 0.35 rad
        // between pixels, as a VLA or MeerKAT field of the size its series are trained for.
        let (geometry, u, v, w, weight) = field(64, 8.0, 0.1, 400, 11);
        let (n, pixel) = (geometry.size, geometry.pixel_rad);
        let x: Vec<f64> = (0..n * n).map(|p| ((p as f64 * 0.37).sin() + 1.2) * if p % 7 == 0 { 3.0 } else { 1.0 }).collect();
        let xc: Vec<Complex64> = x.iter().map(|&a| Complex64::new(a, 0.0)).collect();
        let weighted: Vec<Complex64> = direct::forward_w(n, pixel, &u, &v, &w, &xc).iter().zip(&weight).map(|(v, w)| v * w).collect();
        let truth: Vec<f64> = direct::adjoint_w(n, pixel, &u, &v, &w, &weighted).into_iter().map(|c| c.re).collect();
        let nufft = NufftParams { epsilon: 1e-10, oversampling: 2.0 };
        let all = kernels(geometry, &u, &v, &w, &weight, MAX_ORDER, nufft);
        let coplanar = relative(&PsfConvolution::new(n, &all[0]).unwrap().apply(&x), &truth);
        assert!(coplanar > 1e-3, "the w-term must matter here: {coplanar:e}");
        let mut previous = coplanar;
        for order in 1..=MAX_ORDER {
            let form = WTaylor::new(geometry, &all[..=order], 2).unwrap();
            assert_eq!(form.order(), order);
            let error = relative(&form.apply(&x), &truth);
            assert!(error < previous / 5.0, "order {order}: {error:e} after {previous:e}");
            assert!((form.deviation(&x, &truth) - error).abs() <= 1e-12);
            previous = error;
        }
        // Flux over the whole field, the corners included: the worst case for the series.
        assert!(previous < 1e-5, "order {MAX_ORDER}: {previous:e}");
        // Order 0 is the PSF convolution.
        let zero = WTaylor::new(geometry, &all[..1], 2).unwrap();
        assert!(relative(&zero.apply(&x), &truth) - coplanar < 1e-9);
    }

    #[test]
    fn on_a_wide_field_no_order_is_accurate_and_the_measured_deviation_says_so() {
        // 40 degrees: phases of radians, where only w-planes do.
        let (geometry, u, v, w, weight) = field(32, 40.0, 1.0, 300, 5);
        let (n, pixel) = (geometry.size, geometry.pixel_rad);
        let x: Vec<f64> = (0..n * n).map(|p| 1.0 + (p as f64 * 0.11).cos()).collect();
        let xc: Vec<Complex64> = x.iter().map(|&a| Complex64::new(a, 0.0)).collect();
        let weighted: Vec<Complex64> = direct::forward_w(n, pixel, &u, &v, &w, &xc).iter().zip(&weight).map(|(v, w)| v * w).collect();
        let truth: Vec<f64> = direct::adjoint_w(n, pixel, &u, &v, &w, &weighted).into_iter().map(|c| c.re).collect();
        let nufft = NufftParams { epsilon: 1e-8, oversampling: 2.0 };
        let form = WTaylor::new(geometry, &kernels(geometry, &u, &v, &w, &weight, MAX_ORDER, nufft), 2).unwrap();
        assert!(form.deviation(&x, &truth) > 1e-2, "{:e}", form.deviation(&x, &truth));
    }

    #[test]
    fn a_final_model_further_from_the_operator_than_ten_times_the_dirty_images_tolerance_is_warned_about() {
        let exact = vec![1.0, -2.0, 3.0, 0.5];
        let off = |e: f64| -> Vec<f64> { exact.iter().enumerate().map(|(i, x)| x + if i == 2 { e } else { 0.0 }).collect() };
        let norm = exact.iter().map(|x| x * x).sum::<f64>().sqrt();
        let epsilon = 1e-6;
        let limit = 10.0 * TOLERANCE * epsilon;
        let (d, warning) = final_deviation(&off(0.5 * limit * norm), &exact, epsilon, "the networks");
        assert!((d - 0.5 * limit).abs() < 1e-12 && warning.is_none(), "{d:e}");
        let (d, warning) = final_deviation(&off(2.0 * limit * norm), &exact, epsilon, "the networks");
        let warning = warning.expect("above the limit");
        assert!((d - 2.0 * limit).abs() < 1e-12, "{d:e}");
        assert!(warning.contains("Taylor series in w") && warning.contains("1e-4") && warning.contains("method: nufft"), "{warning}");
    }

    #[test]
    fn kernels_of_another_size_or_too_many_are_refused() {
        let geometry = ImageGeometry::new(16, 1e-4).unwrap();
        let e = WTaylor::new(geometry, &[vec![0.0; 16 * 16]], 1).err().unwrap().to_string();
        assert!(e.contains("32 x 32"), "{e}");
        let e = WTaylor::new(geometry, &vec![vec![0.0; 32 * 32]; MAX_ORDER + 2], 1).err().unwrap().to_string();
        assert!(e.contains("kernels"), "{e}");
        assert!(WTaylor::new(geometry, &[], 1).is_err());
    }
}
