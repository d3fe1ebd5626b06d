//! The traits a stage kind implements: [`Stage`] (one job in, emitted on a port) and
//! [`Source`] (the first stage, producing jobs). The runner gives each stage its own thread.

use super::{Job, Port};
use crate::Result;

/// Sends a job on one of the stage's ports.
pub type Emit<'a> = dyn FnMut(Port, Job) -> Result<()> + 'a;

/// A pipeline stage: takes one job at a time and emits it (transformed) on a port.
pub trait Stage: Send {
    fn process(&mut self, job: Job, emit: &mut Emit<'_>) -> Result<()>;
}

/// The first stage: produces jobs.
pub trait Source: Send {
    /// Produce every job, calling `emit` for each; stop early when `emit` fails or
    /// `cancelled()` turns true.
    fn produce(&mut self, emit: &mut dyn FnMut(Job) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()>;

    /// The job being read when `produce` failed, to name it in the error.
    fn current_job(&self) -> Option<String> {
        None
    }
}
