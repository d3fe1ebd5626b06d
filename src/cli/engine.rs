//! The engine as the command line uses it: the ONNX Runtime library looked up here, at the
//! edge, and injected; a progress bar drawn from the runner's progress reports.

use indicatif::ProgressBar;
use r2d2_imaging::{Engine, EngineOptions, Progress, Result};
use std::sync::{Arc, Mutex};

/// An engine for a run; `onnx` says whether a step may load native ONNX Runtime (the search
/// for it may run `python3`, so it is skipped when nothing needs it).
pub fn engine(threads: usize, onnx: bool) -> Result<(Engine, JobsBar)> {
    let onnx_runtime = if onnx {
        match super::onnx_runtime::find_onnxruntime() {
            Ok(library) => Some(library),
            Err(why) => {
                log::info!("native ONNX Runtime not found: {why}");
                None
            }
        }
    } else {
        None
    };
    let bar = JobsBar { bar: r2d2_imaging::progress::counter("job(s) written") };
    let observer = bar.observer();
    let engine = Engine::new(EngineOptions { threads, onnx_runtime })?.with_progress(observer);
    Ok((engine, bar))
}

/// A count of jobs written, with what each stage is working on beside it.
pub struct JobsBar {
    bar: ProgressBar,
}

impl JobsBar {
    fn observer(&self) -> impl Fn(&Progress) + Send + Sync + 'static {
        let bar = self.bar.clone();
        // What each stage is doing, in the order the stages first reported.
        let activity: Arc<Mutex<Vec<(String, String)>>> = Arc::default();
        move |progress: &Progress| {
            let mut activity = activity.lock().expect("activity");
            let mut set = |stage: &str, what: String| match activity.iter_mut().find(|(s, _)| s == stage) {
                Some(slot) => slot.1 = what,
                None => activity.push((stage.to_string(), what)),
            };
            match progress {
                Progress::Working { stage, job, iteration } if *iteration > 0 => set(stage, format!("{stage}: {job} #{iteration}")),
                Progress::Working { stage, job, .. } => set(stage, format!("{stage}: {job}")),
                Progress::Idle { stage } => set(stage, String::new()),
                Progress::Finished { .. } => bar.inc(1),
            }
            bar.set_message(activity.iter().filter(|(_, a)| !a.is_empty()).map(|(_, a)| a.as_str()).collect::<Vec<_>>().join("  "));
        }
    }
}

impl Drop for JobsBar {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}
