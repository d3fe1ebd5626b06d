//! The Python package (`pip install .`, python/) built and tested as a user gets it: a virtual
//! environment under the target directory (made once, then reused), the package installed
//! into it with maturin, and its pytest suite run (python/tests: the API, the Dask fan-out on a
//! LocalCluster of two worker processes, the Stimela recipe). Nothing is skipped: a missing
//! package, a skipped or an expected-to-fail test fails this test.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn ok(what: &str, out: Output) -> String {
    let text = format!("--- stdout\n{}\n--- stderr\n{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{what} failed ({}):\n{text}", out.status);
    text
}

fn run(what: &str, command: &mut Command) -> String {
    let out = command.output().unwrap_or_else(|e| panic!("{what}: cannot start {:?}: {e}", command.get_program()));
    ok(what, out)
}

/// target/ (or $CARGO_TARGET_DIR): the binary's directory's parent.
fn target_dir() -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_r2d2")).parent().and_then(Path::parent).expect("the binary lies in target/<profile>/").to_path_buf()
}

#[test]
fn python_package_builds_and_passes_its_tests() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let venv = target_dir().join("python-tests-venv");
    let bin = venv.join("bin");
    let python = bin.join("python");
    if !python.exists() {
        // System site-packages: numpy, pyarrow, astropy and onnxruntime come from
        // tests/requirements.txt, installed once by .ci/run.
        run("python3 -m venv", Command::new("python3").args(["-m", "venv", "--system-site-packages"]).arg(&venv));
    }
    let pip = |args: &[&str]| {
        run(
            &format!("pip install {}", args.join(" ")),
            Command::new(&python).args(["-m", "pip", "install", "--quiet", "--disable-pip-version-check"]).args(args).current_dir(root),
        )
    };
    pip(&["-r", "python/tests/requirements.txt"]);
    // The build backend (maturin) is in the environment: no isolated build environment to
    // download each time. Cargo builds the extension in this workspace's target directory.
    let path = format!("{}:{}", bin.display(), std::env::var("PATH").unwrap_or_default());
    run(
        "pip install . (maturin)",
        Command::new(&python)
            .args(["-m", "pip", "install", "--quiet", "--disable-pip-version-check", "--no-build-isolation", "--force-reinstall", "--no-deps", "."])
            .current_dir(root)
            .env("PATH", &path),
    );
    let text = run(
        "pytest python/tests",
        Command::new(&python)
            .args(["-m", "pytest", "-p", "no:cacheprovider", "-rfEsxX", "python/tests"])
            .current_dir(root)
            .env("PATH", &path)
            .env("R2D2_BIN", env!("CARGO_BIN_EXE_r2d2"))
            .env("R2D2_MODELS", root.join("models")),
    );
    let summary = text.lines().rev().find(|l| l.contains(" passed")).unwrap_or_else(|| panic!("no pytest summary:\n{text}"));
    for word in ["skipped", "xfail", "xpassed", "deselected"] {
        assert!(!text.contains(word), "pytest reported '{word}' (nothing may be skipped):\n{text}");
    }
    println!("{summary}");
}
