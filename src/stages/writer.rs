//! `kind: writer`: FITS products named like WSClean's (`<prefix>-dirty.fits`, `-psf.fits`,
//! `-model.fits`, `-residual.fits`, and `-image.fits` for CLEAN) with full WCS and beam, a
//! PNG preview beside each (`<prefix>-dirty.png`, ...; `previews: false` turns them off),
//! and the per-iteration metrics as `<prefix>-metrics.json` and `<prefix>-metrics.parquet`;
//! with `products: dirty`, the dirty image and the PSF only (`r2d2 dirty`'s); with
//! `apply_primary_beam`, the primary beam and the images corrected by it (`-pb.fits`,
//! `-image-pb.fits`, `-model-pb.fits`).
//! A job's products appear together or not at all: they are written into a staging
//! directory and moved into place only when all are complete (`crate::staging`). After a
//! native plugin, every job's products wait staged until the run's end and are moved into
//! place once the plugin has been torn down cleanly (the stage's finish).

use super::step::holds_until_finished;
use crate::job::{BuildContext, Built, Emit, Job, KindFn, Product};
use crate::pipeline::{PipelineSpec, Role, Stage, StageParams, StageSpec};
use crate::job::{FilesWritten, ImageContext, JobProducts, ProductSet, Staged, WriteOptions};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// `kind: writer`: where and what a job's products are written.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct WriterParams {
    /// Output prefix; `{job}` is replaced by the job id. Default `{job}`.
    pub prefix: String,
    /// A PNG preview (log scale, colour bar) beside each FITS product; default true.
    pub previews: bool,
    /// Decades shown by the previews' log scale; default: the dynamic range of the truth
    /// or of the simulated sky when known, else 1e3.
    pub preview_dynamic_range: Option<f64>,
    /// Predict the final model's visibilities into this column of the input MeasurementSet
    /// (`kind: ms` jobs), e.g. MODEL_DATA; created when missing.
    pub model_column: Option<String>,
    /// `all` (default): every product the job has, the metrics, and earlier products at the
    /// prefix that this run does not make removed; `dirty`: `<prefix>-dirty.fits` and
    /// `-psf.fits` (and their previews) only, every other file at the prefix left as it is.
    pub products: ProductSet,
    /// Also write `<prefix>-pb.fits` (the telescope's published primary beam, VLA or MeerKAT
    /// L band, at the observation's centre frequency about the phase centre), and
    /// `<prefix>-image-pb.fits` and `<prefix>-model-pb.fits` divided by it, blank (NaN) where
    /// it is below `primary_beam_limit`; as WSClean's `-apply-primary-beam`. Default false.
    pub apply_primary_beam: bool,
    /// The beam level below which the corrected images are blank; default 0.1.
    pub primary_beam_limit: f64,
}

impl Default for WriterParams {
    fn default() -> Self {
        WriterParams {
            prefix: "{job}".into(),
            previews: true,
            preview_dynamic_range: None,
            model_column: None,
            products: ProductSet::All,
            apply_primary_beam: false,
            primary_beam_limit: crate::primary_beam::DEFAULT_LIMIT,
        }
    }
}

impl StageParams for WriterParams {
    const KIND: &'static str = "writer";
}

/// The kind, as registered.
pub(super) const KIND: KindFn = KindFn {
    name: WriterParams::KIND,
    role: Role::Sink,
    consumes: &[Product::Imaging],
    produces: &[],
    consumes_also: None,
    passes_on: false,
    build: |c| {
        let config: WriterParams = c.params()?;
        // A model column needs jobs read from an MS (`ms`, or in-memory batches that carry an
        // MS's origin): a source that reads none has no column to write, known before imaging.
        if config.model_column.is_some() {
            if let Some((stage, _)) = c.upstream_sources()?.into_iter().find(|(_, source)| !source.reads().may_be_measurement_set()) {
                return Err(c.error(
                    Some("model_column"),
                    format!(
                        "the jobs come from stage '{}' (kind '{}'), which reads no MeasurementSet: only an `ms` source has a column to write the model into",
                        stage.name, stage.kind
                    ),
                ));
            }
        }
        Ok(Built::Stage(Box::new(WriterStage::new(config, c.pipeline, c.stage, several_jobs(c)?, holds_until_finished(c), c.files_written())?)))
    },
};

/// Why the sources before stage `c` may make several jobs (a list or pattern of files, a
/// `split_by`, several seeds), if they may, as each says. Several sources feeding one writer
/// are caught by the writer at run time, when a second job reaches a prefix already written.
fn several_jobs(c: &BuildContext<'_>) -> Result<Option<String>> {
    let why: Vec<String> = c.upstream_sources()?.iter().filter_map(|(_, source)| source.several_jobs()).collect();
    Ok((!why.is_empty()).then(|| why.join("; ")))
}

/// What a writer prefix may contain besides text.
const PLACEHOLDERS: &[&str] = &["{job}"];

pub struct WriterStage {
    prefix: String,
    options: WriteOptions,
    products: ProductSet,
    model_column: Option<String>,
    /// The prefixes written in this run and the job written to each: a prefix without `{job}`
    /// given several jobs would otherwise keep only the last one's products.
    written: std::collections::HashMap<String, String>,
    /// Where the files committed are recorded for the run's report.
    files: FilesWritten,
    /// Whether jobs wait staged until the stage's finish (a native plugin before it), and
    /// those waiting: id, products, and the job itself where its model goes into an MS.
    holds: bool,
    held: Vec<(String, Staged, Option<Job>)>,
}

impl WriterStage {
    /// `several_jobs`: why the sources may make several jobs, if they may (a prefix without
    /// `{job}` is then refused: each job would replace the last one's products).
    /// `holds`: keep every job's products staged until the run's end (see the module).
    pub fn new(
        config: WriterParams,
        pipeline: &PipelineSpec,
        stage: &StageSpec,
        several_jobs: Option<String>,
        holds: bool,
        files: FilesWritten,
    ) -> Result<WriterStage> {
        let name = &stage.name;
        let prefix_error = |m: String| pipeline.stage_error(name, Some("prefix"), &format!("stages.{name}.prefix: {m}"));
        // Placeholders first: a typo would otherwise be written literally into file names.
        let mut rest = config.prefix.as_str();
        while let Some(open) = rest.find('{') {
            let placeholder = rest[open..].find('}').map_or(&rest[open..], |close| &rest[open..=open + close]);
            if !PLACEHOLDERS.contains(&placeholder) {
                return Err(prefix_error(format!("unknown placeholder {placeholder} in \"{}\" (known: {})", config.prefix, PLACEHOLDERS.join(", "))));
            }
            rest = &rest[open + placeholder.len()..];
        }
        crate::fits::check_output_prefix(&config.prefix).map_err(prefix_error)?;
        if let (Some(why), false) = (&several_jobs, config.prefix.contains("{job}")) {
            return Err(prefix_error(format!(
                "\"{}\" has no {{job}}, but the jobs reaching this writer may be several ({why}): each would replace the last one's products; put {{job}} in it",
                config.prefix
            )));
        }
        if let Some(dr) = config.preview_dynamic_range {
            if !(dr > 1.0 && dr.is_finite()) {
                return Err(Error::parameter("preview_dynamic_range", format!("expected a finite number above 1, got {dr}")));
            }
        }
        if config.model_column.as_deref().is_some_and(|c| c.trim().is_empty()) {
            return Err(Error::parameter("model_column", "expected a column name such as MODEL_DATA"));
        }
        if config.model_column.is_some() && config.products == ProductSet::Dirty {
            return Err(Error::parameter("model_column", "products: dirty writes the dirty image and the PSF only, no model"));
        }
        if config.apply_primary_beam {
            crate::primary_beam::check_limit(config.primary_beam_limit).map_err(|m| Error::parameter("primary_beam_limit", m))?;
            if config.products == ProductSet::Dirty {
                return Err(Error::parameter("apply_primary_beam", "products: dirty writes the dirty image and the PSF only, no primary-beam corrected images"));
            }
        }
        Ok(WriterStage {
            prefix: config.prefix,
            options: WriteOptions {
                previews: config.previews,
                preview_dynamic_range: config.preview_dynamic_range,
                primary_beam: config.apply_primary_beam.then_some(config.primary_beam_limit),
            },
            products: config.products,
            model_column: config.model_column,
            written: Default::default(),
            files,
            holds,
            held: Vec::new(),
        })
    }
}

impl Stage<Job> for WriterStage {
    fn process(&mut self, mut job: Job, _emit: &mut Emit<'_>) -> Result<()> {
        let resolved = self.prefix.replace("{job}", &job.id);
        if let Some(earlier) = self.written.get(&resolved) {
            return Err(Error::parameter(
                "prefix",
                format!(
                    "job '{}' would replace the products job '{earlier}' wrote at \"{resolved}\" in this run: put {{job}} in the writer's prefix (\"{}\") so that each job has its own",
                    job.id, self.prefix
                ),
            ));
        }
        self.written.insert(resolved, job.id.clone());
        let staged = JobProducts::from_job(&mut job, self.options.preview_dynamic_range)?.stage(&self.prefix, &self.options, self.products)?;
        if self.holds {
            let id = job.id.clone();
            self.held.push((id, staged, self.model_column.is_some().then_some(job)));
            return Ok(());
        }
        self.commit(&job.id, Some(&job), staged)
    }

    fn finish(&mut self) -> Result<()> {
        for (id, staged, job) in std::mem::take(&mut self.held) {
            self.commit(&id, job.as_ref(), staged)?;
        }
        Ok(())
    }
}

impl WriterStage {
    /// Writes the job's model column where asked (`job` is then given), then moves its staged
    /// products into place.
    fn commit(&self, id: &str, job: Option<&Job>, staged: Staged) -> Result<()> {
        // The model column is written while the products wait staged, and they are moved into
        // place after it: a run killed during the (long) MS write leaves the earlier products
        // beside the earlier model, never this run's products beside the earlier model. A
        // write that fails (the column was checked writable before imaging) still delivers the
        // products, which are right whatever became of the column, and says what it left.
        if let (Some(column), Some(job)) = (&self.model_column, job) {
            if let Err(e) = write_model(job, column) {
                log::error!("job {id}: `{column}` was not written: {e}");
                self.record(id, staged.commit(id)?);
                log::error!("job {id}: the products were written at \"{prefix}\", but `{column}` was not", prefix = self.prefix.replace("{job}", id));
                return Err(e);
            }
        }
        self.record(id, staged.commit(id)?);
        Ok(())
    }

    /// Records the files committed for job `id`, for the run's report.
    fn record(&self, id: &str, files: Vec<std::path::PathBuf>) {
        self.files.lock().expect("files written").entry(id.to_string()).or_default().extend(files);
    }
}

#[cfg(feature = "ms")]
fn write_model(job: &Job, column: &str) -> Result<()> {
    crate::job::write_job_model(job, column).map(|_| ())
}

#[cfg(not(feature = "ms"))]
fn write_model(_job: &Job, _column: &str) -> Result<()> {
    Err(Error::parameter("model_column", "this r2d2 was built without the `ms` feature (MeasurementSets)"))
}
