//! Tables read in passes (issue 25): a job of a file is read again at each pass over its
//! samples (weighting's density, gridding, and the residual update through the operator
//! where its samples are not held), and gives what the same table held in memory gives; with
//! the w-term, the residual update's w-aware Toeplitz form needs one pass.

mod common;
use common::*;
use std::path::Path;

/// A 64 x 64 pipeline of `obs.parquet` read in batches of 300 rows, with `source` extra keys
/// (a split makes the job held in memory), the gridder's `grid` keys and `scheme` weighting;
/// products at `<job>-<name>`.
fn pipeline(name: &str, source: &str, grid: &str, scheme: &str) -> String {
    format!(
        "name: passes\nimage:\n  size: 64\nstages:\n  read:\n    kind: parquet\n    files: obs.parquet\n    batch_rows: 300\n{source}    to: weights\n  weights:\n    kind: weighting\n    scheme: {scheme}\n    to: grid\n  grid:\n    kind: gridder\n{grid}    to: step\n  step:\n    kind: clean\n    major_cycles: 3\n    components_per_cycle: 100\n    to: update\n  update:\n    kind: residual\n    to: step\n    done: write\n  write:\n    kind: writer\n    prefix: \"{{job}}-{name}\"\n"
    )
}

fn run(dir: &Path, name: &str, yaml: &str) -> String {
    std::fs::write(dir.join(format!("{name}.yaml")), yaml).unwrap();
    let out = r2d2(&["run", &format!("{name}.yaml")], dir);
    check(&out);
    stderr(&out)
}

/// Largest difference of two products relative to the first's peak.
fn relative(dir: &Path, a: &str, b: &str) -> f64 {
    let (a, b) = (read(&dir.join(a)), read(&dir.join(b)));
    max_diff(&a, &b) / max_abs(&a)
}

#[test]
fn a_table_read_in_passes_images_as_the_same_table_held() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    observation(dir);
    // Held: a split by frequency (one channel) reads the table into memory (job obs-ch00).
    let held_source = "    split_by: {column: frequency}\n";
    for scheme in ["natural", "briggs", "uniform"] {
        // Coplanar: gridded in chunks of 257 samples as read, against one pass over the held table.
        let coplanar = "    w_term: off\n    chunk_rows: 257\n";
        let log = run(dir, &format!("streamed-{scheme}"), &pipeline(&format!("streamed-{scheme}"), "", coplanar, scheme));
        // A decoded copy unless the temporary directory is on tmpfs.
        assert!(log.contains("read from a decoded copy of obs.parquet at each pass") || log.contains("read from obs.parquet at each pass"), "{log}");
        assert_eq!(log.contains("reads the table once more for the density"), scheme != "natural", "{log}");
        run(dir, &format!("held-{scheme}"), &pipeline(&format!("held-{scheme}"), held_source, "    w_term: off\n", scheme));
        for product in ["dirty", "psf", "model", "residual"] {
            let d = relative(dir, &format!("obs-ch00-held-{scheme}-{product}.fits"), &format!("obs-streamed-{scheme}-{product}.fits"));
            assert!(d < 1e-9, "{scheme} {product}: {d:e}");
        }
    }
    // With the w-term and the exact round trip (method: nufft): the operator planned per
    // chunk and applied at each update, reading the file again (hold_mb 0), against one
    // operator of the held table.
    let nufft = |yaml: String| yaml.replace("    kind: residual\n", "    kind: residual\n    method: nufft\n");
    let streamed = run(dir, "wstream", &nufft(pipeline("wstream", "", "    w_term: on\n    hold_mb: 0\n    chunk_rows: 500\n", "briggs")));
    assert!(streamed.contains("reads the") && streamed.contains("at each residual update") && streamed.contains("obs.parquet"), "{streamed}");
    let held = run(dir, "wheld", &nufft(pipeline("wheld", "", "    w_term: on\n", "briggs")));
    assert!(held.contains("the operator holds the"), "{held}");
    // The default convolution form: the w-aware Toeplitz form built in the one gridding pass,
    // in chunks, the samples not read again.
    let toeplitz = run(dir, "wtoeplitz", &pipeline("wtoeplitz", "", "    w_term: on\n    chunk_rows: 500\n", "briggs"));
    assert!(toeplitz.contains("the residual update convolves with the kernels of") && !toeplitz.contains("at each residual update"), "{toeplitz}");
    // Where the kernels would take more than kernel_mb and more than the samples held, the
    // residual update runs through the operator (here reading the file again: hold_mb).
    let small = run(dir, "wsmall", &pipeline("wsmall", "", "    w_term: on\n    hold_mb: 0.001\n    kernel_mb: 0.001\n", "briggs"));
    assert!(small.contains("w-aware Toeplitz form") && small.contains("would take") && small.contains("at each residual update"), "{small}");
    for product in ["model", "residual"] {
        let d = relative(dir, &format!("obs-wheld-{product}.fits"), &format!("obs-wsmall-{product}.fits"));
        assert!(d < 1e-5, "w-term through the operator {product}: {d:e}");
    }
    let dirty_peak = max_abs(&read(&dir.join("obs-wheld-dirty.fits")));
    for product in ["dirty", "psf", "model", "residual"] {
        let (held, streamed, toeplitz) = (read(&dir.join(format!("obs-wheld-{product}.fits"))), read(&dir.join(format!("obs-wstream-{product}.fits"))), read(&dir.join(format!("obs-wtoeplitz-{product}.fits"))));
        // Each chunk's w-planes are its own: equal to the NUFFT's accuracy.
        let d = max_diff(&held, &streamed) / max_abs(&held);
        assert!(d < 1e-5, "w-term streamed {product}: {d:e}");
        // The Toeplitz form is D to the NUFFT's accuracy (1e-6 of D x, whose scale is the
        // dirty image's): within ten times that of the dirty image's peak. (The residual's own
        // peak is a few hundredths of it after CLEAN.)
        let d = max_diff(&held, &toeplitz) / dirty_peak;
        assert!(d < 1e-5, "w-term Toeplitz form {product}: {d:e}");
    }
    // The 2N PSF of the streamed gridding is that of the held table's (the restored image
    // and CLEAN use it): the restoring beam in the headers agrees.
    let bmaj = |name: &str| -> f64 {
        let bytes = std::fs::read(dir.join(name)).unwrap();
        let header = String::from_utf8_lossy(&bytes[..bytes.len().min(2880 * 4)]).into_owned();
        let card = header.as_bytes().chunks(80).map(|c| String::from_utf8_lossy(c).into_owned()).find(|c| c.starts_with("BMAJ    =")).expect("BMAJ");
        card[10..].split('/').next().unwrap().trim().parse().unwrap()
    };
    for other in ["obs-wstream-image.fits", "obs-wtoeplitz-image.fits"] {
        let (a, b) = (bmaj("obs-wheld-image.fits"), bmaj(other));
        assert!((a - b).abs() < 1e-6 * a, "{other}: {a} {b}");
    }
}

/// A dirty-image pipeline of `obs.parquet` (64 x 64, Briggs 0): `source` extra keys, the
/// gridder's `grid` keys, and a writer of the dirty image and the PSF at `<job>-<name>`.
fn dirty_pipeline(name: &str, source: &str, grid: &str) -> String {
    format!(
        "name: dirty\nimage:\n  size: 64\nstages:\n  read:\n    kind: parquet\n    files: obs.parquet\n    batch_rows: 300\n{source}    to: weights\n  weights:\n    kind: weighting\n    scheme: briggs\n    to: grid\n  grid:\n    kind: gridder\n{grid}    to: write\n  write:\n    kind: writer\n    products: dirty\n    prefix: \"{{job}}-{name}\"\n"
    )
}

/// The files in `dir` whose names start with `prefix`, sorted.
fn files_of(dir: &Path, prefix: &str) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).filter(|n| n.starts_with(prefix)).collect();
    names.sort();
    names
}

/// `r2d2 dirty` is `Engine::dirty`: the source, weighting and gridder stages `r2d2 image` runs,
/// with no step. A table file is read in passes, never held, and with the w-term too no
/// operator and no kernels of `D` are made (each chunk is gridded through its own w-planes);
/// its images are those of the same table held in memory (a split by frequency holds it) and
/// of the table streamed in chunks of 257 samples, through pipelines of the same stages whose
/// writer writes `products: dirty`. Only the dirty image and the PSF are written.
#[test]
fn dirty_reads_a_table_in_passes_as_image_does() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    observation(dir);
    for w_term in ["off", "on"] {
        let name = format!("cli-{w_term}");
        let out = r2d2(&["dirty", "obs.parquet", "--size", "64", "--w-term", w_term, "--name", &name], dir);
        check(&out);
        let log = stderr(&out);
        assert!(log.contains("read from a decoded copy of obs.parquet at each pass") || log.contains("read from obs.parquet at each pass"), "{log}");
        assert!(!log.contains("holds the") && !log.contains("residual update") && !log.contains("again from"), "no form of D: {log}");
        assert_eq!(log.contains("the w-term is corrected by w-gridding"), w_term == "on", "{log}");
        assert_eq!(files_of(dir, &name), [format!("{name}-dirty.fits"), format!("{name}-psf.fits")]);
        let grid = format!("    w_term: {w_term}\n");
        run(dir, &format!("held-{w_term}"), &dirty_pipeline(&format!("held-{w_term}"), "    split_by: {column: frequency}\n", &grid));
        let chunked = format!("{grid}    chunk_rows: 257\n");
        let log = run(dir, &format!("chunked-{w_term}"), &dirty_pipeline(&format!("chunked-{w_term}"), "", &chunked));
        assert!(!log.contains("holds the") && !log.contains("residual update"), "{log}");
        // The writer's previews (on by default), no metrics.
        let chunked_files = ["dirty.fits", "dirty.png", "psf.fits", "psf.png"].map(|p| format!("obs-chunked-{w_term}-{p}"));
        assert_eq!(files_of(dir, &format!("obs-chunked-{w_term}")), chunked_files);
        // Coplanar, the sums in another order; with the w-term, each chunk's w-planes its own.
        let tolerance = if w_term == "off" { 1e-9 } else { 1e-5 };
        for product in ["dirty", "psf"] {
            let cli = format!("{name}-{product}.fits");
            let d = relative(dir, &format!("obs-ch00-held-{w_term}-{product}.fits"), &cli);
            assert!(d < 1e-9, "{w_term} {product}, held: {d:e}");
            let d = relative(dir, &format!("obs-chunked-{w_term}-{product}.fits"), &cli);
            assert!(d < tolerance, "{w_term} {product}, chunks of 257: {d:e}");
        }
    }
}

/// A 512 x 512 field where the w-term turns phases by a tenth of a radian: with the samples held
/// and the w-aware Toeplitz form above kernel_mb, the residual update is a Taylor series in `w` of
/// the PSF convolution, checked against the operator on the dirty image, and the job's products
/// are those of the exact round trip through the operator at every update.
#[test]
fn a_small_w_term_updates_the_residual_by_a_taylor_series_as_the_operator_does() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "2", "--integration-s", "300", "--size", "512", "--seed", "5", "--out", "obs.parquet"], dir));
    let taylor = pipeline("taylor", "", "    w_term: on
    kernel_mb: 150
", "briggs").replace("size: 64", "size: 512");
    let log = run(dir, "taylor", &taylor);
    assert!(log.contains("a Taylor series in w of order") && log.contains("the final residual through the operator"), "{log}");
    let w_term = taylor_w_term(dir);
    assert!(w_term["taylor_order"].as_u64().is_some_and(|o| (1..=3).contains(&o)), "{w_term}");
    assert!(w_term["taylor_deviation"].as_f64().is_some_and(|d| d <= 1e-5) && w_term["max_phase_rad"].as_f64().unwrap() > 1e-2, "{w_term}");
    let exact = taylor.replace("prefix: \"{job}-taylor\"", "prefix: \"{job}-exact\"").replace("    kind: residual\n", "    kind: residual\n    method: nufft\n");
    run(dir, "exact", &exact);
    let coplanar = taylor.replace("prefix: \"{job}-taylor\"", "prefix: \"{job}-flat\"").replace("w_term: on", "w_term: off");
    run(dir, "flat", &coplanar);
    assert_taylor_is_the_exact_update(dir);
    // A final CLEAN after the loop: its cycles apply the Taylor series as the updates did, and
    // the residual it writes is the operator's; its products are those of the final CLEAN
    // through the operator at every cycle (method: nufft). Two major cycles: this field's
    // CLEAN does not converge in 20, and so many cycles of both signs amplify any difference
    // (1e-8 in the flux they start from) into another path.
    let with_final_clean = |yaml: &str, name: &str| {
        yaml.replace("prefix: \"{job}-taylor\"", &format!("prefix: \"{{job}}-{name}\""))
            .replace("    done: write\n", "    done: final\n  final:\n    kind: final_clean\n    major_cycles: 2\n    to: write\n")
    };
    let log = run(dir, "taylor-final", &with_final_clean(&taylor, "taylor-final"));
    assert!(log.contains("the final CLEAN's residual through the operator: the Taylor series in w was"), "{log}");
    let log = run(dir, "exact-final", &with_final_clean(&exact.replace("{job}-exact", "{job}-taylor"), "exact-final"));
    assert!(!log.contains("the final CLEAN's residual through the operator"), "{log}");
    let dirty_peak = max_abs(&read(&dir.join("obs-exact-dirty.fits")));
    for product in ["model", "residual"] {
        let d = max_diff(&read(&dir.join(format!("obs-exact-final-{product}.fits"))), &read(&dir.join(format!("obs-taylor-final-{product}.fits")))) / dirty_peak;
        assert!(d < 1e-5, "final CLEAN's {product}: {d:e}");
    }
    let d = max_diff(&read(&dir.join("obs-taylor-final-model.fits")), &read(&dir.join("obs-taylor-model.fits"))) / dirty_peak;
    assert!(d > 1e-4, "the final CLEAN changed the model: {d:e}");
    // The figures say the written residual's ratio (the operator's). On this field the series'
    // ratio is within 1e-9 of it, so this checks what the figures are taken from, not the form.
    for name in ["taylor", "taylor-final"] {
        let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join(format!("obs-{name}-metrics.json"))).unwrap()).unwrap();
        let norm = |product: &str| read(&dir.join(format!("obs-{name}-{product}.fits"))).iter().map(|v| v * v).sum::<f64>().sqrt();
        let written = norm("residual") / norm("dirty");
        let last = metrics["iterations"].as_array().unwrap().last().unwrap()["residual_ratio"].as_f64().unwrap();
        for (what, ratio) in [("final", metrics["final"]["residual_ratio"].as_f64().unwrap()), ("last iteration", last)] {
            assert!((ratio / written - 1.0).abs() < 1e-6, "{name}: {what} ratio {ratio:e} against the written residual's {written:e}");
        }
    }
}

/// `-metrics.json` `settings.w_term` of the job's `taylor` products.
fn taylor_w_term(dir: &Path) -> serde_json::Value {
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("obs-taylor-metrics.json")).unwrap()).unwrap();
    metrics["settings"]["w_term"].clone()
}

/// The `taylor` products are the `exact` ones (the operator at every update) to the NUFFT's
/// accuracy, and the `flat` (coplanar) residual differs by more: the update's w-term is told apart.
fn assert_taylor_is_the_exact_update(dir: &Path) {
    let dirty_peak = max_abs(&read(&dir.join("obs-exact-dirty.fits")));
    for product in ["dirty", "model", "residual"] {
        let d = max_diff(&read(&dir.join(format!("obs-exact-{product}.fits"))), &read(&dir.join(format!("obs-taylor-{product}.fits")))) / dirty_peak;
        assert!(d < 1e-5, "{product}: {d:e}");
    }
    let d = max_diff(&read(&dir.join("obs-exact-residual.fits")), &read(&dir.join("obs-flat-residual.fits"))) / dirty_peak;
    assert!(d > 1e-4, "coplanar: {d:e}");
}

/// The same where the samples take more than hold_mb and are read again from their file,
/// while the series' kernels fit in kernel_mb: each kernel is gridded in a pass of its own, the
/// updates no longer read the file, and the products are those of the exact round trip.
#[test]
fn a_small_w_term_of_samples_read_from_their_file_updates_the_residual_by_a_taylor_series() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    // 4e4 samples (about 2.3 MB held as `D` alone); the kernels of order 3 at 64 x 64 take
    // about 2 MB, and the w-aware Toeplitz form (which the gridder prefers) more than the
    // samples held.
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "1", "--integration-s", "30", "--size", "64", "--seed", "3", "--out", "obs.parquet"], dir));
    let grid = "    w_term: on\n    hold_mb: 1.5\n    kernel_mb: 2.5\n    chunk_rows: 5000\n";
    let log = run(dir, "taylor", &pipeline("taylor", "", grid, "briggs"));
    assert!(log.contains("no w-aware Toeplitz form for the residual update"), "{log}");
    assert!(log.contains("a Taylor series in w of order") && log.contains("again from") && log.contains("for the final residual"), "{log}");
    assert!(!log.contains("at each residual update"), "{log}");
    let w_term = taylor_w_term(dir);
    assert!(w_term["taylor_order"].as_u64().is_some_and(|o| (1..=3).contains(&o)), "{w_term}");
    let nufft = |yaml: String| yaml.replace("    kind: residual\n", "    kind: residual\n    method: nufft\n");
    let exact = run(dir, "exact", &nufft(pipeline("exact", "", grid, "briggs")));
    assert!(exact.contains("at each residual update"), "{exact}");
    run(dir, "flat", &pipeline("flat", "", &grid.replace("w_term: on", "w_term: off"), "briggs"));
    assert_taylor_is_the_exact_update(dir);
}

#[test]
fn chunk_and_hold_sizes_are_checked() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    observation(dir);
    for (grid, expected) in [("    chunk_rows: 0\n", "chunk_rows"), ("    hold_mb: -1\n", "hold_mb"), ("    kernel_mb: -1\n", "kernel_mb")] {
        std::fs::write(dir.join("bad.yaml"), pipeline("bad", "", grid, "natural")).unwrap();
        let out = r2d2(&["run", "bad.yaml"], dir);
        assert_fails_with(&out, "a bad gridder size", &[expected]);
    }
}

/// One observation kept in parts, each gridded on its own and the images summed (what Dask
/// workers do with the parts they hold, made here in this process): the products of the
/// whole table imaged at once, coplanar to the float rounding of the sums, with the w-term to
/// the NUFFT's accuracy (each part's w-planes are its own).
#[test]
fn an_observation_in_parts_images_as_the_whole_table() {
    use r2d2_imaging::parts::{open_source, LocalParts, PartedObservation, VisSource, VisSummary};
    use r2d2_imaging::vis::OpenOptions;
    use r2d2_imaging::{Engine, EngineOptions, ImageRequest, Observation};
    use std::sync::Arc;
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    observation(dir);
    let path = dir.join("obs.parquet");
    let (meta, source) = open_source(&path, &OpenOptions::default()).unwrap();
    let vis = source.read_all().unwrap();
    // Three parts of unequal sizes, interleaved (as channels or time ranges of one track).
    let group: Vec<usize> = (0..vis.len()).map(|k| (k * 7 / 3) % 3).collect();
    let parts: Vec<VisSource> = vis.partition(&group, 3).into_iter().map(|p| VisSource::Held(Arc::new(p))).collect();
    let described: Vec<(String, _, VisSummary)> = parts.iter().enumerate().map(|(k, p)| (format!("part{k}"), meta.clone(), p.summary())).collect();
    let engine = Engine::new(EngineOptions { threads: 2, onnx_runtime: None }).unwrap();
    for w_term in ["off", "on"] {
        let mut params = ImageRequest::default();
        (params.grid.size, params.step.step, params.step.iterations) = (SIZE, "clean".into(), Some(3));
        (params.grid.weighting, params.grid.robust) = (Some("briggs".into()), Some(0.0));
        params.grid.w_term = r2d2_imaging::imaging::WTermMode::from_name(w_term).unwrap();
        let whole = engine.image(path.as_path(), &params).unwrap();
        let passes = Box::new(LocalParts { parts: parts.clone() });
        let parted = engine.image(Observation::Parts(PartedObservation::new("obs", &described, passes).unwrap()), &params).unwrap();
        let tolerance = if w_term == "off" { 1e-6 } else { 1e-5 };
        for (name, a, b) in [
            ("dirty", &whole.dirty, &parted.dirty),
            ("psf", &whole.psf, &parted.psf),
            ("model", whole.model.as_ref().unwrap(), parted.model.as_ref().unwrap()),
            ("residual", whole.residual.as_ref().unwrap(), parted.residual.as_ref().unwrap()),
        ] {
            let (a, b): (Vec<f64>, Vec<f64>) = (a.iter().map(|&x| x as f64).collect(), b.iter().map(|&x| x as f64).collect());
            let d = max_diff(&a, &b) / max_abs(&a);
            assert!(d < tolerance, "w_term {w_term}, {name}: {d:e}");
        }
        // The header is the same; the fitted beam to the rounding of its PSF's sums.
        assert_eq!(whole.header.len(), parted.header.len());
        for ((key, a), (key_b, b)) in whole.header.iter().zip(&parted.header) {
            assert_eq!(key, key_b);
            match key.as_str() {
                "BMAJ" | "BMIN" | "BPA" => {
                    let (a, b): (f64, f64) = (a.parse().unwrap(), b.parse().unwrap());
                    assert!((a - b).abs() <= 1e-6 * a.abs(), "w_term {w_term}, {key}: {a} {b}");
                }
                _ => assert_eq!(a, b, "w_term {w_term}, {key}"),
            }
        }
    }
    // A part that holds other samples when gridded than when first read (written to
    // meanwhile) stops the job, and nothing is imaged.
    let shrunk = vec![parts[0].clone(), parts[1].clone(), VisSource::Held(Arc::new(Default::default()))];
    let changed = PartedObservation::new("obs", &described, Box::new(LocalParts { parts: shrunk })).unwrap();
    let mut clean = ImageRequest::default();
    (clean.grid.size, clean.step.step) = (SIZE, "clean".into());
    let e = engine.image(Observation::Parts(changed), &clean).unwrap_err().to_string();
    assert!(e.contains("where their first reading found") && e.contains("written to meanwhile"), "{e}");
    // A part of another observation (another phase centre) is refused, naming it.
    let mut other = meta.clone();
    other.phase_centre_dec_deg += 1.0;
    let mixed = vec![described[0].clone(), ("elsewhere.parquet".to_string(), other, described[1].2.clone())];
    let e = PartedObservation::new("obs", &mixed, Box::new(LocalParts { parts: parts[..2].to_vec() })).err().unwrap().to_string();
    assert!(e.contains("elsewhere.parquet") && e.contains("another observation"), "{e}");
}
