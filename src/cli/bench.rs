//! `r2d2 bench`: hot-path benchmarks printing JSON, to compare side by side with peers
//! (`benches/gridder_vs_ducc0.py` runs ducc0 on the same data).

use crate::bench::{
    run_gridder_bench, run_pipeline_bench, run_wgridder_bench, GridderBenchParams, PipelineBenchParams, WGridderBenchParams,
};
use crate::Result;

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
    /// MeasurementSet read throughput: the `ms` source's reader (Stokes I samples in row
    /// chunks, exclusions counted), for benches/ms_read.py.
    MsRead {
        ms: std::path::PathBuf,
        #[arg(long, default_value = "DATA")]
        data_column: String,
    },
    /// The cost of running a native plugin in its own process: the example Landweber plugin's
    /// step in this process and in `r2d2-plugin-host`, side by side, with the residual update
    /// (a 2N FFT convolution) for scale. Medians over the steps; the first step (which sends
    /// the PSF and dirty image to the host) apart.
    NativeIsolation {
        /// The plugin library (built by `cargo build --release`).
        #[arg(long)]
        library: std::path::PathBuf,
        #[arg(long, default_value_t = 512)]
        size: usize,
        #[arg(long, default_value_t = 30)]
        steps: usize,
    },
    /// Kernel tuning scan: for each support width, the shape parameter beta / w (from `b0` in
    /// steps of `db`) with the smallest error against the direct DFT, forward and adjoint. Run
    /// by hand when the kernel changes.
    KernelScan {
        #[arg(long, default_value_t = 2.0)]
        oversampling: f64,
        #[arg(long, default_value_t = 1.6)]
        b0: f64,
        #[arg(long, default_value_t = 0.05)]
        db: f64,
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
        Command::MsRead { ms, data_column } => ms_read(&ms, data_column),
        Command::NativeIsolation { library, size, steps } => native_isolation(&library, size, steps),
        Command::KernelScan { oversampling, b0, db } => kernel_scan(oversampling, b0, db),
    }
}

#[cfg(feature = "ms")]
fn ms_read(path: &std::path::Path, data_column: String) -> Result<()> {
    use crate::vis::TableReader;
    let selection = crate::ms::MsSelection { data_column, ..crate::ms::MsSelection::default() };
    let start = std::time::Instant::now();
    let mut reader = crate::ms::MsReader::open(path, &selection, crate::vis::DEFAULT_BATCH_ROWS)?;
    let mut stats = crate::vis::IngestStats::default();
    let mut kept = 0usize;
    while let Some(batch) = reader.next_batch() {
        kept += crate::vis::record_batch_to_visibilities(&batch?, &mut stats, "bench")?.len();
    }
    let seconds = start.elapsed().as_secs_f64();
    out!("{{\"samples\": {}, \"kept\": {kept}, \"seconds\": {seconds:.3}, \"samples_per_second\": {:.0}}}", stats.rows, stats.rows as f64 / seconds)
}

#[cfg(not(feature = "ms"))]
fn ms_read(_path: &std::path::Path, _data_column: String) -> Result<()> {
    Err(crate::Error::parameter("ms", "this build reads no MeasurementSets (feature `ms` off)"))
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn native_isolation(library: &std::path::Path, n: usize, steps: usize) -> Result<()> {
    use crate::steps::native::{NativeConfig, NativeStep};
    use crate::steps::{NetworkStep, StepInput};
    use std::time::Instant;
    if steps < 2 || n < 2 {
        return Err(crate::Error::parameter("steps", "give at least 2 steps of at least 2 x 2 pixels"));
    }
    // A PSF with a peak and some structure, and a dirty image of noise-like values.
    let mut psf_2n = vec![0.0; 4 * n * n];
    for (k, v) in psf_2n.iter_mut().enumerate() {
        let (x, y) = ((k % (2 * n)) as f64 - n as f64, (k / (2 * n)) as f64 - n as f64);
        *v = (-(x * x + y * y) / 50.0).exp();
    }
    let dirty: Vec<f64> = (0..n * n).map(|k| ((k * 7919) % 1000) as f64 / 1000.0).collect();
    let convolution = crate::operator::PsfConvolution::new(n, &psf_2n)?;
    let mut residual_update = Vec::new();
    for _ in 0..steps.min(10) {
        let t = Instant::now();
        std::hint::black_box(convolution.apply(&dirty));
        residual_update.push(t.elapsed().as_secs_f64());
    }
    let mut rows = Vec::new();
    for isolation in ["none", "process"] {
        let yaml = format!("library: {}\niterations: {steps}\nconfig: {{gain: 0.1}}\nisolation: {isolation}\n", library.display());
        let config: NativeConfig = serde_yaml::from_str(&yaml).map_err(|e| crate::Error::parameter("library", e.to_string()))?;
        let t = Instant::now();
        let mut step = NativeStep::new(config, n, "step")?;
        let create = t.elapsed().as_secs_f64();
        let mut model = vec![0.0; n * n];
        let mut times = Vec::new();
        for i in 1..=steps {
            let input = StepInput { job: "bench", size: n, model: &model, residual: &dirty, dirty: &dirty, psf: &dirty, psf_2n: &psf_2n, psf_convolution: &convolution, mask: None };
            let t = Instant::now();
            model = step.step(i, &input)?;
            times.push(t.elapsed().as_secs_f64());
        }
        let first = times.remove(0);
        rows.push((isolation, create, first, median(times)));
    }
    let update = median(residual_update);
    out!("native plugin step at {n} x {n} ({}), {steps} steps; ms", library.display())?;
    out!("{:<10} {:>10} {:>12} {:>14} {:>22}", "isolation", "create", "first step", "step (median)", "step / residual update")?;
    for (isolation, create, first, step) in &rows {
        out!("{isolation:<10} {:>10.2} {:>12.2} {:>14.2} {:>22.2}", create * 1e3, first * 1e3, step * 1e3, step / update)?;
    }
    let cost = rows[1].3 - rows[0].3;
    out!("isolation costs {:.2} ms per step ({:.2}x the in-process step); the residual update takes {:.2} ms", cost * 1e3, rows[1].3 / rows[0].3, update * 1e3)
}

fn kernel_scan(sigma: f64, b0: f64, db: f64) -> Result<()> {
    use crate::nufft::direct::{adjoint, forward, relative_error};
    use crate::nufft::kernel::KernelShape;
    use crate::nufft::{Nufft2d, NufftParams};
    use num_complex::Complex64;
    use rand::{Rng, SeedableRng};
    use std::f64::consts::PI;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(42);
    let (nx, ny, m) = (64, 48, 3000);
    let x: Vec<f64> = (0..m).map(|_| rng.gen_range(-1.2 * PI..1.2 * PI)).collect();
    let y: Vec<f64> = (0..m).map(|_| rng.gen_range(-PI..PI)).collect();
    let mut random = |n: usize| -> Vec<Complex64> { (0..n).map(|_| Complex64::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0))).collect() };
    let (f, c) = (random(nx * ny), random(m));
    let (want_fwd, want_adj) = (forward(nx, ny, &x, &y, &f), adjoint(nx, ny, &x, &y, &c));
    out!("oversampling {sigma}: best beta / w per support w")?;
    for w in 2..=16usize {
        let mut best = (f64::MAX, 0.0);
        for i in 0..=24 {
            let beta_per_w = b0 + db * i as f64;
            let shape = KernelShape { support: w, beta: beta_per_w * w as f64 };
            let plan = match Nufft2d::with_kernel(nx, ny, &x, &y, shape, NufftParams { epsilon: 1e-14, oversampling: sigma }, 2) {
                Ok(plan) => plan,
                Err(e) => {
                    log::warn!("w {w}: {e}");
                    break;
                }
            };
            let mut fwd = vec![Complex64::default(); m];
            plan.forward(&f, &mut fwd);
            let mut adj = vec![Complex64::default(); nx * ny];
            plan.adjoint(&c, &mut adj);
            let e = relative_error(&fwd, &want_fwd).max(relative_error(&adj, &want_adj));
            if e < best.0 {
                best = (e, beta_per_w);
            }
        }
        out!("w {w:2}: best beta/w {:.2} error {:.2e}", best.1, best.0)?;
    }
    Ok(())
}
