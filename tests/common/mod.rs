//! Helpers shared by the end-to-end tests: run the `r2d2` binary and read its outcome.

#![allow(dead_code)] // each test binary uses some of the helpers

use std::path::Path;
use std::process::{Command, Output};

pub fn r2d2(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_r2d2")).args(args).current_dir(dir).output().expect("r2d2 runs")
}

pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

pub fn check(out: &Output) {
    assert!(out.status.success(), "r2d2 failed: {}", stderr(out));
}

/// Standard output and standard error together (listings go to stdout, errors to stderr).
pub fn text(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

/// Writes the tiny analytic ONNX series of tests/make_test_models.py into `dir` (Python with
/// the `onnx` package is a test requirement: a missing one fails the test, it is not skipped).
pub fn make_test_models(dir: &Path) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/make_test_models.py");
    let out = Command::new("python3").arg(&script).arg(dir).output().expect("python3 runs (a test requirement)");
    assert!(out.status.success(), "{} failed (pip install -r tests/requirements.txt): {}", script.display(), text(&out));
}
