//! `kind: ms`: one imaging job per MeasurementSet (Stokes I of `data_column`, one field, the
//! selected windows and channels), or several with `split_by` (time windows, channels,
//! `spw`, or `field`: one job per field, each with its own phase centre), read in row chunks.

use super::params::MsParams;
use crate::job::{emit_parts, emit_streamed, job_id_problem, stem_id, Truth};
use crate::vis::{read_parts, SplitBy, StreamedTable, TableReader};
use crate::ms::{FieldSelector, MsReader, MsSelection};
use crate::job::Job;
use crate::pipeline::{PipelineSpec, Source, StageSpec};
use crate::Result;
use std::path::PathBuf;

/// The column that makes one job per field (each needs its own phase centre and metadata).
const FIELD_SPLIT: &str = "field";

pub struct MsSource {
    path: PathBuf,
    id: String,
    selection: MsSelection,
    batch_rows: usize,
    truth: Option<Truth>,
    split_by: Option<SplitBy>,
    split_key: String,
    reading: bool,
}

impl MsSource {
    /// `model_columns`: the columns writers downstream predict the model into (`model_column`),
    /// checked now to be writable, so that a write that cannot succeed fails before imaging.
    pub fn new(config: MsParams, pipeline: &PipelineSpec, stage: &StageSpec, image_size: usize, model_columns: &[String]) -> Result<MsSource> {
        let writes_model = !model_columns.is_empty();
        let name = &stage.name;
        let error = |key: &str, message: String| pipeline.stage_error(name, Some(key), &format!("stages.{name}.{key}: {message}"));
        if !crate::ms::is_measurement_set(&config.path) {
            return Err(error("path", format!("'{}' is not a MeasurementSet (a directory with table.dat)", config.path.display())));
        }
        let id = match config.id {
            Some(id) if job_id_problem(&id).is_some() => return Err(error("id", job_id_problem(&id).unwrap_or_default())),
            Some(id) => id,
            None => stem_id(&config.path),
        };
        if config.batch_rows == 0 {
            return Err(error("batch_rows", "expected at least 1".into()));
        }
        let selection = MsSelection { data_column: config.data_column, field: config.field, spw: config.spw, channels: config.channels };
        let split_key = format!("stages.{name}.split_by.column");
        if let Some(split) = &config.split_by {
            split.check().map_err(|m| error("split_by", format!("window: {m}")))?;
            split
                .check_schema(&crate::ms::batch_schema())
                .map_err(|m| pipeline.stage_error(name, Some("split_by"), &format!("{split_key}: {}: {m}", config.path.display())))?;
        }
        // Before any work starts: the MS opens and the selection resolves (one field, windows
        // with Stokes I, channels in range).
        let by_field = matches!(&config.split_by, Some(s) if s.column == FIELD_SPLIT);
        // Checked here, before any work, though the writer would refuse such jobs too.
        if let Some(split) = config.split_by.as_ref().filter(|_| !by_field && writes_model) {
            return Err(error(
                "split_by",
                format!("a writer has `model_column`, which holds one model per MS field: split by `field` or not at all, not by `{}`", split.column),
            ));
        }
        if by_field && selection.field.is_some() {
            return Err(error("field", "one job per field (`split_by: {column: field}`) reads every field: drop `field`".into()));
        }
        if !by_field {
            MsReader::open(&config.path, &selection, config.batch_rows)?;
        }
        for column in model_columns {
            crate::ms::check_model_write(&config.path, column, &selection.data_column)?;
        }
        let truth = Truth::load(config.truth.as_deref(), image_size).map_err(|e| error("truth", e.to_string()))?;
        Ok(MsSource { path: config.path, id, selection, batch_rows: config.batch_rows, truth, split_by: config.split_by, split_key, reading: false })
    }

    /// Reads one selection into jobs; `suffix` is appended to the id (a field's part).
    fn read(
        &self,
        selection: &MsSelection,
        id: &str,
        emit: &mut dyn FnMut(Job) -> Result<()>,
        cancelled: &dyn Fn() -> bool,
    ) -> Result<bool> {
        let split = self.split_by.as_ref().filter(|s| s.column != FIELD_SPLIT);
        if split.is_none() {
            // One job of the selection, read again at each pass: nothing the size of the
            // table is held.
            let (path, chosen, batch_rows) = (self.path.clone(), selection.clone(), self.batch_rows);
            let reopen = move || -> Result<Box<dyn TableReader>> { Ok(Box::new(MsReader::open(&path, &chosen, batch_rows)?)) };
            let reader = MsReader::open(&self.path, selection, self.batch_rows)?;
            let (field, field_name) = (reader.field().0, reader.field().1.to_string());
            let Some(table) = StreamedTable::scan(Box::new(reader), Box::new(reopen), Some(&crate::vis::spill_dir()), cancelled)? else {
                return Ok(false);
            };
            let column = table.meta().extra.get("ms_data_column").cloned().unwrap_or_default();
            log::info!("{} (field {field} '{field_name}', column {column}): {}; {}", self.path.display(), table.stats(), table.reader_summary().unwrap_or_default());
            emit_streamed(id, table, self.truth.as_ref(), emit)?;
            return Ok(true);
        }
        let mut reader = MsReader::open_part(&self.path, selection, self.batch_rows, split.map(|s| s.column.as_str()))?;
        let Some((parts, stats)) = read_parts(&mut reader, split, &self.split_key, cancelled)? else {
            return Ok(false);
        };
        let column = reader.meta().extra.get("ms_data_column").cloned().unwrap_or_default();
        log::info!("{} (field {} '{}', column {column}): {stats}; {}", self.path.display(), reader.field().0, reader.field().1, reader.counts());
        emit_parts(id, reader.meta(), parts, self.truth.as_ref(), Some(&self.path), emit)?;
        Ok(true)
    }
}

impl Source<Job> for MsSource {
    fn produce(&mut self, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()> {
        self.reading = true;
        if self.split_by.as_ref().is_some_and(|s| s.column == FIELD_SPLIT) {
            let fields = crate::ms::fields_with_rows(&self.path)?;
            let width = fields.iter().map(|(id, _)| id.to_string().len()).max().unwrap_or(2).max(2);
            for (field, _) in fields {
                let mut selection = self.selection.clone();
                selection.field = Some(FieldSelector::Id(field));
                let id = format!("{}-field{field:0width$}", self.id);
                if !self.read(&selection, &id, emit, cancelled)? {
                    return Ok(());
                }
            }
        } else if !self.read(&self.selection, &self.id, emit, cancelled)? {
            return Ok(());
        }
        self.reading = false;
        Ok(())
    }

    fn current_job(&self) -> Option<String> {
        self.reading.then(|| self.id.clone())
    }
}
