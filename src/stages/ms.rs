//! `kind: ms`: one imaging job per MeasurementSet (Stokes I of `data_column`, one field, the
//! selected windows and channels), or several with `split_by` (time windows, channels,
//! `spw`, or `field`: one job per field, each with its own phase centre), or with
//! `channels_out` one job per channel group on one grid (WSClean's `-channels-out`), read in
//! row chunks.

use super::writer::WriterParams;
use crate::job::{emit_parts, emit_streamed, job_id_problem, stem_id, Truth};
use crate::job::{ImageContext, Job, Reads, SourceKind, SourceParams};
use crate::ms::{FieldSelector, MsReader, MsSelection};
use crate::pipeline::{PipelineSpec, Source, StageParams, StageSpec};
use crate::vis::{read_parts, SplitBy, StreamedTable, TableReader};
use crate::Result;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// `kind: ms`: a MeasurementSet. Its keys are `path`, `id`, what of the MS to read (the keys
/// of [`MsSelection`]: `data_column`, `field`, `spw`, `channels`), `batch_rows`, `truth`,
/// `split_by`, `channels_out` and `join_channels`.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct MsParams {
    /// The MeasurementSet (a directory).
    pub path: PathBuf,
    /// Job id (default: the MS name without its extension).
    #[serde(default)]
    pub id: Option<String>,
    /// What to read: the data column (default `auto`: CORRECTED_DATA when the MS has it, else
    /// DATA, as WSClean chooses), the field (required when the MS holds several, unless split
    /// by field), the spectral windows (default: all), the channel range `[start, end)` of
    /// every window. Its keys are the stage's own (`data_column: DATA`, not nested).
    #[serde(flatten)]
    pub selection: MsSelection,
    /// Samples per batch (a chunk of rows).
    #[serde(default = "crate::vis::default_batch_rows")]
    pub batch_rows: usize,
    /// Ground truth (FITS, Jy/pixel, same grid as the image) for SNR/logSNR per iteration.
    #[serde(default)]
    pub truth: Option<PathBuf>,
    /// Split into several jobs: `{column: time, window: S}`, `{column: frequency}`,
    /// `{column: spw}`, `{column: field}`, or another numeric column of the batches.
    #[serde(default)]
    pub split_by: Option<SplitBy>,
    /// WSClean's `-channels-out`: the selected channels in this many groups, each a job
    /// `<id>-0000`, `<id>-0001`, ... imaged on one grid (the pixel of the whole band's longest
    /// baseline, where the image's pixel is not given).
    #[serde(default)]
    pub channels_out: Option<usize>,
    /// WSClean's `-join-channels`: with `channels_out`, the whole band too, as the job
    /// `<id>-MFS` on the same grid.
    #[serde(default)]
    pub join_channels: bool,
}

impl MsParams {
    /// `path` with the defaults of the other keys.
    pub fn new(path: impl Into<PathBuf>) -> MsParams {
        MsParams {
            path: path.into(),
            id: None,
            selection: MsSelection::default(),
            batch_rows: crate::vis::default_batch_rows(),
            truth: None,
            split_by: None,
            channels_out: None,
            join_channels: false,
        }
    }
}

impl StageParams for MsParams {
    const KIND: &'static str = "ms";
}

impl SourceParams for MsParams {
    fn reads(&self) -> Reads {
        Reads::MeasurementSet(self.path.clone())
    }
    fn several_jobs(&self) -> Option<String> {
        match (&self.split_by, self.channels_out) {
            (Some(_), _) => Some("an ms source has split_by".to_string()),
            (None, Some(n)) if n > 1 || self.join_channels => Some("an ms source has channels_out".to_string()),
            _ => None,
        }
    }
}

/// The kind, as registered.
pub(super) const KIND: SourceKind<MsParams> = SourceKind::new(|params, c| {
    // A writer that predicts the model into the MS needs one job per field, checked now.
    let model_columns: Vec<String> = c.downstream_params::<WriterParams>()?.into_iter().filter_map(|w| w.model_column).collect();
    Ok(Box::new(MsSource::new(params, c.pipeline, c.stage, c.image().size, &model_columns)?))
});

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
    channels_out: Option<usize>,
    join_channels: bool,
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
        let selection = config.selection;
        if let Some(count) = config.channels_out {
            let refused = match () {
                _ if count == 0 => Some("expected at least 1 channel group".to_string()),
                _ if config.split_by.is_some() => Some("channel groups are jobs of their own: give `channels_out` or `split_by`, not both".into()),
                _ if selection.channel_group.is_some() => Some("`channel_group` selects one group; `channels_out` makes every group: give one".into()),
                _ if writes_model => Some("a writer has `model_column`: channel groups are not predicted into the MS (image the band as one to predict its model)".into()),
                _ => None,
            };
            if let Some(message) = refused {
                return Err(error("channels_out", message));
            }
        } else if config.join_channels {
            return Err(error("join_channels", "the whole band joins channel groups: give `channels_out` too".into()));
        }
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
        Ok(MsSource { path: config.path, id, selection, batch_rows: config.batch_rows, truth, split_by: config.split_by, split_key, channels_out: config.channels_out, join_channels: config.join_channels, reading: false })
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
            let Some(table) = self.scan(selection, cancelled)? else { return Ok(false) };
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

    /// One job's samples of `selection`, read again at each pass: nothing the size of the
    /// table is held. `None` where the run was cancelled.
    fn scan(&self, selection: &MsSelection, cancelled: &dyn Fn() -> bool) -> Result<Option<StreamedTable>> {
        let (path, chosen, batch_rows) = (self.path.clone(), selection.clone(), self.batch_rows);
        let reopen = move || -> Result<Box<dyn TableReader>> { Ok(Box::new(MsReader::open(&path, &chosen, batch_rows)?)) };
        let reader = MsReader::open(&self.path, selection, self.batch_rows)?;
        let (field, field_name) = (reader.field().0, reader.field().1.to_string());
        let Some(table) = StreamedTable::scan(Box::new(reader), Box::new(reopen), Some(&crate::vis::spill_dir()), cancelled)? else {
            return Ok(None);
        };
        let column = table.meta().extra.get("ms_data_column").cloned().unwrap_or_default();
        let group = selection.channel_group.map(|g| format!(", channel group {} of {}", g.index + 1, g.count)).unwrap_or_default();
        log::info!("{} (field {field} '{field_name}', column {column}{group}): {}; {}", self.path.display(), table.stats(), table.reader_summary().unwrap_or_default());
        Ok(Some(table))
    }

    /// `count` channel groups of `selection`, each a job `<id>-0000`, ... on one grid, and with
    /// `join_channels` the whole band as `<id>-MFS`. Every group is scanned before any is
    /// emitted: the whole band's longest baseline, which sets the grid, is the longest of
    /// the groups'.
    fn read_channel_groups(&self, count: usize, id: &str, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<bool> {
        let mut groups = Vec::with_capacity(count);
        for index in 0..count {
            let chosen = MsSelection { channel_group: Some(crate::vis::ChannelGroup { index, count }), ..self.selection.clone() };
            let Some(table) = self.scan(&chosen, cancelled)? else { return Ok(false) };
            groups.push(table);
        }
        let band_max_uv = groups.iter().map(|t| t.max_uv()).fold(0.0, f64::max);
        let mut on_one_grid = |mut job: Job| {
            job.split_max_uv = Some(band_max_uv);
            emit(job)
        };
        for (index, table) in groups.into_iter().enumerate() {
            emit_streamed(&format!("{id}-{}", crate::job::group_label(index)), table, self.truth.as_ref(), &mut on_one_grid)?;
        }
        if self.join_channels {
            let Some(table) = self.scan(&self.selection, cancelled)? else { return Ok(false) };
            emit_streamed(&format!("{id}-{}", crate::job::MFS_LABEL), table, self.truth.as_ref(), &mut on_one_grid)?;
        }
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
        } else if let Some(count) = self.channels_out {
            if !self.read_channel_groups(count, &self.id, emit, cancelled)? {
                return Ok(());
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    /// The `read` stage of a pipeline whose `kind: ms` stage has `keys`, read as its parameters.
    fn read(keys: &str) -> Result<MsParams> {
        let text = format!("stages:\n  read:\n    kind: ms\n    path: a.ms\n{keys}    to: write\n  write: {{kind: writer}}\n");
        let spec = PipelineSpec::parse(&text, Path::new("p.yaml"), &[]).unwrap();
        spec.stage_params::<MsParams>(spec.stage("read").unwrap())
    }

    /// The selection's keys are the stage's own (flattened into `MsParams::selection`), and an
    /// error about one still names it at its line: an unknown key is refused, a wrong value
    /// named by its key, though serde reports neither through the flattened struct.
    #[test]
    fn the_selection_keys_are_the_stages_and_errors_name_them() {
        let params = read("    data_column: DATA\n    spw: [0, 2]\n    channels: [1, 4]\n    batch_rows: 10\n").unwrap();
        let selection = MsSelection { data_column: "DATA".into(), field: None, spw: Some(vec![0, 2]), channels: Some([1, 4]), channel_group: None };
        assert_eq!(params, MsParams { selection, batch_rows: 10, ..MsParams::new("a.ms") });
        assert_eq!(read("").unwrap(), MsParams::new("a.ms"));
        // An unknown key, a misspelt selection key among them.
        for (keys, key, line) in [("    spws: [0]\n", "spws", 5), ("    batch_rows: 10\n    colour: red\n", "colour", 6)] {
            let err = read(keys).unwrap_err().to_string();
            assert!(err.contains(&format!("line {line}")) && err.contains(&format!("stages.read.{key} (ms stage)")) && err.contains("unknown field"), "{err}");
        }
        // A wrong value of a selection key, and of one of the stage's own.
        for (keys, key) in [("    spw: all\n", "spw"), ("    channels: [1]\n", "channels"), ("    batch_rows: many\n", "batch_rows")] {
            let err = read(keys).unwrap_err().to_string();
            assert!(err.contains("line 5") && err.contains(&format!("stages.read.{key} (ms stage)")), "{err}");
        }
        // Written in code and read back from its mapping: the same parameters.
        let typed = MsParams { selection: MsSelection { field: Some(FieldSelector::Name("3C286".into())), ..MsSelection::default() }, ..MsParams::new("a.ms") };
        let spec = crate::StageSpec::typed("read", &typed).unwrap();
        assert_eq!(spec.params()["field"].as_str(), Some("3C286"), "flat, as the YAML writes it");
        assert_eq!(serde_yaml::from_value::<MsParams>(spec.params().clone()).unwrap(), typed);
    }
}
