//! Telescopes, antenna layouts and Earth-rotation uv coverage.
//!
//! Telescopes are data, not code: `data/telescopes/telescopes.yaml` names each telescope, its
//! layouts (antenna tables in ITRF metres beside it) and its typical observing set-ups (what
//! `r2d2 simulate` observes by default, what `r2d2 trainset` draws per sample). Both the
//! registry and the tables are compiled in with `include_str!`, so the binary needs no data
//! files at run time and a simulation cannot silently pick up a different table.
//!
//! Baselines are computed in the ITRF (Earth-fixed, equatorial) frame and projected onto the
//! (u, v, w) frame of the phase centre with the standard rotation (Thompson, Moran & Swenson,
//! eq. 4.1, written for a Greenwich hour angle because ITRF X points at the Greenwich
//! meridian). Units stay in metres here; conversion to wavelengths depends on the frequency
//! and belongs to whoever assembles the visibilities.

use crate::error::{Error, Result};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::sync::OnceLock;

/// Sidereal rate: hours of hour angle per hour of (UTC) time.
pub(crate) const SIDEREAL_PER_SOLAR: f64 = 1.002_737_909_35;

/// Where the registry is, for its errors.
const REGISTRY_PATH: &str = "data/telescopes/telescopes.yaml";
const REGISTRY: &str = include_str!("../../data/telescopes/telescopes.yaml");

/// The antenna tables the registry may name, by file name: every `*.itrf.txt` beside it (listed
/// by `build.rs`).
const TABLES: &[(&str, &str)] = include!(concat!(env!("OUT_DIR"), "/antenna_tables.rs"));

/// A telescope the simulator knows (an entry of the registry).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Telescope {
    /// The registry's key (`vla`, `meerkat`), filled in from the entry's name.
    #[serde(skip)]
    pub key: String,
    /// The name written as `TELESCOPE_NAME` into tables and MeasurementSets (`VLA`, `MeerKAT`).
    pub name: String,
    /// Other names its data go by (CASA writes `EVLA` for the VLA): the telescope is found by
    /// any of them, as by its key and name.
    #[serde(default)]
    pub aliases: Vec<String>,
    /// Configuration name -> antenna table file.
    pub layouts: BTreeMap<String, String>,
    /// A typical observation: what `r2d2 simulate --telescope KEY` does where no option says
    /// otherwise.
    pub observation: ObservationPreset,
    /// What `r2d2 trainset --telescope KEY` draws per sample.
    pub training: TrainingPreset,
}

/// A typical observation of a telescope.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObservationPreset {
    pub configurations: Vec<String>,
    /// Observing time per configuration, hours.
    pub hours: Vec<f64>,
    pub dec_deg: f64,
    /// Lowest frequency, MHz.
    pub frequency_mhz: f64,
    pub channels: usize,
    /// Highest over lowest frequency.
    pub frequency_ratio: f64,
    pub integration_s: f64,
}

/// The ranges a training set draws its observations from, per sample (uniformly).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainingPreset {
    pub configurations: Vec<String>,
    /// Observing time per configuration, `[low, high]` hours.
    pub hours: Vec<[f64; 2]>,
    pub dec_deg: [f64; 2],
    /// Lowest frequency, MHz (only frequency ratios matter once the pixel follows the
    /// super-resolution, but the written tables carry it).
    pub lowest_frequency_mhz: f64,
    /// Number of channels, `[low, high]`.
    pub channels: [usize; 2],
    pub frequency_ratio: [f64; 2],
    /// Integration time when the set does not choose one, seconds.
    pub integration_s: f64,
}

/// Every telescope of the registry, in its order.
pub fn telescopes() -> Result<&'static [Telescope]> {
    static PARSED: OnceLock<std::result::Result<Vec<Telescope>, String>> = OnceLock::new();
    PARSED.get_or_init(|| parse_registry(REGISTRY)).as_deref().map_err(|m| Error::input(REGISTRY_PATH, m.clone()))
}

fn parse_registry(text: &str) -> std::result::Result<Vec<Telescope>, String> {
    let entries: serde_yaml::Mapping = serde_yaml::from_str(text).map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    for (key, value) in entries {
        let key = key.as_str().ok_or("expected telescope names as keys")?.to_string();
        let mut t: Telescope = serde_yaml::from_value(value).map_err(|e| format!("{key}: {e}"))?;
        t.key = key;
        t.check()?;
        out.push(t);
    }
    Ok(out)
}

/// The telescope named `name` (its key, its `TELESCOPE_NAME` or one of its aliases, any case).
pub fn telescope(name: &str) -> Result<&'static Telescope> {
    let all = telescopes()?;
    let wanted = name.trim();
    all.iter().find(|t| t.is_named(wanted)).ok_or_else(|| {
        let known: Vec<&str> = all.iter().map(|t| t.key.as_str()).collect();
        Error::parameter("telescope", format!("expected one of {} (the telescopes in {REGISTRY_PATH}), got '{name}'", known.join(", ")))
    })
}

impl Telescope {
    /// Whether `name` (trimmed) is the telescope's key, name or an alias, in any case.
    pub fn is_named(&self, name: &str) -> bool {
        std::iter::once(&self.key).chain([&self.name]).chain(&self.aliases).any(|n| n.eq_ignore_ascii_case(name))
    }

    /// The antenna array of configuration `config` (any case).
    pub fn array(&self, config: &str) -> Result<Array> {
        let wanted = config.trim().to_ascii_lowercase();
        let file = self.layouts.get(&wanted).ok_or_else(|| {
            let known: Vec<&str> = self.layouts.keys().map(String::as_str).collect();
            Error::parameter("telescope configuration", format!("expected one of {} for {}, got {config:?}", known.join(", "), self.key))
        })?;
        let (_, text) = TABLES.iter().find(|(name, _)| name == file).ok_or_else(|| {
            Error::input(REGISTRY_PATH, format!("{}: layout {wanted}: no antenna table {file} is compiled in", self.key))
        })?;
        let name = if self.layouts.len() == 1 { self.key.clone() } else { format!("{}-{wanted}", self.key) };
        parse_itrf_table(text, &name)
    }

    /// Refuses an entry whose presets name layouts it lacks or give ranges that do not fit.
    fn check(&self) -> std::result::Result<(), String> {
        let key = &self.key;
        let o = &self.observation;
        let t = &self.training;
        if let Some(c) = self.layouts.keys().find(|c| **c != c.to_ascii_lowercase()) {
            return Err(format!("{key}: layout '{c}': names are lower case (options match them in any case)"));
        }
        let mut drawn = t.configurations.clone();
        drawn.sort();
        if drawn.windows(2).any(|w| w[0] == w[1]) {
            return Err(format!("{key}: training lists a configuration twice (each draws its own hours)"));
        }
        for c in o.configurations.iter().chain(&t.configurations) {
            if !self.layouts.contains_key(c) {
                return Err(format!("{key}: configuration '{c}' is not one of its layouts"));
            }
        }
        if o.configurations.len() != o.hours.len() || t.configurations.len() != t.hours.len() {
            return Err(format!("{key}: give one observing time per configuration"));
        }
        let ordered = |[lo, hi]: [f64; 2]| lo.is_finite() && hi.is_finite() && lo <= hi;
        if !t.hours.iter().all(|h| ordered(*h) && h[0] > 0.0) || !ordered(t.dec_deg) || !ordered(t.frequency_ratio) || t.channels[0] < 1 || t.channels[0] > t.channels[1] {
            return Err(format!("{key}: training ranges must be [low, high] with low <= high (positive hours, at least one channel)"));
        }
        Ok(())
    }
}

/// An antenna array: positions in the ITRF frame (metres) and dish diameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    /// Human-readable name, used in error messages and logs (e.g. "vla-a").
    pub name: String,
    /// Antenna positions, ITRF X, Y, Z in metres (X towards Greenwich, Z towards the pole).
    pub positions_itrf: Vec<[f64; 3]>,
    /// Dish diameter of each antenna in metres (same order as `positions_itrf`).
    pub dish_diameter_m: Vec<f64>,
    /// Station name of each antenna: the table's fifth column (`M000`), else its number.
    pub stations: Vec<String>,
}

impl Array {
    /// Number of antennas.
    pub fn n_antennas(&self) -> usize {
        self.positions_itrf.len()
    }

    /// Number of distinct antenna pairs (no autocorrelations), `n (n - 1) / 2`.
    pub fn n_baselines(&self) -> usize {
        let n = self.n_antennas();
        n * n.saturating_sub(1) / 2
    }

    /// Mean antenna position (ITRF metres). The array centre is what the longitude and
    /// latitude refer to; for a compact array like the VLA it lies a few metres below the
    /// surface, which does not matter for angles.
    pub fn mean_position(&self) -> [f64; 3] {
        let n = self.positions_itrf.len().max(1) as f64;
        let mut m = [0.0; 3];
        for p in &self.positions_itrf {
            for k in 0..3 {
                m[k] += p[k];
            }
        }
        m.map(|c| c / n)
    }

    /// East longitude of the array centre in radians, in (-pi, pi].
    pub fn longitude_rad(&self) -> f64 {
        let [x, y, _] = self.mean_position();
        y.atan2(x)
    }

    /// Geocentric latitude of the array centre in radians. This is the angle of the position
    /// vector above the equator, not the geodetic (WGS84) latitude; the two differ by up to
    /// ~0.19 deg. The uv-coverage computation does not use the latitude at all (the ITRF
    /// rotation needs only the hour angle and declination), so the simpler one is enough for
    /// reporting and for elevation-style sanity checks.
    pub fn latitude_rad(&self) -> f64 {
        let [x, y, z] = self.mean_position();
        z.atan2(x.hypot(y))
    }

    /// Refuses a declination that never rises above this array's horizon: from latitude
    /// `lat` a source rises if `dec > lat - 90` (northern site) or `dec < lat + 90` (southern).
    /// Horizon limits are not modelled otherwise (see [`uvw_tracks`]), so such a track would
    /// be simulated as if the Earth were transparent.
    pub fn check_rises(&self, dec_rad: f64) -> Result<()> {
        let lat = self.latitude_rad().to_degrees();
        let dec = dec_rad.to_degrees();
        let (rises, reachable) = if lat >= 0.0 {
            (dec > lat - 90.0, format!("above {:.1} deg", lat - 90.0))
        } else {
            (dec < lat + 90.0, format!("below {:.1} deg", lat + 90.0))
        };
        if rises {
            return Ok(());
        }
        Err(Error::parameter(
            "declination",
            format!("{dec} deg never rises above the horizon of {} (latitude {lat:.1} deg): expected a declination {reachable}", self.name),
        ))
    }

    /// Longest baseline length in metres (0 for fewer than two antennas).
    #[cfg(test)]
    pub fn max_baseline_m(&self) -> f64 {
        let p = &self.positions_itrf;
        let mut best = 0.0f64;
        for i in 0..p.len() {
            for j in i + 1..p.len() {
                best = best.max(norm3(sub3(p[j], p[i])));
            }
        }
        best
    }
}

/// Parse an antenna table: lines starting with `#` and blank lines are ignored; every other
/// line holds `X Y Z dish_diameter [station [mount]]`, with X, Y, Z in ITRF metres and the
/// dish diameter in metres. The station name is kept (a converted MS names its antennas by
/// it; an antenna without one is named by its number); the mount is accepted and ignored.
///
/// `name` is the array name and is used as the "path" in errors, together with the 1-based
/// line number, so a broken table can be fixed without reading code.
pub fn parse_itrf_table(text: &str, name: &str) -> Result<Array> {
    let mut positions = Vec::new();
    let mut diameters = Vec::new();
    let mut stations = Vec::new();
    for (idx, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let lineno = idx + 1;
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.len() < 4 {
            return Err(Error::input(
                name,
                format!(
                    "line {lineno}: expected at least 4 columns (X Y Z dish_diam), found {}: {line:?}",
                    fields.len()
                ),
            ));
        }
        let mut vals = [0.0f64; 4];
        for (k, (v, col)) in vals
            .iter_mut()
            .zip(["X", "Y", "Z", "dish_diam"])
            .enumerate()
        {
            *v = fields[k]
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| {
                    Error::input(
                        name,
                        format!(
                            "line {lineno}: column {col} is not a finite number: {:?}",
                            fields[k]
                        ),
                    )
                })?;
        }
        if vals[3] <= 0.0 {
            return Err(Error::input(
                name,
                format!(
                    "line {lineno}: dish diameter must be positive, got {}",
                    vals[3]
                ),
            ));
        }
        stations.push(fields.get(4).map_or_else(|| format!("{:02}", positions.len()), |s| s.to_string()));
        positions.push([vals[0], vals[1], vals[2]]);
        diameters.push(vals[3]);
    }
    if positions.len() < 2 {
        return Err(Error::input(
            name,
            format!(
                "an interferometer needs at least 2 antennas, the table has {}",
                positions.len()
            ),
        ));
    }
    Ok(Array {
        name: name.to_string(),
        positions_itrf: positions,
        dish_diameter_m: diameters,
        stations,
    })
}

/// What to observe and for how long.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackSpec {
    /// Declination of the phase centre, radians.
    pub dec_rad: f64,
    /// Duration of the observation in hours of (UTC) time, centred on transit at the array
    /// longitude: the local hour angle runs from about `-span/2` to `+span/2` hours (slightly
    /// more, by the sidereal factor 1.0027, since the hour angle advances at the sidereal
    /// rate). Time rather than hour angle, because the paper specifies observation times and
    /// the number of samples is `span * 3600 / integration_s`.
    pub hour_angle_span_h: f64,
    /// Integration (sampling) time in seconds.
    pub integration_s: f64,
}

impl TrackSpec {
    /// Check the values make sense (finite, positive times, |dec| <= 90 deg).
    pub fn validate(&self) -> Result<()> {
        if !self.dec_rad.is_finite() || self.dec_rad.abs() > std::f64::consts::FRAC_PI_2 + 1e-12 {
            return Err(Error::parameter(
                "declination",
                format!(
                    "must be within [-90, 90] deg, got {} deg",
                    self.dec_rad.to_degrees()
                ),
            ));
        }
        if !(self.hour_angle_span_h.is_finite() && self.hour_angle_span_h > 0.0) {
            return Err(Error::parameter(
                "observation time",
                format!(
                    "must be a positive number of hours, got {}",
                    self.hour_angle_span_h
                ),
            ));
        }
        if !(self.integration_s.is_finite() && self.integration_s > 0.0) {
            return Err(Error::parameter(
                "integration time",
                format!(
                    "must be a positive number of seconds, got {}",
                    self.integration_s
                ),
            ));
        }
        Ok(())
    }

    /// Number of time samples: `max(1, round(span * 3600 / integration))`.
    pub fn n_times(&self) -> usize {
        ((self.hour_angle_span_h * 3600.0 / self.integration_s).round() as usize).max(1)
    }
}

/// Baseline coordinates of an observation, as a struct of arrays (one entry per
/// visibility), ordered time-major: all baselines (i < j, lexicographic) of the first
/// integration, then of the second, and so on, as in a MeasurementSet.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct UvwTrack {
    /// u in metres (towards the east of the phase centre).
    pub u_m: Vec<f64>,
    /// v in metres (towards the north celestial pole).
    pub v_m: Vec<f64>,
    /// w in metres (towards the phase centre).
    pub w_m: Vec<f64>,
    /// Time of the sample's integration centre, seconds from the start of the observation.
    pub time_s: Vec<f64>,
    /// First antenna (index into the array's tables), always < `antenna2`.
    pub antenna1: Vec<i32>,
    /// Second antenna.
    pub antenna2: Vec<i32>,
}

impl UvwTrack {
    /// Number of samples (visibilities).
    pub fn len(&self) -> usize {
        self.u_m.len()
    }

    /// Largest projected baseline `sqrt(u^2 + v^2)` in metres (0 if empty). Divided by the
    /// wavelength this is the `max_uv` that fixes the pixel size.
    #[cfg(test)]
    pub fn max_uv_m(&self) -> f64 {
        self.u_m
            .iter()
            .zip(&self.v_m)
            .map(|(u, v)| u.hypot(*v))
            .fold(0.0, f64::max)
    }
}

/// Earth-rotation uv tracks of `array` observing a source at declination `spec.dec_rad` for
/// `spec.hour_angle_span_h` hours centred on transit.
///
/// Samples are at `t_k = (k + 0.5) * integration` for `k = 0..n_times`, and the local hour
/// angle at `t` is `(t - T/2) * omega_sidereal` with `T = n_times * integration`, so the
/// track is symmetric about transit. With ITRF baselines `B = X_j - X_i` and the Greenwich
/// hour angle `H = H_local - east_longitude`:
///
/// ```text
/// u =  sin H Bx + cos H By
/// v = -sin d cos H Bx + sin d sin H By + cos d Bz
/// w =  cos d cos H Bx - cos d sin H By + sin d Bz
/// ```
///
/// The rotation is orthogonal, so `|uvw| = |B|` for every sample. Horizon limits and
/// shadowing are not modelled: the paper's declinations (5..60 deg) with at most 10 h tracks
/// keep the VLA's source above the horizon.
pub fn uvw_tracks(array: &Array, spec: &TrackSpec) -> Result<UvwTrack> {
    spec.validate()?;
    array.check_rises(spec.dec_rad)?;
    let n_ant = array.n_antennas();
    let n_t = spec.n_times();
    let n_bl = array.n_baselines();
    let total = n_t * n_bl;

    let mut out = UvwTrack {
        u_m: Vec::with_capacity(total),
        v_m: Vec::with_capacity(total),
        w_m: Vec::with_capacity(total),
        time_s: Vec::with_capacity(total),
        antenna1: Vec::with_capacity(total),
        antenna2: Vec::with_capacity(total),
    };

    // Baseline vectors once; they do not change with time.
    let p = &array.positions_itrf;
    let mut pairs = Vec::with_capacity(n_bl);
    for i in 0..n_ant {
        for j in i + 1..n_ant {
            pairs.push((i as i32, j as i32, sub3(p[j], p[i])));
        }
    }

    let (sd, cd) = spec.dec_rad.sin_cos();
    let lon = array.longitude_rad();
    // Radians of hour angle per second of time.
    let omega = SIDEREAL_PER_SOLAR * 2.0 * std::f64::consts::PI / 86_400.0;
    let duration = n_t as f64 * spec.integration_s;
    for k in 0..n_t {
        let t = (k as f64 + 0.5) * spec.integration_s;
        let h_local = (t - 0.5 * duration) * omega;
        let (sh, ch) = (h_local - lon).sin_cos();
        for &(a1, a2, [bx, by, bz]) in &pairs {
            out.u_m.push(sh * bx + ch * by);
            out.v_m.push(-sd * ch * bx + sd * sh * by + cd * bz);
            out.w_m.push(cd * ch * bx - cd * sh * by + sd * bz);
            out.time_s.push(t);
            out.antenna1.push(a1);
            out.antenna2.push(a2);
        }
    }
    Ok(out)
}

/// Rotate every (u, v) by `angle_rad` counter-clockwise (w unchanged). This is the paper's
/// random rotation of the sampling pattern: it turns a handful of antenna layouts and
/// declinations into many distinct PSFs while keeping each one physically plausible.
#[cfg(test)]
pub fn rotate_uv(track: &mut UvwTrack, angle_rad: f64) {
    let (s, c) = angle_rad.sin_cos();
    for (u, v) in track.u_m.iter_mut().zip(track.v_m.iter_mut()) {
        let (u0, v0) = (*u, *v);
        *u = c * u0 - s * v0;
        *v = s * u0 + c * v0;
    }
}

fn sub3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[cfg(test)]
fn norm3(a: [f64; 3]) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The VLA in configuration `config` ('a', 'b', 'c' or 'd', case-insensitive).
    fn vla(config: char) -> Result<Array> {
        telescope("vla")?.array(&config.to_string())
    }
    use std::f64::consts::{FRAC_PI_2, PI};

    fn baseline(a: &Array, i: i32, j: i32) -> [f64; 3] {
        sub3(a.positions_itrf[j as usize], a.positions_itrf[i as usize])
    }

    #[test]
    fn vla_tables_parse_with_27_antennas_and_351_baselines() {
        for c in ['a', 'b', 'C', 'D'] {
            let a = vla(c).unwrap();
            assert_eq!(a.n_antennas(), 27, "{}", a.name);
            assert_eq!(a.n_baselines(), 351);
            assert!(a.dish_diameter_m.iter().all(|&d| d == 25.0));
        }
    }

    #[test]
    fn every_telescope_of_the_registry_has_its_layouts_and_presets() {
        let all = telescopes().unwrap();
        assert_eq!(all.iter().map(|t| t.key.as_str()).collect::<Vec<_>>(), ["vla", "meerkat", "ska-mid"]);
        for t in all {
            for config in t.layouts.keys() {
                let a = t.array(config).unwrap();
                assert!(a.n_antennas() >= 27, "{}", a.name);
            }
            assert!(std::ptr::eq(telescope(&t.name).unwrap(), t), "found by its TELESCOPE_NAME too");
            for alias in &t.aliases {
                assert!(std::ptr::eq(telescope(&alias.to_lowercase()).unwrap(), t), "found by its alias {alias}, in any case");
            }
        }
        // Every antenna table beside the registry is compiled in (build.rs lists them).
        assert_eq!(TABLES.len(), 6);
        assert_eq!((telescope(" EVLA ").unwrap().key.as_str(), telescope("MeerKAT+").unwrap().key.as_str()), ("vla", "meerkat"));
        let meerkat = telescope("meerkat").unwrap().array("meerkat").unwrap();
        assert_eq!((meerkat.n_antennas(), meerkat.n_baselines()), (64, 2016));
        assert!(meerkat.dish_diameter_m.iter().all(|&d| d == 13.5));
        assert_eq!((meerkat.stations[0].as_str(), meerkat.stations[63].as_str()), ("M000", "M063"));
        // MeerKAT's longest baseline is 7.7 km; the site is at 30.7 deg S (geodetic; the
        // geocentric latitude reported here is 0.17 deg nearer the equator), 21.4 deg E.
        let longest = meerkat.max_baseline_m();
        assert!((7600.0..7800.0).contains(&longest), "{longest}");
        let (lat, lon) = (meerkat.latitude_rad().to_degrees(), meerkat.longitude_rad().to_degrees());
        assert!((-30.6..-30.4).contains(&lat) && (21.3..21.5).contains(&lon), "{lat} {lon}");
        let ska = telescope("SKA-Mid").unwrap().array("aastar").unwrap();
        assert_eq!(ska.n_antennas(), 143);
        // The SKA dishes of the source's AA* list reach several times MeerKAT's extent.
        assert!(ska.max_baseline_m() > 4.0 * longest, "{}", ska.max_baseline_m());
    }

    #[test]
    fn a_registry_naming_a_missing_layout_or_bad_ranges_is_refused() {
        let entry = |rest: &str| format!("x:\n  name: X\n  layouts: {{a: vlaa.itrf.txt}}\n  observation: {{configurations: [a], hours: [1], dec_deg: 0, frequency_mhz: 1000, channels: 1, frequency_ratio: 1, integration_s: 10}}\n{rest}");
        let good = "  training: {configurations: [a], hours: [[1, 2]], dec_deg: [0, 10], lowest_frequency_mhz: 1000, channels: [1, 2], frequency_ratio: [1, 2], integration_s: 60}\n";
        assert!(parse_registry(&entry(good)).is_ok());
        let e = parse_registry(&entry(&good.replace("configurations: [a]", "configurations: [b]"))).unwrap_err();
        assert!(e.contains("'b' is not one of its layouts"), "{e}");
        let e = parse_registry(&entry(&good.replace("dec_deg: [0, 10]", "dec_deg: [10, 0]"))).unwrap_err();
        assert!(e.contains("low <= high"), "{e}");
        let e = parse_registry(&entry(&good.replace("integration_s: 60", "integration: 60"))).unwrap_err();
        assert!(e.contains("unknown field"), "{e}");
    }

    #[test]
    fn vla_rejects_unknown_configuration() {
        let e = vla('e').unwrap_err().to_string();
        assert!(
            e.contains("telescope configuration") && e.contains("a, b, c, d"),
            "{e}"
        );
    }

    #[test]
    fn vla_site_longitude_and_latitude() {
        // VLA: 107.618 deg W, 34.079 deg N geodetic (geocentric ~33.9 deg).
        let a = vla('a').unwrap();
        assert!((a.longitude_rad().to_degrees() + 107.6).abs() < 0.1);
        let lat = a.latitude_rad().to_degrees();
        assert!((lat - 33.9).abs() < 0.3, "latitude {lat}");
    }

    #[test]
    fn vla_max_baselines_have_the_right_scale() {
        let amax = vla('a').unwrap().max_baseline_m();
        let dmax = vla('d').unwrap().max_baseline_m();
        // A: 36.4 km, D: 1.03 km nominal.
        assert!((30e3..40e3).contains(&amax), "A max baseline {amax}");
        assert!((0.8e3..1.2e3).contains(&dmax), "D max baseline {dmax}");
    }

    #[test]
    fn parse_errors_name_the_line() {
        let text = "#X Y Z dish\n1 2 3 25\n4 5 six 25\n";
        let e = parse_itrf_table(text, "bad.txt").unwrap_err().to_string();
        assert!(
            e.contains("bad.txt") && e.contains("line 3") && e.contains("Z"),
            "{e}"
        );
        // Stations from the fifth column, else numbered.
        assert_eq!(parse_itrf_table("1 2 3 25 W01\n4 5 6 25 E02 ALT-AZ\n", "named").unwrap().stations, ["W01", "E02"]);
        assert_eq!(parse_itrf_table("1 2 3 25\n4 5 6 25\n", "bare").unwrap().stations, ["00", "01"]);
        let e = parse_itrf_table("1 2 3\n", "short.txt")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 1") && e.contains("4 columns"), "{e}");
        let e = parse_itrf_table("# only a header\n1 2 3 25\n", "one")
            .unwrap_err()
            .to_string();
        assert!(e.contains("at least 2 antennas"), "{e}");
        let e = parse_itrf_table("1 2 3 25\n4 5 6 -1\n", "neg")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 2") && e.contains("positive"), "{e}");
    }

    #[test]
    fn track_sizes_times_and_ordering() {
        let a = vla('c').unwrap();
        let spec = TrackSpec {
            dec_rad: 0.5,
            hour_angle_span_h: 1.0,
            integration_s: 60.0,
        };
        let t = uvw_tracks(&a, &spec).unwrap();
        assert_eq!(t.len(), 60 * 351);
        assert_eq!(t.time_s[0], 30.0);
        assert_eq!(t.time_s[t.len() - 1], 3570.0);
        assert_eq!((t.antenna1[0], t.antenna2[0]), (0, 1));
        assert_eq!((t.antenna1[350], t.antenna2[350]), (25, 26));
        assert!(t.antenna1.iter().zip(&t.antenna2).all(|(i, j)| i < j));
        // A span shorter than one integration still gives one sample.
        let short = TrackSpec {
            integration_s: 1e6,
            ..spec
        };
        assert_eq!(uvw_tracks(&a, &short).unwrap().len(), 351);
        let bad = TrackSpec {
            integration_s: 0.0,
            ..spec
        };
        assert!(uvw_tracks(&a, &bad).is_err());
    }

    #[test]
    fn declinations_that_never_rise_are_refused() {
        let a = vla('a').unwrap();
        let lat = a.latitude_rad().to_degrees();
        for dec_deg in [-90.0f64, -70.0, lat - 90.0 - 0.1] {
            let spec = TrackSpec { dec_rad: dec_deg.to_radians(), hour_angle_span_h: 1.0, integration_s: 600.0 };
            let e = uvw_tracks(&a, &spec).unwrap_err().to_string();
            assert!(e.contains("declination") && e.contains("never rises") && e.contains("vla-a") && e.contains("above -56"), "{e}");
        }
        assert!(a.check_rises((lat - 90.0 + 0.1).to_radians()).is_ok());
        // A southern site sees the south pole, not the north one.
        let south = Array { name: "south".into(), positions_itrf: a.positions_itrf.iter().map(|p| [p[0], p[1], -p[2]]).collect(), ..a };
        assert!(south.check_rises(-FRAC_PI_2).is_ok());
        assert!(south.check_rises(FRAC_PI_2).unwrap_err().to_string().contains("below 56"));
    }

    #[test]
    fn projection_preserves_baseline_length() {
        let a = vla('a').unwrap();
        for dec_deg in [-30.0f64, 5.0, 34.0, 60.0, 90.0] {
            let spec = TrackSpec {
                dec_rad: dec_deg.to_radians(),
                hour_angle_span_h: 8.0,
                integration_s: 600.0,
            };
            let t = uvw_tracks(&a, &spec).unwrap();
            for k in 0..t.len() {
                let b = norm3(baseline(&a, t.antenna1[k], t.antenna2[k]));
                let r = norm3([t.u_m[k], t.v_m[k], t.w_m[k]]);
                assert!(
                    (r - b).abs() <= 1e-6 * b,
                    "dec {dec_deg}: |uvw| {r} vs |B| {b}"
                );
            }
        }
    }

    #[test]
    fn pole_source_has_w_equal_bz_and_circular_tracks() {
        let a = vla('b').unwrap();
        let spec = TrackSpec {
            dec_rad: FRAC_PI_2,
            hour_angle_span_h: 12.0,
            integration_s: 300.0,
        };
        let t = uvw_tracks(&a, &spec).unwrap();
        for k in 0..t.len() {
            let [bx, by, bz] = baseline(&a, t.antenna1[k], t.antenna2[k]);
            let scale = norm3([bx, by, bz]);
            assert!((t.w_m[k] - bz).abs() <= 1e-9 * scale);
            let r2 = t.u_m[k] * t.u_m[k] + t.v_m[k] * t.v_m[k];
            assert!((r2 - (bx * bx + by * by)).abs() <= 1e-9 * scale * scale);
        }
        // One baseline over 12 h: a half circle centred on the origin, the angle sweeping
        // ~180 deg (12 h of time is 12.03 h of hour angle) at a uniform rate.
        let b = 5; // baseline (0, 6)
        let n_bl = a.n_baselines();
        let angles: Vec<f64> = (0..spec.n_times())
            .map(|k| t.v_m[k * n_bl + b].atan2(t.u_m[k * n_bl + b]))
            .collect();
        let mut steps: Vec<f64> = angles
            .windows(2)
            .map(|w| {
                let mut d = w[1] - w[0];
                if d > PI {
                    d -= 2.0 * PI
                }
                if d < -PI {
                    d += 2.0 * PI
                }
                d
            })
            .collect();
        // n samples span n - 1 steps; the observation covers n integrations.
        let swept: f64 = steps.iter().sum::<f64>().abs() + steps[0].abs();
        assert!(
            (swept.to_degrees() - 180.0 * 1.0027).abs() < 0.1,
            "swept {}",
            swept.to_degrees()
        );
        steps.sort_by(f64::total_cmp);
        assert!(
            (steps[0] - steps[steps.len() - 1]).abs() < 1e-9,
            "uniform angular rate"
        );
    }

    #[test]
    fn transit_is_at_the_centre_of_the_track() {
        // The track is centred on transit: the two middle samples have opposite local hour
        // angles, and u follows the formula with H = H_local - east longitude.
        let a = vla('d').unwrap();
        let spec = TrackSpec {
            dec_rad: 0.7,
            hour_angle_span_h: 2.0,
            integration_s: 60.0,
        };
        let t = uvw_tracks(&a, &spec).unwrap();
        let n_bl = a.n_baselines();
        // Samples 59 and 60 straddle transit symmetrically (t = 3570 s and 3630 s).
        let h_a = (t.time_s[59 * n_bl] - 3600.0) * SIDEREAL_PER_SOLAR * 2.0 * PI / 86400.0;
        let h_b = (t.time_s[60 * n_bl] - 3600.0) * SIDEREAL_PER_SOLAR * 2.0 * PI / 86400.0;
        assert!((h_a + h_b).abs() < 1e-15);
        let [bx, by, _] = baseline(&a, 0, 1);
        let gh = h_a - a.longitude_rad();
        assert!((t.u_m[59 * n_bl] - (gh.sin() * bx + gh.cos() * by)).abs() < 1e-9);
    }

    #[test]
    fn rotate_uv_rotates_and_keeps_lengths() {
        let a = vla('c').unwrap();
        let spec = TrackSpec {
            dec_rad: 0.3,
            hour_angle_span_h: 1.0,
            integration_s: 300.0,
        };
        let orig = uvw_tracks(&a, &spec).unwrap();
        let mut t = orig.clone();
        rotate_uv(&mut t, FRAC_PI_2);
        for k in 0..t.len() {
            assert!((t.u_m[k] + orig.v_m[k]).abs() < 1e-9);
            assert!((t.v_m[k] - orig.u_m[k]).abs() < 1e-9);
            assert_eq!(t.w_m[k], orig.w_m[k]);
        }
        rotate_uv(&mut t, 0.7);
        assert!((t.max_uv_m() - orig.max_uv_m()).abs() < 1e-6);
    }
}
