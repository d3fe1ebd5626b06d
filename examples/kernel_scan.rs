//! Kernel tuning scan: for each support width w, the kernel shape parameter beta / w (scanned
//! from B0 in steps of DB) that gives the smallest error against the direct DFT, forward and
//! adjoint. Run by hand when the kernel changes:
//! `SIGMA=2 cargo run --release --example kernel_scan` (SIGMA: oversampling; B0, DB optional).

use num_complex::Complex64;
use r2d2_imaging::nufft::direct::{adjoint, forward, relative_error};
use r2d2_imaging::nufft::kernel::KernelShape;
use r2d2_imaging::nufft::{Nufft2d, NufftParams};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

fn env_or(name: &str, default: f64) -> f64 {
    std::env::var(name).ok().and_then(|s| s.parse().ok()).unwrap_or(default)
}

fn main() {
    let (sigma, b0, db) = (env_or("SIGMA", 2.0), env_or("B0", 1.6), env_or("DB", 0.05));
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let (nx, ny, m) = (64, 48, 3000);
    let x: Vec<f64> = (0..m).map(|_| rng.gen_range(-1.2 * PI..1.2 * PI)).collect();
    let y: Vec<f64> = (0..m).map(|_| rng.gen_range(-PI..PI)).collect();
    let mut random = |n: usize| -> Vec<Complex64> { (0..n).map(|_| Complex64::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0))).collect() };
    let (f, c) = (random(nx * ny), random(m));
    let (want_fwd, want_adj) = (forward(nx, ny, &x, &y, &f), adjoint(nx, ny, &x, &y, &c));
    println!("oversampling {sigma}: best beta / w per support w");
    for w in 2..=16usize {
        let mut best = (f64::MAX, 0.0);
        for i in 0..=24 {
            let beta_per_w = b0 + db * i as f64;
            let shape = KernelShape { support: w, beta: beta_per_w * w as f64 };
            let plan = match Nufft2d::with_kernel(nx, ny, &x, &y, shape, NufftParams { epsilon: 1e-14, oversampling: sigma }, 2) {
                Ok(plan) => plan,
                Err(e) => {
                    eprintln!("w {w}: {e}");
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
        println!("w {w:2}: best beta/w {:.2} error {:.2e}", best.1, best.0);
    }
}
