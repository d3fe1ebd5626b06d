//! Command-line interface: option parsing (clap) and dispatch to one module per command. Only
//! [`main`] is public: the commands are the interface, not their option structs.

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
pub(crate) fn write_stdout(line: std::fmt::Arguments<'_>) -> crate::Result<()> {
    use std::io::Write;
    let error = |e| crate::Error::io("standard output", e);
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

/// Where `r2d2 image` and `r2d2 dirty` write their products when no `--name` is given.
const DEFAULT_NAME: &str = "r2d2";

/// Exit status of `r2d2 image` where the products were written but the divergence guard
/// rejected the step's model (a series or CLEAN that diverged: the products hold the best
/// earlier iterate, or the empty model). 1 is every error, where nothing was delivered.
pub const EXIT_MODEL_REJECTED: u8 = 3;

pub fn main() -> ExitCode {
    crate::allocator::release_large_blocks_promptly();
    // WSClean's spellings (`-size 512 512`, `-weight briggs 0`, ...) read as this engine's, or
    // named with their counterpart; arguments that are not UTF-8 go to clap as they are.
    let args: Vec<std::ffi::OsString> = std::env::args_os().collect();
    // The command as typed (the program by its name) goes into the products' HISTORY.
    let program = args.first().and_then(|a| std::path::Path::new(a).file_name()).map_or("r2d2".into(), |n| n.to_string_lossy().into_owned());
    let words = std::iter::once(program).chain(args.iter().skip(1).map(|a| a.to_string_lossy().into_owned()));
    crate::job::record_command_line(words.map(|w| if w.is_empty() || w.contains(char::is_whitespace) { format!("'{w}'") } else { w }).collect::<Vec<_>>().join(" "));
    let words: Vec<std::ffi::OsString> = match args.iter().map(|a| a.to_str().map(str::to_string)).collect::<Option<Vec<String>>>() {
        Some(text) => match wsclean_args::rewrite(text) {
            Ok(rewritten) => rewritten.into_iter().map(Into::into).collect(),
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::FAILURE;
            }
        },
        None => args,
    };
    let matches = <Cli as clap::CommandFactory>::command().get_matches_from(words);
    let cli = match <Cli as clap::FromArgMatches>::from_arg_matches(&matches) {
        Ok(cli) => cli,
        Err(e) => e.exit(),
    };
    let subcommand = matches.subcommand_name().unwrap_or_default().to_string();
    let level = match (cli.quiet, cli.verbose) {
        (true, _) => log::LevelFilter::Error,
        (false, 0) => log::LevelFilter::Info,
        (false, 1) => log::LevelFilter::Debug,
        (false, _) => log::LevelFilter::Trace,
    };
    if cli.quiet {
        crate::progress::silence();
    }
    env_logger::Builder::new()
        .filter_level(level)
        .format_target(false)
        .format_timestamp(None)
        .target(env_logger::Target::Pipe(Box::new(crate::progress::LogWriter)))
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
            eprintln!("error: {}", spelled_as_options(e, &subcommand).report());
            ExitCode::FAILURE
        }
    }
}

/// The error with the option it names (the library names the request's fields and the
/// commands' own, `auto_threshold`, `set`) spelled as the command line spells it
/// (`--auto-threshold`, `--set`).
fn spelled_as_options(error: crate::Error, subcommand: &str) -> crate::Error {
    match error {
        crate::Error::Parameter { name, message } => {
            let command = <Cli as clap::CommandFactory>::command();
            let long = command
                .find_subcommand(subcommand)
                .and_then(|c| c.get_arguments().find(|a| a.get_id() == name.as_str()).and_then(|a| a.get_long()).map(|l| format!("--{l}")));
            crate::Error::Parameter { name: long.unwrap_or(name), message }
        }
        other => other,
    }
}
