//! Visibilities as the imaging works on them ([`Visibilities`]: baselines in wavelengths,
//! weights, samples) and what is known of the observation ([`ObservationMeta`]).

use super::error::TableError;
use super::times::ObservedTimes;
use crate::{Error, Result};
use num_complex::Complex32;
use std::collections::BTreeMap;

/// Speed of light in vacuum, m/s (exact, by the definition of the metre).
pub const SPEED_OF_LIGHT: f64 = 299_792_458.0;

pub(crate) const KEY_RA: &str = "phase_centre_ra_deg";
pub(crate) const KEY_DEC: &str = "phase_centre_dec_deg";
pub(crate) const KEY_TELESCOPE: &str = "telescope";
pub(crate) const KEY_NOISE_SIGMA: &str = "noise_sigma";
pub(crate) const KEY_DYNAMIC_RANGE: &str = "dynamic_range";
/// Written by the Arrow Parquet writer itself (the serialised Arrow schema); it
/// describes the file, not the observation, and is regenerated on every write.
pub(crate) const KEY_ARROW_SCHEMA: &str = "ARROW:schema";

/// Metadata key of when the observation began (FITS `DATE-OBS` text, UTC), where a reader
/// knows it (an MS's `OBSERVATION.TIME_RANGE`) or a table carries it.
pub const DATE_OBS_KEY: &str = "date_obs";

/// Metadata key of what was observed (FITS `OBJECT`): an MS's field name, or a table's own.
pub const OBJECT_KEY: &str = "object";

/// Metadata key of the widest channel's width (Hz) of the samples, where a reader knows it (an
/// MS's `SPECTRAL_WINDOW.CHAN_WIDTH`): an image's bandwidth is its channels' span plus one
/// width (edge to edge, as WSClean's `CDELT3`), not the span of their centres.
pub const CHANNEL_WIDTH_KEY: &str = "channel_width_hz";

/// Metadata key of the band the selected channels cover, edge to edge (`"LOW HIGH"`, Hz),
/// where a reader knows it (an MS's `CHAN_FREQ` and `CHAN_WIDTH`): an image's band is
/// WSClean's (all the channels selected, whatever their flags). A split's parts drop it.
pub const BAND_EDGES_KEY: &str = "band_edges_hz";

/// Group `index` of `count` groups of an observation's channels, lowest frequency first (a
/// MeasurementSet's `channel_group`: WSClean's `-channels-out`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelGroup {
    pub index: usize,
    pub count: usize,
}

/// Metadata keys (in [`ObservationMeta::extra`]) of a simulated table that `r2d2 convert`
/// writes an MS's subtables from: the configurations observed, in the order their antenna ids
/// count (`a,c`), and the integration time, seconds.
pub const CONFIGURATIONS_KEY: &str = "configurations";
pub const INTEGRATION_KEY: &str = "integration_s";
/// The angle the simulated (u, v) coverage was rotated by, degrees (0: none): UVW rotated so
/// no longer follow from the antenna positions and times.
pub const ROTATION_KEY: &str = "uv_rotation_deg";

/// What the observation is, as recorded in the file's key-value metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct ObservationMeta {
    /// Right ascension of the phase centre, degrees.
    pub phase_centre_ra_deg: f64,
    /// Declination of the phase centre, degrees.
    pub phase_centre_dec_deg: f64,
    /// Telescope name, e.g. `VLA`.
    pub telescope: String,
    /// Standard deviation of the noise added per visibility, Jy (simulated data).
    pub noise_sigma: Option<f64>,
    /// Dynamic range of the simulated sky (simulated data).
    pub dynamic_range: Option<f64>,
    /// Every other key, verbatim (a key without value is kept with an empty string).
    pub extra: BTreeMap<String, String>,
}

impl ObservationMeta {
    /// A phase centre and telescope, nothing else known (no noise level, dynamic range or
    /// other keys).
    pub fn new(phase_centre_ra_deg: f64, phase_centre_dec_deg: f64, telescope: &str) -> Self {
        ObservationMeta {
            phase_centre_ra_deg,
            phase_centre_dec_deg,
            telescope: telescope.to_string(),
            noise_sigma: None,
            dynamic_range: None,
            extra: BTreeMap::new(),
        }
    }

    /// Parses metadata from key-value pairs (Parquet file metadata, or an Arrow schema's
    /// metadata for other sources). Errors name `source` and the key.
    pub fn from_pairs<'a>(
        pairs: impl IntoIterator<Item = (&'a str, Option<&'a str>)>,
        source: &str,
    ) -> Result<Self> {
        let mut map: BTreeMap<&str, Option<&str>> = pairs.into_iter().collect();
        map.remove(KEY_ARROW_SCHEMA);
        let metadata = |key: &str, message: String| -> Error {
            TableError::Metadata { table: source.to_string(), key: key.to_string(), message }.into()
        };
        let mut take = |key: &str, what: &str, required: bool| -> Result<Option<String>> {
            match map.remove(key) {
                Some(Some(value)) if !value.trim().is_empty() => Ok(Some(value.trim().to_string())),
                Some(_) => Err(metadata(key, format!("metadata key `{key}` is empty; expected {what}"))),
                None if required => Err(metadata(key, format!("metadata key `{key}` is missing; it is required ({what})"))),
                None => Ok(None),
            }
        };
        let number = |key: &str, text: Option<String>| -> Result<Option<f64>> {
            let Some(text) = text else { return Ok(None) };
            let value: f64 =
                text.parse().map_err(|_| metadata(key, format!("metadata key `{key}` = {text:?}: expected a number")))?;
            check_meta_number(key, value).map_err(|msg| metadata(key, format!("metadata key `{key}` = {text}: {msg}")))?;
            Ok(Some(value))
        };

        let ra_text = take(KEY_RA, "the phase centre right ascension in degrees", true)?;
        let dec_text = take(KEY_DEC, "the phase centre declination in degrees", true)?;
        let telescope = take(KEY_TELESCOPE, "the telescope name", true)?.unwrap_or_default();
        let noise_text = take(KEY_NOISE_SIGMA, "the noise standard deviation in Jy", false)?;
        let range_text = take(KEY_DYNAMIC_RANGE, "the dynamic range of the sky", false)?;
        let extra =
            map.into_iter().map(|(k, v)| (k.to_string(), v.unwrap_or_default().to_string())).collect();
        Ok(ObservationMeta {
            phase_centre_ra_deg: number(KEY_RA, ra_text)?.unwrap_or_default(),
            phase_centre_dec_deg: number(KEY_DEC, dec_text)?.unwrap_or_default(),
            telescope,
            noise_sigma: number(KEY_NOISE_SIGMA, noise_text)?,
            dynamic_range: number(KEY_DYNAMIC_RANGE, range_text)?,
            extra,
        })
    }

    /// The metadata as key-value pairs, numbers with full precision (shortest text that
    /// reads back to the same f64). Checks the values as the reader would.
    pub fn to_pairs(&self) -> Result<Vec<(String, String)>> {
        let mut pairs = Vec::with_capacity(5 + self.extra.len());
        let numbers = [
            (KEY_RA, Some(self.phase_centre_ra_deg)),
            (KEY_DEC, Some(self.phase_centre_dec_deg)),
            (KEY_NOISE_SIGMA, self.noise_sigma),
            (KEY_DYNAMIC_RANGE, self.dynamic_range),
        ];
        for (key, value) in numbers {
            if let Some(value) = value {
                check_meta_number(key, value)
                    .map_err(|msg| Error::parameter(format!("metadata {key}"), format!("{value}: {msg}")))?;
                pairs.push((key.to_string(), format!("{value}")));
            }
        }
        if self.telescope.trim().is_empty() {
            return Err(Error::parameter("metadata telescope", "must not be empty"));
        }
        pairs.push((KEY_TELESCOPE.to_string(), self.telescope.clone()));
        let reserved = [KEY_RA, KEY_DEC, KEY_TELESCOPE, KEY_NOISE_SIGMA, KEY_DYNAMIC_RANGE, KEY_ARROW_SCHEMA];
        for (key, value) in &self.extra {
            if reserved.contains(&key.as_str()) {
                return Err(Error::parameter(
                    format!("metadata extra key `{key}`"),
                    "is reserved for a field of ObservationMeta or by Arrow",
                ));
            }
            pairs.push((key.clone(), value.clone()));
        }
        Ok(pairs)
    }
}

/// Checks a phase centre given as parameters (right ascension, declination in degrees) as the
/// reader would check it in a file, so that no file is written that cannot be read back;
/// errors name `fields` (right ascension, declination): the fields of the parameters that
/// gave them.
pub(crate) fn check_phase_centre(ra_deg: f64, dec_deg: f64, fields: [&str; 2]) -> Result<()> {
    for ((key, value), field) in [(KEY_RA, ra_deg), (KEY_DEC, dec_deg)].into_iter().zip(fields) {
        check_meta_number(key, value).map_err(|msg| Error::parameter(field, format!("{value}: {msg}")))?;
    }
    Ok(())
}

/// Checks a numeric metadata value; the error says what was expected.
pub(crate) fn check_meta_number(key: &str, value: f64) -> std::result::Result<(), &'static str> {
    let (ok, expected) = match key {
        KEY_RA => ((0.0..360.0).contains(&value), "expected a right ascension within [0, 360) degrees"),
        KEY_DEC => ((-90.0..=90.0).contains(&value), "expected a declination within [-90, 90] degrees"),
        KEY_NOISE_SIGMA => (value.is_finite() && value >= 0.0, "expected a finite non-negative noise level"),
        KEY_DYNAMIC_RANGE => (value.is_finite() && value > 0.0, "expected a finite positive dynamic range"),
        _ => (value.is_finite(), "expected a finite number"),
    };
    if ok {
        Ok(())
    } else {
        Err(expected)
    }
}

/// Visibilities ready for imaging: unflagged, finite, positive weight, in wavelengths.
///
/// A table of millions of rows is held whole, so each column has the narrowest type that
/// loses nothing the imaging can see: 40 bytes a sample.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Visibilities {
    /// Baseline u, wavelengths (metres times frequency / c). Double precision: a phase of
    /// `2 pi u l` must stay exact to far better than the NUFFT's accuracy on long baselines.
    pub u: Vec<f64>,
    /// Baseline v, wavelengths.
    pub v: Vec<f64>,
    /// Baseline w, wavelengths. Double precision: the w-term's phase `2 pi w (n - 1)` must
    /// stay exact to the NUFFT's accuracy over wide fields.
    pub w: Vec<f64>,
    /// Stokes I visibility, Jy. Single precision, as a MeasurementSet stores it (and WSClean
    /// grids it): the relative rounding, 6e-8, is far below the noise of any measurement and
    /// the NUFFT's accuracy; gridding accumulates in f64.
    pub vis: Vec<Complex32>,
    /// Natural weight, 1/sigma^2; always positive. Single precision, as a MeasurementSet
    /// stores it; total weights are computed in f64.
    pub weight: Vec<f32>,
    /// Frequency of each sample, Hz. Double precision: the band written to the products'
    /// headers comes from it.
    pub frequency: Vec<f64>,
    /// Imaging weights given with the data (a table's `imaging_weight` column, a .mat file's
    /// `nWimag` squared), one per sample, used by the `given` weighting; empty when none were.
    pub imaging_weight: Vec<f32>,
    /// The tracks the samples were taken in and their integration time (a series' domain
    /// names both), where the data carry times: gathered as they are read, not kept per sample.
    pub times: ObservedTimes,
}

impl Visibilities {
    /// Empty, with room for `n` samples.
    pub fn with_capacity(n: usize) -> Self {
        Visibilities {
            u: Vec::with_capacity(n),
            v: Vec::with_capacity(n),
            w: Vec::with_capacity(n),
            vis: Vec::with_capacity(n),
            weight: Vec::with_capacity(n),
            frequency: Vec::with_capacity(n),
            imaging_weight: Vec::new(),
            times: ObservedTimes::default(),
        }
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.u.len()
    }

    pub fn is_empty(&self) -> bool {
        self.u.is_empty()
    }

    /// Longest projected baseline sqrt(u^2 + v^2), wavelengths; 0 when empty. It sets
    /// the finest resolution the data support, hence the largest sensible pixel.
    pub fn max_uv(&self) -> f64 {
        self.u.iter().zip(&self.v).map(|(u, v)| u.hypot(*v)).fold(0.0, f64::max)
    }

    /// Centre of the observed band and its width (None for a single frequency), Hz.
    pub fn band(&self) -> Option<(f64, Option<f64>)> {
        let (lo, hi) = self.frequency.iter().fold((f64::INFINITY, 0.0f64), |(a, b), &f| (a.min(f), b.max(f)));
        (hi >= lo).then(|| (0.5 * (lo + hi), (hi > lo).then_some(hi - lo)))
    }

    /// Empties it, keeping the room it has: a reader gathering chunk after chunk into one
    /// buffer then touches fresh memory for the first chunk only.
    pub fn clear(&mut self) {
        self.u.clear();
        self.v.clear();
        self.w.clear();
        self.vis.clear();
        self.weight.clear();
        self.frequency.clear();
        self.imaging_weight.clear();
        self.times = ObservedTimes::default();
    }

    /// Appends another batch, moving its samples.
    pub fn push_batch(&mut self, mut other: Visibilities) {
        self.u.append(&mut other.u);
        self.v.append(&mut other.v);
        self.w.append(&mut other.w);
        self.vis.append(&mut other.vis);
        self.weight.append(&mut other.weight);
        self.frequency.append(&mut other.frequency);
        self.imaging_weight.append(&mut other.imaging_weight);
        self.times.merge(&other.times);
    }

    /// Splits the samples into `groups` parts: sample `i` goes to part `group[i]` (< `groups`),
    /// keeping their order within each part. Each part has the whole's times (a caller that
    /// splits by time gives each part its own).
    pub fn partition(self, group: &[usize], groups: usize) -> Vec<Visibilities> {
        assert_eq!(group.len(), self.len(), "one group per sample");
        let mut counts = vec![0usize; groups];
        for &g in group {
            counts[g] += 1;
        }
        let mut parts: Vec<Visibilities> = counts.iter().map(|&n| Visibilities { times: self.times.clone(), ..Visibilities::with_capacity(n) }).collect();
        for (i, &g) in group.iter().enumerate() {
            parts[g].push([self.u[i], self.v[i]], self.w[i], self.vis[i], self.weight[i], self.frequency[i]);
            if let Some(&x) = self.imaging_weight.get(i) {
                parts[g].imaging_weight.push(x);
            }
        }
        parts
    }

    pub(crate) fn push(&mut self, uv: [f64; 2], w: f64, vis: Complex32, weight: f32, frequency: f64) {
        self.u.push(uv[0]);
        self.v.push(uv[1]);
        self.w.push(w);
        self.vis.push(vis);
        self.weight.push(weight);
        self.frequency.push(frequency);
    }
}

/// Largest |u|, |v| or |w| of a sample, metres: no two points on Earth are farther apart than
/// its equatorial diameter, 12 756 km. A longer baseline is a corrupt value (one such row would
/// set the pixel size, 1 / longest baseline, to nonsense); space VLBI is out of scope.
pub const MAX_BASELINE_M: f64 = 1.3e7;

/// Frequencies a radio interferometer on the ground observes at, Hz: the ionosphere reflects
/// what is below a few MHz, the atmosphere absorbs what is above about 1 THz.
pub const FREQUENCY_RANGE_HZ: (f64, f64) = (1e6, 1e13);


/// `telescope` unless it names none (empty, or the `unknown` that readers write then).
pub fn named_telescope(telescope: &str) -> Option<String> {
    let t = telescope.trim();
    (!t.is_empty() && !t.eq_ignore_ascii_case(UNKNOWN_TELESCOPE)).then(|| t.to_string())
}

/// What readers write as the telescope of data that name none.
pub const UNKNOWN_TELESCOPE: &str = "unknown";

/// Samples of a pass, borrowed: a slice of held visibilities or one decoded batch.
#[derive(Clone, Copy, Debug)]
pub struct VisChunk<'a> {
    pub u: &'a [f64],
    pub v: &'a [f64],
    pub w: &'a [f64],
    pub vis: &'a [Complex32],
    pub weight: &'a [f32],
    pub frequency: &'a [f64],
    /// Empty when the data carry no imaging weights.
    pub imaging_weight: &'a [f32],
}

impl<'a> VisChunk<'a> {
    pub fn len(&self) -> usize {
        self.u.len()
    }
    pub fn is_empty(&self) -> bool {
        self.u.is_empty()
    }
}

impl Visibilities {
    /// Samples `range` of these visibilities, borrowed.
    pub fn chunk(&self, range: std::ops::Range<usize>) -> VisChunk<'_> {
        VisChunk {
            u: &self.u[range.clone()],
            v: &self.v[range.clone()],
            w: &self.w[range.clone()],
            vis: &self.vis[range.clone()],
            weight: &self.weight[range.clone()],
            frequency: &self.frequency[range.clone()],
            imaging_weight: if self.imaging_weight.is_empty() { &[] } else { &self.imaging_weight[range] },
        }
    }
}

/// What imaging needs to know of all the samples before its first pass over them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VisSummary {
    pub samples: u64,
    /// Longest projected baseline sqrt(u^2 + v^2), wavelengths.
    pub max_uv: f64,
    pub max_abs_w: f64,
    /// Lowest and highest frequency, Hz (`lowest > highest` when empty).
    pub lowest_hz: f64,
    pub highest_hz: f64,
    /// Whether the samples carry imaging weights (the `given` weighting's).
    pub imaging_weights: bool,
    /// The tracks and integration time of the samples (empty where they carry no times).
    pub times: ObservedTimes,
}

impl VisSummary {
    pub fn empty() -> VisSummary {
        VisSummary { lowest_hz: f64::INFINITY, highest_hz: 0.0, ..VisSummary::default() }
    }

    pub fn of(vis: &Visibilities) -> VisSummary {
        let mut s = VisSummary::empty();
        s.add_visibilities(vis);
        s
    }

    /// Adds held or decoded samples, their times included.
    pub fn add_visibilities(&mut self, vis: &Visibilities) {
        self.add(&vis.chunk(0..vis.len()));
        self.times.merge(&vis.times);
    }

    pub fn add(&mut self, chunk: &VisChunk<'_>) {
        self.samples += chunk.len() as u64;
        self.max_uv = chunk.u.iter().zip(chunk.v).map(|(u, v)| u.hypot(*v)).fold(self.max_uv, f64::max);
        self.max_abs_w = chunk.w.iter().fold(self.max_abs_w, |m, w| m.max(w.abs()));
        for &f in chunk.frequency {
            self.lowest_hz = self.lowest_hz.min(f);
            self.highest_hz = self.highest_hz.max(f);
        }
        self.imaging_weights |= !chunk.imaging_weight.is_empty();
    }

    /// Adds another part's summary to this one (the summary of both parts together).
    pub fn merge(&mut self, other: &VisSummary) {
        self.samples += other.samples;
        self.max_uv = self.max_uv.max(other.max_uv);
        self.max_abs_w = self.max_abs_w.max(other.max_abs_w);
        self.lowest_hz = self.lowest_hz.min(other.lowest_hz);
        self.highest_hz = self.highest_hz.max(other.highest_hz);
        self.imaging_weights |= other.imaging_weights;
        self.times.merge(&other.times);
    }

    /// Centre of the observed band and its width (None for a single frequency), Hz.
    pub fn band(&self) -> Option<(f64, Option<f64>)> {
        let (lo, hi) = (self.lowest_hz, self.highest_hz);
        (hi >= lo).then(|| (0.5 * (lo + hi), (hi > lo).then_some(hi - lo)))
    }
}
