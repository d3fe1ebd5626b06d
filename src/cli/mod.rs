//! Command-line interface: option parsing (clap) and dispatch to one module per command.

/// `println!` for the commands whose output is their result (`models`, `info`, `metrics`,
/// `validate`, `bench`): a closed or full standard output is an error naming it (exit 1), not a
/// panic, and not an exit 0 with the figures lost.
macro_rules! out {
    ($($arg:tt)*) => {
        crate::cli::write_stdout(format_args!($($arg)*))
    };
}


/// Whether descriptor 1 was closed when the process started. The standard library then puts
/// /dev/null there before `main` (so that no file opened later lands on it), after which a
/// closed standard output cannot be told from `> /dev/null`: it is looked at earlier, by a
/// constructor the loader runs before the runtime starts.
static STDOUT_CLOSED_AT_START: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

#[cfg(target_os = "linux")]
#[used]
#[link_section = ".init_array"]
static RECORD_STDOUT_AT_START: extern "C" fn() = record_stdout_at_start;

#[cfg(target_os = "linux")]
extern "C" fn record_stdout_at_start() {
    // SAFETY: F_GETFD only queries the flags of a descriptor number; it touches no memory.
    if unsafe { libc::fcntl(1, libc::F_GETFD) } == -1 {
        STDOUT_CLOSED_AT_START.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// One line to standard output, flushed, its failure an error.
pub(crate) fn write_stdout(line: std::fmt::Arguments<'_>) -> r2d2_imaging::Result<()> {
    use std::io::Write;
    let error = |e| r2d2_imaging::Error::io("standard output", e);
    if STDOUT_CLOSED_AT_START.load(std::sync::atomic::Ordering::Relaxed) {
        return Err(error(std::io::Error::other("closed: the output would be lost")));
    }
    let mut stdout = std::io::stdout().lock();
    writeln!(stdout, "{line}").and_then(|()| stdout.flush()).map_err(error)
}

mod bench;
mod convert;
mod dirty;
mod engine;
mod image;
mod info;
mod metrics;
mod models;
mod onnx_runtime;
mod run;
mod simulate;
mod trainset;
mod wsclean_args;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(name = "r2d2", version, about = "Radio-interferometric imaging with R2D2 deep-network series")]
struct Cli {
    /// More log output (-v: debug, -vv: trace).
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    /// Only errors.
    #[arg(short, long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Simulate an observation (the VLA by default, --telescope) of a sky image (or a procedural sky) into a Parquet table.
    Simulate(simulate::Args),
    /// Training data for R2D2 series: simulated VLA A+C observations of ground truths (.npy).
    Trainset(trainset::Args),
    /// Dirty image and PSF of a Parquet table or a MeasurementSet (PREFIX-dirty.fits, PREFIX-psf.fits).
    Dirty(dirty::Args),
    /// Run a pipeline described in YAML.
    Run(run::RunArgs),
    /// Check a pipeline description without running it.
    Validate(run::ValidateArgs),
    /// Image a Parquet table or a MeasurementSet with the default pipeline (pipelines/image.yaml).
    Image(image::Args),
    /// A MeasurementSet's Stokes I samples as a Parquet visibility table.
    Convert(convert::Args),
    /// Benchmarks of the hot paths, as JSON.
    #[command(subcommand)]
    Bench(bench::Command),
    /// SNR and logSNR of an estimate against a ground truth, as JSON.
    Metrics(metrics::Args),
    /// The model series under models/ (or a given directory) and their manifests' key facts
    Models(models::Args),
    /// What this build will use: ONNX inference backend, gridder SIMD level, threads
    Info(info::Args),
}

/// Exit status of `r2d2 image` where the products were written but the divergence guard
/// rejected the step's model (a series or CLEAN that diverged: the products hold the best
/// earlier iterate, or the empty model). 1 is every error, where nothing was delivered.
pub const EXIT_MODEL_REJECTED: u8 = 3;

pub fn main() -> ExitCode {
    r2d2_imaging::allocator::release_large_blocks_promptly();
    // WSClean's spellings (`-size 512 512`, `-weight briggs 0`, ...) read as this engine's, or
    // named with their counterpart; arguments that are not UTF-8 go to clap as they are.
    let args: Vec<std::ffi::OsString> = std::env::args_os().collect();
    // The command as typed (the program by its name) goes into the products' HISTORY.
    let program = args.first().and_then(|a| std::path::Path::new(a).file_name()).map_or("r2d2".into(), |n| n.to_string_lossy().into_owned());
    let words = std::iter::once(program).chain(args.iter().skip(1).map(|a| a.to_string_lossy().into_owned()));
    r2d2_imaging::job::record_command_line(words.map(|w| if w.is_empty() || w.contains(char::is_whitespace) { format!("'{w}'") } else { w }).collect::<Vec<_>>().join(" "));
    let cli = match args.iter().map(|a| a.to_str().map(str::to_string)).collect::<Option<Vec<String>>>() {
        Some(text) => match wsclean_args::rewrite(text) {
            Ok(rewritten) => Cli::parse_from(rewritten),
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::FAILURE;
            }
        },
        None => Cli::parse_from(args),
    };
    let level = match (cli.quiet, cli.verbose) {
        (true, _) => log::LevelFilter::Error,
        (false, 0) => log::LevelFilter::Info,
        (false, 1) => log::LevelFilter::Debug,
        (false, _) => log::LevelFilter::Trace,
    };
    if cli.quiet {
        r2d2_imaging::progress::silence();
    }
    env_logger::Builder::new()
        .filter_level(level)
        .format_target(false)
        .format_timestamp(None)
        .target(env_logger::Target::Pipe(Box::new(r2d2_imaging::progress::LogWriter)))
        // Through a pipe env_logger cannot tell whether stderr is a terminal.
        .write_style(if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
            env_logger::WriteStyle::Always
        } else {
            env_logger::WriteStyle::Never
        })
        .init();
    let mut model_rejected = false;
    let result = match cli.command {
        Command::Simulate(args) => simulate::run(args),
        Command::Dirty(args) => dirty::run(args),
        Command::Trainset(args) => trainset::run(args),
        Command::Metrics(args) => metrics::run(args),
        Command::Run(args) => run::run(args),
        Command::Validate(args) => run::validate(args),
        Command::Image(args) => image::run(args).map(|rejected| model_rejected = rejected),
        Command::Convert(args) => convert::run(args),
        Command::Bench(cmd) => bench::run(cmd),
        Command::Models(args) => models::run(args),
        Command::Info(args) => info::run(args),
    };
    match result {
        Ok(()) if model_rejected => {
            eprintln!("r2d2: products written, but the step's model was rejected (see the warning above): exit status {EXIT_MODEL_REJECTED}");
            ExitCode::from(EXIT_MODEL_REJECTED)
        }
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // The error and each of its causes, once.
            eprintln!("error: {}", e.report());
            ExitCode::FAILURE
        }
    }
}

/// Options shared by commands that make images.
#[derive(clap::Args, Clone, Debug)]
pub struct ImageOptions {
    /// Image size in pixels (N x N).
    #[arg(long, default_value_t = 512)]
    pub size: usize,
    /// Super-resolution factor: pixel = 1 / (SR * 2 * max_uv). Default: the series' own
    /// (`r2d2 image` with a series), else 1.5.
    #[arg(long, conflicts_with = "pixel_arcsec")]
    pub superresolution: Option<f64>,
    /// Pixel size in arcseconds (instead of --superresolution).
    #[arg(long)]
    pub pixel_arcsec: Option<f64>,
    /// natural, uniform, briggs, or given (the imaging weights that come with the data: a
    /// table's `imaging_weight` column, a .mat file's `nWimag`). Default: the series' own
    /// (`r2d2 image` with a series), else briggs.
    #[arg(long)]
    pub weighting: Option<String>,
    /// Briggs robustness R (implies briggs). Default: the series' own, else 0.
    #[arg(long, allow_hyphen_values = true)]
    pub robust: Option<f64>,
    /// Weighting grid: cells per axis / image size.
    #[arg(long, default_value_t = r2d2_imaging::weighting::DEFAULT_GRID_FACTOR)]
    pub weighting_grid_factor: f64,
    /// NUFFT accuracy (relative).
    #[arg(long, default_value_t = 1e-6)]
    pub epsilon: f64,
    /// NUFFT oversampling factor.
    #[arg(long, default_value_t = 2.0)]
    pub oversampling: f64,
    /// The w-term: auto (corrected by w-gridding where it turns a phase by more than
    /// --epsilon over the field), on, or off (coplanar, for comparison).
    #[arg(long, default_value = "auto", value_parser = r2d2_imaging::operator::WTermMode::from_name)]
    pub w_term: r2d2_imaging::operator::WTermMode,
    /// Threads (0: all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

/// The super-resolution factor when neither the options nor a series give one.
const DEFAULT_SUPERRESOLUTION: f64 = 1.5;

impl ImageOptions {
    /// The weighting the options ask for (`None`: none asked; `--robust` alone means Briggs).
    pub fn weighting(&self) -> r2d2_imaging::Result<Option<r2d2_imaging::Weighting>> {
        r2d2_imaging::Weighting::from_options(self.weighting.as_deref(), self.robust)
    }

    pub fn dirty_params(&self) -> r2d2_imaging::Result<r2d2_imaging::imaging::DirtyParams> {
        use r2d2_imaging::imaging::{DirtyParams, PixelScale};
        use r2d2_imaging::{limits, Error};
        limits::check_image_size(self.size).map_err(|m| Error::parameter("--size", m))?;
        limits::check_threads(self.threads).map_err(|m| Error::parameter("--threads", m))?;
        Ok(DirtyParams {
            size: self.size,
            pixel: match self.pixel_arcsec {
                Some(p) => PixelScale::Arcsec(p),
                None => PixelScale::SuperResolution(self.superresolution.unwrap_or(DEFAULT_SUPERRESOLUTION)),
            },
            weighting: self.weighting()?.unwrap_or(r2d2_imaging::Weighting::Briggs { robust: 0.0 }),
            grid_factor: self.weighting_grid_factor,
            nufft: r2d2_imaging::nufft::NufftParams { epsilon: self.epsilon, oversampling: self.oversampling },
            w_term: self.w_term,
            threads: self.threads,
        })
    }
}
