//! Real YAML pipelines end to end through the `r2d2` binary, and every configuration and
//! runtime error case the engine promises to report cleanly.

mod common;

use common::{assert_fails_with, check, r2d2, stderr};
use r2d2_imaging::fits::read_image;
use std::path::Path;
use std::process::{Command, Output};

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

    // A PNG preview per FITS product: a 64^2 image is shown 8x enlarged (512 rows) under a
    // title line (12 + 14 + 10 rows), with the offset axes below it (tick, gap, labels and
    // caption: 5 + 4 + 2 x 14 + 4 rows), half a label line and a 12-row margin.
    for product in ["dirty", "psf", "model", "residual", "image"] {
        let file = std::fs::File::open(d.join(format!("out/sim-5-{product}.png"))).unwrap();
        let mut reader = png::Decoder::new(std::io::BufReader::new(file)).read_info().unwrap();
        let mut pixels = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut pixels).unwrap();
        assert_eq!(info.height, 12 + 14 + 10 + 512 + (5 + 4 + 2 * 14 + 4) + 7 + 12, "{product}");
        assert!(info.width > 12 + 512 + 16 + 20 && info.width < 1024, "{product}: width {}", info.width);
        assert_eq!(info.color_type, png::ColorType::Rgb);
        // Not blank: the image area (from x = 12, y = 36) holds several colours.
        let row_bytes = 3 * info.width as usize;
        let distinct: std::collections::HashSet<&[u8]> =
            (36..36 + 512).flat_map(|y| pixels[y * row_bytes + 36..y * row_bytes + 36 + 3 * 512].chunks(3)).collect();
        assert!(distinct.len() > 1, "{product}: blank preview");
    }

    // The metrics again as Parquet: the same rows as the JSON, stage seconds as metadata.
    use arrow::array::{Array, Float64Array, UInt32Array};
    use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
    let builder = ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(d.join("out/sim-5-metrics.parquet")).unwrap()).unwrap();
    let kv = builder.metadata().file_metadata().key_value_metadata().unwrap().clone();
    let value = |key: &str| kv.iter().find(|k| k.key == key).and_then(|k| k.value.clone()).unwrap();
    assert_eq!(value("job"), "sim-5");
    let stage_seconds: serde_json::Value = serde_json::from_str(&value("stage_seconds")).unwrap();
    assert_eq!(stage_seconds, metrics["stage_seconds"]);
    let batches: Vec<_> = builder.build().unwrap().map(|b| b.unwrap()).collect();
    assert_eq!(batches.len(), 1);
    let b = &batches[0];
    let col = |name: &str| b.column_by_name(name).unwrap().as_any().downcast_ref::<Float64Array>().unwrap().clone();
    let iteration = b.column_by_name("iteration").unwrap().as_any().downcast_ref::<UInt32Array>().unwrap().clone();
    assert_eq!(iteration.values().to_vec(), [1, 2, 3]);
    // serde_json's parser (without its float_roundtrip feature) may miss by one ulp.
    let same = |a: f64, json: &serde_json::Value| (a - json.as_f64().unwrap()).abs() <= 1e-15 * a.abs();
    for (k, m) in iterations.iter().enumerate() {
        for name in ["residual_ratio", "snr", "logsnr", "step_seconds", "residual_seconds"] {
            assert!(same(col(name).value(k), &m[name]), "{name} at {k}: {} vs {}", col(name).value(k), m[name]);
        }
    }
    assert_eq!(col("snr").null_count(), 0);
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
    check(&r2d2(&["run", "p.yaml", "--set", "step.major_cycles=1", "--set", "write.prefix=o3/{job}", "--set", "write.previews=false"], d));
    let written: Vec<String> = std::fs::read_dir(d.join("o3")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert!(written.iter().any(|f| f.ends_with(".fits")) && !written.iter().any(|f| f.ends_with(".png")), "{written:?}");
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

/// `r2d2 validate p.yaml --set ...` (`text` written to `d/p.yaml`) fails cleanly with each of
/// `expected` and the file's name in its message, which is returned.
fn validate_fails(d: &Path, text: &str, sets: &[&str], what: &str, expected: Vec<&str>) -> String {
    std::fs::write(d.join("p.yaml"), text).unwrap();
    let mut args = vec!["validate", "p.yaml"];
    for set in sets {
        args.extend(["--set", set]);
    }
    let expected: Vec<&str> = expected.into_iter().chain(["p.yaml"]).collect();
    assert_fails_with(&r2d2(&args, d), what, &expected)
}

/// A wrong value inside a stage's parameters (an unknown enum value, a wrong type, nested in a
/// flow collection) is reported at the line and column of the value in the file, an unknown
/// key at the key's; a value that came from `--set` is reported as the `--set`, not at a line
/// of the file (which does not hold it).
#[test]
fn stage_parameter_errors_point_at_their_yaml_line() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let good = small_pipeline(None);
    let residual = "    kind: residual\n";
    let split_source = "  source:\n    kind: parquet\n    files: a.parquet\n    split_by: {column: time, windw: 600}\n    to: weights\n".to_string();
    let cases: Vec<(&str, String, Vec<&str>, Vec<&str>)> = vec![
        ("unknown scheme", good.replace("scheme: briggs", "scheme: brigs"), vec![], vec!["line 15, column 13", "stages.weights.scheme", "`brigs`", "`briggs`"]),
        ("unknown method", good.replace(residual, &format!("{residual}    method: nuft\n")), vec![], vec!["line 28, column 13", "stages.update.method", "`nuft`", "`nufft`"]),
        ("wrong type in a list", good.replace("hours: [1]", "hours: [1, x]"), vec![], vec!["line 10, column 16", "stages.source.hours[1]", "expected f64"]),
        ("wrong type", good.replace("robust: 0", "robust: zero"), vec![], vec!["line 16, column 13", "stages.weights.robust", "expected f64"]),
        ("unknown key", good.replace("    kind: writer\n", "    kind: writer\n    options: {previews: true}\n"), vec![], vec!["line 32, column 5", "stages.write.options", "unknown field"]),
        ("unknown key in a flow mapping", small_pipeline(Some(&split_source)), vec![], vec!["line 8, column 30", "stages.source.split_by.windw", "`window`"]),
        // A model column needs an MS to write into: a simulated (or Parquet) source has none,
        // known when the pipeline is checked, not after imaging.
        (
            "model column without an MS",
            good.replace("    kind: writer\n", "    kind: writer\n    model_column: MODEL_DATA\n"),
            vec![],
            vec!["line 32, column 5", "stages.write.model_column", "stage 'source' (kind 'simulate')", "reads no MeasurementSet"],
        ),
        // The file is fine: the wrong value is the command line's.
        ("from --set", good.clone(), vec!["weights.scheme=brigs"], vec!["stages.weights.scheme", "override weights.scheme=brigs", "`brigs`"]),
        ("nested from --set", good.clone(), vec!["source.hours=[1, x]"], vec!["stages.source.hours[1]", "override source.hours=[1, x]"]),
        ("image key from --set", good.clone(), vec!["image.size=abc"], vec!["image.size, as set by the override image.size=abc", "expected usize"]),
        // A wrong value of the file is still found at its line when `--set` changed another.
        ("file, beside a --set", good.replace("robust: 0", "robust: zero"), vec!["weights.scheme=uniform"], vec!["line 16, column 13", "stages.weights.robust"]),
    ];
    for (what, text, sets, expected) in cases {
        let err = validate_fails(d, &text, &sets, what, expected);
        if !sets.is_empty() && what.contains("--set") && !what.starts_with("file") {
            assert!(!err.contains("line "), "{what}: a value of the command line has no line in the file: {err}");
        }
    }
    // A wrong value of the file that `--set` replaces is no error.
    std::fs::write(d.join("p.yaml"), good.replace("scheme: briggs", "scheme: brigs")).unwrap();
    check(&r2d2(&["validate", "p.yaml", "--set", "weights.scheme=briggs"], d));
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
    // The default step is the shipped series that serves the size: at 64 the 512 one, measured
    // there on held-out skies (its domain names the size), without the off-size warning.
    let out = r2d2(&["image", "obs.parquet", "--size", "64", "--truth", "obs.sky.fits", "--name", "res/obs"], d);
    check(&out);
    assert!(stderr(&out).contains("series 'vla-r2d2-512' chosen for 64 x 64 (trained for [512], measured at 64 x 64 on held-out data)"), "{}", stderr(&out));
    assert!(!stderr(&out).contains("no series was trained for 64 x 64"), "{}", stderr(&out));
    for product in ["dirty", "psf", "model", "residual"] {
        assert!(d.join(format!("res/obs-{product}.fits")).exists(), "{product}");
    }
    let series = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/vla-r2d2-512/manifest.yaml");
    let manifest: serde_yaml::Value = serde_yaml::from_str(&std::fs::read_to_string(series).unwrap()).unwrap();
    let networks = manifest["networks"].as_sequence().unwrap().len();
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("res/obs-metrics.json")).unwrap()).unwrap();
    // One iteration per network, then one per cycle of the final CLEAN on the residual, one for
    // its smoothed-residual steps and one where faint islands left its model.
    let final_clean = &v["settings"]["final_clean"];
    let final_steps = final_clean["major_cycles"].as_u64().unwrap() as usize
        + usize::from(final_clean["scale_steps"].as_u64().unwrap() > 0)
        + usize::from(final_clean["faint_islands"].as_u64().unwrap() > 0);
    assert_eq!(v["iterations"].as_array().unwrap().len(), networks + final_steps, "one iteration per network of the default series, per final cycle, for the smoothed-residual steps and for the faint islands' removal");
    assert!(v["iterations"][0]["logsnr"].is_number());

    // CLEAN on request, with its restored image.
    check(&r2d2(&["image", "obs.parquet", "--size", "64", "--step", "clean", "--iterations", "2", "--truth", "obs.sky.fits", "--name", "cl/obs"], d));
    for product in ["dirty", "psf", "model", "residual", "image"] {
        assert!(d.join(format!("cl/obs-{product}.fits")).exists(), "{product}");
    }
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("cl/obs-metrics.json")).unwrap()).unwrap();
    assert!(v["iterations"][1]["logsnr"].is_number());
    // A network series over the same prefix restores its own model: CLEAN's restored image is
    // replaced, not left beside the new products as if it were theirs.
    let clean_image = std::fs::read(d.join("cl/obs-image.fits")).unwrap();
    check(&r2d2(&["image", "obs.parquet", "--size", "64", "--name", "cl/obs"], d));
    assert!(d.join("cl/obs-image.png").exists() && d.join("cl/obs-model.fits").exists());
    assert_ne!(std::fs::read(d.join("cl/obs-image.fits")).unwrap(), clean_image);

    // A series name that is nowhere says where it looked.
    let out = r2d2(&["image", "obs.parquet", "--size", "64", "--step", "nosuch", "--name", "x"], d);
    assert!(!out.status.success() && stderr(&out).contains("no model series of that name"), "{}", stderr(&out));
}

/// WSClean's uv cuts and tapers are keys of the weighting stage: a pipeline with them images as
/// `r2d2 image` with the same options does (the same dirty image, the super-resolution factor
/// applied to the longest baseline kept), records them in the metrics and the FITS headers,
/// logs what each cut left out, and a bad value is reported at its line, naming the key.
#[test]
fn uv_cuts_and_tapers_are_keys_of_the_weighting_stage() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Baselines of 360 to 15800 wavelengths.
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--seed", "4", "--out", "obs.parquet"], d));
    let source = "  source:\n    kind: parquet\n    files: obs.parquet\n    to: weights\n";
    let uv = "    robust: 0\n    minuv_l: 2000\n    maxuv_l: 12000\n    taper_gaussian: 10\n    taper_tukey: 3000\n";
    let yaml = small_pipeline(Some(source)).replace("    robust: 0\n", uv);
    std::fs::write(d.join("p.yaml"), &yaml).unwrap();
    let out = r2d2(&["run", "p.yaml"], d);
    check(&out);
    assert!(stderr(&out).contains("below minuv_l") && stderr(&out).contains("above maxuv_l"), "{}", stderr(&out));
    let options = ["--robust", "0", "--minuv-l", "2000", "--maxuv-l", "12000", "--taper-gaussian", "10", "--taper-tukey", "3000"];
    let mut args = vec!["image", "obs.parquet", "--size", "64", "--step", "clean", "--iterations", "1", "--name", "cli/obs"];
    args.extend_from_slice(&options);
    check(&r2d2(&args, d));
    let (a, b) = (read_image(&d.join("out/obs-dirty.fits")).unwrap(), read_image(&d.join("cli/obs-dirty.fits")).unwrap());
    assert_eq!(a.wcs, b.wcs);
    let peak = b.data.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    assert!(a.data.iter().zip(&b.data).all(|(x, y)| (x - y).abs() <= 1e-9 * peak), "the pipeline's and r2d2 image's dirty images differ");
    // The pixel is the super-resolution factor's on the longest baseline kept (12000).
    let pixel_rad = b.wcs.unwrap().pixel_deg.to_radians();
    assert!((pixel_rad * 1.5 * 2.0 * 12000.0 - 1.0).abs() < 1e-9, "{pixel_rad}");
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("out/obs-metrics.json")).unwrap()).unwrap();
    let weighting = &v["settings"]["weighting"];
    assert_eq!((weighting["minuv_l"].as_f64(), weighting["taper_tukey"].as_f64()), (Some(2000.0), Some(3000.0)), "{weighting}");
    assert!(weighting["left_out"]["minuv_l"].as_u64().unwrap() > 0 && weighting["left_out"]["maxuv_l"].as_u64().unwrap() > 0, "{weighting}");
    let header = std::fs::read(d.join("out/obs-dirty.fits")).unwrap();
    let card = "WEIGHTUV= 'minuv_l=2000 maxuv_l=12000 taper_gaussian=10 taper_tukey=3000";
    assert!(header.windows(card.len()).any(|w| w == card.as_bytes()), "{card} in the header");
    // A bad value at its line, by its key.
    validate_fails(d, &yaml.replace("minuv_l: 2000", "minuv_l: -2000"), &[], "negative minuv_l", vec!["stages.weights.minuv_l", "line 13", ">= 0"]);
    validate_fails(d, &yaml.replace("    maxuv_l: 12000\n", ""), &[], "taper_tukey without maxuv_l", vec!["stages.weights.taper_tukey", "maxuv_l"]);
}

#[test]
fn shipped_pipelines_validate() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for p in ["quickstart.yaml", "stream.yaml", "image.yaml", "ipc.yaml"] {
        let out = r2d2(&["validate", &format!("pipelines/{p}")], root);
        // image.yaml names obs.parquet, which does not exist in the repository.
        if p == "image.yaml" {
            assert!(stderr(&out).contains("obs.parquet"), "{}", stderr(&out));
        } else {
            check(&out);
        }
    }
}

fn simulate_small(d: &Path, seed: &str, out: &str, extra: &[&str]) {
    let mut args = vec!["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--seed", seed, "--out", out];
    args.extend_from_slice(extra);
    check(&r2d2(&args, d));
}

/// The batches of a Parquet visibility table, with its key-value metadata on the schema (as
/// an upstream process would send them over Arrow IPC), in batches of `rows`.
fn parquet_batches(path: &Path, rows: usize) -> (std::sync::Arc<arrow::datatypes::Schema>, Vec<arrow::array::RecordBatch>) {
    use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
    let builder = ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(path).unwrap()).unwrap();
    let metadata: std::collections::HashMap<String, String> = builder
        .metadata()
        .file_metadata()
        .key_value_metadata()
        .unwrap()
        .iter()
        .filter(|kv| kv.key != "ARROW:schema")
        .map(|kv| (kv.key.clone(), kv.value.clone().unwrap_or_default()))
        .collect();
    let schema = std::sync::Arc::new(builder.schema().as_ref().clone().with_metadata(metadata));
    let batches = builder.with_batch_size(rows).build().unwrap().map(|b| b.unwrap().with_schema(schema.clone()).unwrap()).collect();
    (schema, batches)
}

/// `a.parquet`, a small simulated table, and its batches of 500 rows.
fn small_table_batches(d: &Path) -> (std::sync::Arc<arrow::datatypes::Schema>, Vec<arrow::array::RecordBatch>) {
    simulate_small(d, "3", "a.parquet", &[]);
    parquet_batches(&d.join("a.parquet"), 500)
}

/// An Arrow IPC stream of the batches, and the byte offsets where each batch's message ends.
fn ipc_stream(schema: &arrow::datatypes::Schema, batches: &[arrow::array::RecordBatch]) -> (Vec<u8>, Vec<usize>) {
    let mut writer = arrow::ipc::writer::StreamWriter::try_new(Vec::new(), schema).unwrap();
    let mut ends = Vec::new();
    for b in batches {
        writer.write(b).unwrap();
        ends.push(writer.get_ref().len());
    }
    writer.finish().unwrap();
    (writer.into_inner().unwrap(), ends)
}

fn r2d2_stdin(args: &[&str], dir: &Path, input: &[u8]) -> Output {
    use std::io::Write;
    let mut child = Command::new(env!("CARGO_BIN_EXE_r2d2"))
        .args(args)
        .current_dir(dir)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("r2d2 runs");
    let mut stdin = child.stdin.take().unwrap();
    // r2d2 may stop reading early (an error): a broken pipe here is then expected.
    let _ = stdin.write_all(input);
    drop(stdin);
    child.wait_with_output().unwrap()
}

fn ipc_source(path: &str, extra: &str) -> String {
    format!("  source:\n    kind: arrow-ipc\n    path: \"{path}\"\n{extra}    to: weights\n")
}

/// An Arrow IPC stream on standard input, and an IPC file, image exactly like the Parquet
/// file they were made from.
#[test]
fn arrow_ipc_on_stdin_and_from_a_file_images_like_parquet() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (schema, batches) = small_table_batches(d);
    assert!(batches.len() > 2, "several batches");
    let (stream, _) = ipc_stream(&schema, &batches);
    let mut file = arrow::ipc::writer::FileWriter::try_new(Vec::new(), &schema).unwrap();
    for b in &batches {
        file.write(b).unwrap();
    }
    file.finish().unwrap();
    std::fs::write(d.join("a.arrow"), file.into_inner().unwrap()).unwrap();

    let parquet = "  source:\n    kind: parquet\n    files: a.parquet\n    to: weights\n";
    std::fs::write(d.join("pq.yaml"), small_pipeline(Some(parquet))).unwrap();
    std::fs::write(d.join("stdin.yaml"), small_pipeline(Some(&ipc_source("-", "")))).unwrap();
    std::fs::write(d.join("file.yaml"), small_pipeline(Some(&ipc_source("a.arrow", "    id: from-file\n")))).unwrap();
    check(&r2d2(&["run", "pq.yaml"], d));
    check(&r2d2_stdin(&["run", "stdin.yaml"], d, &stream));
    let from_file = r2d2(&["run", "file.yaml"], d);
    check(&from_file);
    // The file is read in passes, standard input once and held.
    assert!(stderr(&from_file).contains("a.arrow at each pass"), "{}", stderr(&from_file));
    for product in ["dirty", "psf", "model", "residual", "image"] {
        let expected = read_image(&d.join(format!("out/a-{product}.fits"))).unwrap();
        for id in ["stdin", "from-file"] {
            let got = read_image(&d.join(format!("out/{id}-{product}.fits"))).unwrap();
            assert_eq!(got.data, expected.data, "{id} {product} differs from the Parquet route");
            assert_eq!(got.wcs, expected.wcs, "{id} {product} WCS");
        }
    }
}

/// A stream cut in the middle of a batch: the run fails naming the stage and the job, and
/// no product (partial or not) is written. Bytes that are no IPC at all fail the same way.
#[test]
fn corrupt_arrow_ipc_mid_stream_fails_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (schema, batches) = small_table_batches(d);
    let (stream, ends) = ipc_stream(&schema, &batches);
    // Halfway through the third batch's message.
    let cut = (ends[1] + ends[2]) / 2;
    std::fs::write(d.join("p.yaml"), small_pipeline(Some(&ipc_source("-", "")))).unwrap();
    for (what, input) in [("truncated", &stream[..cut]), ("not IPC", &b"this is not an Arrow IPC stream at all"[..])] {
        let out = r2d2_stdin(&["run", "p.yaml"], d, input);
        assert!(!out.status.success(), "{what}: accepted");
        let err = stderr(&out);
        assert!(err.contains("stage 'source' (arrow-ipc), job 'stdin'") && err.contains("standard input"), "{what}: {err}");
        let written: Vec<_> = std::fs::read_dir(d.join("out")).map(|r| r.filter_map(|e| e.ok()).map(|e| e.file_name()).collect()).unwrap_or_default();
        assert!(written.is_empty(), "{what}: files written: {written:?}");
    }
    let out = r2d2_stdin(&["run", "p.yaml"], d, &stream[..cut]);
    assert!(stderr(&out).contains("corrupt Arrow IPC data after row 1000"), "{}", stderr(&out));
}

/// A stream of `batches` whose first record batch header claims a body of `claimed` bytes
/// (the body that follows is the real one), with its end-of-stream marker.
fn ipc_stream_claiming(schema: &arrow::datatypes::Schema, batches: &[arrow::array::RecordBatch], claimed: i64) -> Vec<u8> {
    let mut writer = arrow::ipc::writer::StreamWriter::try_new(Vec::new(), schema).unwrap();
    let start = writer.get_ref().len();
    for b in batches {
        writer.write(b).unwrap();
    }
    writer.finish().unwrap();
    let mut stream = writer.into_inner().unwrap();
    // The message: continuation marker, header length, header (a flatbuffer), body.
    assert_eq!(stream[start..start + 4], [0xff; 4]);
    let length = i32::from_le_bytes(stream[start + 4..start + 8].try_into().unwrap()) as usize;
    let header = start + 8..start + 8 + length;
    let body = arrow::ipc::root_as_message(&stream[header.clone()]).unwrap().bodyLength();
    let places: Vec<usize> = (header.start..header.end - 8).filter(|&i| stream[i..i + 8] == body.to_le_bytes()).collect();
    assert_eq!(places.len(), 1, "the body length {body} is found once in the header");
    stream[places[0]..places[0] + 8].copy_from_slice(&claimed.to_le_bytes());
    assert_eq!(arrow::ipc::root_as_message(&stream[header]).unwrap().bodyLength(), claimed);
    stream
}

/// A record batch header claiming a 1 TiB body: refused before anything is allocated, on
/// standard input (against the memory there is) and from a file (against what is left in
/// it), with an error naming the input, the stage and the size, not an aborted process.
#[test]
fn arrow_ipc_declared_sizes_are_bounded_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (schema, batches) = small_table_batches(d);
    let stream = ipc_stream_claiming(&schema, &batches[..2], 1 << 40);
    std::fs::write(d.join("huge.arrows"), &stream).unwrap();
    std::fs::write(d.join("stdin.yaml"), small_pipeline(Some(&ipc_source("-", "")))).unwrap();
    std::fs::write(d.join("file.yaml"), small_pipeline(Some(&ipc_source("huge.arrows", "")))).unwrap();
    let from_stdin = r2d2_stdin(&["run", "stdin.yaml"], d, &stream);
    let from_file = r2d2(&["run", "file.yaml"], d);
    for (out, input, bound) in [(from_stdin, "standard input", "memory available"), (from_file, "huge.arrows", "left in the input")] {
        let err = assert_fails_with(&out, input, &["stage 'source' (arrow-ipc)", input, "1099511627776 bytes", bound]);
        assert!(!err.contains("panicked"), "{err}");
    }
}

/// Two inputs with the same file name would be the same job, the second overwriting the
/// first's products: `validate` and `run` refuse them, naming both files, and write nothing.
#[test]
fn inputs_with_the_same_job_id_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for sub in ["a", "b"] {
        std::fs::create_dir(d.join(sub)).unwrap();
        simulate_small(d, "3", &format!("{sub}/obs.parquet"), &[]);
    }
    let source = "  source:\n    kind: parquet\n    files: [a/obs.parquet, \"b/*.parquet\"]\n    to: weights\n";
    std::fs::write(d.join("p.yaml"), small_pipeline(Some(source))).unwrap();
    for command in ["validate", "run"] {
        let expected = ["p.yaml", "line 7", "stages.source.files", "a/obs.parquet", "b/obs.parquet", "job 'obs'"];
        assert_fails_with(&r2d2(&[command, "p.yaml"], d), command, &expected);
    }
    assert!(!d.join("out").exists(), "products written");
}

/// A stream cut at a batch boundary (an upstream process that died between batches) lacks
/// the end-of-stream marker: refused by default, naming the input, so that part of an
/// observation is not imaged as if it were all of it; `allow_truncated: true` images the rows
/// received, with a warning.
#[test]
fn arrow_ipc_without_end_of_stream_is_refused_unless_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (schema, batches) = small_table_batches(d);
    let (stream, ends) = ipc_stream(&schema, &batches);
    let cut = &stream[..ends[1]];
    std::fs::write(d.join("cut.arrows"), cut).unwrap();
    std::fs::write(d.join("stdin.yaml"), small_pipeline(Some(&ipc_source("-", "")))).unwrap();
    std::fs::write(d.join("file.yaml"), small_pipeline(Some(&ipc_source("cut.arrows", "")))).unwrap();
    for (out, input) in [(r2d2_stdin(&["run", "stdin.yaml"], d, cut), "standard input"), (r2d2(&["run", "file.yaml"], d), "cut.arrows")] {
        assert_fails_with(&out, input, &["stage 'source' (arrow-ipc)", input, "end-of-stream marker", "after row 1000", "allow_truncated"]);
        assert!(!d.join("out").exists(), "{input}: products written");
    }
    let allowed = small_pipeline(Some(&ipc_source("-", "    allow_truncated: true\n")));
    std::fs::write(d.join("allowed.yaml"), allowed).unwrap();
    let out = r2d2_stdin(&["run", "allowed.yaml"], d, cut);
    check(&out);
    let err = stderr(&out);
    assert!(err.contains("WARN") && err.contains("standard input") && err.contains("end-of-stream marker"), "{err}");
    assert!(d.join("out/stdin-dirty.fits").exists());
    // A complete stream needs no option and gives no warning.
    let out = r2d2_stdin(&["run", "allowed.yaml"], d, &stream);
    check(&out);
    assert!(!stderr(&out).contains("WARN"), "{}", stderr(&out));
}

/// A second stream after the first's end-of-stream marker (two files concatenated) is refused,
/// naming the file and the byte offset, not dropped with exit 0.
#[test]
fn arrow_ipc_stream_followed_by_another_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (schema, batches) = small_table_batches(d);
    let (stream, _) = ipc_stream(&schema, &batches);
    std::fs::write(d.join("two.arrows"), [stream.as_slice(), stream.as_slice()].concat()).unwrap();
    std::fs::write(d.join("two.yaml"), small_pipeline(Some(&ipc_source("two.arrows", "")))).unwrap();
    let offset = format!("byte offset {}", stream.len());
    let out = r2d2(&["run", "two.yaml"], d);
    assert_fails_with(&out, "two.arrows", &["two.arrows", "end-of-stream marker", &offset, "second stream"]);
    assert!(!d.join("out").exists(), "products written");
    let out = r2d2(&["convert", "two.arrows", "two.parquet"], d);
    assert_fails_with(&out, "convert", &["two.arrows", &offset]);
    assert!(!d.join("two.parquet").exists());
}

/// SIGTERM (what a batch scheduler or `kill` sends) stops a run like Ctrl-C: at a job
/// boundary, with an error and a non-zero exit, every job's products complete or absent, and
/// no staging directory left behind.
#[test]
fn sigterm_stops_a_run_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Enough jobs that the run is still going when the first one is written.
    let source = "  source:\n    kind: simulate\n    jobs: 500\n    configurations: [c]\n    hours: [1]\n    integration_s: 300\n    to: weights\n";
    std::fs::write(d.join("p.yaml"), small_pipeline(Some(source))).unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_r2d2"))
        .args(["run", "p.yaml"])
        .current_dir(d)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let started = std::time::Instant::now();
    while job_ids_if_any(&d.join("out")).is_empty() {
        assert!(started.elapsed().as_secs() < 120, "no job written in two minutes");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let kill = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(kill.success());
    let out = child.wait_with_output().unwrap();
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "not stopped cleanly ({}): {err}", out.status);
    assert!(err.contains("interrupted"), "{err}");
    let ids = job_ids_if_any(&d.join("out"));
    assert!(ids.len() < 500, "the run was not stopped");
    let mut names: Vec<String> = std::fs::read_dir(d.join("out")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    let complete: Vec<String> = ids
        .iter()
        .flat_map(|id| ["dirty", "psf", "model", "residual", "image"].iter().flat_map(move |p| [format!("{id}-{p}.fits"), format!("{id}-{p}.png")]).chain([format!("{id}-metrics.json"), format!("{id}-metrics.parquet")]))
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    assert_eq!(names, complete, "partial products or a staging directory left");
}

/// The job ids written in `dir` (by their metrics), none if it does not exist yet.
fn job_ids_if_any(dir: &Path) -> Vec<String> {
    if dir.is_dir() {
        job_ids(dir)
    } else {
        Vec::new()
    }
}

/// Mistakes that used to run anyway, writing nothing or the wrong thing: each is refused by
/// `validate` with the file, the key and what was expected.
#[test]
fn small_configuration_mistakes_are_refused_by_validate() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_small(d, "3", "obs.parquet", &[]);
    let with_source = |source: &str| small_pipeline(Some(&format!("  source:\n    kind: parquet\n{source}    to: weights\n")));
    let onnx = small_pipeline(None).replace("    kind: clean\n    major_cycles: 3\n    components_per_cycle: 200\n", "    kind: onnx\n    series: vla-r2d2-128\n");
    let cases: Vec<(&str, String, Vec<&str>, Vec<&str>)> = vec![
        // The truth is 64 x 64 (the simulated sky): nothing to compare at 128.
        ("truth of another size", with_source("    files: obs.parquet\n    truth: obs.sky.fits\n"), vec!["image.size=128"], vec!["obs.sky.fits", "64 x 64", "128 x 128"]),
        ("no files", with_source("    files: []\n"), vec![], vec!["stages.source.files", "at least one"]),
        // A mask names its key and file; a level that is no level names its key.
        ("mask file missing", small_pipeline(None).replace("    major_cycles: 3\n", "    major_cycles: 3\n    fits_mask: no-mask.fits\n"), vec![], vec!["stages.step.fits_mask", "no-mask.fits"]),
        ("mask file missing, series", onnx.replace("    series: vla-r2d2-128\n", "    series: vla-r2d2-128\n    fits_mask: no-mask.fits\n"), vec![], vec!["stages.step.fits_mask", "no-mask.fits"]),
        ("auto-mask of no level", small_pipeline(None).replace("    major_cycles: 3\n", "    major_cycles: 3\n    auto_mask: -1\n"), vec![], vec!["stages.step.auto_mask", "positive number of noise sigmas", "-1"]),
        ("unknown placeholder", small_pipeline(None).replace("out/{job}", "out/{jobb}"), vec![], vec!["stages.write.prefix", "{jobb}", "{job}"]),
        ("prefix without a file name", small_pipeline(None).replace("out/{job}", "out/"), vec![], vec!["stages.write.prefix", "out/", "file name"]),
        ("size the series cannot take", onnx.clone(), vec!["image.size=100"], vec!["vla-r2d2-128", "multiple of 8", "100"]),
        ("size 0", small_pipeline(None), vec!["image.size=0"], vec!["image.size", "at least 8"]),
        // The operator takes even sizes of at least 8 only, whatever the step.
        ("odd size", small_pipeline(None), vec!["image.size=63"], vec!["image.size = 63", "even image size of at least 8"]),
        ("odd size, CLEAN", small_pipeline(None), vec!["image.size=511"], vec!["image.size = 511", "even image size of at least 8"]),
        ("size under 8", small_pipeline(None), vec!["image.size=6"], vec!["image.size = 6", "even image size of at least 8"]),
        ("robust out of range", small_pipeline(None).replace("robust: 0", "robust: -1e30"), vec![], vec!["line 16, column 5: stages.weights.robust", "from -5 to 5", "-1000000000000000000000000000000"]),
        // What the simulation would refuse, before any job.
        ("declination the VLA never sees", small_pipeline(None).replace("hours: [1]\n", "hours: [1]\n    dec_deg: -90\n"), vec![], vec!["line 11, column 5: stages.source.dec_deg", "-90 deg never rises", "vla-c", "above -56"]),
        ("frequency the readers refuse", small_pipeline(None).replace("hours: [1]\n", "hours: [1]\n    frequency_mhz: 1.0e9\n"), vec![], vec!["line 11, column 5: stages.source.frequency_mhz", "frequencies from 1e6 to 1e13 Hz", "got 1e15 Hz"]),
        ("zero integration time", small_pipeline(None).replace("integration_s: 300", "integration_s: 0"), vec![], vec!["line 11, column 5: stages.source.integration_s", "invalid integration_s: must be a positive number of seconds"]),
        // Named by the stage's key (the parameters' field), not as the command line spells it.
        ("frequency ratio under 1", small_pipeline(None).replace("hours: [1]\n", "hours: [1]\n    frequency_ratio: 0.5\n"), vec![], vec!["line 11, column 5: stages.source.frequency_ratio: invalid frequency_ratio: expected highest/lowest frequency >= 1, got 0.5"]),
        ("flag fraction of 1", small_pipeline(None).replace("hours: [1]\n", "hours: [1]\n    flag_fraction: 1\n"), vec![], vec!["line 11, column 5: stages.source.flag_fraction: invalid flag_fraction: expected a fraction in [0, 1), got 1"]),
        ("unknown configuration", small_pipeline(None).replace("configurations: [c]", "configurations: [q]"), vec![], vec!["line 9, column 5: stages.source.configurations: invalid configurations: expected one of a, b, c, d"]),
        ("right ascension out of range", small_pipeline(None).replace("hours: [1]\n", "hours: [1]\n    ra_deg: 400\n"), vec![], vec!["line 11, column 5: stages.source.ra_deg: invalid ra_deg: 400: expected a right ascension within [0, 360) degrees"]),
        ("negative weighting grid factor", small_pipeline(None).replace("robust: 0\n", "robust: 0\n    grid_factor: -1\n"), vec![], vec!["line 17, column 5: stages.weights.grid_factor: invalid grid_factor: expected a positive number, got -1"]),
        ("prefix too long", small_pipeline(None).replace("out/{job}", &format!("out/{}{{job}}", "x".repeat(250))), vec![], vec!["stages.write.prefix", "file name would have", "255"]),
    ];
    for (what, text, sets, expected) in cases {
        validate_fails(d, &text, &sets, what, expected);
    }
    // A byte-order mark before the first key: valid, and errors keep their lines.
    std::fs::write(d.join("bom.yaml"), format!("\u{feff}{}", small_pipeline(None))).unwrap();
    check(&r2d2(&["validate", "bom.yaml"], d));
    let typo = small_pipeline(None).replace("scheme: briggs", "scheme: brigs");
    std::fs::write(d.join("bom.yaml"), &typo).unwrap();
    let plain = stderr(&r2d2(&["validate", "bom.yaml"], d));
    std::fs::write(d.join("bom.yaml"), format!("\u{feff}{typo}")).unwrap();
    let err = stderr(&r2d2(&["validate", "bom.yaml"], d));
    assert!(err == plain && err.contains("bom.yaml: line 15, column 13") && err.contains("brigs"), "{err}");
    // The series takes multiples of 8 other than its training size.
    std::fs::write(d.join("p.yaml"), onnx).unwrap();
    check(&r2d2(&["validate", "p.yaml", "--set", "image.size=72"], d));
    // WSClean's -name with a trailing slash names no file.
    let out = r2d2(&["image", "obs.parquet", "--size", "64", "--step", "clean", "--name", "res/"], d);
    assert!(!out.status.success() && stderr(&out).contains("file name"), "{}", stderr(&out));
    assert!(!d.join("res-dirty.fits").exists() && !d.join("res").exists());
}

fn job_ids(dir: &Path) -> Vec<String> {
    let mut ids: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().to_string_lossy().strip_suffix("-metrics.json").map(str::to_string))
        .collect();
    ids.sort();
    ids
}

/// One file split into jobs by time windows (Parquet) and by channel (Arrow IPC on stdin).
#[test]
fn split_by_time_windows_and_channels() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_small(d, "6", "a.parquet", &["--nfreq", "2", "--freq-ratio", "1.3"]);
    let (schema, batches) = parquet_batches(&d.join("a.parquet"), 700);
    let times: Vec<f64> = batches
        .iter()
        .flat_map(|b| b.column_by_name("time").unwrap().as_any().downcast_ref::<arrow::array::Float64Array>().unwrap().values().to_vec())
        .collect();
    let (t0, t1) = times.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &t| (a.min(t), b.max(t)));
    let windows = ((t1 - t0) / 1200.0).floor() as usize + 1;
    assert!(windows >= 3, "a 1 h track gives at least 3 windows of 20 min");

    let source = "  source:\n    kind: parquet\n    files: a.parquet\n    split_by: {column: time, window: 1200}\n    to: weights\n";
    std::fs::write(d.join("time.yaml"), small_pipeline(Some(source)).replace("out/{job}", "time/{job}")).unwrap();
    check(&r2d2(&["run", "time.yaml"], d));
    let expected: Vec<String> = (0..windows).map(|k| format!("a-t{k:03}")).collect();
    assert_eq!(job_ids(&d.join("time")), expected);

    let (stream, _) = ipc_stream(&schema, &batches);
    let source = ipc_source("-", "    id: a\n    split_by:\n      column: frequency\n");
    std::fs::write(d.join("chan.yaml"), small_pipeline(Some(&source)).replace("out/{job}", "chan/{job}")).unwrap();
    check(&r2d2_stdin(&["run", "chan.yaml"], d, &stream));
    assert_eq!(job_ids(&d.join("chan")), ["a-ch00", "a-ch01"]);
    // The two channels see the sky through different uv coverages: different dirty images.
    let dirty = |id: &str| read_image(&d.join(format!("chan/{id}-dirty.fits"))).unwrap().data;
    assert_ne!(dirty("a-ch00"), dirty("a-ch01"));

    // An unknown column: before any work (Parquet), or when the stream's schema arrives (IPC),
    // the error names the YAML key and the available columns.
    let bad = small_pipeline(Some("  source:\n    kind: parquet\n    files: a.parquet\n    split_by: {column: tim, window: 600}\n    to: weights\n"));
    std::fs::write(d.join("bad.yaml"), bad).unwrap();
    let out = r2d2(&["validate", "bad.yaml"], d);
    assert!(!out.status.success());
    let err = stderr(&out);
    for e in ["bad.yaml", "line 8", "stages.source.split_by.column", "`tim`", "columns: u, v, w, frequency"] {
        assert!(err.contains(e), "'{e}' missing from: {err}");
    }
    std::fs::write(d.join("bad2.yaml"), small_pipeline(Some(&ipc_source("-", "    split_by: {column: chan}\n")))).unwrap();
    let out = r2d2_stdin(&["run", "bad2.yaml"], d, &stream);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(err.contains("stages.source.split_by.column") && err.contains("`chan`") && err.contains("time"), "{err}");
    let out = r2d2(&["validate", "bad2.yaml", "--set", "source.split_by.window=-5"], d);
    assert!(stderr(&out).contains("split_by.window") && stderr(&out).contains("positive"), "{}", stderr(&out));
}

/// The jobs of one split keep their numbers and share one grid (issue 56.8, 56.22): a channel
/// flagged throughout makes no job and is named in a warning, the channels after it keep
/// theirs (each product's CRVAL3 is its channel's frequency); time windows of A and C
/// configurations, whose longest baselines differ tenfold, share one pixel size.
#[test]
fn split_jobs_keep_their_numbers_and_share_one_grid() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_small(d, "7", "f.parquet", &["--nfreq", "4", "--freq-ratio", "1.3"]);
    let flag = "import pyarrow as pa, pyarrow.parquet as pq, numpy as np\n\
                t = pq.read_table('f.parquet')\n\
                f = t['frequency'].to_numpy()\n\
                flag = t['flag'].to_numpy(zero_copy_only=False) | (f == np.unique(f)[1])\n\
                pq.write_table(t.set_column(t.schema.get_field_index('flag'), 'flag', pa.array(flag)), 'f.parquet')";
    let out = Command::new("python3").args(["-c", flag]).current_dir(d).output().expect("python3 runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let source = "  source:\n    kind: parquet\n    files: f.parquet\n    split_by: {column: frequency}\n    to: weights\n";
    std::fs::write(d.join("chan.yaml"), small_pipeline(Some(source)).replace("out/{job}", "chan/{job}")).unwrap();
    let out = r2d2(&["run", "chan.yaml"], d);
    check(&out);
    assert_eq!(job_ids(&d.join("chan")), ["f-ch00", "f-ch02", "f-ch03"]);
    let err = stderr(&out);
    assert!(err.contains("WARN") && err.contains("f.parquet: ch01 (`frequency` ") && err.contains("has no sample left to image"), "{err}");
    let channels: Vec<f64> = (0..4).map(|k| 1.4e9 * (1.0 + 0.3 * k as f64 / 3.0)).collect();
    for (id, k) in [("f-ch00", 0), ("f-ch02", 2), ("f-ch03", 3)] {
        let wcs = read_image(&d.join(format!("chan/{id}-dirty.fits"))).unwrap().wcs.unwrap();
        let freq = wcs.freq_hz.unwrap();
        let nearest = (0..4).min_by(|&a, &b| (channels[a] - freq).abs().total_cmp(&(channels[b] - freq).abs())).unwrap();
        assert_eq!(nearest, k, "{id}: CRVAL3 {freq} Hz is channel {nearest} of {channels:?}");
    }

    simulate_small(d, "8", "ac.parquet", &["--configs", "a,c", "--hours", "1,1"]);
    let source = "  source:\n    kind: parquet\n    files: ac.parquet\n    split_by: {column: time, window: 3600}\n    to: weights\n";
    std::fs::write(d.join("time.yaml"), small_pipeline(Some(source)).replace("out/{job}", "time/{job}")).unwrap();
    check(&r2d2(&["run", "time.yaml"], d));
    let ids = job_ids(&d.join("time"));
    assert!(ids.len() >= 2, "{ids:?}");
    let pixels: Vec<f64> = ids.iter().map(|id| read_image(&d.join(format!("time/{id}-dirty.fits"))).unwrap().wcs.unwrap().pixel_deg).collect();
    assert!(pixels.iter().all(|&p| p == pixels[0]), "{ids:?}: pixel sizes {pixels:?}");
}

/// Progress bars draw only on a terminal: with stderr captured there is no bar, and `-q`
/// leaves stderr empty on success.
#[test]
fn no_progress_output_when_stderr_is_not_a_terminal() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("p.yaml"), small_pipeline(None)).unwrap();
    let out = r2d2(&["run", "p.yaml"], d);
    check(&out);
    let err = stderr(&out);
    assert!(err.contains("job(s) in"), "log lines still come: {err}");
    assert!(!err.contains('\r') && !err.contains('\u{1b}'), "terminal control characters: {err:?}");
    let out = r2d2(&["-q", "run", "p.yaml", "--set", "write.prefix=q/{job}"], d);
    check(&out);
    assert!(out.stderr.is_empty(), "{}", stderr(&out));
}
