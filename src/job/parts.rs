//! Jobs from the parts of a table: their ids, the ground truth they share, and the inputs
//! their products must never replace.

use super::state::Job;
use crate::fits::ImageWcs;
use crate::vis::{ObservationMeta, Part, StreamedTable, VisSource};
use std::sync::Arc;
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// The ground truth shared by a source's jobs, read when the source is built.
pub struct Truth {
    image: Vec<f64>,
    dynamic_range: Option<f64>,
    path: PathBuf,
    wcs: Option<ImageWcs>,
}

impl Truth {
    /// Reads the truth for `size x size` images; another size is an error (it was ignored,
    /// leaving the metrics without SNR and the user without a word).
    pub fn load(path: Option<&Path>, size: usize) -> Result<Option<Truth>> {
        let Some(path) = path else { return Ok(None) };
        let image = crate::fits::read_image(path)?;
        if (image.nx, image.ny) != (size, size) {
            return Err(Error::input(
                path,
                format!("the truth is {} x {} pixels, but the pipeline images {size} x {size} (image.size): it must be on the image's grid", image.nx, image.ny),
            ));
        }
        Ok(Some(Truth { dynamic_range: crate::metrics::dynamic_range(&image.data), image: image.data, path: path.to_path_buf(), wcs: image.wcs }))
    }
}

/// Emits one job per part, ids `<id>` or `<id>-<suffix>`; the parts of a split share the
/// longest baseline of them all, which sets their pixel size ([`Job::split_max_uv`]).
/// `source` is the file the parts were read from (none for memory and standard input): with the
/// truth's file it is the job's inputs, which its products never replace.
pub fn emit_parts(
    id: &str,
    meta: &ObservationMeta,
    parts: Vec<Part>,
    truth: Option<&Truth>,
    source: Option<&Path>,
    emit: &mut dyn FnMut(Job) -> Result<()>,
) -> Result<()> {
    let split_max_uv = parts.iter().any(|p| p.suffix.is_some()).then(|| parts.iter().map(|p| p.vis.max_uv()).fold(0.0, f64::max));
    if let Some(max_uv) = split_max_uv {
        log::info!("{id}: the {} jobs of the split share one pixel size, set by their longest baseline ({max_uv:.6e} wavelengths)", parts.len());
    }
    for part in parts {
        let job_id = match &part.suffix {
            Some(s) => format!("{id}-{s}"),
            None => id.to_string(),
        };
        log::info!("job {job_id}: {} visibilities", part.vis.len());
        let mut meta = meta.clone();
        if part.suffix.is_some() {
            // The band of the whole selection is not a part's: its samples' frequencies say it.
            meta.extra.remove(crate::vis::BAND_EDGES_KEY);
        }
        let mut job = Job::new(job_id, meta, part.vis);
        job.split_max_uv = split_max_uv;
        if let Some(t) = truth {
            job.truth = Some(t.image.clone());
            job.truth_dynamic_range = t.dynamic_range;
            job.truth_wcs = t.wcs;
            job.inputs.push(t.path.clone());
        }
        job.inputs.extend(source.map(Path::to_path_buf));
        emit(job)?;
    }
    Ok(())
}

/// Emits the one job of a table read again from its file at each pass.
pub fn emit_streamed(
    id: &str,
    table: StreamedTable,
    truth: Option<&Truth>,
    emit: &mut dyn FnMut(Job) -> Result<()>,
) -> Result<()> {
    if table.stats().kept() == 0 {
        return Err(Error::input(table.path(), crate::vis::nothing_to_image(table.stats())));
    }
    log::info!("job {id}: {} visibilities, read from {} at each pass", table.stats().kept(), table.read_by_each_pass());
    let path = table.path().to_path_buf();
    let meta = table.meta().clone();
    let mut job = Job::from_source(id, meta, VisSource::Streamed(Arc::new(table)));
    job.inputs.push(path);
    with_truth(&mut job, truth);
    emit(job)
}

/// Emits the one job of an observation in parts gridded where they live.
pub fn emit_parted(observation: crate::vis::PartedObservation, truth: Option<&Truth>, emit: &mut dyn FnMut(Job) -> Result<()>) -> Result<()> {
    log::info!("job {}: {} visibilities in {}", observation.id, observation.summary.samples, observation.passes.describe());
    let (id, meta) = (observation.id.clone(), observation.meta.clone());
    let mut job = Job::from_source(id, meta, VisSource::Parts(Arc::new(observation)));
    with_truth(&mut job, truth);
    emit(job)
}

fn with_truth(job: &mut Job, truth: Option<&Truth>) {
    if let Some(t) = truth {
        job.truth = Some(t.image.clone());
        job.truth_dynamic_range = t.dynamic_range;
        job.truth_wcs = t.wcs;
        job.inputs.push(t.path.clone());
    }
}

/// Why `id` cannot name a job, if it cannot: it becomes a file name inside the writer's
/// prefix (`{job}`), so it must be one name, neither empty nor a path.
pub fn job_id_problem(id: &str) -> Option<String> {
    if id.trim().is_empty() {
        return Some("expected a non-empty job id".into());
    }
    if id.contains(['/', '\\']) || id == "." || id == ".." {
        return Some(format!("job id '{id}' is a path: a job id is one file name (it replaces {{job}} in the writer's prefix, and must not lead out of its directory)"));
    }
    None
}

/// A table's job id: the file name without its extension.
pub fn stem_id(path: &Path) -> String {
    path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "job".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn job_ids_are_one_file_name() {
        assert_eq!(job_id_problem("obs-field01"), None);
        for bad in ["", "  ", "a/b", "../x", "..", ".", "a\\b"] {
            assert!(job_id_problem(bad).is_some(), "{bad:?}");
        }
    }
}
