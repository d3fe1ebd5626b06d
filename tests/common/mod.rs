//! Helpers shared by the end-to-end tests: run the `r2d2` binary and read its outcome.

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
