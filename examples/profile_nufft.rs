//! Profiling harness: `profile_nufft PHASE REPS [THREADS] [N] [SIZE] [EPS]` runs one phase
//! (plan, grid, degrid) REPS times on the benchmark's data and prints each time.

use num_complex::Complex64;
use r2d2_imaging::bench::synthetic_visibilities;
use r2d2_imaging::nufft::{Nufft2d, NufftParams};
use std::time::Instant;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let phase = a.get(1).map(String::as_str).unwrap_or("grid").to_string();
    let reps: usize = a.get(2).map(|s| s.parse().unwrap()).unwrap_or(5);
    let threads: usize = a.get(3).map(|s| s.parse().unwrap()).unwrap_or(1);
    let n: usize = a.get(4).map(|s| s.parse().unwrap()).unwrap_or(2_000_000);
    let size: usize = a.get(5).map(|s| s.parse().unwrap()).unwrap_or(512);
    let eps: f64 = a.get(6).map(|s| s.parse().unwrap()).unwrap_or(1e-5);
    let (x, y, c) = synthetic_visibilities(n, 1);
    let params = NufftParams { epsilon: eps, ..Default::default() };
    let plan = Nufft2d::new(size, size, &x, &y, params, threads).unwrap();
    let image = vec![Complex64::new(0.5, -0.25); size * size];
    let mut img = vec![Complex64::default(); size * size];
    let mut vis = vec![Complex64::default(); n];
    let mut times = Vec::new();
    let mut cpus = Vec::new();
    let mut faults = Vec::new();
    for _ in 0..reps {
        let f0 = stat_field(7);
        let c0 = cpu_seconds();
        let t = Instant::now();
        match phase.as_str() {
            "plan" => drop(Nufft2d::new(size, size, &x, &y, params, threads).unwrap()),
            "grid" => plan.adjoint(&c, &mut img),
            "degrid" => plan.forward(&image, &mut vis),
            "grid_sorted" => plan.adjoint_sorted(&c, &mut img),
            "degrid_sorted" => plan.forward_sorted(&image, &mut vis),
            p => panic!("unknown phase {p}"),
        }
        times.push(t.elapsed().as_secs_f64());
        cpus.push(cpu_seconds() - c0);
        faults.push(stat_field(7) - f0);
    }
    let best = times.iter().cloned().fold(f64::MAX, f64::min);
    let cpu_mean = cpus.iter().sum::<f64>() / reps as f64;
    println!("{phase}: best wall {best:.4} s  mean cpu {cpu_mean:.4} s  walls {times:.3?} minor faults {faults:?}");
}

/// Field `i` (0-based, after the command name) of /proc/self/stat.
fn stat_field(i: usize) -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    after.split_whitespace().nth(i).and_then(|s| s.parse().ok()).unwrap_or(0.0)
}

/// User + system CPU time of the whole process (all threads), from /proc (10 ms ticks).
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks: f64 = f.get(11).and_then(|s| s.parse().ok()).unwrap_or(0.0) + f.get(12).and_then(|s| s.parse().ok()).unwrap_or(0.0);
    ticks / 100.0
}
