//! What the sources of table files share (`kind: parquet`, `kind: mat`): the `files` key (a
//! path, a list, or glob patterns), expanded into files of the kind's own format, and the
//! source reading them: one job per file, named after it, or several per file with
//! `split_by` (time windows, frequency channels), read one record batch at a time.

use crate::job::{emit_parts, emit_streamed, stem_id, BuildContext, ImageContext, Job, Truth};
use crate::pipeline::Source;
use crate::vis::{format_of, open, read_parts, OpenOptions, SplitBy, StreamedTable, TableFormat, TableReader, VisReader};
use crate::Result;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// One file (or glob pattern) or a list of them.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(untagged)]
pub enum Files {
    One(String),
    Many(Vec<String>),
}

impl Files {
    /// The files and patterns, in order.
    pub fn patterns(&self) -> &[String] {
        match self {
            Files::One(f) => std::slice::from_ref(f),
            Files::Many(fs) => fs,
        }
    }

    /// Why a source of these files may make several jobs (several files, a pattern), if it may;
    /// `kind` names the source in the reason.
    pub fn several_jobs(&self, kind: &str) -> Option<String> {
        match self.patterns() {
            [_, _, ..] => Some(format!("a {kind} source lists several files")),
            patterns => patterns.iter().find(|f| is_pattern(f)).map(|pattern| format!("a {kind} source's files are a pattern ({pattern})")),
        }
    }
}

/// Whether `file` is a glob pattern rather than a file's name.
fn is_pattern(file: &str) -> bool {
    file.contains(['*', '?', '['])
}

/// The source kind reading `format`, for the error about a file of another format.
fn kind_reading(format: TableFormat) -> &'static str {
    match format {
        TableFormat::Parquet => "parquet",
        TableFormat::Mat => "mat",
        TableFormat::ArrowIpc => "arrow-ipc",
        TableFormat::MeasurementSet => "ms",
    }
}

/// A source reading table files of one format, one job per file (or several with `split_by`).
pub struct TableFiles {
    paths: Vec<PathBuf>,
    batch_rows: usize,
    truth: Option<Truth>,
    split_by: Option<SplitBy>,
    split_key: String,
    current_job: Option<String>,
}

impl TableFiles {
    /// The stage's `files`, every pattern matching a file of `format` (a file whose format cannot
    /// be told is reported when it is read), no two of one job's name; `split_by`'s column in
    /// every file.
    pub fn new(format: TableFormat, files: &Files, batch_rows: usize, truth: Option<&Path>, split_by: Option<SplitBy>, ctx: &BuildContext<'_>) -> Result<TableFiles> {
        let patterns = files.patterns();
        if patterns.is_empty() {
            return Err(ctx.error(Some("files"), "expected at least one file or glob pattern"));
        }
        let mut paths = Vec::new();
        for pattern in patterns {
            let matches: Vec<PathBuf> = glob::glob(pattern)
                .map_err(|e| ctx.error(Some("files"), format!("bad pattern '{pattern}': {e}")))?
                .filter_map(|p| p.ok())
                .collect();
            if matches.is_empty() {
                return Err(ctx.error(Some("files"), format!("'{pattern}' matches no file")));
            }
            paths.extend(matches);
        }
        // Each kind reads its own format: a file of another is refused, naming the kind for it.
        for path in &paths {
            if let Some(found) = format_of(path).ok().filter(|found| *found != format) {
                return Err(ctx.error(
                    Some("files"),
                    format!("{} is in the {} format, not {}: `kind: {}` reads it", path.display(), found.name(), format.name(), kind_reading(found)),
                ));
            }
        }
        // Jobs are named after their files (products too): two files of one name would be one
        // job, the second overwriting the first's products.
        let mut ids: std::collections::HashMap<String, &PathBuf> = std::collections::HashMap::new();
        for path in &paths {
            if let Some(first) = ids.insert(stem_id(path), path) {
                let message = format!(
                    "{} and {} would both be job '{}' (a job is named after its file, without directory or extension): rename one, or image them in separate runs",
                    first.display(),
                    path.display(),
                    stem_id(path)
                );
                return Err(ctx.error(Some("files"), message));
            }
        }
        let split_key = format!("stages.{}.split_by", ctx.name());
        let split_error = |m: String| ctx.pipeline.stage_error(ctx.name(), Some("split_by"), &m);
        if let Some(split) = &split_by {
            split.check().map_err(|m| split_error(format!("{split_key}.window: {m}")))?;
            // Before any work starts: every file's schema must have the column.
            for path in &paths {
                let schema = match format {
                    TableFormat::Parquet => VisReader::open(path, 1)?.schema().clone(),
                    _ => open(path, &OpenOptions { batch_rows: 1, ..OpenOptions::default() })?.schema(),
                };
                split.check_schema(&schema).map_err(|m| split_error(format!("{split_key}.column: {}: {m}", path.display())))?;
            }
        }
        let truth = Truth::load(truth, ctx.image().size).map_err(|e| ctx.error(Some("truth"), e))?;
        Ok(TableFiles { paths, batch_rows: batch_rows.max(1), truth, split_by, split_key, current_job: None })
    }
}

impl Source<Job> for TableFiles {
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
            // A Parquet table reads only the columns used; a .mat through the one reader.
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
