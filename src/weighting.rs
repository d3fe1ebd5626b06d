//! Imaging weights: natural, uniform and Briggs (robust), as in the reference implementation
//! and WSClean.
//!
//! The uv plane (in the operator's `[-pi, pi)` coordinates) is cut into `floor(grid_factor * N)`
//! cells per axis and folded onto one half plane (`(u, v) -> (-u, -v)` where `v < 0`, since a
//! real image has Hermitian visibilities). `G_k` is the summed natural weight in visibility k's
//! cell. Briggs: `f2 = (5 * 10^-R)^2 * sum(w) / sum_cells(G^2)` and the imaging weight is
//! `1 / (1 + f2 G_k)`. Uniform: `1 / G_k`.
//!
//! The weights returned multiply the natural weights (they are the squares of the reference
//! code's `nWimag`). One deliberate difference from the reference: its uniform weighting
//! counts visibilities per cell, this one sums natural weights per cell (as WSClean does, and
//! as the Briggs formula's R -> -inf limit does). The two agree when natural weights are equal.
//!
//! uv cuts and tapers ([`UvControls`]: WSClean's minimum and maximum uv distance, Gaussian and
//! Tukey tapers) are applied as WSClean applies them: after the density pass (a sample they cut
//! still counts in the density and in Briggs' `f2`), on the weighting grid (each sample takes
//! the value at its cell's corner nearest `u = -inf, v = 0` in WSClean's orientation), as a
//! factor of the imaging weight ([`UvShape`]). A sample beyond the grid (`|u|` or `|v|` at or
//! beyond the image's Nyquist limit `1 / (2 pixel)`) has imaging weight 0 and is left out of
//! the density, as in WSClean.

use crate::{Error, Result};

/// The Briggs robustness accepted: WSClean and CASA use -2..2, and beyond +-5 the weights are
/// natural or uniform to within 1e-4 (`briggs_limits_are_natural_and_uniform`), so a value
/// outside this range is a mistake (a typo, a value meant for another option).
pub(crate) const ROBUST_RANGE: (f64, f64) = (-5.0, 5.0);

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Weighting {
    Natural,
    Uniform,
    /// Briggs robust weighting with robustness R (-2: near uniform, +2: near natural).
    Briggs { robust: f64 },
    /// The imaging weights given with the data (a table's `imaging_weight` column, the square
    /// of a .mat file's `nWimag`), as the reference uses a file's `nWimag` when told to.
    Given,
}

/// A weighting scheme as a configuration names it (`scheme: briggs`); Briggs takes its
/// robustness from beside it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum WeightingScheme {
    #[serde(alias = "Natural")]
    Natural,
    #[serde(alias = "Uniform")]
    Uniform,
    #[serde(alias = "Briggs", alias = "robust")]
    Briggs,
    #[serde(alias = "Given")]
    Given,
}

impl WeightingScheme {
    /// The scheme as a configuration and a series' manifest name it.
    pub fn name(self) -> &'static str {
        match self {
            WeightingScheme::Natural => "natural",
            WeightingScheme::Uniform => "uniform",
            WeightingScheme::Briggs => "briggs",
            WeightingScheme::Given => "given",
        }
    }

    /// The weighting, with `robust` for Briggs (ignored otherwise).
    pub fn with_robust(self, robust: f64) -> Result<Weighting> {
        match self {
            WeightingScheme::Natural => Ok(Weighting::Natural),
            WeightingScheme::Uniform => Ok(Weighting::Uniform),
            WeightingScheme::Briggs => Weighting::from_name("briggs", robust),
            WeightingScheme::Given => Ok(Weighting::Given),
        }
    }
}

impl Weighting {
    /// The scheme, without its robustness.
    pub fn scheme(&self) -> WeightingScheme {
        match self {
            Weighting::Natural => WeightingScheme::Natural,
            Weighting::Uniform => WeightingScheme::Uniform,
            Weighting::Briggs { .. } => WeightingScheme::Briggs,
            Weighting::Given => WeightingScheme::Given,
        }
    }

    /// Briggs' robustness; `None` for the other schemes.
    pub fn robust(&self) -> Option<f64> {
        match self {
            Weighting::Briggs { robust } => Some(*robust),
            _ => None,
        }
    }

    /// Parse `natural`, `uniform` or `briggs` (with its robustness).
    pub fn from_name(name: &str, robust: f64) -> Result<Weighting> {
        match name.to_ascii_lowercase().as_str() {
            "natural" => Ok(Weighting::Natural),
            "uniform" => Ok(Weighting::Uniform),
            "given" => Ok(Weighting::Given),
            "briggs" | "robust" => {
                let (low, high) = ROBUST_RANGE;
                if !(low..=high).contains(&robust) {
                    return Err(Error::parameter(
                        "robust",
                        format!("expected a Briggs robustness from {low} to {high} (-2: near uniform, 2: near natural; beyond that nothing changes), got {robust}"),
                    ));
                }
                Ok(Weighting::Briggs { robust })
            }
            other => Err(Error::parameter(
                "weighting",
                format!("expected one of natural, uniform, briggs, given (the imaging weights given with the data), got '{other}'"),
            )),
        }
    }

    /// The weighting a user's options ask for, where each may be absent: `None` when neither is
    /// given (the caller's default applies: a series' own), a robustness alone means Briggs,
    /// a scheme alone takes robustness 0. The command line and Python share this reading.
    pub fn from_options(name: Option<&str>, robust: Option<f64>) -> Result<Option<Weighting>> {
        match (name, robust) {
            (None, None) => Ok(None),
            (None, Some(robust)) => Weighting::from_name("briggs", robust).map(Some),
            (Some(name), Some(robust)) => match Weighting::from_name(name, robust)? {
                // A robustness means Briggs: with another scheme it would be dropped unsaid.
                w @ Weighting::Briggs { .. } => Ok(Some(w)),
                other => Err(Error::parameter("robust", format!("a Briggs robustness ({robust}) was given with {other} weighting, which has none: drop it, or ask for briggs"))),
            },
            (Some(name), None) => Weighting::from_name(name, 0.0).map(Some),
        }
    }
}

impl std::fmt::Display for Weighting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Weighting::Natural => write!(f, "natural"),
            Weighting::Uniform => write!(f, "uniform"),
            Weighting::Briggs { robust } => write!(f, "briggs {robust}"),
            Weighting::Given => write!(f, "given"),
        }
    }
}

/// The weighting where neither the request nor a series gives one: Briggs 0, between natural's
/// sensitivity and uniform's resolution, as WSClean's users usually choose.
pub const DEFAULT_WEIGHTING: Weighting = Weighting::Briggs { robust: 0.0 };

/// Default weighting-grid factor (cells per axis / image size), as in the reference.
pub const DEFAULT_GRID_FACTOR: f64 = 2.0;

/// uv cuts and tapers as a request gives them (WSClean's): `None` leaves each out.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct UvControls {
    /// Samples nearer the uv origin than this (wavelengths) are left out.
    pub minuv_l: Option<f64>,
    /// Samples farther from the uv origin than this (wavelengths) are left out.
    pub maxuv_l: Option<f64>,
    /// A Gaussian taper whose image-plane FWHM is this (arcsec):
    /// `exp(-r^2 / (2 s^2))`, `s = sqrt(8 ln 2) / (2 pi FWHM)` wavelengths.
    pub taper_gaussian: Option<f64>,
    /// A Tukey transition this wide (wavelengths) inside `maxuv_l`: the weight falls from 1 at
    /// `maxuv_l - taper_tukey` to 0 at `maxuv_l` as `(1 + cos(pi (r - maxuv_l + taper_tukey) / taper_tukey)) / 2`.
    pub taper_tukey: Option<f64>,
}

impl UvControls {
    /// Whether nothing is cut or tapered.
    pub fn is_empty(&self) -> bool {
        *self == UvControls::default()
    }

    /// An error naming the field of a value out of range: lengths negative or not finite, a
    /// minimum at or above the maximum, a taper not positive, a Tukey transition without the
    /// maximum it ends at or wider than it.
    pub fn check(&self) -> Result<()> {
        let finite = |name: &str, value: Option<f64>, positive: bool, what: &str| -> Result<()> {
            match value {
                Some(x) if !x.is_finite() || x < 0.0 || (positive && x == 0.0) => {
                    Err(Error::parameter(name, format!("expected {what} {}, got {x}", if positive { "> 0" } else { ">= 0" })))
                }
                _ => Ok(()),
            }
        };
        finite("minuv_l", self.minuv_l, false, "a uv distance in wavelengths")?;
        finite("maxuv_l", self.maxuv_l, true, "a uv distance in wavelengths")?;
        finite("taper_gaussian", self.taper_gaussian, true, "the taper's image-plane FWHM in arcsec")?;
        finite("taper_tukey", self.taper_tukey, true, "the width of the Tukey transition in wavelengths")?;
        if let (Some(min), Some(max)) = (self.minuv_l, self.maxuv_l) {
            if min >= max {
                return Err(Error::parameter("minuv_l", format!("expected a minimum uv distance below maxuv_l ({max} wavelengths), got {min}: nothing would remain")));
            }
        }
        match (self.taper_tukey, self.maxuv_l) {
            (Some(_), None) => Err(Error::parameter("taper_tukey", "the Tukey transition ends at maxuv_l: give maxuv_l as well (as WSClean needs)")),
            (Some(width), Some(max)) if width > max => {
                Err(Error::parameter("taper_tukey", format!("expected a transition no wider than maxuv_l ({max} wavelengths), got {width}")))
            }
            _ => Ok(()),
        }
    }

    /// The longest baseline (wavelengths) kept of samples whose longest is `max_uv`.
    pub fn longest_kept(&self, max_uv: f64) -> f64 {
        self.maxuv_l.map_or(max_uv, |m| m.min(max_uv))
    }

    /// The theoretic beam's FWHM (radians) of data whose longest baseline is `max_uv`
    /// wavelengths: 1 / the longest baseline kept, or the Gaussian taper's FWHM where that is
    /// wider (WSClean's theoretic beam).
    pub fn theoretic_beam_rad(&self, max_uv: f64) -> f64 {
        let taper = self.taper_gaussian.map_or(0.0, |fwhm_arcsec| (fwhm_arcsec / 3600.0).to_radians());
        (1.0 / self.longest_kept(max_uv)).max(taper)
    }

    /// The controls given, by the request's field names (`minuv_l 100, taper_gaussian 2`),
    /// empty where none is.
    pub fn describe(&self) -> String {
        [("minuv_l", self.minuv_l), ("maxuv_l", self.maxuv_l), ("taper_gaussian", self.taper_gaussian), ("taper_tukey", self.taper_tukey)]
            .into_iter()
            .filter_map(|(name, value)| value.map(|v| format!("{name} {v}")))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// Why a sample is left out of the image by the uv selection.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Exclusion {
    /// Its `|u|` or `|v|` lies at or beyond the image's Nyquist limit: beyond the grid.
    Beyond,
    /// Nearer the origin than `minuv_l`.
    BelowMin,
    /// Farther than `maxuv_l`.
    AboveMax,
}

/// Whether operator coordinates `(x, y)` lie beyond the grid (`|x|` or `|y|` at or beyond pi:
/// `|u|` or `|v|` at or beyond `1 / (2 pixel)`); not a number is beyond.
pub(crate) fn beyond_grid((x, y): (f64, f64)) -> bool {
    !(x.abs() < std::f64::consts::PI && y.abs() < std::f64::consts::PI)
}

/// [`UvControls`] on a weighting grid of `cells` cells per axis, every length in cells: what a
/// [`WeightRule`] applies, and what travels with it to where a part of the samples is weighted.
/// The default cuts nothing but the samples beyond the grid.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct UvShape {
    /// Cells per axis; 0: no cut or taper.
    cells: usize,
    /// Squared distances (cells^2) below which and above which a sample is cut.
    min_sq: f64,
    max_sq: Option<f64>,
    /// `-1 / (2 s^2)` of the Gaussian taper (cells^-2); 0: none.
    gaussian: f64,
    /// The Tukey transition's outer radius (`maxuv_l`) and width, in cells.
    tukey: Option<(f64, f64)>,
}

impl UvShape {
    /// `uv` (checked) on the weighting grid of a `image_size` image of `pixel_rad` pixels with
    /// `grid_factor` cells per pixel and axis.
    pub fn new(uv: &UvControls, image_size: usize, grid_factor: f64, pixel_rad: f64) -> Result<UvShape> {
        uv.check()?;
        if uv.is_empty() {
            return Ok(UvShape::default());
        }
        let cells = grid_cells(grid_factor, image_size)?;
        // Cells per wavelength: the grid spans 1 / pixel wavelengths.
        let scale = cells as f64 * pixel_rad;
        let min = uv.minuv_l.unwrap_or(0.0) * scale;
        let max = uv.maxuv_l.map(|m| m * scale);
        let gaussian = uv.taper_gaussian.map_or(0.0, |fwhm_arcsec| {
            let fwhm_rad = (fwhm_arcsec / 3600.0).to_radians();
            let s = (8.0 * std::f64::consts::LN_2).sqrt() / (2.0 * std::f64::consts::PI * fwhm_rad) * scale;
            -1.0 / (2.0 * s * s)
        });
        let tukey = uv.taper_tukey.zip(max).map(|(width, max)| (max, width * scale));
        Ok(UvShape { cells, min_sq: min * min, max_sq: max.map(|m| m * m), gaussian, tukey })
    }

    /// Whether only the samples beyond the grid are cut (no control given).
    pub fn is_none(&self) -> bool {
        self.cells == 0
    }

    /// The squared distance (cells^2) from the uv origin of the weighting cell's corner of the
    /// sample at operator coordinates `point` (`x = -2 pi u pixel`, `y = 2 pi v pixel`): folded
    /// onto `v >= 0`, the corner of lower `u` and lower `v`, as WSClean evaluates its cuts and
    /// tapers.
    fn corner_sq(&self, (x, y): (f64, f64)) -> f64 {
        let (x, y) = if y < 0.0 { (-x, -y) } else { (x, y) };
        let n = self.cells as f64;
        let offset = |t: f64| (t / std::f64::consts::TAU * n + 0.5 * n).floor() - 0.5 * n;
        let (du, dv) = (offset(-x), offset(y));
        du * du + dv * dv
    }

    /// Why the sample at `point` is left out, if it is.
    pub(crate) fn exclusion(&self, point: (f64, f64)) -> Option<Exclusion> {
        if beyond_grid(point) {
            return Some(Exclusion::Beyond);
        }
        if self.is_none() {
            return None;
        }
        let d2 = self.corner_sq(point);
        if d2 < self.min_sq {
            Some(Exclusion::BelowMin)
        } else if self.max_sq.is_some_and(|max| d2 > max) {
            Some(Exclusion::AboveMax)
        } else {
            None
        }
    }

    /// The factor of the sample's imaging weight at `point`: 0 where it is cut, the tapers'
    /// product otherwise.
    pub fn factor(&self, point: (f64, f64)) -> f64 {
        if self.exclusion(point).is_some() {
            return 0.0;
        }
        if self.is_none() {
            return 1.0;
        }
        let d2 = self.corner_sq(point);
        let mut factor = if self.gaussian != 0.0 { (d2 * self.gaussian).exp() } else { 1.0 };
        if let Some((outer, width)) = self.tukey {
            let inner = outer - width;
            if d2 > inner * inner {
                factor *= 0.5 * (1.0 + (std::f64::consts::PI * (inner - d2.sqrt()) / width).cos());
            }
        }
        factor
    }
}

/// How many samples the uv selection left out, and why.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct UvCounts {
    pub samples: u64,
    pub beyond: u64,
    pub below_min: u64,
    pub above_max: u64,
}

impl UvCounts {
    /// Counts the sample at `point`.
    pub fn add(&mut self, shape: &UvShape, point: (f64, f64)) {
        self.samples += 1;
        match shape.exclusion(point) {
            Some(Exclusion::Beyond) => self.beyond += 1,
            Some(Exclusion::BelowMin) => self.below_min += 1,
            Some(Exclusion::AboveMax) => self.above_max += 1,
            None => {}
        }
    }

    pub fn kept(&self) -> u64 {
        self.samples - self.beyond - self.below_min - self.above_max
    }

    /// What was left out, in words (`None` where nothing was), on a grid whose Nyquist limit
    /// is `limit_l` wavelengths for `pixel_arcsec` pixels.
    pub fn describe(&self, limit_l: f64, pixel_arcsec: f64) -> Option<String> {
        let mut parts = Vec::new();
        if self.below_min > 0 {
            parts.push(format!("{} below minuv_l", self.below_min));
        }
        if self.above_max > 0 {
            parts.push(format!("{} above maxuv_l", self.above_max));
        }
        if self.beyond > 0 {
            parts.push(format!(
                "{} beyond the grid: |u| or |v| past the Nyquist limit {limit_l:.1} wavelengths of {pixel_arcsec:.4} arcsec pixels, left out as WSClean leaves them",
                self.beyond
            ));
        }
        (!parts.is_empty()).then(|| format!("uv selection: {} of {} samples left out ({}), {} kept", self.samples - self.kept(), self.samples, parts.join("; "), self.kept()))
    }

    /// An error where nothing is left to image, naming what left out most (the pixel size
    /// where the grid did).
    pub fn check_kept(&self, limit_l: f64, pixel_arcsec: f64) -> Result<()> {
        if self.kept() > 0 || self.samples == 0 {
            return Ok(());
        }
        let name = [(self.beyond, "pixel_arcsec"), (self.below_min, "minuv_l"), (self.above_max, "maxuv_l")].into_iter().max_by_key(|(n, _)| *n).map_or("pixel_arcsec", |(_, name)| name);
        let what = self.describe(limit_l, pixel_arcsec).unwrap_or_default();
        Err(Error::parameter(name, format!("nothing would remain to image: {what}")))
    }
}

/// The weighting grid's cells per axis for `grid_factor` and `image_size`, checked.
fn grid_cells(grid_factor: f64, image_size: usize) -> Result<usize> {
    check_grid(grid_factor, image_size)?;
    Ok(cells_of(grid_factor, image_size))
}

/// `floor(grid_factor N)`, at least 1; a product a rounding error below a whole number counts
/// as that number (a factor computed as `cells / N` gives back `cells`).
pub fn cells_of(grid_factor: f64, image_size: usize) -> usize {
    let exact = grid_factor * image_size as f64;
    ((exact + 1e-9 * exact.max(1.0)).floor() as usize).max(1)
}

/// The grid factor whose weighting grid at `image_size` has the cells of the default grid at
/// `trained_size`: the same uv cell in wavelengths at the same pixel, so uniform and Briggs
/// weights, and the PSF, are those a series trained at `trained_size` saw (the weights of a
/// fixed set of samples depend on the cell: a field twice as wide halves it, and Briggs 0's
/// PSF at 1024 pixels is not its PSF at 512). WSClean's `-super-weight` is its inverse ratio.
pub fn grid_factor_of_trained_field(trained_size: usize, image_size: usize) -> f64 {
    DEFAULT_GRID_FACTOR * trained_size as f64 / image_size.max(1) as f64
}

/// Imaging weights (multiplying the natural weights) for visibilities at `(u, v)` given in the
/// operator's coordinates (radians per pixel, `[-pi, pi)`), for an `image_size` image.
pub(crate) fn imaging_weights(
    u: &[f64],
    v: &[f64],
    natural_weight: &[f64],
    image_size: usize,
    scheme: Weighting,
    grid_factor: f64,
) -> Result<Vec<f64>> {
    if u.len() != v.len() || u.len() != natural_weight.len() {
        return Err(Error::parameter("visibilities", "u, v and weight arrays differ in length"));
    }
    weigh(|k| (u[k], v[k]), |k| natural_weight[k], u.len(), image_size, scheme, grid_factor, UvShape::default(), |imaging, _| imaging)
}

/// Total weights (natural x imaging) of visibilities whose operator coordinates (as in
/// [`imaging_weights`]) `point(k)` gives, without a per-visibility array beside the result:
/// the coordinates and cells are computed again where they are needed (memory is the limit on
/// large tables, and this is a small part of the time). `uv` cuts and tapers them.
pub(crate) fn total_weights(
    point: impl Fn(usize) -> (f64, f64),
    natural_weight: &[f32],
    image_size: usize,
    scheme: Weighting,
    grid_factor: f64,
    uv: UvShape,
) -> Result<Vec<f64>> {
    let natural = |k: usize| f64::from(natural_weight[k]);
    weigh(point, natural, natural_weight.len(), image_size, scheme, grid_factor, uv, |imaging, natural| imaging * natural)
}

/// Imaging weight of each of `n` visibilities, combined with its natural weight by `combine`.
/// Refuses a weighting grid factor that is not a positive number, or whose grid of
/// `(grid_factor N)^2` cells does not fit in the memory available (checked in f64 before
/// anything is allocated: 1e4 asked for terabytes, 1e9 overflowed).
pub(crate) fn check_grid(grid_factor: f64, image_size: usize) -> Result<()> {
    if !(grid_factor > 0.0) || !grid_factor.is_finite() {
        return Err(Error::parameter("grid_factor", format!("expected a positive number, got {grid_factor}")));
    }
    let cells = cells_of(grid_factor, image_size) as f64;
    crate::limits::check_memory(cells * cells * 8.0, &format!("a weighting grid of {cells:.0} x {cells:.0} cells (grid factor {grid_factor} x {image_size} pixels)"))
        .map_err(|m| Error::parameter("grid_factor", m))
}

fn weigh(
    point: impl Fn(usize) -> (f64, f64),
    natural_weight: impl Fn(usize) -> f64,
    n: usize,
    image_size: usize,
    scheme: Weighting,
    grid_factor: f64,
    uv: UvShape,
    combine: impl Fn(f64, f64) -> f64,
) -> Result<Vec<f64>> {
    if scheme == Weighting::Given {
        return Err(Error::parameter("weighting", "`given` takes the imaging weights given with the visibilities, which these have none of"));
    }
    let mut density = DensityGrid::new(scheme, image_size, grid_factor)?;
    density.add(n, &point, &natural_weight);
    let rule = density.finish().with_uv(uv);
    Ok((0..n).map(|k| combine(rule.imaging_weight(point(k)), natural_weight(k))).collect())
}

/// The summed natural weight per weighting cell, gathered over the samples (given in as many
/// calls of [`add`](Self::add) as the caller likes: a table read in chunks): the first of the
/// two passes of uniform and Briggs weighting. Natural and given weighting need no grid.
pub struct DensityGrid {
    scheme: Weighting,
    cells: usize,
    density: Vec<f64>,
    sum_w: f64,
}

impl DensityGrid {
    pub fn new(scheme: Weighting, image_size: usize, grid_factor: f64) -> Result<DensityGrid> {
        if !scheme.needs_density() {
            return Ok(DensityGrid { scheme, cells: 0, density: Vec::new(), sum_w: 0.0 });
        }
        let cells = grid_cells(grid_factor, image_size)?;
        Ok(DensityGrid { scheme, cells, density: vec![0.0; cells * cells], sum_w: 0.0 })
    }

    /// Adds `n` samples at operator coordinates `point(k)` with natural weight `natural(k)`;
    /// a sample beyond the grid ([`beyond_grid`]) is not imaged and adds nothing.
    pub fn add(&mut self, n: usize, point: impl Fn(usize) -> (f64, f64), natural: impl Fn(usize) -> f64) {
        if self.density.is_empty() {
            return;
        }
        for k in 0..n {
            let p = point(k);
            if beyond_grid(p) {
                continue;
            }
            let w = natural(k);
            self.density[cell_of(self.cells, p)] += w;
            self.sum_w += w;
        }
    }

    /// Adds another part's density (gathered on the same grid) to this one.
    pub fn merge(&mut self, other: &DensityGrid) -> Result<()> {
        if (self.scheme, self.cells) != (other.scheme, other.cells) {
            return Err(Error::parameter("weighting", "two parts' uv densities were gathered for different weightings or grids"));
        }
        self.density.iter_mut().zip(&other.density).for_each(|(a, b)| *a += b);
        self.sum_w += other.sum_w;
        Ok(())
    }

    /// The summed natural weight per cell (row-major, `cells x cells`; empty where the
    /// scheme needs none) and over all cells: what a part sends to be summed.
    pub fn raw(&self) -> (&[f64], f64) {
        (&self.density, self.sum_w)
    }

    /// A density gathered elsewhere, as [`raw`](Self::raw) gave it: an error where its cell
    /// count is not the grid's of `scheme`, `image_size` and `grid_factor`.
    pub fn from_raw(scheme: Weighting, image_size: usize, grid_factor: f64, density: Vec<f64>, sum_w: f64) -> Result<DensityGrid> {
        let mut grid = DensityGrid::new(scheme, image_size, grid_factor)?;
        if density.len() != grid.density.len() {
            return Err(Error::parameter("weighting", format!("a uv density of {} cells where {} was expected", density.len(), grid.density.len())));
        }
        grid.density = density;
        grid.sum_w = sum_w;
        Ok(grid)
    }

    /// The imaging weight of every sample from now on.
    pub fn finish(self) -> WeightRule {
        let DensityGrid { scheme, cells, density, sum_w } = self;
        let f2 = match scheme {
            Weighting::Briggs { robust } => {
                let sum_g2: f64 = density.iter().map(|g| g * g).sum();
                if sum_g2 > 0.0 {
                    (5.0 * 10f64.powf(-robust)).powi(2) * sum_w / sum_g2
                } else {
                    0.0
                }
            }
            _ => 0.0,
        };
        WeightRule { scheme, cells, density, f2, uv: UvShape::default() }
    }
}

/// A sample's imaging weight from its position alone, once the density of the whole
/// uv-coverage is known: no per-sample array is needed, so a table read in chunks is weighted
/// as it is gridded.
#[derive(Clone, Debug)]
pub struct WeightRule {
    scheme: Weighting,
    cells: usize,
    density: Vec<f64>,
    f2: f64,
    /// The uv cuts and tapers, applied after the density.
    uv: UvShape,
}

impl WeightRule {
    /// Natural weighting (the imaging weight is 1).
    pub fn natural() -> WeightRule {
        WeightRule { scheme: Weighting::Natural, cells: 0, density: Vec::new(), f2: 0.0, uv: UvShape::default() }
    }

    pub fn scheme(&self) -> Weighting {
        self.scheme
    }

    /// The rule with the uv cuts and tapers `uv` (in place of any it had).
    pub fn with_uv(mut self, uv: UvShape) -> WeightRule {
        self.uv = uv;
        self
    }

    /// The uv cuts and tapers (what travels beside [`raw`](Self::raw)).
    pub fn uv(&self) -> UvShape {
        self.uv
    }

    /// The factor of the cuts and tapers at `point` (0 beyond the grid): what a weight given
    /// with the data is multiplied by.
    pub fn selection(&self, point: (f64, f64)) -> f64 {
        self.uv.factor(point)
    }

    /// The density per cell (empty where the scheme needs none) and Briggs' `f^2`: what the
    /// rule travels as to where a part of the samples is weighted.
    pub fn raw(&self) -> (&[f64], f64) {
        (&self.density, self.f2)
    }

    /// The rule [`raw`](Self::raw) gave for `scheme`: an error where the density is not a
    /// square grid (or not empty, for a scheme that needs none).
    pub fn from_raw(scheme: Weighting, density: Vec<f64>, f2: f64) -> Result<WeightRule> {
        let cells = (density.len() as f64).sqrt().round() as usize;
        if cells * cells != density.len() || scheme.needs_density() == density.is_empty() {
            return Err(Error::parameter("weighting", format!("a {scheme} weighting rule of {} cells: expected a square grid of cells for uniform and Briggs, none otherwise", density.len())));
        }
        Ok(WeightRule { scheme, cells, density, f2, uv: UvShape::default() })
    }

    /// The imaging weight (multiplying the natural weight) at operator coordinates `point`;
    /// 1 for natural weighting, and for `given` (whose weights come with the samples), times
    /// the uv cuts and tapers (0 beyond the grid).
    pub fn imaging_weight(&self, point: (f64, f64)) -> f64 {
        let selection = self.uv.factor(point);
        if selection == 0.0 {
            return 0.0;
        }
        selection * self.density_weight(point)
    }

    /// The weight the density gives the sample at `point`.
    fn density_weight(&self, point: (f64, f64)) -> f64 {
        match self.scheme {
            Weighting::Natural | Weighting::Given => 1.0,
            Weighting::Uniform => {
                let g = self.density[cell_of(self.cells, point)];
                if g > 0.0 {
                    1.0 / g
                } else {
                    0.0
                }
            }
            Weighting::Briggs { .. } => 1.0 / (1.0 + self.f2 * self.density[cell_of(self.cells, point)]),
        }
    }
}

impl Weighting {
    /// Whether the scheme needs the density of the whole uv-coverage before any sample's
    /// weight is known (a second pass over the data).
    pub fn needs_density(&self) -> bool {
        matches!(self, Weighting::Uniform | Weighting::Briggs { .. })
    }
}

/// The weighting cell of operator coordinates `(u, v)` on a `cells x cells` grid, folded onto
/// the half plane `v >= 0`.
fn cell_of(cells: usize, (u, v): (f64, f64)) -> usize {
    let (u, v) = if v < 0.0 { (-u, -v) } else { (u, v) };
    let index = |t: f64| -> usize {
        let c = ((t + std::f64::consts::PI) * cells as f64 / (2.0 * std::f64::consts::PI)).floor();
        c.clamp(0.0, (cells - 1) as f64) as usize
    };
    index(v) * cells + index(u)
}

#[cfg(test)]
mod tests {
    /// `--robust` means Briggs (issue 56.21: `--weighting natural --robust 1` dropped it unsaid).
    #[test]
    fn a_robustness_with_another_scheme_is_refused() {
        for name in ["natural", "uniform", "given"] {
            let e = Weighting::from_options(Some(name), Some(1.0)).unwrap_err().to_string();
            assert!(e.contains("robust") && e.contains(name), "{e}");
        }
        assert_eq!(Weighting::from_options(Some("briggs"), Some(1.0)).unwrap(), Some(Weighting::Briggs { robust: 1.0 }));
        assert_eq!(Weighting::from_options(None, Some(-1.0)).unwrap(), Some(Weighting::Briggs { robust: -1.0 }));
        assert_eq!(Weighting::from_options(Some("natural"), None).unwrap(), Some(Weighting::Natural));
    }

    use super::*;

    #[test]
    fn a_trained_fields_grid_factor_gives_its_cells_at_any_size() {
        for trained in [128, 512] {
            for size in [64, 100, 256, 512, 768, 999, 1000, 1024, 1536, 2048, 3000, 4096] {
                let factor = grid_factor_of_trained_field(trained, size);
                assert_eq!(cells_of(factor, size), 2 * trained, "trained {trained}, size {size}, factor {factor}");
            }
        }
        assert_eq!(cells_of(DEFAULT_GRID_FACTOR, 512), 1024);
        assert_eq!((cells_of(1.5, 3), cells_of(0.1, 3)), (4, 1));
    }

    #[test]
    fn grids_beyond_memory_are_refused() {
        check_grid(2.0, 512).unwrap();
        for factor in [1e4, 1e9, 1e300] {
            let e = check_grid(factor, 512).unwrap_err().to_string();
            assert!(e.contains("weighting grid") && e.contains("memory"), "{factor}: {e}");
        }
        for factor in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(check_grid(factor, 512).unwrap_err().to_string().contains("positive"), "{factor}");
        }
    }

    fn sample() -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        // A dense core and a sparse outer region, like real uv coverage.
        let mut u = Vec::new();
        let mut v = Vec::new();
        for k in 0..5000 {
            let r = if k % 5 == 0 { 2.5 } else { 0.3 } * ((k as f64 * 0.618).fract());
            let t = k as f64 * 2.399;
            u.push(r * t.cos());
            v.push(r * t.sin());
        }
        let w = vec![4.0; u.len()];
        (u, v, w)
    }

    #[test]
    fn uniform_flattens_the_cell_density() {
        let (u, v, w) = sample();
        let iw = imaging_weights(&u, &v, &w, 64, Weighting::Uniform, 2.0).unwrap();
        // Sum of total weights per occupied cell is 1 for uniform weighting.
        let cells = 128;
        let mut per_cell = std::collections::HashMap::new();
        for k in 0..u.len() {
            let (uu, vv) = if v[k] < 0.0 { (-u[k], -v[k]) } else { (u[k], v[k]) };
            let c = |t: f64| ((t + std::f64::consts::PI) * cells as f64 / (2.0 * std::f64::consts::PI)).floor() as i64;
            *per_cell.entry((c(uu), c(vv))).or_insert(0.0) += w[k] * iw[k];
        }
        assert!(per_cell.values().all(|s: &f64| (s - 1.0).abs() < 1e-12));
    }

    #[test]
    fn robustness_outside_the_range_is_refused() {
        for robust in [-1e30, -5.5, 5.5, 1e30, f64::NAN, f64::INFINITY] {
            let e = Weighting::from_name("briggs", robust).unwrap_err().to_string();
            assert!(e.contains("robust") && e.contains("from -5 to 5") && e.contains(&format!("got {robust}")), "{e}");
        }
        for robust in [-5.0, -2.0, 0.0, 2.0, 5.0] {
            assert_eq!(Weighting::from_name("robust", robust).unwrap(), Weighting::Briggs { robust });
        }
    }

    #[test]
    fn briggs_limits_are_natural_and_uniform() {
        let (u, v, w) = sample();
        let uniform = imaging_weights(&u, &v, &w, 64, Weighting::Uniform, 2.0).unwrap();
        let plus5 = imaging_weights(&u, &v, &w, 64, Weighting::Briggs { robust: 5.0 }, 2.0).unwrap();
        let minus5 = imaging_weights(&u, &v, &w, 64, Weighting::Briggs { robust: -5.0 }, 2.0).unwrap();
        // Weights matter up to a global scale (the PSF normalisation removes it).
        let scale_n = plus5[0];
        assert!(plus5.iter().all(|x| (x / scale_n - 1.0).abs() < 1e-4));
        let ratio: Vec<f64> = minus5.iter().zip(&uniform).map(|(b, u)| b / u).collect();
        assert!(ratio.iter().all(|r| (r / ratio[0] - 1.0).abs() < 1e-4));
    }

    #[test]
    fn total_weights_are_imaging_times_natural_weights_bit_for_bit() {
        let (u, v, _) = sample();
        let natural: Vec<f32> = (0..u.len()).map(|k| 0.3 + (k % 7) as f32).collect();
        for scheme in [Weighting::Natural, Weighting::Uniform, Weighting::Briggs { robust: 0.5 }] {
            let wide: Vec<f64> = natural.iter().map(|&w| f64::from(w)).collect();
            let imaging = imaging_weights(&u, &v, &wide, 64, scheme, 2.0).unwrap();
            let total = total_weights(|k| (u[k], v[k]), &natural, 64, scheme, 2.0, UvShape::default()).unwrap();
            let expected: Vec<f64> = imaging.iter().zip(&wide).map(|(i, n)| i * n).collect();
            assert_eq!(total, expected, "{scheme}");
        }
        assert!(imaging_weights(&u, &v[1..], &[1.0; 3], 64, Weighting::Uniform, 2.0).is_err());
    }

    #[test]
    fn unknown_scheme_names_the_choices() {
        let err = Weighting::from_name("superuniform", 0.0).unwrap_err().to_string();
        assert!(err.contains("natural, uniform, briggs"), "{err}");
    }

    /// A 64-pixel image of 1 arcsec pixels on a grid of 128 cells: the operator coordinates of
    /// `(u, v)` wavelengths, and the length of one cell in wavelengths.
    fn uv_grid() -> (ImageGeometryForTest, f64) {
        let pixel = (1.0f64 / 3600.0).to_radians();
        (ImageGeometryForTest { pixel }, 1.0 / (128.0 * pixel))
    }

    struct ImageGeometryForTest {
        pixel: f64,
    }

    impl ImageGeometryForTest {
        fn point(&self, u: f64, v: f64) -> (f64, f64) {
            let s = std::f64::consts::TAU * self.pixel;
            (-s * u, s * v)
        }
        fn shape(&self, uv: UvControls) -> UvShape {
            UvShape::new(&uv, 64, 2.0, self.pixel).unwrap()
        }
    }

    /// The tapers have their formulas' values at the corner of the sample's weighting cell
    /// (lower u and v, after folding onto v >= 0), as WSClean evaluates them: the Gaussian of
    /// image-plane FWHM F is `exp(-r^2 / (2 s^2))` with `s = sqrt(8 ln 2) / (2 pi F)`, the
    /// Tukey taper `(1 + cos(pi (r - (maxuv - width)) / width)) / 2` inside `maxuv`.
    #[test]
    fn tapers_are_their_formulas_at_the_weighting_cells_corner() {
        let (g, cell) = uv_grid();
        // Cell offsets (10, 5): a corner at (10, 5) cells, r = sqrt(125) cells.
        let (u, v) = (10.3 * cell, 5.6 * cell);
        let r = 125f64.sqrt() * cell;
        let fwhm_arcsec = 4.0;
        let s = (8.0 * std::f64::consts::LN_2).sqrt() / (std::f64::consts::TAU * (fwhm_arcsec / 3600.0f64).to_radians());
        let gaussian = g.shape(UvControls { taper_gaussian: Some(fwhm_arcsec), ..Default::default() });
        let expected = (-r * r / (2.0 * s * s)).exp();
        assert!(expected > 0.1 && expected < 0.99, "a test point inside the taper: {expected}");
        for (uu, vv) in [(u, v), (-u, -v)] {
            // The mirrored sample (folded onto v >= 0) is in the same cell.
            let got = gaussian.factor(g.point(uu, vv));
            assert!((got - expected).abs() < 1e-12, "({uu}, {vv}): {got} vs {expected}");
        }
        // The transition of width 20 cells ends at r + 10 cells: the corner is half-way.
        let tukey = g.shape(UvControls { maxuv_l: Some(r + 10.0 * cell), taper_tukey: Some(20.0 * cell), ..Default::default() });
        assert!((tukey.factor(g.point(u, v)) - 0.5).abs() < 1e-12);
        // A quarter of the way in: (1 + cos(pi / 4)) / 2.
        let tukey = g.shape(UvControls { maxuv_l: Some(r + 15.0 * cell), taper_tukey: Some(20.0 * cell), ..Default::default() });
        let quarter = 0.5 * (1.0 + std::f64::consts::FRAC_PI_4.cos());
        assert!((tukey.factor(g.point(u, v)) - quarter).abs() < 1e-12);
        // Inside the transition 1; beyond maxuv 0.
        assert_eq!(tukey.factor(g.point(0.5 * cell, 0.5 * cell)), 1.0);
        assert_eq!(tukey.factor(g.point(40.0 * cell, 0.0)), 0.0);
    }

    /// The cuts compare the cell corner's distance with the limits; a sample beyond the grid
    /// is left out whatever is asked; each is counted by why.
    #[test]
    fn cuts_leave_out_samples_by_their_cells_corner() {
        let (g, cell) = uv_grid();
        let shape = g.shape(UvControls { minuv_l: Some(9.5 * cell), maxuv_l: Some(30.5 * cell), ..Default::default() });
        // Corners (10, 0) and (9, 0): a sample at 10.5 cells is kept, one at 9.9 is not.
        assert_eq!(shape.factor(g.point(10.5 * cell, 0.2 * cell)), 1.0);
        assert_eq!(shape.factor(g.point(9.9 * cell, 0.2 * cell)), 0.0);
        assert_eq!(shape.factor(g.point(30.9 * cell, 0.0)), 1.0, "the corner (30, 0) is inside maxuv");
        assert_eq!(shape.factor(g.point(31.0 * cell, 0.0)), 0.0);
        let beyond = g.point(64.5 * cell, 0.0);
        assert_eq!((shape.factor(beyond), UvShape::default().factor(beyond)), (0.0, 0.0));
        let mut counts = UvCounts::default();
        for (u, v) in [(10.5, 0.2), (9.9, 0.2), (31.0, 0.0), (64.5, 0.0), (-70.0, 3.0)] {
            counts.add(&shape, g.point(u * cell, v * cell));
        }
        assert_eq!(counts, UvCounts { samples: 5, beyond: 2, below_min: 1, above_max: 1 });
        assert_eq!(counts.kept(), 1);
        let nothing = UvCounts { samples: 3, beyond: 1, below_min: 2, above_max: 0 };
        let e = nothing.check_kept(1e4, 1.0).unwrap_err().to_string();
        assert!(e.contains("minuv_l") && e.contains("nothing would remain"), "{e}");
    }

    /// As in WSClean, the cuts apply after the density pass: the samples they leave out still
    /// count in the density and in Briggs' normalisation, so a kept sample's weight is the
    /// uncut one's. A sample beyond the grid counts in neither.
    #[test]
    fn cuts_apply_after_the_density_and_the_grids_edge_before_it() {
        let (u, v, w) = sample();
        let scheme = Weighting::Briggs { robust: 0.0 };
        let natural: Vec<f32> = w.iter().map(|&x| x as f32).collect();
        let pixel = 1.0 / (2.0 * std::f64::consts::PI);
        // Operator coordinates: one wavelength is one radian per pixel here.
        let uv = UvControls { minuv_l: Some(0.2), maxuv_l: Some(2.0), ..Default::default() };
        let shape = UvShape::new(&uv, 64, 2.0, pixel).unwrap();
        let cut = total_weights(|k| (u[k], v[k]), &natural, 64, scheme, 2.0, shape).unwrap();
        let uncut = total_weights(|k| (u[k], v[k]), &natural, 64, scheme, 2.0, UvShape::default()).unwrap();
        let (mut kept, mut left_out) = (0, 0);
        for k in 0..u.len() {
            if cut[k] == 0.0 {
                left_out += 1;
            } else {
                kept += 1;
                assert_eq!(cut[k], uncut[k]);
            }
        }
        assert!(kept > 1000 && left_out > 1000, "{kept} kept, {left_out} left out");
        // A sample beyond the grid: weight 0, and the others' weights as without it.
        let (mut u2, mut v2, mut n2) = (u.clone(), v.clone(), natural.clone());
        u2.push(3.5);
        v2.push(0.0);
        n2.push(1e6);
        let with = total_weights(|k| (u2[k], v2[k]), &n2, 64, scheme, 2.0, UvShape::default()).unwrap();
        assert_eq!(with[u.len()], 0.0);
        assert_eq!(&with[..u.len()], &uncut[..]);
    }

    #[test]
    fn bad_cuts_and_tapers_are_refused_naming_the_field() {
        let bad = |uv: UvControls, field: &str, words: &str| {
            let e = uv.check().unwrap_err();
            let text = e.to_string();
            assert!(text.contains(field) && text.contains(words), "{uv:?}: {text}");
        };
        bad(UvControls { minuv_l: Some(-1.0), ..Default::default() }, "minuv_l", ">= 0");
        bad(UvControls { maxuv_l: Some(0.0), ..Default::default() }, "maxuv_l", "> 0");
        bad(UvControls { maxuv_l: Some(f64::INFINITY), ..Default::default() }, "maxuv_l", "inf");
        bad(UvControls { minuv_l: Some(500.0), maxuv_l: Some(500.0), ..Default::default() }, "minuv_l", "below maxuv_l");
        bad(UvControls { taper_gaussian: Some(f64::NAN), ..Default::default() }, "taper_gaussian", "FWHM");
        bad(UvControls { taper_gaussian: Some(-2.0), ..Default::default() }, "taper_gaussian", "> 0");
        bad(UvControls { taper_tukey: Some(10.0), ..Default::default() }, "taper_tukey", "maxuv_l");
        bad(UvControls { taper_tukey: Some(10.0), maxuv_l: Some(5.0), ..Default::default() }, "taper_tukey", "no wider");
        let fine = UvControls { minuv_l: Some(0.0), maxuv_l: Some(5.0), taper_gaussian: Some(1.0), taper_tukey: Some(5.0) };
        fine.check().unwrap();
        assert_eq!((fine.longest_kept(3.0), fine.longest_kept(9.0), UvControls::default().longest_kept(9.0)), (3.0, 5.0, 9.0));
    }
}
