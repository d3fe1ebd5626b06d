//! `kind: arrow`: observations handed in by the embedding program as Arrow record batches
//! (`Engine::run`'s inputs), one job per input, or several with `split_by`. The batches have
//! the Parquet format's columns and its observation metadata in the schema's metadata, and
//! are checked exactly as an Arrow IPC stream's are. Observations in parts gridded where they
//! live (`Engine::image` of an [`Observation::Parts`](crate::Observation)) come in here too,
//! one job each.

use crate::job::{emit_parted, emit_parts, job_id_problem, Truth};
use crate::job::{BuildContext, ImageContext, Job, Reads, SourceKind, SourceParams};
use crate::pipeline::{Source, StageParams};
use crate::vis::{read_parts, MemoryInput, MemoryTable, PartedObservation, SplitBy, TableReader};
use crate::Result;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

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

impl SourceParams for ArrowParams {
    fn reads(&self) -> Reads {
        Reads::Memory
    }
    fn several_jobs(&self) -> Option<String> {
        self.split_by.as_ref().map(|_| "an arrow source has split_by".to_string())
    }
}

/// The kind, as registered.
pub(super) const KIND: SourceKind<ArrowParams> = SourceKind::new(|params, c| Ok(Box::new(MemorySource::new(params, c)?)));

pub struct MemorySource {
    inputs: Vec<MemoryInput>,
    parted: Vec<PartedObservation>,
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
        let parted = ctx.take_parted();
        if inputs.is_empty() && parted.is_empty() && !ctx.validating() {
            return Err(ctx.error(Some("kind"), "kind 'arrow' reads in-memory inputs (Engine::run), and the run was given none"));
        }
        let mut ids = std::collections::HashSet::new();
        for id in inputs.iter().map(|i| &i.id).chain(parted.iter().map(|p| &p.id)) {
            if let Some(problem) = job_id_problem(id) {
                return Err(ctx.error(None, format!("an in-memory input: {problem}")));
            }
            if !ids.insert(id.as_str()) {
                return Err(ctx.error(None, format!("two in-memory inputs are both job '{id}': the second's products would overwrite the first's")));
            }
        }
        if config.split_by.is_some() && !parted.is_empty() {
            return Err(ctx.error(Some("split_by"), "an observation in parts is imaged as one job: split it into parts of its own instead"));
        }
        if let Some(split) = &config.split_by {
            split.check().map_err(|m| ctx.error(Some("split_by"), format!("window: {m}")))?;
        }
        let truth = Truth::load(config.truth.as_deref(), ctx.image().size).map_err(|e| ctx.error(Some("truth"), e))?;
        let split_key = format!("stages.{}.split_by", ctx.name());
        Ok(MemorySource { inputs, parted, truth, split_by: config.split_by, split_key, current_job: None })
    }
}

impl Source<Job> for MemorySource {
    fn produce(&mut self, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()> {
        for input in std::mem::take(&mut self.inputs) {
            self.current_job = Some(input.id.clone());
            let source = format!("in-memory input '{}'", input.id);
            let mut reader = MemoryTable::new(input, &source)?;
            let Some((parts, stats)) = read_parts(&mut reader, self.split_by.as_ref(), &self.split_key, cancelled)? else {
                return Ok(());
            };
            stats.log(reader.source());
            emit_parts(reader.id(), reader.meta(), parts, self.truth.as_ref(), None, emit)?;
        }
        for observation in std::mem::take(&mut self.parted) {
            if cancelled() {
                return Ok(());
            }
            self.current_job = Some(observation.id.clone());
            emit_parted(observation, self.truth.as_ref(), emit)?;
        }
        self.current_job = None;
        Ok(())
    }

    fn current_job(&self) -> Option<String> {
        self.current_job.clone()
    }
}

