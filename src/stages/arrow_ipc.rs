//! `kind: arrow-ipc`: visibilities as an Arrow IPC stream (or file) with the Parquet format's
//! columns and metadata, from a file or from standard input (`path: -`): how a calibration
//! process upstream streams batches in. One job, or several with `split_by`. A job of a
//! whole regular file is read again at each pass (nothing the size of the table is held);
//! standard input, a pipe and a split are read once and held.

use crate::job::{emit_parts, emit_streamed, job_id_problem, stem_id, Truth};
use crate::job::{ImageContext, Job, Reads, SourceKind, SourceParams};
use crate::pipeline::{PipelineSpec, Source, StageParams, StageSpec};
use crate::vis::{read_parts, IpcReader, SplitBy, StreamedTable, TableReader, STDIN};
use crate::Result;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// `kind: arrow-ipc`: an Arrow IPC stream or file.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ArrowIpcParams {
    /// An IPC stream or file, or `-` for standard input (stream format).
    pub path: String,
    /// Job id (default: the file name without extension; `stdin` for standard input).
    #[serde(default)]
    pub id: Option<String>,
    /// Ground truth (FITS, Jy/pixel, same grid as the image) for SNR/logSNR per iteration.
    #[serde(default)]
    pub truth: Option<PathBuf>,
    /// Split the table into several jobs by a column.
    #[serde(default)]
    pub split_by: Option<SplitBy>,
    /// Image a stream that ends without its end-of-stream marker (a sender that stopped
    /// between batches), with a warning, instead of failing.
    #[serde(default)]
    pub allow_truncated: bool,
}

impl ArrowIpcParams {
    /// `path` with the defaults of the other keys.
    pub fn new(path: impl Into<String>) -> ArrowIpcParams {
        ArrowIpcParams { path: path.into(), id: None, truth: None, split_by: None, allow_truncated: false }
    }
}

impl StageParams for ArrowIpcParams {
    const KIND: &'static str = "arrow-ipc";
}

impl SourceParams for ArrowIpcParams {
    fn reads(&self) -> Reads {
        Reads::Files(vec![PathBuf::from(&self.path)])
    }
    fn several_jobs(&self) -> Option<String> {
        self.split_by.as_ref().map(|_| "an arrow-ipc source has split_by".to_string())
    }
}

/// The kind, as registered.
pub(super) const KIND: SourceKind<ArrowIpcParams> = SourceKind::new(|params, c| Ok(Box::new(ArrowIpcSource::new(params, c.pipeline, c.stage, c.image().size)?)));

pub struct ArrowIpcSource {
    path: String,
    id: String,
    truth: Option<Truth>,
    split_by: Option<SplitBy>,
    split_key: String,
    allow_truncated: bool,
    reading: bool,
}

impl ArrowIpcSource {
    pub fn new(config: ArrowIpcParams, pipeline: &PipelineSpec, stage: &StageSpec, image_size: usize) -> Result<ArrowIpcSource> {
        let name = &stage.name;
        if config.path != STDIN && !Path::new(&config.path).exists() {
            return Err(pipeline.stage_error(
                name,
                Some("path"),
                &format!("stages.{name}.path: '{}' does not exist (a file, or - for standard input)", config.path),
            ));
        }
        let id = match config.id {
            Some(id) if job_id_problem(&id).is_some() => {
                let problem = job_id_problem(&id).unwrap_or_default();
                return Err(pipeline.stage_error(name, Some("id"), &format!("stages.{name}.id: {problem}")));
            }
            Some(id) => id,
            None if config.path == STDIN => "stdin".into(),
            None => stem_id(Path::new(&config.path)),
        };
        if let Some(split) = &config.split_by {
            split.check().map_err(|m| pipeline.stage_error(name, Some("split_by"), &format!("stages.{name}.split_by.window: {m}")))?;
        }
        let truth = Truth::load(config.truth.as_deref(), image_size)
            .map_err(|e| pipeline.stage_error(name, Some("truth"), &format!("stages.{name}.truth: {e}")))?;
        Ok(ArrowIpcSource { path: config.path, id, truth, split_by: config.split_by, split_key: format!("stages.{name}.split_by"), allow_truncated: config.allow_truncated, reading: false })
    }
}

impl Source<Job> for ArrowIpcSource {
    fn produce(&mut self, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()> {
        self.reading = true;
        let regular_file = self.path != STDIN && std::fs::metadata(&self.path).is_ok_and(|m| m.is_file());
        if regular_file && self.split_by.is_none() {
            let (file, allow_truncated) = (self.path.clone(), self.allow_truncated);
            let reopen = move || -> Result<Box<dyn TableReader>> { Ok(Box::new(IpcReader::open(&file, allow_truncated)?)) };
            let Some(table) = StreamedTable::scan(reopen()?, Box::new(reopen), Some(&crate::vis::spill_dir()), cancelled)? else {
                return Ok(());
            };
            table.stats().log(Path::new(&self.path));
            self.reading = false;
            return emit_streamed(&self.id, table, self.truth.as_ref(), emit);
        }
        let mut reader = IpcReader::open(&self.path, self.allow_truncated)?;
        let Some((parts, stats)) = read_parts(&mut reader, self.split_by.as_ref(), &self.split_key, cancelled)? else {
            return Ok(());
        };
        stats.log(TableReader::source(&reader));
        self.reading = false;
        let source = (self.path != STDIN).then(|| Path::new(&self.path));
        emit_parts(&self.id, TableReader::meta(&reader), parts, self.truth.as_ref(), source, emit)
    }

    fn current_job(&self) -> Option<String> {
        self.reading.then(|| self.id.clone())
    }
}
