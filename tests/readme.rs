//! The README's commands run as written (its ```sh blocks, in order, in one directory), so the
//! front door stays true: the quick start, imaging a MeasurementSet, predicting into it.
//! `cargo` and `pip` lines are what CI itself does and are skipped; `target/release/r2d2` is
//! the binary under test. An MS to image is made first (the README's `obs.ms`).

use std::path::Path;
use std::process::Command;

/// The commands of the README's ```sh blocks: continuation lines joined, comments dropped.
fn commands(readme: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut in_sh = false;
    let mut pending = String::new();
    for line in readme.lines() {
        if line.trim_start().starts_with("```") {
            in_sh = !in_sh && line.trim() == "```sh";
            continue;
        }
        if !in_sh {
            continue;
        }
        let code = line.split(" #").next().unwrap_or("").trim_end();
        let code = if code.trim_start().starts_with('#') { "" } else { code };
        if let Some(head) = code.strip_suffix('\\') {
            pending.push_str(head);
            continue;
        }
        pending.push_str(code);
        let command = std::mem::take(&mut pending).trim().to_string();
        if !command.is_empty() {
            out.push(command);
        }
    }
    out
}

#[test]
fn the_readme_commands_run_as_written() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let all = commands(&readme);
    assert!(all.iter().any(|c| c.contains("pipelines/quickstart.yaml")) && all.iter().any(|c| c.contains("image obs.ms")), "{all:?}");
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir(d.join("pipelines")).unwrap();
    std::fs::copy(root.join("pipelines/quickstart.yaml"), d.join("pipelines/quickstart.yaml")).unwrap();
    let bin = env!("CARGO_BIN_EXE_r2d2");
    let run = |command: &str| {
        let out = Command::new("sh").arg("-c").arg(command).current_dir(d).output().unwrap();
        assert!(out.status.success(), "`{command}` failed:\n{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        // The quick start is the first run a newcomer sees: an observation inside the series'
        // domain, nothing to warn about.
        let log = String::from_utf8_lossy(&out.stderr);
        assert!(!(command.contains("quickstart") && log.contains("WARN")), "the quick start warns:\n{log}");
    };
    // The README's obs.ms: a VLA observation at 300 s integrations (small, so the test is
    // quick) long enough for the series, which rejects its model on shorter tracks (exit 3).
    run(&format!("{bin} simulate --configs a,c --hours 4,1 --integration-s 300 --seed 2 --out obs.parquet -q && {bin} convert obs.parquet obs.ms -q"));
    let mut ran = 0;
    for command in &all {
        if command.starts_with("cargo ") || command.starts_with("pip ") {
            continue;
        }
        run(&command.replace("target/release/r2d2", bin));
        ran += 1;
    }
    assert!(ran >= 4, "{all:?}");
    // What the commands promise exists.
    for file in ["out/quickstart/sim-7-image.fits", "out/quickstart/sim-7-model.fits", "obs-image.fits", "obs-model.fits", "obs-residual.fits"] {
        assert!(d.join(file).is_file(), "{file} missing");
    }
}

#[test]
fn commands_are_read_from_sh_blocks_only() {
    let text = "x\n```sh\na --b \\\n   c   # note\n# comment\ncargo test\n```\n```python\nimport y\n```\n```sh\nz\n```\n";
    assert_eq!(commands(text), ["a --b    c", "cargo test", "z"]);
}
