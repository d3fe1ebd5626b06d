//! `r2d2 trainset`: a training/validation/test set for R2D2 series, one simulated
//! observation per ground truth, written as stacked .npy arrays plus per-sample scalars.

use ndarray::{Array2, Array3};
use crate::fits::{read_image, write_image, BrightnessUnit, ImageWcs};
use crate::vis::{write_parquet, ObservationMeta, VisTable};
use crate::nufft::NufftParams;
use crate::simulate::trainset::{make_sample, SampleInfo, TrainSample, TrainsetParams, TruthSource};
use crate::{Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

#[derive(clap::Args)]
pub struct Args {
    /// Directory of ground truths (2-D .npy float32/float64 or FITS, N x N, non-negative,
    /// zero background), used in file-name order; each is exponentiated to its sample's DR.
    #[arg(long, conflicts_with = "procedural", required_unless_present = "procedural")]
    truths: Option<PathBuf>,
    /// Dynamic range of the --truths images before exponentiation (1 / their noise level).
    #[arg(long, default_value_t = 50.0)]
    source_dr: f64,
    /// Instead of --truths: this many procedural radio skies (sky seed = sample seed).
    #[arg(long)]
    procedural: Option<usize>,
    /// Kind of procedural sky: `classic` (compact sources, Gaussian complexes, double-lobed
    /// galaxies, thresholded diffuse patches), `extended` (textured lobes, spiral disks,
    /// halos and relics: emission over decades of brightness across large areas) or
    /// `field-filling` (the same objects, one spanning the field inside a faint cocoon).
    #[arg(long, value_enum, default_value_t = SkyKind::Classic)]
    sky: SkyKind,
    /// Convolve each truth with a Gaussian of this FWHM in pixels (then peak 1, cut at 1/DR),
    /// or `LOW..HIGH` drawn per sample: the sky as imaged at that resolution, as real radio
    /// images are, with no texture finer than the data measure (`training/README.md`).
    #[arg(long, value_parser = parse_range)]
    truth_fwhm_px: Option<(f64, f64)>,
    /// Image size N.
    #[arg(long, default_value_t = 128)]
    size: usize,
    /// Seed of sample 0; sample k uses SEED + k.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Lowest and highest target dynamic range (log-uniform).
    #[arg(long, default_value_t = 1e3)]
    dr_min: f64,
    #[arg(long, default_value_t = 1e5)]
    dr_max: f64,
    /// Telescope whose training preset the observations are drawn from
    /// (`data/telescopes/telescopes.yaml`: vla, meerkat, ska-mid).
    #[arg(long, default_value = "vla")]
    telescope: String,
    /// Integration time in seconds (longer: fewer points, faster); `LOW..HIGH` draws one per
    /// sample. Default: the telescope's training preset's.
    #[arg(long, value_parser = parse_range)]
    integration_s: Option<(f64, f64)>,
    /// Super-resolution factor, or `LOW..HIGH` drawn per sample.
    #[arg(long, default_value = "1.5", value_parser = parse_range)]
    superresolution: (f64, f64),
    /// Briggs robustness, or `LOW..HIGH` drawn per sample (e.g. `-1..1`).
    #[arg(long, default_value = "0", allow_hyphen_values = true, value_parser = parse_range)]
    robust: (f64, f64),
    /// NUFFT accuracy.
    #[arg(long, default_value_t = 1e-6)]
    epsilon: f64,
    /// Samples simulated at once (0: all cores); each runs single-threaded.
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Also write each sample's visibilities (vis/NNNNN.parquet) and truth (vis/NNNNN.sky.fits),
    /// for imaging test samples with other methods.
    #[arg(long)]
    parquet: bool,
    /// Output directory (replaced as a whole once every sample is done).
    #[arg(long)]
    out: PathBuf,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum SkyKind {
    Classic,
    Extended,
    FieldFilling,
}

/// `X` (a fixed value) or `LOW..HIGH` (a range drawn from per sample).
fn parse_range(text: &str) -> std::result::Result<(f64, f64), String> {
    let number = |t: &str| t.trim().parse::<f64>().map_err(|_| format!("expected a number or LOW..HIGH, got '{text}'"));
    let (lo, hi) = match text.split_once("..") {
        Some((lo, hi)) => (number(lo)?, number(hi)?),
        None => (number(text)?, number(text)?),
    };
    if !(lo <= hi) {
        return Err(format!("expected LOW <= HIGH, got '{text}'"));
    }
    Ok((lo, hi))
}

/// A range as the set's description records it: a number when fixed, `[low, high]` otherwise.
fn range_json((lo, hi): (f64, f64)) -> serde_json::Value {
    if lo == hi {
        serde_json::json!(lo)
    } else {
        serde_json::json!([lo, hi])
    }
}

#[derive(Serialize)]
struct SampleRecord<'a> {
    index: usize,
    source: String,
    #[serde(flatten)]
    info: &'a SampleInfo,
}

fn read_truth(path: &Path) -> Result<Vec<f64>> {
    let is_npy = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    if is_npy {
        let file = || std::fs::File::open(path).map_err(|e| Error::io(path, e));
        let array: Array2<f64> = match ndarray_npy::ReadNpyExt::read_npy(file()?) {
            Ok(a) => a,
            Err(_) => {
                let a: Array2<f32> = ndarray_npy::ReadNpyExt::read_npy(file()?)
                    .map_err(|e| Error::input(path, format!("expected a 2-D float32 or float64 .npy array: {e}")))?;
                a.mapv(f64::from)
            }
        };
        if array.nrows() != array.ncols() {
            return Err(Error::input(path, format!("expected a square image, got {:?}", array.shape())));
        }
        Ok(array.iter().copied().collect())
    } else {
        let image = read_image(path)?;
        if image.nx != image.ny {
            return Err(Error::input(path, format!("expected a square image, got {} x {}", image.nx, image.ny)));
        }
        Ok(image.data)
    }
}

fn truth_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut files = Vec::new();
    for entry in entries {
        let path = entry.map_err(|e| Error::io(dir, e))?.path();
        let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
        if matches!(ext.as_deref(), Some("npy" | "fits" | "fit")) {
            files.push(path);
        }
    }
    files.sort();
    if files.is_empty() {
        return Err(Error::input(dir, "no .npy or .fits ground truths in this directory"));
    }
    Ok(files)
}

fn stack(samples: &[TrainSample], n: usize, pick: impl Fn(&TrainSample) -> &[f64]) -> Array3<f32> {
    let data: Vec<f32> = samples.iter().flat_map(|s| pick(s).iter().map(|&v| v as f32)).collect();
    Array3::from_shape_vec((samples.len(), n, n), data).expect("every sample has n x n pixels")
}

/// Phase centre of the simulated observations: RA is arbitrary, Dec the drawn declination.
const PHASE_CENTRE_RA_DEG: f64 = 180.0;

/// Write sample `k`'s visibilities and sky into `dir` (`--parquet`), as soon as it is made:
/// held until the end, every sample's table at once (a MeerKAT sample's takes a few hundred
/// MB) exhausted the memory of sets of a few dozen.
fn write_visibilities(dir: &Path, k: usize, s: &TrainSample, table: &VisTable) -> Result<()> {
    let dec = s.info.observation.dec_deg;
    let meta = ObservationMeta {
        phase_centre_ra_deg: PHASE_CENTRE_RA_DEG,
        phase_centre_dec_deg: dec,
        telescope: crate::simulate::telescope::telescope(&s.info.observation.telescope)?.name.clone(),
        noise_sigma: Some(s.info.tau),
        dynamic_range: Some(s.info.observation.dynamic_range),
        extra: [("simulation_seed".to_string(), s.info.seed.to_string())].into_iter().collect(),
    };
    write_parquet(&dir.join(format!("{k:05}.parquet")), table, &meta)?;
    let wcs = ImageWcs { ra_deg: PHASE_CENTRE_RA_DEG, dec_deg: dec, pixel_deg: s.pixel_rad.to_degrees(), freq_hz: None, bandwidth_hz: None };
    let n = (s.truth.len() as f64).sqrt() as usize;
    write_image(&dir.join(format!("{k:05}.sky.fits")), &s.truth, n, n, &wcs, BrightnessUnit::JyPerPixel, None, &[])
}

/// The set's `.partial` directory, removed when this is dropped unless the set was swapped in:
/// a set that fails anywhere (a sample, a write, the swap, a panic) leaves none of what it wrote.
struct PartialDir<'a> {
    path: &'a Path,
    swapped_in: bool,
}

impl Drop for PartialDir<'_> {
    fn drop(&mut self) {
        if !self.swapped_in {
            let _ = std::fs::remove_dir_all(self.path);
        }
    }
}

fn write_json(path: &Path, value: &impl Serialize) -> Result<()> {
    let text = serde_json::to_string_pretty(value).map_err(|e| Error::parameter("json", e.to_string()))?;
    std::fs::write(path, text).map_err(|e| Error::io(path, e))
}

pub fn run(args: Args) -> Result<()> {
    let telescope = crate::simulate::telescope::telescope(&args.telescope)?;
    let integration_s = args.integration_s.unwrap_or((telescope.training.integration_s, telescope.training.integration_s));
    let params = TrainsetParams {
        telescope,
        size: args.size,
        superresolution: args.superresolution,
        robust: args.robust,
        dynamic_range: (args.dr_min, args.dr_max),
        integration_s,
        truth_fwhm_px: args.truth_fwhm_px,
        nufft: NufftParams { epsilon: args.epsilon, oversampling: 2.0 },
    };
    // The library's field is the range; the command line gives it as two options.
    params.validate().map_err(|e| match e {
        Error::Parameter { name, message } if name == "dynamic_range" => Error::parameter("--dr-min/--dr-max", message),
        other => other,
    })?;
    crate::limits::check_image_size(args.size).map_err(|m| Error::parameter("--size", m))?;
    crate::limits::check_threads(args.threads).map_err(|m| Error::parameter("--threads", m))?;
    let (sources, truths): (Vec<String>, Vec<Option<Vec<f64>>>) = match (&args.truths, args.procedural) {
        (Some(dir), _) => {
            let files = truth_files(dir)?;
            let mut truths = Vec::with_capacity(files.len());
            for f in &files {
                let t = read_truth(f)?;
                if t.len() != args.size * args.size {
                    return Err(Error::input(f, format!("expected a {0} x {0} image (--size)", args.size)));
                }
                truths.push(Some(t));
            }
            (files.iter().map(|f| f.file_name().unwrap_or_default().to_string_lossy().into_owned()).collect(), truths)
        }
        (None, Some(count)) if count > 0 => {
            let kind = match args.sky {
                SkyKind::Classic => "procedural",
                SkyKind::Extended => "extended",
                SkyKind::FieldFilling => "field-filling",
            };
            ((0..count).map(|k| format!("{kind}:{}", args.seed + k as u64)).collect(), vec![None; count])
        }
        _ => return Err(Error::parameter("procedural", "expected --truths DIR or --procedural COUNT > 0")),
    };
    let total = truths.len();
    // Plain threads taking the next sample in turn, not a rayon pool: a rayon worker waiting
    // for its sample's single-threaded compute pool steals further samples meanwhile, so
    // samples piled up at once (MeerKAT's, a few GB each, exhausted the memory).
    let workers = if args.threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { args.threads }.min(total.max(1));
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    let started = std::time::Instant::now();
    let made: Vec<std::sync::Mutex<Option<Result<TrainSample>>>> = (0..total).map(|_| std::sync::Mutex::new(None)).collect();
    // Everything is written beside the target, then swapped in: never a half-written set.
    let partial = args.out.with_extension("partial");
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(|e| Error::io(&partial, e))?;
    }
    let vis_dir = partial.join("vis");
    std::fs::create_dir_all(if args.parquet { &vis_dir } else { &partial }).map_err(|e| Error::io(&partial, e))?;
    let mut guard = PartialDir { path: &partial, swapped_in: false };
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| loop {
                let k = next.fetch_add(1, Ordering::Relaxed);
                if k >= total {
                    break;
                }
                let seed = args.seed + k as u64;
                let source = match &truths[k] {
                    Some(data) => TruthSource::Image { data, source_dr: args.source_dr },
                    None => match args.sky {
                        SkyKind::Classic => TruthSource::Procedural { seed },
                        SkyKind::Extended => TruthSource::Extended { seed },
                        SkyKind::FieldFilling => TruthSource::FieldFilling { seed },
                    },
                };
                let sample = make_sample(source, &params, seed, 1, args.parquet)
                    .and_then(|mut s| {
                        if let Some(table) = s.table.take() {
                            write_visibilities(&vis_dir, k, &s, &table)?;
                        }
                        Ok(s)
                    })
                    .map_err(|e| Error::parameter(format!("sample {k} ({})", sources[k]), e.to_string()));
                let failed = sample.is_err();
                *made[k].lock().expect("no worker panics holding a slot") = Some(sample);
                if failed {
                    // The first error ends the set: no more samples are started.
                    next.store(total, Ordering::Relaxed);
                    break;
                }
                let finished = done.fetch_add(1, Ordering::Relaxed) + 1;
                if finished % 20 == 0 || finished == total {
                    log::info!("{finished}/{total} samples, {:.1} s", started.elapsed().as_secs_f64());
                }
            });
        }
    });
    // Slots are taken in order, so every slot before a failed one is filled: the first
    // error is met before any slot left empty.
    let samples: Vec<TrainSample> = made.into_iter().map_while(|slot| slot.into_inner().expect("no worker panics holding a slot")).collect::<Result<_>>()?;
    let n = args.size;
    let arrays: [(&str, Array3<f32>); 4] = [
        ("truth.npy", stack(&samples, n, |s| &s.truth)),
        ("dirty.npy", stack(&samples, n, |s| &s.dirty)),
        ("noise_dirty.npy", stack(&samples, n, |s| &s.noise_dirty)),
        ("psf2n.npy", stack(&samples, 2 * n, |s| &s.psf_2n)),
    ];
    for (name, array) in &arrays {
        let path = partial.join(name);
        let file = std::fs::File::create(&path).map_err(|e| Error::io(&path, e))?;
        ndarray_npy::WriteNpyExt::write_npy(array, std::io::BufWriter::new(file))
            .map_err(|e| Error::input(&path, format!("writing .npy: {e}")))?;
    }
    let records: Vec<SampleRecord> =
        samples.iter().enumerate().map(|(index, s)| SampleRecord { index, source: sources[index].clone(), info: &s.info }).collect();
    write_json(&partial.join("samples.json"), &records)?;
    let points: Vec<usize> = samples.iter().map(|s| s.info.points).collect();
    write_json(
        &partial.join("trainset.json"),
        &serde_json::json!({
            "samples": total,
            "size": n,
            "seed": args.seed,
            "truths": args.truths.as_ref().map(|p| p.display().to_string()),
            "source_dr": args.truths.as_ref().map(|_| args.source_dr),
            "procedural": args.procedural,
            "sky": args.procedural.and_then(|_| clap::ValueEnum::to_possible_value(&args.sky)).map(|v| v.get_name().to_string()),
            "truth_fwhm_px": args.truth_fwhm_px.map(range_json),
            "telescope": telescope.key,
            "track_hours": telescope.training.configurations.iter().cloned().zip(telescope.training.hours.iter().copied()).collect::<std::collections::BTreeMap<_, _>>(),
            "dynamic_range": [args.dr_min, args.dr_max],
            "integration_s": range_json(integration_s),
            "superresolution": range_json(args.superresolution),
            "weighting": {"scheme": "briggs", "robust": range_json(args.robust)},
            "epsilon": args.epsilon,
            "points_min": points.iter().min(),
            "points_max": points.iter().max(),
            "seconds": started.elapsed().as_secs_f64(),
            "r2d2_version": env!("CARGO_PKG_VERSION"),
        }),
    )?;
    // A set already at the target is moved aside, not removed, until the new one is in its
    // place: a failed swap puts it back.
    let previous = PathBuf::from({
        let mut name = args.out.clone().into_os_string();
        name.push(".previous");
        name
    });
    if args.out.exists() {
        if previous.exists() {
            std::fs::remove_dir_all(&previous).map_err(|e| Error::io(&previous, e))?;
        }
        std::fs::rename(&args.out, &previous).map_err(|e| Error::io(&args.out, e))?;
    }
    if let Err(e) = std::fs::rename(&partial, &args.out) {
        if previous.exists() {
            let _ = std::fs::rename(&previous, &args.out);
        }
        return Err(Error::io(&args.out, e));
    }
    guard.swapped_in = true;
    if previous.exists() {
        std::fs::remove_dir_all(&previous).map_err(|e| Error::io(&previous, e))?;
    }
    log::info!(
        "wrote {total} samples to {} in {:.1} s ({}..{} points each)",
        args.out.display(),
        started.elapsed().as_secs_f64(),
        points.iter().min().unwrap_or(&0),
        points.iter().max().unwrap_or(&0)
    );
    Ok(())
}
