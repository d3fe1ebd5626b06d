//! The products of an observation imaged in channel groups (WSClean's `-channels-out`): each
//! group's (`NAME-0000-*`, ...), the whole band's (`NAME-MFS-*`, with `-join-channels`), and a
//! FITS cube of each image product (`NAME-cube-*`), written together or not at all.

use super::products::{check_spares_inputs, prefix_parts, JobProducts, ProductSet, WriteOptions};
use crate::fits::{write_cube, Beam, BrightnessUnit, ImageWcs};
use crate::staging::Staging;
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// Every group's products, lowest frequency first, and the whole band's.
pub struct ChannelProducts {
    /// One per channel group, lowest frequency first, all on one grid.
    pub channels: Vec<JobProducts>,
    /// The whole band imaged as one on the same grid (WSClean's `-join-channels` MFS image).
    pub mfs: Option<JobProducts>,
}

/// The name part of group `index`'s products (`0000`), as WSClean names them.
pub fn group_label(index: usize) -> String {
    format!("{index:04}")
}

/// The name part of the whole band's products.
pub const MFS_LABEL: &str = "MFS";

/// The name part of the cubes.
pub const CUBE_LABEL: &str = "cube";

impl ChannelProducts {
    /// Refuses a prefix at which any product of the groups, the whole band or the cubes
    /// would replace one of `inputs` (checked before imaging, as a single job's are).
    pub fn check_spares_inputs(prefix: &str, id: &str, count: usize, inputs: &[&Path], set: ProductSet) -> Result<()> {
        let labels = (0..count).map(group_label).chain([MFS_LABEL.to_string(), CUBE_LABEL.to_string()]);
        for label in labels {
            check_spares_inputs(&format!("{prefix}-{label}"), id, inputs, set)?;
        }
        Ok(())
    }

    /// Writes every group's products (`<prefix>-0000-dirty.fits`, ...), the whole band's
    /// (`<prefix>-MFS-...`) and the cubes (`<prefix>-cube-dirty.fits`, ...), all appearing
    /// together or none; returns the files written, and why no cubes were, where they were not.
    pub fn write(&self, prefix: &str, options: &WriteOptions, set: ProductSet) -> Result<(Vec<PathBuf>, Option<String>)> {
        let first = self.channels.first().ok_or_else(|| Error::parameter("channels_out", "no channel group was imaged"))?;
        crate::fits::check_output_prefix(prefix).map_err(|m| Error::parameter("name", m))?;
        let (dir, stem) = prefix_parts(prefix, &first.id);
        let mut staging = Staging::new(&dir)?;
        for (index, job) in self.channels.iter().enumerate() {
            job.stage_into(&mut staging, &dir, &format!("{stem}-{}", group_label(index)), options, set)?;
        }
        if let Some(mfs) = &self.mfs {
            mfs.stage_into(&mut staging, &dir, &format!("{stem}-{MFS_LABEL}"), options, set)?;
        }
        let no_cubes = match cube_axis(&self.channels) {
            Ok(axis) => {
                self.stage_cubes(&mut staging, &dir.join(format!("{stem}-{CUBE_LABEL}")), axis)?;
                None
            }
            Err(why) => Some(why),
        };
        let written = staging.commit()?;
        log::info!("wrote {} files of {} channel groups to {}-*", written.len(), self.channels.len(), dir.join(&stem).display());
        Ok((written, no_cubes))
    }

    /// A cube of each image product every group has: its planes the groups', in order.
    fn stage_cubes(&self, staging: &mut Staging, prefix: &Path, (start_hz, step_hz): (f64, f64)) -> Result<()> {
        let first = &self.channels[0];
        let n = first.size;
        let wcs = ImageWcs { freq_hz: Some(start_hz), bandwidth_hz: Some(step_hz), ..first.wcs };
        // One beam where every group has the same (a beam given by the request); otherwise
        // each plane's is in its group's files and listed here, and the cube carries none.
        let beams: Vec<Option<Beam>> = self.channels.iter().map(|c| c.beam).collect();
        let common = beams[0].filter(|b| beams.iter().all(|o| o.is_some_and(|c| same_beam(&c, b))));
        let mut extra = first.extra_keywords();
        extra.push(("HISTORY", format!("cube of {} channel groups (WSClean's -channels-out): plane k is the group NAME-k's image; CDELT3 is the step between the groups' centres", self.channels.len())));
        if common.is_none() {
            for (k, beam) in beams.iter().enumerate() {
                let text = beam.map_or("none".to_string(), |b| format!("{:.6e} x {:.6e} deg, PA {:.3} deg", b.major_deg, b.minor_deg, b.pa_deg));
                extra.push(("HISTORY", format!("plane {k} restoring beam: {text}")));
            }
        }
        type Pick = fn(&JobProducts) -> Option<&Vec<f32>>;
        let products: [(&str, Pick, BrightnessUnit); 5] = [
            ("dirty", |c| Some(&c.dirty), BrightnessUnit::JyPerBeam),
            ("psf", |c| Some(&c.psf), BrightnessUnit::JyPerBeam),
            ("model", |c| c.model.as_ref(), BrightnessUnit::JyPerPixel),
            ("residual", |c| c.residual.as_ref(), BrightnessUnit::JyPerBeam),
            ("image", |c| c.image.as_ref(), BrightnessUnit::JyPerBeam),
        ];
        for (name, pick, unit) in products {
            let planes: Option<Vec<&Vec<f32>>> = self.channels.iter().map(pick).collect();
            let Some(planes) = planes else { continue };
            let cube: Vec<f64> = planes.iter().flat_map(|p| p.iter().map(|&v| f64::from(v))).collect();
            let target = PathBuf::from(format!("{}-{name}.fits", prefix.display()));
            staging.write(target, |path| write_cube(path, &cube, n, n, planes.len(), &wcs, unit, common.as_ref(), &extra))?;
        }
        Ok(())
    }
}

fn same_beam(a: &Beam, b: &Beam) -> bool {
    let close = |x: f64, y: f64| (x - y).abs() <= 1e-9 * x.abs().max(y.abs()).max(1e-300);
    close(a.major_deg, b.major_deg) && close(a.minor_deg, b.minor_deg) && close(a.pa_deg, b.pa_deg)
}

/// The cube's FREQ axis: the first group's centre and the step between centres, or why the
/// groups' centres are not evenly spaced (a linear axis would misplace planes) or unknown.
fn cube_axis(channels: &[JobProducts]) -> std::result::Result<(f64, f64), String> {
    let centres: Option<Vec<f64>> = channels.iter().map(|c| c.wcs.freq_hz).collect();
    let centres = centres.ok_or("a channel group's frequency is unknown")?;
    match centres.as_slice() {
        [] => Err("no channel group".into()),
        [only] => Ok((*only, channels[0].wcs.bandwidth_hz.unwrap_or(1.0))),
        [first, .., last] => {
            let step = (last - first) / (centres.len() - 1) as f64;
            let off = centres.iter().enumerate().map(|(k, f)| (f - (first + k as f64 * step)).abs()).fold(0.0, f64::max);
            if !(step.abs() > 0.0) || off > 1e-6 * step.abs() {
                return Err(format!(
                    "the channel groups' centres are not evenly spaced (off a linear axis by up to {off:.4e} Hz, a {:.3e} of the step): a channel count that the number of groups divides gives even groups",
                    off / step.abs()
                ));
            }
            Ok((*first, step))
        }
    }
}
