//! A pass over one part of an observation ([`part_density`], [`part_images`],
//! [`part_apply_normal`]): a function of the part and a [`PartPass`], run where the part is
//! read; [`LocalParts`] runs them here, part after part, and sums what they give.

use super::data::VisChunk;
use super::parted::{add_to, PartImages, PartPass, PartPasses};
use super::stream::VisSource;
use crate::operator::{DoubledKernelGridder, ImageGeometry, ImageGridder, MeasurementOperator};
use num_complex::Complex64;
use crate::operator::toeplitz::WToeplitzBuilder;
use crate::weighting::{DensityGrid, UvCounts, UvShape, WeightRule, Weighting};
use crate::{Error, Result};
use rayon::prelude::*;

pub(super) fn no_given_weights() -> Error {
    Error::parameter(
        "weighting",
        "`given` uses the imaging weights given with the data (a table's `imaging_weight` column, a .mat file's `nWimag`), and these visibilities carry none: choose natural, uniform or briggs",
    )
}

/// Total weights (natural x imaging, x the given imaging weight for `given`) of a chunk's
/// samples, the rule's uv cuts and tapers applied.
pub fn chunk_weights(chunk: &VisChunk<'_>, geometry: ImageGeometry, rule: &WeightRule) -> Result<Vec<f64>> {
    let n = chunk.len();
    let natural = |k: usize| f64::from(chunk.weight[k]);
    let point = |k: usize| geometry.uv_to_phase(chunk.u[k], chunk.v[k]);
    if rule.scheme() == Weighting::Given {
        if chunk.imaging_weight.len() != n {
            return Err(no_given_weights());
        }
        return Ok((0..n).into_par_iter().map(|k| natural(k) * f64::from(chunk.imaging_weight[k]) * rule.selection(point(k))).collect());
    }
    Ok((0..n).into_par_iter().map(|k| rule.imaging_weight(point(k)) * natural(k)).collect())
}

/// The uv density of a part's samples on the weighting grid (uniform and Briggs; an empty
/// grid for natural and given weighting).
pub fn part_density(vis: &VisSource, pass: &PartPass) -> Result<DensityGrid> {
    Ok(density_and_counts(vis, pass, None)?.0)
}

/// [`part_density`], and with `uv`, how many samples its cuts (and the grid's edge) leave
/// out: one pass over the samples where either is asked for, none otherwise.
pub(crate) fn density_and_counts(vis: &VisSource, pass: &PartPass, uv: Option<&UvShape>) -> Result<(DensityGrid, Option<UvCounts>)> {
    let (geometry, weighting) = (pass.geometry()?, pass.weighting()?);
    let mut density = DensityGrid::new(weighting, geometry.size, pass.grid_factor)?;
    let mut counts = uv.map(|_| UvCounts::default());
    if weighting.needs_density() || counts.is_some() {
        vis.for_each_chunk(pass.chunk_rows, &mut |c| {
            let point = |k: usize| geometry.uv_to_phase(c.u[k], c.v[k]);
            density.add(c.len(), point, |k| f64::from(c.weight[k]));
            if let (Some(counts), Some(uv)) = (&mut counts, uv) {
                (0..c.len()).for_each(|k| counts.add(uv, point(k)));
            }
            Ok(())
        })?;
    }
    Ok((density, counts))
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
        let (chunk_dirty, chunk_psf) = op.dirty_image_and_psf(c.vis);
        add_to(&mut dirty, &chunk_dirty);
        add_to(&mut psf, &chunk_psf);
        planes = planes.max(op.w_planes());
        samples += c.len() as u64;
        drop(op);
        doubled.add(c.u, c.v, &weight, c.vis)
    })?;
    let (_, _, psf_2n) = doubled.unnormalised();
    Ok(PartImages { dirty, psf, psf_2n, samples, planes })
}

/// The dirty image of `vis` weighted by `rule` through each chunk's w-gridded operator, with
/// the kernels of the w-aware Toeplitz form gridded by `builder` in the same pass (the
/// residual update's `D` thereafter: the samples are not needed again); not normalised, the
/// PSFs left empty (the finished kernels give them).
pub fn w_toeplitz_images(vis: &VisSource, pass: &PartPass, rule: &WeightRule, builder: &mut WToeplitzBuilder) -> Result<PartImages> {
    let (geometry, nufft) = (pass.geometry()?, pass.nufft());
    let mut dirty = vec![0.0; geometry.pixels()];
    let (mut samples, mut planes) = (0u64, None);
    vis.for_each_chunk(pass.chunk_rows, &mut |c| {
        let weight = chunk_weights(&c, geometry, rule)?;
        let op = MeasurementOperator::part_for_mode(true, geometry, c.u, c.v, c.w, &weight, nufft, pass.threads)?;
        add_to(&mut dirty, &op.dirty_image(c.vis));
        planes = planes.max(op.w_planes());
        samples += c.len() as u64;
        drop(op);
        builder.add(c.u, c.v, c.w, &weight)
    })?;
    Ok(PartImages { dirty, psf: Vec::new(), psf_2n: Vec::new(), samples, planes })
}

/// The 2N PSF of a part's samples with each total weight times `factor(w)` (not scaled by
/// `kappa`): a kernel of the residual update's Taylor series in w (`crate::operator::taylor`) where
/// the samples are read from their file at each pass.
pub fn part_doubled_psf_of(vis: &VisSource, pass: &PartPass, rule: &WeightRule, factor: impl Fn(f64) -> Complex64 + Sync) -> Result<Vec<f64>> {
    let geometry = pass.geometry()?;
    let mut gridder = DoubledKernelGridder::new(geometry, pass.nufft(), pass.threads)?;
    vis.for_each_chunk(pass.chunk_rows, &mut |c| {
        let weight = chunk_weights(&c, geometry, rule)?;
        gridder.add(c.u, c.v, &weight, |k| factor(c.w[k]))
    })?;
    Ok(gridder.finish(1.0))
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
    fn w_toeplitz_images(&self, pass: &PartPass, rule: &WeightRule, builder: &mut WToeplitzBuilder) -> Result<Option<PartImages>> {
        let mut sum = PartImages::default();
        for part in &self.parts {
            sum.add(&w_toeplitz_images(part, pass, rule, builder)?)?;
        }
        Ok(Some(sum))
    }
    fn apply_normal(&self, pass: &PartPass, rule: &WeightRule, x: &[f64]) -> Result<Vec<f64>> {
        let mut sum = vec![0.0; x.len()];
        for part in &self.parts {
            add_to(&mut sum, &part_apply_normal(part, pass, rule, x)?);
        }
        Ok(sum)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nufft::NufftParams;

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

    /// A part of 200 samples, its `w` and weights scaled by `w` and `weight`.
    fn part_table(w: f64, weight: f64) -> crate::vis::VisTable {
        let mut t = crate::vis::table::tests::test_table(200);
        t.w_m.iter_mut().for_each(|x| *x *= w);
        t.weight.iter_mut().for_each(|x| *x *= weight);
        t
    }

    /// A part replaced between passes by one of as many samples with other values (`w` x 0.9,
    /// the weights doubled), as a Dask worker opens it for each pass: the pass fails naming the
    /// part, checked against what its first reading found (which travels as text); before, only
    /// the sum of the parts' sample counts was compared, and the pass imaged the new table.
    #[test]
    fn a_part_changed_between_passes_fails_the_pass_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("part0.parquet");
        let meta = crate::vis::ObservationMeta::new(10.0, 20.0, "VLA");
        crate::vis::write_parquet(&path, &part_table(1.0, 1.0), &meta).unwrap();
        let options = crate::vis::OpenOptions::default();
        let (_, first) = crate::parts::open_source(&path, &options).unwrap();
        let check = first.part_check().expect("a part read first has a check");
        let check = crate::parts::PartCheck::from_text(&check.to_text()).unwrap();
        assert_eq!(Some(check), first.part_check());
        let geometry = ImageGeometry::new(64, 1e-4).unwrap();
        let pass = PartPass::new(geometry, Weighting::Natural, 1.0, true, NufftParams::default(), 1, 64);
        let rule = part_density(&first, &pass).unwrap().finish();
        // Unchanged, every pass reads it.
        let again = crate::parts::open_pass(&path, &options, Some(&check)).unwrap();
        assert_eq!(part_images(&again, &pass, &rule).unwrap().samples, 200);
        crate::vis::write_parquet(&path, &part_table(0.9, 2.0), &meta).unwrap();
        let changed = crate::parts::open_pass(&path, &options, Some(&check)).unwrap();
        for e in [part_images(&changed, &pass, &rule).unwrap_err(), part_apply_normal(&changed, &pass, &rule, &vec![0.0; 64 * 64]).unwrap_err()] {
            let e = e.to_string();
            assert!(e.contains("part0.parquet") && e.contains("changed between passes") && e.contains("as many samples as its first reading (200)"), "{e}");
        }
        // Unchecked, as every pass was before, the changed part images without a word.
        let unchecked = crate::parts::open_pass(&path, &options, None).unwrap();
        assert_eq!(part_images(&unchecked, &pass, &rule).unwrap().samples, 200);
        assert!(crate::parts::PartCheck::from_text("200:12").is_err());
    }
}
