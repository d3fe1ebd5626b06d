//! `kind: parquet`: one imaging job per Parquet file (a path, a list, or glob patterns), or
//! several per file with `split_by` (time windows, frequency channels), read one record
//! batch at a time. A file of another single-file format (a MATLAB .mat observation) is read
//! by its content through the one reader (`vis::open`).

use super::params::{Files, ParquetParams};
use crate::job::{emit_parts, emit_streamed, stem_id, Truth};
use crate::vis::{format_of, open, read_parts, OpenOptions, SplitBy, StreamedTable, TableFormat, TableReader};
use crate::job::Job;
use crate::pipeline::{PipelineSpec, Source, StageSpec};
use crate::vis::VisReader;
use crate::Result;
use std::path::PathBuf;

pub struct ParquetSource {
    paths: Vec<PathBuf>,
    batch_rows: usize,
    truth: Option<Truth>,
    split_by: Option<SplitBy>,
    split_key: String,
    current_job: Option<String>,
}

impl ParquetSource {
    pub fn new(config: ParquetParams, pipeline: &PipelineSpec, stage: &StageSpec, image_size: usize) -> Result<ParquetSource> {
        let name = &stage.name;
        let patterns = match config.files {
            Files::One(f) => vec![f],
            Files::Many(v) => v,
        };
        if patterns.is_empty() {
            return Err(pipeline.stage_error(name, Some("files"), &format!("stages.{name}.files: expected at least one file or glob pattern")));
        }
        let mut paths = Vec::new();
        for pattern in &patterns {
            let matches: Vec<PathBuf> = glob::glob(pattern)
                .map_err(|e| pipeline.stage_error(name, Some("files"), &format!("stages.{name}.files: bad pattern '{pattern}': {e}")))?
                .filter_map(|p| p.ok())
                .collect();
            if matches.is_empty() {
                return Err(pipeline.stage_error(name, Some("files"), &format!("stages.{name}.files: '{pattern}' matches no file")));
            }
            paths.extend(matches);
        }
        // Jobs are named after their files (products too): two files of one name would be one
        // job, the second overwriting the first's products.
        let mut ids: std::collections::HashMap<String, &PathBuf> = std::collections::HashMap::new();
        for path in &paths {
            if let Some(first) = ids.insert(stem_id(path), path) {
                let message = format!(
                    "stages.{name}.files: {} and {} would both be job '{}' (a job is named after its file, without directory or extension): rename one, or image them in separate runs",
                    first.display(),
                    path.display(),
                    stem_id(path)
                );
                return Err(pipeline.stage_error(name, Some("files"), &message));
            }
        }
        let split_key = format!("stages.{name}.split_by");
        if let Some(split) = &config.split_by {
            split.check().map_err(|m| pipeline.stage_error(name, Some("split_by"), &format!("stages.{name}.split_by.window: {m}")))?;
            // Before any work starts: every file's footer must have the column.
            for path in &paths {
                let reader = VisReader::open(path, 1)?;
                split.check_schema(reader.schema()).map_err(|m| {
                    pipeline.stage_error(name, Some("split_by"), &format!("{split_key}.column: {}: {m}", path.display()))
                })?;
            }
        }
        let truth = Truth::load(config.truth.as_deref(), image_size)
            .map_err(|e| pipeline.stage_error(name, Some("truth"), &format!("stages.{name}.truth: {e}")))?;
        Ok(ParquetSource { paths, batch_rows: config.batch_rows.max(1), truth, split_by: config.split_by, split_key, current_job: None })
    }
}

impl Source<Job> for ParquetSource {
    fn produce(&mut self, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()> {
        for path in &self.paths {
            let id = stem_id(path);
            self.current_job = Some(id.clone());
            let format = format_of(path)?;
            if self.split_by.is_none() && format != TableFormat::Mat {
                // One job of the whole table, read again at each pass: nothing the size of the
                // table is held (a .mat file is read whole by its format).
                let (file, batch_rows) = (path.clone(), self.batch_rows);
                let reopen = move || open(&file, &OpenOptions { batch_rows, ..OpenOptions::default() });
                let Some(table) = StreamedTable::scan(reopen()?, Box::new(reopen), Some(&crate::vis::spill_dir()), cancelled)? else {
                    return Ok(());
                };
                table.stats().log(path);
                emit_streamed(&id, table, self.truth.as_ref(), emit)?;
                continue;
            }
            let extra: Vec<&str> = self.split_by.iter().map(|s| s.column.as_str()).collect();
            // A Parquet table reads only the columns used; any other single-file format (a .mat)
            // through the one reader, by its content.
            let mut reader: Box<dyn TableReader> = if format == TableFormat::Parquet {
                Box::new(VisReader::open_with_columns(path, self.batch_rows, &extra)?)
            } else {
                open(path, &OpenOptions { batch_rows: self.batch_rows, ..OpenOptions::default() })?
            };
            let Some((parts, stats)) = read_parts(reader.as_mut(), self.split_by.as_ref(), &self.split_key, cancelled)? else {
                return Ok(());
            };
            stats.log(path);
            emit_parts(&id, reader.meta(), parts, self.truth.as_ref(), Some(path), emit)?;
        }
        self.current_job = None;
        Ok(())
    }

    fn current_job(&self) -> Option<String> {
        self.current_job.clone()
    }
}
