//! The writer's `model_column`: a job's final model predicted into the MeasurementSet it was
//! read from.

use super::state::Job;
use crate::ms::{write_model_column, ModelReport, ModelTarget, Origin, ORIGIN_KEY};
use crate::operator::WTermMode;
use crate::{Error, Result};

/// The writer's `model_column` for one job: predicts the job's final model into `column` of
/// the MS it was read from (the origin in its metadata), with the gridder's default NUFFT
/// accuracy.
pub fn write_job_model(job: &Job, column: &str) -> Result<ModelReport> {
    let origin: Origin = job
        .meta
        .extra
        .get(ORIGIN_KEY)
        .map(|text| serde_json::from_str(text))
        .transpose()
        .map_err(|e| Error::parameter("model_column", format!("job '{}': unreadable MS origin in its metadata: {e}", job.id)))?
        .ok_or_else(|| {
            Error::parameter("model_column", format!("job '{}' was not read from a MeasurementSet (`kind: ms`): there is no MS to write `{column}` into", job.id))
        })?;
    let imaging = job.imaging.as_ref().ok_or_else(|| Error::parameter("model_column", format!("job '{}' was never gridded", job.id)))?;
    // The prediction the images were made with: the gridder's NUFFT, and the w-term where it
    // included it.
    let target = ModelTarget {
        column,
        geometry: imaging.geometry,
        model: &imaging.model,
        nufft: imaging.nufft,
        w_term: if imaging.w_term { WTermMode::On } else { WTermMode::Off },
        threads: 0,
    };
    let report = write_model_column(&origin, &target)?;
    log::info!(
        "job {}: wrote `{column}` of {} ({} rows, {} samples{})",
        job.id,
        origin.path.display(),
        report.rows,
        report.samples,
        if report.beyond_nyquist > 0 { format!(", {} beyond the image's Nyquist limit left zero", report.beyond_nyquist) } else { String::new() }
    );
    Ok(report)
}
