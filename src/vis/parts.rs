//! One observation kept in parts that are gridded where they live (Dask workers, or this
//! process part after part), its image-domain loop run once: every pass over the samples is a
//! sum over the parts. A part's pass ([`part_density`], [`part_images`],
//! [`part_apply_normal`]) is a function of the part and a [`PartPass`] (which travels to the
//! part as JSON); the job's side of it is [`PartPasses`], which makes the pass on every part
//! and sums what they give, in part order.

use super::data::ObservationMeta;
use super::operator::chunk_weights;
use super::stream::{VisSource, VisSummary};
use crate::nufft::NufftParams;
use crate::operator::{normalise_by_psf_peak, ImageGeometry, ImageGridder, MeasurementOperator};
use crate::weighting::{DensityGrid, WeightRule, Weighting, WeightingScheme};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// What a pass over one part needs beside the part: the image grid, the weighting, whether
/// the w-term is corrected, the NUFFT's accuracy, and the part's threads and chunk size.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartPass {
    pub size: usize,
    pub pixel_rad: f64,
    pub scheme: WeightingScheme,
    /// Briggs' robustness (0 for the other schemes).
    pub robust: f64,
    pub grid_factor: f64,
    pub w_term: bool,
    pub epsilon: f64,
    pub oversampling: f64,
    /// Threads of the part's gridding (0: every core of where it runs).
    pub threads: usize,
    /// Samples gridded at a time.
    pub chunk_rows: usize,
}

impl PartPass {
    pub fn new(geometry: ImageGeometry, weighting: Weighting, grid_factor: f64, w_term: bool, nufft: NufftParams, threads: usize, chunk_rows: usize) -> PartPass {
        PartPass {
            size: geometry.size,
            pixel_rad: geometry.pixel_rad,
            scheme: weighting.scheme(),
            robust: weighting.robust().unwrap_or(0.0),
            grid_factor,
            w_term,
            epsilon: nufft.epsilon,
            oversampling: nufft.oversampling,
            threads,
            chunk_rows: chunk_rows.max(1),
        }
    }

    pub fn geometry(&self) -> Result<ImageGeometry> {
        ImageGeometry::new(self.size, self.pixel_rad)
    }
    pub fn weighting(&self) -> Result<Weighting> {
        self.scheme.with_robust(self.robust)
    }
    pub fn nufft(&self) -> NufftParams {
        NufftParams { epsilon: self.epsilon, oversampling: self.oversampling }
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("a pass serialises")
    }

    pub fn from_json(text: &str) -> Result<PartPass> {
        serde_json::from_str(text).map_err(|e| Error::parameter("pass", format!("expected a part pass as JSON ({e}), got {text:.200}")))
    }
}

/// What one part adds to a job's images, before they are normalised by the whole PSF's
/// peak: the images are linear in the samples, so the parts' sum is the whole's (to the order
/// of floating-point additions).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PartImages {
    /// `Re{Phi^H (omega y)}`, `N x N`.
    pub dirty: Vec<f64>,
    /// `Re{Phi^H Phi delta}`, `N x N`.
    pub psf: Vec<f64>,
    /// The coplanar PSF over twice the field, `2N x 2N`.
    pub psf_2n: Vec<f64>,
    pub samples: u64,
    /// The most w-planes of any of the part's chunks; `None` where coplanar.
    pub planes: Option<usize>,
}

impl PartImages {
    /// Adds `other` (another part's) to these images: an error where the two are of
    /// different sizes (parts gridded for different images).
    pub fn add(&mut self, other: &PartImages) -> Result<()> {
        if self.samples == 0 && self.dirty.is_empty() {
            *self = other.clone();
            return Ok(());
        }
        if (self.dirty.len(), self.psf.len(), self.psf_2n.len()) != (other.dirty.len(), other.psf.len(), other.psf_2n.len()) {
            return Err(Error::parameter("parts", "two parts gave images of different sizes"));
        }
        add_to(&mut self.dirty, &other.dirty);
        add_to(&mut self.psf, &other.psf);
        add_to(&mut self.psf_2n, &other.psf_2n);
        self.samples += other.samples;
        self.planes = self.planes.max(other.planes);
        Ok(())
    }

    /// The dirty image, PSF and 2N PSF normalised by `kappa = 1 / PSF peak`, and `kappa`.
    pub fn normalise(mut self, size: usize) -> Result<NormalisedImages> {
        if self.samples == 0 {
            return Err(Error::parameter("weight", "all visibilities have zero weight: nothing to image"));
        }
        let kappa = normalise_by_psf_peak(size, &mut self.dirty, &mut self.psf)?;
        self.psf_2n.iter_mut().for_each(|p| *p *= kappa);
        Ok(NormalisedImages { dirty: self.dirty, psf: self.psf, psf_2n: self.psf_2n, kappa, planes: self.planes })
    }
}

/// A job's images normalised by the PSF's peak.
pub struct NormalisedImages {
    pub dirty: Vec<f64>,
    pub psf: Vec<f64>,
    pub psf_2n: Vec<f64>,
    pub kappa: f64,
    pub planes: Option<usize>,
}

/// The uv density of a part's samples on the weighting grid (uniform and Briggs; an empty
/// grid for natural and given weighting).
pub fn part_density(vis: &VisSource, pass: &PartPass) -> Result<DensityGrid> {
    let (geometry, weighting) = (pass.geometry()?, pass.weighting()?);
    let mut density = DensityGrid::new(weighting, geometry.size, pass.grid_factor)?;
    if weighting.needs_density() {
        vis.for_each_chunk(pass.chunk_rows, &mut |c| {
            density.add(c.len(), |k| geometry.uv_to_phase(c.u[k], c.v[k]), |k| f64::from(c.weight[k]));
            Ok(())
        })?;
    }
    Ok(density)
}

/// A part's images, weighted by `rule` (the whole observation's): with the w-term, each chunk
/// of the part through an operator of its own w-planes; coplanar, gridded as read.
pub fn part_images(vis: &VisSource, pass: &PartPass, rule: &WeightRule) -> Result<PartImages> {
    let (geometry, nufft) = (pass.geometry()?, pass.nufft());
    let pixels = geometry.pixels();
    let mut samples = 0u64;
    if !pass.w_term {
        let mut gridder = ImageGridder::new(geometry, nufft, pass.threads)?;
        vis.for_each_chunk(pass.chunk_rows, &mut |c| {
            let weight = chunk_weights(&c, geometry, rule)?;
            samples += c.len() as u64;
            gridder.add(c.u, c.v, &weight, c.vis)
        })?;
        let (dirty, psf, psf_2n) = gridder.unnormalised();
        return Ok(PartImages { dirty, psf, psf_2n, samples, planes: None });
    }
    let (mut dirty, mut psf) = (vec![0.0; pixels], vec![0.0; pixels]);
    let mut doubled = ImageGridder::doubled_psf_only(geometry, nufft, pass.threads)?;
    let mut planes: Option<usize> = None;
    vis.for_each_chunk(pass.chunk_rows, &mut |c| {
        let weight = chunk_weights(&c, geometry, rule)?;
        let op = MeasurementOperator::part_for_mode(true, geometry, c.u, c.v, c.w, &weight, nufft, pass.threads)?;
        add_to(&mut dirty, &op.dirty_image(c.vis));
        add_to(&mut psf, &op.psf());
        planes = planes.max(op.w_planes());
        samples += c.len() as u64;
        drop(op);
        doubled.add(c.u, c.v, &weight, c.vis)
    })?;
    let (_, _, psf_2n) = doubled.unnormalised();
    Ok(PartImages { dirty, psf, psf_2n, samples, planes })
}

/// `Re{Phi^H Phi x}` over a part's samples (not scaled by `kappa`, which is the whole's), each
/// chunk's operator planned, applied and dropped.
pub fn part_apply_normal(vis: &VisSource, pass: &PartPass, rule: &WeightRule, x: &[f64]) -> Result<Vec<f64>> {
    let (geometry, nufft) = (pass.geometry()?, pass.nufft());
    if x.len() != geometry.pixels() {
        return Err(Error::parameter("image", format!("expected {} pixels ({} x {}), got {}", geometry.pixels(), geometry.size, geometry.size, x.len())));
    }
    let mut sum = vec![0.0; x.len()];
    vis.for_each_chunk(pass.chunk_rows, &mut |c| {
        let weight = chunk_weights(&c, geometry, rule)?;
        let op = MeasurementOperator::part_for_mode(pass.w_term, geometry, c.u, c.v, c.w, &weight, nufft, pass.threads)?;
        add_to(&mut sum, &op.apply_normal(x));
        Ok(())
    })?;
    Ok(sum)
}

/// Where a parted observation's passes are made: on every part, their results summed in part
/// order (so a run is reproducible to the bit).
pub trait PartPasses: Send + Sync {
    /// Names the parts in logs and messages ("3 parts on a Dask cluster").
    fn describe(&self) -> String;
    /// The summed uv density of the parts.
    fn density(&self, pass: &PartPass) -> Result<DensityGrid>;
    /// The summed images of the parts.
    fn images(&self, pass: &PartPass, rule: &WeightRule) -> Result<PartImages>;
    /// The summed `Re{Phi^H Phi x}` of the parts.
    fn apply_normal(&self, pass: &PartPass, rule: &WeightRule, x: &[f64]) -> Result<Vec<f64>>;
}

/// One observation in parts: what imaging must know of all its samples before the first pass
/// (each part's summary, combined), its metadata (the first part's: every part must have the
/// same phase centre), and where its passes are made.
pub struct PartedObservation {
    pub id: String,
    pub meta: ObservationMeta,
    pub summary: VisSummary,
    pub passes: Box<dyn PartPasses>,
}

impl PartedObservation {
    /// From each part's metadata and summary, in part order: an error naming the part whose
    /// phase centre or telescope differs from the first's.
    pub fn new(id: impl Into<String>, parts: &[(String, ObservationMeta, VisSummary)], passes: Box<dyn PartPasses>) -> Result<PartedObservation> {
        let Some((first_name, first, _)) = parts.first() else {
            return Err(Error::parameter("parts", "expected at least one part"));
        };
        let mut summary = VisSummary::empty();
        for (name, meta, part) in parts {
            let same = meta.phase_centre_ra_deg == first.phase_centre_ra_deg && meta.phase_centre_dec_deg == first.phase_centre_dec_deg && meta.telescope == first.telescope;
            if !same {
                return Err(Error::parameter(
                    "parts",
                    format!(
                        "part {name} is of another observation than part {first_name}: phase centre ({}, {}) deg and telescope '{}' against ({}, {}) deg and '{}'",
                        meta.phase_centre_ra_deg, meta.phase_centre_dec_deg, meta.telescope, first.phase_centre_ra_deg, first.phase_centre_dec_deg, first.telescope
                    ),
                ));
            }
            summary.merge(part);
        }
        if summary.samples == 0 {
            return Err(Error::parameter("parts", format!("the {} parts hold no unflagged visibility with weight: nothing to image", parts.len())));
        }
        Ok(PartedObservation { id: id.into(), meta: first.clone(), summary, passes })
    }
}

/// Parts read in this process, one after the other (each a file read again at each pass, or
/// samples held): what a cluster's workers do, here; the reference the cluster is tested against.
pub struct LocalParts {
    pub parts: Vec<VisSource>,
}

impl PartPasses for LocalParts {
    fn describe(&self) -> String {
        format!("{} parts in this process", self.parts.len())
    }
    fn density(&self, pass: &PartPass) -> Result<DensityGrid> {
        let mut sum: Option<DensityGrid> = None;
        for part in &self.parts {
            let grid = part_density(part, pass)?;
            match &mut sum {
                Some(s) => s.merge(&grid)?,
                None => sum = Some(grid),
            }
        }
        sum.map_or_else(|| DensityGrid::new(pass.weighting()?, pass.size, pass.grid_factor), Ok)
    }
    fn images(&self, pass: &PartPass, rule: &WeightRule) -> Result<PartImages> {
        let mut sum = PartImages::default();
        for part in &self.parts {
            sum.add(&part_images(part, pass, rule)?)?;
        }
        Ok(sum)
    }
    fn apply_normal(&self, pass: &PartPass, rule: &WeightRule, x: &[f64]) -> Result<Vec<f64>> {
        let mut sum = vec![0.0; x.len()];
        for part in &self.parts {
            add_to(&mut sum, &part_apply_normal(part, pass, rule, x)?);
        }
        Ok(sum)
    }
}

fn add_to(sum: &mut [f64], part: &[f64]) {
    sum.iter_mut().zip(part).for_each(|(s, p)| *s += p);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pass_and_a_weighting_rule_travel_unchanged() {
        let geometry = ImageGeometry::new(64, 1e-5).unwrap();
        let pass = PartPass::new(geometry, Weighting::Briggs { robust: -0.5 }, 1.5, true, NufftParams::default(), 3, 1000);
        assert_eq!(PartPass::from_json(&pass.to_json()).unwrap(), pass);
        assert_eq!(pass.weighting().unwrap(), Weighting::Briggs { robust: -0.5 });
        let e = PartPass::from_json("{\"size\": 64}").unwrap_err().to_string();
        assert!(e.contains("part pass"), "{e}");
        // A density gathered in two parts, sent as its raw cells and rebuilt, weights every
        // point as the density of the whole does.
        let points: Vec<(f64, f64)> = (0..500).map(|k| ((k as f64 * 0.37).sin() * 3.0, (k as f64 * 0.11).cos() * 3.0)).collect();
        let scheme = pass.weighting().unwrap();
        let mut whole = DensityGrid::new(scheme, 64, 1.5).unwrap();
        whole.add(points.len(), |k| points[k], |k| 1.0 + k as f64 % 3.0);
        let mut first = DensityGrid::new(scheme, 64, 1.5).unwrap();
        first.add(200, |k| points[k], |k| 1.0 + k as f64 % 3.0);
        let mut second = DensityGrid::new(scheme, 64, 1.5).unwrap();
        second.add(300, |k| points[200 + k], |k| 1.0 + (200 + k) as f64 % 3.0);
        let (cells, sum_w) = second.raw();
        first.merge(&DensityGrid::from_raw(scheme, 64, 1.5, cells.to_vec(), sum_w).unwrap()).unwrap();
        let (whole, summed) = (whole.finish(), first.finish());
        let (cells, f2) = summed.raw();
        let travelled = WeightRule::from_raw(scheme, cells.to_vec(), f2).unwrap();
        for &p in &points {
            let (a, b) = (whole.imaging_weight(p), travelled.imaging_weight(p));
            assert!((a - b).abs() <= 1e-12 * a.abs(), "{a} {b}");
        }
        assert!(WeightRule::from_raw(scheme, vec![1.0; 7], f2).is_err());
        assert!(DensityGrid::from_raw(scheme, 64, 1.5, vec![1.0; 7], 1.0).is_err());
    }
}
