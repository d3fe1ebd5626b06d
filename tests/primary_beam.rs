//! `r2d2 image --apply-primary-beam` end to end: the beam written is the published one (EVLA
//! Memo 195's polynomial, evaluated here from the memo's printed coefficients), the corrected
//! images are the restored image and the model divided by it inside the cut and blank outside,
//! and a telescope without a model is refused before anything is imaged or written.

use num_complex::Complex64;
use r2d2_imaging::simulate::{sample_coverage, ObservationSpec};
use r2d2_imaging::vis::{write_parquet, ObservationMeta, VisTable};
use std::path::Path;
use std::process::{Command, Output};

fn r2d2(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_r2d2")).args(args).current_dir(dir).output().expect("r2d2 runs")
}

fn check(out: &Output) {
    assert!(out.status.success(), "r2d2 failed: {}\nstderr: {}", out.status, String::from_utf8_lossy(&out.stderr));
}

/// A product's pixels (NaN kept: `fits::read_image` refuses blanks) and header cards.
struct Product {
    data: Vec<f32>,
    header: fitsio::FitsFile,
}

fn product(path: &Path) -> Product {
    let mut f = fitsio::FitsFile::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let data = f.primary_hdu().unwrap().read_image(&mut f).unwrap();
    Product { data, header: f }
}

impl Product {
    fn key<T: fitsio::headers::ReadsKey>(&mut self, name: &str) -> T {
        let hdu = self.header.primary_hdu().unwrap();
        hdu.read_key(&mut self.header, name).unwrap_or_else(|e| panic!("{name}: {e}"))
    }
}

/// EVLA Memo 195, L band, the row of 1424 MHz (nearest to the simulation's 1.4 GHz):
/// 1 + a x^2 + b x^4 + c x^6, x = r[arcmin] nu[GHz], the polynomial taken as 0 past its null.
fn memo_1424(r_arcmin: f64, ghz: f64) -> f64 {
    let x = r_arcmin * ghz;
    let mut value = 1.0;
    for (k, (c, scale)) in [(-1.462, 1e-3), (8.23, 1e-7), (-1.83, 1e-10)].into_iter().enumerate() {
        value += c * scale * x.powi(2 * (k as i32 + 1));
    }
    value.max(0.0)
}

#[test]
fn apply_primary_beam_writes_the_beam_and_the_images_divided_by_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    check(&r2d2(&["simulate", "--configs", "d", "--hours", "1", "--integration-s", "300", "--size", "64", "--seed", "4", "--out", "obs.parquet"], d));
    // 45" pixels: a 48' field, wider than the beam's cut at 1.4 GHz (its corners lie beyond it).
    let common = ["image", "obs.parquet", "--size", "64", "--pixel-arcsec", "45", "--step", "clean", "--iterations", "2"];
    let mut args = common.to_vec();
    // WSClean's spelling.
    args.extend(["-apply-primary-beam", "-name", "pb"]);
    check(&r2d2(&args, d));

    let mut pb = product(&d.join("pb-pb.fits"));
    let image = product(&d.join("pb-image.fits")).data;
    let model = product(&d.join("pb-model.fits")).data;
    let mut image_pb = product(&d.join("pb-image-pb.fits"));
    let model_pb = product(&d.join("pb-model-pb.fits")).data;
    let (pixel_deg, ghz): (f64, f64) = (pb.key("CDELT2"), pb.key::<f64>("CRVAL3") * 1e-9);
    assert_eq!((pb.key::<String>("PBLIMIT"), pb.key::<String>("BUNIT")), ("0.1".to_string(), String::new()));
    let model_name: String = pb.key("PBMODEL");
    assert!(model_name.contains("EVLA Memo 195") && model_name.contains("1424 MHz"), "{model_name}");
    assert_eq!(image_pb.key::<String>("BUNIT"), "JY/BEAM");
    assert_eq!(image_pb.key::<f64>("CRVAL1"), pb.key::<f64>("CRVAL1"));

    // The beam: 1 at the phase centre (the reference pixel), the memo's polynomial at each
    // pixel's true distance from it.
    let n = 64;
    let centre = n / 2;
    assert_eq!(pb.data[centre * n + centre], 1.0);
    let mut worst: f64 = 0.0;
    for y in 0..n {
        for x in 0..n {
            let (l, m) = (((x as f64) - centre as f64) * pixel_deg.to_radians(), ((y as f64) - centre as f64) * pixel_deg.to_radians());
            let r_arcmin = (l * l + m * m).sqrt().asin().to_degrees() * 60.0;
            worst = worst.max((f64::from(pb.data[y * n + x]) - memo_1424(r_arcmin, ghz)).abs());
        }
    }
    assert!(worst < 1e-6, "the beam differs from the memo's by up to {worst}");

    // Corrected: divided by the beam where it reaches the cut, blank elsewhere; both occur.
    let (mut kept, mut blank) = (0, 0);
    for i in 0..n * n {
        let b = pb.data[i];
        for (corrected, original) in [(image_pb.data[i], image[i]), (model_pb[i], model[i])] {
            if b >= 0.1 {
                assert!((corrected - original / b).abs() <= 1e-6 * (original / b).abs().max(1e-6), "pixel {i}: {corrected} against {original} / {b}");
                kept += 1;
            } else {
                assert!(corrected.is_nan(), "pixel {i}: beam {b} below the cut, yet {corrected}");
                blank += 1;
            }
        }
    }
    assert!(kept > 1000 && blank > 100, "{kept} kept, {blank} blank");

    // A run without it at the same prefix retires them, as every other product it does not make.
    let mut args = common.to_vec();
    args.extend(["--name", "pb"]);
    check(&r2d2(&args, d));
    for suffix in ["pb", "image-pb", "model-pb"] {
        assert!(!d.join(format!("pb-{suffix}.fits")).exists(), "{suffix}");
    }
    // The cut as WSClean's -primary-beam-limit: more is blank at a higher one.
    let mut args = common.to_vec();
    args.extend(["--apply-primary-beam", "-primary-beam-limit", "0.5", "--name", "half"]);
    check(&r2d2(&args, d));
    let half = product(&d.join("half-image-pb.fits")).data;
    assert!(half.iter().filter(|v| v.is_nan()).count() > image_pb.data.iter().filter(|v| v.is_nan()).count());
}

#[test]
fn a_telescope_without_a_beam_model_is_refused_before_imaging() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let spec = ObservationSpec {
        telescope: "vla".into(),
        configurations: vec![("d".to_string(), 0.25)],
        dec_deg: 40.0,
        integration_s: 300.0,
        frequencies_hz: vec![1.4e9],
        flag_fraction: 0.0,
        random_rotation: false,
        seed: 1,
    };
    let cov = sample_coverage(&spec).unwrap();
    let n = cov.len();
    let table = VisTable { u_m: cov.u_m, v_m: cov.v_m, w_m: cov.w_m, frequency: cov.frequency_hz, vis: vec![Complex64::new(1.0, 0.0); n], ..Default::default() };
    write_parquet(&d.join("atca.parquet"), &table, &ObservationMeta::new(10.0, 40.0, "ATCA")).unwrap();
    let out = r2d2(&["image", "atca.parquet", "--size", "64", "--step", "clean", "--iterations", "1", "--apply-primary-beam", "--name", "x"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(err.contains("apply") && err.contains("primary") && err.contains("'ATCA'") && err.contains("VLA, MeerKAT"), "{err}");
    assert!(!err.contains("iteration 1"), "imaged before refusing: {err}");
    assert!(!d.join("x-dirty.fits").exists() && !d.join("x-pb.fits").exists());
    // A cut outside (0, 1), and the cut without the option, are refused naming the option.
    let out = r2d2(&["image", "atca.parquet", "--apply-primary-beam", "--primary-beam-limit", "1.5", "--name", "x"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("primary") && err.contains("between 0 and 1"), "{err}");
    let out = r2d2(&["image", "atca.parquet", "--primary-beam-limit", "0.2", "--name", "x"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("primary-beam-limit") && err.contains("apply_primary_beam as well"), "{err}");
    // r2d2 dirty writes the dirty image and the PSF only.
    let out = r2d2(&["dirty", "atca.parquet", "-apply-primary-beam", "--name", "x"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("r2d2 image --apply-primary-beam"), "{err}");
}
