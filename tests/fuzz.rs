//! A deterministic mutation fuzzer over the inputs r2d2 takes from outside: a Parquet table,
//! an Arrow IPC stream (plain, and with LZ4 and ZSTD buffers), a pipeline's YAML, a FITS truth
//! image (plain and gzip-compressed), a series manifest, a MeasurementSet's table files
//! (written by python-casacore, tests/make_ms.py), the networks and manifest of an ONNX
//! series (tests/make_test_models.py; on ONNX Runtime where it is found, and on tract) and a
//! staging journal planted in an output directory. Each valid seed file (for an MS or a
//! series, one of its files picked at random) is mutated (bit flips, interesting bytes, cut,
//! duplicated or deleted ranges, truncation) by a seeded generator and given to the release
//! binary; every case must end with success (exit 0) or a clean error (exit 1, an `error:`
//! line naming the input), never a panic (exit 101, or "panicked" printed), a signal (abort,
//! segfault) or a hang (60 s). A planted journal is first written from names picked at random
//! (the prefix's products, paths out of the directory, other files, empty and odd names), and
//! whatever it says, no file but the run's products may change.
//!
//! `cargo test --release --test fuzz` runs 12 cases per input kind (about a minute in all);
//! more by hand:
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

/// Runs r2d2 with a time limit; the outcome in words if it is not a clean one (an error must
/// contain `names`, the input's name).
fn run_bounded(args: &[&str], dir: &Path, names: &str) -> Option<String> {
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
        Some(s) if s.code() == Some(1) && err.contains("error:") && !err.contains("panicked") && err.contains(names) => None,
        Some(s) => Some(format!("{s}: {}", err.chars().rev().take(1500).collect::<String>().chars().rev().collect::<String>())),
    }
}

struct Kind {
    name: &'static str,
    /// The input's files (paths relative to the case directory) and their valid bytes.
    files: Vec<(String, Vec<u8>)>,
    /// How many of `files`, from the first, may be mutated (one picked per case).
    mutable: usize,
    args: Vec<String>,
    /// What an error must name (the input).
    names: &'static str,
    /// Makes the mutable file's content afresh for each case (before its mutations), from the
    /// generator and the case directory.
    craft: Option<fn(&mut ChaCha8Rng, &Path) -> Vec<u8>>,
    /// Whether files outside `out/` and those named `keep*` inside it must be left as they
    /// were, none added.
    guarded: bool,
}

/// A staging journal planted in `out/`: products and retired files from a pool of names, most
/// of them nothing a commit of prefix `out/x` writes.
fn planted_journal(rng: &mut ChaCha8Rng, case_dir: &Path) -> Vec<u8> {
    let absolute = case_dir.join("precious2.txt").display().to_string();
    let pool = [
        "x-dirty.fits", "x-psf.fits", "x-model.fits", "x-residual.fits", "../victim/precious.txt", "../precious2.txt", absolute.as_str(), "keep.txt", "y-dirty.fits", ".", "..", "",
        "x-dirty.fits/../keep.txt", "new/x-dirty.fits", "x-dirty.fits\0.txt", "./x-dirty.fits", "x-dirty.fits ",
    ];
    let mut names = || -> Vec<String> { (0..rng.gen_range(0..4)).map(|_| pool[rng.gen_range(0..pool.len())].to_string()).collect() };
    let (products, retired) = (names(), names());
    let version = [1, 1, 1, 0, 2, -1][rng.gen_range(0..6)];
    serde_json::json!({"version": version, "products": products, "retired": retired}).to_string().into_bytes()
}

/// Files of `dir`, relative to it, that a guarded kind must leave as they were.
fn guarded_files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    tree(dir, dir).into_iter().filter(|(name, _)| !name.starts_with("out/") || name.starts_with("out/keep")).collect()
}

/// `bytes` gzip-compressed.
fn gzipped(bytes: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut encoder = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    encoder.write_all(bytes).unwrap();
    encoder.finish().unwrap()
}

/// Every file under `dir`, as (path relative to `under`, bytes), in name order.
fn tree(dir: &Path, under: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files = Vec::new();
    let mut entries: Vec<_> = std::fs::read_dir(dir).unwrap().flatten().map(|e| e.path()).collect();
    entries.sort();
    for path in entries {
        if path.is_dir() {
            files.extend(tree(&path, under));
        } else {
            files.push((path.strip_prefix(under).unwrap().to_string_lossy().into_owned(), std::fs::read(&path).unwrap()));
        }
    }
    files
}

/// An Arrow IPC stream of the observation's table (schema metadata included), its buffers
/// compressed with `compression`.
fn ipc_stream(parquet: &Path, compression: Option<arrow::ipc::CompressionType>) -> Vec<u8> {
    use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
    let builder = ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(parquet).unwrap()).unwrap();
    let schema = builder.schema().clone();
    let mut out = Vec::new();
    let options = arrow::ipc::writer::IpcWriteOptions::default().try_with_compression(compression).unwrap();
    let mut writer = arrow::ipc::writer::StreamWriter::try_new_with_options(&mut out, &schema, options).unwrap();
    for batch in builder.with_batch_size(1000).build().unwrap() {
        writer.write(&batch.unwrap()).unwrap();
    }
    writer.finish().unwrap();
    drop(writer);
    out
}

#[test]
fn mutated_inputs_end_in_success_or_a_clean_error() {
    let cases = env_number("R2D2_FUZZ_CASES", 12);
    let seed = env_number("R2D2_FUZZ_SEED", 1);
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let obs = d.join("obs.parquet");
    let pipeline = |source: &str, step: &str| {
        format!(
            "name: fuzz\nimage:\n  size: {SIZE}\nstages:\n  source:\n{source}    to: weights\n  weights:\n    kind: weighting\n    scheme: briggs\n    robust: 0\n    to: grid\n  grid:\n    kind: gridder\n    to: step\n  step:\n{step}    to: update\n  update:\n    kind: residual\n    to: step\n    done: write\n  write:\n    kind: writer\n    prefix: \"out/{{job}}\"\n"
        )
    };
    let clean = "    kind: clean\n    major_cycles: 2\n";
    let from_obs = "    kind: parquet\n    files: ../obs.parquet\n";
    let series = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/vla-r2d2-128");
    let manifest_pipeline = pipeline(from_obs, "    kind: onnx\n    series: series\n").replace(&format!("size: {SIZE}"), "size: 128");
    // The MS of the observation (as CASA lays it out, and as DP3 does: IncrementalStMan and
    // TiledColumnStMan), and the tiny analytic ONNX series.
    for (out, options) in [("obs.ms", &[][..]), ("dp3.ms", &["--stman", "dp3"][..])] {
        let ms = std::process::Command::new("python3")
            .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/make_ms.py"))
            .args(["obs.parquet", out])
            .args(options)
            .current_dir(d)
            .output()
            .expect("python3 runs (a test requirement)");
        assert!(ms.status.success(), "tests/make_ms.py failed (pip install -r tests/requirements.txt): {}", stderr(&ms));
    }
    common::make_test_models(&d.join("models"), 0.5);
    let s = |v: &[&str]| v.iter().map(|a| a.to_string()).collect::<Vec<_>>();
    let file = |name: &str, bytes: Vec<u8>| vec![(name.to_string(), bytes)];
    let image = |input: &str| s(&["image", input, "--size", &SIZE.to_string(), "--step", "clean", "--name", "out/x"]);
    // The series' files with the manifest first, then the pipeline running it on `backend`.
    let onnx_series = |manifest_first: bool, backend: &str| {
        let mut files: Vec<(String, Vec<u8>)> = tree(&d.join("models/landweber"), &d.join("models"));
        files.sort_by_key(|(name, _)| name.ends_with("manifest.yaml") != manifest_first);
        let step = format!("    kind: onnx\n    series: landweber\n    backend: {backend}\n");
        files.push(("onnx.yaml".into(), pipeline(from_obs, &step).into_bytes()));
        files
    };
    let mut series_files = vec![("series/manifest.yaml".to_string(), std::fs::read(series.join("manifest.yaml")).unwrap())];
    series_files.extend(tree(&series, &series).into_iter().filter(|(n, _)| n.ends_with(".onnx")).map(|(n, b)| (format!("series/{n}"), b)));
    series_files.push(("manifest.yaml".into(), manifest_pipeline.into_bytes()));
    let ms_files: Vec<(String, Vec<u8>)> = tree(&d.join("obs.ms"), d).into_iter().map(|(n, b)| (n.replacen("obs.ms", "in.ms", 1), b)).collect();
    let dp3_files: Vec<(String, Vec<u8>)> = tree(&d.join("dp3.ms"), d).into_iter().map(|(n, b)| (n.replacen("dp3.ms", "in.ms", 1), b)).collect();
    // An Arrow IPC stream of the observation (its buffers compressed with `compression`) and a
    // pipeline reading it.
    let ipc_kind = |name: &'static str, compression| Kind {
        name,
        files: [file("in.arrows", ipc_stream(&obs, compression)), file("ipc.yaml", pipeline("    kind: arrow-ipc\n    path: in.arrows\n", clean).into_bytes())].concat(),
        mutable: 1,
        args: s(&["run", "ipc.yaml"]),
        names: "in.arrows",
        craft: None,
        guarded: false,
    };
    let networks = onnx_series(false, "auto").iter().filter(|(n, _)| n.ends_with(".onnx")).count();
    let kinds = [
        Kind { name: "parquet", files: file("in.parquet", std::fs::read(&obs).unwrap()), mutable: 1, args: image("in.parquet"), names: "in.parquet", craft: None, guarded: false },
        ipc_kind("arrow-ipc", None),
        Kind { name: "yaml", files: file("in.yaml", pipeline(from_obs, clean).into_bytes()), mutable: 1, args: s(&["run", "in.yaml"]), names: "", craft: None, guarded: false },
        Kind {
            name: "fits-truth",
            files: file("truth.fits", std::fs::read(d.join("obs.sky.fits")).unwrap()),
            mutable: 1,
            args: s(&["image", "../obs.parquet", "--size", &SIZE.to_string(), "--step", "clean", "--truth", "truth.fits", "--name", "out/x"]),
            names: "truth.fits",
            craft: None,
            guarded: false,
        },
        Kind { name: "manifest", files: series_files, mutable: 1, args: s(&["validate", "manifest.yaml"]), names: "", craft: None, guarded: false },
        Kind {
            name: "measurement-set",
            mutable: ms_files.len(),
            files: ms_files,
            args: s(&["dirty", "in.ms", "--size", &SIZE.to_string(), "--name", "out/x"]),
            names: "in.ms",
            craft: None,
            guarded: false,
        },
        Kind {
            name: "measurement-set-dp3",
            mutable: dp3_files.len(),
            files: dp3_files,
            args: s(&["dirty", "in.ms", "--size", &SIZE.to_string(), "--name", "out/x"]),
            names: "in.ms",
            craft: None,
            guarded: false,
        },
        ipc_kind("arrow-ipc-lz4", Some(arrow::ipc::CompressionType::LZ4_FRAME)),
        ipc_kind("arrow-ipc-zstd", Some(arrow::ipc::CompressionType::ZSTD)),
        Kind {
            name: "fits-gzip",
            files: file("truth.fits.gz", gzipped(&std::fs::read(d.join("obs.sky.fits")).unwrap())),
            mutable: 1,
            args: s(&["image", "../obs.parquet", "--size", &SIZE.to_string(), "--step", "clean", "--truth", "truth.fits.gz", "--name", "out/x"]),
            names: "truth.fits.gz",
            craft: None,
            guarded: false,
        },
        Kind {
            name: "staging-journal",
            files: [
                file("out/.r2d2-staging-planted/journal.json", b"{}".to_vec()),
                file("out/.r2d2-staging-planted/new/x-dirty.fits", b"planted bytes".to_vec()),
                file("out/.r2d2-staging-planted/new/keep.txt", b"planted bytes".to_vec()),
                file("out/.r2d2-staging-planted/earlier/0", b"planted bytes".to_vec()),
                file("out/.r2d2-staging-planted/earlier/1", b"planted bytes".to_vec()),
                file("out/keep.txt", b"the user's file beside the products".to_vec()),
                file("out/keep-y-dirty.fits", b"another prefix's product".to_vec()),
                file("victim/precious.txt", b"the user's file".to_vec()),
                file("precious2.txt", b"the user's other file".to_vec()),
            ]
            .concat(),
            mutable: 1,
            args: s(&["dirty", "../obs.parquet", "--size", &SIZE.to_string(), "--name", "out/x"]),
            names: "",
            craft: Some(planted_journal),
            guarded: true,
        },
        Kind { name: "onnx-manifest", files: onnx_series(true, "auto"), mutable: 1, args: s(&["run", "onnx.yaml"]), names: "landweber", craft: None, guarded: false },
        Kind { name: "onnx-network-ort", files: onnx_series(false, "auto"), mutable: networks, args: s(&["run", "onnx.yaml"]), names: "landweber", craft: None, guarded: false },
        Kind { name: "onnx-network-tract", files: onnx_series(false, "tract"), mutable: networks, args: s(&["run", "onnx.yaml"]), names: "landweber", craft: None, guarded: false },
    ];
    // The unmutated seeds succeed: the harness starts from valid inputs.
    let mut failures = Vec::new();
    let kept = Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-failures");
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let began = Instant::now();
    for kind in &kinds {
        for case in 0..=cases {
            let case_dir = d.join(format!("{}-{case}", kind.name));
            let mut files = kind.files.clone();
            let mutated = rng.gen_range(0..kind.mutable);
            if let Some(craft) = kind.craft.filter(|_| case > 0) {
                files[mutated].1 = craft(&mut rng, &case_dir);
            }
            // A crafted file is mutated one case in two (the rest test it as crafted).
            if case > 0 && (kind.craft.is_none() || rng.gen_bool(0.5)) {
                for _ in 0..rng.gen_range(1..=4) {
                    mutate(&mut files[mutated].1, &mut rng);
                }
            }
            for (name, bytes) in &files {
                let path = case_dir.join(name);
                std::fs::create_dir_all(path.parent().unwrap()).unwrap();
                std::fs::write(path, bytes).unwrap();
            }
            let args: Vec<&str> = kind.args.iter().map(String::as_str).collect();
            let before = kind.guarded.then(|| guarded_files(&case_dir));
            let mut outcome = run_bounded(&args, &case_dir, kind.names);
            if let Some(before) = before {
                let after = guarded_files(&case_dir);
                if after != before {
                    let names = |files: &[(String, Vec<u8>)]| files.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
                    let changed = format!("files outside the run's products changed: before {:?}, after {:?}", names(&before), names(&after));
                    outcome = Some(outcome.map_or(changed.clone(), |o| format!("{o}; {changed}")));
                }
            }
            if case == 0 {
                assert!(outcome.is_none(), "{}: the unmutated seed failed: {outcome:?}", kind.name);
                let out = Command::new(env!("CARGO_BIN_EXE_r2d2")).args(&args).current_dir(&case_dir).output().unwrap();
                check(&out);
                assert!(!stderr(&out).contains("panicked"));
            }
            if let Some(outcome) = outcome {
                // The whole input, the mutated file among the rest, to reproduce the case.
                let keep = kept.join(format!("seed{seed}-{}-{case}", kind.name));
                let _ = std::fs::remove_dir_all(&keep);
                for (name, bytes) in &files {
                    let path = keep.join(name);
                    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
                    std::fs::write(path, bytes).unwrap();
                }
                failures.push(format!("{} case {case}, {} mutated (kept in {}; r2d2 {}): {outcome}", kind.name, files[mutated].0, keep.display(), kind.args.join(" ")));
            }
            std::fs::remove_dir_all(&case_dir).unwrap();
        }
    }
    eprintln!("{} mutated cases of {} kinds in {:.1} s", cases as usize * kinds.len(), kinds.len(), began.elapsed().as_secs_f64());
    assert!(failures.is_empty(), "{} of {} mutated cases did not end cleanly:\n{}", failures.len(), cases as usize * kinds.len(), failures.join("\n\n"));
}

/// Cases the fuzzer found, kept as they were fixed.
#[test]
fn damaged_inputs_the_fuzzer_found_fail_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    common::make_test_models(&d.join("models"), 0.5);
    // Seed 3, onnx-network-tract case 248: the graph's output renamed to a value no node makes
    // ("y" to "{"); tract panicked while loading it, and the panic's text reached the terminal.
    let network = d.join("models/landweber/lw3.onnx");
    let mut bytes = std::fs::read(&network).unwrap();
    let output = b"b\x1d\n\x01y";
    let at = bytes.windows(output.len()).position(|w| w == output).expect("the graph output 'y' of tests/make_test_models.py");
    bytes[at + output.len() - 1] = b'{';
    std::fs::write(&network, bytes).unwrap();
    for backend in ["tract", "auto"] {
        let step = format!("    kind: onnx\n    series: models/landweber\n    backend: {backend}\n");
        let text = format!(
            "image:\n  size: {SIZE}\nstages:\n  source:\n    kind: parquet\n    files: obs.parquet\n    to: weights\n  weights:\n    kind: weighting\n    scheme: natural\n    to: grid\n  grid:\n    kind: gridder\n    to: step\n  step:\n{step}    to: update\n  update:\n    kind: residual\n    to: step\n    done: write\n    divergence_guard: false\n    early_stop: false\n  write:\n    kind: writer\n    prefix: \"out-{backend}/{{job}}\"\n"
        );
        // The whole series runs (this Landweber diverges, and the guard would stop it before
        // network 3, the damaged one).
        std::fs::write(d.join("p.yaml"), text).unwrap();
        let out = common::r2d2(&["run", "p.yaml"], d);
        let err = common::assert_fails_with(&out, backend, &["lw3.onnx", "stage 'step' (onnx)"]);
        assert!(!err.contains("panicked"), "{backend}: {err}");
        assert!(!d.join(format!("out-{backend}")).exists(), "{backend}: products written");
    }
}
