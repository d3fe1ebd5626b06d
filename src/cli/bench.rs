//! `r2d2 bench`: hot-path benchmarks printing JSON, to compare side by side with peers
//! (`benches/gridder_vs_ducc0.py` runs ducc0 on the same data).

use r2d2_imaging::bench::{
    run_gridder_bench, run_pipeline_bench, run_wgridder_bench, GridderBenchParams, PipelineBenchParams, WGridderBenchParams,
};
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
    /// W-gridding and w-degridding throughput (the w-term on a wide field; points uniform in
    /// the uv disc, w uniform up to w-factor times the disc radius).
    Wgridder {
        #[arg(long, default_value_t = 1_000_000)]
        visibilities: usize,
        #[arg(long, default_value_t = 1024)]
        size: usize,
        /// Field of view (image edge) in degrees.
        #[arg(long, default_value_t = 15.0)]
        fov: f64,
        #[arg(long, default_value_t = 1.0)]
        w_factor: f64,
        #[arg(long, default_value_t = 1e-5)]
        epsilon: f64,
        /// Grid oversampling; 0: the one a cost model suggests for each kind of plan.
        #[arg(long, default_value_t = 0.0)]
        oversampling: f64,
        /// Threads (0: all cores).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// Best of this many runs.
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// The same jobs through one pipeline run (stages concurrently) vs one run per job, one
    /// after another: the throughput ratio. The jobs are copies of one simulated Parquet table.
    Pipeline {
        #[arg(long, default_value_t = 8)]
        jobs: usize,
        #[arg(long, default_value_t = 256)]
        size: usize,
        /// VLA configuration of the simulated observation.
        #[arg(long, default_value_t = 'c')]
        configuration: char,
        #[arg(long, default_value_t = 2.0)]
        hours: f64,
        #[arg(long, default_value_t = 30.0)]
        integration_s: f64,
        /// CLEAN major cycles per job.
        #[arg(long, default_value_t = 4)]
        major_cycles: usize,
        /// Threads per stage (0: all cores).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        #[arg(long, default_value_t = 2)]
        channel_capacity: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

pub fn run(cmd: Command) -> Result<()> {
    match cmd {
        Command::Gridder { visibilities, size, epsilon, threads, repeats, seed } => {
            let report = run_gridder_bench(&GridderBenchParams { visibilities, size, epsilon, threads, repeats, seed })?;
            out!("{}", serde_json::to_string_pretty(&report).expect("report serialises"))?;
            Ok(())
        }
        Command::Wgridder { visibilities, size, fov, w_factor, epsilon, oversampling, threads, repeats, seed } => {
            let params = WGridderBenchParams {
                visibilities,
                size,
                fov_deg: fov,
                w_factor,
                epsilon,
                oversampling,
                threads,
                repeats,
                seed,
            };
            let report = run_wgridder_bench(&params)?;
            out!("{}", serde_json::to_string_pretty(&report).expect("report serialises"))?;
            Ok(())
        }
        Command::Pipeline { jobs, size, configuration, hours, integration_s, major_cycles, threads, channel_capacity, seed } => {
            let params = PipelineBenchParams { jobs, size, configuration, hours, integration_s, major_cycles, threads, channel_capacity, seed };
            let report = run_pipeline_bench(&params)?;
            out!("{}", serde_json::to_string_pretty(&report).expect("report serialises"))?;
            Ok(())
        }
    }
}
