//! `r2d2 bench`: hot-path benchmarks printing JSON, to compare side by side with peers
//! (`benches/gridder_vs_ducc0.py` runs ducc0 on the same data).

use r2d2_imaging::bench::{run_gridder_bench, GridderBenchParams};
use r2d2_imaging::Result;

#[derive(clap::Subcommand)]
pub enum Command {
    /// Gridding and degridding throughput (points uniform in the uv disc).
    Gridder {
        #[arg(long, default_value_t = 2_000_000)]
        visibilities: usize,
        #[arg(long, default_value_t = 512)]
        size: usize,
        #[arg(long, default_value_t = 1e-5)]
        epsilon: f64,
        /// Threads (0: all cores).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// Best of this many runs.
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

pub fn run(cmd: Command) -> Result<()> {
    match cmd {
        Command::Gridder { visibilities, size, epsilon, threads, repeats, seed } => {
            let report = run_gridder_bench(&GridderBenchParams { visibilities, size, epsilon, threads, repeats, seed })?;
            println!("{}", serde_json::to_string_pretty(&report).expect("report serialises"));
            Ok(())
        }
    }
}
