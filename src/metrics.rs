//! Image-quality metrics of the R2D2 papers: SNR, logSNR and the residual ratio.

/// `SNR(x_hat, x) = 20 log10(||x|| / ||x - x_hat||)` in dB (infinite for a perfect estimate).
pub fn snr(estimate: &[f64], truth: &[f64]) -> f64 {
    assert_eq!(estimate.len(), truth.len(), "images differ in size");
    let signal: f64 = truth.iter().map(|t| t * t).sum::<f64>().sqrt();
    let error: f64 = truth.iter().zip(estimate).map(|(t, e)| (t - e) * (t - e)).sum::<f64>().sqrt();
    20.0 * (signal / error).log10()
}

/// `rlog(x) = x_max log_a(a x / x_max + 1)`, negative pixels clipped to 0, `x_max` the peak of
/// the image being mapped: a logarithmic stretch that weighs faint emission like bright.
pub(crate) fn rlog(image: &[f64], a: f64) -> Vec<f64> {
    let peak = image.iter().copied().fold(0.0f64, f64::max);
    if peak <= 0.0 {
        return vec![0.0; image.len()];
    }
    let ln_a = a.ln();
    image.iter().map(|&x| peak * (a * x.max(0.0) / peak + 1.0).ln() / ln_a).collect()
}

/// `logSNR = SNR(rlog(x_hat), rlog(x))` with `a` the dynamic range of the ground truth.
pub fn log_snr(estimate: &[f64], truth: &[f64], dynamic_range: f64) -> f64 {
    snr(&rlog(estimate, dynamic_range), &rlog(truth, dynamic_range))
}

/// `||r|| / ||x_d||`: the residual dirty image relative to the dirty image.
pub fn residual_ratio(residual: &[f64], dirty: &[f64]) -> f64 {
    let norm = |v: &[f64]| v.iter().map(|a| a * a).sum::<f64>().sqrt();
    norm(residual) / norm(dirty)
}

/// The pixel-wise mean of equally sized images.
pub(crate) fn pixel_mean(images: &[Vec<f64>]) -> Vec<f64> {
    let n = images.first().map_or(0, Vec::len);
    let mut mean = vec![0.0; n];
    for image in images {
        assert_eq!(image.len(), n, "images differ in size");
        mean.iter_mut().zip(image).for_each(|(m, x)| *m += x);
    }
    mean.iter_mut().for_each(|m| *m /= images.len().max(1) as f64);
    mean
}

/// The spread of independently trained realisations' images, as the R2D2 reference reports
/// its epistemic uncertainty: per pixel the standard deviation over the realisations (of the
/// population, dividing by their count) over their mean, where the mean exceeds `threshold`,
/// and 0 elsewhere (the reference writes NaN there; images here stay finite). Also the mean
/// relative uncertainty: the map's average over every pixel, the masked ones counting 0.
pub(crate) fn std_over_mean(images: &[Vec<f64>], threshold: f64) -> (Vec<f64>, f64) {
    let mean = pixel_mean(images);
    let count = images.len().max(1) as f64;
    let map: Vec<f64> = mean
        .iter()
        .enumerate()
        .map(|(k, &m)| {
            if m > threshold {
                let variance = images.iter().map(|im| (im[k] - m).powi(2)).sum::<f64>() / count;
                variance.sqrt() / m
            } else {
                0.0
            }
        })
        .collect();
    let average = map.iter().sum::<f64>() / map.len().max(1) as f64;
    (map, average)
}

/// Dynamic range of a ground truth: peak over the faintest positive pixel.
pub fn dynamic_range(truth: &[f64]) -> Option<f64> {
    let peak = truth.iter().copied().fold(0.0f64, f64::max);
    let faint = truth.iter().copied().filter(|&x| x > 0.0).fold(f64::INFINITY, f64::min);
    (peak > 0.0 && faint.is_finite()).then(|| peak / faint)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn std_over_mean_of_realisations_by_hand() {
        // Pixel 0: values 1, 2, 3 -> mean 2, population std sqrt(2/3); pixel 1: all 4 -> 0;
        // pixel 2: mean 0.1, below the threshold -> 0.
        let images = vec![vec![1.0, 4.0, 0.0], vec![2.0, 4.0, 0.1], vec![3.0, 4.0, 0.2]];
        let (map, average) = std_over_mean(&images, 0.5);
        assert!((map[0] - (2.0f64 / 3.0).sqrt() / 2.0).abs() < 1e-15, "{map:?}");
        assert_eq!((map[1], map[2]), (0.0, 0.0));
        assert!((average - map[0] / 3.0).abs() < 1e-15);
        assert_eq!(pixel_mean(&images)[..2], [2.0, 4.0]);
    }

    #[test]
    fn snr_of_a_known_error() {
        let truth = vec![3.0, 4.0];
        let est = vec![3.0, 4.5]; // ||x|| = 5, ||err|| = 0.5 -> 20 dB
        assert!((snr(&est, &truth) - 20.0).abs() < 1e-12);
        assert!(snr(&truth, &truth).is_infinite());
    }

    #[test]
    fn rlog_maps_peak_to_peak_and_zero_to_zero() {
        let img = vec![0.0, 1e-4, 0.5, 2.0, -1.0];
        let r = rlog(&img, 1e4);
        assert!((r[3] - 2.0 * (1e4f64 + 1.0).ln() / 1e4f64.ln()).abs() < 1e-12);
        assert_eq!(r[0], 0.0);
        assert_eq!(r[4], 0.0);
        // rlog is monotone and lifts faint emission: 5e-5 of the peak maps to ~4.4% of it.
        assert!((r[1] / r[3] - 1.5f64.ln() / 1e4f64.ln() / (1e4f64 + 1.0).ln() * 1e4f64.ln()).abs() < 1e-9 && r[1] < r[2]);
    }

    #[test]
    fn log_snr_matches_snr_of_stretched_images() {
        let truth = vec![1.0, 0.01, 0.0001, 0.0];
        let est = vec![0.9, 0.012, 0.0, 0.001];
        let expected = snr(&rlog(&est, 1e4), &rlog(&truth, 1e4));
        assert_eq!(log_snr(&est, &truth, 1e4), expected);
    }
}

/// The noise of an image as a robust standard deviation: 1.4826 times the median absolute
/// deviation from the median (the Gaussian-equivalent sigma, insensitive to the few bright
/// pixels of residual sources). 0 for an empty image. Takes f32 (products) or f64 (the
/// loop's images) pixels without a converted copy.
pub fn robust_sigma<T: Copy + Into<f64>>(image: &[T]) -> f64 {
    let mut values: Vec<f64> = image.iter().map(|&v| v.into()).filter(|v: &f64| v.is_finite()).collect();
    if values.is_empty() {
        return 0.0;
    }
    let median = |v: &mut Vec<f64>| {
        let mid = v.len() / 2;
        *v.select_nth_unstable_by(mid, f64::total_cmp).1
    };
    let centre = median(&mut values);
    let mut deviations: Vec<f64> = values.iter().map(|v| (v - centre).abs()).collect();
    1.4826 * median(&mut deviations)
}

#[cfg(test)]
mod robust_sigma_tests {
    use super::robust_sigma;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    #[test]
    fn robust_sigma_is_the_gaussian_sigma_despite_bright_outliers() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let normal = Normal::new(0.5, 0.02).unwrap();
        let mut image: Vec<f32> = (0..40_000).map(|_| normal.sample(&mut rng) as f32).collect();
        for v in image.iter_mut().step_by(100) {
            *v = 50.0;
        }
        let sigma = robust_sigma(&image);
        assert!((sigma - 0.02).abs() < 0.001, "{sigma}");
        assert_eq!(robust_sigma::<f32>(&[]), 0.0);
        let wide: Vec<f64> = image.iter().map(|&v| f64::from(v)).collect();
        assert_eq!(robust_sigma(&wide), sigma, "f64 pixels give the same figure");
    }
}
