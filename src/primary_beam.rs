//! Published Stokes-I power beams of single dishes, for primary-beam corrected images: the
//! VLA's polynomial beams (Perley 2016, EVLA Memo 195) and MeerKAT's L-band cosine-squared
//! beam (Mauch et al. 2020). A beam is circularly symmetric about the pointing centre and
//! normalised to 1 there; it is evaluated as a function of the angular distance from it.
//!
//! What the caller knows of the observation (its telescope, its frequency) is given as
//! values: this module knows nothing of files, options or metadata keys.

use std::f64::consts::PI;

/// A telescope with a published beam model here.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BeamTelescope {
    Vla,
    MeerKat,
}

impl BeamTelescope {
    /// The telescopes with a beam here, as their data name them.
    pub const ALL: [BeamTelescope; 2] = [BeamTelescope::Vla, BeamTelescope::MeerKat];

    pub fn name(self) -> &'static str {
        match self {
            BeamTelescope::Vla => "VLA",
            BeamTelescope::MeerKat => "MeerKAT",
        }
    }
}

/// Below this beam value a primary-beam corrected image is blanked (NaN), by default. The
/// published models describe the main lobe, fitted to measurements that reach down to a few
/// per cent; dividing by less than a tenth multiplies the noise more than tenfold. (WSClean's
/// `-primary-beam-limit` defaults to 0.005 with EveryBeam's beams; CASA's `pblimit` to 0.2.)
pub const DEFAULT_LIMIT: f64 = 0.1;

/// One observation's power beam: a model at one frequency.
#[derive(Clone, Debug, PartialEq)]
pub struct PrimaryBeam {
    model: Model,
    frequency_hz: f64,
}

#[derive(Clone, Debug, PartialEq)]
enum Model {
    /// EVLA Memo 195: A(x) = 1 + a x^2 + b x^4 + c x^6 with x the distance
    /// from the pointing centre in arcmin times the frequency in GHz; the coefficients of the
    /// tabulated frequency used, and where the polynomial first reaches zero (x), beyond which
    /// it no longer describes the beam and the beam is taken as 0.
    VlaPolynomial { band: &'static str, table_mhz: f64, coefficients: [f64; 3], null_x: f64 },
    /// Mauch et al. 2020: A(rho) = [cos(1.189 pi rho / theta) / (1 - 4 (1.189 rho / theta)^2)]^2
    /// with theta the half-power width (radians) at the frequency.
    MeerKatCosine { fwhm_rad: f64 },
}

/// The VLA's receiver bands (GHz) where the memo tabulates the beam.
const VLA_BANDS: &[(&str, f64, f64)] = &[
    ("L", 1.0, 2.0),
    ("S", 2.0, 4.0),
    ("C", 4.0, 8.0),
    ("X", 8.0, 12.0),
    ("Ku", 12.0, 18.0),
    ("K", 18.0, 26.5),
    ("Ka", 26.5, 40.0),
    ("Q", 40.0, 50.0),
];

/// EVLA Memo 195 (R. Perley 2016, "Jansky Very Large Array Primary Beam Characteristics"),
/// the tables of Stokes-I polynomial coefficients per frequency from L to Q band: (MHz,
/// a x 1e3, b x 1e7, c x 1e10), as the memo prints them and CASA's `PBMath1DEVLA`
/// (which EveryBeam, and so WSClean, uses) transcribes them. One row of the X-band table,
/// between 10948 and 11180 MHz, is read by CASA as a second 10052 MHz (which overwrites the
/// first); here it is taken as 11052 MHz, its place in the table. The memo's P-band fits are
/// left out: several have a positive minimum instead of a null, so that where their main lobe
/// ends is not defined by the fit.
#[rustfmt::skip]
const VLA_TABLE: &[(f64, f64, f64, f64)] = &[
    // L
    (1040.0, -1.529, 8.69, -1.88), (1104.0, -1.486, 8.15, -1.68), (1168.0, -1.439, 7.53, -1.45),
    (1232.0, -1.450, 7.87, -1.63), (1296.0, -1.428, 7.62, -1.54), (1360.0, -1.449, 8.02, -1.74),
    (1424.0, -1.462, 8.23, -1.83), (1488.0, -1.455, 7.92, -1.63), (1552.0, -1.435, 7.54, -1.49),
    (1680.0, -1.443, 7.74, -1.57), (1744.0, -1.462, 8.02, -1.69), (1808.0, -1.488, 8.38, -1.83),
    (1872.0, -1.486, 8.26, -1.75), (1936.0, -1.459, 7.93, -1.62), (2000.0, -1.508, 8.31, -1.68),
    // S
    (2052.0, -1.429, 7.52, -1.47), (2180.0, -1.389, 7.06, -1.33), (2436.0, -1.377, 6.90, -1.27),
    (2564.0, -1.381, 6.92, -1.26), (2692.0, -1.402, 7.23, -1.40), (2820.0, -1.433, 7.62, -1.54),
    (2948.0, -1.433, 7.46, -1.42), (3052.0, -1.467, 8.05, -1.70), (3180.0, -1.497, 8.38, -1.80),
    (3308.0, -1.504, 8.37, -1.77), (3436.0, -1.521, 8.63, -1.88), (3564.0, -1.505, 8.37, -1.75),
    (3692.0, -1.521, 8.51, -1.79), (3820.0, -1.534, 8.57, -1.77), (3948.0, -1.516, 8.30, -1.66),
    // C
    (4052.0, -1.406, 7.41, -1.48), (4180.0, -1.385, 7.09, -1.36), (4308.0, -1.380, 7.08, -1.37),
    (4436.0, -1.362, 6.95, -1.35), (4564.0, -1.365, 6.92, -1.31), (4692.0, -1.339, 6.56, -1.17),
    (4820.0, -1.371, 7.06, -1.40), (4948.0, -1.358, 6.91, -1.34), (5052.0, -1.360, 6.91, -1.33),
    (5180.0, -1.353, 6.74, -1.25), (5308.0, -1.359, 6.82, -1.27), (5436.0, -1.380, 7.05, -1.37),
    (5564.0, -1.376, 6.99, -1.31), (5692.0, -1.405, 7.39, -1.47), (5820.0, -1.394, 7.29, -1.45),
    (5948.0, -1.428, 7.57, -1.57), (6052.0, -1.445, 7.68, -1.50), (6148.0, -1.422, 7.38, -1.38),
    (6308.0, -1.463, 7.94, -1.62), (6436.0, -1.478, 8.22, -1.74), (6564.0, -1.473, 8.00, -1.62),
    (6692.0, -1.455, 7.76, -1.53), (6820.0, -1.487, 8.22, -1.72), (6948.0, -1.472, 8.05, -1.67),
    (7052.0, -1.470, 8.01, -1.64), (7180.0, -1.503, 8.50, -1.84), (7308.0, -1.482, 8.19, -1.72),
    (7436.0, -1.498, 8.22, -1.66), (7564.0, -1.490, 8.18, -1.66), (7692.0, -1.481, 7.98, -1.56),
    (7820.0, -1.474, 7.94, -1.57), (7948.0, -1.448, 7.69, -1.51),
    // X
    (8052.0, -1.403, 7.21, -1.37), (8180.0, -1.398, 7.10, -1.32), (8308.0, -1.402, 7.16, -1.35),
    (8436.0, -1.400, 7.12, -1.32), (8564.0, -1.391, 6.95, -1.25), (8692.0, -1.409, 7.34, -1.49),
    (8820.0, -1.410, 7.36, -1.45), (8948.0, -1.410, 7.34, -1.43), (9052.0, -1.403, 7.20, -1.36),
    (9180.0, -1.396, 7.09, -1.31), (9308.0, -1.432, 7.68, -1.55), (9436.0, -1.414, 7.43, -1.47),
    (9564.0, -1.416, 7.45, -1.47), (9692.0, -1.406, 7.26, -1.39), (9820.0, -1.412, 7.36, -1.43),
    (9948.0, -1.409, 7.29, -1.39), (10052.0, -1.421, 7.46, -1.45), (10180.0, -1.409, 7.25, -1.36),
    (10308.0, -1.402, 7.13, -1.31), (10436.0, -1.399, 7.09, -1.29), (10564.0, -1.413, 7.37, -1.43),
    (10692.0, -1.412, 7.34, -1.41), (10820.0, -1.401, 7.12, -1.31), (10948.0, -1.401, 7.12, -1.31),
    (11052.0, -1.401, 7.12, -1.31), (11180.0, -1.394, 6.99, -1.24), (11308.0, -1.394, 7.01, -1.26),
    (11436.0, -1.391, 6.94, -1.22), (11564.0, -1.389, 6.92, -1.22), (11692.0, -1.386, 6.80, -1.15),
    (11820.0, -1.391, 6.88, -1.19), (11948.0, -1.399, 6.97, -1.22),
    // Ku
    (12052.0, -1.399, 7.17, -1.34), (12180.0, -1.392, 7.07, -1.31), (12308.0, -1.393, 7.19, -1.38),
    (12436.0, -1.393, 7.20, -1.40), (12564.0, -1.395, 7.19, -1.38), (12692.0, -1.397, 7.20, -1.37),
    (12820.0, -1.388, 7.06, -1.32), (12948.0, -1.397, 7.18, -1.36), (13052.0, -1.400, 7.27, -1.40),
    (13180.0, -1.406, 7.44, -1.50), (13308.0, -1.403, 7.37, -1.47), (13436.0, -1.392, 7.08, -1.31),
    (13564.0, -1.384, 6.94, -1.24), (13692.0, -1.382, 6.95, -1.25), (13820.0, -1.376, 6.88, -1.24),
    (13948.0, -1.384, 6.98, -1.28), (14052.0, -1.400, 7.36, -1.48), (14180.0, -1.397, 7.29, -1.45),
    (14308.0, -1.399, 7.32, -1.45), (14436.0, -1.396, 7.25, -1.42), (14564.0, -1.393, 7.20, -1.39),
    (14692.0, -1.384, 7.03, -1.31), (14820.0, -1.388, 7.06, -1.32), (14948.0, -1.393, 7.16, -1.37),
    (15052.0, -1.402, 7.38, -1.48), (15180.0, -1.407, 7.47, -1.53), (15308.0, -1.406, 7.41, -1.48),
    (15436.0, -1.399, 7.31, -1.44), (15564.0, -1.397, 7.28, -1.43), (15692.0, -1.401, 7.35, -1.46),
    (15820.0, -1.402, 7.34, -1.45), (15948.0, -1.399, 7.30, -1.44), (16052.0, -1.419, 7.59, -1.54),
    (16180.0, -1.419, 7.59, -1.52), (16308.0, -1.412, 7.40, -1.44), (16436.0, -1.407, 7.32, -1.40),
    (16564.0, -1.408, 7.32, -1.41), (16692.0, -1.410, 7.34, -1.40), (16820.0, -1.407, 7.27, -1.38),
    (16948.0, -1.423, 7.63, -1.55), (17052.0, -1.437, 7.87, -1.66), (17180.0, -1.438, 7.84, -1.64),
    (17308.0, -1.445, 7.98, -1.71), (17436.0, -1.452, 8.10, -1.77), (17564.0, -1.458, 8.13, -1.70),
    (17692.0, -1.456, 8.06, -1.72), (17820.0, -1.453, 8.00, -1.68), (17948.0, -1.452, 7.99, -1.69),
    // K
    (19052.0, -1.419, 7.56, -1.53), (19180.0, -1.426, 7.70, -1.59), (19308.0, -1.433, 7.82, -1.64),
    (19436.0, -1.429, 7.73, -1.60), (19564.0, -1.427, 7.70, -1.59), (19692.0, -1.425, 7.65, -1.56),
    (19820.0, -1.430, 7.76, -1.62), (19948.0, -1.434, 7.81, -1.63), (21052.0, -1.448, 8.05, -1.73),
    (21180.0, -1.436, 7.84, -1.63), (21308.0, -1.441, 7.94, -1.68), (21436.0, -1.439, 7.89, -1.66),
    (21564.0, -1.442, 7.96, -1.69), (21692.0, -1.435, 7.81, -1.61), (21820.0, -1.442, 7.92, -1.66),
    (21948.0, -1.439, 7.82, -1.61), (23052.0, -1.401, 7.21, -1.37), (23180.0, -1.408, 7.31, -1.41),
    (23308.0, -1.407, 7.28, -1.39), (23436.0, -1.407, 7.31, -1.41), (23564.0, -1.419, 7.47, -1.47),
    (23692.0, -1.395, 7.10, -1.33), (23820.0, -1.413, 7.36, -1.42), (23948.0, -1.402, 7.21, -1.36),
    (25052.0, -1.402, 7.17, -1.31), (25180.0, -1.432, 7.73, -1.58), (25308.0, -1.407, 7.22, -1.33),
    (25436.0, -1.417, 7.43, -1.45), (25564.0, -1.422, 7.52, -1.48), (25692.0, -1.427, 7.59, -1.52),
    (25820.0, -1.416, 7.42, -1.44), (25948.0, -1.422, 7.46, -1.45),
    // Ka
    (28052.0, -1.444, 7.61, -1.44), (28180.0, -1.439, 7.54, -1.42), (28308.0, -1.457, 7.87, -1.58),
    (28436.0, -1.457, 7.90, -1.60), (28564.0, -1.455, 7.87, -1.59), (28692.0, -1.458, 7.88, -1.58),
    (28820.0, -1.453, 7.81, -1.56), (28948.0, -1.460, 7.98, -1.64), (31052.0, -1.415, 7.44, -1.44),
    (31180.0, -1.408, 7.26, -1.37), (31308.0, -1.413, 7.28, -1.36), (31436.0, -1.394, 7.07, -1.30),
    (31564.0, -1.404, 7.23, -1.37), (31692.0, -1.427, 7.48, -1.44), (31820.0, -1.418, 7.48, -1.48),
    (31948.0, -1.413, 7.37, -1.42), (34052.0, -1.42, 7.28, -1.34), (34180.0, -1.46, 7.77, -1.53),
    (34308.0, -1.42, 7.41, -1.42), (34436.0, -1.42, 7.36, -1.39), (34564.0, -1.46, 7.76, -1.52),
    (34692.0, -1.42, 7.34, -1.38), (34820.0, -1.42, 7.34, -1.39), (34948.0, -1.45, 7.68, -1.49),
    (37152.0, -1.42, 7.47, -1.44), (37280.0, -1.41, 7.35, -1.40), (37408.0, -1.45, 7.65, -1.46),
    (37536.0, -1.41, 7.13, -1.29), (37664.0, -1.41, 7.30, -1.38), (37792.0, -1.45, 7.75, -1.50),
    (37820.0, -1.45, 7.68, -1.49), (38048.0, -1.41, 7.38, -1.43),
    // Q
    (41052.0, -1.453, 7.69, -1.47), (41180.0, -1.479, 8.03, -1.61), (41308.0, -1.475, 7.97, -1.58),
    (41436.0, -1.451, 7.73, -1.51), (41564.0, -1.450, 7.71, -1.51), (41692.0, -1.465, 7.79, -1.49),
    (41820.0, -1.460, 7.73, -1.47), (41948.0, -1.434, 7.47, -1.40), (43052.0, -1.428, 7.40, -1.38),
    (43180.0, -1.418, 7.29, -1.34), (43308.0, -1.433, 7.49, -1.43), (43436.0, -1.438, 7.55, -1.45),
    (43564.0, -1.419, 7.36, -1.40), (43692.0, -1.397, 7.13, -1.33), (43820.0, -1.423, 7.39, -1.40),
    (43948.0, -1.452, 7.68, -1.47),
];

/// Mauch et al. 2020 (ApJ 888, 61), eqs. 3 and 4: MeerKAT's L-band half-power width is
/// 57.5 arcmin at 1.5 GHz, inversely proportional to frequency; the cosine-taper constant
/// 1.189 puts the half-power point at rho = theta / 2.
const MEERKAT_FWHM_ARCMIN_AT_1_5_GHZ: f64 = 57.5;
const MEERKAT_TAPER: f64 = 1.189;
/// MeerKAT's L band (GHz), where the model was measured.
const MEERKAT_L_BAND: (f64, f64) = (0.856, 1.712);

const ARCMIN_PER_RAD: f64 = 60.0 * 180.0 / PI;

impl PrimaryBeam {
    /// The beam of `telescope` at `frequency_hz` (the observation's centre frequency), or why
    /// there is none (a frequency outside the bands the model covers).
    pub fn new(telescope: BeamTelescope, frequency_hz: f64) -> Result<PrimaryBeam, String> {
        if !(frequency_hz.is_finite() && frequency_hz > 0.0) {
            return Err(format!("expected a positive frequency, got {frequency_hz} Hz"));
        }
        let ghz = frequency_hz * 1e-9;
        let model = match telescope {
            BeamTelescope::Vla => {
                if !VLA_BANDS.iter().any(|(_, low, high)| (*low..=*high).contains(&ghz)) {
                    let bands: Vec<String> = VLA_BANDS.iter().map(|(b, lo, hi)| format!("{b} {lo}-{hi}")).collect();
                    return Err(format!("{ghz} GHz is in none of the VLA bands EVLA Memo 195 tabulates (GHz: {})", bands.join(", ")));
                }
                // The nearest frequency the memo tabulates, as CASA and EveryBeam choose.
                let &(table_mhz, a, b, c) = VLA_TABLE
                    .iter()
                    .min_by(|x, y| (x.0 - ghz * 1e3).abs().total_cmp(&(y.0 - ghz * 1e3).abs()))
                    .expect("the table has rows");
                let band = VLA_BANDS.iter().find(|(_, low, high)| (*low..=*high).contains(&(table_mhz * 1e-3))).map_or("?", |(b, ..)| b);
                let coefficients = [a * 1e-3, b * 1e-7, c * 1e-10];
                Model::VlaPolynomial { band, table_mhz, coefficients, null_x: first_null(&coefficients) }
            }
            BeamTelescope::MeerKat => {
                let (low, high) = MEERKAT_L_BAND;
                if !(low..=high).contains(&ghz) {
                    return Err(format!("{ghz} GHz is outside MeerKAT's L band ({low}-{high} GHz), the one band Mauch et al. 2020 model"));
                }
                Model::MeerKatCosine { fwhm_rad: MEERKAT_FWHM_ARCMIN_AT_1_5_GHZ / ARCMIN_PER_RAD * (1.5 / ghz) }
            }
        };
        Ok(PrimaryBeam { model, frequency_hz })
    }

    /// The power beam at angular distance `rho_rad` from the pointing centre (1 there).
    pub fn power(&self, rho_rad: f64) -> f64 {
        match &self.model {
            Model::VlaPolynomial { coefficients, null_x, .. } => {
                let x = rho_rad * ARCMIN_PER_RAD * self.frequency_hz * 1e-9;
                if x >= *null_x {
                    return 0.0;
                }
                polynomial(coefficients, x * x).clamp(0.0, 1.0)
            }
            Model::MeerKatCosine { fwhm_rad } => {
                let k = MEERKAT_TAPER * rho_rad / fwhm_rad;
                let denominator = 1.0 - 4.0 * k * k;
                // At k = 1/2 numerator and denominator vanish together: the limit is pi / 4.
                let amplitude = if denominator.abs() < 1e-9 { PI / 4.0 } else { (PI * k).cos() / denominator };
                amplitude * amplitude
            }
        }
    }

    /// The beam on an image of `size` x `size` pixels of `pixel_rad` in the SIN projection
    /// about the pointing centre (taken to be the phase centre, at the reference pixel
    /// `size / 2`), in FITS storage order: pixel (x, y) lies at l = (x - size/2) pixel,
    /// m = (y - size/2) pixel, at the true angular distance asin(sqrt(l^2 + m^2)); a pixel
    /// beyond the horizon (l^2 + m^2 > 1) has beam 0.
    pub fn image(&self, size: usize, pixel_rad: f64) -> Vec<f64> {
        let centre = (size / 2) as f64;
        let mut out = Vec::with_capacity(size * size);
        for y in 0..size {
            let m = (y as f64 - centre) * pixel_rad;
            for x in 0..size {
                let l = (x as f64 - centre) * pixel_rad;
                let s = (l * l + m * m).sqrt();
                out.push(if s <= 1.0 { self.power(s.asin()) } else { 0.0 });
            }
        }
        out
    }

    /// What the beam is, for headers and logs (the model, its source, and for the VLA the band
    /// and the tabulated frequency used), short enough for a FITS card's value.
    pub fn description(&self) -> String {
        match &self.model {
            Model::VlaPolynomial { band, table_mhz, .. } => {
                format!("VLA {band} band, EVLA Memo 195 (Perley 2016) at {table_mhz} MHz")
            }
            Model::MeerKatCosine { fwhm_rad } => {
                format!("MeerKAT L band, Mauch et al. 2020, FWHM {:.2} arcmin", fwhm_rad * ARCMIN_PER_RAD)
            }
        }
    }
}

/// 1 + a y + b y^2 + c y^3 at y = x^2.
fn polynomial(c: &[f64; 3], y: f64) -> f64 {
    1.0 + y * (c[0] + y * (c[1] + y * c[2]))
}

/// The smallest x > 0 where the polynomial reaches zero: the edge of the main lobe, beyond
/// which a fit to it means nothing. Found by stepping out in x (arcmin GHz) and bisecting the
/// step that changes sign.
fn first_null(c: &[f64; 3]) -> f64 {
    const STEP: f64 = 0.25;
    const FAR: f64 = 200.0;
    let mut x = 0.0;
    while x < FAR {
        let next = x + STEP;
        if polynomial(c, next * next) <= 0.0 {
            let (mut lo, mut hi) = (x, next);
            for _ in 0..60 {
                let mid = 0.5 * (lo + hi);
                if polynomial(c, mid * mid) > 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            return hi;
        }
        x = next;
    }
    FAR
}

/// `image / beam` where the beam reaches `limit`, NaN elsewhere (the blanking of a primary-beam
/// corrected image, as WSClean's below its `-primary-beam-limit`).
pub fn correct(image: &[f64], beam: &[f64], limit: f64) -> Vec<f64> {
    image.iter().zip(beam).map(|(&v, &b)| if b >= limit && b > 0.0 { v / b } else { f64::NAN }).collect()
}

/// Checks a blanking limit: a beam value in (0, 1).
pub fn check_limit(limit: f64) -> Result<(), String> {
    if limit.is_finite() && limit > 0.0 && limit < 1.0 {
        Ok(())
    } else {
        Err(format!("expected a beam level between 0 and 1 (exclusive), got {limit}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ARCMIN: f64 = PI / (180.0 * 60.0);

    /// The memo's form, written out term by term from its table's printed coefficients.
    fn memo(a: f64, b: f64, c: f64, r_arcmin: f64, ghz: f64) -> f64 {
        let x = r_arcmin * ghz;
        1.0 + a * 1e-3 * x.powi(2) + b * 1e-7 * x.powi(4) + c * 1e-10 * x.powi(6)
    }

    /// Mauch et al. 2020 eqs. 3-4, written out.
    fn mauch(rho_arcmin: f64, ghz: f64) -> f64 {
        let theta = 57.5 * 1.5 / ghz;
        let k = 1.189 * rho_arcmin / theta;
        ((1.189 * PI * rho_arcmin / theta).cos() / (1.0 - 4.0 * k * k)).powi(2)
    }

    /// The radius (arcmin) where `f` falls to one half, by bisection.
    fn half_power_radius(f: impl Fn(f64) -> f64, far: f64) -> f64 {
        let (mut lo, mut hi) = (0.0, far);
        for _ in 0..80 {
            let mid = 0.5 * (lo + hi);
            if f(mid) > 0.5 { lo = mid } else { hi = mid }
        }
        lo
    }

    #[test]
    fn vla_beams_are_the_memos_polynomials_at_the_nearest_tabulated_frequency() {
        // 1.4 GHz: the L-band row of 1424 MHz (the nearest), evaluated at the image's frequency.
        let beam = PrimaryBeam::new(BeamTelescope::Vla, 1.4e9).unwrap();
        assert!(beam.description().contains("L band") && beam.description().contains("1424 MHz"), "{}", beam.description());
        assert!(beam.description().len() <= 68 && PrimaryBeam::new(BeamTelescope::MeerKat, 0.9e9).unwrap().description().len() <= 68);
        for r in [0.0, 5.0, 10.0, 15.0, 20.0, 25.0] {
            let want = memo(-1.462, 8.23, -1.83, r, 1.4);
            assert!((beam.power(r * ARCMIN) - want).abs() < 1e-12, "r = {r}': {} against {want}", beam.power(r * ARCMIN));
        }
        // 6.04 GHz (C band): the 6052 MHz row; 34.1 GHz (Ka): the 34052 MHz row; 2.01 GHz:
        // L band's last row (2000 MHz), nearer than S band's first.
        let c = PrimaryBeam::new(BeamTelescope::Vla, 6.04e9).unwrap();
        assert!((c.power(4.0 * ARCMIN) - memo(-1.445, 7.68, -1.50, 4.0, 6.04)).abs() < 1e-12);
        let ka = PrimaryBeam::new(BeamTelescope::Vla, 34.1e9).unwrap().description();
        assert!(ka.contains("Ka band") && ka.contains("34052 MHz"), "{ka}");
        let edge = PrimaryBeam::new(BeamTelescope::Vla, 2.01e9).unwrap().description();
        assert!(edge.contains("L band") && edge.contains("2000 MHz"), "{edge}");
    }

    #[test]
    fn the_vla_half_power_width_is_the_memos() {
        // The memo: FWHM close to 42 arcmin / nu(GHz) (the L-band beams' half-power radius is
        // near x = 21 arcmin GHz), and at every band within a few per cent of it.
        for ghz in [1.4, 3.0, 6.0, 10.0, 15.0, 22.0, 33.0, 45.0] {
            let beam = PrimaryBeam::new(BeamTelescope::Vla, ghz * 1e9).unwrap();
            let fwhm = 2.0 * half_power_radius(|r| beam.power(r * ARCMIN), 120.0 / ghz);
            assert!((fwhm * ghz / 42.0 - 1.0).abs() < 0.05, "{ghz} GHz: FWHM {fwhm}' = {}'/nu", fwhm * ghz);
        }
        let beam = PrimaryBeam::new(BeamTelescope::Vla, 1.424e9).unwrap();
        let memo_radius = half_power_radius(|r| memo(-1.462, 8.23, -1.83, r, 1.424), 60.0);
        let ours = half_power_radius(|r| beam.power(r * ARCMIN), 60.0);
        assert!((ours - memo_radius).abs() < 1e-9, "{ours} against {memo_radius}");
    }

    #[test]
    fn the_vla_beam_is_zero_beyond_its_first_null_and_falls_to_it() {
        for &(mhz, ..) in VLA_TABLE {
            let beam = PrimaryBeam::new(BeamTelescope::Vla, mhz * 1e6).unwrap();
            let Model::VlaPolynomial { null_x, .. } = beam.model else { unreachable!() };
            assert!(null_x > 30.0 && null_x < 100.0, "{mhz} MHz: first null at x = {null_x}");
            let mut last = 1.0;
            for i in 0..=400 {
                let r = 0.3 * i as f64 / (mhz * 1e-3) * ARCMIN;
                let p = beam.power(r);
                assert!((0.0..=1.0).contains(&p) && p <= last + 1e-12, "{mhz} MHz: not falling at {i}: {p} after {last}");
                last = p;
            }
            assert_eq!(last, 0.0, "{mhz} MHz: the beam does not reach zero by x = 120");
        }
    }

    #[test]
    fn meerkat_is_mauch_et_al_and_its_width_is_theirs() {
        let beam = PrimaryBeam::new(BeamTelescope::MeerKat, 1.28e9).unwrap();
        for r in [0.0, 10.0, 20.0, 33.0, 40.0, 60.0] {
            assert!((beam.power(r * ARCMIN) - mauch(r, 1.28)).abs() < 1e-12, "{r}'");
        }
        // The half-power width: 57.5' at 1.5 GHz, 67.4' at 1.28 GHz.
        let fwhm = 2.0 * half_power_radius(|r| beam.power(r * ARCMIN), 60.0);
        assert!((fwhm - 57.5 * 1.5 / 1.28).abs() < 0.05, "{fwhm}");
        let at_1_5 = PrimaryBeam::new(BeamTelescope::MeerKat, 1.5e9).unwrap();
        assert!((2.0 * half_power_radius(|r| at_1_5.power(r * ARCMIN), 60.0) - 57.5).abs() < 0.05);
        // Continuous through the removable singularity at 1.189 rho / theta = 1/2.
        let theta = 57.5 * 1.5 / 1.28;
        let singular = theta / (2.0 * 1.189) * ARCMIN;
        assert!((beam.power(singular) - (PI / 4.0).powi(2)).abs() < 1e-6);
        assert!((beam.power(singular * (1.0 + 1e-7)) - beam.power(singular)).abs() < 1e-6);
    }

    #[test]
    fn frequencies_outside_the_models_are_refused() {
        for (telescope, hz) in [(BeamTelescope::Vla, 0.7e9), (BeamTelescope::Vla, 0.33e9), (BeamTelescope::Vla, 60e9), (BeamTelescope::MeerKat, 3.0e9), (BeamTelescope::MeerKat, 0.6e9)] {
            let e = PrimaryBeam::new(telescope, hz).unwrap_err();
            assert!(e.contains("GHz"), "{e}");
        }
        assert!(PrimaryBeam::new(BeamTelescope::Vla, f64::NAN).is_err());
    }

    #[test]
    fn the_image_is_the_beam_at_each_pixels_true_distance() {
        let beam = PrimaryBeam::new(BeamTelescope::Vla, 1.4e9).unwrap();
        let (n, pixel) = (64, 30.0 * ARCMIN / 32.0);
        let img = beam.image(n, pixel);
        assert_eq!(img[32 * n + 32], 1.0);
        let (l, m) = (-20.0 * pixel, 11.0 * pixel);
        let want = beam.power((l * l + m * m as f64).sqrt().asin());
        assert_eq!(img[(32 + 11) * n + (32 - 20)], want);
        let corrected = correct(&[2.0, 3.0, 4.0], &[0.5, 0.05, 0.0], DEFAULT_LIMIT);
        assert_eq!(corrected[0], 4.0);
        assert!(corrected[1].is_nan() && corrected[2].is_nan());
        assert!(check_limit(0.0).is_err() && check_limit(1.0).is_err() && check_limit(0.2).is_ok());
    }
}
