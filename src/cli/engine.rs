//! The engine as the command line uses it: the ONNX Runtime library looked up here, at the
//! edge, and injected; a progress bar drawn from the runner's progress reports.

use indicatif::ProgressBar;
use crate::{Engine, EngineOptions, Progress, Result};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

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
    let bar = JobsBar { bar: crate::progress::counter("job(s) written") };
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
        // What each stage is doing, in the order the stages first reported; when each job was
        // first seen past an iteration (for its time left).
        let activity: Arc<Mutex<Vec<(String, String)>>> = Arc::default();
        let started: Arc<Mutex<HashMap<String, (Instant, usize)>>> = Arc::default();
        move |progress: &Progress| {
            let mut activity = activity.lock().expect("activity");
            let mut started = started.lock().expect("started");
            let mut set = |stage: &str, what: String| match activity.iter_mut().find(|(s, _)| s == stage) {
                Some(slot) => slot.1 = what,
                None => activity.push((stage.to_string(), what)),
            };
            match progress {
                Progress::Working { stage, job, iteration, of } if *iteration > 0 => {
                    let (t0, i0) = *started.entry(job.clone()).or_insert((Instant::now(), *iteration));
                    set(stage, format!("{stage}: {job} {}", iteration_text(*iteration, *of, i0, t0.elapsed())))
                }
                Progress::Working { stage, job, .. } => set(stage, format!("{stage}: {job}")),
                Progress::Idle { stage } => set(stage, String::new()),
                Progress::Finished { job } => {
                    started.remove(job);
                    bar.inc(1)
                }
            }
            bar.set_message(activity.iter().filter(|(_, a)| !a.is_empty()).map(|(_, a)| a.as_str()).collect::<Vec<_>>().join("  "));
        }
    }
}

/// `iteration` of `of` (`of` 0: not known) and the time left, from the pace since iteration
/// `first` was seen `elapsed` ago: `3/15, ~12 s left`.
fn iteration_text(iteration: usize, of: usize, first: usize, elapsed: Duration) -> String {
    if of == 0 {
        return format!("#{iteration}");
    }
    let done = iteration.saturating_sub(first);
    if done == 0 || iteration >= of {
        return format!("{iteration}/{of}");
    }
    let left = elapsed.as_secs_f64() / done as f64 * (of - iteration) as f64;
    let left = if left < 90.0 { format!("{left:.0} s") } else { format!("{:.0} min", left / 60.0) };
    format!("{iteration}/{of}, ~{left} left")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iterations_show_their_total_and_the_time_left_at_the_pace_so_far() {
        assert_eq!(iteration_text(3, 0, 1, Duration::from_secs(4)), "#3");
        assert_eq!(iteration_text(1, 15, 1, Duration::ZERO), "1/15");
        assert_eq!(iteration_text(3, 15, 1, Duration::from_secs(4)), "3/15, ~24 s left");
        assert_eq!(iteration_text(5, 15, 1, Duration::from_secs(60)), "5/15, ~2 min left");
        assert_eq!(iteration_text(15, 15, 1, Duration::from_secs(60)), "15/15");
    }
}

impl Drop for JobsBar {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}
