//! Importing the reference implementation's checkpoints (training/import_reference.py) and
//! running what it makes: checkpoints in the reference's exact layout, with random weights, are
//! written by tests/make_reference_checkpoints.py (the published series cannot be downloaded
//! here); the exported networks are checked against PyTorch on both backends; a series of three
//! realisations images a small observation, and its uncertainty map is checked against the
//! three realisations run one by one.

mod common;
// The command line's lookup of native ONNX Runtime, which the library leaves to its caller.
#[path = "../src/cli/onnx_runtime.rs"]
mod onnx_runtime;

use common::{assert_fails_with, check, observation, r2d2, read, stderr, SIZE};
use r2d2_imaging::models::{use_onnx_runtime, LoadedNetwork};
use r2d2_imaging::BackendChoice;
use std::path::{Path, PathBuf};
use std::process::Command;

fn python(args: &[&str], dir: &Path) -> String {
    let out = Command::new("python3").args(args).current_dir(dir).output().expect("python3 runs (a test requirement)");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "python3 {args:?} failed (pip install -r training/requirements.txt):\n{text}");
    text
}

fn repo(path: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path).to_string_lossy().into_owned()
}

/// Reference checkpoints (`make_reference_checkpoints.py` arguments) in `dir/ckpt-NAME`,
/// imported into `dir/NAME` with the check's input and PyTorch outputs in `dir/check-NAME`.
fn import(dir: &Path, name: &str, fixture: &[&str]) -> PathBuf {
    let ckpt = format!("ckpt-{name}");
    let mut args = vec![repo("tests/make_reference_checkpoints.py"), ckpt.clone()];
    args.extend(fixture.iter().map(|s| s.to_string()));
    python(&args.iter().map(String::as_str).collect::<Vec<_>>(), dir);
    let check_dir = format!("check-{name}");
    let size = SIZE.to_string();
    let importer = repo("training/import_reference.py");
    python(&[&importer, &ckpt, name, "--check-size", &size, "--check-out", &check_dir, "--threads", "2"], dir);
    dir.join(name)
}

fn read_f32(path: &Path) -> Vec<f32> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

/// Every network of the series, on ONNX Runtime and on tract, reproduces PyTorch's output on
/// the importer's check input to 1e-5 of its peak.
fn backends_match_pytorch(dir: &Path, name: &str, networks: &[&str]) {
    let input = read_f32(&dir.join(format!("check-{name}/input.f32")));
    use_onnx_runtime(&onnx_runtime::find_onnxruntime().expect("native ONNX Runtime (pip install onnxruntime)")).unwrap();
    for network in networks {
        let expected = read_f32(&dir.join(format!("check-{name}/{}", network.replace('/', "-").replace(".onnx", ".f32"))));
        let path = dir.join(name).join(network);
        for backend in [BackendChoice::Ort, BackendChoice::Tract] {
            let got = LoadedNetwork::load(&path, SIZE, backend, 2).unwrap().run(&input).unwrap();
            let peak = expected.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let error = got.iter().zip(&expected).fold(0.0f32, |m, (a, b)| m.max((a - b).abs())) / peak;
            assert!(error <= 1e-5, "{name}/{network} on {backend:?}: {error:e} of the peak from PyTorch");
        }
    }
}

fn manifest(dir: &Path) -> serde_yaml::Value {
    serde_yaml::from_str(&std::fs::read_to_string(dir.join("manifest.yaml")).unwrap()).unwrap()
}

fn sha256sum(path: &Path) -> String {
    let out = Command::new("sha256sum").arg(path).output().expect("sha256sum runs");
    String::from_utf8_lossy(&out.stdout).split_whitespace().next().unwrap().to_string()
}

#[test]
fn reference_uwdsr_checkpoint_imports_and_matches_pytorch_on_both_backends() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let series = import(d, "uwdsr", &["--arch", "uwdsr", "--networks", "1", "--channels", "8", "--poolings", "2"]);
    let m = manifest(&series);
    assert_eq!(m["network"]["kind"], "uwdsr");
    assert_eq!((m["network"]["base_channels"].as_u64(), m["network"]["poolings"].as_u64()), (Some(8), Some(2)));
    assert_eq!(m["networks"][0], "R2D2_UWDSR_N1.onnx");
    let hp = &m["provenance"]["imported_from"]["hyper_parameters"];
    assert_eq!((hp["num_chans"].as_u64(), hp["architecture"].as_str(), hp["data_path"].as_str()), (Some(8), Some("uwdsr"), Some("data/vla")));
    backends_match_pytorch(d, "uwdsr", &["R2D2_UWDSR_N1.onnx"]);
}

/// A pipeline imaging `obs.parquet` (truth `obs.sky.fits`) with the series `series`.
fn pipeline(series: &str) -> String {
    format!(
        "image: {{size: {SIZE}}}\nstages:\n  read: {{kind: parquet, files: obs.parquet, truth: obs.sky.fits, to: weights}}\n  weights: {{kind: weighting, scheme: briggs, robust: 0, to: grid}}\n  grid: {{kind: gridder, to: step}}\n  step: {{kind: onnx, series: {series}, backend: ort, to: update}}\n  update: {{kind: residual, to: step, done: write}}\n  write: {{kind: writer, prefix: \"out/{{job}}\"}}\n"
    )
}

#[test]
fn three_realisations_image_their_mean_with_the_std_over_mean_map() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let series = import(d, "unet3", &["--arch", "unet", "--networks", "2", "--realisations", "3", "--channels", "8", "--poolings", "2"]);
    // The manifest: sources with their checksums, three realisations, the published validity.
    let m = manifest(&series);
    let files = m["provenance"]["imported_from"]["files"].as_sequence().unwrap();
    assert_eq!(files.len(), 6);
    for f in files {
        let path = d.join("ckpt-unet3").join(f["path"].as_str().unwrap());
        assert_eq!(f["sha256"].as_str().unwrap(), sha256sum(&path), "{}", path.display());
    }
    assert_eq!(m["realisations"].as_sequence().unwrap().len(), 3);
    assert_eq!(m["realisations"][2][1], "V3/R2D2_UNet_N2.onnx");
    assert_eq!(m["validity"]["robust"], serde_yaml::from_str::<serde_yaml::Value>("[-1.0, 1.0]").unwrap());
    assert_eq!(m["network"]["kind"], "unet");
    backends_match_pytorch(d, "unet3", &["V1/R2D2_UNet_N1.onnx", "V3/R2D2_UNet_N2.onnx"]);

    observation(d);
    std::fs::write(d.join("p.yaml"), pipeline("unet3")).unwrap();
    // A shallow dynamic range, so that the map's threshold (peak / dynamic range) masks pixels.
    // The networks are untrained (random weights): the divergence guard, which watches each
    // realisation, would stop them; this test is of the mean and its map, so it is off.
    let all = r2d2(&["run", "p.yaml", "--set", "write.prefix=\"all/{job}\"", "--set", "write.preview_dynamic_range=3", "--set", "update.divergence_guard=false"], d);
    check(&all);
    let mut singles = Vec::new();
    for r in 1..=3 {
        // Each realisation alone runs its whole series, as it does inside the mean's run (where
        // the early stop never cuts a realisation short, and the guard is off here).
        let (realisation, prefix) = (format!("step.realisation={r}"), format!("write.prefix=\"v{r}/{{job}}\""));
        let whole = ["--set", "update.early_stop=false", "--set", "update.divergence_guard=false"];
        check(&r2d2(&[&["run", "p.yaml", "--set", &realisation, "--set", &prefix][..], &whole[..]].concat(), d));
        singles.push(read(&d.join(format!("v{r}/obs-model.fits"))));
        assert!(!d.join(format!("v{r}/obs-uncertainty.fits")).exists(), "one realisation has no uncertainty map");
    }
    // The mean of the three runs is the model; the map is their population std over that mean
    // where the mean exceeds the threshold the metrics state, 0 elsewhere.
    let model = read(&d.join("all/obs-model.fits"));
    let map = read(&d.join("all/obs-uncertainty.fits"));
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("all/obs-metrics.json")).unwrap()).unwrap();
    let threshold = metrics["realisations"]["uncertainty_threshold"].as_f64().unwrap();
    let peak = model.iter().fold(0.0f64, |m, v| m.max(*v));
    assert!((threshold - peak / 3.0).abs() <= 1e-6 * peak, "threshold {threshold}, peak {peak}");
    assert!(peak > 0.0, "the mean model is all zero: the test would prove nothing");
    let mut masked = 0;
    for k in 0..model.len() {
        let values = [singles[0][k], singles[1][k], singles[2][k]];
        let mean = values.iter().sum::<f64>() / 3.0;
        let std = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 3.0).sqrt();
        // FITS stores float32: compare to its precision.
        assert!((model[k] - mean).abs() <= 1e-6 * peak, "pixel {k}: model {} mean {mean}", model[k]);
        let expected = if mean > threshold { std / mean } else { 0.0 };
        masked += usize::from(mean <= threshold);
        assert!((map[k] - expected).abs() <= 1e-5 * expected.abs().max(1.0), "pixel {k}: map {} expected {expected}", map[k]);
    }
    assert!(masked > 0 && masked < model.len(), "the threshold should mask some pixels and keep others ({masked})");
    assert!(d.join("all/obs-uncertainty.png").exists());
    // Each realisation's final figures are those of its run alone; the mean's are given too.
    let finals = metrics["realisations"]["final"].as_array().unwrap();
    for r in 0..3 {
        let alone: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join(format!("v{}/obs-metrics.json", r + 1))).unwrap()).unwrap();
        let alone = alone["iterations"].as_array().unwrap().last().unwrap().clone();
        for key in ["snr", "logsnr", "residual_ratio"] {
            let (a, b) = (finals[r][key].as_f64().unwrap(), alone[key].as_f64().unwrap());
            assert!((a - b).abs() <= 1e-9 * b.abs().max(1.0), "realisation {}: {key} {a} vs {b} alone", r + 1);
        }
    }
    let mean = &metrics["realisations"]["mean"];
    let truth = read(&d.join("obs.sky.fits"));
    let snr = r2d2_imaging::metrics::snr(&model, &truth);
    assert!((mean["snr"].as_f64().unwrap() - snr).abs() < 1e-3, "{mean} vs {snr}");

    // Outside the validity ranges: a warning by default, an error with `validity: error`.
    let out = r2d2(&["run", "p.yaml", "--set", "weights.robust=2", "--set", "step.networks=1", "--set", "write.prefix=\"w/{job}\""], d);
    check(&out);
    assert!(stderr(&out).contains("Briggs robust 2 is outside the series' range -1..1"), "{}", stderr(&out));
    let out = r2d2(&["run", "p.yaml", "--set", "image.superresolution=3", "--set", "step.validity=error"], d);
    assert_fails_with(&out, "SR outside the range", &["super-resolution 3.000", "outside the series' range 1.5..2.5", "validity"]);
    let out = r2d2(&["run", "p.yaml", "--set", "step.realisation=4"], d);
    assert_fails_with(&out, "no such realisation", &["realisations 1..=3", "asked for 4"]);
}
