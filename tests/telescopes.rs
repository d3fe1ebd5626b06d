//! Telescopes as data (`data/telescopes/`): the layouts are the published antenna positions,
//! `r2d2 simulate --telescope` observes with a telescope's preset and names it in what it
//! writes, and `series: auto` runs the series trained for the data's telescope, or images a
//! telescope no series was trained for with CLEAN and says so.

mod common;

use common::{check, r2d2, stderr};
use std::path::Path;
use std::process::Command;

/// Positions published as WGS84 longitude, latitude (deg) and height (m), from the source the
/// tables were made from (simms 3.0.2's skamid.geodetic.yaml), converted back from the
/// tables' ITRF by astropy: the tables hold those positions and the conversion is right.
#[test]
fn layouts_hold_the_published_geodetic_positions() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/telescopes");
    let script = r##"
import sys
from astropy.coordinates import EarthLocation
import astropy.units as u
published = {
    ("meerkat.itrf.txt", "M000"): (21.44380263, -30.71292499, 1095.967),
    ("meerkat.itrf.txt", "M063"): (21.40819056, -30.72764891, 1103.023),
    ("skamid-aastar.itrf.txt", "SKA001"): (21.449412, -30.71329, 1098.074),
}
for (file, name), (lon, lat, h) in published.items():
    rows = [l.split() for l in open(f"{sys.argv[1]}/{file}") if not l.startswith("#") and l.strip()]
    x, y, z = next(map(float, r[:3]) for r in rows if r[4] == name)
    g = EarthLocation.from_geocentric(x, y, z, unit=u.m).to_geodetic("WGS84")
    err = (abs(g.lon.deg - lon), abs(g.lat.deg - lat), abs(g.height.to_value(u.m) - h))
    assert err[0] < 1e-7 and err[1] < 1e-7 and err[2] < 1e-3, (file, name, err)
print("ok")
"##;
    let out = Command::new("python3").arg("-c").arg(script).arg(&dir).output().expect("python3 runs (a test requirement)");
    assert!(out.status.success() && String::from_utf8_lossy(&out.stdout).contains("ok"), "{}", String::from_utf8_lossy(&out.stderr));
}

/// `r2d2 simulate --telescope T` fills in T's preset and writes T's name as the telescope; an
/// MS made from it carries it in OBSERVATION.
fn simulated_ms(d: &Path, telescope: &str, config: &str, name: &str, expect: &str) {
    let parquet = format!("{name}.parquet");
    check(&r2d2(
        &["simulate", "--telescope", telescope, "--configs", config, "--hours", "1", "--nfreq", "1", "--integration-s", "600", "--size", "64", "--dr", "100", "--out", &parquet],
        d,
    ));
    check(&r2d2(&["convert", &parquet, &format!("{name}.ms")], d));
    let read = Command::new("python3")
        .arg("-c")
        .arg("import sys; from casacore.tables import table; t = table(sys.argv[1] + '/OBSERVATION', ack=False); print(t.getcol('TELESCOPE_NAME')[0])")
        .arg(d.join(format!("{name}.ms")))
        .output()
        .expect("python3 runs");
    assert_eq!(String::from_utf8_lossy(&read.stdout).trim(), expect, "{}", String::from_utf8_lossy(&read.stderr));
    // As MeerKAT's (and SKA-Mid's) pipelines write an MS: WEIGHT and SIGMA in a
    // TiledShapeStMan, the data tiled, autocorrelations.
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/make_ms.py");
    let made = Command::new("python3")
        .arg(&script)
        .args([parquet.as_str(), &format!("{name}-pipeline.ms"), "--stman", "meerkat", "--autocorrelations", "--interval", "600"])
        .current_dir(d)
        .output()
        .expect("python3 runs");
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
}

/// `r2d2 image NAME-pipeline.ms --size 64 --name NAME` with no other option: its output
/// (checked to succeed) and its metrics.
fn image_pipeline_ms(d: &Path, name: &str) -> (std::process::Output, serde_json::Value) {
    let out = r2d2(&["image", &format!("{name}-pipeline.ms"), "--size", "64", "--name", name], d);
    common::check_written(&out);
    let metrics = serde_json::from_str(&std::fs::read_to_string(d.join(format!("{name}-metrics.json"))).unwrap()).unwrap();
    (out, metrics)
}

/// A pipeline-written MS of a telescope no series was trained for (SKA-Mid) is imaged with
/// CLEAN and a warning that names the telescope and the series there are, with no option
/// beyond the size; the VLA's data keep the series.
#[test]
fn a_telescope_without_a_series_is_imaged_by_clean_with_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulated_ms(d, "ska-mid", "aastar", "ska", "SKA-Mid");
    let (out, metrics) = image_pipeline_ms(d, "ska");
    let warnings = metrics["warnings"].to_string();
    assert!(warnings.contains("'SKA-Mid'") && warnings.contains("built-in CLEAN") && warnings.contains("vla-r2d2-512 (vla)"), "{warnings}");
    assert!(warnings.contains("meerkat-r2d2-512 (meerkat)"), "{warnings}");
    assert_eq!(metrics["telescope"], "SKA-Mid");
    assert!(stderr(&out).contains("no series was trained for the telescope 'SKA-Mid'"), "{}", stderr(&out));

    // The VLA's data at the same size: a series (off its size, as before), not CLEAN.
    check(&r2d2(&["simulate", "--telescope", "vla", "--configs", "c", "--hours", "1", "--nfreq", "1", "--integration-s", "600", "--size", "64", "--dr", "100", "--out", "vla.parquet"], d));
    let out = r2d2(&["image", "vla.parquet", "--size", "64", "--name", "vla"], d);
    common::check_written(&out);
    let metrics = std::fs::read_to_string(d.join("vla-metrics.json")).unwrap();
    assert!(!metrics.contains("built-in CLEAN"), "{metrics}");
    assert!(stderr(&out).contains("series 'vla-r2d2"), "{}", stderr(&out));
    assert!(!metrics.contains("name no telescope"), "{metrics}");

    // An MS that names no telescope (TELESCOPE_NAME emptied): a series runs, and the job says
    // that nothing checked the data against the telescope it was trained for.
    let blank = "import sys; from casacore.tables import table; t = table(sys.argv[1] + '/OBSERVATION', readonly=False, ack=False); t.putcol('TELESCOPE_NAME', [''] * t.nrows()); t.close()";
    let out = Command::new("python3").arg("-c").arg(blank).arg(d.join("ska-pipeline.ms")).output().expect("python3 runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (_, metrics) = image_pipeline_ms(d, "ska");
    let warnings = metrics["warnings"].to_string();
    assert!(warnings.contains("the data name no telescope") && warnings.contains("trained for vla"), "{warnings}");

    let out = r2d2(&["simulate", "--telescope", "alma", "--out", "x.parquet"], d);
    common::assert_fails_with(&out, "unknown telescope", &["vla, meerkat, ska-mid", "'alma'"]);
}

/// A MeerKAT MS as MeerKAT's pipelines write one is imaged by the project's MeerKAT series,
/// off its trained size too (the telescope counts before the size), and not by CLEAN or a
/// VLA series.
#[test]
fn meerkat_data_are_imaged_by_the_meerkat_series() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulated_ms(d, "meerkat", "meerkat", "mk", "MeerKAT");
    let (out, metrics) = image_pipeline_ms(d, "mk");
    let log = stderr(&out);
    assert!(log.contains("meerkat-r2d2-512") && !log.contains("built-in CLEAN") && !log.contains("series 'vla-r2d2"), "{log}");
    assert_eq!(metrics["telescope"], "MeerKAT");
    // Off its trained size: said in the job's metrics, not only in the log. The telescope is
    // the series' own; the short track (1 h of its 8..12 h) is said.
    let warnings = metrics["warnings"].to_string();
    assert!(!warnings.contains("the data come from the telescope") && warnings.contains("running it at 64 x 64"), "{warnings}");
    assert!(warnings.contains("a track of 1.0 h"), "{warnings}");
}

/// With a series trained for MeerKAT among the series found, `auto` runs it on MeerKAT data
/// (and not CLEAN), and `r2d2 models` lists it under its telescope.
#[test]
fn auto_runs_the_series_trained_for_the_datas_telescope() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::make_test_models(&d.join("models"), 0.5);
    let manifest = d.join("models/landweber/manifest.yaml");
    let text = std::fs::read_to_string(&manifest).unwrap().replace("name: landweber", "name: meerkat-landweber");
    std::fs::write(&manifest, format!("{text}validity: {{telescopes: [meerkat], image_sizes: [64]}}\n")).unwrap();
    let with_models = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_r2d2")).args(args).current_dir(d).env("R2D2_MODELS", d.join("models")).output().expect("r2d2 runs")
    };
    check(&r2d2(&["simulate", "--telescope", "meerkat", "--hours", "1", "--nfreq", "1", "--integration-s", "600", "--size", "64", "--dr", "100", "--out", "mk.parquet"], d));
    let out = with_models(&["image", "mk.parquet", "--size", "64", "--name", "mk"]);
    common::check_written(&out);
    let log = stderr(&out);
    assert!(log.contains("series 'meerkat-landweber'") && !log.contains("built-in CLEAN"), "{log}");
    let metrics = std::fs::read_to_string(d.join("mk-metrics.json")).unwrap();
    assert!(!metrics.contains("was not trained for this job"), "{metrics}");

    let out = with_models(&["models"]);
    check(&out);
    let listing = String::from_utf8_lossy(&out.stdout).into_owned();
    let meerkat = listing.find("telescope meerkat:").expect("a meerkat group");
    assert!(listing[meerkat..].contains("meerkat-landweber"), "{listing}");
    // The other test series declare no telescope: `auto` may run them on any data, so no
    // telescope is said to be without a series.
    assert!(listing.contains("no telescope declared") && !listing.contains("without a series"), "{listing}");
}

/// `r2d2 simulate` dates its samples as a real observation's (MJD seconds, UTC): at each
/// configuration's middle integration the local mean sidereal time at its array's centre is
/// the phase centre's right ascension, by astropy (UT1 taken as UTC, as the simulation does;
/// they differ by under 0.9 s), configuration k observed on day k after 2025-06-01. The
/// metadata name the configurations and the integration time.
#[test]
fn simulated_times_put_the_phase_centre_on_the_meridian_mid_track() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let layouts = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/telescopes");
    let script = r#"
import sys
import numpy as np, pyarrow.parquet as pq
from astropy.utils import iers
iers.conf.auto_download = False
from astropy.time import Time
from astropy.coordinates import EarthLocation
import astropy.units as u
parquet, ra, configs, integration, layouts = sys.argv[1], float(sys.argv[2]), sys.argv[3], sys.argv[4], sys.argv[5:]
t = pq.read_table(parquet)
meta = {k.decode(): v.decode() for k, v in t.schema.metadata.items()}
assert meta["configurations"] == configs and float(meta["integration_s"]) == float(integration), meta
times = np.unique(t["time"].to_numpy())
tracks = np.split(times, np.nonzero(np.diff(times) > 3600.0)[0] + 1)
assert len(tracks) == len(layouts), (len(tracks), len(layouts))
for day, (track, layout) in enumerate(zip(tracks, layouts)):
    assert len(track) % 2 == 1, len(track)
    xyz = np.loadtxt(layout, usecols=(0, 1, 2)).mean(axis=0)
    lon = EarthLocation.from_geocentric(*xyz, unit=u.m).lon
    middle = Time(track[len(track) // 2] / 86400.0, format="mjd", scale="utc")
    middle.delta_ut1_utc = 0.0
    lst = middle.sidereal_time("mean", longitude=lon).hour
    off = ((lst - ra / 15.0 + 12.0) % 24.0 - 12.0) * 3600.0
    assert abs(off) < 1.0, (day, off)
    assert middle.iso[:10] == f"2025-06-{day + 1:02d}", (day, middle.iso)
    print(f"day {day}: {middle.iso}, LST - RA = {off * 1e3:.1f} ms")
"#;
    for (telescope, configs, hours, ra, files) in [
        ("vla", "a,c", "0.75,0.25", "250", vec!["vlaa.itrf.txt", "vlac.itrf.txt"]),
        ("meerkat", "meerkat", "0.25", "30.5", vec!["meerkat.itrf.txt"]),
    ] {
        // Odd numbers of integrations (9 and 3 of 300 s): the middle one is at transit.
        check(&r2d2(
            &["simulate", "--telescope", telescope, "--configs", configs, "--hours", hours, "--integration-s", "300", "--ra", ra, "--size", "64", "--nfreq", "1", "--out", "t.parquet"],
            d,
        ));
        let out = Command::new("python3")
            .arg("-c")
            .arg(script)
            .args(["t.parquet", ra, configs, "300"])
            .args(files.iter().map(|f| layouts.join(f)))
            .current_dir(d)
            .output()
            .expect("python3 runs");
        assert!(out.status.success(), "{telescope}: {}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        eprint!("{telescope}: {}", String::from_utf8_lossy(&out.stdout));
    }
}
