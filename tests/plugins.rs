//! Native network-step plugins (`kind: native`) end to end: the same `r2d2` binary images the
//! same observation with the built-in CLEAN step, the Rust example plugin, the C example
//! plugin and an ONNX series, changing only the step stage in the YAML; the plugin's result is checked against
//! projected Landweber iterations computed here; and every plugin failure (missing file or
//! symbol, ABI mismatch, create error, step error, panic, NaN) ends the run with a clear
//! error naming the library, never a crash.
//!
//! The plugin crates are cdylibs of the workspace, which `cargo test` does not produce, so the
//! tests build them once with the same cargo into a target directory of their own (no lock
//! shared with the running `cargo test`), and compile the C plugins with the C compiler the
//! build already needs (`$CC` or `cc`).

mod common;

use common::{check, landweber_reference, make_test_models, max_abs, max_diff, observation, output_within, r2d2, read, stderr, ReferenceOperator, SIZE};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn library_file(crate_lib_name: &str) -> String {
    format!("{}{crate_lib_name}{}", std::env::consts::DLL_PREFIX, std::env::consts::DLL_SUFFIX)
}

/// The release libraries of the Rust plugin crates, built once per test run.
fn rust_plugins() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let target = Path::new(env!("CARGO_TARGET_TMPDIR")).join("plugins");
        let out = Command::new(env!("CARGO"))
            .args(["build", "--release", "-p", "r2d2-landweber", "-p", "r2d2-faulty-plugin", "--manifest-path"])
            .arg(root().join("Cargo.toml"))
            .arg("--target-dir")
            .arg(&target)
            .output()
            .expect("cargo runs");
        assert!(out.status.success(), "building the plugin crates failed:\n{}", stderr(&out));
        let dir = target.join("release");
        for lib in ["r2d2_landweber", "r2d2_faulty_plugin"] {
            assert!(dir.join(library_file(lib)).is_file(), "{} was not built", library_file(lib));
        }
        dir
    })
}

fn landweber() -> PathBuf {
    rust_plugins().join(library_file("r2d2_landweber"))
}

fn faulty() -> PathBuf {
    rust_plugins().join(library_file("r2d2_faulty_plugin"))
}

/// Compile C source (a file, or text written to `dir`) against the header into a shared library.
fn c_plugin(dir: &Path, name: &str, source: &Path) -> PathBuf {
    let output = dir.join(library_file(name));
    let compiler = std::env::var("CC").unwrap_or_else(|_| "cc".into());
    let out = Command::new(&compiler)
        .args(["-std=c11", "-Wall", "-Wextra", "-Werror", "-O2", "-shared", "-fPIC", "-I"])
        .arg(root().join("plugins/r2d2-plugin/include"))
        .arg(source)
        .arg("-o")
        .arg(&output)
        .output()
        .unwrap_or_else(|e| panic!("the C compiler '{compiler}' (from $CC or cc) is needed by this test: {e}"));
    assert!(out.status.success(), "compiling {} failed:\n{}", source.display(), stderr(&out));
    output
}

fn c_plugin_from_text(dir: &Path, name: &str, text: &str) -> PathBuf {
    let source = dir.join(format!("{name}.c"));
    std::fs::write(&source, text).unwrap();
    c_plugin(dir, name, &source)
}

/// A 64^2 pipeline on `obs.parquet` with the given step stage (the only part that varies).
fn pipeline(step: &str) -> String {
    format!(
        "name: plugins\nimage:\n  size: {SIZE}\nstages:\n  source:\n    kind: parquet\n    files: obs.parquet\n    to: weights\n  weights:\n    kind: weighting\n    scheme: briggs\n    robust: 0\n    to: grid\n  grid:\n    kind: gridder\n    to: step\n  step:\n{step}    to: update\n  update:\n    kind: residual\n    method: toeplitz\n    to: step\n    done: write\n  write:\n    kind: writer\n    prefix: \"out/{{job}}\"\n"
    )
}

fn native_step(library: &Path, iterations: usize, config: &str) -> String {
    format!("    kind: native\n    library: \"{}\"\n    iterations: {iterations}\n    config: {config}\n", library.display())
}

#[test]
fn clean_rust_plugin_and_c_plugin_run_from_yaml_alone_and_the_plugin_runs_projected_landweber() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let reference = ReferenceOperator::new(&d.join("obs.parquet"));
    let gain = reference.landweber_gain();
    let iterations = 4;
    let c_library = c_plugin(d, "c_landweber", &root().join("plugins/examples/c/landweber.c"));
    let steps = [
        ("clean", "    kind: clean\n    major_cycles: 3\n".to_string()),
        ("rust", native_step(&landweber(), iterations, &format!("{{gain: {gain:e}}}"))),
        ("c", native_step(&c_library, iterations, &format!("{{gain: {gain:e}}}"))),
        ("onnx", "    kind: onnx\n    series: models/landweber\n".to_string()),
    ];
    make_test_models(&d.join("models"), gain);
    for (name, step) in &steps {
        std::fs::write(d.join(format!("{name}.yaml")), pipeline(step)).unwrap();
        check(&r2d2(&["run", &format!("{name}.yaml"), "--set", &format!("write.prefix=out-{name}/{{job}}")], d));
    }
    let product = |name: &str, what: &str| read(&d.join(format!("out-{name}/obs-{what}.fits")));

    // CLEAN ran in the same pipeline.
    let dirty = product("clean", "dirty");
    assert!(max_abs(&product("clean", "residual")) < 0.5 * max_abs(&dirty), "CLEAN did not reduce the residual");

    // The Rust plugin's model is projected Landweber, computed here from the written dirty
    // image and an independent D (FITS values are float32: relative error ~1e-7).
    let model = product("rust", "model");
    let (expected, expected_residual) = landweber_reference(&reference, &dirty, gain, 0.0, iterations, true);
    let scale = max_abs(&expected);
    assert!(scale > 0.0);
    let error = max_diff(&model, &expected) / scale;
    assert!(error < 1e-5, "native model differs from projected Landweber by {error:e} of its peak");
    let residual_error = max_diff(&product("rust", "residual"), &expected_residual) / max_abs(&expected_residual);
    assert!(residual_error < 1e-5, "native residual differs from x_d - D x by {residual_error:e} of its peak");
    // The check can tell: without the projection (or with one step fewer) the result is far off.
    let (unprojected, _) = landweber_reference(&reference, &dirty, gain, 0.0, iterations, false);
    assert!(max_diff(&model, &unprojected) / scale > 1e-2, "positivity made no difference: the test would not notice it missing");
    let (fewer, _) = landweber_reference(&reference, &dirty, gain, 0.0, iterations - 1, true);
    assert!(max_diff(&model, &fewer) / scale > 1e-2);
    assert!(model.iter().all(|&v| v >= 0.0));
    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("out-rust/obs-metrics.json")).unwrap()).unwrap();
    let ratios: Vec<f64> = metrics["iterations"].as_array().unwrap().iter().map(|m| m["residual_ratio"].as_f64().unwrap()).collect();
    assert_eq!(ratios.len(), iterations);
    assert!(ratios.windows(2).all(|w| w[1] < w[0]), "Landweber with gain 1/||D|| must reduce the residual: {ratios:?}");
    // A native step's model is restored too (model at the beam plus residual).
    assert!(d.join("out-rust/obs-image.fits").exists());

    // The C plugin, built against the header alone, computes the same numbers.
    assert_eq!(product("c", "model"), model, "C and Rust plugins disagree");

    // The ONNX series (4 networks of tests/make_test_models.py, each `gain x residual + 0.01`)
    // ran in the same binary from YAML alone, and computed the same loop with the bias term.
    let onnx = product("onnx", "model");
    let (expected, _) = landweber_reference(&reference, &dirty, gain, 0.01, iterations, true);
    let error = max_diff(&onnx, &expected) / max_abs(&expected);
    assert!(error < 1e-5, "ONNX model differs from projected Landweber with bias by {error:e} of its peak");
    // (10x the 1e-5 tolerance above; measured 8.4e-4.)
    let bias_effect = max_diff(&onnx, &model) / scale;
    assert!(bias_effect > 1e-4, "the bias term changed the model by only {bias_effect:e} of its peak: the check would not notice it missing");
}

/// A pipeline that must fail before imaging: exit code 1 (an error returned, not a panic of
/// the host, which would exit with 101, nor a signal), every expected fragment in the message,
/// and no product written.
fn fails_before_imaging(d: &Path, name: &str, step: &str, expect: &[&str]) {
    std::fs::write(d.join(format!("{name}.yaml")), pipeline(step)).unwrap();
    for command in ["validate", "run"] {
        let out = r2d2(&[command, &format!("{name}.yaml")], d);
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(1), "{name} ({command}): expected a clean failure (exit 1), got {:?}: {err}", out.status);
        for e in expect {
            assert!(err.contains(e), "{name} ({command}): '{e}' missing from: {err}");
        }
    }
    assert!(!d.join("out").exists(), "{name}: products written although the pipeline was invalid");
}

/// The four functions after the version, doing nothing (for libraries that differ in the version).
const STUBS: &str = "void *r2d2_plugin_create(const char *c, uint64_t n, uint32_t i) { (void)c; (void)n; (void)i; return 0; }\n\
int32_t r2d2_plugin_step(void *h, const r2d2_step_input *in, double *out) { (void)h; (void)in; (void)out; return 1; }\n\
const char *r2d2_plugin_last_error(const void *h) { (void)h; return \"stub\"; }\n\
void r2d2_plugin_destroy(void *h) { (void)h; }\n";

/// A library whose constructor leaves a mark: checking it must not run it.
#[test]
fn validate_reads_the_library_without_loading_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let marker = d.join("constructor-ran");
    let text = format!(
        "#include \"r2d2_plugin.h\"\n#include <stdio.h>\n__attribute__((constructor)) static void mark(void) {{ FILE *f = fopen(\"{}\", \"w\"); if (f) fclose(f); }}\n{STUBS}",
        marker.display()
    );
    // Without the version function the file check refuses it before anything loads it.
    let library = c_plugin_from_text(d, "marking", &text);
    for isolation in ["process", "none"] {
        let step = native_step(&library, 2, "{}") + &format!("    isolation: {isolation}\n");
        fails_before_imaging(d, &format!("marking-{isolation}"), &step, &["missing symbol r2d2_plugin_abi_version (read from the file, not loaded)"]);
        assert!(!marker.exists(), "checking the library ran its constructor ({isolation})");
    }
    // A complete plugin is created in the isolated host: its constructor runs there, not in
    // r2d2, also under `isolation: none` (which only `run` honours). The constructor writes the
    // name of the process it runs in.
    let naming = text.replace("if (f) fclose(f);", "if (f) { FILE *c = fopen(\"/proc/self/comm\", \"r\"); int ch; while (c && (ch = fgetc(c)) != EOF) fputc(ch, f); if (c) fclose(c); fclose(f); }");
    let complete = c_plugin_from_text(d, "marking_complete", &format!("{naming}uint32_t r2d2_plugin_abi_version(void) {{ return R2D2_PLUGIN_ABI_VERSION; }}\n"));
    for isolation in ["process", "none"] {
        let _ = std::fs::remove_file(&marker);
        std::fs::write(d.join("complete.yaml"), pipeline(&(native_step(&complete, 2, "{}") + &format!("    isolation: {isolation}\n")))).unwrap();
        let out = r2d2(&["validate", "complete.yaml"], d);
        assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
        assert!(stderr(&out).contains("the plugin refused its configuration {}: stub"), "{}", stderr(&out));
        let process = std::fs::read_to_string(&marker).unwrap_or_default();
        assert!(process.starts_with("r2d2-plugin-ho"), "isolation: {isolation}: validate ran the plugin's constructor in '{}', not in its host", process.trim());
    }
}

#[test]
fn plugin_load_and_create_errors_come_before_imaging_and_name_the_library() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let missing = d.join("nowhere/libnothing.so");
    fails_before_imaging(d, "missing", &native_step(&missing, 2, "{}"), &[&missing.display().to_string(), "no such plugin library", "stages.step.library"]);

    let not_a_library = d.join("notes.so");
    std::fs::write(&not_a_library, "not a shared library").unwrap();
    fails_before_imaging(d, "garbage", &native_step(&not_a_library, 2, "{}"), &["notes.so", "not a shared library: the file does not start with an ELF header"]);

    let unrelated = c_plugin_from_text(d, "unrelated", "int some_function(void) { return 1; }\n");
    fails_before_imaging(d, "unrelated", &native_step(&unrelated, 2, "{}"), &[&unrelated.display().to_string(), "missing symbol r2d2_plugin_abi_version"]);

    let future = c_plugin_from_text(
        d,
        "future",
        &format!("#include \"r2d2_plugin.h\"\nuint32_t r2d2_plugin_abi_version(void) {{ return R2D2_PLUGIN_ABI_VERSION + 1; }}\n{STUBS}"),
    );
    fails_before_imaging(d, "future", &native_step(&future, 2, "{}"), &[&future.display().to_string(), "plugin ABI version 2, but this r2d2 speaks version 1"]);

    let incomplete = c_plugin_from_text(
        d,
        "incomplete",
        "#include \"r2d2_plugin.h\"\nuint32_t r2d2_plugin_abi_version(void) { return R2D2_PLUGIN_ABI_VERSION; }\n",
    );
    fails_before_imaging(d, "incomplete", &native_step(&incomplete, 2, "{}"), &["incomplete", "missing symbol r2d2_plugin_create"]);

    let faulty = faulty();
    let faulty_name = faulty.display().to_string();
    fails_before_imaging(d, "create_error", &native_step(&faulty, 2, "{fail: create_error}"), &[&faulty_name, "refused its configuration", "refusing to run at image size 64 as asked"]);
    fails_before_imaging(d, "create_panic", &native_step(&faulty, 2, "{fail: create_panic}"), &[&faulty_name, "plugin panicked: create panicked as asked"]);
    // The plugin's own configuration checks reach the user.
    fails_before_imaging(d, "plugin_key", &native_step(&faulty, 2, "{fail: none, oops: 1}"), &[&faulty_name, "unknown field `oops`"]);
    fails_before_imaging(d, "bad_gain", &native_step(&landweber(), 2, "{gain: -1}"), &["r2d2_landweber", "config.gain: expected a positive finite step size, got -1"]);

    // The host's own keys.
    let step = native_step(&faulty, 2, "{fail: none}");
    fails_before_imaging(d, "host_key", &step.replace("    iterations: 2\n", "    iterations: 2\n    positivty: false\n"), &["line 21", "positivty", "positivity"]);
    fails_before_imaging(d, "no_iterations", &step.replace("    iterations: 2\n", ""), &["missing field `iterations`"]);
    fails_before_imaging(d, "zero_iterations", &step.replace("iterations: 2", "iterations: 0"), &["stages.step.iterations", "at least one"]);
    fails_before_imaging(d, "config_list", &step.replace("{fail: none}", "[1, 2]"), &["stages.step.config", "expected a mapping"]);
}

#[test]
fn plugin_step_failures_stop_the_run_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let faulty = faulty();
    let cases = [
        ("step_error", "{fail: step_error, at: 2}", vec!["plugin step 2 failed (status 1): step 2 failed as asked"]),
        ("step_panic", "{fail: step_panic}", vec!["plugin step 1 failed (status 1): plugin panicked: step 1 panicked as asked"]),
        ("nan", "{fail: nan, at: 2}", vec!["plugin step 2 returned a non-finite increment NaN at pixel (x 1, y 0)"]),
        ("unwritten", "{fail: unwritten}", vec!["plugin step 1 returned a non-finite increment NaN at pixel (x 0, y 0)"]),
        // Finite but absurd: named where it appears, not at the writer.
        ("huge", "{fail: huge, at: 2}", vec!["invalid model after step 2: 1 pixel(s) are not finite or exceed 1e30 in magnitude, the first 1e300 at pixel (x 1, y 0)", "diverging network or plugin"]),
    ];
    // The same messages whether the plugin runs in its host process (default) or in r2d2.
    for isolation in ["process", "none"] {
        for (name, config, expect) in &cases {
            let step = native_step(&faulty, 3, config) + &format!("    isolation: {isolation}\n");
            let out = run_step(d, &format!("{name}-{isolation}"), &step);
            let err = stderr(&out);
            assert_eq!(out.status.code(), Some(1), "{name}: expected a clean failure (exit 1), got {:?}: {err}", out.status);
            assert!(err.contains("stage 'step' (native), job 'obs'"), "{name}: {err}");
            // (A huge model is caught by the step stage, after the plugin returned.)
            assert!(*name == "huge" || err.contains(&faulty.display().to_string()), "{name}: library not named: {err}");
            for e in expect {
                assert!(err.contains(e), "{name} ({isolation}): '{e}' missing from: {err}");
            }
            assert!(!d.join(format!("out-{name}-{isolation}")).exists(), "{name}: a failed job left products");
        }
    }
    // The same plugin, not asked to fail, completes the series (a zero increment).
    std::fs::write(d.join("ok.yaml"), pipeline(&native_step(&faulty, 2, "{fail: none}"))).unwrap();
    check(&r2d2(&["run", "ok.yaml"], d));
    assert!(read(&d.join("out/obs-model.fits")).iter().all(|&v| v == 0.0));
}

/// Runs the pipeline with `step` as `NAME.yaml`, writing to `out-NAME/`.
fn run_step(d: &Path, name: &str, step: &str) -> std::process::Output {
    std::fs::write(d.join(format!("{name}.yaml")), pipeline(step)).unwrap();
    r2d2(&["run", &format!("{name}.yaml"), "--set", &format!("write.prefix=out-{name}/{{job}}")], d)
}

/// [`run_step`], failing the test if the run takes more than two minutes.
fn run_step_within(d: &Path, name: &str, step: &str) -> std::process::Output {
    std::fs::write(d.join(format!("{name}.yaml")), pipeline(step)).unwrap();
    let prefix = format!("write.prefix=out-{name}/{{job}}");
    output_within(Command::new(env!("CARGO_BIN_EXE_r2d2")).args(["run", &format!("{name}.yaml"), "--set", &prefix]).current_dir(d), std::time::Duration::from_secs(120))
}

#[test]
fn isolated_plugins_that_crash_exit_or_hang_fail_the_run_naming_library_stage_and_job() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let faulty = faulty();
    let cases = [
        ("segfault", "killed by signal 11 (SIGSEGV, a segmentation fault)"),
        ("abort", "killed by signal 6 (SIGABRT, abort)"),
        ("exit", "the plugin ended its host process with exit status 0 (a plugin must return from every call, never exit)"),
        ("hang", "the plugin did not answer within"),
    ];
    for (fault, expect) in cases {
        // Fails at the second step: the first job's first step went through the host.
        let step = native_step(&faulty, 3, &format!("{{fail: {fault}, at: 2}}")) + "    timeout: 2\n";
        let began = std::time::Instant::now();
        let out = run_step(d, fault, &step);
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(1), "{fault}: expected a clean failure (exit 1), got {:?}: {err}", out.status);
        for e in [expect, "the plugin failed while running step 2", "stage 'step' (native), job 'obs'", &faulty.display().to_string()] {
            assert!(err.contains(e), "{fault}: '{e}' missing from: {err}");
        }
        assert!(!d.join(format!("out-{fault}")).exists(), "{fault}: a failed job left products");
        assert!(began.elapsed().as_secs() < 60, "{fault}: took {:?}", began.elapsed());
    }
    // The faults are real: loaded into r2d2 itself, the segfault kills the engine.
    let step = native_step(&faulty, 3, "{fail: segfault}") + "    isolation: none\n";
    let out = run_step(d, "segfault-in-process", &step);
    assert_eq!(out.status.code(), None, "an in-process segfault should kill r2d2: {}", stderr(&out));

    // A host that cannot be found is a clear error, before imaging.
    let step = native_step(&faulty, 2, "{fail: none}");
    std::fs::write(d.join("nohost.yaml"), pipeline(&step)).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_r2d2"))
        .args(["run", "nohost.yaml"])
        .current_dir(d)
        .env("R2D2_PLUGIN_HOST", d.join("no-such-host"))
        .output()
        .unwrap();
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("R2D2_PLUGIN_HOST=") && err.contains("is not a file"), "{err}");
}

/// A C plugin whose steps return a zero increment, with the test's code put into it (`EXTRA`
/// before the functions, `CREATE`, `STEP`, `DESTROY` at the end of each): a plugin that
/// misbehaves where a real one might. `p->buffer` holds N x N doubles; a step fails with
/// `p->message` when it sets it and returns non-zero.
const MISBEHAVING: &str = r#"#define _DEFAULT_SOURCE
#include "r2d2_plugin.h"
#include <pthread.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
typedef struct { uint64_t n; double *buffer; char *message; } plugin;
EXTRA
uint32_t r2d2_plugin_abi_version(void) { return R2D2_PLUGIN_ABI_VERSION; }
void *r2d2_plugin_create(const char *c, uint64_t n, uint32_t i) {
    (void)c; (void)i;
    plugin *p = calloc(1, sizeof *p); p->n = n; p->buffer = malloc(n * n * sizeof(double));
    CREATE
    return p;
}
int32_t r2d2_plugin_step(void *h, const r2d2_step_input *in, double *out) {
    plugin *p = h; (void)in;
    for (uint64_t k = 0; k < p->n * p->n; k++) out[k] = 0.0;
    STEP
    return 0;
}
const char *r2d2_plugin_last_error(const void *h) { const plugin *p = h; return p && p->message ? p->message : "failed"; }
void r2d2_plugin_destroy(void *h) { plugin *p = h; DESTROY free(p->buffer); free(p->message); free(p); }
"#;

fn misbehaving_plugin(d: &Path, name: &str, [extra, create, step, destroy]: [&str; 4]) -> PathBuf {
    let text = MISBEHAVING.replace("EXTRA", extra).replace("CREATE", create).replace("STEP", step).replace("DESTROY", destroy);
    c_plugin_from_text(d, name, &text)
}

/// A write through a null pointer the compiler can neither see nor drop (both volatile).
const SEGFAULT: &str = "volatile int *volatile nowhere = 0; *nowhere = 1;";

/// The files a run left under `dir` (none when it does not exist).
fn files_in(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir).map(|entries| entries.map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect()).unwrap_or_default()
}

/// A plugin that crashes as it is torn down (its destroy, the library's destructor, a heap it
/// overflowed in a step and glibc finds corrupt at the free) fails the run before anything is
/// written; so does one whose destroy hangs. Loaded into r2d2, the crash ends r2d2 before the
/// products are written.
#[test]
fn a_crash_or_hang_in_a_plugins_teardown_fails_the_run_before_anything_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let torn_down = "the plugin failed while being torn down (its destroy, the library's unloading): ";
    let cases = [
        ("destroy_segfault", ["", "", "", SEGFAULT], vec![torn_down, "killed by signal 11 (SIGSEGV, a segmentation fault)"]),
        (
            "destructor_segfault",
            [&format!("__attribute__((destructor)) static void unloaded(void) {{ {SEGFAULT} }}"), "", "", ""],
            vec!["killed by signal 11 (SIGSEGV, a segmentation fault)"],
        ),
        // 256 bytes past the buffer: the next chunk's header, which free() checks.
        ("heap_overflow", ["", "", "memset(p->buffer, 0x5a, p->n * p->n * sizeof(double) + 256);", ""], vec![torn_down, "killed by signal 6 (SIGABRT, abort)"]),
        ("destroy_hang", ["", "", "", "for (;;) sleep(1);"], vec![torn_down, "the plugin did not answer within 2.0 s (timeout: 2 s); its host process was stopped"]),
    ];
    for (name, code, expect) in &cases {
        let library = misbehaving_plugin(d, name, *code);
        let out = run_step_within(d, name, &(native_step(&library, 3, "{}") + "    timeout: 2\n"));
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(1), "{name}: expected a clean failure (exit 1), got {:?}: {err}", out.status);
        for e in expect.iter().chain(&["stage 'step' (native), job 'obs'", &library.display().to_string()]) {
            assert!(err.contains(e), "{name}: '{e}' missing from: {err}");
        }
        assert_eq!(files_in(&d.join(format!("out-{name}"))), Vec::<String>::new(), "{name}: the run wrote products: {err}");
    }
    // In r2d2 itself the crash ends r2d2, before the products are written.
    let library = misbehaving_plugin(d, "destroy_segfault_in_process", ["", "", "", SEGFAULT]);
    let out = run_step(d, "destroy_segfault_in_process", &(native_step(&library, 3, "{}") + "    isolation: none\n"));
    assert_eq!(out.status.code(), None, "a segfault in an in-process plugin's destroy should end r2d2: {}", stderr(&out));
    // (The staging directory the killed run left is rolled back by the next run there.)
    let written: Vec<String> = files_in(&d.join("out-destroy_segfault_in_process")).into_iter().filter(|f| !f.starts_with(".r2d2-staging-")).collect();
    assert!(written.is_empty(), "products written before the plugin was torn down: {written:?}");
    // The same plugin with a destroy that works: the products are written.
    let library = misbehaving_plugin(d, "tidy", ["", "", "", ""]);
    for isolation in ["process", "none"] {
        let name = format!("tidy-{isolation}");
        check(&run_step(d, &name, &(native_step(&library, 3, "{}") + &format!("    isolation: {isolation}\n"))));
        assert!(d.join(format!("out-{name}/obs-model.fits")).is_file(), "{name}: no model");
    }
}

/// The protocol has pipes of its own: a plugin thread reading standard input, a plugin closing
/// descriptors 0 and 1 or printing, change nothing; an error message longer than a frame is
/// cut with a note, not taken for the plugin ending its process.
#[test]
fn plugins_that_use_standard_streams_or_give_huge_messages_cannot_break_the_protocol() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    // The reader is started, and given time to block on standard input, before create
    // returns: the first bytes the engine sends reach it first.
    let drain = "static void *drain(void *arg) { char b[4096]; (void)arg; while (read(0, b, sizeof b) > 0) {} return 0; }";
    let working = [
        ("stdin_reader", [drain, "pthread_t t; pthread_create(&t, 0, drain, 0); pthread_detach(t); usleep(200000);", "", ""]),
        ("closes_stdio", ["", "close(0); close(1);", "", ""]),
        ("prints", ["#include <stdio.h>", "", "printf(\"S\\x01 stray output\\n\"); fflush(stdout);", ""]),
    ];
    for (name, code) in working {
        let library = misbehaving_plugin(d, name, code);
        let out = run_step_within(d, name, &(native_step(&library, 3, "{}") + "    timeout: 10\n"));
        check(&out);
        assert!(d.join(format!("out-{name}/obs-model.fits")).is_file(), "{name}: no model: {}", stderr(&out));
    }
    // 20 MB of message: more than a frame may hold (16 MiB).
    let library = misbehaving_plugin(d, "long_message", ["", "", "p->message = malloc(20000001); memset(p->message, 'x', 20000000); p->message[20000000] = 0; return 1;", ""]);
    let out = run_step(d, "long_message", &native_step(&library, 3, "{}"));
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{}", &err[err.len().saturating_sub(2000)..]);
    let shown = 1 << 16;
    let failed = "plugin step 1 failed (status 1): ";
    let expect = format!("{failed}{}", "x".repeat(100));
    let note = format!("[... cut: the message has {} bytes, the first {shown} are shown]", failed.len() + 20_000_000);
    assert!(err.contains(&expect) && err.contains(&note), "{}", &err[err.len().saturating_sub(2000)..]);
    assert!(err.len() < shown + 10_000, "{} bytes on standard error", err.len());
    assert!(!err.contains("exit status"), "the plugin is blamed for an exit: {}", &err[err.len().saturating_sub(2000)..]);
    assert!(files_in(&d.join("out-long_message")).is_empty());
}

/// A FIFO or a directory given as the library is said to be one (not "no such plugin
/// library"), at once: the FIFO is never opened, which would block.
#[cfg(unix)]
#[test]
fn a_fifo_or_a_directory_as_the_library_is_not_a_regular_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    assert!(Command::new("mkfifo").arg(d.join("fifo.so")).status().unwrap().success());
    std::fs::create_dir(d.join("dir.so")).unwrap();
    for (name, kind) in [("fifo.so", "a FIFO (named pipe)"), ("dir.so", "a directory")] {
        std::fs::write(d.join("p.yaml"), pipeline(&native_step(&d.join(name), 2, "{fail: none}"))).unwrap();
        for command in ["validate", "run"] {
            let out = output_within(Command::new(env!("CARGO_BIN_EXE_r2d2")).args([command, "p.yaml"]).current_dir(d), std::time::Duration::from_secs(60));
            let err = stderr(&out);
            assert_eq!(out.status.code(), Some(1), "{name} {command}: {err}");
            for e in [name, "stages.step.library", kind, "not a regular file"] {
                assert!(err.contains(e), "{name} {command}: '{e}' missing from: {err}");
            }
            assert!(!err.contains("no such plugin library"), "{name} {command}: {err}");
        }
    }
}

/// An R2D2_PLUGIN_HOST that is not a plugin host (it exits, cannot be executed, or starts other
/// processes and never answers) is blamed, not the plugin; the wait for it is bounded and
/// nothing it started is left running.
#[cfg(unix)]
#[test]
fn a_bad_plugin_host_is_blamed_and_leaves_no_process_behind() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    std::fs::write(d.join("p.yaml"), pipeline(&native_step(&faulty(), 2, "{fail: none}"))).unwrap();
    std::fs::write(d.join("text.txt"), "not a program\n").unwrap();
    // A marker of this test's own in the command lines of the processes the scripts start.
    let script = |name: &str, body: &str| {
        let path = d.join(name);
        std::fs::write(&path, format!("#!/bin/sh\n{body}\n")).unwrap();
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).unwrap();
        path
    };
    let marker = "987.2514";
    let hosts = [
        (PathBuf::from("/bin/false"), "before its handshake"),
        (d.join("text.txt"), "could not be executed"),
        (script("exits.sh", &format!("sleep {marker} &\nexit 0")), "before its handshake"),
        (script("hangs.sh", &format!("sleep {marker} &\nsleep {marker}")), "sent no handshake within"),
    ];
    for (host, how) in hosts {
        let out = output_within(
            Command::new(env!("CARGO_BIN_EXE_r2d2")).args(["run", "p.yaml"]).current_dir(d).env("R2D2_PLUGIN_HOST", &host),
            std::time::Duration::from_secs(60),
        );
        let err = stderr(&out);
        let name = host.display().to_string();
        assert_eq!(out.status.code(), Some(1), "{name}: {err}");
        for e in [&format!("R2D2_PLUGIN_HOST={name}"), "cannot start the plugin host", how] {
            assert!(err.contains(e), "{name}: '{e}' missing from: {err}");
        }
        assert!(!err.contains("the plugin failed") && !err.contains("stages.step.library"), "{name}: the plugin is blamed: {err}");
        assert!(!d.join("out").exists(), "{name}: products written");
        // Killed processes may take a moment to go.
        let began = std::time::Instant::now();
        while !processes_mentioning(marker).is_empty() && began.elapsed().as_secs() < 2 {
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let left = processes_mentioning(marker);
        assert!(left.is_empty(), "{name}: processes left running: {left:?}");
    }
}

/// Processes whose command line mentions `needle` (the plugin hosts of one library).
fn processes_mentioning(needle: &str) -> Vec<String> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir("/proc").unwrap().flatten() {
        if let Ok(cmdline) = std::fs::read(entry.path().join("cmdline")) {
            if String::from_utf8_lossy(&cmdline).contains(needle) {
                found.push(entry.file_name().to_string_lossy().into_owned());
            }
        }
    }
    found
}

#[test]
fn ctrl_c_stops_a_hung_isolated_plugin() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    // A copy under a name of this test's own, to find its host process.
    let library = d.join(library_file("hung_plugin_for_ctrl_c"));
    std::fs::copy(faulty(), &library).unwrap();
    std::fs::write(d.join("hang.yaml"), pipeline(&native_step(&library, 3, "{fail: hang}"))).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_r2d2"))
        .args(["run", "hang.yaml"])
        .current_dir(d)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let needle = library.display().to_string();
    let began = std::time::Instant::now();
    while processes_mentioning(&needle).is_empty() {
        assert!(began.elapsed().as_secs() < 60, "the plugin host never started");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    // Long enough for the job to reach the step, where the plugin hangs (64 x 64: well under a second).
    std::thread::sleep(std::time::Duration::from_millis(2000));
    // SIGINT to r2d2 alone (not its process group): the engine must stop the host itself.
    let status = Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(status.success());
    let stopped = std::time::Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if stopped.elapsed().as_secs() > 20 {
            let _ = child.kill();
            panic!("r2d2 did not stop within 20 s of Ctrl-C with a hung plugin");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    let mut err = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
    assert_eq!(status.code(), Some(1), "{err}");
    assert!(err.contains("interrupted"), "{err}");
    assert!(!d.join("out").exists(), "products written by an interrupted run");
    std::thread::sleep(std::time::Duration::from_millis(200));
    assert!(processes_mentioning(&needle).is_empty(), "the plugin host outlived r2d2");
}

/// In an embedding program each run has its own stop: cancelling one whose plugin hangs kills
/// that run's host at once (not after the plugin's timeout), and the next run in the same
/// process is not taken for interrupted.
#[test]
fn an_embedding_program_cancels_a_run_with_a_hung_plugin_and_runs_again() {
    use r2d2_imaging::{Engine, EngineOptions};
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let library = d.join(library_file("hung_plugin_for_embedding"));
    std::fs::copy(faulty(), &library).unwrap();
    let engine = Engine::new(EngineOptions { threads: 2, onnx_runtime: None }).unwrap();
    let spec = |fault: &str| {
        let step = native_step(&library, 3, &format!("{{fail: {fault}, at: 2}}")) + "    timeout: 30\n";
        let text = pipeline(&step).replace("files: obs.parquet", &format!("files: \"{}\"", d.join("obs.parquet").display()));
        engine.load_yaml(&text, "embedded.yaml", &[format!("write.prefix={}/{{job}}", d.join(format!("out-{fault}")).display())]).unwrap()
    };
    let cancel = Arc::new(AtomicBool::new(false));
    let flag = cancel.clone();
    // Long enough for the job to reach the step, where the plugin hangs.
    let canceller = std::thread::spawn(move || {
        std::thread::sleep(std::time::Duration::from_secs(2));
        flag.store(true, Ordering::SeqCst);
    });
    let began = std::time::Instant::now();
    let err = engine.run(&spec("hang"), Vec::new(), None, cancel).unwrap_err().to_string();
    canceller.join().unwrap();
    assert!(began.elapsed().as_secs() < 15, "the cancelled run took {:?}: the hung plugin was left to its 30 s timeout", began.elapsed());
    assert!(err.contains("interrupted: its host process was stopped"), "{err}");
    assert!(!d.join("out-hang").exists(), "products written by a cancelled run");
    std::thread::sleep(std::time::Duration::from_millis(200));
    assert!(processes_mentioning(&library.display().to_string()).is_empty(), "the plugin host outlived the cancelled run");
    // The next run, in the same process: its plugin's crash is reported as such.
    let err = engine.run(&spec("segfault"), Vec::new(), None, Arc::default()).unwrap_err().to_string();
    assert!(err.contains("killed by signal 11") && !err.contains("interrupted"), "{err}");
}

#[test]
fn shipped_native_pipeline_validates_with_the_example_plugin() {
    // pipelines/native.yaml names target/release/...; point it at the library built here.
    let library = landweber();
    let out = r2d2(&["validate", "pipelines/native.yaml", "--set", &format!("step.library={}", library.display())], root());
    check(&out);
}

#[test]
fn image_command_takes_a_plugin_library() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    let reference = ReferenceOperator::new(&d.join("obs.parquet"));
    let gain = reference.landweber_gain();
    let library = landweber();
    let config = format!("{{gain: {gain:e}}}");
    let args = ["image", "obs.parquet", "--size", "64", "--step", library.to_str().unwrap(), "--iterations", "3", "--plugin-config", &config, "--name", "lw"];
    check(&r2d2(&args, d));
    let (expected, _) = landweber_reference(&reference, &read(&d.join("lw-dirty.fits")), gain, 0.0, 3, true);
    let error = max_diff(&read(&d.join("lw-model.fits")), &expected) / max_abs(&expected);
    assert!(error < 1e-5, "r2d2 image --step <library>: {error:e}");

    // A configuration for a step that takes none is refused, not ignored.
    let out = r2d2(&["image", "obs.parquet", "--size", "64", "--plugin-config", "{gain: 1}", "--name", "x"], d);
    assert!(!out.status.success() && stderr(&out).contains("invalid --plugin-config: only a native plugin takes a configuration"), "{}", stderr(&out));
}
