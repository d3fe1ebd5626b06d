//! Fault injection against the release binary: the process killed (SIGKILL, no chance to
//! clean up) at moments through a run, a full disk, a read-only output directory. Each must
//! keep the all-or-nothing promise: a job's products are the earlier run's or this run's,
//! never a mix, and a failure leaves the earlier products as they were. (Plugin faults:
//! tests/plugins.rs; SIGTERM and Ctrl-C: tests/pipeline.rs and tests/plugins.rs.)
//!
//! A kill between the renames of a commit is made exact by a test hook
//! (`R2D2_TEST_KILL_AFTER_RENAMES=N`: the process kills itself after N renames); the next run
//! writing into the directory rolls the commit back, or forward if every rename was done.
//!
//! The disk faults need a private mount namespace (`unshare -rm`, util-linux); CI machines
//! allow it, and without one the test fails rather than passing untested.

mod common;

use common::{check, observation, r2d2, SIZE};
use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

fn pipeline() -> String {
    format!(
        "name: faults\nimage:\n  size: {SIZE}\nstages:\n  source:\n    kind: parquet\n    files: obs.parquet\n    to: weights\n  weights:\n    kind: weighting\n    scheme: briggs\n    robust: 0\n    to: grid\n  grid:\n    kind: gridder\n    to: step\n  step:\n    kind: clean\n    major_cycles: 2\n    to: update\n  update:\n    kind: residual\n    to: step\n    done: write\n  write:\n    kind: writer\n    prefix: \"out/{{job}}\"\n"
    )
}

/// Every file of `dir` (names starting with '.' included) and its bytes.
fn contents(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut files = BTreeMap::new();
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        files.insert(name, if entry.path().is_file() { std::fs::read(entry.path()).unwrap() } else { Vec::new() });
    }
    files
}

/// Products (visible files) only.
fn products(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    contents(dir).into_iter().filter(|(n, _)| !n.starts_with('.')).collect()
}

/// Names of the staging directories left in `dir`.
fn staging_left(dir: &Path) -> Vec<String> {
    contents(dir).into_keys().filter(|n| n.starts_with(".r2d2-staging")).collect()
}

/// Replaces whatever is in `dir` by `files`.
fn restore(dir: &Path, files: &BTreeMap<String, Vec<u8>>) {
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let _ = std::fs::remove_dir_all(entry.path()).or_else(|_| std::fs::remove_file(entry.path()));
    }
    for (name, bytes) in files {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
}

/// A later run writing into `out/` (`r2d2 dirty` under another prefix), which recovers what a
/// killed commit left there; its standard error.
fn later_run(d: &Path) -> String {
    let out = r2d2(&["dirty", "obs.parquet", "--size", &SIZE.to_string(), "--name", "out/later"], d);
    check(&out);
    let err = common::stderr(&out);
    let out_dir = d.join("out");
    for name in ["later-dirty.fits", "later-psf.fits"] {
        std::fs::remove_file(out_dir.join(name)).unwrap();
    }
    assert!(staging_left(&out_dir).is_empty(), "staging left after the later run: {:?}", staging_left(&out_dir));
    err
}

#[test]
fn a_run_killed_at_any_moment_leaves_the_earlier_products_or_the_new_ones_never_a_mix() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    std::fs::write(d.join("p.yaml"), pipeline()).unwrap();
    let run = |cycles: &str| Command::new(env!("CARGO_BIN_EXE_r2d2")).args(["run", "p.yaml", "--set", &format!("step.major_cycles={cycles}")]).current_dir(d).spawn().unwrap();
    // The two complete sets: 2 and 3 major cycles (their models, residuals and metrics differ).
    assert!(run("3").wait().unwrap().success());
    let new = products(&d.join("out"));
    assert!(run("2").wait().unwrap().success());
    let old = products(&d.join("out"));
    assert_ne!(old["obs-model.fits"], new["obs-model.fits"]);
    let began = std::time::Instant::now();
    let mut child = run("3");
    child.wait().unwrap();
    let full = began.elapsed();
    let (mut saw_old, mut saw_new) = (0, 0);
    for k in 0..12 {
        // Back to the earlier set, then kill a run at a fraction of its length.
        for entry in std::fs::read_dir(d.join("out")).unwrap().flatten() {
            let _ = std::fs::remove_dir_all(entry.path()).or_else(|_| std::fs::remove_file(entry.path()));
        }
        for (name, bytes) in &old {
            std::fs::write(d.join("out").join(name), bytes).unwrap();
        }
        let mut child = run("3");
        std::thread::sleep(full.mul_f64(k as f64 / 6.0));
        let _ = child.kill();
        let _ = child.wait();
        // What any later run writing there finds, once it has recovered a commit cut short.
        later_run(d);
        // Products carry run-specific values (timings, dates), so a new set is recognised as
        // one in which no file that differs between the two runs is the earlier one.
        let now = products(&d.join("out"));
        assert_eq!(now.keys().collect::<Vec<_>>(), old.keys().collect::<Vec<_>>(), "killed at {k}/6: the set of products changed");
        let differing: Vec<&String> = old.keys().filter(|n| old[*n] != new[*n]).collect();
        let still_old: Vec<&&String> = differing.iter().filter(|n| now[**n] == old[**n]).collect();
        if still_old.len() == differing.len() {
            saw_old += 1;
        } else if still_old.is_empty() {
            saw_new += 1;
        } else {
            panic!("killed at {k}/6 of the run: a mix of earlier and new products (still the earlier: {still_old:?} of {differing:?})");
        }
    }
    // The kills fell both before and after the commit, so both outcomes were checked.
    assert!(saw_old > 0 && saw_new > 0, "old {saw_old}, new {saw_new}: the kill times missed one side");
}

#[test]
fn a_commit_killed_between_renames_is_rolled_back_or_forward_by_the_next_run() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    std::fs::write(d.join("p.yaml"), pipeline()).unwrap();
    let out_dir = d.join("out");
    check(&r2d2(&["run", "p.yaml", "-q"], d));
    let old = products(&out_dir);
    // Every earlier product is moved aside, then every new one moved in.
    let renames = 2 * old.len();
    for n in 0..=renames {
        restore(&out_dir, &old);
        let killed = Command::new(env!("CARGO_BIN_EXE_r2d2"))
            .args(["run", "p.yaml", "-q", "--set", "step.major_cycles=3"])
            .current_dir(d)
            .env("R2D2_TEST_KILL_AFTER_RENAMES", n.to_string())
            .output()
            .unwrap();
        assert_eq!(std::os::unix::process::ExitStatusExt::signal(&killed.status), Some(9), "after {n} renames: {}", common::stderr(&killed));
        let left = products(&out_dir);
        assert_eq!(staging_left(&out_dir).len(), 1, "after {n} renames");
        if n > 0 && n < renames {
            assert_ne!(left, old, "after {n} renames the directory is as before: the hook did not cut the commit");
        }
        let said = later_run(d);
        let now = products(&out_dir);
        if n < renames {
            assert!(said.contains("rolled back"), "after {n} renames: {said}");
            assert!(now == old, "after {n} of {renames} renames and a later run: not the earlier set, byte for byte");
        } else {
            // Every file moved in: the new set stands whole, as the kill left it.
            assert!(said.contains("rolled forward"), "{said}");
            assert!(now == left, "after all renames and a later run: not the new set, byte for byte");
            assert_ne!(now["obs-model.fits"], old["obs-model.fits"]);
        }
    }
}

/// Runs `script` in a private mount namespace (as `sh -c`), in `dir`; stdout and stderr.
fn in_namespace(dir: &Path, script: &str) -> (String, String) {
    let probe = Command::new("unshare").args(["-rm", "true"]).output();
    assert!(probe.is_ok_and(|o| o.status.success()), "no private mount namespace here (unshare -rm): the disk faults cannot be injected");
    let out = Command::new("unshare").args(["-rm", "sh", "-c", script]).current_dir(dir).output().unwrap();
    (String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
}

#[test]
fn a_full_disk_or_a_read_only_directory_fails_cleanly_and_keeps_the_earlier_products() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    std::fs::write(d.join("p.yaml"), pipeline()).unwrap();
    let exe = env!("CARGO_BIN_EXE_r2d2");
    // A small disk: a first run fits; the disk is then filled but for 8 KiB, and a second run
    // (another result) must fail naming the full disk and leave the first run's files whole.
    let script = format!(
        "set -u; mkdir -p out && mount -t tmpfs -o size=1m tmpfs out && {exe} run p.yaml -q || exit 9; \
         md5sum out/* > before.txt; dd if=/dev/zero of=out/.filler bs=4k 2>/dev/null; truncate -s -8k out/.filler; \
         {exe} run p.yaml -q --set step.major_cycles=3; echo \"rc=$?\"; rm out/.filler; md5sum out/* > after.txt; \
         cmp before.txt after.txt && echo same; ls -A out | grep -c staging"
    );
    let (stdout, err) = in_namespace(d, &script);
    assert!(stdout.contains("rc=1\n"), "{stdout}{err}");
    assert!(err.contains("No space left on device"), "{err}");
    assert!(stdout.contains("same\n"), "the earlier products changed: {stdout}{err}");
    assert!(stdout.trim_end().ends_with("\n0") || stdout.trim_end() == "0", "staging left behind: {stdout}");

    // A read-only output directory: refused naming it, nothing written anywhere.
    let script = format!("mkdir -p out && mount -t tmpfs -o ro tmpfs out && {exe} run p.yaml -q; echo \"rc=$?\"; ls -A out | wc -l");
    let (stdout, err) = in_namespace(d, &script);
    assert_eq!(stdout, "rc=1\n0\n", "{err}");
    assert!(err.contains("out") && err.contains("Read-only file system"), "{err}");

    // An output "directory" that is a file: refused naming it.
    std::fs::write(d.join("file"), "a file").unwrap();
    let out = r2d2(&["run", "p.yaml", "--set", "write.prefix=file/{job}"], d);
    let err = common::assert_fails_with(&out, "output path is a file", &["file"]);
    assert!(std::fs::read_to_string(d.join("file")).unwrap() == "a file", "{err}");
    check(&r2d2(&["run", "p.yaml", "--set", "write.prefix=dir/{job}"], d));
}

/// Every file of `dir` and below, and its bytes.
fn tree(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut files = BTreeMap::new();
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let path = entry.path();
        if path.is_dir() {
            files.extend(tree(&path).into_iter().map(|(k, v)| (format!("{}/{k}", entry.file_name().to_string_lossy()), v)));
        } else {
            files.insert(entry.file_name().to_string_lossy().into_owned(), std::fs::read(&path).unwrap());
        }
    }
    files
}

/// Outputs that would land on inputs (issue 23): each is refused with an error naming both,
/// before any work, and every file the user had is left byte for byte.
#[test]
fn outputs_never_replace_or_delete_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    std::fs::create_dir(d.join("keep")).unwrap();
    std::fs::copy(d.join("obs.parquet"), d.join("keep/obs.parquet")).unwrap();
    std::fs::write(d.join("keep/notes.txt"), "the user's notes").unwrap();
    std::fs::copy(d.join("obs.sky.fits"), d.join("t-model.fits")).unwrap();
    std::fs::copy(d.join("obs.parquet"), d.join("x-metrics.parquet")).unwrap();
    let before = tree(d);
    let refused = |args: &[&str], words: &[&str]| {
        let out = r2d2(args, d);
        common::assert_fails_with(&out, &args.join(" "), words);
        assert_eq!(tree(d), before, "{}: the files changed", args.join(" "));
    };
    // `convert` onto a directory that is not an MS (with the input inside it), onto itself,
    // and to a Parquet path that is a directory.
    refused(&["convert", "keep/obs.parquet", "keep/"], &["keep", "input"]);
    refused(&["convert", "obs.parquet", "keep"], &["keep", "not a MeasurementSet"]);
    refused(&["convert", "obs.parquet", "obs.parquet"], &["obs.parquet", "input"]);
    // Products over the truth, or over the visibility table.
    let image = ["image", "--size", "64", "--step", "clean", "--iterations", "1"];
    refused(&[&image[..], &["obs.parquet", "--truth", "t-model.fits", "--name", "t"]].concat(), &["t-model.fits", "would replace the input"]);
    refused(&[&image[..], &["x-metrics.parquet", "--name", "x"]].concat(), &["x-metrics.parquet", "would replace the input"]);
    // Several jobs and a prefix without {job}: `validate` and `run` refuse it.
    let text = pipeline().replace("    files: obs.parquet\n", "    files: obs.parquet\n    split_by: {column: time, window: 600}\n").replace("out/{job}", "out/all");
    std::fs::write(d.join("p.yaml"), text).unwrap();
    let before = tree(d);
    for command in ["validate", "run"] {
        let out = r2d2(&[command, "p.yaml"], d);
        common::assert_fails_with(&out, command, &["p.yaml", "out/all", "{job}", "split_by"]);
        assert_eq!(tree(d), before);
    }
}

/// A staging directory planted in a shared output directory (issue 56), its journal naming
/// files outside it (`..`, an absolute path): the next run writing there leaves them alone,
/// warns, and writes its own products.
#[test]
fn a_planted_staging_journal_changes_nothing_outside_the_run_s_products() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    std::fs::create_dir_all(d.join("victimdir")).unwrap();
    for name in ["victimdir/precious.txt", "precious2.txt", "abs.txt"] {
        std::fs::write(d.join(name), format!("the user's {name}")).unwrap();
    }
    let planted = d.join("out/.r2d2-staging-planted");
    for name in ["new/x-dirty.fits", "earlier/2", "earlier/3"] {
        std::fs::create_dir_all(planted.join(name).parent().unwrap()).unwrap();
        std::fs::write(planted.join(name), "planted bytes").unwrap();
    }
    let journal = serde_json::json!({
        "version": 1,
        "products": ["x-dirty.fits", "../victimdir/precious.txt"],
        "retired": ["../precious2.txt", d.join("abs.txt")],
    });
    std::fs::write(planted.join("journal.json"), journal.to_string()).unwrap();
    let before: BTreeMap<String, Vec<u8>> = tree(d).into_iter().filter(|(name, _)| !name.starts_with("out/")).collect();
    let out = r2d2(&["dirty", "obs.parquet", "--size", &SIZE.to_string(), "--name", "out/obs"], d);
    check(&out);
    let err = common::stderr(&out);
    assert!(err.contains(".r2d2-staging-planted") && err.contains("left as it is") && err.contains("../victimdir/precious.txt"), "a warning names the journal: {err}");
    let after: BTreeMap<String, Vec<u8>> = tree(d).into_iter().filter(|(name, _)| !name.starts_with("out/")).collect();
    assert!(after == before, "files outside out/ changed: {:?}", after.keys().collect::<Vec<_>>());
    assert!(d.join("out/obs-dirty.fits").exists() && d.join("out/obs-psf.fits").exists(), "the run's products are written");
}
