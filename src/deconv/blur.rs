//! The Gaussian blur that smooths a sky to a resolution and the final CLEAN's residual: one
//! separable pass per axis, zero outside the image, every output normalised by the whole
//! kernel's sum (so flux near the edges leaves the image, as it would through a beam).

/// `image` (N x N, row-major) convolved with a unit-sum Gaussian of standard deviation `sigma`
/// pixels, the kernel cut `reach_sigmas` sigma out (at most N - 1 pixels).
pub fn gaussian_blur(image: &[f64], n: usize, sigma: f64, reach_sigmas: f64) -> Vec<f64> {
    let reach = ((reach_sigmas * sigma).ceil() as usize).min(n.saturating_sub(1));
    let kernel: Vec<f64> = (0..=reach).map(|k| (-0.5 * (k as f64 / sigma).powi(2)).exp()).collect();
    let norm = kernel[0] + 2.0 * kernel[1..].iter().sum::<f64>();
    let blur_line = |line: &[f64], out: &mut [f64]| {
        for (i, o) in out.iter_mut().enumerate() {
            let lo = i.saturating_sub(reach);
            let hi = (i + reach).min(n - 1);
            *o = (lo..=hi).map(|j| line[j] * kernel[i.abs_diff(j)]).sum::<f64>() / norm;
        }
    };
    let mut rows = vec![0.0; n * n];
    for iy in 0..n {
        blur_line(&image[iy * n..(iy + 1) * n], &mut rows[iy * n..(iy + 1) * n]);
    }
    let mut out = vec![0.0; n * n];
    let (mut column, mut blurred) = (vec![0.0; n], vec![0.0; n]);
    for ix in 0..n {
        for iy in 0..n {
            column[iy] = rows[iy * n + ix];
        }
        blur_line(&column, &mut blurred);
        for iy in 0..n {
            out[iy * n + ix] = blurred[iy];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against the analytic case: a point far from the edges becomes the sampled Gaussian
    /// (unit sum, the given width); one at the edge loses the half that falls outside.
    #[test]
    fn a_point_becomes_the_sampled_gaussian_and_the_edge_loses_flux() {
        let (n, sigma) = (41, 2.5);
        let mut point = vec![0.0; n * n];
        point[20 * n + 20] = 1.0;
        let out = gaussian_blur(&point, n, sigma, 4.0);
        let norm: f64 = (-10..=10).map(|k: i32| (-0.5 * (k as f64 / sigma).powi(2)).exp()).sum();
        for (iy, ix) in [(20, 20), (20, 23), (17, 22), (25, 25)] {
            let (dy, dx) = (iy as f64 - 20.0, ix as f64 - 20.0);
            let expected = (-0.5 * (dx * dx + dy * dy) / (sigma * sigma)).exp() / (norm * norm);
            assert!((out[iy * n + ix] - expected).abs() < 1e-15, "({iy}, {ix}): {} against {expected}", out[iy * n + ix]);
        }
        assert!((out.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert_eq!(out[20 * n + 31], 0.0, "cut 4 sigma (10 px) out");
        let mut edge = vec![0.0; n * n];
        edge[20 * n] = 1.0;
        let kept: f64 = gaussian_blur(&edge, n, sigma, 4.0).iter().sum();
        assert!((kept - (1.0 + norm) / (2.0 * norm)).abs() < 1e-12, "half the kernel and the centre row: {kept}");
    }
}
