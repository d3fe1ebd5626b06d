//! Progress bars (indicatif) for long work. They are drawn on stderr only when it is a
//! terminal and not silenced (`-q`); otherwise they cost nothing and print nothing. Log
//! lines go through [`LogWriter`], which hides the bars while a line is written so the two
//! do not tear each other.

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::{IsTerminal, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::OnceLock;
use std::time::Duration;

static SILENCED: AtomicBool = AtomicBool::new(false);
static BARS: OnceLock<MultiProgress> = OnceLock::new();

/// No bars at all (`-q`); call before the first bar is made.
pub fn silence() {
    SILENCED.store(true, Ordering::SeqCst);
}

fn bars() -> &'static MultiProgress {
    BARS.get_or_init(|| {
        let visible = !SILENCED.load(Ordering::SeqCst) && std::io::stderr().is_terminal();
        MultiProgress::with_draw_target(if visible { ProgressDrawTarget::stderr() } else { ProgressDrawTarget::hidden() })
    })
}

/// A spinner with elapsed time, a count of `unit` and a message, ticking on its own.
pub fn counter(unit: &str) -> ProgressBar {
    let style = ProgressStyle::with_template(&format!("{{spinner}} {{elapsed_precise}} {{pos}} {unit} {{wide_msg}}"))
        .expect("progress template is valid");
    let bar = bars().add(ProgressBar::no_length().with_style(style));
    bar.enable_steady_tick(Duration::from_millis(200));
    bar
}

/// Writes log lines to stderr with the bars hidden meanwhile (`env_logger` pipes through it).
pub struct LogWriter;

impl Write for LogWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        bars().suspend(|| std::io::stderr().write_all(buf))?;
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}
