//! What a run hands every stage it builds beside its YAML ([`RunContext`]): the pipeline's
//! image settings, the observations handed in as record batches (the `arrow` source reads
//! them) and the sink receiving each finished job's products (the `products` stage delivers
//! to it). Each input is taken by the one stage that uses it.

use super::products::JobProducts;
use super::state::Job;
use crate::imaging::ImageConfig;
use crate::pipeline::{BuildContext, PipelineSpec};
use crate::vis::{MemoryInput, PartedObservation};
use crate::Result;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

/// The files each job's writers committed (job id -> paths), as the run goes.
pub type FilesWritten = Arc<Mutex<BTreeMap<String, Vec<PathBuf>>>>;

/// Receives each finished job's products (the `products` stage calls it, one job at a time,
/// from the stage's thread). An error fails the run, naming the stage and job.
pub trait ProductSink: Send {
    fn deliver(&mut self, products: JobProducts) -> Result<()>;
}

impl<F: FnMut(JobProducts) -> Result<()> + Send> ProductSink for F {
    fn deliver(&mut self, products: JobProducts) -> Result<()> {
        self(products)
    }
}

/// The context of a run of jobs (the payload's [`crate::pipeline::Payload::Context`]).
pub struct RunContext {
    /// The pipeline's `image` section, checked.
    pub image: ImageConfig,
    inputs: Mutex<Option<Vec<MemoryInput>>>,
    parted: Mutex<Option<Vec<PartedObservation>>>,
    sink: Mutex<Option<Box<dyn ProductSink>>>,
    written: FilesWritten,
}

impl RunContext {
    /// For a run of `spec`: reads and checks its `image` section (errors at its line).
    pub fn new(spec: &PipelineSpec, inputs: Vec<MemoryInput>, sink: Option<Box<dyn ProductSink>>) -> Result<RunContext> {
        let image: ImageConfig = spec.shared()?;
        // Before any stage is built: a size this machine cannot take would otherwise surface
        // as an aborted allocation, not as an error about the key.
        crate::limits::check_image_size(image.size).map_err(|m| spec.top_error("image", &format!("image.size = {}: {m}", image.size)))?;
        Ok(RunContext { image, inputs: Mutex::new(Some(inputs)), parted: Mutex::new(Some(Vec::new())), sink: Mutex::new(sink), written: FilesWritten::default() })
    }

    /// The files the run's writers committed so far, by job.
    pub fn files_written(&self) -> BTreeMap<String, Vec<PathBuf>> {
        self.written.lock().expect("files written").clone()
    }

    /// With observations in parts for the `arrow` source too.
    pub fn with_parted(self, parted: Vec<PartedObservation>) -> RunContext {
        RunContext { parted: Mutex::new(Some(parted)), ..self }
    }
}

/// What a stage kind reads of the run's context while building a stage.
pub trait ImageContext {
    /// The pipeline's image geometry.
    fn image(&self) -> &ImageConfig;
    /// The run's in-memory inputs (for the one source that reads them); `None` once taken.
    fn take_inputs(&self) -> Option<Vec<MemoryInput>>;
    /// The run's observations in parts (taken with the in-memory inputs, by the same source).
    fn take_parted(&self) -> Vec<PartedObservation>;
    /// The run's product sink (for the one stage that delivers to it); `None` once taken or
    /// when the run has none.
    fn take_sink(&self) -> Option<Box<dyn ProductSink>>;
    /// Where a writer records the files it commits, for the run's report.
    fn files_written(&self) -> FilesWritten;
}

impl ImageContext for BuildContext<'_, Job> {
    fn image(&self) -> &ImageConfig {
        &self.context.image
    }
    fn take_inputs(&self) -> Option<Vec<MemoryInput>> {
        self.context.inputs.lock().expect("run inputs").take()
    }
    fn take_parted(&self) -> Vec<PartedObservation> {
        self.context.parted.lock().expect("run inputs").take().unwrap_or_default()
    }
    fn take_sink(&self) -> Option<Box<dyn ProductSink>> {
        self.context.sink.lock().expect("run sink").take()
    }
    fn files_written(&self) -> FilesWritten {
        self.context.written.clone()
    }
}
