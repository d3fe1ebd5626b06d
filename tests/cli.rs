//! End-to-end tests of the `r2d2` binary: simulate -> dirty -> metrics, positions checked with
//! astropy (an independent WCS implementation), and errors for bad input.

use num_complex::Complex64;
use r2d2_imaging::fits::read_image;
use r2d2_imaging::simulate::{frequency_channels, sample_coverage, ObservationSpec};
use r2d2_imaging::vis::{write_parquet, ObservationMeta, VisTable, SPEED_OF_LIGHT};
use std::path::Path;
use std::process::{Command, Output};

fn r2d2(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_r2d2")).args(args).current_dir(dir).output().expect("r2d2 runs")
}

fn check(out: &Output) {
    assert!(
        out.status.success(),
        "r2d2 failed: {}\nstdout: {}\nstderr: {}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

fn text(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

fn argmax(v: &[f64]) -> usize {
    v.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap().0
}

#[test]
fn simulate_then_dirty_writes_wsclean_style_products() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(
        &[
            "simulate", "--sky", "procedural:3", "--configs", "c,d", "--hours", "2,1", "--dec", "30", "--dr", "1000",
            "--size", "128", "--integration-s", "120", "--nfreq", "2", "--freq-ratio", "1.5", "--flag-fraction", "0.1",
            "--seed", "3", "--out", "obs.parquet",
        ],
        d,
    ));
    assert!(d.join("obs.sky.fits").exists());
    check(&r2d2(&["dirty", "obs.parquet", "--size", "128", "--name", "obs"], d));
    let dirty = read_image(&d.join("obs-dirty.fits")).unwrap();
    let psf = read_image(&d.join("obs-psf.fits")).unwrap();
    assert_eq!((dirty.nx, dirty.ny), (128, 128));
    assert_eq!(dirty.unit.as_deref(), Some("JY/BEAM"));
    // PSF: peak exactly 1 (to float32) at (N/2, N/2).
    let peak = argmax(&psf.data);
    assert_eq!((peak % 128, peak / 128), (64, 64));
    assert!((psf.data[peak] - 1.0).abs() < 1e-6);
    // Same WCS as the sky model: the dirty image is of the sky that was simulated.
    let sky = read_image(&d.join("obs.sky.fits")).unwrap();
    let (ws, wd) = (sky.wcs.unwrap(), dirty.wcs.unwrap());
    assert_eq!((ws.ra_deg, ws.dec_deg), (wd.ra_deg, wd.dec_deg));
    assert!((ws.pixel_deg / wd.pixel_deg - 1.0).abs() < 1e-9);
    // The dirty image correlates with the sky it came from.
    let corr: f64 = sky.data.iter().zip(&dirty.data).map(|(a, b)| a * b).sum::<f64>()
        / (sky.data.iter().map(|a| a * a).sum::<f64>().sqrt() * dirty.data.iter().map(|a| a * a).sum::<f64>().sqrt());
    assert!(corr > 0.3, "dirty image barely correlates with the sky: {corr}");
    // A name whose product would be the input, or lie inside an input MS, is refused before
    // anything is written (the engine's check, which `r2d2 image` makes too, saying which);
    // the input is as it was.
    let table = std::fs::read(d.join("obs.parquet")).unwrap();
    std::fs::copy(d.join("obs.parquet"), d.join("t-dirty.fits")).unwrap();
    let out = r2d2(&["dirty", "t-dirty.fits", "--size", "128", "--name", "t"], d);
    assert!(!out.status.success() && text(&out).contains("the product t-dirty.fits would replace the input t-dirty.fits"), "{}", text(&out));
    assert_eq!(std::fs::read(d.join("t-dirty.fits")).unwrap(), table, "the input is untouched");
    assert!(!d.join("t-psf.fits").exists(), "nothing written");
    check(&r2d2(&["convert", "obs.parquet", "obs.ms"], d));
    let out = r2d2(&["dirty", "obs.ms", "--size", "128", "--name", "obs.ms/table"], d);
    assert!(!out.status.success() && text(&out).contains("would lie inside the input obs.ms"), "{}", text(&out));
    assert!(!d.join("obs.ms/table-dirty.fits").exists() && !d.join("obs.ms/table-psf.fits").exists(), "nothing written into the MS");

    let metrics = r2d2(&["metrics", "--truth", "obs.sky.fits", "--estimate", "obs.sky.fits", "--dr", "1000"], d);
    check(&metrics);
    let json: serde_json::Value = serde_json::from_slice(&metrics.stdout).unwrap();
    assert!(json["snr"].is_null() || json["snr"].as_f64().unwrap() > 100.0, "{json}");
}

#[test]
fn simulation_is_reproducible_from_its_seed() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let args = |out: &'static str, seed: &'static str| {
        vec![
            "simulate", "--configs", "d", "--hours", "1", "--size", "64", "--integration-s", "300", "--seed", seed,
            "--out", out,
        ]
    };
    check(&r2d2(&args("a.parquet", "11"), d));
    check(&r2d2(&args("b.parquet", "11"), d));
    check(&r2d2(&args("c.parquet", "12"), d));
    let read = |p: &str| std::fs::read(d.join(p)).unwrap();
    assert_eq!(read("a.parquet"), read("b.parquet"), "same seed, different files");
    assert_ne!(read("a.parquet"), read("c.parquet"));
    assert_eq!(read("a.sky.fits"), read("b.sky.fits"));
}

/// One VLA configuration observed for some hours at 1.4 GHz, one channel, nothing flagged, the
/// coverage not rotated.
fn vla_at_1_4_ghz(configuration: (char, f64), dec_deg: f64, integration_s: f64) -> ObservationSpec {
    ObservationSpec {
        telescope: "vla".into(),
        configurations: vec![(configuration.0.to_string(), configuration.1)],
        dec_deg,
        integration_s,
        frequencies_hz: frequency_channels(1.4e9, 1, 1.0).unwrap(),
        flag_fraction: 0.0,
        random_rotation: false,
        seed: 1,
    }
}

/// A point source at a known RA/Dec offset must peak on the pixel astropy assigns to it.
#[test]
fn point_source_lands_on_the_pixel_astropy_gives_its_position() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ra0, dec0) = (150.0f64, 60.0f64);
    let spec = vla_at_1_4_ghz(('b', 4.0), dec0, 60.0);
    let cov = sample_coverage(&spec).unwrap();
    let pixel_deg = 1.0 / (1.5 * 2.0 * cov.max_uv()) * 180.0 / std::f64::consts::PI;
    // Source 20.3 pixels east and 11.2 pixels north of the phase centre, in true angle.
    let (ra_s, dec_s) = (ra0 + 20.3 * pixel_deg / dec0.to_radians().cos(), dec0 + 11.2 * pixel_deg);
    let (a, d0, a0) = (ra_s.to_radians(), dec_s.to_radians(), ra0.to_radians());
    let l = d0.cos() * (a - a0).sin();
    let m = d0.sin() * dec0.to_radians().cos() - d0.cos() * dec0.to_radians().sin() * (a - a0).cos();
    let vis: Vec<Complex64> = (0..cov.len())
        .map(|k| {
            let scale = cov.frequency_hz[k] / SPEED_OF_LIGHT;
            let (u, v) = (cov.u_m[k] * scale, cov.v_m[k] * scale);
            Complex64::from_polar(1.0, 2.0 * std::f64::consts::PI * (u * l + v * m))
        })
        .collect();
    let n = cov.len();
    let table = VisTable {
        u_m: cov.u_m,
        v_m: cov.v_m,
        w_m: cov.w_m,
        frequency: cov.frequency_hz,
        vis,
        weight: vec![1.0; n],
        ..Default::default()
    };
    write_parquet(&d.join("point.parquet"), &table, &ObservationMeta::new(ra0, dec0, "VLA")).unwrap();
    check(&r2d2(&["dirty", "point.parquet", "--size", "128", "--weighting", "uniform", "--name", "point"], d));
    let dirty = read_image(&d.join("point-dirty.fits")).unwrap();
    let peak = argmax(&dirty.data);
    let (px, py) = (peak % dirty.nx, peak / dirty.nx);

    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/world_to_pixel.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(d.join("point-dirty.fits"))
        .arg(ra_s.to_string())
        .arg(dec_s.to_string())
        .output()
        .expect("python3 runs (install tests/requirements.txt)");
    assert!(out.status.success(), "astropy check failed (pip install -r tests/requirements.txt): {}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8(out.stdout).unwrap();
    let xy: Vec<f64> = text.split_whitespace().map(|s| s.parse().unwrap()).collect();
    assert_eq!((px, py), (xy[0].round() as usize, xy[1].round() as usize), "peak at {px},{py}; astropy puts the source at {xy:?}");
    // East is left: the source sits at lower x than the centre, north at higher y.
    assert!(px < 64 && py > 64);
}

#[test]
fn bad_input_gives_errors_that_name_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = r2d2(&["dirty", "missing.parquet", "--name", "x"], d);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("missing.parquet"), "{err}");

    std::fs::write(d.join("garbage.parquet"), b"this is not parquet").unwrap();
    let out = r2d2(&["dirty", "garbage.parquet", "--name", "x"], d);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("garbage.parquet"));
    assert!(!d.join("x-dirty.fits").exists() && !d.join("x-psf.fits").exists(), "no partial products");

    let out = r2d2(&["simulate", "--configs", "a,q", "--hours", "1,1", "--out", "o.parquet"], d);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("a, b, c, d"), "{}", String::from_utf8_lossy(&out.stderr));

    let out = r2d2(&["simulate", "--configs", "a,c", "--hours", "1", "--out", "o.parquet"], d);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("hours"));

    let out = r2d2(&["dirty", "x.parquet", "--weighting", "superuniform"], d);
    assert!(!out.status.success());
}

/// The library names the fields of what it is asked (`frequency_ratio`, `flag_fraction`); the
/// command line names the option as typed (`--freq-ratio`), whatever its field is called.
#[test]
fn simulate_and_trainset_errors_name_the_option_as_typed() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let cases: [(&[&str], &str); 13] = [
        (&["simulate", "--freq-ratio", "0.5"], "invalid --freq-ratio: expected highest/lowest frequency >= 1, got 0.5"),
        (&["simulate", "--nfreq", "2", "--freq-ratio", "1"], "invalid --freq-ratio: 2 frequencies at a ratio of 1"),
        (&["simulate", "--flag-fraction", "1.5"], "invalid --flag-fraction: expected a fraction in [0, 1), got 1.5"),
        (&["simulate", "--nfreq", "0"], "invalid --nfreq: expected at least one frequency"),
        (&["simulate", "--configs", "q", "--hours", "1"], "invalid --configs: expected one of a, b, c, d"),
        (&["simulate", "--configs", "c", "--hours", "0"], "invalid --hours: must be a positive number of hours"),
        (&["simulate", "--dec", "91"], "invalid --dec: must be within [-90, 90] deg"),
        (&["simulate", "--integration-s", "0"], "invalid --integration-s: must be a positive number of seconds"),
        (&["trainset", "--procedural", "1", "--truth-fwhm-px", "100"], "invalid --truth-fwhm-px: expected 0 < low <= high <= 16 pixels"),
        (&["trainset", "--procedural", "1", "--integration-s", "0"], "invalid --integration-s: expected positive times up to a day"),
        (&["simulate", "--ra", "400", "--size", "64"], "invalid --ra: 400: expected a right ascension within [0, 360) degrees"),
        (&["simulate", "--dr", "0.5", "--size", "64"], "invalid --dr: must be a finite number greater than 1, got 0.5"),
        (&["trainset", "--procedural", "1", "--dr-min", "0.5"], "invalid --dr-min/--dr-max: expected 1 < low <= high"),
    ];
    for (args, expected) in cases {
        let args: Vec<&str> = args.iter().copied().chain(["--out", "out"]).collect();
        let out = r2d2(&args, d);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        assert!(err.contains(expected), "{args:?}: '{expected}' missing from: {err}");
    }
    assert_eq!(std::fs::read_dir(d).unwrap().count(), 0, "nothing written");
}

/// What `simulate` and `dirty` would refuse only late, or with a message blaming something
/// else, is refused before any work, naming the option and what is expected. The input of
/// `dirty` does not exist: the options are checked before it is read.
#[test]
fn options_are_refused_before_any_work_naming_what_is_expected() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir(d.join("o")).unwrap();
    let long = "x".repeat(240);
    let deep = vec!["d".repeat(200); 5].join("/");
    let sim = ["simulate", "--configs", "c", "--hours", "1"];
    let cases: Vec<(Vec<&str>, Vec<&str>)> = vec![
        (vec!["--dec", "-90", "--out", "s.parquet"], vec!["--dec", "-90 deg never rises", "vla-c", "above -56"]),
        (vec!["--freq-mhz", "1e9", "--out", "s.parquet"], vec!["--freq-mhz", "from 1e6 to 1e13 Hz", "got 1e15 Hz"]),
        (vec!["--freq-mhz", "1e6", "--freq-ratio", "100", "--out", "s.parquet"], vec!["--freq-ratio", "got 1e14 Hz"]),
        (vec!["--integration-s", "0", "--out", "s.parquet"], vec!["--integration-s", "positive number of seconds, got 0"]),
        (vec!["--out", "o/"], vec!["--out", "\"o/\" names a directory"]),
        (vec!["--out", "o"], vec!["--out", "\"o\" is a directory", "o/obs.parquet"]),
        (vec!["--out", "new/"], vec!["--out", "\"new/\" names a directory"]),
        (vec!["--robust", "-1e30", "--out", "s.parquet"], vec!["robust", "from -5 to 5"]),
        (vec!["--size", "63", "--out", "s.parquet"], vec!["size", "even image size of at least 8", "got 63"]),
    ];
    for (extra, expected) in cases {
        let args: Vec<&str> = sim.iter().copied().chain(extra.iter().copied()).collect();
        let out = r2d2(&args, d);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{extra:?}: {err}");
        assert!(!err.contains("visibilities"), "{extra:?}: simulated first: {err}");
        for e in expected {
            assert!(err.contains(e), "{extra:?}: '{e}' missing from: {err}");
        }
    }
    let long_out = format!("{long}.parquet");
    let deep_out = format!("{deep}/obs.parquet");
    for (out, expected) in [(long_out.as_str(), "255"), (deep_out.as_str(), "1024")] {
        let args: Vec<&str> = sim.iter().copied().chain(["--out", out]).collect();
        let err = String::from_utf8_lossy(&r2d2(&args, d).stderr).into_owned();
        assert!(err.contains("--out") && err.contains(expected) && !err.contains("visibilities"), "{err}");
    }
    assert_eq!(std::fs::read_dir(d).unwrap().count(), 1, "only o/ is there");

    let long_name = format!("out/{long}");
    let deep_name = format!("{deep}/obs");
    let cases: [(&[&str], &[&str]); 5] = [
        (&["--size", "63"], &["--size", "even image size of at least 8", "got 63"]),
        (&["--weighting-grid-factor=-1"], &["--weighting-grid-factor", "positive number, got -1"]),
        (&["--robust", "-1e30"], &["robust", "from -5 to 5"]),
        (&["--name", &long_name], &["--name", &long_name, "file name would have", "255"]),
        (&["--name", &deep_name], &["--name", "cfitsio", "1024"]),
    ];
    for (extra, expected) in cases {
        let args: Vec<&str> = ["dirty", "missing.parquet"].into_iter().chain(extra.iter().copied()).collect();
        let err = String::from_utf8_lossy(&r2d2(&args, d).stderr).into_owned();
        assert!(!err.contains("missing.parquet"), "{extra:?}: the input was read first: {err}");
        for e in expected {
            assert!(err.contains(e), "{extra:?}: '{e}' missing from: {err}");
        }
    }
}

/// An error with a cause beneath it (cfitsio's report, what reading a plugin library found) is
/// printed on one line naming the file and the cause, each once.
#[test]
fn errors_print_the_file_and_their_cause_once() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("notes.fits"), "not an image\n".repeat(300)).unwrap();
    let out = r2d2(&["metrics", "--truth", "notes.fits", "--estimate", "notes.fits"], d);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    let line = err.lines().find(|l| l.starts_with("error: ")).unwrap_or_else(|| panic!("no error line: {err}"));
    assert!(line.starts_with("error: notes.fits: cannot open as FITS: "), "{err}");
    assert_eq!(line.matches("notes.fits").count(), 1, "the file once: {err}");
    assert_eq!(line.matches("cfitsio status").count(), 1, "cfitsio's report once: {err}");

    std::fs::write(d.join("libnotes.so"), "not a library\n").unwrap();
    let pipeline = "image: {size: 16}\nstages:\n  source: {kind: simulate, to: weights}\n  weights: {kind: weighting, scheme: natural, to: grid}\n  grid: {kind: gridder, to: step}\n  step: {kind: native, library: libnotes.so, iterations: 1, to: update}\n  update: {kind: residual, to: step, done: write}\n  write: {kind: writer, prefix: out/x}\n";
    std::fs::write(d.join("p.yaml"), pipeline).unwrap();
    let out = r2d2(&["validate", "p.yaml"], d);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    let line = err.lines().find(|l| l.starts_with("error: ")).unwrap_or_else(|| panic!("no error line: {err}"));
    assert_eq!(line.matches("libnotes.so").count(), 1, "the library once: {err}");
    assert_eq!(line.matches("does not start with an ELF header").count(), 1, "the cause once: {err}");
    assert!(line.contains("stages.step.library"), "{err}");
}

/// parquet 55 panics on some corrupt pages (apache/arrow-rs#9434); the reader contains that,
/// and the user sees an error naming the file, not the panic hook's "thread ... panicked at".
#[test]
fn contained_decoder_panics_print_no_panic_message() {
    use arrow::array::{ArrayRef, Float64Array, RecordBatch};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Dictionary-encoded columns (as most writers produce), damaged at many places.
    let n = 20_000;
    let ramp = |scale: f64| std::sync::Arc::new(Float64Array::from((0..n).map(|i| scale * (i % 5000) as f64).collect::<Vec<_>>())) as ArrayRef;
    let columns = vec![
        ("u", ramp(1.0)),
        ("v", ramp(-2.0)),
        ("w", ramp(0.1)),
        ("frequency", std::sync::Arc::new(Float64Array::from(vec![1.4e9; n])) as ArrayRef),
        ("vis_re", ramp(0.5)),
        ("vis_im", ramp(0.25)),
    ];
    let batch = RecordBatch::try_from_iter(columns).unwrap();
    let metadata = [("phase_centre_ra_deg", "10"), ("phase_centre_dec_deg", "40"), ("telescope", "VLA")];
    let kv = metadata.iter().map(|(k, v)| parquet::file::metadata::KeyValue::new(k.to_string(), v.to_string())).collect();
    let props = parquet::file::properties::WriterProperties::builder().set_key_value_metadata(Some(kv)).build();
    let mut bytes = Vec::new();
    let mut writer = parquet::arrow::ArrowWriter::try_new(&mut bytes, batch.schema(), Some(props)).unwrap();
    writer.write(&batch).unwrap();
    writer.close().unwrap();
    // 24 bytes overwritten at 64 places spread over the file.
    let mut contained = 0;
    for k in 0..64 {
        let start = k * bytes.len() / 64;
        let end = (start + 24).min(bytes.len());
        let mut damaged = bytes.clone();
        damaged[start..end].fill(0xa5 ^ k as u8);
        std::fs::write(d.join("damaged.parquet"), &damaged).unwrap();
        let out = r2d2(&["dirty", "damaged.parquet", "--size", "64", "--name", "x"], d);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains("panicked"), "damage at {start}..{end}: {err}");
        if err.contains("decoder failed (") {
            assert!(err.contains("damaged.parquet") && !out.status.success(), "{err}");
            contained += 1;
        }
    }
    assert!(contained > 0, "no damage made the decoder panic: this test no longer tests anything");
}

/// One row a million kilometres long among a real observation's would set the pixel size
/// (1 / longest baseline) to nonsense: it is excluded and counted, with a warning, and the
/// images are those of the observation without it.
#[test]
fn physically_impossible_rows_are_excluded_with_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let cov = sample_coverage(&vla_at_1_4_ghz(('c', 1.0), 40.0, 300.0)).unwrap();
    let n = cov.len();
    let mut table = VisTable {
        u_m: cov.u_m,
        v_m: cov.v_m,
        w_m: cov.w_m,
        frequency: cov.frequency_hz,
        vis: vec![Complex64::new(1.0, 0.0); n],
        ..Default::default()
    };
    let meta = ObservationMeta::new(10.0, 40.0, "VLA");
    write_parquet(&d.join("good.parquet"), &table, &meta).unwrap();
    table.u_m.push(1e9);
    table.v_m.push(0.0);
    table.w_m.push(0.0);
    table.frequency.push(1.4e9);
    table.vis.push(Complex64::new(1.0, 0.0));
    write_parquet(&d.join("bad.parquet"), &table, &meta).unwrap();
    check(&r2d2(&["dirty", "good.parquet", "--size", "64", "--name", "good"], d));
    let out = r2d2(&["dirty", "bad.parquet", "--size", "64", "--name", "bad"], d);
    check(&out);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("WARN") && err.contains("bad.parquet") && err.contains("1 physically impossible"), "{err}");
    for product in ["dirty", "psf"] {
        let good = read_image(&d.join(format!("good-{product}.fits"))).unwrap();
        let bad = read_image(&d.join(format!("bad-{product}.fits"))).unwrap();
        assert_eq!((good.wcs, good.data), (bad.wcs, bad.data), "{product}");
    }
}

/// A visibility of 1e38 (finite and within single precision, the visibilities' type, so not
/// excluded) blows up the dirty image: the run fails naming the gridder stage, the job and the
/// image, not at the writer.
#[test]
fn huge_finite_visibilities_are_named_where_they_appear() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let cov = sample_coverage(&vla_at_1_4_ghz(('c', 1.0), 40.0, 300.0)).unwrap();
    let n = cov.len();
    let mut vis = vec![Complex64::new(1.0, 0.0); n];
    vis[n / 2] = Complex64::new(1e38, 0.0);
    let table = VisTable { u_m: cov.u_m, v_m: cov.v_m, w_m: cov.w_m, frequency: cov.frequency_hz, vis, ..Default::default() };
    write_parquet(&d.join("huge.parquet"), &table, &ObservationMeta::new(10.0, 40.0, "VLA")).unwrap();
    let out = r2d2(&["image", "huge.parquet", "--size", "64", "--step", "clean", "--name", "out/huge"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    for e in ["(gridder), job 'huge'", "invalid dirty image", "exceed 1e30 in magnitude", "check the data column"] {
        assert!(err.contains(e), "'{e}' missing from: {err}");
    }
    assert!(!d.join("out").exists() || std::fs::read_dir(d.join("out")).unwrap().next().is_none(), "products written");
}

/// Runs `r2d2` under a 4 GB address-space limit and a 60 s timeout, so that a size the checks
/// let through fails fast instead of taking the machine's memory or hanging.
fn r2d2_bounded(args: &[&str], dir: &Path) -> Output {
    Command::new("sh")
        .arg("-c")
        .arg("ulimit -v 4000000; exec timeout 60 \"$0\" \"$@\"")
        .arg(env!("CARGO_BIN_EXE_r2d2"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("sh runs")
}

/// Image sizes, simulated sample counts and thread counts beyond what the machine can hold are
/// refused up front with an error naming the option, instead of an abort on a 100 GB
/// allocation or a hang starting 100 000 threads.
#[test]
fn sizes_beyond_the_machine_are_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--out", "obs.parquet"], d));
    let cases: [(&[&str], &[&str]); 4] = [
        (&["dirty", "obs.parquet", "--size", "100000", "--pixel-arcsec", "0.01", "--name", "x"], &["size", "100000 x 100000", "memory available"]),
        (&["simulate", "--configs", "c", "--hours", "1e4", "--size", "64", "--out", "big.parquet"], &["hours", "samples", "memory available"]),
        (&["simulate", "--configs", "c", "--hours", "1", "--size", "100000", "--pixel-arcsec", "0.01", "--out", "big.parquet"], &["size", "100000 x 100000", "memory available"]),
        (&["dirty", "obs.parquet", "--size", "64", "--threads", "100000", "--name", "x"], &["threads", "100000", "cores"]),
    ];
    for (args, expected) in cases {
        let out = r2d2_bounded(args, d);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        for e in expected {
            assert!(err.contains(e), "{args:?}: '{e}' missing from: {err}");
        }
    }
    assert!(!d.join("x-dirty.fits").exists() && !d.join("big.parquet").exists());

    // The same limits in a pipeline, reported by validate with the file and the key.
    let pipeline = "image: {size: 64}\nstages:\n  source: {kind: simulate, to: weights}\n  weights: {kind: weighting, scheme: natural, to: grid}\n  grid: {kind: gridder, to: step}\n  step: {kind: clean, to: update}\n  update: {kind: residual, to: step, done: write}\n  write: {kind: writer}\n";
    std::fs::write(d.join("p.yaml"), pipeline).unwrap();
    check(&r2d2(&["validate", "p.yaml"], d));
    for (set, expected) in [("image.size=100000", "image.size"), ("threads=4000", "threads")] {
        let out = r2d2_bounded(&["validate", "p.yaml", "--set", set], d);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{set}: {err}");
        assert!(err.contains("p.yaml") && err.contains(expected), "{set}: {err}");
    }
}

/// `r2d2 dirty` creates the output directory, writes its two products all or nothing, and
/// names a full disk as such. The disk is a 100 kB tmpfs in a private mount namespace: a
/// 128 x 128 dirty image fits, the PSF after it does not.
#[test]
fn dirty_products_are_all_or_nothing_and_a_full_disk_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--out", "obs.parquet"], d));
    check(&r2d2(&["dirty", "obs.parquet", "--size", "64", "--name", "new/dir/obs"], d));
    assert!(d.join("new/dir/obs-dirty.fits").exists() && d.join("new/dir/obs-psf.fits").exists());

    // A private mount namespace is a test requirement (util-linux unshare; CI machines allow
    // it): without one the full-disk half fails here rather than passing untested.
    let probe = Command::new("unshare").args(["-rm", "true"]).output();
    assert!(probe.is_ok_and(|o| o.status.success()), "no private mount namespace here (unshare -rm): the full-disk check cannot run");
    let script = format!(
        "mkdir -p full && mount -t tmpfs -o size=100k tmpfs full && {} dirty obs.parquet --size 128 --name full/x; echo \"rc=$?\"; ls -A full",
        env!("CARGO_BIN_EXE_r2d2")
    );
    let out = Command::new("unshare").args(["-rm", "sh", "-c", &script]).current_dir(d).output().unwrap();
    let (stdout, err) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(stdout.starts_with("rc=1\n"), "{stdout}{err}");
    assert_eq!(stdout.trim_end(), "rc=1", "files left on the full disk: {stdout}");
    assert!(err.contains("x-psf.fits") && err.contains("No space left on device"), "{err}");
}

/// Commands whose output is their result: a closed pipe, a full device or a closed standard
/// output is an error naming standard output (exit 1), never a panic or an exit 0 with the
/// figures lost.
#[test]
fn a_closed_or_full_standard_output_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let shell = |script: &str| Command::new("sh").arg("-c").arg(script).env("R2D2", env!("CARGO_BIN_EXE_r2d2")).current_dir(d).output().unwrap();
    // `head -c 0` closes the pipe at once; the exit status of r2d2 is what the script prints.
    for (script, words) in [
        ("\"$R2D2\" info > /dev/full; echo status $?", &["standard output", "No space left"][..]),
        ("\"$R2D2\" info >&-; echo status $?", &["standard output", "closed"][..]),
        ("(sleep 0.5; \"$R2D2\" info; echo status $? >&2) | head -c 0", &["standard output", "Broken pipe"][..]),
    ] {
        let out = shell(script);
        let all = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        assert!(all.contains("status 1"), "{script}: {all}");
        assert!(!all.contains("panicked"), "{script}: {all}");
        for w in words {
            assert!(all.contains(w), "{script}: '{w}' missing: {all}");
        }
    }
}

/// A truth on another grid than the image (another pixel size or centre, the right size) is
/// warned about, not scored silently; on the image's own grid, nothing is said.
#[test]
fn a_truth_on_another_grid_is_warned_about() {
    use r2d2_imaging::fits::{write_image, BrightnessUnit};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--seed", "3", "--out", "obs.parquet"], d));
    let truth = read_image(&d.join("obs.sky.fits")).unwrap();
    let wcs = truth.wcs.unwrap();
    for (name, other) in [
        ("pixel.fits", r2d2_imaging::fits::ImageWcs { pixel_deg: wcs.pixel_deg * 1.5, ..wcs }),
        ("centre.fits", r2d2_imaging::fits::ImageWcs { dec_deg: wcs.dec_deg + 0.1, ..wcs }),
    ] {
        write_image(&d.join(name), &truth.data, 64, 64, &other, BrightnessUnit::JyPerPixel, None, &[]).unwrap();
        let out = r2d2(&["image", "obs.parquet", "--size", "64", "--step", "clean", "--iterations", "1", "--truth", name, "--name", "t"], d);
        check(&out);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("the truth is on another grid"), "{name}: {err}");
    }
    let out = r2d2(&["image", "obs.parquet", "--size", "64", "--step", "clean", "--iterations", "1", "--truth", "obs.sky.fits", "--name", "t"], d);
    check(&out);
    assert!(!String::from_utf8_lossy(&out.stderr).contains("another grid"));
}

/// Under an address-space limit (`ulimit -v`), what is left of it is the memory budget: a size
/// it cannot hold is a clear error about memory, not an aborted allocation or a blamed input.
#[test]
fn an_address_space_limit_is_the_memory_budget() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--seed", "3", "--out", "obs.parquet"], d));
    let script = "ulimit -v 1000000; \"$R2D2\" image obs.parquet --size 4096 --step clean --name big; echo status $?";
    let out = Command::new("sh").arg("-c").arg(script).env("R2D2", env!("CARGO_BIN_EXE_r2d2")).current_dir(d).output().unwrap();
    let all = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(all.contains("status 1") && all.contains("4096 x 4096") && all.contains("address-space limit"), "{all}");
    assert!(!all.contains("panicked") && !all.contains("memory allocation"), "{all}");
    // A FITS image the file holds (sparse: 2 GB declared, nothing on disk) but the budget
    // cannot: `metrics` and `simulate --sky` refuse it naming the file.
    let mut header = String::new();
    for card in ["SIMPLE  =                    T", "BITPIX  =                  -32", "NAXIS   =                    2", "NAXIS1  =                24000", "NAXIS2  =                24000", "END"] {
        header.push_str(&format!("{card:<80}"));
    }
    let header = format!("{header:<2880}");
    let file = std::fs::File::create(d.join("big.fits")).unwrap();
    std::io::Write::write_all(&mut &file, header.as_bytes()).unwrap();
    file.set_len(2880 + (24000u64 * 24000 * 4).div_ceil(2880) * 2880).unwrap();
    for args in ["metrics --truth big.fits --estimate big.fits", "simulate --sky big.fits --configs c --hours 0.25 --integration-s 300 --out sky.parquet"] {
        let script = format!("ulimit -v 1000000; \"$R2D2\" {args}; echo status $?");
        let out = Command::new("sh").arg("-c").arg(&script).env("R2D2", env!("CARGO_BIN_EXE_r2d2")).current_dir(d).output().unwrap();
        let all = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        assert!(all.contains("status 1") && all.contains("big.fits") && all.contains("24000 x 24000") && all.contains("address-space limit"), "{args}: {all}");
        assert!(!all.contains("panicked") && !all.contains("memory allocation"), "{args}: {all}");
    }
}

/// Address spaces too small for the run's threads and inference runtime end with an error
/// about memory, never a panic, an abort, a crash inside the runtime or a hang, for a table
/// and a MeasurementSet, the default (network) step and CLEAN.
#[test]
fn small_address_spaces_end_in_a_memory_error() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "128", "--seed", "3", "--out", "obs.parquet"], d));
    check(&r2d2(&["convert", "obs.parquet", "obs.ms"], d));
    let mut failures = Vec::new();
    for limit in [200_000, 300_000, 400_000, 600_000, 800_000, 1_000_000, 1_200_000, 1_500_000] {
        for (input, step) in [("obs.parquet", "auto"), ("obs.ms", "auto"), ("obs.parquet", "clean")] {
            let script = format!("ulimit -v {limit}; timeout -s KILL 120 \"$R2D2\" image {input} --size 128 --step {step} --name out-{limit}/x; echo status $?");
            let out = Command::new("sh").arg("-c").arg(&script).env("R2D2", env!("CARGO_BIN_EXE_r2d2")).current_dir(d).output().unwrap();
            let all = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
            let clean = (all.contains("status 0") || (all.contains("status 1") && all.contains("error:")))
                && !all.contains("panicked")
                && !all.contains("memory allocation");
            if !clean {
                failures.push(format!("ulimit -v {limit}, {input}, step {step}:\n{all}"));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n---\n"));
}

/// `auto` picks the shipped series whose declared domain holds the job's setting (Briggs +1:
/// the broad VLA series, not the one trained at 0); a series named outside its domain is
/// warned about, and the warning names the series that covers the job.
#[test]
fn a_job_outside_the_series_domain_is_pointed_to_one_that_covers_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // One network on this C observation (its dirty image's mean is negative: no short
    // baselines) may diverge: the products are written either way (exit 0, or 3 where the
    // guard rejected the model); this test is about which series is chosen and said.
    let written = |out: &std::process::Output| assert!(matches!(out.status.code(), Some(0 | 3)), "{}", String::from_utf8_lossy(&out.stderr));
    // A track and integration inside both VLA series' (6..13 h, 300 s): only the setting differs.
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "6", "--integration-s", "300", "--size", "512", "--seed", "3", "--out", "obs.parquet"], d));
    let out = r2d2(&["image", "obs.parquet", "--size", "512", "--robust", "1", "--iterations", "1", "--name", "a"], d);
    written(&out);
    let log = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(log.contains("series 'vla-r2d2-512-broad' chosen for 512 x 512: 'vla-r2d2-512' was not trained for this setting (Briggs robust 1 is outside"), "{log}");
    assert!(!log.contains("was not trained for this job"), "{log}");
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("a-metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["settings"]["step"]["series"], "vla-r2d2-512-broad", "{metrics}");

    let out = r2d2(&["image", "obs.parquet", "--size", "512", "--robust", "1", "--step", "vla-r2d2-512", "--iterations", "1", "--name", "b"], d);
    written(&out);
    let log = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(log.contains("series 'vla-r2d2-512' was not trained for this job") && log.contains("Briggs robust 1 is outside"), "{log}");
    assert!(log.contains("series 'vla-r2d2-512-broad' was trained for it"), "{log}");
    // SR 2.5 at Briggs 0: the broad series too (the narrow one's domain stops at SR 2.0).
    let out = r2d2(&["image", "obs.parquet", "--size", "512", "--superresolution", "2.5", "--iterations", "1", "--name", "e"], d);
    written(&out);
    let log = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(log.contains("series 'vla-r2d2-512-broad' chosen for 512 x 512: 'vla-r2d2-512' was not trained for this setting (super-resolution 2.5"), "{log}");
    // Inside the domain there is nothing to point to.
    let out = r2d2(&["image", "obs.parquet", "--size", "512", "--robust", "0", "--iterations", "1", "--name", "c"], d);
    written(&out);
    assert!(!String::from_utf8_lossy(&out.stderr).contains("was trained for it"));
}

/// A track shorter than the series was trained on is said at the job, with the track measured
/// from the data's times and the series' range; a track of two configurations counts both
/// (as training counts them), and is inside.
#[test]
fn a_track_shorter_than_the_series_was_trained_on_is_warned_about() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let image = |hours: &str, configs: &str, name: &str| {
        let table = format!("{name}.parquet");
        check(&r2d2(&["simulate", "--configs", configs, "--hours", hours, "--integration-s", "300", "--size", "128", "--seed", "3", "--out", &table], d));
        let out = r2d2(&["image", &table, "--size", "128", "--step", "vla-r2d2-128", "--iterations", "1", "--name", name], d);
        // Products written, or exit 3 where the guard rejected the one network's model.
        assert!(matches!(out.status.code(), Some(0 | 3)), "{}", text(&out));
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let log = image("1", "c", "short");
    assert!(log.contains("series 'vla-r2d2-128' was not trained for this job: a track of 1.0 h"), "{log}");
    assert!(log.contains("outside the series' range 6..13 h (the hours of observation it was trained on)"), "{log}");
    assert!(!log.contains("integration time of"), "300 s is the series' own: {log}");
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("short-metrics.json")).unwrap()).unwrap();
    assert_eq!((metrics["settings"]["track_hours"].as_f64(), metrics["settings"]["integration_s"].as_f64()), (Some(1.0), Some(300.0)), "{metrics}");
    // A 5 h + C 2 h: 7 h, as a training sample of A 5..10 h + C 1..3 h counts its track.
    let log = image("5,2", "a,c", "long");
    assert!(!log.contains("a track of") && !log.contains("was not trained for this job"), "{log}");
}

/// A WSClean command line for CLEAN runs with WSClean's meanings given `--step clean`: the
/// loop ends on the auto-threshold, well within the major cycles allowed, with the residual's
/// noise recorded; the same options with the default (network) step are refused, naming
/// `--step clean`, and nothing is written.
#[test]
fn wsclean_clean_controls_run_with_their_meanings() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--seed", "4", "--out", "obs.parquet"], d));
    let wsclean = ["-size", "64", "64", "-weight", "briggs", "0", "-niter", "5000", "-auto-threshold", "3", "-mgain", "0.8", "-gain", "0.1", "-j", "1"];
    let mut args = vec!["image", "obs.parquet", "--step", "clean", "-name", "ws"];
    args.extend(wsclean);
    check(&r2d2(&args, d));
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("ws-metrics.json")).unwrap()).unwrap();
    let cycles = metrics["iterations"].as_array().unwrap().len();
    assert!(cycles < 20 && metrics["stop"]["reason"] == "converged", "{metrics}");
    let noise = metrics["residual_noise_jy_per_beam"].as_f64().unwrap();
    let residual = read_image(&d.join("ws-residual.fits")).unwrap().data;
    let peak = residual.iter().fold(0.0f64, |m, r| m.max(r.abs()));
    // The last minor cycle stopped at 3 sigma of the residual it started from; the exact
    // residual of the next major cycle is close to it.
    assert!(peak < 5.0 * noise && peak > 0.0, "residual peak {peak} against noise {noise}");

    let mut args = vec!["image", "obs.parquet", "-name", "net"];
    args.extend(wsclean);
    let out = r2d2(&args, d);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("invalid --step:") && stderr.contains("are for the step clean"), "{stderr}");
    assert!(!d.join("net-metrics.json").exists());
}

/// A quarter of an hour of VLA C at 1.4 GHz, every visibility 1 Jy (a point source at the
/// phase centre), observed by `telescope`.
fn point_source_table(path: &Path, telescope: &str) {
    let cov = sample_coverage(&vla_at_1_4_ghz(('c', 0.25), 40.0, 300.0)).unwrap();
    let n = cov.len();
    let table = VisTable { u_m: cov.u_m, v_m: cov.v_m, w_m: cov.w_m, frequency: cov.frequency_hz, vis: vec![Complex64::new(1.0, 0.0); n], ..Default::default() };
    write_parquet(path, &table, &ObservationMeta::new(10.0, 40.0, telescope)).unwrap();
}

/// A telescope name FITS cannot hold as it is (not printable ASCII, or longer than a header
/// card): `dirty` and `image` write the same TELESCOP, what FITS holds of it, and say so; no
/// failure after imaging, no character dropped without a word.
#[test]
fn telescope_names_fits_cannot_hold_are_written_as_they_can_be_and_said() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let long = format!("{}'s array", "T".repeat(70));
    for (file, telescope, written, note) in [
        ("unicode.parquet", "ÅSKAP–Ø", "?SKAP??".to_string(), "3 character(s) other than printable ASCII written as '?'"),
        ("long.parquet", long.as_str(), "T".repeat(68), "cut to 68 characters"),
    ] {
        point_source_table(&d.join(file), telescope);
        for command in [vec!["dirty", file, "--size", "64", "--name", "d"], vec!["image", file, "--size", "64", "--step", "clean", "--iterations", "2", "--name", "i"]] {
            let out = r2d2(&command, d);
            check(&out);
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(err.contains("WARN") && err.contains("TELESCOP") && err.contains(&format!("{telescope:?} is written as {written:?}")) && err.contains(note), "{command:?}: {err}");
            assert_eq!(err.matches("TELESCOP:").count(), 1, "{command:?}: said once: {err}");
            let header = Command::new("python3")
                .args(["-c", "import sys; from astropy.io import fits; print(fits.getheader(sys.argv[1])['TELESCOP'])"])
                .arg(d.join(format!("{}-dirty.fits", command.last().unwrap())))
                .output()
                .unwrap();
            assert_eq!(String::from_utf8_lossy(&header.stdout).trim_end(), written, "{command:?}: {}", text(&header));
        }
    }
}

/// Products whose names hold `[` (which cfitsio would read as an extension selector) read
/// back as a truth and by `metrics` (issue 56.22); a prefix under a link that leads round a
/// loop is refused naming the loop, not "File exists" (issue 56.19).
#[test]
fn bracketed_product_names_read_back_and_a_link_loop_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    point_source_table(&d.join("obs.parquet"), "VLA");
    check(&r2d2(&["dirty", "obs.parquet", "--size", "64", "--name", "a[1]"], d));
    let out = r2d2(&["metrics", "--truth", "a[1]-dirty.fits", "--estimate", "a[1]-psf.fits"], d);
    check(&out);
    assert!(String::from_utf8_lossy(&out.stdout).contains("snr"), "{}", text(&out));
    check(&r2d2(&["image", "obs.parquet", "--size", "64", "--step", "clean", "--iterations", "2", "--truth", "a[1]-dirty.fits", "--name", "t"], d));

    std::os::unix::fs::symlink("loop", d.join("loop")).unwrap();
    let out = r2d2(&["dirty", "obs.parquet", "--size", "64", "--name", "loop/x"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("loop: a symbolic link that leads round a loop of links (to loop)") && !err.contains("File exists"), "{err}");
}

/// WSClean's uv cuts and tapers on the command line (its spelling and this engine's): a bad
/// value is refused naming the option, before anything is read; a selection that leaves
/// nothing to image is refused, naming what left everything out; a pixel coarser than the
/// data's Nyquist limit images, the baselines beyond the grid left out and counted in the log.
#[test]
fn uv_cuts_tapers_and_a_coarse_pixel_on_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Baselines of 360 to 15800 wavelengths.
    check(&r2d2(&["simulate", "--configs", "c", "--hours", "1", "--integration-s", "300", "--size", "64", "--seed", "4", "--out", "obs.parquet"], d));
    let cases: [(&[&str], &[&str]); 7] = [
        (&["--minuv-l", "-5"], &["invalid --minuv-l", ">= 0, got -5"]),
        (&["-minuv-l", "500", "-maxuv-l", "400"], &["invalid --minuv-l", "below maxuv_l"]),
        (&["--taper-tukey", "100"], &["invalid --taper-tukey", "maxuv_l"]),
        (&["--taper-gaussian", "nan"], &["invalid --taper-gaussian", "NaN"]),
        (&["-taper-gaussian", "0"], &["-taper-gaussian 0", "positive angle"]),
        // Found reading the data (`r2d2 image` names the stage, and the field).
        (&["--minuv-l", "1e5"], &["invalid ", "nothing would remain", "below minuv_l"]),
        (&["--pixel-arcsec", "400"], &["pixel", "nothing would remain", "beyond the grid"]),
    ];
    for (options, expected) in cases {
        for command in [&["dirty", "obs.parquet", "--size", "64", "--name", "bad"][..], &["image", "obs.parquet", "--size", "64", "--step", "clean", "--name", "bad"][..]] {
            let args: Vec<&str> = command.iter().chain(options).copied().collect();
            let out = r2d2(&args, d);
            assert!(!out.status.success(), "{args:?} succeeded");
            for word in expected {
                assert!(text(&out).contains(word), "{args:?}: '{word}' missing from: {}", text(&out));
            }
            assert!(!d.join("bad-dirty.fits").exists(), "{args:?}: products written");
        }
    }
    // A 40 arcsec pixel: a Nyquist limit of 2580 wavelengths.
    for command in [&["dirty", "obs.parquet"][..], &["image", "obs.parquet", "--step", "clean", "--iterations", "1"][..]] {
        let args: Vec<&str> = command.iter().copied().chain(["--size", "64", "--pixel-arcsec", "40", "--name", "coarse"]).collect();
        let out = r2d2(&args, d);
        check(&out);
        assert!(text(&out).contains("beyond the grid: |u| or |v| past the Nyquist limit 2578.3 wavelengths"), "{}", text(&out));
    }
}

/// Point sources `(east, north, flux)` (offsets in pixels of the SR 1.5 grid, true angle) of
/// a VLA C observation at 1.4 GHz, phase centre RA 150, Dec 40, with Gaussian noise of
/// `noise` Jy per visibility (real and imaginary parts); the pixel size in degrees.
fn point_sources_table(path: &Path, sources: &[(f64, f64, f64)], noise: f64) -> f64 {
    let (ra0, dec0) = (150.0f64, 40.0f64);
    let cov = sample_coverage(&vla_at_1_4_ghz(('c', 2.0), dec0, 300.0)).unwrap();
    let pixel_rad = 1.0 / (1.5 * 2.0 * cov.max_uv());
    let lm: Vec<(f64, f64, f64)> = sources.iter().map(|&(e, n, s)| (e * pixel_rad, n * pixel_rad, s)).collect();
    // Box-Muller on a xorshift: reproducible without a generator crate.
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let vis: Vec<Complex64> = (0..cov.len())
        .map(|k| {
            let scale = cov.frequency_hz[k] / SPEED_OF_LIGHT;
            let (u, v) = (cov.u_m[k] * scale, cov.v_m[k] * scale);
            let (r, t) = ((-2.0 * uniform().ln()).sqrt(), 2.0 * std::f64::consts::PI * uniform());
            let sky: Complex64 = lm.iter().map(|&(l, m, s)| Complex64::from_polar(s, 2.0 * std::f64::consts::PI * (u * l + v * m))).sum();
            sky + noise * Complex64::new(r * t.cos(), r * t.sin())
        })
        .collect();
    let n = cov.len();
    let table = VisTable { u_m: cov.u_m, v_m: cov.v_m, w_m: cov.w_m, frequency: cov.frequency_hz, vis, weight: vec![1.0; n], ..Default::default() };
    write_parquet(path, &table, &ObservationMeta::new(ra0, dec0, "VLA")).unwrap();
    pixel_rad.to_degrees()
}

/// Whether a FITS file's header has `text` (HISTORY records are ASCII in the header blocks).
fn header_has(path: &Path, text: &str) -> bool {
    let bytes = std::fs::read(path).unwrap();
    let header = &bytes[..bytes.len().min(2880 * 4)];
    header.windows(text.len()).any(|w| w == text.as_bytes())
}

/// `--fits-mask` with `--step clean`: a mask made as users make it (the restored image of an
/// unmasked run above a level, written on its header's grid, here with one source left out)
/// confines the components to it, so the source left out stays whole in the residual and
/// the one inside gets the flux of the unmasked run; a mask on another grid is refused naming
/// the file, what it has and what the image has.
#[test]
fn a_fits_mask_confines_clean_and_one_on_another_grid_is_refused() {
    use r2d2_imaging::fits::{write_image, BrightnessUnit};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // One source east (left), one west (right), both north of the centre.
    point_sources_table(&d.join("obs.parquet"), &[(12.0, 6.0, 1.0), (-14.0, 9.0, 0.5)], 0.1);
    let clean = ["--size", "64", "--step", "clean", "--niter", "20000", "--auto-threshold", "1"];
    let run = |extra: &[&str], name: &str| {
        let mut args = vec!["image", "obs.parquet", "--name", name];
        args.extend(clean);
        args.extend(extra);
        r2d2(&args, d)
    };
    check(&run(&[], "open"));
    let image = read_image(&d.join("open-image.fits")).unwrap();
    let open_model = read_image(&d.join("open-model.fits")).unwrap().data;
    let n = image.nx;
    let peak = image.data.iter().fold(0.0f64, |m, v| m.max(*v));
    // Above a tenth of the peak, in the left half only (FITS order: x along RA, east left).
    let left = |k: usize| k % n < n / 2;
    let mask: Vec<f64> = (0..n * n).map(|k| if image.data[k] > 0.1 * peak && left(k) { 1.0 } else { 0.0 }).collect();
    assert!(mask.iter().sum::<f64>() > 4.0);
    write_image(&d.join("mask.fits"), &mask, n, n, &image.wcs.unwrap(), BrightnessUnit::Ratio, None, &[]).unwrap();
    check(&run(&["--fits-mask", "mask.fits"], "masked"));
    let model = read_image(&d.join("masked-model.fits")).unwrap().data;
    let outside: Vec<usize> = (0..n * n).filter(|&k| model[k] != 0.0 && mask[k] == 0.0).collect();
    assert!(outside.is_empty(), "components outside the mask at {outside:?}");
    // The source inside: its flux as the unmasked run found it (the mask is on it: the
    // orientation of the file is the image's).
    let flux = |m: &[f64], half: &dyn Fn(usize) -> bool| (0..n * n).filter(|&k| half(k)).map(|k| m[k]).sum::<f64>();
    let (inside, open_inside) = (flux(&model, &left), flux(&open_model, &left));
    assert!((inside - open_inside).abs() < 0.05 * open_inside && (inside - 1.0).abs() < 0.1, "masked {inside} against unmasked {open_inside}");
    // The source outside: no model, and its peak in the residual as in the dirty image.
    let right = |k: usize| !left(k);
    assert_eq!(flux(&model, &right), 0.0);
    assert!(flux(&open_model, &right) > 0.4, "the unmasked run cleaned it: {}", flux(&open_model, &right));
    let right_peak = |path: &str| {
        let data = read_image(&d.join(path)).unwrap().data;
        (0..n * n).filter(|&k| right(k)).fold(0.0f64, |m, k| m.max(data[k]))
    };
    let (residual, dirty, open_residual) = (right_peak("masked-residual.fits"), right_peak("masked-dirty.fits"), right_peak("open-residual.fits"));
    assert!((residual - dirty).abs() < 0.25 * dirty && open_residual < 0.2 * dirty, "right half: residual {residual}, dirty {dirty}, unmasked residual {open_residual}");
    // The products say which mask.
    assert!(header_has(&d.join("masked-model.fits"), "mask: fits_mask=mask.fits"));
    assert!(!header_has(&d.join("open-model.fits"), "mask:"));

    // A mask on another grid: refused, naming the file, what it has and what the image has.
    let wcs = image.wcs.unwrap();
    write_image(&d.join("small.fits"), &mask[..32 * 32], 32, 32, &wcs, BrightnessUnit::Ratio, None, &[]).unwrap();
    write_image(&d.join("pixel.fits"), &mask, n, n, &r2d2_imaging::fits::ImageWcs { pixel_deg: wcs.pixel_deg * 2.0, ..wcs }, BrightnessUnit::Ratio, None, &[]).unwrap();
    write_image(&d.join("centre.fits"), &mask, n, n, &r2d2_imaging::fits::ImageWcs { dec_deg: wcs.dec_deg + 1.0, ..wcs }, BrightnessUnit::Ratio, None, &[]).unwrap();
    for (file, said) in [("small.fits", &["32 x 32", "64 x 64"][..]), ("pixel.fits", &["its pixel is"][..]), ("centre.fits", &["its centre is"][..]), ("none.fits", &["none.fits"][..])] {
        let out = run(&["--fits-mask", file], "bad");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(file) && said.iter().all(|s| err.contains(s)), "{file}: {err}");
        assert!(!d.join("bad-model.fits").exists());
    }
    // WSClean's spelling, and a native plugin refuses a mask.
    check(&run(&["-fits-mask", "mask.fits"], "ws"));
    assert_eq!(read_image(&d.join("ws-model.fits")).unwrap().data, model);
    let out = r2d2(&["image", "obs.parquet", "--size", "64", "--step", "plugin.so", "--fits-mask", "mask.fits", "--name", "p"], d);
    assert!(!out.status.success() && text(&out).contains("fits-mask"), "{}", text(&out));
}

/// `--auto-mask 5 --auto-threshold 1` (WSClean's usual deep clean): the run converges,
/// cleans deeper than the auto-threshold alone would leave the sources, and says so; a series
/// takes `--auto-mask` as well.
#[test]
fn auto_mask_runs_to_convergence_and_is_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    point_sources_table(&d.join("obs.parquet"), &[(12.0, 6.0, 1.0), (-14.0, 9.0, 0.5), (3.0, -15.0, 0.05)], 0.1);
    check(&r2d2(&["image", "obs.parquet", "--size", "64", "--step", "clean", "-niter", "100000", "-auto-mask", "5", "-auto-threshold", "1", "--name", "auto"], d));
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("auto-metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["stop"]["reason"], "converged", "{metrics}");
    assert_eq!(metrics["settings"]["mask"]["auto_mask"], 5.0);
    assert!(header_has(&d.join("auto-model.fits"), "mask: auto_mask=5"));
    let model = read_image(&d.join("auto-model.fits")).unwrap().data;
    let total: f64 = model.iter().sum();
    assert!((total - 1.55).abs() < 0.05 * 1.55, "model flux {total}");
    // A network series takes it too (its model kept to where the data show emission), WSClean's
    // spelling included, and -auto-threshold (its final CLEAN's depth; not without that final
    // CLEAN); the other CLEAN controls are still for CLEAN only.
    check(&r2d2(&["image", "obs.parquet", "--size", "64", "-auto-mask", "5", "-auto-threshold", "1", "--name", "net"], d));
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("net-metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["settings"]["mask"]["auto_mask"], 5.0);
    assert_eq!(metrics["settings"]["final_clean"]["auto_threshold_sigmas"], 1.0, "{metrics}");
    let out = r2d2(&["image", "obs.parquet", "--size", "64", "-auto-threshold", "1", "--no-final-clean", "--name", "net2"], d);
    assert!(!out.status.success() && text(&out).contains("final CLEAN, which is off"), "{}", text(&out));
    let out = r2d2(&["image", "obs.parquet", "--size", "64", "-mgain", "0.8", "--name", "net3"], d);
    assert!(!out.status.success() && text(&out).contains("are for the step clean"), "{}", text(&out));
}

/// `trainset --parquet` writes each sample's visibilities and sky as the sample is made (not
/// all of them held to the end), and the set is swapped in whole: the tables are those the
/// samples were imaged from (as many points as the set records), and no `.partial` is left.
#[test]
fn a_trainset_writes_each_samples_table_and_leaves_nothing_partial() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    check(&r2d2(&["trainset", "--procedural", "3", "--size", "32", "--integration-s", "600", "--threads", "2", "--parquet", "--out", "set", "-q"], dir));
    assert!(!dir.join("set.partial").exists());
    let records: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("set/samples.json")).unwrap()).unwrap();
    for k in 0..3 {
        let (vis, _, _) = r2d2_imaging::vis::read_parquet(&dir.join(format!("set/vis/{k:05}.parquet"))).unwrap();
        let points = records[k]["points"].as_u64().unwrap() as usize;
        assert!(points > 0 && vis.u.len() == points, "sample {k}: {} samples read, {points} points", vis.u.len());
        assert_eq!(read_image(&dir.join(format!("set/vis/{k:05}.sky.fits"))).unwrap().data.len(), 32 * 32);
    }
    // A set that fails leaves the one already there as it was; one that succeeds replaces it,
    // leaving nothing beside it.
    std::fs::write(dir.join("set/mine.txt"), "kept").unwrap();
    std::fs::create_dir(dir.join("empty")).unwrap();
    let failed = r2d2(&["trainset", "--truths", "empty", "--size", "32", "--parquet", "--out", "set", "-q"], dir);
    assert!(!failed.status.success() && text(&failed).contains("no .npy or .fits ground truths"), "{}", text(&failed));
    assert!(dir.join("set/mine.txt").exists() && dir.join("set/vis/00002.parquet").exists());
    check(&r2d2(&["trainset", "--procedural", "2", "--size", "32", "--integration-s", "600", "--parquet", "--out", "set", "-q"], dir));
    assert!(!dir.join("set/mine.txt").exists() && !dir.join("set/vis/00002.parquet").exists() && dir.join("set/vis/00001.parquet").exists());
    assert!(!dir.join("set.partial").exists() && !dir.join("set.previous").exists());
}
