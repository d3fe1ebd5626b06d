//! `kind: parquet`: one imaging job per Parquet file (a path, a list, or glob patterns),
//! read one record batch at a time.

use crate::pipeline::config::{PipelineConfig, StageConfig};
use crate::pipeline::{Job, Source};
use crate::vis::{VisReader, Visibilities, DEFAULT_BATCH_ROWS};
use crate::Result;
use serde::Deserialize;
use std::path::PathBuf;

#[derive(Deserialize)]
#[serde(untagged)]
pub enum Files {
    One(String),
    Many(Vec<String>),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParquetConfig {
    /// A file, a list of files, or glob patterns (relative to the working directory).
    files: Files,
    #[serde(default = "batch_rows")]
    batch_rows: usize,
    /// Ground truth (FITS, Jy/pixel, same grid as the image) for SNR/logSNR per iteration.
    #[serde(default)]
    truth: Option<PathBuf>,
}

fn batch_rows() -> usize {
    DEFAULT_BATCH_ROWS
}

pub struct ParquetSource {
    paths: Vec<PathBuf>,
    batch_rows: usize,
    truth: Option<Vec<f64>>,
}

impl ParquetSource {
    pub fn new(config: ParquetConfig, pipeline: &PipelineConfig, stage: &StageConfig) -> Result<ParquetSource> {
        let patterns = match config.files {
            Files::One(f) => vec![f],
            Files::Many(v) => v,
        };
        let mut paths = Vec::new();
        for pattern in &patterns {
            let matches: Vec<PathBuf> = glob::glob(pattern)
                .map_err(|e| pipeline.stage_error(&stage.name, Some("files"), &format!("stages.{}.files: bad pattern '{pattern}': {e}", stage.name)))?
                .filter_map(|p| p.ok())
                .collect();
            if matches.is_empty() {
                return Err(pipeline.stage_error(
                    &stage.name,
                    Some("files"),
                    &format!("stages.{}.files: '{pattern}' matches no file", stage.name),
                ));
            }
            paths.extend(matches);
        }
        let truth = match &config.truth {
            Some(path) => Some(crate::fits::read_image(path)?.data),
            None => None,
        };
        Ok(ParquetSource { paths, batch_rows: config.batch_rows.max(1), truth })
    }
}

impl Source for ParquetSource {
    fn produce(&mut self, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()> {
        for path in &self.paths {
            let mut reader = VisReader::open(path, self.batch_rows)?;
            let mut vis = Visibilities::default();
            for batch in reader.by_ref() {
                if cancelled() {
                    return Ok(());
                }
                vis.push_batch(batch?);
            }
            let id = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "job".into());
            log::info!("job {id}: {}: {}", path.display(), reader.stats());
            let mut job = Job::new(id, reader.meta().clone(), vis);
            if let Some(t) = &self.truth {
                job.truth_dynamic_range = crate::metrics::dynamic_range(t);
                job.truth = Some(t.clone());
            }
            emit(job)?;
        }
        Ok(())
    }
}
