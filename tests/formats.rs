//! Every table format through the one reader (`vis::open`): the same observation as Parquet,
//! Arrow IPC (stream and file) and MATLAB .mat files as the reference implementation keeps
//! them (v5, v5 compressed, v7.3/HDF5; made with scipy and h5py by tests/make_mat.py) images
//! the same, by `r2d2 dirty`, after `r2d2 convert`, and by `r2d2 image`; the .mat's `nWimag`
//! is honoured by the `given` weighting (checked against the same samples with the imaging
//! weights folded into the natural ones); bad files are errors naming the file and variable.

mod common;

use r2d2_imaging::fits::read_image;
use std::path::Path;
use std::process::{Command, Output};

fn r2d2(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_r2d2")).args(args).current_dir(dir).output().expect("r2d2 runs")
}

fn check(out: &Output) {
    assert!(out.status.success(), "r2d2 failed: {}\nstderr: {}", out.status, String::from_utf8_lossy(&out.stderr));
}

fn python(args: &[&str], dir: &Path) {
    let out = Command::new("python3").args(args).current_dir(dir).output().expect("python3 runs (a test requirement)");
    assert!(out.status.success(), "python3 {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
}

fn make_mat(dir: &Path, out: &str, options: &[&str]) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/make_mat.py");
    let mut args = vec![script.to_str().unwrap(), "obs.parquet", out];
    args.extend_from_slice(options);
    python(&args, dir);
}

/// A one-channel observation (the reference's .mat holds one), its dirty image and PSF.
fn observation(dir: &Path) {
    check(&r2d2(
        &[
            "simulate", "--sky", "procedural:5", "--configs", "c", "--hours", "2", "--dec", "35", "--dr", "1000", "--size", "64",
            "--integration-s", "300", "--flag-fraction", "0.1", "--seed", "5", "--out", "obs.parquet",
        ],
        dir,
    ));
}

fn dirty(dir: &Path, input: &str, name: &str, weighting: &str) -> (Vec<f64>, Vec<f64>) {
    check(&r2d2(&["dirty", input, "--size", "64", "--weighting", weighting, "--name", name], dir));
    let read = |suffix: &str| read_image(&dir.join(format!("{name}-{suffix}.fits"))).unwrap().data;
    (read("dirty"), read("psf"))
}

/// Largest difference relative to the largest value of `b`.
fn relative(a: &[f64], b: &[f64]) -> f64 {
    let peak = b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    a.iter().zip(b).fold(0.0f64, |m, (x, y)| m.max((x - y).abs())) / peak
}

#[test]
fn every_format_images_as_the_parquet_table_it_was_made_from() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    python(
        &[
            "-c",
            "import pyarrow as pa, pyarrow.parquet as pq\nt = pq.read_table('obs.parquet')\nwith pa.ipc.new_stream('obs.arrows', t.schema) as w: w.write_table(t)\nwith pa.ipc.new_file('obs.arrow', t.schema) as w: w.write_table(t)\n",
        ],
        d,
    );
    make_mat(d, "v5.mat", &["--version", "5"]);
    make_mat(d, "v5z.mat", &["--version", "5z", "--rows"]);
    make_mat(d, "v73.mat", &["--version", "7.3"]);
    make_mat(d, "v73m.mat", &["--version", "7.3", "--unit-m", "--single"]);
    let (reference, psf) = dirty(d, "obs.parquet", "ref", "briggs");
    // Parquet and Arrow carry the same values; the .mat files carry them in double precision
    // through a change of units (v73m: visibilities and baselines rounded to single).
    for (input, tolerance) in [("obs.arrows", 0.0), ("obs.arrow", 0.0), ("v5.mat", 1e-6), ("v5z.mat", 1e-6), ("v73.mat", 1e-6), ("v73m.mat", 1e-5)] {
        let name = input.replace('.', "-");
        let (image, p) = dirty(d, input, &name, "briggs");
        assert!(relative(&image, &reference) <= tolerance, "{input}: dirty image {} off the Parquet table's", relative(&image, &reference));
        assert!(relative(&p, &psf) <= tolerance, "{input}: PSF {} off", relative(&p, &psf));
    }
    // `r2d2 convert` makes the Parquet format of each; `r2d2 image` reads a .mat directly.
    check(&r2d2(&["convert", "v73.mat", "from-mat.parquet"], d));
    let (converted, _) = dirty(d, "from-mat.parquet", "conv", "briggs");
    assert!(relative(&converted, &reference) <= 1e-6);
    check(&r2d2(&["image", "v5z.mat", "--size", "64", "--step", "clean", "--iterations", "2", "--name", "img"], d));
    assert!(d.join("img-model.fits").exists() && d.join("img-image.fits").exists());
    // A pipeline reads a .mat with `kind: mat`, as `r2d2 image` does; `kind: parquet` refuses
    // it before anything runs, naming the kind that reads it.
    let pipeline = |kind: &str| {
        format!(
            "image: {{size: 64, superresolution: 1.5}}\nstages:\n  read: {{kind: {kind}, files: v5z.mat, to: weights}}\n  weights: {{kind: weighting, scheme: briggs, robust: 0, to: grid}}\n  grid: {{kind: gridder, to: step}}\n  step: {{kind: clean, major_cycles: 2, to: update}}\n  update: {{kind: residual, to: step, done: write}}\n  write: {{kind: writer, prefix: yaml}}\n"
        )
    };
    std::fs::write(d.join("mat.yaml"), pipeline("mat")).unwrap();
    check(&r2d2(&["run", "mat.yaml"], d));
    let model = |prefix: &str| read_image(&d.join(format!("{prefix}-model.fits"))).unwrap().data;
    assert_eq!(model("yaml"), model("img"), "kind: mat images the .mat as r2d2 image does");
    std::fs::write(d.join("parquet.yaml"), pipeline("parquet")).unwrap();
    let out = r2d2(&["validate", "parquet.yaml"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("stages.read.files: v5z.mat is in the MATLAB .mat format, not Parquet: `kind: mat` reads it"), "{err}");
    // A .mat names no telescope (`unknown`): `auto` runs the series for the size, with no
    // telescope warning and no fall-back to CLEAN, as on a table that names none.
    let out = r2d2(&["image", "v5z.mat", "--size", "64", "--iterations", "1", "--name", "auto"], d);
    check(&out);
    let metrics = std::fs::read_to_string(d.join("auto-metrics.json")).unwrap();
    assert!(!metrics.contains("built-in CLEAN") && !metrics.contains("the telescope 'unknown'"), "{metrics}");
    assert!(String::from_utf8_lossy(&out.stderr).contains("series 'vla-r2d2"), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn a_mats_imaging_weights_are_used_by_the_given_weighting() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    make_mat(d, "iw.mat", &["--version", "5", "--imaging-weights", "--folded", "folded.parquet"]);
    make_mat(d, "iw73.mat", &["--version", "7.3", "--imaging-weights"]);
    let (folded, folded_psf) = dirty(d, "folded.parquet", "folded", "natural");
    for input in ["iw.mat", "iw73.mat"] {
        let name = input.replace('.', "-");
        let (given, psf) = dirty(d, input, &name, "given");
        assert!(relative(&given, &folded) < 1e-6 && relative(&psf, &folded_psf) < 1e-6, "{input}: {}", relative(&given, &folded));
        // They are weights, not ignored: natural weighting of the .mat is another image.
        let (natural, _) = dirty(d, input, &format!("{name}-nat"), "natural");
        assert!(relative(&natural, &folded) > 1e-3, "{input}: the given weights changed nothing");
    }
    // A table without imaging weights cannot be weighted `given`.
    let out = r2d2(&["dirty", "obs.parquet", "--size", "64", "--weighting", "given"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("given") && err.contains("carry none"), "{err}");
}

#[test]
fn bad_mat_files_are_errors_naming_the_file_and_variable() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    make_mat(d, "no-y.mat", &["--version", "5", "--drop", "y"]);
    make_mat(d, "no-freq.mat", &["--version", "7.3", "--drop", "frequency"]);
    make_mat(d, "good.mat", &["--version", "5z"]);
    let bytes = std::fs::read(d.join("good.mat")).unwrap();
    std::fs::write(d.join("cut.mat"), &bytes[..bytes.len() / 2]).unwrap();
    let mut header_only = bytes[..128].to_vec();
    // An element declaring far more bytes than the file holds.
    header_only.extend_from_slice(&[14, 0, 0, 0, 0xff, 0xff, 0xff, 0x7f]);
    std::fs::write(d.join("huge.mat"), header_only).unwrap();
    for (file, words) in [
        ("no-y.mat", vec!["no-y.mat", "`y`"]),
        ("no-freq.mat", vec!["no-freq.mat", "`frequency`"]),
        ("cut.mat", vec!["cut.mat"]),
        ("huge.mat", vec!["huge.mat", "past the end"]),
    ] {
        let out = r2d2(&["dirty", file, "--size", "64"], d);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && !err.contains("panicked"), "{file}: {err}");
        for w in words {
            assert!(err.contains(w), "{file}: '{w}' missing from: {err}");
        }
    }
}

/// `r2d2` with `args` in `dir`, killed (and the test failed) after `limit`.
fn r2d2_within(args: &[&str], dir: &Path, limit: std::time::Duration) -> Output {
    common::output_within(Command::new(env!("CARGO_BIN_EXE_r2d2")).args(args).current_dir(dir).stdin(std::process::Stdio::null()), limit)
}

/// A FIFO fed `file` by a writer of its own (`cat`, killed when done with: it blocks until
/// a reader opens the FIFO, which a refused input never does).
struct FedFifo(std::process::Child);

impl FedFifo {
    fn new(dir: &Path, fifo: &str, file: &str) -> FedFifo {
        let _ = std::fs::remove_file(dir.join(fifo));
        assert!(Command::new("mkfifo").arg(dir.join(fifo)).status().expect("mkfifo runs").success());
        FedFifo(Command::new("sh").args(["-c", &format!("cat {file} > {fifo}")]).current_dir(dir).spawn().unwrap())
    }
}

impl Drop for FedFifo {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A table given as a named pipe (`mkfifo`, or the shell's `<(cat obs.mat)`) is refused at
/// once, naming it: it was opened twice, the first open taking the bytes that told its
/// format and the second waiting for a writer for ever (.mat), or read as empty (Parquet,
/// Arrow). The Arrow IPC source stage reads such a stream once, and images it.
#[cfg(unix)]
#[test]
fn a_table_given_as_a_named_pipe_is_refused_at_once_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    make_mat(d, "obs.mat", &["--version", "5"]);
    python(
        &["-c", "import pyarrow as pa, pyarrow.parquet as pq\nt = pq.read_table('obs.parquet')\nwith pa.ipc.new_stream('obs.arrows', t.schema) as w: w.write_table(t)\n"],
        d,
    );
    let limit = std::time::Duration::from_secs(60);
    for file in ["obs.mat", "obs.parquet", "obs.arrows"] {
        let fifo = format!("fifo-{file}");
        let _writer = FedFifo::new(d, &fifo, file);
        for command in ["dirty", "convert"] {
            let args: Vec<&str> = if command == "dirty" { vec!["dirty", &fifo, "--size", "64", "--name", "p"] } else { vec!["convert", &fifo, "p.parquet"] };
            let out = r2d2_within(&args, d, limit);
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(!out.status.success(), "{file} through a FIFO: {command} succeeded");
            assert!(err.contains(&format!("{fifo}: a FIFO (named pipe), not a regular file")) && err.contains("save it to a file"), "{file}: {err}");
        }
        assert!(!d.join("p-dirty.fits").exists() && !d.join("p.parquet").exists());
    }
    // Read once as a stream by the Arrow IPC source: imaged as the file itself is.
    let pipeline = |path: &str| format!("name: fifo\nimage:\n  size: 64\nstages:\n  source:\n    kind: arrow-ipc\n    path: {path}\n    id: obs\n    to: weights\n  weights:\n    kind: weighting\n    scheme: briggs\n    robust: 0\n    to: grid\n  grid:\n    kind: gridder\n    to: write\n  write:\n    kind: writer\n    prefix: \"out-{path}/{{job}}\"\n");
    std::fs::write(d.join("file.yaml"), pipeline("obs.arrows")).unwrap();
    check(&r2d2(&["run", "file.yaml"], d));
    std::fs::write(d.join("fifo.yaml"), pipeline("fifo.arrows")).unwrap();
    let _writer = FedFifo::new(d, "fifo.arrows", "obs.arrows");
    check(&r2d2_within(&["run", "fifo.yaml"], d, limit));
    let image = |path: &str| read_image(&d.join(format!("out-{path}/obs-dirty.fits"))).unwrap().data;
    assert_eq!(image("fifo.arrows"), image("obs.arrows"));
}

/// Every codec Parquet writers use (pyarrow: snappy by default, gzip, brotli, lz4, zstd) and
/// Arrow IPC's two (LZ4 frame, ZSTD) read as the uncompressed table; a compressed IPC
/// buffer declaring more bytes than memory holds is refused before anything is allocated.
#[test]
fn every_parquet_and_arrow_ipc_compression_codec_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    python(
        &[
            "-c",
            "import pyarrow as pa, pyarrow.parquet as pq\nt = pq.read_table('obs.parquet')\nfor c in ['none', 'snappy', 'gzip', 'brotli', 'lz4', 'zstd']:\n    pq.write_table(t, f'c-{c}.parquet', compression=c)\nfor c in ['lz4', 'zstd']:\n    o = pa.ipc.IpcWriteOptions(compression=c)\n    with pa.ipc.new_stream(f'c-{c}.arrows', t.schema, options=o) as w: w.write_table(t)\n    with pa.ipc.new_file(f'c-{c}.arrow', t.schema, options=o) as w: w.write_table(t)\n",
        ],
        d,
    );
    let (reference, psf) = dirty(d, "obs.parquet", "ref", "briggs");
    for codec in ["none", "snappy", "gzip", "brotli", "lz4", "zstd"] {
        let mut inputs = vec![format!("c-{codec}.parquet")];
        if matches!(codec, "lz4" | "zstd") {
            inputs.extend([format!("c-{codec}.arrows"), format!("c-{codec}.arrow")]);
        }
        for input in inputs {
            let (image, p) = dirty(d, &input, &input.replace('.', "-"), "briggs");
            assert!(relative(&image, &reference) == 0.0 && relative(&p, &psf) == 0.0, "{input}: {}", relative(&image, &reference));
        }
    }
    // A compressed buffer's first 8 bytes declare its decompressed length; arrow allocates
    // that much before decompressing. Found after the stream's schema message, by the
    // LZ4 frame magic that follows the length (the first buffer of the first batch).
    let mut bytes = std::fs::read(d.join("c-lz4.arrows")).unwrap();
    let frame = bytes.windows(4).position(|w| w == [0x04, 0x22, 0x4d, 0x18]).expect("an LZ4 frame");
    bytes[frame - 8..frame].copy_from_slice(&(1i64 << 50).to_le_bytes());
    std::fs::write(d.join("huge.arrows"), bytes).unwrap();
    let out = r2d2(&["dirty", "huge.arrows", "--size", "64"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("huge.arrows") && err.contains("a compressed record batch declares 11258999") && err.contains("once decompressed, more than"), "{err}");
}

/// Valid FITS images as astropy writes them: scaled integers (BITPIX 16 and 8 with BSCALE and
/// BZERO, each stored pixel 2 or 1 bytes) and gzip-compressed (`.fits.gz`), read as the truth
/// of `metrics` and as the sky of `simulate` (they were refused as truncated: the stored size
/// was taken from the scaled type, or from the compressed file).
#[test]
fn scaled_and_gzipped_fits_images_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    python(
        &[
            "-c",
            "from astropy.io import fits\nimport numpy as np\nh = fits.open('obs.sky.fits')[0]\nfor name, kind in [('sky16.fits', 'int16'), ('sky8.fits', 'uint8')]:\n    hdu = fits.PrimaryHDU(h.data.astype(np.float64), header=h.header.copy())\n    hdu.scale(kind, 'minmax')\n    hdu.writeto(name)\n    assert fits.getheader(name)['BITPIX'] == int(kind.strip('uint')) and 'BSCALE' in fits.getheader(name)\nfits.PrimaryHDU(h.data, header=h.header).writeto('sky.fits.gz')\n",
        ],
        d,
    );
    // BITPIX 8 keeps 256 levels of the sky, 16 bits 65536, gzip every bit.
    for (file, least_snr) in [("sky.fits.gz", f64::INFINITY), ("sky16.fits", 60.0), ("sky8.fits", 20.0)] {
        let out = r2d2(&["metrics", "--truth", file, "--estimate", "obs.sky.fits", "--dr", "1000"], d);
        check(&out);
        let metrics: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        // An exact match has no finite SNR (printed as null).
        let snr = metrics["snr"].as_f64().unwrap_or(f64::INFINITY);
        assert!(snr >= least_snr, "{file}: SNR {snr} against the float sky: {metrics}");
        let table = format!("from-{file}.parquet");
        check(&r2d2(&["simulate", "--sky", file, "--configs", "c", "--hours", "0.25", "--integration-s", "300", "--seed", "5", "--out", &table], d));
        assert!(d.join(&table).exists(), "{file}");
    }
}

/// .mat variables of the wrong kind say what they hold and what was expected: complex weights
/// (the count was compared and found equal), a text frequency ("holds 0 values"), a number as
/// the unit (taken as wavelengths without a word), a variable that is an HDF5 soft link (an
/// offset of 0xffffffffffffffff); a soft link the reader does not use is passed over. Half of
/// `y` NaN images the rest, with a warning saying how many were excluded and why.
#[test]
fn mat_variables_of_the_wrong_kind_say_what_they_hold_and_what_was_expected() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    observation(d);
    make_mat(d, "obs.mat", &["--version", "5"]);
    make_mat(d, "obs73.mat", &["--version", "7.3"]);
    python(
        &[
            "-c",
            "import scipy.io as sio, numpy as np, h5py, shutil\nm = {k: v for k, v in sio.loadmat('obs.mat').items() if not k.startswith('__')}\nn = m['y'].size\ndef save(name, **change):\n    sio.savemat(name, {**m, **change})\nsave('cplx-nwimag.mat', nWimag=(np.ones(n) + 1j).reshape(-1, 1))\nsave('cplx-nw.mat', nW=(np.ones(n) + 1j).reshape(-1, 1))\nsave('text-freq.mat', frequency='1.4e9')\nsave('num-unit.mat', unit=np.float64(3))\ny = m['y'].copy()\ny[::2] = np.nan\nsave('nan-y.mat', y=y)\nfor name, link in [('link-nw.mat', 'nW'), ('link-other.mat', 'x')]:\n    shutil.copy('obs73.mat', name)\n    with h5py.File(name, 'a') as f:\n        if link in f: del f[link]\n        f[link] = h5py.SoftLink('/u')\n",
        ],
        d,
    );
    for (file, variable, expected) in [
        ("cplx-nwimag.mat", "nWimag", "complex values: expected real numbers"),
        ("cplx-nw.mat", "nW", "complex values: expected real numbers"),
        ("text-freq.mat", "frequency", "holds text ('1.4e9'): expected a real number (Hz)"),
        ("num-unit.mat", "unit", "holds a number (3): expected text ('m', or none for wavelengths)"),
        ("link-nw.mat", "nW", "is at the root but is no dataset it can read (expected a dataset, as MATLAB writes each variable; a soft or external link?)"),
    ] {
        let out = r2d2(&["dirty", file, "--size", "64"], d);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(&format!("{file}: ")) && err.contains(&format!("`{variable}` ")) && err.contains(expected), "{file}: {err}");
    }
    check(&r2d2(&["dirty", "link-other.mat", "--size", "64", "--name", "other"], d));
    let out = r2d2(&["dirty", "nan-y.mat", "--size", "64", "--name", "nan"], d);
    check(&out);
    let err = String::from_utf8_lossy(&out.stderr);
    let warning = err.lines().find(|l| l.starts_with("[WARN ] nan-y.mat: ")).unwrap_or_else(|| panic!("no warning: {err}"));
    let counts: Vec<u64> = warning.split_whitespace().filter_map(|w| w.parse().ok()).take(2).collect();
    assert!(warning.contains("samples excluded: a value not finite (NaN") && counts.len() == 2 && counts[0] == (counts[1] + 1) / 2, "{warning}");
}
