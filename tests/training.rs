//! The training path end to end in seconds (training/smoke.py): ground truths, `r2d2 trainset`,
//! two networks, ONNX export, manifest, resume, evaluation against the engine's CLEAN, and
//! the Python D against the engine's Toeplitz residual. Needs the Python packages of
//! training/requirements.txt (`.ci/run` installs them); a missing one fails this test.

use std::process::Command;

#[test]
fn training_smoke_run() {
    let root = env!("CARGO_MANIFEST_DIR");
    let output = Command::new("python3")
        .arg(format!("{root}/training/smoke.py"))
        .arg("--r2d2")
        .arg(env!("CARGO_BIN_EXE_r2d2"))
        .current_dir(root)
        .output()
        .expect("python3 must be on PATH for the training smoke test (pip install -r training/requirements.txt)");
    assert!(
        output.status.success(),
        "training/smoke.py failed ({}):\n--- stdout\n{}\n--- stderr\n{}",
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
}
