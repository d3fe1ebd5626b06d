//! A deterministic mutation fuzzer over the inputs r2d2 takes from outside: a Parquet table,
//! an Arrow IPC stream, a pipeline's YAML, a FITS truth image and a series manifest. Each
//! valid seed file is mutated (bit flips, interesting bytes, cut, duplicated or deleted
//! ranges, truncation) by a seeded generator and given to the release binary; every case must
//! end with success (exit 0) or a clean error (exit 1, an `error:` line), never a panic (exit
//! 101, or "panicked" printed), a signal (abort, segfault) or a hang (60 s).
//!
//! `cargo test --release --test fuzz` runs 12 cases per input kind (seconds); more by hand:
//!
//!     R2D2_FUZZ_CASES=2000 R2D2_FUZZ_SEED=7 cargo test --release --test fuzz -- --nocapture
//!
//! A failing case is kept under the test's target directory (`fuzz-failures/`), with the
//! command that reproduces it, and named in the failure message.

mod common;

use common::{check, observation, stderr, SIZE};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn env_number(name: &str, default: u64) -> u64 {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// One mutation of `data`, in place.
fn mutate(data: &mut Vec<u8>, rng: &mut ChaCha8Rng) {
    if data.is_empty() {
        data.push(rng.gen());
        return;
    }
    let len = data.len();
    let at = rng.gen_range(0..len);
    match rng.gen_range(0..7) {
        0 => data[at] ^= 1 << rng.gen_range(0..8),
        1 => data[at] = [0x00, 0xff, 0x7f, 0x80, 0x01, b'-', b'9', b'{', b':'][rng.gen_range(0..9)],
        2 => {
            // Overwrite 8 bytes with an extreme little-endian integer or float (sizes, counts).
            let word: u64 = [u64::MAX, 1 << 40, 0x7ff0_0000_0000_0000, 0x7fef_ffff_ffff_ffff, 0, 1 << 31][rng.gen_range(0..6)];
            for (k, b) in word.to_le_bytes().iter().enumerate() {
                if at + k < len {
                    data[at + k] = *b;
                }
            }
        }
        3 => data.truncate(at),
        4 => {
            let end = (at + rng.gen_range(1..64)).min(len);
            data.drain(at..end);
        }
        5 => {
            let end = (at + rng.gen_range(1..64)).min(len);
            let copy = data[at..end].to_vec();
            let to = rng.gen_range(0..=data.len());
            data.splice(to..to, copy);
        }
        _ => {
            let bytes: Vec<u8> = (0..rng.gen_range(1..16)).map(|_| rng.gen()).collect();
            data.splice(at..at, bytes);
        }
    }
}

/// Runs r2d2 with a time limit; the outcome in words if it is not a clean one.
fn run_bounded(args: &[&str], dir: &Path) -> Option<String> {
    let mut child = Command::new(env!("CARGO_BIN_EXE_r2d2"))
        .args(args)
        .current_dir(dir)
        .env("R2D2_MODELS", Path::new(env!("CARGO_MANIFEST_DIR")).join("models"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("r2d2 runs");
    let mut err = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut text = String::new();
        let _ = std::io::Read::read_to_string(&mut err, &mut text);
        text
    });
    let began = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break Some(status);
        }
        if began.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let err = reader.join().unwrap();
    match status {
        None => Some("hung (killed after 60 s)".into()),
        Some(s) if s.code() == Some(0) && !err.contains("panicked") => None,
        Some(s) if s.code() == Some(1) && err.contains("error:") && !err.contains("panicked") => None,
        Some(s) => Some(format!("{s}: {}", err.chars().rev().take(1500).collect::<String>().chars().rev().collect::<String>())),
    }
}

struct Kind {
    name: &'static str,
    /// The file the mutated bytes are written to (relative to the case directory).
    file: &'static str,
    seed: Vec<u8>,
    args: Vec<String>,
}

/// An Arrow IPC stream of the observation's table (schema metadata included).
fn ipc_stream(parquet: &Path) -> Vec<u8> {
    use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
    let builder = ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(parquet).unwrap()).unwrap();
    let schema = builder.schema().clone();
    let mut out = Vec::new();
    let mut writer = arrow::ipc::writer::StreamWriter::try_new(&mut out, &schema).unwrap();
    for batch in builder.with_batch_size(1000).build().unwrap() {
        writer.write(&batch.unwrap()).unwrap();
    }
    writer.finish().unwrap();
    drop(writer);
    out
}

fn copy_series(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap().flatten() {
        if entry.path().extension().is_some_and(|e| e == "onnx") {
            let target = to.join(entry.file_name());
            if std::fs::hard_link(entry.path(), &target).is_err() {
                std::fs::copy(entry.path(), &target).unwrap();
            }
        }
    }
}

#[test]
fn mutated_inputs_end_in_success_or_a_clean_error() {
    let cases = env_number("R2D2_FUZZ_CASES", 12);
    let seed = env_number("R2D2_FUZZ_SEED", 1);
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let obs = d.join("obs.parquet");
    let pipeline = |source: &str| {
        format!(
            "name: fuzz\nimage:\n  size: {SIZE}\nstages:\n  source:\n{source}    to: weights\n  weights:\n    kind: weighting\n    scheme: briggs\n    robust: 0\n    to: grid\n  grid:\n    kind: gridder\n    to: step\n  step:\n    kind: clean\n    major_cycles: 2\n    to: update\n  update:\n    kind: residual\n    to: step\n    done: write\n  write:\n    kind: writer\n    prefix: \"out/{{job}}\"\n"
        )
    };
    let series = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/vla-r2d2-128");
    let manifest_pipeline = "name: m\nimage:\n  size: 128\nstages:\n  source:\n    kind: parquet\n    files: ../obs.parquet\n    to: weights\n  weights:\n    kind: weighting\n    scheme: briggs\n    robust: 0\n    to: grid\n  grid:\n    kind: gridder\n    to: step\n  step:\n    kind: onnx\n    series: series\n    to: update\n  update:\n    kind: residual\n    to: step\n    done: write\n  write:\n    kind: writer\n    prefix: \"out/{job}\"\n";
    let s = |v: &[&str]| v.iter().map(|a| a.to_string()).collect::<Vec<_>>();
    let image = |input: &str| s(&["image", input, "--size", &SIZE.to_string(), "--step", "clean", "--name", "out/x"]);
    let kinds = [
        Kind { name: "parquet", file: "in.parquet", seed: std::fs::read(&obs).unwrap(), args: image("in.parquet") },
        Kind {
            name: "arrow-ipc",
            file: "in.arrows",
            seed: ipc_stream(&obs),
            args: s(&["run", "ipc.yaml"]),
        },
        Kind { name: "yaml", file: "in.yaml", seed: pipeline("    kind: parquet\n    files: ../obs.parquet\n").into_bytes(), args: s(&["run", "in.yaml"]) },
        Kind {
            name: "fits-truth",
            file: "truth.fits",
            seed: std::fs::read(d.join("obs.sky.fits")).unwrap(),
            args: s(&["image", "../obs.parquet", "--size", &SIZE.to_string(), "--step", "clean", "--truth", "truth.fits", "--name", "out/x"]),
        },
        Kind {
            name: "manifest",
            file: "series/manifest.yaml",
            seed: std::fs::read(series.join("manifest.yaml")).unwrap(),
            args: s(&["validate", "manifest.yaml"]),
        },
    ];
    // The unmutated seeds succeed: the harness starts from valid inputs.
    let mut failures = Vec::new();
    let kept = Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-failures");
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for kind in &kinds {
        for case in 0..=cases {
            let case_dir = d.join(format!("{}-{case}", kind.name));
            std::fs::create_dir_all(&case_dir).unwrap();
            std::fs::write(case_dir.join("ipc.yaml"), pipeline("    kind: arrow-ipc\n    path: in.arrows\n")).unwrap();
            if kind.name == "manifest" {
                copy_series(&series, &case_dir.join("series"));
                std::fs::write(case_dir.join("manifest.yaml"), manifest_pipeline).unwrap();
            }
            let mut data = kind.seed.clone();
            if case > 0 {
                for _ in 0..rng.gen_range(1..=4) {
                    mutate(&mut data, &mut rng);
                }
            }
            std::fs::write(case_dir.join(kind.file), &data).unwrap();
            let args: Vec<&str> = kind.args.iter().map(String::as_str).collect();
            let outcome = run_bounded(&args, &case_dir);
            if case == 0 {
                assert!(outcome.is_none(), "{}: the unmutated seed failed: {outcome:?}", kind.name);
                let out = Command::new(env!("CARGO_BIN_EXE_r2d2")).args(&args).current_dir(&case_dir).output().unwrap();
                check(&out);
                assert!(!stderr(&out).contains("panicked"));
            }
            if let Some(outcome) = outcome {
                let keep = kept.join(format!("seed{seed}-{}-{case}", kind.name));
                std::fs::create_dir_all(&keep).unwrap();
                std::fs::write(keep.join(Path::new(kind.file).file_name().unwrap()), &data).unwrap();
                failures.push(format!("{} case {case} (kept in {}; r2d2 {}): {outcome}", kind.name, keep.display(), kind.args.join(" ")));
            }
            std::fs::remove_dir_all(&case_dir).unwrap();
        }
    }
    assert!(failures.is_empty(), "{} of {} mutated cases did not end cleanly:\n{}", failures.len(), cases as usize * kinds.len(), failures.join("\n\n"));
}
