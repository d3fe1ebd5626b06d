//! The traits a stage kind implements: [`Stage`] (one item in, emitted on a port) and
//! [`Source`] (the first stage, producing items), and what the machinery needs of an item
//! ([`Payload`]). The runner gives each stage its own thread.

use crate::Result;

/// What flows through a pipeline, as far as the machinery needs to know it.
pub trait Payload: Send + 'static {
    /// What a stage can need from an item and add to it; checked along the graph before a run.
    type Product: ProductKind;
    /// What every stage is built with beside its YAML (in-memory inputs, sinks, shared settings).
    type Context: Send + Sync;
    /// What a source stage says of the items it will make, read from its parameters before
    /// anything is built or read ([`StageKind::source_info`](super::StageKind::source_info)):
    /// what the stages after it check theirs against (`()` where nothing is said).
    type SourceInfo: ?Sized;
    /// The item's name, unique within a run (errors and progress name it).
    fn id(&self) -> &str;
    /// How far the item has come round a loop (for progress reports).
    fn iteration(&self) -> usize;
    /// How many times round the loop the item is planned to go (0: not known), so progress
    /// can say "3 of 15".
    fn iterations_planned(&self) -> usize {
        0
    }
    /// Adds time spent on the item by a stage.
    fn add_stage_seconds(&mut self, stage: &str, seconds: f64);
}

/// What a stage needs an item to carry, or adds to it: checked along the graph before
/// anything runs, so that a missing stage is an error about the pipeline, not about an item.
pub trait ProductKind: Copy + Eq + std::fmt::Debug + Send + Sync + 'static {
    /// The product as a user reads it, and the kind of stage that makes it.
    fn describe(self) -> (&'static str, &'static str);
}

/// Where a stage sends an item: its `to` stage, or (a loop's last stage only) its `done`
/// stage when the loop ends for that item.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Port {
    Next,
    Done,
}

/// Sends an item on one of the stage's ports.
pub type Emit<'a, J> = dyn FnMut(Port, J) -> Result<()> + 'a;

/// A pipeline stage: takes one item at a time and emits it (transformed) on a port.
pub trait Stage<J>: Send {
    fn process(&mut self, item: J, emit: &mut Emit<'_, J>) -> Result<()>;

    /// Called once, after the stage's last item, when nothing has stopped the run (a stopped
    /// run skips it): settles what the stage still holds (a plugin torn down, products held
    /// back committed). The stages before it in the graph have finished by then; an error
    /// fails the run, so the stages after it finish nothing.
    fn finish(&mut self) -> Result<()> {
        Ok(())
    }
}

/// The first stage: produces items.
pub trait Source<J>: Send {
    /// Produce every item, calling `emit` for each; stop early when `emit` fails or
    /// `cancelled()` turns true.
    fn produce(&mut self, emit: &mut dyn FnMut(J) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()>;

    /// The item being read when `produce` failed, to name it in the error.
    fn current_job(&self) -> Option<String> {
        None
    }
}
