//! Gridder throughput benchmark: plan (point sorting), adjoint NUFFT ("gridding": points to
//! image) and forward NUFFT ("degridding": image to points) on synthetic data, timed as the
//! best of several runs.
//!
//! The data mimic a radio interferometer imaged at super-resolution 1.5: points uniform in the
//! uv disc whose radius makes the image pixel 1/1.5 of the Nyquist size, i.e. in the NUFFT's
//! radians-per-pixel coordinates `|(x, y)| <= pi / 1.5`, with random complex values. The
//! report also estimates the achieved accuracy against a direct DFT on a sample of outputs,
//! so a comparison with another gridder can check that neither side bought speed with
//! accuracy. [`run_wgridder_bench`] does the same for the transforms with the w-term
//! (`nufft::wgrid`) on a wide field.

use crate::nufft::wgrid::{max_w_phase, suggested_oversampling, WGridPlan};
use crate::nufft::{ChunkedAdjoint, Nufft2d, NufftParams};
use crate::{Error, Result};
use num_complex::Complex64;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::Serialize;
use std::time::Instant;

/// What to benchmark.
#[derive(Clone, Debug)]
pub struct GridderBenchParams {
    /// Number of points (visibilities).
    pub visibilities: usize,
    /// Image edge in pixels (the image is `size x size`).
    pub size: usize,
    /// Requested relative accuracy.
    pub epsilon: f64,
    /// Worker threads (0: all cores).
    pub threads: usize,
    /// Runs per measurement; the best one is reported.
    pub repeats: usize,
    /// Seed of the synthetic data.
    pub seed: u64,
}

impl Default for GridderBenchParams {
    fn default() -> Self {
        GridderBenchParams { visibilities: 2_000_000, size: 512, epsilon: 1e-5, threads: 1, repeats: 3, seed: 1 }
    }
}

/// Timings (seconds, best of `repeats`) and throughputs (million points per second).
#[derive(Clone, Debug, Serialize)]
pub struct GridderReport {
    pub visibilities: usize,
    pub size: usize,
    pub epsilon: f64,
    pub threads: usize,
    /// Kernel support in grid cells.
    pub support: usize,
    /// Oversampled grid edge (`grid_size x grid_size`).
    pub grid_size: usize,
    pub oversampling: f64,
    /// Plan construction: kernel fit, FFT plans, point positions and the sort by tile.
    pub plan_seconds: f64,
    /// Adjoint (points to image) on a built plan: spreading, FFT and kernel correction.
    pub grid_seconds: f64,
    /// Forward (image to points) on a built plan: correction, FFT and interpolation.
    pub degrid_seconds: f64,
    /// The grid-to-image FFT and correction step of the adjoint alone.
    pub fft_seconds: f64,
    /// The image-to-grid correction and FFT step of the forward transform alone.
    pub degrid_fft_seconds: f64,
    /// Throughput including the plan (a gridder that sorts on every call does this work).
    pub grid_mvis_per_s: f64,
    pub degrid_mvis_per_s: f64,
    /// Throughput with a reused plan (iterative imaging), values in the caller's order.
    pub grid_mvis_per_s_planned: f64,
    pub degrid_mvis_per_s_planned: f64,
    /// Throughput with a reused plan and values kept in the plan's order
    /// (`adjoint_sorted` / `forward_sorted`: no permutation).
    pub grid_mvis_per_s_sorted: f64,
    pub degrid_mvis_per_s_sorted: f64,
    /// The adjoint as the gridder stage runs it without a NUFFT residual: all points in
    /// chunks (`nufft::ChunkedAdjoint`), each chunk sorted on its own, no plan over all points.
    pub grid_chunked_seconds: f64,
    pub grid_mvis_per_s_chunked: f64,
    /// Relative L2 difference of the chunked adjoint's image from the one-plan adjoint's.
    pub grid_chunked_rel_diff: f64,
    /// Relative L2 error against a direct DFT, estimated on a random sample of outputs
    /// (image pixels for the adjoint, points for the forward transform).
    pub grid_rel_error: f64,
    pub degrid_rel_error: f64,
}

/// Points uniform in the disc `|(x, y)| <= pi / 1.5` and random complex values in the unit
/// square, deterministic in `seed`.
pub fn synthetic_visibilities(n: usize, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<Complex64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let radius = std::f64::consts::PI / 1.5;
    let mut x = Vec::with_capacity(n);
    let mut y = Vec::with_capacity(n);
    let mut c = Vec::with_capacity(n);
    for _ in 0..n {
        let r = radius * rng.gen::<f64>().sqrt();
        let theta = 2.0 * std::f64::consts::PI * rng.gen::<f64>();
        x.push(r * theta.cos());
        y.push(r * theta.sin());
        c.push(Complex64::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0)));
    }
    (x, y, c)
}

fn best_of<T>(repeats: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut last = None;
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        let out = f();
        best = best.min(start.elapsed().as_secs_f64());
        last = Some(out);
    }
    (best, last.expect("at least one run"))
}

/// Run the benchmark.
pub fn run_gridder_bench(p: &GridderBenchParams) -> Result<GridderReport> {
    if p.size < 2 || p.size % 2 != 0 {
        return Err(Error::parameter("size", format!("expected an even image size >= 2, got {}", p.size)));
    }
    if p.visibilities == 0 {
        return Err(Error::parameter("visibilities", "expected at least one visibility"));
    }
    let n = p.size;
    let (x, y, vis) = synthetic_visibilities(p.visibilities, p.seed);
    let params = NufftParams { epsilon: p.epsilon, oversampling: NufftParams::default().oversampling };
    let mut image_rng = ChaCha8Rng::seed_from_u64(p.seed ^ 0x5eed);
    let image: Vec<Complex64> =
        (0..n * n).map(|_| Complex64::new(image_rng.gen_range(-1.0..1.0), image_rng.gen_range(-1.0..1.0))).collect();

    // Surface parameter errors before timing.
    let probe = Nufft2d::new(n, n, &x, &y, params, p.threads)?;
    drop(probe);
    let (plan_seconds, plan) = best_of(p.repeats, || Nufft2d::new(n, n, &x, &y, params, p.threads).expect("checked above"));

    let mut dirty = vec![Complex64::default(); n * n];
    let mut model_vis = vec![Complex64::default(); p.visibilities];
    let (grid_sorted_seconds, ()) = best_of(p.repeats, || plan.adjoint_sorted(&vis, &mut dirty));
    let (degrid_sorted_seconds, ()) = best_of(p.repeats, || plan.forward_sorted(&image, &mut model_vis));
    let (fft_seconds, ()) = best_of(p.repeats, || plan.time_grid_to_image());
    let (degrid_fft_seconds, ()) = best_of(p.repeats, || plan.time_image_to_grid());

    // Last, so that the outputs checked below are those of the caller-order transforms.
    let (grid_seconds, ()) = best_of(p.repeats, || plan.adjoint(&vis, &mut dirty));
    let (degrid_seconds, ()) = best_of(p.repeats, || plan.forward(&image, &mut model_vis));
    let (grid_rel_error, degrid_rel_error) =
        plan.install(|| sampled_errors(n, &x, &y, &vis, &dirty, &image, &model_vis, p.seed));
    let chunk = crate::operator::chunk_points(p.visibilities);
    let chunked_adjoint = || -> Result<Vec<Complex64>> {
        let mut adjoint = ChunkedAdjoint::new(n, n, 1, params, p.threads)?;
        for start in (0..p.visibilities).step_by(chunk) {
            let end = (start + chunk).min(p.visibilities);
            adjoint.add(&x[start..end], &y[start..end], |_, k| vis[start + k])?;
        }
        Ok(adjoint.finish().pop().expect("one transform"))
    };
    let (grid_chunked_seconds, chunked) = best_of(p.repeats, chunked_adjoint);
    let chunked = chunked?;
    let grid_chunked_rel_diff = crate::nufft::direct::relative_error(&chunked, &dirty);

    let m = p.visibilities as f64 / 1e6;
    let (grid_size, _) = plan.grid_size();
    Ok(GridderReport {
        visibilities: p.visibilities,
        size: n,
        epsilon: p.epsilon,
        threads: plan.install(rayon::current_num_threads),
        support: plan.kernel_shape().support,
        grid_size,
        oversampling: grid_size as f64 / n as f64,
        plan_seconds,
        grid_seconds,
        degrid_seconds,
        fft_seconds,
        degrid_fft_seconds,
        grid_mvis_per_s: m / (plan_seconds + grid_seconds),
        degrid_mvis_per_s: m / (plan_seconds + degrid_seconds),
        grid_mvis_per_s_planned: m / grid_seconds,
        degrid_mvis_per_s_planned: m / degrid_seconds,
        grid_mvis_per_s_sorted: m / grid_sorted_seconds,
        degrid_mvis_per_s_sorted: m / degrid_sorted_seconds,
        grid_chunked_seconds,
        grid_mvis_per_s_chunked: m / grid_chunked_seconds,
        grid_chunked_rel_diff,
        grid_rel_error,
        degrid_rel_error,
    })
}

/// Relative L2 errors of the adjoint (on 16 random pixels) and of the forward transform (on
/// 64 random points) against direct sums.
#[allow(clippy::too_many_arguments)]
fn sampled_errors(
    n: usize,
    x: &[f64],
    y: &[f64],
    vis: &[Complex64],
    dirty: &[Complex64],
    image: &[Complex64],
    model_vis: &[Complex64],
    seed: u64,
) -> (f64, f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xe770);
    let pixels: Vec<usize> = (0..16).map(|_| rng.gen_range(0..n * n)).collect();
    let points: Vec<usize> = (0..64).map(|_| rng.gen_range(0..x.len())).collect();
    let half = (n / 2) as f64;
    let grid_pairs: Vec<(Complex64, Complex64)> = pixels
        .par_iter()
        .map(|&j| {
            let (jx, jy) = ((j % n) as f64 - half, (j / n) as f64 - half);
            let exact: Complex64 = x
                .iter()
                .zip(y)
                .zip(vis)
                .map(|((&xk, &yk), &ck)| ck * Complex64::from_polar(1.0, -(xk * jx + yk * jy)))
                .sum();
            (dirty[j], exact)
        })
        .collect();
    let degrid_pairs: Vec<(Complex64, Complex64)> = points
        .par_iter()
        .map(|&k| {
            // exp(i (x jx + y jy)) by recurrences along rows, re-seeded per row.
            let step_x = Complex64::from_polar(1.0, x[k]);
            let mut exact = Complex64::default();
            for iy in 0..n {
                let mut ph = Complex64::from_polar(1.0, x[k] * -half + y[k] * (iy as f64 - half));
                let row = &image[iy * n..(iy + 1) * n];
                let mut s = Complex64::default();
                for v in row {
                    s += v * ph;
                    ph *= step_x;
                }
                exact += s;
            }
            (model_vis[k], exact)
        })
        .collect();
    let rel = |pairs: &[(Complex64, Complex64)]| {
        let num: f64 = pairs.iter().map(|(a, b)| (a - b).norm_sqr()).sum();
        let den: f64 = pairs.iter().map(|(_, b)| b.norm_sqr()).sum();
        (num / den).sqrt()
    };
    (rel(&grid_pairs), rel(&degrid_pairs))
}

/// What to benchmark in `r2d2 bench wgridder`: the w-term transforms ([`WGridPlan`]) on a
/// field where the w-term matters.
#[derive(Clone, Debug)]
pub struct WGridderBenchParams {
    pub visibilities: usize,
    /// Image edge in pixels.
    pub size: usize,
    /// Field of view (the image edge) in degrees.
    pub fov_deg: f64,
    /// `|w|` up to this times the largest `|(u, v)|`.
    pub w_factor: f64,
    pub epsilon: f64,
    /// Oversampling of the uv grid (w-gridding chooses the w-planes' own); 0:
    /// [`suggested_oversampling`] for each kind of plan.
    pub oversampling: f64,
    /// Worker threads (0: all cores).
    pub threads: usize,
    pub repeats: usize,
    pub seed: u64,
}

impl Default for WGridderBenchParams {
    fn default() -> Self {
        WGridderBenchParams {
            visibilities: 1_000_000,
            size: 1024,
            fov_deg: 15.0,
            w_factor: 1.0,
            epsilon: 1e-5,
            oversampling: 0.0,
            threads: 1,
            repeats: 3,
            seed: 1,
        }
    }
}

/// Timings (seconds, best of `repeats`), throughputs (million visibilities per second) and
/// sampled accuracies of the w-term transforms, for a complex-image plan
/// ([`WGridPlan::new`]) and a real-image one ([`WGridPlan::new_real`], which mirrors
/// negative `w`).
#[derive(Clone, Debug, Serialize)]
pub struct WGridderReport {
    pub visibilities: usize,
    pub size: usize,
    pub fov_deg: f64,
    pub pixel_rad: f64,
    /// Largest `|(u, v)|` and `|w|` of the data, in wavelengths.
    pub uv_max: f64,
    pub w_max: f64,
    /// [`max_w_phase`] of the data: the largest phase the w-term adds, radians.
    pub max_w_phase: f64,
    pub epsilon: f64,
    pub threads: usize,
    pub complex: WGridderTimings,
    pub real: WGridderTimings,
}

/// One kind of plan's figures in a [`WGridderReport`].
#[derive(Clone, Debug, Serialize)]
pub struct WGridderTimings {
    /// Grid oversampling (asked for, or [`suggested_oversampling`]), kernel support, grid
    /// edge and w-planes.
    pub oversampling: f64,
    pub support: usize,
    pub grid_size: usize,
    pub planes: usize,
    pub plan_seconds: f64,
    pub grid_seconds: f64,
    pub degrid_seconds: f64,
    /// Including the plan (sorting), as a gridder that sorts in every call.
    pub grid_mvis_per_s: f64,
    pub degrid_mvis_per_s: f64,
    /// With a reused plan.
    pub grid_mvis_per_s_planned: f64,
    pub degrid_mvis_per_s_planned: f64,
    /// Relative L2 error against the direct sum with the w-term, on 16 random pixels
    /// (gridding) and 64 random visibilities (degridding). The degridded image is real in
    /// both cases; the real plan's dirty image is the real part of the complex one's.
    pub grid_rel_error: f64,
    pub degrid_rel_error: f64,
}

/// uv uniform in the disc whose radius makes the pixel 1/1.5 of the Nyquist size, `w`
/// uniform in `[-w_factor, w_factor]` times that radius, random complex values.
#[allow(clippy::type_complexity)]
pub fn synthetic_uvw(n: usize, pixel_rad: f64, w_factor: f64, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<Complex64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let uv_max = 1.0 / (1.5 * 2.0 * pixel_rad);
    let (mut u, mut v, mut w, mut c) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n));
    for _ in 0..n {
        let r = uv_max * rng.gen::<f64>().sqrt();
        let theta = 2.0 * std::f64::consts::PI * rng.gen::<f64>();
        u.push(r * theta.cos());
        v.push(r * theta.sin());
        w.push(uv_max * w_factor * rng.gen_range(-1.0..=1.0));
        c.push(Complex64::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0)));
    }
    (u, v, w, c)
}

/// Run the w-gridding benchmark.
pub fn run_wgridder_bench(p: &WGridderBenchParams) -> Result<WGridderReport> {
    if p.visibilities == 0 {
        return Err(Error::parameter("visibilities", "expected at least one visibility"));
    }
    if !(p.fov_deg > 0.0 && p.fov_deg < 180.0) {
        return Err(Error::parameter("fov", format!("expected a field between 0 and 180 degrees, got {}", p.fov_deg)));
    }
    let n = p.size;
    let pixel = p.fov_deg.to_radians() / n as f64;
    let (u, v, w, vis) = synthetic_uvw(p.visibilities, pixel, p.w_factor, p.seed);
    let params = |real: bool| NufftParams {
        epsilon: p.epsilon,
        oversampling: if p.oversampling > 0.0 { p.oversampling } else { suggested_oversampling(n, pixel, &w, real, p.epsilon) },
    };
    let mut image_rng = ChaCha8Rng::seed_from_u64(p.seed ^ 0x5eed);
    let image: Vec<f64> = (0..n * n).map(|_| image_rng.gen_range(-1.0..1.0)).collect();
    let image_c: Vec<Complex64> = image.iter().map(|&x| Complex64::new(x, 0.0)).collect();

    // Direct sums on a sample of outputs.
    let mut rng = ChaCha8Rng::seed_from_u64(p.seed ^ 0xe770);
    let pixels: Vec<usize> = (0..16).map(|_| rng.gen_range(0..n * n)).collect();
    let points: Vec<usize> = (0..64).map(|_| rng.gen_range(0..p.visibilities)).collect();
    let tau = 2.0 * std::f64::consts::PI;
    let lmt = |j: usize| {
        let l = -pixel * ((j % n) as f64 - (n / 2) as f64);
        let m = pixel * ((j / n) as f64 - (n / 2) as f64);
        (l, m, crate::nufft::wgrid::n_minus_one(l * l + m * m))
    };
    let pool = crate::parallel::shared_pool(p.threads)?;
    let (exact_dirty, exact_vis): (Vec<Complex64>, Vec<Complex64>) = pool.install(|| {
        let dirty = pixels
            .par_iter()
            .map(|&j| {
                let (l, m, t) = lmt(j);
                (0..u.len()).map(|k| vis[k] * Complex64::from_polar(1.0, -tau * (u[k] * l + v[k] * m + w[k] * t))).sum()
            })
            .collect();
        let model = points
            .par_iter()
            .map(|&k| {
                (0..n * n)
                    .map(|j| {
                        let (l, m, t) = lmt(j);
                        image[j] * Complex64::from_polar(1.0, tau * (u[k] * l + v[k] * m + w[k] * t))
                    })
                    .sum()
            })
            .collect();
        (dirty, model)
    });
    let rel = |pairs: Vec<(Complex64, Complex64)>| {
        let num: f64 = pairs.iter().map(|(a, b)| (a - b).norm_sqr()).sum();
        let den: f64 = pairs.iter().map(|(_, b)| b.norm_sqr()).sum();
        (num / den).sqrt()
    };
    let mvis = p.visibilities as f64 / 1e6;
    let timings = |plan: &WGridPlan, plan_seconds: f64, grid_seconds: f64, degrid_seconds: f64, errors: (f64, f64)| WGridderTimings {
        oversampling: plan.grid_size().0 as f64 / n as f64,
        support: plan.kernel_support(),
        grid_size: plan.grid_size().0,
        planes: plan.planes(),
        plan_seconds,
        grid_seconds,
        degrid_seconds,
        grid_mvis_per_s: mvis / (plan_seconds + grid_seconds),
        degrid_mvis_per_s: mvis / (plan_seconds + degrid_seconds),
        grid_mvis_per_s_planned: mvis / grid_seconds,
        degrid_mvis_per_s_planned: mvis / degrid_seconds,
        grid_rel_error: errors.0,
        degrid_rel_error: errors.1,
    };

    let make = || WGridPlan::new(n, pixel, &u, &v, &w, params(false), p.threads);
    drop(make()?);
    let (plan_seconds, plan) = best_of(p.repeats, || make().expect("checked above"));
    let (grid_seconds, dirty) = best_of(p.repeats, || plan.adjoint(&vis));
    let (degrid_seconds, model_vis) = best_of(p.repeats, || plan.forward(&image_c));
    let errors = (
        rel(pixels.iter().zip(&exact_dirty).map(|(&j, &e)| (dirty[j], e)).collect()),
        rel(points.iter().zip(&exact_vis).map(|(&k, &e)| (model_vis[k], e)).collect()),
    );
    let complex = timings(&plan, plan_seconds, grid_seconds, degrid_seconds, errors);
    drop(plan);

    let make = || WGridPlan::new_real(n, pixel, &u, &v, &w, params(true), p.threads);
    let (plan_seconds, plan) = best_of(p.repeats, || make().expect("checked above"));
    let (grid_seconds, dirty) = best_of(p.repeats, || plan.adjoint_real(&vis));
    let (degrid_seconds, model_vis) = best_of(p.repeats, || plan.forward_real(&image));
    let errors = (
        rel(pixels.iter().zip(&exact_dirty).map(|(&j, e)| (Complex64::new(dirty[j], 0.0), Complex64::new(e.re, 0.0))).collect()),
        rel(points.iter().zip(&exact_vis).map(|(&k, &e)| (model_vis[k], e)).collect()),
    );
    let real = timings(&plan, plan_seconds, grid_seconds, degrid_seconds, errors);

    let uv_max = u.iter().zip(&v).fold(0.0f64, |a, (u, v)| a.max(u.hypot(*v)));
    let w_max = w.iter().fold(0.0f64, |a, w| a.max(w.abs()));
    Ok(WGridderReport {
        visibilities: p.visibilities,
        size: n,
        fov_deg: p.fov_deg,
        pixel_rad: pixel,
        uv_max,
        w_max,
        max_w_phase: max_w_phase(n, pixel, w_max),
        epsilon: p.epsilon,
        threads: pool.current_num_threads(),
        complex,
        real,
    })
}

/// `r2d2 bench pipeline`: the same jobs through one pipeline run (stages concurrently on
/// their threads) and one run per job, one after another.
///
/// The jobs are copies of one simulated observation written to Parquet before any timing,
/// so reading is cheap and the imaging stages (gridding, network step, residual update,
/// writing) dominate, not the simulation.
#[derive(Clone, Debug)]
pub struct PipelineBenchParams {
    pub jobs: usize,
    /// Image edge in pixels.
    pub size: usize,
    /// VLA configuration and hours of the simulated observation.
    pub configuration: char,
    pub hours: f64,
    pub integration_s: f64,
    /// CLEAN major cycles (imaging-loop iterations) per job.
    pub major_cycles: usize,
    /// Threads per stage (0: all cores).
    pub threads: usize,
    pub channel_capacity: usize,
    pub seed: u64,
}

impl Default for PipelineBenchParams {
    fn default() -> Self {
        PipelineBenchParams {
            jobs: 8,
            size: 256,
            configuration: 'c',
            hours: 2.0,
            integration_s: 30.0,
            major_cycles: 4,
            threads: 1,
            channel_capacity: 2,
            seed: 1,
        }
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct PipelineBenchReport {
    pub jobs: usize,
    pub size: usize,
    pub visibilities_per_job: usize,
    pub major_cycles: usize,
    pub threads_per_stage: usize,
    pub cores: usize,
    /// All jobs through one pipeline run.
    pub concurrent_seconds: f64,
    /// One run per job, one after another.
    pub sequential_seconds: f64,
    /// Jobs per second of each way.
    pub concurrent_jobs_per_second: f64,
    pub sequential_jobs_per_second: f64,
    /// `sequential_seconds / concurrent_seconds`: the throughput gained by running stages
    /// concurrently.
    pub throughput_ratio: f64,
    /// Seconds per stage summed over jobs, for each way.
    pub concurrent_stage_seconds: std::collections::BTreeMap<String, f64>,
    pub sequential_stage_seconds: std::collections::BTreeMap<String, f64>,
}

/// Removes the benchmark's scratch directory however the run ends.
struct ScratchDir(std::path::PathBuf);

impl Drop for ScratchDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

pub fn run_pipeline_bench(p: &PipelineBenchParams) -> Result<PipelineBenchReport> {
    use crate::params::{CleanParams, Files, GridderParams, ParquetParams, ResidualParams, WeightingParams, WriterParams};
    use crate::imaging::ImageConfig;
    use crate::pipeline::{PipelineSpec, StageSpec};
    use crate::simulate::observe::ObservationSpec;
    use crate::simulate::{simulate, SimulationRequest, SkyModel};
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;

    if p.jobs == 0 || p.major_cycles == 0 {
        return Err(Error::parameter("jobs", "expected at least one job and one major cycle"));
    }
    if p.channel_capacity == 0 {
        return Err(Error::parameter("channel capacity", "expected at least 1"));
    }
    let dir = ScratchDir(std::env::temp_dir().join(format!("r2d2-bench-pipeline-{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).map_err(|e| Error::io(&dir.0, e))?;
    let request = SimulationRequest {
        observation: ObservationSpec {
            telescope: "vla".into(),
            configurations: vec![(p.configuration.to_string(), p.hours)],
            dec_deg: 40.0,
            integration_s: p.integration_s,
            frequencies_hz: vec![1.4e9],
            flag_fraction: 0.0,
            random_rotation: true,
            seed: p.seed,
        },
        sky: SkyModel::Procedural { seed: p.seed },
        size: p.size,
        pixel: crate::imaging::PixelScale::SuperResolution(1.5),
        dynamic_range: 1e4,
        noise_weighting: crate::weighting::Weighting::Briggs { robust: 0.0 },
        phase_centre_deg: (180.0, 40.0),
        nufft: NufftParams::default(),
        threads: 0,
    };
    let out = simulate(&request)?;
    let files: Vec<String> = (0..p.jobs).map(|k| format!("job-{k}.parquet")).collect();
    crate::vis::write_parquet(&dir.0.join(&files[0]), &out.table, &out.meta)?;
    for f in &files[1..] {
        std::fs::copy(dir.0.join(&files[0]), dir.0.join(f)).map_err(|e| Error::io(dir.0.join(f), e))?;
    }
    let out_prefix = dir.0.join("out").join("{job}").to_string_lossy().into_owned();
    let pipeline = |files: &[String]| -> Result<PipelineSpec> {
        let list: Vec<String> = files.iter().map(|f| dir.0.join(f).to_string_lossy().into_owned()).collect();
        let stages = vec![
            StageSpec::typed("read", &ParquetParams::new(Files::Many(list)))?.to("weights"),
            StageSpec::typed("weights", &WeightingParams::default())?.to("grid"),
            StageSpec::typed("grid", &GridderParams::default())?.to("step"),
            StageSpec::typed("step", &CleanParams { major_cycles: p.major_cycles, ..CleanParams::default() })?.to("update"),
            StageSpec::typed("update", &ResidualParams::default())?.to("step").done("write"),
            StageSpec::typed("write", &WriterParams { prefix: out_prefix.clone(), ..WriterParams::default() })?,
        ];
        let mut spec = PipelineSpec::new("bench", &ImageConfig { size: p.size, superresolution: None, pixel_arcsec: None, longest_baseline: None }, stages)?;
        spec.threads = p.threads;
        spec.channel_capacity = p.channel_capacity;
        Ok(spec)
    };
    let engine = crate::Engine::new(crate::EngineOptions { threads: p.threads, onnx_runtime: None })?;
    let cancel = Arc::new(AtomicBool::new(false));
    let add = |into: &mut std::collections::BTreeMap<String, f64>, from: &std::collections::BTreeMap<String, f64>| {
        for (k, v) in from {
            *into.entry(k.clone()).or_insert(0.0) += v;
        }
    };
    let all = pipeline(&files)?;
    let start = Instant::now();
    let concurrent = engine.run(&all, Vec::new(), None, cancel.clone())?;
    let concurrent_seconds = start.elapsed().as_secs_f64();
    let mut sequential_stage_seconds = std::collections::BTreeMap::new();
    let start = Instant::now();
    for f in &files {
        let report = engine.run(&pipeline(std::slice::from_ref(f))?, Vec::new(), None, cancel.clone())?;
        add(&mut sequential_stage_seconds, &report.stage_seconds);
    }
    let sequential_seconds = start.elapsed().as_secs_f64();
    Ok(PipelineBenchReport {
        jobs: p.jobs,
        size: p.size,
        visibilities_per_job: out.table.len(),
        major_cycles: p.major_cycles,
        threads_per_stage: p.threads,
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        concurrent_seconds,
        sequential_seconds,
        concurrent_jobs_per_second: p.jobs as f64 / concurrent_seconds,
        sequential_jobs_per_second: p.jobs as f64 / sequential_seconds,
        throughput_ratio: sequential_seconds / concurrent_seconds,
        concurrent_stage_seconds: concurrent.stage_seconds,
        sequential_stage_seconds,
    })
}
