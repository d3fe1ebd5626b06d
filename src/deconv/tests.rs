//! Tests of CLEAN, the beam fit and restoration.

use super::beam::{fit_beam, fit_circular_beam, restoring_beam, Beam, BeamFit, FWHM_PER_SIGMA};
use super::hogbom::{hogbom, HogbomParams};
use super::restore::{fast_len, restore};

#[test]
fn an_absurd_beam_fit_is_replaced_by_the_main_lobes_circle_with_a_warning() {
    let (n, pixel_rad) = (64, 1e-4);
    // A Gaussian PSF: the fit stands, no warning.
    let (beam, warning) = restoring_beam(&sky_gaussian(n, 6.0, 3.0, 30.0), n, pixel_rad, BeamFit::Elliptical).unwrap();
    assert!(warning.is_none(), "{warning:?}");
    assert!((beam.major_deg - fit_beam(&sky_gaussian(n, 6.0, 3.0, 30.0), n, pixel_rad).unwrap().major_deg).abs() < 1e-12);
    // One baseline's fringes (a snapshot of two antennas): the main lobe is a stripe across
    // the whole field, which no beam narrower than the field fits.
    let psf: Vec<f64> = (0..n * n).map(|k| (2.0 * std::f64::consts::PI * ((k % n) as f64 - (n / 2) as f64) / 16.0).cos()).collect();
    let (beam, warning) = restoring_beam(&psf, n, pixel_rad, BeamFit::Elliptical).unwrap();
    let warning = warning.expect("a warning");
    assert!(warning.contains("circular beam"), "{warning}");
    let field_deg = (n as f64 * pixel_rad).to_degrees();
    assert!(beam.major_deg == beam.minor_deg && beam.major_deg < field_deg, "{beam:?} field {field_deg}");
    // The circular fit has the same fallback.
    let (circle, warning) = restoring_beam(&psf, n, pixel_rad, BeamFit::Circular).unwrap();
    assert!(warning.is_some() && circle == beam, "{circle:?} {warning:?}");
}

#[test]
fn a_circular_beam_fit_finds_a_circles_width_and_the_best_single_width_of_an_ellipse() {
    let (n, pixel_rad) = (64, 1e-4_f64);
    let pix_deg = pixel_rad.to_degrees();
    // A circular Gaussian PSF: its own FWHM.
    let beam = fit_circular_beam(&sky_gaussian(n, 5.0, 5.0, 0.0), n, pixel_rad).unwrap();
    assert!((beam.major_deg / pix_deg - 5.0).abs() < 1e-6 && beam.minor_deg == beam.major_deg && beam.pa_deg == 0.0, "{beam:?}");
    // A 6 x 3 pixel ellipse: one width between the axes, which no nearby width fits better
    // over the main lobe (the pixels above 0.35 of the peak and the centre's neighbours).
    let psf = sky_gaussian(n, 6.0, 3.0, 30.0);
    let fwhm = fit_circular_beam(&psf, n, pixel_rad).unwrap().major_deg / pix_deg;
    assert!(fwhm > 3.0 && fwhm < 6.0 && (fwhm / 18f64.sqrt() - 1.0).abs() < 0.15, "{fwhm}");
    let cost = |fwhm_pix: f64| {
        let circle = sky_gaussian(n, fwhm_pix, fwhm_pix, 0.0);
        let (c, mut total) = (n / 2, 0.0);
        for iy in 0..n {
            for ix in 0..n {
                let k = iy * n + ix;
                let neighbour = ix.abs_diff(c) <= 1 && iy.abs_diff(c) <= 1;
                if psf[k] >= 0.35 || neighbour {
                    total += (circle[k] - psf[k]).powi(2);
                }
            }
        }
        total
    };
    assert!(cost(fwhm) < cost(fwhm * 1.01) && cost(fwhm) < cost(fwhm * 0.99), "{} {} {}", cost(fwhm * 0.99), cost(fwhm), cost(fwhm * 1.01));
}
use crate::nufft::NufftParams;
use crate::operator::{doubled_psf, ImageGeometry, MeasurementOperator};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Random baselines filling a disc of `max_uv` wavelengths: an Airy-like PSF with real
/// sidelobes. Returns the geometry, the N x N PSF and the 2N x 2N PSF.
fn real_psf(n: usize, superresolution: f64, seed: u64) -> (ImageGeometry, Vec<f64>, Vec<f64>) {
    let max_uv = 1000.0;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (mut u, mut v) = (Vec::new(), Vec::new());
    while u.len() < 5000 {
        let (a, b): (f64, f64) = (rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0));
        if a * a + b * b <= 1.0 {
            u.push(a * max_uv);
            v.push(b * max_uv);
        }
    }
    let w = vec![1.0; u.len()];
    let g = ImageGeometry::from_superresolution(n, superresolution, max_uv).unwrap();
    let nufft = NufftParams { epsilon: 1e-10, oversampling: 2.0 };
    let op = MeasurementOperator::new(g, &u, &v, &w, nufft, 2).unwrap();
    let psf2 = doubled_psf(g, &u, &v, &w, op.kappa(), nufft, 2).unwrap();
    (g, op.psf(), psf2)
}

/// `sum_k S_k PSF(. - p_k)`: the dirty image of point sources at pixel centres.
fn dirty_of(sources: &[(usize, usize, f64)], psf2: &[f64], n: usize) -> Vec<f64> {
    let m = 2 * n;
    let mut dirty = vec![0.0; n * n];
    for &(px, py, s) in sources {
        for iy in 0..n {
            for ix in 0..n {
                dirty[iy * n + ix] += s * psf2[(iy + n - py) * m + ix + n - px];
            }
        }
    }
    dirty
}

fn max_abs(x: &[f64]) -> f64 {
    x.iter().fold(0.0f64, |m, v| m.max(v.abs()))
}

#[test]
fn single_point_source_is_cleaned_to_one_pixel() {
    let n = 64;
    let (_, _, psf2) = real_psf(n, 1.5, 1);
    let (px, py, s) = (20, 41, 2.5);
    let dirty = dirty_of(&[(px, py, s)], &psf2, n);
    let params = HogbomParams { threshold: 1e-4 * s, ..Default::default() };
    let out = hogbom(&dirty, &psf2, n, &params);
    let elsewhere: f64 = out.components.iter().enumerate().filter(|(i, _)| *i != py * n + px).map(|(_, c)| c.abs()).sum();
    assert_eq!(elsewhere, 0.0, "components away from the source");
    let flux = out.components[py * n + px];
    assert!((flux - s).abs() < 1e-3 * s, "flux {flux} vs {s}");
    assert!(max_abs(&out.residual) < 1e-3 * s, "residual peak {}", max_abs(&out.residual));
    assert!(out.last_peak.abs() < params.threshold);
    assert!(out.n_components > 1 && out.n_components < params.max_components);
}

#[test]
fn two_separated_sources_get_their_fluxes() {
    let n = 64;
    let (_, _, psf2) = real_psf(n, 1.5, 2);
    let sources = [(15, 18, 3.0), (44, 47, 1.2)];
    let dirty = dirty_of(&sources, &psf2, n);
    let out = hogbom(&dirty, &psf2, n, &HogbomParams { threshold: 1e-4, ..Default::default() });
    for &(px, py, s) in &sources {
        let flux = out.components[py * n + px];
        assert!((flux - s).abs() < 1e-3 * s, "source at ({px}, {py}): {flux} vs {s}");
    }
    let total: f64 = out.components.iter().map(|c| c.abs()).sum();
    assert!((total - 4.2).abs() < 2e-3, "total |flux| {total}");
    assert!(max_abs(&out.residual) < 1e-3);
}

/// A mask (WSClean's `-fits-mask`): no component outside it, whatever is brighter there (of
/// either sign, in either search), and the sources inside get their fluxes with the outside
/// one's sidelobes subtracted nowhere but left in the residual.
#[test]
fn a_mask_keeps_every_component_inside_it() {
    let n = 64;
    let (_, _, psf2) = real_psf(n, 1.5, 5);
    // The brightest source, a negative one, and a faint one outside a box around the two inside.
    let sources = [(12, 14, 5.0), (50, 40, -3.0), (30, 52, 0.3), (40, 20, 1.0), (44, 24, 0.5)];
    let dirty = dirty_of(&sources, &psf2, n);
    let inside = |k: usize| (34..50).contains(&(k % n)) && (14..30).contains(&(k / n));
    let mask: Vec<bool> = (0..n * n).map(inside).collect();
    for positive_only in [false, true] {
        let params = HogbomParams { threshold: 1e-3, positive_only, mask: Some(mask.clone()), max_components: 5000, ..Default::default() };
        let out = hogbom(&dirty, &psf2, n, &params);
        let outside: Vec<usize> = (0..n * n).filter(|&k| out.components[k] != 0.0 && !inside(k)).collect();
        assert!(outside.is_empty(), "positive_only {positive_only}: components outside the mask at {outside:?}");
        assert!(out.n_components > 0);
        // The two inside are cleaned; their fluxes are off by the outside sources' sidelobes.
        for &(px, py, s) in &sources[3..] {
            let flux = out.components[py * n + px];
            assert!((flux - s).abs() < 0.1 * s, "source at ({px}, {py}): {flux} vs {s}");
        }
        // The outside sources stay in the residual.
        assert!((out.residual[14 * n + 12] - dirty[14 * n + 12]).abs() < 0.5, "{}", out.residual[14 * n + 12]);
    }
    // An empty mask takes nothing; a mask of every pixel is no mask.
    let none = hogbom(&dirty, &psf2, n, &HogbomParams { mask: Some(vec![false; n * n]), ..Default::default() });
    assert_eq!((none.n_components, &none.residual), (0, &dirty));
    let all = HogbomParams { threshold: 1e-3, mask: Some(vec![true; n * n]), ..Default::default() };
    assert_eq!(hogbom(&dirty, &psf2, n, &all), hogbom(&dirty, &psf2, n, &HogbomParams { mask: None, ..all.clone() }));
}

/// With a mask only its pixels are searched and updated: the components are those of a
/// naive Högbom that subtracts the PSF over the whole image and searches inside the mask, and
/// the residual is the same inside the mask and the dirty image's outside it.
#[test]
fn a_masked_clean_takes_the_components_of_a_whole_image_subtraction() {
    let n = 64;
    let m = 2 * n;
    let (_, _, psf2) = real_psf(n, 1.5, 7);
    let sources = [(12, 14, 5.0), (50, 40, -3.0), (30, 52, 0.3), (40, 20, 1.0), (44, 24, 0.5), (20, 44, 0.8)];
    let dirty = dirty_of(&sources, &psf2, n);
    // Two boxes and a ring's worth of scattered pixels: several runs per row.
    let inside = |k: usize| {
        let (x, y) = (k % n, k / n);
        ((34..50).contains(&x) && (14..30).contains(&y)) || ((16..25).contains(&x) && (40..48).contains(&y)) || (x * 7 + y * 3) % 11 == 0
    };
    let mask: Vec<bool> = (0..n * n).map(inside).collect();
    let params = HogbomParams { threshold: 1e-2, mask: Some(mask.clone()), max_components: 3000, ..Default::default() };
    let out = hogbom(&dirty, &psf2, n, &params);
    let (mut r, mut components, mut taken) = (dirty.clone(), vec![0.0; n * n], 0);
    while taken < params.max_components {
        let (k, peak) = (0..n * n).filter(|&k| mask[k]).map(|k| (k, r[k])).fold((0, 0.0f64), |b, (k, v)| if v.abs() > b.1.abs() { (k, v) } else { b });
        if peak.abs() < params.threshold {
            break;
        }
        let amount = params.gain * peak;
        components[k] += amount;
        taken += 1;
        let (px, py) = (k % n, k / n);
        r.iter_mut().enumerate().for_each(|(j, v)| *v -= amount * psf2[(j / n + n - py) * m + (j % n + n - px)]);
    }
    assert!(taken > 100, "{taken} components");
    assert_eq!(out.n_components, taken);
    let worst = (0..n * n).map(|k| (out.components[k] - components[k]).abs()).fold(0.0f64, f64::max);
    assert!(worst < 1e-12, "components differ by {worst}");
    for k in 0..n * n {
        let want = if mask[k] { r[k] } else { dirty[k] };
        assert!((out.residual[k] - want).abs() < 1e-12, "residual at {k}: {} against {want}", out.residual[k]);
    }
}

#[test]
fn threshold_stops_cleaning_at_the_right_component() {
    let n = 32;
    let (_, _, psf2) = real_psf(n, 1.5, 3);
    let dirty = dirty_of(&[(10, 12, 1.0)], &psf2, n);
    let params = HogbomParams { threshold: 0.3, ..Default::default() };
    let out = hogbom(&dirty, &psf2, n, &params);
    // The peak decays as 0.9^k: 0.9^11 = 0.314 >= 0.3 > 0.9^12 = 0.282.
    assert_eq!(out.n_components, 12);
    assert!((out.last_peak - 0.9f64.powi(12)).abs() < 1e-9, "last peak {}", out.last_peak);
    assert!(max_abs(&out.residual) < 0.3);
}

#[test]
fn budget_stops_cleaning_and_reports_the_remaining_peak() {
    let n = 32;
    let (_, _, psf2) = real_psf(n, 1.5, 4);
    let dirty = dirty_of(&[(10, 12, 1.0)], &psf2, n);
    let out = hogbom(&dirty, &psf2, n, &HogbomParams { max_components: 5, ..Default::default() });
    assert_eq!(out.n_components, 5);
    assert!((out.last_peak - 0.9f64.powi(5)).abs() < 1e-9);
    assert!((out.components[12 * n + 10] - (1.0 - 0.9f64.powi(5))).abs() < 1e-9);
    let none = hogbom(&dirty, &psf2, n, &HogbomParams { max_components: 0, ..Default::default() });
    assert_eq!(none.n_components, 0);
    assert_eq!(none.residual, dirty);
    assert!((none.last_peak - 1.0).abs() < 1e-9);
}

#[test]
fn positive_only_ignores_negative_peaks() {
    let n = 48;
    let (_, _, psf2) = real_psf(n, 1.5, 5);
    let (pos, neg) = ((12, 30, 1.0), (34, 14, -3.0));
    let dirty = dirty_of(&[pos, neg], &psf2, n);
    let out = hogbom(&dirty, &psf2, n, &HogbomParams { threshold: 0.05, positive_only: true, ..Default::default() });
    assert!(out.components.iter().all(|&c| c >= 0.0));
    assert_eq!(out.components[neg.1 * n + neg.0], 0.0);
    // The positive source sits on the negative one's sidelobes, which stay uncleaned: its
    // component is its dirty value, within the sidelobes' reach of the true flux.
    let flux = out.components[pos.1 * n + pos.0];
    let taken: f64 = out.components.iter().sum();
    println!("positive_only: component {flux} at the positive source, {taken} in all, dirty value {}", dirty[pos.1 * n + pos.0]);
    assert!((flux - 1.0).abs() < 0.2, "{flux}");
    assert!(out.n_components < 10_000, "stopped by the threshold");
    // The negative source's positive sidelobes are cleaned too (spread over many pixels),
    // but no single one of them reaches the positive source.
    let largest_elsewhere = out
        .components
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != pos.1 * n + pos.0)
        .fold(0.0f64, |m, (_, &c)| m.max(c));
    assert!(largest_elsewhere < 0.5 * flux, "{largest_elsewhere} elsewhere vs {flux} ({taken} in all)");
    assert!(out.last_peak < 0.05 && out.residual.iter().all(|&r| r < 0.05));
    // The negative source is still in the residual.
    assert!(out.residual[neg.1 * n + neg.0] < -2.5, "{}", out.residual[neg.1 * n + neg.0]);
    // Without the restriction the brighter negative source is taken first.
    let both = hogbom(&dirty, &psf2, n, &HogbomParams { max_components: 1, ..Default::default() });
    assert!((both.components[neg.1 * n + neg.0] - 0.1 * dirty[neg.1 * n + neg.0]).abs() < 1e-12);
}

/// A PSF that does not describe the residual (here sidelobes of 1.5: on sparse real data
/// the w-term makes each position's response differ from the central PSF) lets the
/// image-plane residual grow without bound; the minor cycle stops at the first peak well above
/// the one it started from, and the major cycle measures the true residual.
#[test]
fn a_minor_cycle_stops_where_its_peak_rises_above_its_start() {
    let n = 32;
    let m = 2 * n;
    let mut psf2 = vec![0.0; m * m];
    psf2[n * m + n] = 1.0;
    psf2[n * m + n + 3] = 1.5;
    psf2[n * m + n - 3] = 1.5;
    let mut dirty = vec![0.0; n * n];
    dirty[16 * n + 16] = 1.0;
    let out = hogbom(&dirty, &psf2, n, &HogbomParams::default());
    assert!(out.n_components < 10_000, "{} components", out.n_components);
    assert!(out.last_peak.abs() > crate::deconv::hogbom::RISE_LIMIT, "stopped at the rise: {}", out.last_peak);
    assert!(max_abs(&out.residual) < 2.0 * crate::deconv::hogbom::RISE_LIMIT, "the residual stays bounded: {}", max_abs(&out.residual));
}

#[test]
fn nan_pixels_are_never_peaks() {
    let n = 32;
    let (_, _, psf2) = real_psf(n, 1.5, 9);
    let mut dirty = dirty_of(&[(10, 12, 1.0)], &psf2, n);
    dirty[3 * n + 4] = f64::NAN;
    let out = hogbom(&dirty, &psf2, n, &HogbomParams { threshold: 0.01, ..Default::default() });
    assert!((out.components[12 * n + 10] - 1.0).abs() < 0.011, "{}", out.components[12 * n + 10]);
    assert_eq!(out.components.iter().filter(|c| **c != 0.0).count(), 1);
    let all_nan = hogbom(&vec![f64::NAN; n * n], &psf2, n, &HogbomParams::default());
    assert_eq!(all_nan.n_components, 0);
    assert!(all_nan.last_peak.is_nan());
}

#[test]
fn params_are_validated() {
    assert!(HogbomParams::default().validate().is_ok());
    let err = HogbomParams { gain: 1.5, ..Default::default() }.validate().unwrap_err().to_string();
    assert!(err.contains("gain"), "{err}");
    let err = HogbomParams { threshold: -1.0, ..Default::default() }.validate().unwrap_err().to_string();
    assert!(err.contains("threshold"), "{err}");
}

#[test]
fn clean_speed_at_512() {
    let n = 512;
    let (_, _, psf2) = real_psf(n, 1.5, 6);
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let sources: Vec<(usize, usize, f64)> =
        (0..20).map(|_| (rng.gen_range(0..n), rng.gen_range(0..n), rng.gen_range(0.1..1.0))).collect();
    let dirty = dirty_of(&sources, &psf2, n);
    let params = HogbomParams { max_components: 2000, ..Default::default() };
    let start = std::time::Instant::now();
    let out = hogbom(&dirty, &psf2, n, &params);
    let seconds = start.elapsed().as_secs_f64();
    assert_eq!(out.n_components, 2000);
    println!(
        "Hogbom CLEAN at {n}^2: {} components in {seconds:.3} s = {:.0} components/s ({} rayon threads)",
        out.n_components,
        out.n_components as f64 / seconds,
        rayon::current_num_threads()
    );
    assert!(max_abs(&out.residual) < max_abs(&dirty));
}

/// An elliptical Gaussian written in sky terms, independently of `quadratic_from_beam`:
/// offsets east `e = -(ix - N/2)` and north `n = iy - N/2`; the major axis points
/// `(sin PA, cos PA)` in (east, north).
fn sky_gaussian(n: usize, major_pix: f64, minor_pix: f64, pa_deg: f64) -> Vec<f64> {
    let (s, c) = pa_deg.to_radians().sin_cos();
    let (sa, sb) = (major_pix / FWHM_PER_SIGMA, minor_pix / FWHM_PER_SIGMA);
    let mut img = vec![0.0; n * n];
    for iy in 0..n {
        for ix in 0..n {
            let east = -(ix as f64 - (n / 2) as f64);
            let north = iy as f64 - (n / 2) as f64;
            let along = east * s + north * c;
            let across = east * c - north * s;
            img[iy * n + ix] = (-0.5 * (along * along / (sa * sa) + across * across / (sb * sb))).exp();
        }
    }
    img
}

#[test]
fn fit_recovers_analytic_gaussians() {
    let n = 64;
    let pixel_rad: f64 = 1e-5;
    let pix_deg = pixel_rad.to_degrees();
    for &(major, minor, pa) in
        &[(6.0, 3.0, 0.0), (6.0, 3.0, 30.0), (7.0, 4.0, -60.0), (5.0, 2.5, 90.0), (3.0, 2.0, 45.0), (2.4, 1.6, -20.0)]
    {
        let beam = fit_beam(&sky_gaussian(n, major, minor, pa), n, pixel_rad).unwrap();
        assert!((beam.major_deg / pix_deg - major).abs() < 1e-3 * major, "{beam:?} vs {major} px");
        assert!((beam.minor_deg / pix_deg - minor).abs() < 1e-3 * minor, "{beam:?} vs {minor} px");
        assert!((beam.pa_deg - pa).abs() < 0.1, "PA {} vs {pa}", beam.pa_deg);
    }
    // -90 is the same orientation as 90, reported in (-90, 90].
    let beam = fit_beam(&sky_gaussian(n, 6.0, 3.0, -90.0), n, pixel_rad).unwrap();
    assert!((beam.pa_deg - 90.0).abs() < 0.1, "{beam:?}");
    // A circular beam: equal axes, PA irrelevant but finite.
    let beam = fit_beam(&sky_gaussian(n, 4.0, 4.0, 0.0), n, pixel_rad).unwrap();
    assert!((beam.major_deg - beam.minor_deg).abs() < 1e-6 * beam.major_deg && beam.pa_deg.is_finite());
}

#[test]
fn sidelobes_do_not_change_the_main_lobe_fit() {
    let n = 96;
    let pixel_rad: f64 = 1e-5;
    let (major, minor, pa) = (6.0, 4.0, 30.0);
    let mut psf = sky_gaussian(n, major, minor, pa);
    // A negative ring at 3 major FWHM plus a positive one further out.
    for iy in 0..n {
        for ix in 0..n {
            let r = ((ix as f64 - 48.0).powi(2) + (iy as f64 - 48.0).powi(2)).sqrt();
            psf[iy * n + ix] += -0.15 * (-0.5 * ((r - 18.0) / 2.0).powi(2)).exp() + 0.08 * (-0.5 * ((r - 28.0) / 2.0).powi(2)).exp();
        }
    }
    let beam = fit_beam(&psf, n, pixel_rad).unwrap();
    let pix_deg = pixel_rad.to_degrees();
    assert!((beam.major_deg / pix_deg - major).abs() < 0.01 * major, "{beam:?}");
    assert!((beam.minor_deg / pix_deg - minor).abs() < 0.01 * minor, "{beam:?}");
    assert!((beam.pa_deg - pa).abs() < 0.5, "{beam:?}");
}

/// Half-maximum width of a profile through the centre, by linear interpolation.
fn half_width(profile: impl Fn(isize) -> f64) -> f64 {
    let crossing = |dir: isize| {
        let mut k = 0;
        while profile(dir * (k + 1)) > 0.5 {
            k += 1;
        }
        let (a, b) = (profile(dir * k), profile(dir * (k + 1)));
        k as f64 + (a - 0.5) / (a - b)
    };
    crossing(1) + crossing(-1)
}

#[test]
fn real_psf_fit_matches_its_half_power_width() {
    let n = 128;
    let (g, psf, _) = real_psf(n, 4.0, 8);
    let beam = fit_beam(&psf, n, g.pixel_rad).unwrap();
    let c = (n / 2) as isize;
    let at = |ix: isize, iy: isize| psf[(iy * n as isize + ix) as usize];
    let wx = half_width(|k| at(c + k, c));
    let wy = half_width(|k| at(c, c + k));
    let pix_deg = g.pixel_rad.to_degrees();
    let (major, minor) = (beam.major_deg / pix_deg, beam.minor_deg / pix_deg);
    // A disc of uv coverage: nearly circular, FWHM 0.705 / max_uv (Airy amplitude pattern).
    let airy = 0.705 / 1000.0 / g.pixel_rad;
    println!("real PSF: fit {major:.3} x {minor:.3} px at {:.1} deg; measured {wx:.3} x {wy:.3} px; Airy {airy:.3} px", beam.pa_deg);
    for w in [wx, wy] {
        assert!(minor <= w * 1.03 && w <= major * 1.03, "fit {major} x {minor} px, measured width {w}");
    }
    assert!(major / minor < 1.1);
    assert!((0.5 * (major + minor) - airy).abs() < 0.05 * airy);
}

#[test]
fn degenerate_psfs_are_clear_errors() {
    let n = 32;
    let zeros = vec![0.0; n * n];
    let err = fit_beam(&zeros, n, 1e-5).unwrap_err().to_string();
    assert!(err.contains("psf") && err.contains("centre"), "{err}");
    let off = sky_gaussian(n, 4.0, 3.0, 0.0);
    let mut shifted = vec![0.0; n * n];
    for iy in 0..n - 3 {
        for ix in 0..n - 5 {
            shifted[(iy + 3) * n + ix + 5] = off[iy * n + ix];
        }
    }
    let err = fit_beam(&shifted, n, 1e-5).unwrap_err().to_string();
    assert!(err.contains("peaks at pixel (21, 19)"), "{err}");
    let err = fit_beam(&off[..10], n, 1e-5).unwrap_err().to_string();
    assert!(err.contains("32 x 32"), "{err}");
    let mut nan = off.clone();
    nan[3] = f64::NAN;
    assert!(fit_beam(&nan, n, 1e-5).unwrap_err().to_string().contains("NaN"));
    assert!(fit_beam(&off, n, 0.0).is_err());
}

/// `sum y^2 f / sum f` along a line: the Gaussian's variance in pixels^2 there.
fn variance(profile: impl Fn(isize) -> f64, reach: isize) -> f64 {
    let (mut s0, mut s2) = (0.0, 0.0);
    for k in -reach..=reach {
        s0 += profile(k);
        s2 += (k * k) as f64 * profile(k);
    }
    s2 / s0
}

#[test]
fn restored_point_source_has_its_flux_as_peak_and_the_beam_shape() {
    let n = 64;
    let pixel_rad: f64 = 1e-5;
    let pix_deg = pixel_rad.to_degrees();
    let (px, py) = (30isize, 36isize);
    let mut model = vec![0.0; n * n];
    model[py as usize * n + px as usize] = 2.0;
    let (major, minor) = (8.0, 4.0);
    for pa in [0.0, 90.0] {
        let beam = Beam { major_deg: major * pix_deg, minor_deg: minor * pix_deg, pa_deg: pa };
        let img = restore(&model, n, &beam, pixel_rad);
        let at = |ix: isize, iy: isize| img[(iy * n as isize + ix) as usize];
        let (ipk, vpk) = img.iter().enumerate().fold((0, f64::MIN), |b, (i, &v)| if v > b.1 { (i, v) } else { b });
        assert_eq!((ipk % n, ipk / n), (px as usize, py as usize));
        assert!((vpk - 2.0).abs() < 1e-9, "peak {vpk}");
        // Widths from the second moment along x and along y (FWHM = 2.3548 sigma).
        let fx = variance(|k| at(px + k, py), 25).sqrt() * FWHM_PER_SIGMA;
        let fy = variance(|k| at(px, py + k), 25).sqrt() * FWHM_PER_SIGMA;
        let (along_y, along_x) = if pa == 0.0 { (major, minor) } else { (minor, major) };
        assert!((fy - along_y).abs() < 1e-3 * along_y, "PA {pa}: FWHM along y {fy} vs {along_y}");
        assert!((fx - along_x).abs() < 1e-3 * along_x, "PA {pa}: FWHM along x {fx} vs {along_x}");
    }
    // PA 45: the major axis runs north-east, i.e. towards -x and +y.
    let beam = Beam { major_deg: major * pix_deg, minor_deg: minor * pix_deg, pa_deg: 45.0 };
    let img = restore(&model, n, &beam, pixel_rad);
    let at = |ix: isize, iy: isize| img[(iy * n as isize + ix) as usize];
    let ne = at(px - 4, py + 4);
    let nw = at(px + 4, py + 4);
    let expected_ne = 2.0 * (-0.5 * 32.0 / (major / FWHM_PER_SIGMA).powi(2)).exp();
    assert!((ne - expected_ne).abs() < 1e-9 && ne > 10.0 * nw, "NE {ne} (expected {expected_ne}), NW {nw}");
    // Total flux = S x beam area (2 pi sigma_major sigma_minor) in Jy/beam x pixels.
    let total: f64 = img.iter().sum();
    let area = 2.0 * std::f64::consts::PI * major * minor / (FWHM_PER_SIGMA * FWHM_PER_SIGMA);
    assert!((total - 2.0 * area).abs() < 1e-6 * total);
}

#[test]
fn restore_does_not_wrap_around_the_edges() {
    let n = 32;
    let pixel_rad: f64 = 1e-5;
    let pix_deg = pixel_rad.to_degrees();
    let mut model = vec![0.0; n * n];
    model[0] = 1.0; // corner (0, 0)
    let beam = Beam { major_deg: 6.0 * pix_deg, minor_deg: 6.0 * pix_deg, pa_deg: 0.0 };
    let img = restore(&model, n, &beam, pixel_rad);
    // The far corner is ~44 pixels away: exp(-0.5 (44 / 2.55)^2) ~ 1e-65.
    assert!(img[n * n - 1].abs() < 1e-12 && img[n - 1].abs() < 1e-12, "{} {}", img[n * n - 1], img[n - 1]);
    assert!((img[0] - 1.0).abs() < 1e-12);
}

#[test]
fn fitted_beam_round_trips_through_restore() {
    // Restoring a unit point source at the centre gives back a PSF whose fit is the beam.
    let n = 64;
    let pixel_rad: f64 = 2e-5;
    let pix_deg = pixel_rad.to_degrees();
    let beam = Beam { major_deg: 7.0 * pix_deg, minor_deg: 3.5 * pix_deg, pa_deg: -35.0 };
    let mut model = vec![0.0; n * n];
    model[(n / 2) * n + n / 2] = 1.0;
    let fit = fit_beam(&restore(&model, n, &beam, pixel_rad), n, pixel_rad).unwrap();
    assert!((fit.major_deg - beam.major_deg).abs() < 1e-6 * beam.major_deg);
    assert!((fit.minor_deg - beam.minor_deg).abs() < 1e-6 * beam.minor_deg);
    assert!((fit.pa_deg - beam.pa_deg).abs() < 1e-4);
}

#[test]
fn fast_len_is_smooth_and_minimal() {
    assert_eq!(fast_len(64), 64);
    assert_eq!(fast_len(77), 80);
    assert_eq!(fast_len(97), 100);
    assert_eq!(fast_len(1), 1);
}
