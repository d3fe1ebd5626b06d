//! The engine's log records for Python's `logging`: logger `r2d2_imaging` and its children
//! (`r2d2_imaging.stages.residual`, ... from the record's module path).
//!
//! Engine threads never touch Python: a record is queued, and the Python thread that waits on
//! the engine (`run_released`) hands the queue to `logging` between its short waits and at the
//! end, holding the GIL as it already does there. Taking the GIL from an engine thread could
//! deadlock against a Python thread that holds it while it waits for the engine. The queue is
//! bounded; what overflows is counted and said in one record. Which records are queued
//! follows the Python logger's effective level, read at each call.

use pyo3::prelude::*;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

/// Records held between two hand-overs at most (a run logs a few per iteration).
const QUEUE_LIMIT: usize = 10_000;

struct Record {
    level: log::Level,
    target: String,
    message: String,
}

static QUEUE: Mutex<VecDeque<Record>> = Mutex::new(VecDeque::new());
static DROPPED: AtomicUsize = AtomicUsize::new(0);

struct Bridge;

impl log::Log for Bridge {
    fn enabled(&self, metadata: &log::Metadata) -> bool {
        // Other crates (ONNX Runtime, the table library) speak only to warn.
        metadata.level() <= log::max_level() && (metadata.target().starts_with("r2d2_imaging") || metadata.level() <= log::Level::Warn)
    }

    fn log(&self, record: &log::Record) {
        if !self.enabled(record.metadata()) {
            return;
        }
        let Ok(mut queue) = QUEUE.lock() else { return };
        if queue.len() >= QUEUE_LIMIT {
            queue.pop_front();
            DROPPED.fetch_add(1, Ordering::Relaxed);
        }
        queue.push_back(Record { level: record.level(), target: record.target().to_string(), message: record.args().to_string() });
    }

    fn flush(&self) {}
}

static BRIDGE: Bridge = Bridge;

/// Install the bridge as the process's logger (once; a host that installed its own keeps it).
pub(crate) fn install() {
    if log::set_logger(&BRIDGE).is_ok() {
        log::set_max_level(log::LevelFilter::Warn);
    }
}

/// The Python logger's effective level as the engine's filter (at each call, so a level set
/// after import counts). An error is a signal handler's exception (Ctrl-C): returned, never
/// dropped.
pub(crate) fn follow_level(py: Python<'_>) -> PyResult<()> {
    let level = logger(py, "r2d2_imaging")?.call_method0("getEffectiveLevel")?.extract::<i32>()?;
    log::set_max_level(match level {
        ..=5 => log::LevelFilter::Trace,
        6..=10 => log::LevelFilter::Debug,
        11..=20 => log::LevelFilter::Info,
        21..=30 => log::LevelFilter::Warn,
        _ => log::LevelFilter::Error,
    });
    Ok(())
}

fn logger<'py>(py: Python<'py>, name: &str) -> PyResult<Bound<'py, PyAny>> {
    py.import("logging")?.call_method1("getLogger", (name,))
}

/// Hand the queued records to `logging` (on the calling Python thread, GIL held). An
/// exception from it is one a signal handler raised meanwhile (logging reports its handlers'
/// own errors itself): it is returned, and the records not yet handed over are dropped.
pub(crate) fn hand_over(py: Python<'_>) -> PyResult<()> {
    let records: Vec<Record> = match QUEUE.lock() {
        Ok(mut queue) => queue.drain(..).collect(),
        Err(_) => return Ok(()),
    };
    let dropped = DROPPED.swap(0, Ordering::Relaxed);
    if dropped > 0 {
        emit(py, "r2d2_imaging", log::Level::Warn, &format!("{dropped} engine log record(s) dropped: more than {QUEUE_LIMIT} between two hand-overs"))?;
    }
    for r in records {
        let name = if r.target.starts_with("r2d2_imaging") { r.target.replace("::", ".") } else { format!("r2d2_imaging.{}", r.target.replace("::", ".")) };
        emit(py, &name, r.level, &r.message)?;
    }
    Ok(())
}

fn emit(py: Python<'_>, name: &str, level: log::Level, message: &str) -> PyResult<()> {
    let number = match level {
        log::Level::Error => 40,
        log::Level::Warn => 30,
        log::Level::Info => 20,
        log::Level::Debug => 10,
        log::Level::Trace => 5,
    };
    logger(py, name)?.call_method1("log", (number, "%s", message))?;
    Ok(())
}
