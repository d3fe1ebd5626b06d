//! The reference the NUFFT is tested against: direct O(N^2 M) sums over every pixel and point,
//! with the same sign and centring conventions as [`super::Nufft2d`]. Slow by design; for
//! tests and the kernel scan (`cargo run --release --example kernel_scan`).

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
