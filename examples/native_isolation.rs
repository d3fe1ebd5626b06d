//! The cost of running a native plugin in its own process: the example Landweber plugin's
//! step at N x N (default 512) loaded into this process and in `r2d2-plugin-host`, side by
//! side, with the engine's own per-iteration work (the residual update, a 2N FFT convolution)
//! for scale. Medians over the steps; the first step (which sends the PSF and dirty image to
//! the host) is reported apart.
//!
//!     cargo build --release && cargo run --release --example native_isolation -- [N] [STEPS]

use r2d2_imaging::operator::PsfConvolution;
use r2d2_imaging::steps::native::{NativeConfig, NativeStep};
use r2d2_imaging::steps::{NetworkStep, StepInput};
use std::path::PathBuf;
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> r2d2_imaging::Result<()> {
    let mut args = std::env::args().skip(1);
    let n: usize = args.next().map(|a| a.parse().expect("N")).unwrap_or(512);
    let steps: usize = args.next().map(|a| a.parse().expect("STEPS")).unwrap_or(30);
    let library = PathBuf::from(format!("target/release/{}r2d2_landweber{}", std::env::consts::DLL_PREFIX, std::env::consts::DLL_SUFFIX));
    // A PSF with a peak and some structure, and a dirty image of noise-like values.
    let mut psf_2n = vec![0.0; 4 * n * n];
    for (k, v) in psf_2n.iter_mut().enumerate() {
        let (x, y) = ((k % (2 * n)) as f64 - n as f64, (k / (2 * n)) as f64 - n as f64);
        *v = (-(x * x + y * y) / 50.0).exp();
    }
    let dirty: Vec<f64> = (0..n * n).map(|k| ((k * 7919) % 1000) as f64 / 1000.0).collect();
    let convolution = PsfConvolution::new(n, &psf_2n)?;
    let mut residual_update = Vec::new();
    for _ in 0..steps.min(10) {
        let t = Instant::now();
        std::hint::black_box(convolution.apply(&dirty));
        residual_update.push(t.elapsed().as_secs_f64());
    }
    let mut rows = Vec::new();
    for isolation in ["none", "process"] {
        let yaml = format!("library: {}\niterations: {steps}\nconfig: {{gain: 0.1}}\nisolation: {isolation}\n", library.display());
        let config: NativeConfig = serde_yaml::from_str(&yaml).expect("config");
        let t = Instant::now();
        let mut step = NativeStep::new(config, n, "step")?;
        let create = t.elapsed().as_secs_f64();
        let mut model = vec![0.0; n * n];
        let mut times = Vec::new();
        for i in 1..=steps {
            let input = StepInput { job: "bench", size: n, model: &model, residual: &dirty, dirty: &dirty, psf: &dirty, psf_2n: &psf_2n, psf_convolution: &convolution };
            let t = Instant::now();
            model = step.step(i, &input)?;
            times.push(t.elapsed().as_secs_f64());
        }
        let first = times.remove(0);
        rows.push((isolation, create, first, median(times)));
    }
    let update = median(residual_update);
    println!("native plugin step at {n} x {n} (example Landweber plugin), {steps} steps; ms");
    println!("{:<10} {:>10} {:>12} {:>14} {:>22}", "isolation", "create", "first step", "step (median)", "step / residual update");
    for (isolation, create, first, step) in &rows {
        println!("{isolation:<10} {:>10.2} {:>12.2} {:>14.2} {:>22.2}", create * 1e3, first * 1e3, step * 1e3, step / update);
    }
    let cost = rows[1].3 - rows[0].3;
    println!("isolation costs {:.2} ms per step ({:.2}x the in-process step); the residual update takes {:.2} ms", cost * 1e3, rows[1].3 / rows[0].3, update * 1e3);
    Ok(())
}
