//! Helpers shared by the end-to-end tests: run the `r2d2` binary and read its outcome.

#![allow(dead_code)] // each test binary uses some of the helpers

use r2d2_imaging::fits::read_image;
use r2d2_imaging::imaging::{DirtyParams, NormalOperator, WTermMode};
use r2d2_imaging::NufftParams;
use r2d2_imaging::vis::read_parquet;
use std::path::Path;
use std::process::{Command, Output};

/// Runs `r2d2` in `dir`, with the repository's `models/` as the model directory (the binary may
/// be built outside the repository, where it would not find them by itself).
pub fn r2d2(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_r2d2"))
        .args(args)
        .current_dir(dir)
        .env("R2D2_MODELS", Path::new(env!("CARGO_MANIFEST_DIR")).join("models"))
        .output()
        .expect("r2d2 runs")
}

/// `command`'s output, failing the test if it runs past `limit` (it is then killed): a run
/// that waits for ever must not pass as a slow one.
pub fn output_within(command: &mut Command, limit: std::time::Duration) -> Output {
    let mut child = command.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped()).spawn().unwrap();
    let began = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        if began.elapsed() > limit {
            child.kill().unwrap();
            panic!("still running after {limit:?}: {}", stderr(&child.wait_with_output().unwrap()));
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Asserts that `out` failed cleanly (exit status 1, not a signal) with every one of `expected`
/// in its standard error; `what` names the case in messages. Returns the standard error.
pub fn assert_fails_with(out: &Output, what: &str, expected: &[&str]) -> String {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(1), "{what}: expected a clean failure, got {}: {err}", out.status);
    for e in expected {
        assert!(err.contains(e), "{what}: '{e}' missing from: {err}");
    }
    err
}

pub fn check(out: &Output) {
    assert!(out.status.success(), "r2d2 failed: {}", stderr(out));
}

/// Products written: exit status 0, or 3 where the divergence guard rejected the step's model
/// (for tests about something else than whether the step converges).
pub fn check_written(out: &Output) {
    assert!(matches!(out.status.code(), Some(0 | 3)), "r2d2 failed: {}", stderr(out));
}

/// Standard output and standard error together (listings go to stdout, errors to stderr).
pub fn text(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

/// Writes the tiny analytic ONNX series of tests/make_test_models.py into `dir` (Python with
/// the `onnx` package is a test requirement: a missing one fails the test, it is not skipped).
/// The Landweber series' gain is `gain`.
pub fn make_test_models(dir: &Path, gain: f64) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/make_test_models.py");
    let out = Command::new("python3").arg(&script).arg(dir).arg("--gain").arg(gain.to_string()).output().expect("python3 runs (a test requirement)");
    assert!(out.status.success(), "{} failed (pip install -r tests/requirements.txt): {}", script.display(), text(&out));
}

/// Image side of the shared test observation.
pub const SIZE: usize = 64;

/// A short VLA C observation in `dir/obs.parquet` (64 x 64 image, 1 h, 300 s integrations).
pub fn observation(dir: &Path) {
    check(&r2d2(
        &["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", &SIZE.to_string(), "--seed", "3", "--out", "obs.parquet"],
        dir,
    ));
}

pub fn read(path: &Path) -> Vec<f64> {
    read_image(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).data
}

pub fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |m, x| m.max(x.abs()))
}

pub fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).fold(0.0, |m, (x, y)| m.max((x - y).abs()))
}

/// `D x` through a NUFFT round trip at accuracy 1e-10, for the same weights as the default
/// pipeline (Briggs 0, super-resolution 1.5) and with the w-term where the pipeline includes
/// it (`auto`): not the 2N-PSF convolution the pipeline's residual uses where the w-term is
/// negligible, so it checks that too.
pub struct ReferenceOperator {
    operator: NormalOperator,
}

impl ReferenceOperator {
    pub fn new(observation: &Path) -> ReferenceOperator {
        let (vis, _, _) = read_parquet(observation).unwrap();
        let params = DirtyParams {
            size: SIZE,
            threads: 1,
            nufft: NufftParams { epsilon: 1e-10, oversampling: 2.0 },
            w_term: WTermMode::Auto,
            ..DirtyParams::default()
        };
        let operator = NormalOperator::new(&vis, &params).unwrap();
        ReferenceOperator { operator }
    }

    pub fn apply(&self, x: &[f64]) -> Vec<f64> {
        self.operator.apply(x)
    }

    /// 1 / ||D||: a step size for which Landweber iterations converge.
    pub fn landweber_gain(&self) -> f64 {
        1.0 / self.operator.norm(1e-8, 200)
    }
}

/// `iterations` steps of `x_i = P(x_{i-1} + gain (x_d - D x_{i-1}) + bias alpha_i)`, P the
/// projection on the positive orthant (or the identity), alpha_i the reference loop's
/// normalisation (mean of the dirty image for i = 1, else of x_{i-1}); returns the estimate
/// and its residual. With bias 0 it is plain projected Landweber.
pub fn landweber_reference(d: &ReferenceOperator, dirty: &[f64], gain: f64, bias: f64, iterations: usize, positivity: bool) -> (Vec<f64>, Vec<f64>) {
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let mut x = vec![0.0; dirty.len()];
    let mut r = dirty.to_vec();
    for i in 1..=iterations {
        let alpha = if i == 1 { mean(dirty) } else { mean(&x) };
        for (xi, ri) in x.iter_mut().zip(&r) {
            *xi += gain * ri + bias * alpha;
            if positivity {
                *xi = xi.max(0.0);
            }
        }
        let dx = d.apply(&x);
        r = dirty.iter().zip(&dx).map(|(a, b)| a - b).collect();
    }
    (x, r)
}
