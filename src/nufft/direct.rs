//! The reference the NUFFT is tested against: direct O(N^2 M) sums over every pixel and point,
//! with the same sign and centring conventions as [`super::Nufft2d`]. Slow by design; for
//! tests, the gridder benchmark and the kernel scan (`r2d2 bench kernel-scan`).

use num_complex::Complex64;

/// Pixels to points: `out_k = sum_pixels f(ix, iy) e^{i (x_k jx + y_k jy)}`, `j` from the centre.
pub fn forward(nx: usize, ny: usize, x: &[f64], y: &[f64], f: &[Complex64]) -> Vec<Complex64> {
    x.iter()
        .zip(y)
        .map(|(&xk, &yk)| {
            let mut s = Complex64::default();
            for iy in 0..ny {
                for ix in 0..nx {
                    let ph = xk * (ix as f64 - (nx / 2) as f64) + yk * (iy as f64 - (ny / 2) as f64);
                    s += f[iy * nx + ix] * Complex64::from_polar(1.0, ph);
                }
            }
            s
        })
        .collect()
}

/// Points to pixels, the adjoint of [`forward`].
pub fn adjoint(nx: usize, ny: usize, x: &[f64], y: &[f64], c: &[Complex64]) -> Vec<Complex64> {
    let mut out = vec![Complex64::default(); nx * ny];
    for iy in 0..ny {
        for ix in 0..nx {
            let (jx, jy) = (ix as f64 - (nx / 2) as f64, iy as f64 - (ny / 2) as f64);
            out[iy * nx + ix] =
                x.iter().zip(y).zip(c).map(|((&xk, &yk), &ck)| ck * Complex64::from_polar(1.0, -(xk * jx + yk * jy))).sum();
        }
    }
    out
}

/// `|a - b| / |b|` in the 2-norm.
pub fn relative_error(a: &[Complex64], b: &[Complex64]) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(a, b)| (a - b).norm_sqr()).sum();
    let den: f64 = b.iter().map(|b| b.norm_sqr()).sum();
    (num / den).sqrt()
}

/// `n - 1` and the phase `2 pi (u l + v m + w (n - 1))` conventions of [`super::wgrid`]: pixel
/// `(ix, iy)` of a `size x size` image at `l = -pixel (ix - size/2)`, `m = pixel (iy - size/2)`.
#[cfg(test)]
fn lmt(size: usize, pixel: f64, ix: usize, iy: usize) -> (f64, f64, f64) {
    let l = -pixel * (ix as f64 - (size / 2) as f64);
    let m = pixel * (iy as f64 - (size / 2) as f64);
    (l, m, super::wgrid::n_minus_one(l * l + m * m))
}

/// Image to visibilities with the w-term: `V_k = sum f exp(+2 pi i (u_k l + v_k m + w_k (n - 1)))`
/// (`u, v, w` in wavelengths; see [`super::wgrid`]).
#[cfg(test)]
pub fn forward_w(size: usize, pixel: f64, u: &[f64], v: &[f64], w: &[f64], f: &[Complex64]) -> Vec<Complex64> {
    (0..u.len())
        .map(|k| {
            let mut s = Complex64::default();
            for iy in 0..size {
                for ix in 0..size {
                    let (l, m, t) = lmt(size, pixel, ix, iy);
                    let ph = 2.0 * std::f64::consts::PI * (u[k] * l + v[k] * m + w[k] * t);
                    s += f[iy * size + ix] * Complex64::from_polar(1.0, ph);
                }
            }
            s
        })
        .collect()
}

/// Visibilities to image with the w-term, the adjoint of [`forward_w`].
#[cfg(test)]
pub fn adjoint_w(size: usize, pixel: f64, u: &[f64], v: &[f64], w: &[f64], c: &[Complex64]) -> Vec<Complex64> {
    let mut out = vec![Complex64::default(); size * size];
    for iy in 0..size {
        for ix in 0..size {
            let (l, m, t) = lmt(size, pixel, ix, iy);
            out[iy * size + ix] = (0..u.len())
                .map(|k| c[k] * Complex64::from_polar(1.0, -2.0 * std::f64::consts::PI * (u[k] * l + v[k] * m + w[k] * t)))
                .sum();
        }
    }
    out
}
