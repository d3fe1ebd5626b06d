//! Real YAML pipelines end to end through the `r2d2` binary, and every configuration and
//! runtime error case the engine promises to report cleanly.

mod common;

use common::{check, r2d2, stderr};
use r2d2_imaging::fits::read_image;
use std::path::Path;

/// A small, fast pipeline (64^2, short VLA C observation) with `{extra}` appended to the
/// clean stage and `{source}` replacing the source stage when given.
fn small_pipeline(source: Option<&str>) -> String {
    let source = source.unwrap_or(
        "  source:\n    kind: simulate\n    seed: 5\n    dynamic_range: 1000\n    configurations: [c]\n    hours: [1]\n    integration_s: 300\n    to: weights\n",
    );
    format!(
        "name: small\nimage:\n  size: 64\nstages:\n{source}  weights:\n    kind: weighting\n    scheme: briggs\n    robust: 0\n    to: grid\n  grid:\n    kind: gridder\n    to: step\n  step:\n    kind: clean\n    major_cycles: 3\n    components_per_cycle: 200\n    to: update\n  update:\n    kind: residual\n    to: step\n    done: write\n  write:\n    kind: writer\n    prefix: \"out/{{job}}\"\n"
    )
}

#[test]
fn simulate_clean_write_pipeline_produces_checked_products() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("p.yaml"), small_pipeline(None)).unwrap();
    check(&r2d2(&["validate", "p.yaml"], d));
    check(&r2d2(&["run", "p.yaml"], d));
    for product in ["dirty", "psf", "model", "residual", "image"] {
        let img = read_image(&d.join(format!("out/sim-5-{product}.fits"))).unwrap();
        assert_eq!((img.nx, img.ny), (64, 64), "{product}");
        let wcs = img.wcs.expect("celestial WCS");
        assert_eq!((wcs.ra_deg, wcs.dec_deg), (180.0, 40.0));
        assert!(img.data.iter().all(|v| v.is_finite()));
    }
    let dirty = read_image(&d.join("out/sim-5-dirty.fits")).unwrap().data;
    let residual = read_image(&d.join("out/sim-5-residual.fits")).unwrap().data;
    let model = read_image(&d.join("out/sim-5-model.fits")).unwrap().data;
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    assert!(norm(&residual) < 0.5 * norm(&dirty), "CLEAN did not reduce the residual");
    assert!(model.iter().filter(|v| **v != 0.0).count() > 0, "empty model");
    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("out/sim-5-metrics.json")).unwrap()).unwrap();
    let iterations = metrics["iterations"].as_array().unwrap();
    assert_eq!(iterations.len(), 3);
    let ratios: Vec<f64> = iterations.iter().map(|m| m["residual_ratio"].as_f64().unwrap()).collect();
    assert!(ratios.windows(2).all(|w| w[1] < w[0]), "residual ratio must fall: {ratios:?}");
    assert!(iterations[0]["snr"].is_number(), "a simulated job reports SNR");
    // The image header carries the restoring beam.
    let header = std::fs::read(d.join("out/sim-5-image.fits")).unwrap();
    assert!(String::from_utf8_lossy(&header[..2880 * 2]).contains("BMAJ"));
}

#[test]
fn set_overrides_values_and_names_unknown_stages() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("p.yaml"), small_pipeline(None)).unwrap();
    check(&r2d2(&["run", "p.yaml", "--set", "step.major_cycles=2", "--set", "write.prefix=o2/{job}"], d));
    let metrics = std::fs::read_to_string(d.join("o2/sim-5-metrics.json")).unwrap();
    let v: serde_json::Value = serde_json::from_str(&metrics).unwrap();
    assert_eq!(v["iterations"].as_array().unwrap().len(), 2);
    let out = r2d2(&["validate", "p.yaml", "--set", "nosuch.key=1"], d);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("no stage 'nosuch'"), "{}", stderr(&out));
}

/// Each broken description fails validation with file, line and the allowed choices.
#[test]
fn configuration_errors_name_file_line_and_choices() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let good = small_pipeline(None);
    let cases: Vec<(&str, String, Vec<&str>)> = vec![
        ("unknown key", good.replace("    gain_x: 1\n", "").replace("    major_cycles: 3\n", "    major_cycles: 3\n    gian: 0.2\n"), vec!["line 24", "gian", "gain"]),
        ("wrong type", good.replace("major_cycles: 3", "major_cycles: many"), vec!["line 23", "major_cycles", "invalid type"]),
        ("dangling stage", good.replace("    to: grid\n", "    to: gird\n"), vec!["line 17", "gird", "stages: source, weights, grid"]),
        ("unknown kind", good.replace("kind: gridder", "kind: griddr"), vec!["line 19", "griddr", "gridder"]),
        ("missing to", good.replace("    to: weights\n", ""), vec!["source", "missing `to`"]),
        ("bad cycle", good.replace("    to: grid\n", "    to: source\n"), vec!["source stage cannot receive"]),
        ("bad cycle 2", good.replace("    done: write\n", "    done: weights\n"), vec!["cycle", "weights"]),
        ("top-level key", format!("colour: red\n{good}"), vec!["line 1", "colour"]),
        ("yaml syntax", good.replace("  size: 64", "  size: [64"), vec!["line"]),
    ];
    for (what, text, expect) in cases {
        std::fs::write(d.join("bad.yaml"), &text).unwrap();
        let out = r2d2(&["validate", "bad.yaml"], d);
        assert!(!out.status.success(), "{what}: accepted");
        let err = stderr(&out);
        assert!(err.contains("bad.yaml"), "{what}: no file name in: {err}");
        for e in expect {
            assert!(err.contains(e), "{what}: '{e}' missing from: {err}");
        }
    }
}

/// A corrupt file mid-stream: the first job is finished and its products are intact, the
/// failed job leaves nothing behind, the error names the stage and job, and the exit code is non-zero.
#[test]
fn a_failing_job_stops_the_run_cleanly_and_keeps_finished_products() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(
        &["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--seed", "2", "--out", "a.parquet"],
        d,
    ));
    std::fs::write(d.join("b.parquet"), b"PAR1 this file is corrupt PAR1").unwrap();
    let source = "  source:\n    kind: parquet\n    files: [a.parquet, b.parquet]\n    to: weights\n";
    std::fs::write(d.join("p.yaml"), small_pipeline(Some(source))).unwrap();
    let out = r2d2(&["run", "p.yaml"], d);
    assert!(!out.status.success(), "a corrupt input must fail the run");
    let err = stderr(&out);
    assert!(err.contains("stage 'source'") && err.contains("b.parquet"), "{err}");
    for product in ["dirty", "psf", "model", "residual", "image", "metrics"] {
        let ext = if product == "metrics" { "json" } else { "fits" };
        assert!(d.join(format!("out/a-{product}.{ext}")).exists(), "finished job lost its {product}");
    }
    let leftovers: Vec<_> = std::fs::read_dir(d.join("out")).unwrap().filter_map(|e| e.ok()).map(|e| e.file_name()).filter(|n| !n.to_string_lossy().starts_with("a-")).collect();
    assert!(leftovers.is_empty(), "partial files left: {leftovers:?}");
}

#[test]
fn image_command_runs_the_default_pipeline() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(
        &["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--seed", "4", "--out", "obs.parquet"],
        d,
    ));
    check(&r2d2(&["image", "obs.parquet", "--size", "64", "--iterations", "2", "--truth", "obs.sky.fits", "--name", "res/obs"], d));
    for product in ["dirty", "psf", "model", "residual", "image"] {
        assert!(d.join(format!("res/obs-{product}.fits")).exists(), "{product}");
    }
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("res/obs-metrics.json")).unwrap()).unwrap();
    assert!(v["iterations"][1]["logsnr"].is_number());
}

#[test]
fn shipped_pipelines_validate() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for p in ["quickstart.yaml", "stream.yaml", "image.yaml"] {
        let out = r2d2(&["validate", &format!("pipelines/{p}")], root);
        // image.yaml names obs.parquet, which does not exist in the repository.
        if p == "image.yaml" {
            assert!(stderr(&out).contains("obs.parquet"), "{}", stderr(&out));
        } else {
            check(&out);
        }
    }
}
