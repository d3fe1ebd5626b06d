//! The Python package (`pip install .`, python/) built and tested as a user gets it: a virtual
//! environment under the target directory (made once, then reused), the package installed
//! into it with maturin, and its pytest suite run (python/tests: the API, the Dask fan-out on a
//! LocalCluster of two worker processes, the Stimela recipe). Nothing is skipped: a missing
//! package, a skipped or an expected-to-fail test fails this test.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

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

/// The virtual environment with the package installed, made once per test run; its `bin/`.
fn installed_package() -> &'static Path {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| {
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
        run(
            "pip install . (maturin)",
            Command::new(&python)
                .args(["-m", "pip", "install", "--quiet", "--disable-pip-version-check", "--no-build-isolation", "--force-reinstall", "--no-deps", "."])
                .current_dir(root)
                .env("PATH", search_path(&bin)),
        );
        bin
    })
}

/// PATH with the environment's `bin/` first.
fn search_path(bin: &Path) -> String {
    format!("{}:{}", bin.display(), std::env::var("PATH").unwrap_or_default())
}

#[test]
fn python_package_builds_and_passes_its_tests() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let bin = installed_package();
    let text = run(
        "pytest python/tests",
        Command::new(bin.join("python"))
            .args(["-m", "pytest", "-p", "no:cacheprovider", "-rfEsxX", "python/tests"])
            .current_dir(root)
            .env("PATH", search_path(bin))
            .env("R2D2_BIN", env!("CARGO_BIN_EXE_r2d2"))
            .env("R2D2_MODELS", root.join("models")),
    );
    let summary = text.lines().rev().find(|l| l.contains(" passed")).unwrap_or_else(|| panic!("no pytest summary:\n{text}"));
    for word in ["skipped", "xfail", "xpassed", "deselected"] {
        assert!(!text.contains(word), "pytest reported '{word}' (nothing may be skipped):\n{text}");
    }
    println!("{summary}");
}

/// A process forked after the engine ran (a `multiprocessing.Pool` with Linux's default
/// start method) gets a clear error, with the default threads and with one, instead of waiting
/// for ever on the parent's compute threads, which the fork did not copy; a pool started with
/// the 'spawn' method, as the error advises, images as the parent did.
#[test]
fn a_process_forked_after_the_engine_ran_is_refused_and_spawned_ones_image() {
    let bin = installed_package();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    run(
        "r2d2 simulate",
        Command::new(env!("CARGO_BIN_EXE_r2d2"))
            .args(["-q", "simulate", "--configs", "c", "--hours", "0.25", "--integration-s", "300", "--size", "64", "--seed", "5", "--out", "obs.parquet"])
            .current_dir(d),
    );
    let script = r#"
import multiprocessing, os
import r2d2_imaging

def model_sum(threads):
    return float(r2d2_imaging.image("obs.parquet", size=64, step="clean", iterations=2, threads=threads).model.sum())

def refusal(threads):
    try:
        model_sum(threads)
    except r2d2_imaging.R2D2Error as e:
        return os.getpid(), str(e)
    return os.getpid(), "imaged"

if __name__ == "__main__":
    expected = model_sum(0)
    with multiprocessing.get_context("fork").Pool(2) as pool:
        refusals = pool.map(refusal, [0, 1])
    for pid, message in refusals:
        start = f"this process ({pid}) was forked from process {os.getpid()} after the engine had started its compute threads there"
        assert message.startswith(start) and 'multiprocessing.get_context("spawn")' in message, message
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        results = pool.map(model_sum, [0, 1])
    assert results == [expected, expected], (results, expected)
    print("forked children refused:", refusals[0][1])
    print("spawned children imaged:", results)
"#;
    std::fs::write(d.join("fork.py"), script).unwrap();
    // In a process group of its own, so that a hung pool's workers go with the script.
    let mut child = std::os::unix::process::CommandExt::process_group(
        Command::new(bin.join("python")).arg("fork.py").current_dir(d).stdout(Stdio::piped()).stderr(Stdio::piped()),
        0,
    )
    .spawn()
    .expect("python runs");
    let began = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if began.elapsed() > Duration::from_secs(120) {
            // SAFETY: kill(2) on the group this test started (the child is not reaped yet).
            unsafe { libc::kill(-(child.id() as libc::pid_t), libc::SIGKILL) };
            let out = child.wait_with_output().unwrap();
            panic!("the forked children still run after 120 s (a hang):\n{}", String::from_utf8_lossy(&out.stderr));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let text = ok("python fork.py", child.wait_with_output().unwrap());
    assert!(text.contains("spawned children imaged"), "{text}");
}
