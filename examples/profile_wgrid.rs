//! Profiling harness: `profile_wgrid PHASE REPS [THREADS] [N] [SIZE] [FOV_DEG] [EPS]
//! [OVERSAMPLING]` runs one phase of the w-term transforms (plan, grid, degrid) REPS times on
//! the w-gridding benchmark's data and prints each time.

use num_complex::Complex64;
use r2d2_imaging::bench::synthetic_uvw;
use r2d2_imaging::nufft::wgrid::WGridPlan;
use r2d2_imaging::nufft::NufftParams;
use std::time::Instant;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let arg = |i: usize, default: &str| a.get(i).cloned().unwrap_or_else(|| default.to_string());
    let phase = arg(1, "grid");
    let reps: usize = arg(2, "3").parse().unwrap();
    let threads: usize = arg(3, "1").parse().unwrap();
    let n: usize = arg(4, "1000000").parse().unwrap();
    let size: usize = arg(5, "1024").parse().unwrap();
    let fov: f64 = arg(6, "15").parse().unwrap();
    let epsilon: f64 = arg(7, "1e-5").parse().unwrap();
    let oversampling: f64 = arg(8, "2").parse().unwrap();
    let pixel = fov.to_radians() / size as f64;
    let (u, v, w, c) = synthetic_uvw(n, pixel, 1.0, 1);
    let params = NufftParams { epsilon, oversampling };
    let plan = WGridPlan::new(size, pixel, &u, &v, &w, params, threads).unwrap();
    eprintln!("{} planes, support {} (w {}), grid {:?}", plan.planes(), plan.kernel_support(), plan.w_support(), plan.grid_size());
    let image = vec![Complex64::new(0.5, -0.25); size * size];
    for _ in 0..reps {
        let t = Instant::now();
        match phase.as_str() {
            "plan" => drop(WGridPlan::new(size, pixel, &u, &v, &w, params, threads).unwrap()),
            "grid" => drop(plan.adjoint(&c)),
            "degrid" => drop(plan.forward(&image)),
            other => panic!("unknown phase {other}"),
        }
        println!("{phase} {:.3} s", t.elapsed().as_secs_f64());
    }
}
