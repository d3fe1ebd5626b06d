//! Training data for R2D2 series, made by the same simulator and operator that imaging uses,
//! so a network learns exactly the measurement operator it will meet at inference.
//!
//! Each sample is a randomised observation of the set's telescope, drawn from the ranges of
//! its training preset (`data/telescopes/telescopes.yaml`; the VLA's is the paper's A+C:
//! declination 5..60 deg, A 5..10 h, C 1..3 h, 1..4 frequencies with highest/lowest 1..2),
//! rotated at random and up to 20% flagged, a super-resolution, Briggs robustness and integration time drawn per sample from
//! the set's ranges (a single value each by default: SR 1.5, Briggs 0, 300 s), noise for a
//! target dynamic range drawn log-uniformly, and a ground truth exponentiated to that dynamic
//! range (or a procedural radio sky made at it). A sample holds what sequential training needs: the truth, the
//! dirty image `x_d = kappa Re{Phi^H y_w}`, the 2N PSF (the kernel of `D`, peak at (N, N)) and
//! the back-projected noise `b = kappa Re{Phi^H n_w}` (pruning compares residuals with it).
//!
//! Every random choice comes from the sample's seed, so a sample is a pure function of its
//! inputs and can be regenerated alone.

use super::observe::{frequency_channels, sample_coverage, simulate_visibilities, NoiseModel, ObservationSpec};
use super::extended::{extended_sky, field_filling_sky};
use super::sky::{exponentiate, procedural_sky, smooth_to_resolution, SkyParams};
use super::telescope::Telescope;
use crate::imaging::{dirty_image, DirtyParams, PixelScale};
use crate::nufft::NufftParams;
use crate::operator::{doubled_psf, ImageGeometry, WTermMode};
use crate::vis::VisTable;
use crate::weighting::{Weighting, DEFAULT_GRID_FACTOR};
use crate::{Error, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::collections::BTreeMap;

/// Random stream of the truth's resolution (apart from the observation's draws, which stay
/// those of a set made without it).
const STREAM_TRUTH_RESOLUTION: u64 = 12;

/// Random stream of the observation parameters (the simulator's own streams use the seed
/// with other stream numbers, so the choices stay independent).
const STREAM_PARAMETERS: u64 = 11;

/// What is fixed across a training set. Each `(low, high)` range is drawn from per sample
/// (uniformly; the dynamic range log-uniformly); `low == high` fixes the value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrainsetParams {
    /// The telescope whose training preset the observations are drawn from.
    pub telescope: &'static Telescope,
    pub size: usize,
    pub superresolution: (f64, f64),
    /// Briggs robustness.
    pub robust: (f64, f64),
    /// Target dynamic ranges, drawn log-uniformly in `[low, high]`.
    pub dynamic_range: (f64, f64),
    /// Integration time, seconds: sets the number of points per observation.
    pub integration_s: (f64, f64),
    /// FWHM in pixels of the Gaussian each truth is convolved with (`None`: as generated),
    /// drawn per sample: the sky as an instrument of that resolution would image it, as real
    /// radio images used as truths are, so that it holds no texture finer than the data measure.
    pub truth_fwhm_px: Option<(f64, f64)>,
    pub nufft: NufftParams,
}

/// Whether `(low, high)` is a usable range of finite values within `[min, max]`.
fn range_ok((lo, hi): (f64, f64), min: f64, max: f64) -> bool {
    lo.is_finite() && hi.is_finite() && lo <= hi && lo >= min && hi <= max
}

impl TrainsetParams {
    pub fn validate(&self) -> Result<()> {
        let (lo, hi) = self.dynamic_range;
        if !(lo > 1.0 && hi >= lo && hi.is_finite()) {
            return Err(Error::parameter("dynamic_range", format!("expected 1 < low <= high, got {lo}..{hi}")));
        }
        let (t0, t1) = self.integration_s;
        if !range_ok(self.integration_s, f64::MIN_POSITIVE, 86_400.0) {
            return Err(Error::parameter("integration_s", format!("expected positive times up to a day, low <= high, got {t0}..{t1}")));
        }
        let (s0, s1) = self.superresolution;
        if !range_ok(self.superresolution, 1.0, 10.0) {
            return Err(Error::parameter("superresolution", format!("expected 1 <= low <= high <= 10, got {s0}..{s1}")));
        }
        let (r0, r1) = self.robust;
        let (low, high) = crate::weighting::ROBUST_RANGE;
        if !range_ok(self.robust, low, high) {
            return Err(Error::parameter("robust", format!("expected {low} <= low <= high <= {high}, got {r0}..{r1}")));
        }
        if let Some((f0, f1)) = self.truth_fwhm_px {
            if !(range_ok((f0, f1), f64::MIN_POSITIVE, self.size as f64 / 8.0)) {
                return Err(Error::parameter("truth_fwhm_px", format!("expected 0 < low <= high <= {} pixels (an eighth of the image), got {f0}..{f1}", self.size / 8)));
            }
        }
        ImageGeometry::new(self.size, 1e-6).map(|_| ())
    }
}

/// The randomised observation of one sample (recorded with it).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ObservationDraw {
    pub telescope: String,
    pub dec_deg: f64,
    /// Hours of each configuration, recorded as `hours_<configuration>` (`hours_a`).
    #[serde(flatten)]
    pub hours: BTreeMap<String, f64>,
    /// The configurations in the order they are observed.
    #[serde(skip)]
    pub configurations: Vec<String>,
    pub lowest_frequency_hz: f64,
    pub frequencies: usize,
    pub frequency_ratio: f64,
    pub flag_fraction: f64,
    pub dynamic_range: f64,
    pub superresolution: f64,
    pub robust: f64,
    pub integration_s: f64,
}

impl ObservationDraw {
    /// The telescope's training ranges and the set's ranges, drawn from `seed`. The imaging
    /// settings are drawn after the observation, so a set of fixed settings draws the same
    /// observations as before they could vary (and the VLA's draws are those of the paper's
    /// A+C ranges written in code before telescopes were data).
    pub fn random(seed: u64, params: &TrainsetParams) -> ObservationDraw {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(STREAM_PARAMETERS);
        let (lo, hi) = params.dynamic_range;
        let t = &params.telescope.training;
        let dec_deg = rng.gen_range(t.dec_deg[0]..=t.dec_deg[1]);
        let hours = t.configurations.iter().zip(&t.hours).map(|(c, [h0, h1])| (format!("hours_{c}"), rng.gen_range(*h0..=*h1))).collect();
        let mut draw = ObservationDraw {
            telescope: params.telescope.key.clone(),
            dec_deg,
            hours,
            configurations: t.configurations.clone(),
            lowest_frequency_hz: t.lowest_frequency_mhz * 1e6,
            frequencies: rng.gen_range(t.channels[0]..=t.channels[1]),
            frequency_ratio: rng.gen_range(t.frequency_ratio[0]..=t.frequency_ratio[1]),
            flag_fraction: rng.gen_range(0.0..0.2),
            dynamic_range: (lo.ln() + (hi.ln() - lo.ln()) * rng.gen::<f64>()).exp(),
            superresolution: params.superresolution.0,
            robust: params.robust.0,
            integration_s: params.integration_s.0,
        };
        let mut within = |(a, b): (f64, f64)| if b > a { rng.gen_range(a..=b) } else { a };
        draw.superresolution = within(params.superresolution);
        draw.robust = within(params.robust);
        draw.integration_s = within(params.integration_s);
        draw
    }

    pub fn spec(&self, seed: u64) -> Result<ObservationSpec> {
        Ok(ObservationSpec {
            telescope: self.telescope.clone(),
            configurations: self.configurations.iter().map(|c| (c.clone(), self.hours[&format!("hours_{c}")])).collect(),
            dec_deg: self.dec_deg,
            integration_s: self.integration_s,
            frequencies_hz: frequency_channels(self.lowest_frequency_hz, self.frequencies, self.frequency_ratio)?,
            flag_fraction: self.flag_fraction,
            random_rotation: true,
            seed,
        })
    }
}

/// Where a sample's ground truth comes from.
#[derive(Clone, Copy, Debug)]
pub enum TruthSource<'a> {
    /// A low-dynamic-range image (peak-normalised inside, zero background), exponentiated to
    /// the sample's dynamic range; `source_dr` is its own dynamic range (1 / its noise level).
    Image { data: &'a [f64], source_dr: f64 },
    /// A procedural radio sky made at the sample's dynamic range from this seed.
    Procedural { seed: u64 },
    /// A sky of extended emission (`simulate::extended`) made at the sample's dynamic range.
    Extended { seed: u64 },
    /// A field-filling sky (`simulate::extended::field_filling_sky`) at the sample's dynamic range.
    FieldFilling { seed: u64 },
}

/// One training sample (images row-major, `N x N` except the `2N x 2N` PSF).
#[derive(Clone, Debug)]
pub struct TrainSample {
    pub truth: Vec<f64>,
    pub dirty: Vec<f64>,
    pub psf_2n: Vec<f64>,
    /// `kappa Re{Phi^H n_w}`: the noise's share of the dirty image.
    pub noise_dirty: Vec<f64>,
    pub info: SampleInfo,
    /// The visibilities (with noise), if asked for: for imaging the sample with other methods.
    pub table: Option<VisTable>,
    /// Pixel size, radians.
    pub pixel_rad: f64,
}

/// Scalars recorded per sample.
#[derive(Clone, Debug, Serialize)]
pub struct SampleInfo {
    pub seed: u64,
    /// Noise standard deviation per visibility (complex), Jy.
    pub tau: f64,
    pub kappa: f64,
    /// Unflagged visibilities imaged.
    pub points: usize,
    pub pixel_arcsec: f64,
    /// FWHM (pixels) the truth was smoothed to, if it was.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truth_fwhm_px: Option<f64>,
    #[serde(flatten)]
    pub observation: ObservationDraw,
}

/// Simulate and image one sample. Runs on `threads` threads (1 when samples run in parallel).
/// `keep_table` keeps the visibility table in the sample.
pub fn make_sample(truth: TruthSource, params: &TrainsetParams, seed: u64, threads: usize, keep_table: bool) -> Result<TrainSample> {
    params.validate()?;
    let n = params.size;
    let draw = ObservationDraw::random(seed, params);
    let dr = draw.dynamic_range;
    let sky = match truth {
        TruthSource::Image { data, source_dr } => {
            if data.len() != n * n {
                return Err(Error::parameter("truth", format!("expected {n} x {n} = {} pixels, got {}", n * n, data.len())));
            }
            if data.iter().any(|&p| !(p >= 0.0) || !p.is_finite()) {
                return Err(Error::parameter("truth", "a ground truth must be finite and non-negative"));
            }
            let mut sky = data.to_vec();
            exponentiate(&mut sky, source_dr, dr)?;
            sky
        }
        TruthSource::Procedural { seed } => procedural_sky(&SkyParams::new(n, dr, seed))?,
        TruthSource::Extended { seed } => extended_sky(&SkyParams::new(n, dr, seed))?,
        TruthSource::FieldFilling { seed } => field_filling_sky(&SkyParams::new(n, dr, seed))?,
    };
    let truth_fwhm_px = params.truth_fwhm_px.map(|(lo, hi)| {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(STREAM_TRUTH_RESOLUTION);
        if hi > lo { rng.gen_range(lo..=hi) } else { lo }
    });
    let sky = match truth_fwhm_px {
        Some(fwhm) => smooth_to_resolution(sky, n, fwhm, dr),
        None => sky,
    };
    let coverage = sample_coverage(&draw.spec(seed)?)?;
    let geometry = PixelScale::SuperResolution(draw.superresolution).geometry(n, coverage.max_uv())?;
    let weighting = Weighting::Briggs { robust: draw.robust };
    let model = NoiseModel { dynamic_range: dr, weighting, grid_factor: DEFAULT_GRID_FACTOR };
    let sim = simulate_visibilities(&sky, geometry, &coverage, &model, WTermMode::Off, params.nufft, threads, seed)?;

    // Through the same table -> visibilities -> dirty products path as a Parquet file would go.
    let table = |vis: Vec<num_complex::Complex64>| VisTable {
        u_m: coverage.u_m.clone(),
        v_m: coverage.v_m.clone(),
        w_m: coverage.w_m.clone(),
        frequency: coverage.frequency_hz.clone(),
        vis,
        weight: vec![1.0 / (sim.noise_sigma * sim.noise_sigma); coverage.len()],
        flag: coverage.flag.clone(),
        // Kept so that the sample's table converts to a MeasurementSet (rows by time and baseline).
        time: coverage.time_s.clone(),
        antenna1: coverage.antenna1.clone(),
        antenna2: coverage.antenna2.clone(),
    };
    let vis_table = table(sim.vis.clone());
    let (vis, _) = vis_table.to_visibilities("simulated sample")?;
    // The table a sample is imaged from by other imagers (the engine's `image`, WSClean) holds
    // the baselines' w, so its visibilities are predicted with the w-term, by the imaging's
    // rule, as a real observation's are; the training images above stay coplanar.
    let kept_table = match keep_table {
        false => None,
        true => {
            let (u, v) = coverage.uv_wavelengths();
            let mut with_w = crate::operator::predict(geometry, &u, &v, &coverage.w_wavelengths(), &sky, WTermMode::Auto, params.nufft, threads)?;
            with_w.iter_mut().zip(&sim.noise).for_each(|(y, n)| *y += n);
            Some(table(with_w))
        }
    };
    let (noise, _) = table(sim.noise.clone()).to_visibilities("simulated noise")?;
    let dirty_params = DirtyParams {
        size: n,
        pixel: PixelScale::SuperResolution(draw.superresolution),
        weighting,
        grid_factor: DEFAULT_GRID_FACTOR,
        nufft: params.nufft,
        // Training is coplanar: the series learns D as the PSF convolution it is then.
        w_term: WTermMode::Off,
        threads,
        uv: Default::default(),
    };
    let products = dirty_image(&vis, &dirty_params)?;
    let kappa = products.operator.kappa();
    let noise_dirty = products.operator.dirty_image(&noise.vis);
    let psf_2n = doubled_psf(geometry, &vis.u, &vis.v, &products.weight, kappa, params.nufft, threads)?;
    Ok(TrainSample {
        truth: sky,
        dirty: products.dirty,
        psf_2n,
        noise_dirty,
        info: SampleInfo {
            seed,
            tau: sim.noise_sigma,
            kappa,
            points: vis.len(),
            pixel_arcsec: geometry.pixel_arcsec(),
            truth_fwhm_px,
            observation: draw,
        },
        table: kept_table,
        pixel_rad: geometry.pixel_rad,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::operator::PsfConvolution;

    fn params() -> TrainsetParams {
        TrainsetParams {
            telescope: crate::simulate::telescope::telescope("vla").unwrap(),
            size: 32,
            superresolution: (1.5, 1.5),
            robust: (0.0, 0.0),
            dynamic_range: (1e3, 1e5),
            integration_s: (1800.0, 1800.0),
            truth_fwhm_px: None,
            nufft: NufftParams { epsilon: 1e-8, oversampling: 2.0 },
        }
    }

    /// The truth's resolution is drawn per sample from its own stream: the observation is that
    /// of the set made without it, and the truth is the plain one smoothed to the drawn FWHM.
    #[test]
    fn a_truth_resolution_is_drawn_per_sample_and_leaves_the_observation_alone() {
        let smooth = TrainsetParams { truth_fwhm_px: Some((1.0, 3.0)), ..params() };
        let mut drawn = Vec::new();
        for seed in [3, 4] {
            let plain = make_sample(TruthSource::Procedural { seed }, &params(), seed, 1, false).unwrap();
            let s = make_sample(TruthSource::Procedural { seed }, &smooth, seed, 1, false).unwrap();
            assert_eq!(plain.info.observation, s.info.observation);
            assert!(plain.info.truth_fwhm_px.is_none());
            let fwhm = s.info.truth_fwhm_px.unwrap();
            assert!((1.0..=3.0).contains(&fwhm), "{fwhm}");
            assert_eq!(s.truth, smooth_to_resolution(plain.truth, 32, fwhm, s.info.observation.dynamic_range));
            drawn.push(fwhm);
        }
        assert_ne!(drawn[0], drawn[1]);
        assert!(TrainsetParams { truth_fwhm_px: Some((0.0, 2.0)), ..params() }.validate().is_err());
        assert!(TrainsetParams { truth_fwhm_px: Some((1.0, 5.0)), ..params() }.validate().is_err());
    }

    #[test]
    fn draws_stay_in_the_papers_ranges_and_follow_the_seed() {
        let ranged = TrainsetParams { superresolution: (1.5, 2.5), robust: (-1.0, 1.0), integration_s: (100.0, 400.0), ..params() };
        for seed in 0..200 {
            let d = ObservationDraw::random(seed, &params());
            let r = ObservationDraw::random(seed, &ranged);
            // The observation itself does not depend on the imaging ranges.
            assert_eq!((d.dec_deg, &d.hours, d.dynamic_range), (r.dec_deg, &r.hours, r.dynamic_range));
            assert_eq!((d.superresolution, d.robust, d.integration_s), (1.5, 0.0, 1800.0));
            assert!((1.5..=2.5).contains(&r.superresolution) && (-1.0..=1.0).contains(&r.robust) && (100.0..=400.0).contains(&r.integration_s));
            assert!((5.0..=60.0).contains(&d.dec_deg) && (5.0..=10.0).contains(&d.hours["hours_a"]) && (1.0..=3.0).contains(&d.hours["hours_c"]));
            assert!((1..=4).contains(&d.frequencies) && (1.0..=2.0).contains(&d.frequency_ratio));
            assert!((0.0..0.2).contains(&d.flag_fraction) && (1e3..=1e5).contains(&d.dynamic_range));
            assert_eq!(d, ObservationDraw::random(seed, &params()));
        }
        assert_ne!(ObservationDraw::random(1, &params()), ObservationDraw::random(2, &params()));
    }

    /// The VLA's draws from the registry are those the committed series' data were made with
    /// when the ranges were code: sample 0 of `training/reproduce.sh vla-r2d2-512-broad`'s
    /// classic skies (seed 100000), as its samples.json recorded it.
    #[test]
    fn vla_draws_are_those_the_shipped_series_were_trained_on() {
        let broad = TrainsetParams { superresolution: (1.5, 2.5), robust: (-1.0, 1.0), integration_s: (200.0, 450.0), ..params() };
        let d = ObservationDraw::random(100000, &broad);
        assert_eq!((d.dec_deg, d.hours["hours_a"], d.hours["hours_c"]), (31.23210928542795, 7.58892522475332, 1.6921363302763672));
        assert_eq!((d.frequencies, d.frequency_ratio, d.flag_fraction), (3, 1.6432148850239297, 0.10067725267206665));
        assert_eq!((d.dynamic_range, d.superresolution, d.robust, d.integration_s), (26913.420264327848, 1.606363561987386, 0.6056763231086113, 417.747856678782));
        let json = serde_json::to_value(&d).unwrap();
        assert_eq!((json["hours_a"].as_f64(), json["telescope"].as_str()), (Some(7.58892522475332), Some("vla")));
    }

    /// MeerKAT's draws follow its preset: one configuration, L band, southern declinations.
    #[test]
    fn meerkat_draws_follow_its_preset() {
        let meerkat = TrainsetParams { telescope: crate::simulate::telescope::telescope("MeerKAT").unwrap(), ..params() };
        for seed in 0..50 {
            let d = ObservationDraw::random(seed, &meerkat);
            assert_eq!(d.configurations, ["meerkat"]);
            assert!((8.0..=12.0).contains(&d.hours["hours_meerkat"]) && (-60.0..=0.0).contains(&d.dec_deg), "{d:?}");
            assert_eq!(d.lowest_frequency_hz, 856e6);
            let spec = d.spec(seed).unwrap();
            assert_eq!(spec.telescope, "meerkat");
            spec.validate().unwrap();
        }
    }

    /// The dirty image is the PSF convolution of the truth plus the back-projected noise:
    /// `x_d = D x + b`, with D from the 2N PSF. Ties the four arrays of a sample together.
    /// The kept table is the truth predicted with the w-term plus the sample's noise: imaged
    /// with its w (as the engine and WSClean do), it is consistent; the coplanar prediction
    /// the training images come from would not be, where the w-term matters.
    #[test]
    fn the_kept_table_is_predicted_with_its_w() {
        let meerkat = TrainsetParams {
            telescope: crate::simulate::telescope::telescope("meerkat").unwrap(),
            size: 128,
            integration_s: (1800.0, 1800.0),
            dynamic_range: (1e5, 1e5),
            ..params()
        };
        let s = make_sample(TruthSource::Procedural { seed: 3 }, &meerkat, 11, 2, true).unwrap();
        let (vis, _) = s.table.as_ref().unwrap().to_visibilities("kept").unwrap();
        let geometry = ImageGeometry::new(meerkat.size, s.pixel_rad).unwrap();
        let rms_from = |mode: WTermMode| {
            let y = crate::operator::predict(geometry, &vis.u, &vis.v, &vis.w, &s.truth, mode, meerkat.nufft, 2).unwrap();
            let sum: f64 = y.iter().zip(&vis.vis).map(|(p, t)| (num_complex::Complex64::new(t.re as f64, t.im as f64) - p).norm_sqr()).sum();
            (sum / y.len() as f64).sqrt()
        };
        let (with_w, coplanar) = (rms_from(WTermMode::On), rms_from(WTermMode::Off));
        // What is left after the w-prediction is the noise (tau per complex sample).
        assert!((with_w / s.info.tau - 1.0).abs() < 0.05, "{with_w} vs tau {}", s.info.tau);
        assert!(coplanar > 1.5 * with_w, "the w-term does not matter here: {coplanar} vs {with_w}");
    }

    #[test]
    fn dirty_is_psf_convolution_of_truth_plus_noise() {
        let s = make_sample(TruthSource::Procedural { seed: 4 }, &params(), 9, 2, false).unwrap();
        let d = PsfConvolution::new(32, &s.psf_2n).unwrap();
        let dx = d.apply(&s.truth);
        let err: f64 = s.dirty.iter().zip(&dx).zip(&s.noise_dirty).map(|((y, a), b)| (y - a - b).powi(2)).sum::<f64>().sqrt();
        let norm: f64 = s.dirty.iter().map(|y| y * y).sum::<f64>().sqrt();
        assert!(err / norm < 1e-6, "relative mismatch {}", err / norm);
        assert!((s.psf_2n[32 * 64 + 32] - 1.0).abs() < 1e-9, "2N PSF peak at (N, N) is 1");
        let peak = s.truth.iter().copied().fold(0.0, f64::max);
        assert!((peak - 1.0).abs() < 1e-12);
        assert!(s.noise_dirty.iter().any(|&b| b != 0.0));
    }

    #[test]
    fn image_truths_are_exponentiated_to_the_drawn_range() {
        let mut img = vec![0.0; 32 * 32];
        for (k, p) in img.iter_mut().enumerate().skip(300).take(200) {
            *p = 0.02 + (k % 50) as f64 / 50.0;
        }
        let s = make_sample(TruthSource::Image { data: &img, source_dr: 50.0 }, &params(), 3, 1, false).unwrap();
        let dr = s.info.observation.dynamic_range;
        let faint = s.truth.iter().copied().filter(|&x| x > 0.0).fold(f64::INFINITY, f64::min);
        // The faintest emission (0.02 of the peak, the source's 1/DR) lands near 1/DR.
        assert!(faint < 10.0 / dr && faint > 0.1 / dr, "faintest {faint} vs 1/DR {}", 1.0 / dr);
        let bad = make_sample(TruthSource::Image { data: &img[1..], source_dr: 50.0 }, &params(), 3, 1, false);
        assert!(bad.unwrap_err().to_string().contains("truth"));
    }
}
