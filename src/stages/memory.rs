//! `kind: arrow`: observations handed in by the embedding program as Arrow record batches
//! (`Engine::run`'s inputs), one job per input, or several with `split_by`. The batches have
//! the Parquet format's columns and its observation metadata in the schema's metadata, and
//! are checked exactly as an Arrow IPC stream's are.

use crate::ingest::{emit_parts, read_parts, SplitBy, TableReader, Truth};
use crate::pipeline::registry::BuildContext;
use crate::pipeline::{Job, MemoryInput, Source, StageParams};
use crate::vis::{validate_schema, ObservationMeta};
use crate::{Error, Result};
use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// `kind: arrow`: the run's in-memory inputs.
#[derive(Clone, Debug, Default, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct ArrowParams {
    /// Ground truth (FITS, Jy/pixel, same grid as the image) for SNR/logSNR per iteration.
    pub truth: Option<PathBuf>,
    /// Split each input into several jobs by a column.
    pub split_by: Option<SplitBy>,
}

impl StageParams for ArrowParams {
    const KIND: &'static str = "arrow";
}

pub struct MemorySource {
    inputs: Vec<MemoryInput>,
    truth: Option<Truth>,
    split_by: Option<SplitBy>,
    split_key: String,
    current_job: Option<String>,
}

impl MemorySource {
    pub fn new(config: ArrowParams, ctx: &BuildContext<'_>) -> Result<MemorySource> {
        let inputs = match ctx.take_inputs() {
            Some(inputs) => inputs,
            None if ctx.validating() => Vec::new(),
            None => return Err(ctx.error(Some("kind"), "kind 'arrow' reads the run's in-memory inputs, which another source took already")),
        };
        if inputs.is_empty() && !ctx.validating() {
            return Err(ctx.error(Some("kind"), "kind 'arrow' reads in-memory inputs (Engine::run), and the run was given none"));
        }
        let mut ids = std::collections::HashSet::new();
        for input in &inputs {
            if let Some(problem) = crate::ingest::job_id_problem(&input.id) {
                return Err(ctx.error(None, format!("an in-memory input: {problem}")));
            }
            if !ids.insert(input.id.as_str()) {
                return Err(ctx.error(None, format!("two in-memory inputs are both job '{}': the second's products would overwrite the first's", input.id)));
            }
        }
        if let Some(split) = &config.split_by {
            split.check().map_err(|m| ctx.error(Some("split_by"), format!("window: {m}")))?;
        }
        let truth = Truth::load(config.truth.as_deref(), ctx.image().size).map_err(|e| ctx.error(Some("truth"), e))?;
        let split_key = format!("stages.{}.split_by", ctx.name());
        Ok(MemorySource { inputs, truth, split_by: config.split_by, split_key, current_job: None })
    }
}

impl Source for MemorySource {
    fn produce(&mut self, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()> {
        for input in std::mem::take(&mut self.inputs) {
            self.current_job = Some(input.id.clone());
            let source = format!("in-memory input '{}'", input.id);
            let mut reader = BatchReader::new(input, &source)?;
            let Some((parts, stats)) = read_parts(&mut reader, self.split_by.as_ref(), &self.split_key, cancelled)? else {
                return Ok(());
            };
            stats.log(&reader.source);
            emit_parts(&reader.id, &reader.meta, parts, self.truth.as_ref(), None, emit)?;
        }
        self.current_job = None;
        Ok(())
    }

    fn current_job(&self) -> Option<String> {
        self.current_job.clone()
    }
}

/// An in-memory input read as a visibility table: the metadata and columns are checked when
/// it is opened, as for a file.
struct BatchReader {
    id: String,
    /// Names the input in messages.
    source: PathBuf,
    meta: ObservationMeta,
    schema: SchemaRef,
    input: MemoryInput,
    failed: bool,
}

impl BatchReader {
    /// `name` names the input in messages.
    fn new(input: MemoryInput, name: &str) -> Result<BatchReader> {
        let schema = input.batches.schema();
        let meta = ObservationMeta::from_pairs(schema.metadata().iter().map(|(k, v)| (k.as_str(), Some(v.as_str()))), name)?;
        validate_schema(&schema, name)?;
        Ok(BatchReader { id: input.id.clone(), source: PathBuf::from(name), meta, schema, input, failed: false })
    }
}

/// An in-memory input as a visibility table, its metadata and columns checked as a file's are,
/// for a caller that scans it itself (e.g. with [`crate::ingest::split_rows`]); `name` names
/// it in messages.
pub fn memory_table(input: MemoryInput, name: &str) -> Result<impl TableReader> {
    BatchReader::new(input, name)
}

impl TableReader for BatchReader {
    fn source(&self) -> &Path {
        &self.source
    }
    fn meta(&self) -> &ObservationMeta {
        &self.meta
    }
    fn schema(&self) -> SchemaRef {
        self.schema.clone()
    }
    fn next_batch(&mut self) -> Option<Result<RecordBatch>> {
        if self.failed {
            return None;
        }
        match self.input.batches.next()? {
            Ok(batch) if batch.schema().fields() != self.schema.fields() => {
                self.failed = true;
                Some(Err(Error::input(&self.source, "a record batch's columns differ from the input's schema")))
            }
            Ok(batch) => Some(Ok(batch)),
            Err(e) => {
                self.failed = true;
                Some(Err(Error::input(&self.source, format!("reading a record batch: {e}"))))
            }
        }
    }
}
