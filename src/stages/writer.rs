//! `kind: writer`: FITS products named like WSClean's (`<prefix>-dirty.fits`, `-psf.fits`,
//! `-model.fits`, `-residual.fits`, and `-image.fits` for CLEAN) with full WCS and beam, and
//! `<prefix>-metrics.json`. A job's products appear together or not at all: they are
//! written into a staging directory and moved into place only when all are complete.

use crate::fits::{write_image, BrightnessUnit, ImageWcs};
use crate::pipeline::{Emit, Job, Stage};
use crate::{Error, Result};
use serde::Deserialize;
use std::path::{Path, PathBuf};

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WriterConfig {
    /// Output prefix; `{job}` is replaced by the job id.
    #[serde(default = "prefix")]
    prefix: String,
}

fn prefix() -> String {
    "{job}".into()
}

pub struct WriterStage {
    prefix: String,
}

impl WriterStage {
    pub fn new(config: WriterConfig) -> Result<WriterStage> {
        if config.prefix.trim().is_empty() {
            return Err(Error::parameter("prefix", "expected a non-empty output prefix"));
        }
        Ok(WriterStage { prefix: config.prefix })
    }
}

/// Products of one job, staged in a directory beside their final place.
struct Staging {
    dir: PathBuf,
    moves: Vec<(PathBuf, PathBuf)>,
}

impl Staging {
    fn new(target_dir: &Path, job: &str) -> Result<Staging> {
        std::fs::create_dir_all(target_dir).map_err(|e| Error::io(target_dir, e))?;
        let dir = target_dir.join(format!(".r2d2-staging-{job}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        Ok(Staging { dir, moves: Vec::new() })
    }

    /// A staged path for the final file `target`.
    fn file(&mut self, target: PathBuf) -> PathBuf {
        let staged = self.dir.join(target.file_name().expect("products have file names"));
        self.moves.push((staged.clone(), target));
        staged
    }

    fn commit(mut self) -> Result<()> {
        for (from, to) in std::mem::take(&mut self.moves) {
            std::fs::rename(&from, &to).map_err(|e| Error::io(&to, e))?;
        }
        Ok(())
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

impl Stage for WriterStage {
    fn process(&mut self, job: Job, _emit: &mut Emit<'_>) -> Result<()> {
        let im = job.imaging.as_ref().ok_or_else(|| Error::parameter("writer", "the job was never gridded: nothing to write"))?;
        let prefix = PathBuf::from(self.prefix.replace("{job}", &job.id));
        let dir = prefix.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")).to_path_buf();
        let stem = prefix.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| job.id.clone());
        let target = |suffix: &str| dir.join(format!("{stem}-{suffix}"));
        let mut staging = Staging::new(&dir, &job.id)?;
        let n = im.geometry.size;
        let wcs = ImageWcs {
            ra_deg: job.meta.phase_centre_ra_deg,
            dec_deg: job.meta.phase_centre_dec_deg,
            pixel_deg: im.geometry.pixel_rad.to_degrees(),
            freq_hz: im.frequency_hz,
            bandwidth_hz: None,
        };
        let beam = im.beam.as_ref();
        let extra = [("TELESCOP", job.meta.telescope.clone()), ("R2D2ITER", job.iteration.to_string())];
        let mut products: Vec<(&str, &[f64], BrightnessUnit)> = vec![
            ("dirty.fits", &im.dirty, BrightnessUnit::JyPerBeam),
            ("psf.fits", &im.psf, BrightnessUnit::JyPerBeam),
        ];
        if job.iteration > 0 {
            products.push(("model.fits", &im.model, BrightnessUnit::JyPerPixel));
            products.push(("residual.fits", &im.residual, BrightnessUnit::JyPerBeam));
        }
        let restored;
        if job.step_kind.as_deref().is_some_and(|k| k.ends_with("+restore")) {
            if let Some(beam) = beam {
                let smooth = crate::deconv::restore(&im.model, n, beam, im.geometry.pixel_rad);
                restored = smooth.iter().zip(&im.residual).map(|(m, r)| m + r).collect::<Vec<f64>>();
                products.push(("image.fits", &restored, BrightnessUnit::JyPerBeam));
            }
        }
        for (suffix, data, unit) in &products {
            let path = staging.file(target(suffix));
            write_image(&path, data, n, n, &wcs, *unit, beam, &extra)?;
        }
        let metrics = serde_json::json!({
            "job": job.id,
            "iterations": job.metrics,
            "stage_seconds": job.stage_seconds,
            "image_size": n,
            "pixel_arcsec": im.geometry.pixel_arcsec(),
        });
        let path = staging.file(target("metrics.json"));
        std::fs::write(&path, serde_json::to_string_pretty(&metrics).expect("metrics serialise")).map_err(|e| Error::io(&path, e))?;
        staging.commit()?;
        log::info!("job {}: wrote {} products to {}-*", job.id, products.len() + 1, dir.join(&stem).display());
        Ok(())
    }
}
