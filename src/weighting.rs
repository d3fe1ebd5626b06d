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
    weigh(|k| (u[k], v[k]), |k| natural_weight[k], u.len(), image_size, scheme, grid_factor, |imaging, _| imaging)
}

/// Total weights (natural x imaging) of visibilities whose operator coordinates (as in
/// [`imaging_weights`]) `point(k)` gives, without a per-visibility array beside the result:
/// the coordinates and cells are computed again where they are needed (memory is the limit on
/// large tables, and this is a small part of the time).
pub(crate) fn total_weights(
    point: impl Fn(usize) -> (f64, f64),
    natural_weight: &[f32],
    image_size: usize,
    scheme: Weighting,
    grid_factor: f64,
) -> Result<Vec<f64>> {
    let natural = |k: usize| f64::from(natural_weight[k]);
    weigh(point, natural, natural_weight.len(), image_size, scheme, grid_factor, |imaging, natural| imaging * natural)
}

/// Imaging weight of each of `n` visibilities, combined with its natural weight by `combine`.
/// Refuses a weighting grid factor that is not a positive number, or whose grid of
/// `(grid_factor N)^2` cells does not fit in the memory available (checked in f64 before
/// anything is allocated: 1e4 asked for terabytes, 1e9 overflowed).
pub(crate) fn check_grid(grid_factor: f64, image_size: usize) -> Result<()> {
    if !(grid_factor > 0.0) || !grid_factor.is_finite() {
        return Err(Error::parameter("weighting grid factor", format!("expected a positive number, got {grid_factor}")));
    }
    let cells = (grid_factor * image_size as f64).floor().max(1.0);
    crate::limits::check_memory(cells * cells * 8.0, &format!("a weighting grid of {cells:.0} x {cells:.0} cells (grid factor {grid_factor} x {image_size} pixels)"))
        .map_err(|m| Error::parameter("weighting grid factor", m))
}

fn weigh(
    point: impl Fn(usize) -> (f64, f64),
    natural_weight: impl Fn(usize) -> f64,
    n: usize,
    image_size: usize,
    scheme: Weighting,
    grid_factor: f64,
    combine: impl Fn(f64, f64) -> f64,
) -> Result<Vec<f64>> {
    if scheme == Weighting::Given {
        return Err(Error::parameter("weighting", "`given` takes the imaging weights given with the visibilities, which these have none of"));
    }
    let mut density = DensityGrid::new(scheme, image_size, grid_factor)?;
    density.add(n, &point, &natural_weight);
    let rule = density.finish();
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
        check_grid(grid_factor, image_size)?;
        let cells = ((grid_factor * image_size as f64).floor() as usize).max(1);
        Ok(DensityGrid { scheme, cells, density: vec![0.0; cells * cells], sum_w: 0.0 })
    }

    /// Adds `n` samples at operator coordinates `point(k)` with natural weight `natural(k)`.
    pub fn add(&mut self, n: usize, point: impl Fn(usize) -> (f64, f64), natural: impl Fn(usize) -> f64) {
        if self.density.is_empty() {
            return;
        }
        for k in 0..n {
            let w = natural(k);
            self.density[cell_of(self.cells, point(k))] += w;
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
        WeightRule { scheme, cells, density, f2 }
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
}

impl WeightRule {
    /// Natural weighting (the imaging weight is 1).
    pub fn natural() -> WeightRule {
        WeightRule { scheme: Weighting::Natural, cells: 0, density: Vec::new(), f2: 0.0 }
    }

    pub fn scheme(&self) -> Weighting {
        self.scheme
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
        Ok(WeightRule { scheme, cells, density, f2 })
    }

    /// The imaging weight (multiplying the natural weight) at operator coordinates `point`;
    /// 1 for natural weighting, and for `given` (whose weights come with the samples).
    pub fn imaging_weight(&self, point: (f64, f64)) -> f64 {
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
            let total = total_weights(|k| (u[k], v[k]), &natural, 64, scheme, 2.0).unwrap();
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
}
