//! One observation kept in parts that are gridded where they live (Dask workers, or this
//! process part after part), its image-domain loop run once: every pass over the samples is a
//! sum over the parts ([`PartPasses`]). What a pass needs beside its part ([`PartPass`],
//! which travels to the part as JSON) and what it gives ([`PartImages`]); the passes
//! themselves are in `parts.rs`.

use super::data::{ObservationMeta, VisSummary};
use crate::nufft::NufftParams;
use crate::operator::{normalise_by_psf_peak, ImageGeometry};
use crate::operator::toeplitz::WToeplitzBuilder;
use crate::weighting::{DensityGrid, UvShape, WeightRule, Weighting, WeightingScheme};
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
    /// The uv cuts and tapers of the job's weighting rule (none by default).
    #[serde(default)]
    pub uv: UvShape,
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
            uv: UvShape::default(),
        }
    }

    /// The job's weighting rule from what [`WeightRule::raw`] gave of it, with this pass's uv
    /// cuts and tapers: the rule where a part is weighted.
    pub fn rule(&self, density: Vec<f64>, f2: f64) -> Result<WeightRule> {
        Ok(WeightRule::from_raw(self.weighting()?, density, f2)?.with_uv(self.uv))
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

/// Where a parted observation's passes are made: on every part, their results summed in part
/// order (so a run is reproducible to the bit).
pub trait PartPasses: Send + Sync {
    /// Names the parts in logs and messages ("3 parts on a Dask cluster").
    fn describe(&self) -> String;
    /// The summed uv density of the parts.
    fn density(&self, pass: &PartPass) -> Result<DensityGrid>;
    /// The summed images of the parts.
    fn images(&self, pass: &PartPass, rule: &WeightRule) -> Result<PartImages>;
    /// The parts' dirty images (as [`w_toeplitz_images`](super::w_toeplitz_images)), with
    /// the kernels of the w-aware Toeplitz form of their `D` added to `builder` in the same
    /// pass; `None` where the parts cannot add to one builder (they live in other processes):
    /// the residual update then runs through the operator over the parts.
    fn w_toeplitz_images(&self, _pass: &PartPass, _rule: &WeightRule, _builder: &mut WToeplitzBuilder) -> Result<Option<PartImages>> {
        Ok(None)
    }
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

pub(super) fn add_to(sum: &mut [f64], part: &[f64]) {
    sum.iter_mut().zip(part).for_each(|(s, p)| *s += p);
}

