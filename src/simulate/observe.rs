//! A simulated observation: a telescope's uv coverage over one or more configurations and
//! frequencies, random rotation and flagging, then visibilities `Phi x + n` with the noise
//! level the reference implementation derives from a target dynamic range.
//!
//! Noise (conventions file, "Noise and simulation"): with `L1 = ||Re{Phi_1^H Phi_1}||_S` for
//! the operator weighted once by the imaging weights and `L2` for twice,
//! `eta = sqrt(L2 / L1)` and `tau = sqrt(2 L1) / (DR eta)`; natural weighting has `eta = 1`.
//! Complex noise `(randn + i randn) tau / sqrt(2)`; natural weights `1 / tau^2`.

use super::telescope::{self, TrackSpec};
use crate::nufft::NufftParams;
use crate::operator::{doubled_psf, spectral_norm, ImageGeometry, PsfConvolution, WTermMode};
use crate::weighting::{imaging_weights, Weighting};
use crate::{Error, Result};
use num_complex::Complex64;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// Speed of light in m/s.
pub const SPEED_OF_LIGHT: f64 = 299_792_458.0;

/// Independent random streams of one seed, so changing one choice never shifts another.
const STREAM_ROTATION: u64 = 1;
const STREAM_FLAGS: u64 = 2;
const STREAM_NOISE: u64 = 3;

/// What the telescope observes.
#[derive(Clone, Debug, PartialEq)]
pub struct ObservationSpec {
    /// The telescope (a key or name of `data/telescopes/telescopes.yaml`: `vla`, `meerkat`).
    pub telescope: String,
    /// Its configurations and the observing time in each, hours (e.g. `[("a", 6.0), ("c", 2.0)]`).
    pub configurations: Vec<(String, f64)>,
    pub dec_deg: f64,
    pub integration_s: f64,
    /// Observing frequencies in Hz.
    pub frequencies_hz: Vec<f64>,
    /// Fraction of samples flagged at random, in [0, 1).
    pub flag_fraction: f64,
    /// Rotate the whole uv coverage by a random angle (as the paper does to vary coverage).
    pub random_rotation: bool,
    pub seed: u64,
}

impl ObservationSpec {
    /// Checks everything a simulation of this observation would refuse, before any sample is
    /// made: the configurations, each track (times, declination), the frequencies, the flag
    /// fraction, and the memory the samples need. Its errors name the field of
    /// [`ObservationRequest`] (or of this spec, `frequencies_hz`) the value came from: the
    /// telescope's `declination` is `dec_deg`, a configuration's observation time `hours`.
    pub fn validate(&self) -> Result<()> {
        if self.configurations.is_empty() {
            return Err(Error::parameter("configurations", "expected at least one telescope configuration"));
        }
        let scope = telescope::telescope(&self.telescope)?;
        let as_fields = |e| as_field(e, &[("telescope configuration", "configurations"), ("declination", "dec_deg"), ("observation time", "hours"), ("integration time", "integration_s")]);
        for (config, hours) in &self.configurations {
            let (array, hours) = (scope.array(config).map_err(as_fields)?, *hours);
            // The track first: a zero integration time would otherwise be reported as a
            // sample count that does not fit in memory.
            TrackSpec { dec_rad: self.dec_deg.to_radians(), hour_angle_span_h: hours, integration_s: self.integration_s }.validate().map_err(as_fields)?;
            array.check_rises(self.dec_deg.to_radians()).map_err(as_fields)?;
        }
        if self.frequencies_hz.is_empty() {
            return Err(Error::parameter("frequencies_hz", "expected at least one frequency"));
        }
        for &f in &self.frequencies_hz {
            check_frequency(f, "frequencies_hz")?;
        }
        if !(0.0..1.0).contains(&self.flag_fraction) {
            return Err(Error::parameter("flag_fraction", format!("expected a fraction in [0, 1), got {}", self.flag_fraction)));
        }
        check_sample_count(self)
    }
}

/// An observation as options ask for it: what they leave open is the telescope's typical
/// observation's (`data/telescopes/telescopes.yaml`). `r2d2 simulate` and `kind: simulate`
/// both make their observation through it.
#[derive(Clone, Debug, Default)]
pub struct ObservationRequest {
    pub telescope: String,
    pub configurations: Option<Vec<String>>,
    pub hours: Option<Vec<f64>>,
    pub dec_deg: Option<f64>,
    pub integration_s: Option<f64>,
    pub channels: Option<usize>,
    pub frequency_mhz: Option<f64>,
    pub frequency_ratio: Option<f64>,
    pub flag_fraction: f64,
    pub random_rotation: bool,
    pub seed: u64,
}

impl ObservationRequest {
    /// The observation, checked (`ObservationSpec::validate`).
    pub fn spec(&self) -> Result<ObservationSpec> {
        let preset = &telescope::telescope(&self.telescope)?.observation;
        let configurations = self.configurations.clone().unwrap_or_else(|| preset.configurations.clone());
        let hours = self.hours.clone().unwrap_or_else(|| preset.hours.clone());
        if configurations.len() != hours.len() {
            return Err(Error::parameter(
                "hours",
                format!("give one observing time per configuration: {} configurations, {} times", configurations.len(), hours.len()),
            ));
        }
        let spec = ObservationSpec {
            telescope: self.telescope.clone(),
            configurations: configurations.into_iter().zip(hours).collect(),
            dec_deg: self.dec_deg.unwrap_or(preset.dec_deg),
            integration_s: self.integration_s.unwrap_or(preset.integration_s),
            frequencies_hz: frequency_channels(
                self.frequency_mhz.unwrap_or(preset.frequency_mhz) * 1e6,
                self.channels.unwrap_or(preset.channels),
                self.frequency_ratio.unwrap_or(preset.frequency_ratio),
            )?,
            flag_fraction: self.flag_fraction,
            random_rotation: self.random_rotation,
            seed: self.seed,
        };
        spec.validate()?;
        Ok(spec)
    }
}

/// Refuses a frequency the readers would exclude as physically impossible
/// ([`crate::vis::FREQUENCY_RANGE_HZ`]): the data written would be unreadable.
fn check_frequency(hz: f64, what: &str) -> Result<()> {
    let (low, high) = crate::vis::FREQUENCY_RANGE_HZ;
    if !(low..=high).contains(&hz) {
        return Err(Error::parameter(
            what,
            format!("expected frequencies from {low:e} to {high:e} Hz (a ground-based interferometer's, which the readers accept), got {hz:e} Hz"),
        ));
    }
    Ok(())
}

/// A parameter error of a lower layer named as this one's field (`renames`: its name, the
/// field's); any other error as it is.
fn as_field(e: Error, renames: &[(&str, &str)]) -> Error {
    match e {
        Error::Parameter { name, message } => match renames.iter().find(|(from, _)| *from == name) {
            Some((_, field)) => Error::parameter(*field, message),
            None => Error::Parameter { name, message },
        },
        other => other,
    }
}

/// `count` frequencies spaced evenly from `lowest` to `lowest * ratio`. Its errors name the
/// fields of [`ObservationRequest`] that give them: `frequency_mhz`, `channels` and
/// `frequency_ratio`.
pub fn frequency_channels(lowest_hz: f64, count: usize, ratio: f64) -> Result<Vec<f64>> {
    check_frequency(lowest_hz, "frequency_mhz")?;
    if count == 0 {
        return Err(Error::parameter("channels", "expected at least one frequency"));
    }
    if !(ratio >= 1.0) || !ratio.is_finite() {
        return Err(Error::parameter("frequency_ratio", format!("expected highest/lowest frequency >= 1, got {ratio}")));
    }
    check_frequency(lowest_hz * ratio, "frequency_ratio")?;
    if count == 1 {
        return Ok(vec![lowest_hz]);
    }
    if ratio == 1.0 {
        // Every channel would be the same frequency: the same samples several times over,
        // which no MeasurementSet holds (one sample per channel).
        return Err(Error::parameter("frequency_ratio", format!("{count} frequencies at a ratio of 1 would all be {lowest_hz} Hz: give the band's highest/lowest frequency above 1 (a ratio of 1.2, say), or one frequency")));
    }
    Ok((0..count).map(|k| lowest_hz * (1.0 + (ratio - 1.0) * k as f64 / (count - 1) as f64)).collect())
}

/// The sampled (u, v, w) of every visibility, one row per baseline, time and frequency.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Coverage {
    pub u_m: Vec<f64>,
    pub v_m: Vec<f64>,
    pub w_m: Vec<f64>,
    pub frequency_hz: Vec<f64>,
    pub time_s: Vec<f64>,
    pub antenna1: Vec<i32>,
    pub antenna2: Vec<i32>,
    pub flag: Vec<bool>,
    /// Each configuration's track, in the order observed.
    pub tracks: Vec<CoverageTrack>,
    /// The angle the whole (u, v) coverage was rotated by, radians (0: not rotated).
    pub rotation_rad: f64,
}

/// One configuration's share of a [`Coverage`].
#[derive(Clone, Debug, PartialEq)]
pub struct CoverageTrack {
    /// The configuration (a layout of the telescope), lower case.
    pub configuration: String,
    /// Its samples, every channel's: `coverage.u_m[samples]`.
    pub samples: std::ops::Range<usize>,
    /// Its samples' `time_s` less this are seconds from its track's start.
    pub time_offset_s: f64,
    /// The track's length, seconds (its integrations, whole): transit is at its middle.
    pub duration_s: f64,
    /// East longitude of its array's centre, radians: what its hour angles are reckoned from.
    pub longitude_rad: f64,
}

impl Coverage {
    /// The samples' times as a real observation's: MJD seconds, UTC (a MeasurementSet's TIME).
    /// Configuration `k` is observed on day `k` after [`super::epoch::REFERENCE_MJD`], its
    /// track centred on the transit of right ascension `ra_deg` nearest that day's noon, so
    /// that each sample's local sidereal time is the right ascension plus the hour angle its
    /// (u, v, w) were computed for. `time_s` itself stays seconds from the first track's start
    /// (training's tracks need no date).
    pub fn utc_times(&self, ra_deg: f64) -> Vec<f64> {
        let mut times = self.time_s.clone();
        for (day, track) in self.tracks.iter().enumerate() {
            let transit = super::epoch::transit_on_day(ra_deg.to_radians(), track.longitude_rad, day);
            let start = transit * super::epoch::SECONDS_PER_DAY - 0.5 * track.duration_s;
            for t in &mut times[track.samples.clone()] {
                *t = start + (*t - track.time_offset_s);
            }
        }
        times
    }

    pub fn len(&self) -> usize {
        self.u_m.len()
    }
    /// (u, v) in wavelengths.
    pub fn uv_wavelengths(&self) -> (Vec<f64>, Vec<f64>) {
        (self.wavelengths(&self.u_m), self.wavelengths(&self.v_m))
    }

    /// w of every sample in wavelengths.
    pub fn w_wavelengths(&self) -> Vec<f64> {
        self.wavelengths(&self.w_m)
    }

    fn wavelengths(&self, metres: &[f64]) -> Vec<f64> {
        metres.iter().zip(&self.frequency_hz).map(|(x, f)| x * f / SPEED_OF_LIGHT).collect()
    }
    /// Longest unflagged baseline in wavelengths.
    pub fn max_uv(&self) -> f64 {
        let (u, v) = self.uv_wavelengths();
        u.iter()
            .zip(&v)
            .zip(&self.flag)
            .filter(|(_, f)| !**f)
            .map(|((u, v), _)| (u * u + v * v).sqrt())
            .fold(0.0, f64::max)
    }
}

/// Bytes a simulation holds per visibility sample: the coverage and table columns (u, v, w,
/// frequency, time, antennas, flag: 49), the visibility and weight (24), the operators' copies
/// in wavelengths (16) and their sorting and scratch, rounded up.
const SIMULATION_BYTES_PER_SAMPLE: f64 = 200.0;

/// Refuses an observation whose samples cannot fit in memory, counted before any is made (in
/// f64: hours of 1e300 must not wrap a count).
fn check_sample_count(spec: &ObservationSpec) -> Result<()> {
    let mut samples = 0.0;
    let scope = telescope::telescope(&spec.telescope)?;
    for (config, hours) in &spec.configurations {
        let integrations = (hours * 3600.0 / spec.integration_s).round().max(1.0);
        samples += integrations * scope.array(config)?.n_baselines() as f64 * spec.frequencies_hz.len() as f64;
    }
    let what = format!(
        "an observation of {samples:.3e} samples ({} configuration(s), {} s integrations, {} channel(s))",
        spec.configurations.len(),
        spec.integration_s,
        spec.frequencies_hz.len()
    );
    crate::limits::check_memory(samples * SIMULATION_BYTES_PER_SAMPLE, &what).map_err(|m| Error::parameter("hours", m))
}

/// Earth-rotation coverage of every configuration and frequency, rotated and flagged as asked.
pub fn sample_coverage(spec: &ObservationSpec) -> Result<Coverage> {
    spec.validate()?;
    let mut cov = Coverage::default();
    let mut time_offset = 0.0;
    // Antenna numbers of later configurations continue after the earlier ones'.
    let mut first_antenna = 0;
    let scope = telescope::telescope(&spec.telescope)?;
    for (config, hours) in &spec.configurations {
        let (array, hours) = (scope.array(config)?, *hours);
        let track_spec = TrackSpec { dec_rad: spec.dec_deg.to_radians(), hour_angle_span_h: hours, integration_s: spec.integration_s };
        let track = telescope::uvw_tracks(&array, &track_spec)?;
        let base = first_antenna as i32;
        cov.tracks.push(CoverageTrack {
            configuration: config.trim().to_ascii_lowercase(),
            samples: cov.len()..cov.len() + track.len() * spec.frequencies_hz.len(),
            time_offset_s: time_offset,
            duration_s: track_spec.n_times() as f64 * spec.integration_s,
            longitude_rad: array.longitude_rad(),
        });
        for &f in &spec.frequencies_hz {
            cov.u_m.extend_from_slice(&track.u_m);
            cov.v_m.extend_from_slice(&track.v_m);
            cov.w_m.extend_from_slice(&track.w_m);
            cov.frequency_hz.extend(std::iter::repeat(f).take(track.len()));
            // One track after another, times distinct (training's relative times; simulate
            // dates each on its own day: `utc_times`).
            cov.time_s.extend(track.time_s.iter().map(|t| t + time_offset));
            cov.antenna1.extend(track.antenna1.iter().map(|a| a + base));
            cov.antenna2.extend(track.antenna2.iter().map(|a| a + base));
        }
        time_offset += hours * 3600.0;
        first_antenna += array.n_antennas();
    }
    if spec.random_rotation {
        let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
        rng.set_stream(STREAM_ROTATION);
        let angle: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
        cov.rotation_rad = angle;
        let (s, c) = angle.sin_cos();
        for (u, v) in cov.u_m.iter_mut().zip(cov.v_m.iter_mut()) {
            let (uu, vv) = (*u, *v);
            *u = c * uu - s * vv;
            *v = s * uu + c * vv;
        }
    }
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    rng.set_stream(STREAM_FLAGS);
    cov.flag = (0..cov.len()).map(|_| rng.gen_bool(spec.flag_fraction)).collect();
    Ok(cov)
}

/// How the simulated data will be imaged: fixes the noise level through `eta`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseModel {
    pub dynamic_range: f64,
    pub weighting: Weighting,
    pub grid_factor: f64,
}

/// Visibilities and the noise they carry.
#[derive(Clone, Debug)]
pub struct Simulated {
    /// `Phi_raw x + n`, in the coverage's order.
    pub vis: Vec<Complex64>,
    /// The noise `n` alone (training data needs its back-projection for pruning).
    pub noise: Vec<Complex64>,
    /// Standard deviation of the complex noise (tau).
    pub noise_sigma: f64,
    /// Briggs correction factor (1 for natural weighting).
    pub eta: f64,
}

/// `||Re{Phi^H diag(weight) Phi}||_S` over the unflagged visibilities (no kappa), by Lanczos
/// on its Toeplitz form: the convolution with the unscaled 2N PSF, gridded once. Each
/// iteration then costs two FFTs instead of two NUFFTs over every visibility (MeerKAT's
/// millions of samples made the noise level most of a training sample's time); the two
/// agree to the NUFFT's accuracy (test `the_noise_norm_by_the_psf_is_the_operators`).
fn normal_operator_norm(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    nufft: NufftParams,
    threads: usize,
) -> Result<f64> {
    // The operator's checks (baselines within the image's Nyquist limit, weights) first.
    crate::operator::check_points(geometry, u, v, weight)?;
    let psf_2n = doubled_psf(geometry, u, v, weight, 1.0, nufft, threads)?;
    let normal = PsfConvolution::new(geometry.size, &psf_2n)?;
    // On the simulation's own threads, as the NUFFT was (not rayon's global pool).
    Ok(crate::parallel::shared_pool(threads)?.install(|| spectral_norm(|x| normal.apply(x), geometry.pixels(), 1e-7, 300)))
}

/// Noise level for a target dynamic range, per the reference formula.
pub fn noise_level(
    geometry: ImageGeometry,
    coverage: &Coverage,
    model: &NoiseModel,
    nufft: NufftParams,
    threads: usize,
) -> Result<(f64, f64, f64)> {
    if !(model.dynamic_range > 1.0) || !model.dynamic_range.is_finite() {
        return Err(Error::parameter("dynamic_range", format!("expected a dynamic range > 1, got {}", model.dynamic_range)));
    }
    let (u, v) = coverage.uv_wavelengths();
    let keep: Vec<usize> = (0..coverage.len()).filter(|&k| !coverage.flag[k]).collect();
    let u: Vec<f64> = keep.iter().map(|&k| u[k]).collect();
    let v: Vec<f64> = keep.iter().map(|&k| v[k]).collect();
    let (x, y): (Vec<f64>, Vec<f64>) = u.iter().zip(&v).map(|(&u, &v)| geometry.uv_to_phase(u, v)).unzip();
    let ones = vec![1.0; u.len()];
    let iw = imaging_weights(&x, &y, &ones, geometry.size, model.weighting, model.grid_factor)?;
    let l1 = normal_operator_norm(geometry, &u, &v, &iw, nufft, threads)?;
    let eta = if model.weighting == Weighting::Natural {
        1.0
    } else {
        let iw2: Vec<f64> = iw.iter().map(|w| w * w).collect();
        (normal_operator_norm(geometry, &u, &v, &iw2, nufft, threads)? / l1).sqrt()
    };
    Ok(((2.0 * l1).sqrt() / (model.dynamic_range * eta), eta, l1))
}

/// Visibilities of `sky` (Jy/pixel on `geometry`) over `coverage`, plus Gaussian noise for the
/// target dynamic range. Flagged samples are simulated too (they stay in the data, flagged)
/// but do not count towards the noise level. `w_term` says whether the prediction includes
/// the w-term (the imaging's rule, so that what is simulated images as it was made).
#[allow(clippy::too_many_arguments)]
pub fn simulate_visibilities(
    sky: &[f64],
    geometry: ImageGeometry,
    coverage: &Coverage,
    model: &NoiseModel,
    w_term: WTermMode,
    nufft: NufftParams,
    threads: usize,
    seed: u64,
) -> Result<Simulated> {
    if sky.len() != geometry.pixels() {
        return Err(Error::parameter("sky", format!("expected {} pixels, got {}", geometry.pixels(), sky.len())));
    }
    let (tau, eta, _) = noise_level(geometry, coverage, model, nufft, threads)?;
    let (u, v) = coverage.uv_wavelengths();
    let vis = crate::operator::predict(geometry, &u, &v, &coverage.w_wavelengths(), sky, w_term, nufft, threads)?;
    let mut vis = vis;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(STREAM_NOISE);
    let s = tau / std::f64::consts::SQRT_2;
    let noise: Vec<Complex64> = (0..vis.len())
        .map(|_| {
            let (a, b): (f64, f64) = (rng.sample(StandardNormal), rng.sample(StandardNormal));
            Complex64::new(a * s, b * s)
        })
        .collect();
    vis.iter_mut().zip(&noise).for_each(|(y, n)| *y += n);
    Ok(Simulated { vis, noise, noise_sigma: tau, eta })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::sky::{procedural_sky, SkyParams};

    /// The noise's operator norm by the PSF's Toeplitz form is the Lanczos norm of the NUFFT
    /// normal operator itself, to the NUFFT's accuracy, for natural and Briggs weights.
    #[test]
    fn the_noise_norm_by_the_psf_is_the_operators() {
        let cov = sample_coverage(&small_spec(5)).unwrap();
        let (u, v) = cov.uv_wavelengths();
        let geometry = ImageGeometry::new(64, 0.45 / cov.max_uv() / 1.5).unwrap();
        let nufft = NufftParams { epsilon: 1e-10, oversampling: 2.0 };
        let (x, y): (Vec<f64>, Vec<f64>) = u.iter().zip(&v).map(|(&u, &v)| geometry.uv_to_phase(u, v)).unzip();
        for weighting in [Weighting::Natural, Weighting::Briggs { robust: 0.0 }] {
            let w = imaging_weights(&x, &y, &vec![1.0; u.len()], 64, weighting, crate::weighting::DEFAULT_GRID_FACTOR).unwrap();
            let op = crate::operator::MeasurementOperator::new(geometry, &u, &v, &w, nufft, 1).unwrap();
            let direct = spectral_norm(|x| op.apply_normal(x), geometry.pixels(), 1e-10, 300) / op.kappa();
            let by_psf = normal_operator_norm(geometry, &u, &v, &w, nufft, 1).unwrap();
            assert!((by_psf / direct - 1.0).abs() < 1e-7, "{weighting}: {by_psf} vs {direct}");
        }
    }

    fn small_spec(seed: u64) -> ObservationSpec {
        ObservationSpec {
            telescope: "vla".into(),
            configurations: vec![("c".into(), 1.0), ("d".into(), 0.5)],
            dec_deg: 40.0,
            integration_s: 120.0,
            frequencies_hz: frequency_channels(1.0e9, 2, 1.5).unwrap(),
            flag_fraction: 0.1,
            random_rotation: true,
            seed,
        }
    }

    #[test]
    fn coverage_and_visibilities_are_reproducible_from_the_seed() {
        let nufft = NufftParams::default();
        let run = |seed| {
            let cov = sample_coverage(&small_spec(seed)).unwrap();
            let g = ImageGeometry::from_superresolution(64, 1.5, cov.max_uv()).unwrap();
            let sky = procedural_sky(&SkyParams::new(64, 1e3, seed)).unwrap();
            let model = NoiseModel { dynamic_range: 1e3, weighting: Weighting::Briggs { robust: 0.0 }, grid_factor: 2.0 };
            let sim = simulate_visibilities(&sky, g, &cov, &model, WTermMode::Off, nufft, 2, seed).unwrap();
            (cov, sim.vis)
        };
        let (c1, v1) = run(5);
        let (c2, v2) = run(5);
        let (c3, v3) = run(6);
        assert_eq!(c1, c2);
        assert_eq!(v1, v2);
        assert_ne!(c1.u_m, c3.u_m);
        assert_ne!(v1, v3);
        // 2 configurations x 27 antennas, 351 baselines, 2 frequencies.
        assert_eq!(c1.len(), (30 + 15) * 351 * 2);
        let flagged = c1.flag.iter().filter(|f| **f).count() as f64 / c1.len() as f64;
        assert!((flagged - 0.1).abs() < 0.01, "flagged fraction {flagged}");
    }

    /// Each configuration's track is recorded with its samples, its antennas numbered after the
    /// earlier ones'; dated, configuration k lies on day k after the reference date, centred on
    /// the transit of the right ascension at its array's longitude, its integrations as far
    /// apart as in `time_s`.
    #[test]
    fn tracks_are_recorded_and_dated_a_day_apart() {
        let cov = sample_coverage(&small_spec(4)).unwrap();
        assert_eq!(cov.tracks.iter().map(|t| t.configuration.as_str()).collect::<Vec<_>>(), ["c", "d"]);
        assert_eq!((cov.tracks[0].samples.clone(), cov.tracks[1].samples.clone()), (0..30 * 351 * 2, 30 * 351 * 2..45 * 351 * 2));
        assert_eq!((cov.tracks[0].duration_s, cov.tracks[1].duration_s), (3600.0, 1800.0));
        let ids = |k: usize| cov.antenna1[cov.tracks[k].samples.clone()].iter().chain(&cov.antenna2[cov.tracks[k].samples.clone()]).fold((i32::MAX, 0), |(lo, hi), &a| (lo.min(a), hi.max(a)));
        assert_eq!((ids(0), ids(1)), ((0, 26), (27, 53)));
        assert!(cov.rotation_rad != 0.0);
        let ra = 123.0f64;
        let times = cov.utc_times(ra);
        for (day, track) in cov.tracks.iter().enumerate() {
            let t = &times[track.samples.clone()];
            let (first, last) = t.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(x), b.max(x)));
            let middle = (first + last) / 2.0 / crate::simulate::epoch::SECONDS_PER_DAY;
            let transit = crate::simulate::epoch::transit_on_day(ra.to_radians(), track.longitude_rad, day);
            assert!((middle - transit).abs() * 86_400.0 < 1e-3, "day {day}: middle {middle}, transit {transit}");
            assert_eq!(last - first, track.duration_s - 120.0);
            assert!((middle - crate::simulate::epoch::REFERENCE_MJD - day as f64 - 0.5).abs() < 0.5);
        }
    }

    /// Dense `Re{Phi^H diag(w) Phi}` from a direct DFT, for an independent check of the norms.
    fn dense_normal_norm(g: ImageGeometry, u: &[f64], v: &[f64], w: &[f64]) -> f64 {
        let n = g.size;
        let coord = |i: usize| (-g.pixel_rad * ((i % n) as f64 - (n / 2) as f64), g.pixel_rad * ((i / n) as f64 - (n / 2) as f64));
        let p = n * n;
        let mut dense = vec![0.0; p * p];
        for a in 0..p {
            for b in 0..p {
                let ((la, ma), (lb, mb)) = (coord(a), coord(b));
                dense[a * p + b] = (0..u.len())
                    .map(|k| w[k] * (2.0 * std::f64::consts::PI * (u[k] * (la - lb) + v[k] * (ma - mb))).cos())
                    .sum();
            }
        }
        // Plain power iteration, run long: an algorithm independent of the Lanczos under test.
        let apply = |x: &[f64]| -> Vec<f64> { (0..p).map(|a| dense[a * p..(a + 1) * p].iter().zip(x).map(|(d, x)| d * x).sum()).collect() };
        let mut x = vec![1.0; p];
        let mut norm = 0.0;
        for _ in 0..20000 {
            let y = apply(&x);
            norm = y.iter().map(|v| v * v).sum::<f64>().sqrt();
            x = y.into_iter().map(|v| v / norm).collect();
        }
        norm
    }

    #[test]
    fn noise_level_follows_the_reference_formula_and_the_data_carry_it() {
        let spec = ObservationSpec { configurations: vec![("d".into(), 0.5)], integration_s: 300.0, ..small_spec(3) };
        let cov = sample_coverage(&spec).unwrap();
        let g = ImageGeometry::from_superresolution(8, 1.5, cov.max_uv()).unwrap();
        let dr = 500.0;
        let model = NoiseModel { dynamic_range: dr, weighting: Weighting::Briggs { robust: 0.0 }, grid_factor: 2.0 };
        let nufft = NufftParams { epsilon: 1e-10, oversampling: 2.0 };
        let (tau, eta, _) = noise_level(g, &cov, &model, nufft, 1).unwrap();

        // Independent: dense operators from the direct DFT, weights from the public function.
        let (u, v) = cov.uv_wavelengths();
        let keep: Vec<usize> = (0..cov.len()).filter(|&k| !cov.flag[k]).collect();
        let (u, v): (Vec<f64>, Vec<f64>) = keep.iter().map(|&k| (u[k], v[k])).unzip();
        let (x, y): (Vec<f64>, Vec<f64>) = u.iter().zip(&v).map(|(&u, &v)| g.uv_to_phase(u, v)).unzip();
        let iw = imaging_weights(&x, &y, &vec![1.0; u.len()], 8, model.weighting, 2.0).unwrap();
        let l1 = dense_normal_norm(g, &u, &v, &iw);
        let l2 = dense_normal_norm(g, &u, &v, &iw.iter().map(|w| w * w).collect::<Vec<_>>());
        let eta_ref = (l2 / l1).sqrt();
        let tau_ref = (2.0 * l1).sqrt() / (dr * eta_ref);
        assert!((eta / eta_ref - 1.0).abs() < 1e-5, "eta {eta} vs {eta_ref}");
        assert!((tau / tau_ref - 1.0).abs() < 1e-5, "tau {tau} vs {tau_ref}");

        // The simulated noise has that standard deviation.
        let sky = vec![0.0; 64];
        let sim = simulate_visibilities(&sky, g, &cov, &model, WTermMode::Off, nufft, 1, 3).unwrap();
        let var = sim.vis.iter().map(|y| y.norm_sqr()).sum::<f64>() / sim.vis.len() as f64;
        assert!((var.sqrt() / tau - 1.0).abs() < 0.02, "noise std {} vs tau {tau}", var.sqrt());
    }

    #[test]
    fn natural_weighting_has_unit_eta() {
        let cov = sample_coverage(&small_spec(2)).unwrap();
        let g = ImageGeometry::from_superresolution(32, 1.5, cov.max_uv()).unwrap();
        let model = NoiseModel { dynamic_range: 1e4, weighting: Weighting::Natural, grid_factor: 2.0 };
        let (tau, eta, l) = noise_level(g, &cov, &model, NufftParams::default(), 2).unwrap();
        assert_eq!(eta, 1.0);
        assert!((tau - (2.0 * l).sqrt() / 1e4).abs() < 1e-15 * tau.max(1.0));
    }

    #[test]
    fn bad_parameters_are_named() {
        // By the request's fields, which the YAML and the command line each spell their own way.
        let request = |r: ObservationRequest| r.spec().unwrap_err().to_string();
        let vla = || ObservationRequest { telescope: "vla".into(), ..Default::default() };
        let e = request(ObservationRequest { frequency_ratio: Some(0.5), ..vla() });
        assert!(e.contains("invalid frequency_ratio") && e.contains("got 0.5"), "{e}");
        let e = request(ObservationRequest { flag_fraction: 1.0, ..vla() });
        assert!(e.contains("invalid flag_fraction") && e.contains("got 1"), "{e}");
        let e = request(ObservationRequest { channels: Some(0), ..vla() });
        assert!(e.contains("invalid channels"), "{e}");
        let e = request(ObservationRequest { configurations: Some(vec!["q".into()]), hours: Some(vec![1.0]), ..vla() });
        assert!(e.contains("invalid configurations") && e.contains("a, b, c, d"), "{e}");
        assert!(frequency_channels(1e9, 2, 0.5).unwrap_err().to_string().contains("invalid frequency_ratio"));
        // Several channels at ratio 1 would be one frequency several times over.
        let e = frequency_channels(1e9, 4, 1.0).unwrap_err().to_string();
        assert!(e.contains("invalid frequency_ratio") && e.contains("4 frequencies"), "{e}");
        // Frequencies the readers would exclude: the simulated data would be unreadable.
        for hz in [1e15, 1e5, 0.0, f64::NAN] {
            let e = frequency_channels(hz, 1, 1.0).unwrap_err().to_string();
            assert!(e.contains("invalid frequency_mhz") && e.contains("from 1e6 to 1e13 Hz"), "{e}");
        }
        assert!(frequency_channels(1e13, 1, 1.0).is_ok());
        assert!(frequency_channels(1e12, 2, 100.0).unwrap_err().to_string().contains("invalid frequency_ratio"));
        assert!(frequency_channels(1e9, 0, 1.0).unwrap_err().to_string().contains("invalid channels"));
        let spec = ObservationSpec { frequencies_hz: vec![1e9, 1e14], ..small_spec(1) };
        let e = sample_coverage(&spec).unwrap_err().to_string();
        assert!(e.contains("invalid frequencies_hz") && e.contains("got 1e14 Hz"), "{e}");
        // The track's own checks come before the sample count (which a zero time makes infinite).
        for integration_s in [0.0, -1.0, f64::NAN] {
            let e = sample_coverage(&ObservationSpec { integration_s, ..small_spec(1) }).unwrap_err().to_string();
            assert!(e.contains("invalid integration_s") && !e.contains("memory"), "{e}");
        }
        let e = sample_coverage(&ObservationSpec { configurations: vec![("c".into(), 0.0)], ..small_spec(1) }).unwrap_err().to_string();
        assert!(e.contains("invalid hours"), "{e}");
        let e = sample_coverage(&ObservationSpec { dec_deg: -90.0, ..small_spec(1) }).unwrap_err().to_string();
        assert!(e.contains("invalid dec_deg") && e.contains("-90 deg never rises"), "{e}");
        let e = sample_coverage(&ObservationSpec { dec_deg: 91.0, ..small_spec(1) }).unwrap_err().to_string();
        assert!(e.contains("invalid dec_deg") && e.contains("within [-90, 90] deg"), "{e}");
        let spec = ObservationSpec { flag_fraction: 1.5, ..small_spec(1) };
        assert!(sample_coverage(&spec).unwrap_err().to_string().contains("invalid flag_fraction"));
        let spec = ObservationSpec { configurations: vec![("x".into(), 1.0)], ..small_spec(1) };
        let e = sample_coverage(&spec).unwrap_err().to_string();
        assert!(e.contains("invalid configurations") && e.contains("got \"x\""), "{e}");
        let e = sample_coverage(&ObservationSpec { configurations: vec![], ..small_spec(1) }).unwrap_err().to_string();
        assert!(e.contains("invalid configurations"), "{e}");
    }
}
