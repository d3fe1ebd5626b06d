//! NUFFT against a direct (O(N^2 M)) DFT, and adjointness.

use crate::nufft::direct::{adjoint as direct_adjoint, forward as direct_forward, relative_error};
use super::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_points(m: usize, rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<f64>) {
    // Cover more than one period so wrapping is exercised.
    let x = (0..m).map(|_| rng.gen_range(-1.2 * std::f64::consts::PI..1.2 * std::f64::consts::PI)).collect();
    let y = (0..m).map(|_| rng.gen_range(-std::f64::consts::PI..std::f64::consts::PI)).collect();
    (x, y)
}

fn random_complex(n: usize, rng: &mut ChaCha8Rng) -> Vec<Complex64> {
    (0..n).map(|_| Complex64::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0))).collect()
}

fn check_against_dft(epsilon: f64, oversampling: f64, nx: usize, ny: usize, m: usize, threads: usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let (x, y) = random_points(m, &mut rng);
    let plan = Nufft2d::new(nx, ny, &x, &y, NufftParams { epsilon, oversampling }, threads).unwrap();

    let f = random_complex(nx * ny, &mut rng);
    let mut fwd = vec![Complex64::default(); m];
    plan.forward(&f, &mut fwd);
    let err_fwd = relative_error(&fwd, &direct_forward(nx, ny, &x, &y, &f));

    let c = random_complex(m, &mut rng);
    let mut adj = vec![Complex64::default(); nx * ny];
    plan.adjoint(&c, &mut adj);
    let err_adj = relative_error(&adj, &direct_adjoint(nx, ny, &x, &y, &c));

    eprintln!("eps {epsilon:e} sigma {oversampling} w {}: forward {err_fwd:.2e} adjoint {err_adj:.2e}", plan.kernel_shape().support);
    assert!(err_fwd <= 2.0 * epsilon, "forward error {err_fwd:e} > 2 eps (eps {epsilon:e}, sigma {oversampling})");
    assert!(err_adj <= 2.0 * epsilon, "adjoint error {err_adj:e} > 2 eps (eps {epsilon:e}, sigma {oversampling})");
}

#[test]
fn matches_direct_dft_eps_1e3() {
    check_against_dft(1e-3, 2.0, 64, 48, 3000, 2);
}

#[test]
fn matches_direct_dft_eps_1e6() {
    check_against_dft(1e-6, 2.0, 64, 48, 3000, 2);
}

#[test]
fn matches_direct_dft_eps_1e10() {
    check_against_dft(1e-10, 2.0, 64, 48, 3000, 1);
}

#[test]
fn matches_direct_dft_low_oversampling() {
    for eps in [1e-3, 1e-6] {
        check_against_dft(eps, 1.25, 48, 64, 2000, 2);
    }
    check_against_dft(1e-10, 1.5, 48, 64, 2000, 2);
    check_against_dft(1e-8, 1.7, 48, 64, 2000, 2);
}

#[test]
fn matches_direct_dft_all_supports() {
    // Every compiled kernel width gets exercised at least once.
    for eps in [5e-2, 1e-2, 1e-3, 1e-4, 1e-5, 1e-7, 1e-8, 1e-9, 1e-11, 1e-12, 1e-13, 1e-14] {
        check_against_dft(eps, 2.0, 32, 32, 500, 2);
    }
}

#[test]
fn forward_and_adjoint_are_adjoint() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let (nx, ny, m) = (96, 80, 20_000);
    let (x, y) = random_points(m, &mut rng);
    let plan = Nufft2d::new(nx, ny, &x, &y, NufftParams { epsilon: 1e-9, oversampling: 2.0 }, 2).unwrap();
    let f = random_complex(nx * ny, &mut rng);
    let c = random_complex(m, &mut rng);
    let mut af = vec![Complex64::default(); m];
    plan.forward(&f, &mut af);
    let mut ahc = vec![Complex64::default(); nx * ny];
    plan.adjoint(&c, &mut ahc);
    // <A f, c> = <f, A^H c>
    let lhs: Complex64 = af.iter().zip(&c).map(|(a, c)| a * c.conj()).sum();
    let rhs: Complex64 = f.iter().zip(&ahc).map(|(f, a)| f * a.conj()).sum();
    assert!((lhs - rhs).norm() <= 1e-12 * lhs.norm(), "{lhs} vs {rhs}");
}

#[test]
fn gridding_is_bit_reproducible_with_threads() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let (x, y) = random_points(400_000, &mut rng);
    let c = random_complex(400_000, &mut rng);
    let plan = Nufft2d::new(128, 128, &x, &y, NufftParams::default(), 2).unwrap();
    let run = || {
        let mut out = vec![Complex64::default(); 128 * 128];
        plan.adjoint(&c, &mut out);
        out
    };
    let first = run();
    for _ in 0..3 {
        assert!(run() == first, "gridding depends on thread scheduling");
    }
}

#[test]
fn thread_count_does_not_change_results_beyond_rounding() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let (x, y) = random_points(50_000, &mut rng);
    let c = random_complex(50_000, &mut rng);
    let mut images = Vec::new();
    for threads in [1, 2] {
        let plan = Nufft2d::new(64, 64, &x, &y, NufftParams::default(), threads).unwrap();
        let mut out = vec![Complex64::default(); 64 * 64];
        plan.adjoint(&c, &mut out);
        images.push(out);
    }
    assert!(relative_error(&images[0], &images[1]) < 1e-13);
}

#[test]
fn chunked_adjoint_matches_direct_dft_and_one_plan() {
    let (nx, ny, m) = (32, 24, 3000);
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let (x, y) = random_points(m, &mut rng);
    let c = random_complex(m, &mut rng);
    let params = NufftParams { epsilon: 1e-10, oversampling: 2.0 };
    let mut chunked = ChunkedAdjoint::new(nx, ny, 2, params, 2).unwrap();
    // Uneven chunks, one of them empty; transform 1 holds the values doubled.
    for range in [0..1000, 1000..1000, 1000..1001, 1001..m] {
        let start = range.start;
        chunked.add(&x[range.clone()], &y[range], |t, k| c[start + k] * (t + 1) as f64).unwrap();
    }
    let images = chunked.finish();
    let direct = direct_adjoint(nx, ny, &x, &y, &c);
    assert!(relative_error(&images[0], &direct) < 1e-9, "{}", relative_error(&images[0], &direct));
    let plan = Nufft2d::new(nx, ny, &x, &y, params, 2).unwrap();
    let mut whole = vec![Complex64::default(); nx * ny];
    plan.adjoint(&c, &mut whole);
    assert!(relative_error(&images[0], &whole) < 1e-14, "{}", relative_error(&images[0], &whole));
    let doubled: Vec<Complex64> = whole.iter().map(|z| z * 2.0).collect();
    assert!(relative_error(&images[1], &doubled) < 1e-14);
    let err = ChunkedAdjoint::new(nx, ny, 1, params, 2).unwrap().add(&[f64::NAN], &[0.0], |_, _| c[0]).unwrap_err();
    assert!(err.to_string().contains("finite point coordinates"), "{err}");
}

#[test]
fn empty_point_set_gives_zero_image() {
    let plan = Nufft2d::new(16, 16, &[], &[], NufftParams::default(), 1).unwrap();
    let mut out = vec![Complex64::new(1.0, 1.0); 256];
    plan.adjoint(&[], &mut out);
    assert!(out.iter().all(|v| v.norm() == 0.0));
}

#[test]
fn odd_image_size_is_rejected() {
    let err = Nufft2d::new(15, 16, &[], &[], NufftParams::default(), 1).err().unwrap().to_string();
    assert!(err.contains("image size"), "{err}");
}


#[test]
fn every_supported_simd_level_gives_the_same_result() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (nx, ny, m) = (64, 48, 20_000);
    let (x, y) = random_points(m, &mut rng);
    let f = random_complex(nx * ny, &mut rng);
    let c = random_complex(m, &mut rng);
    for eps in [1e-3, 1e-6, 1e-12] {
        let mut plan = Nufft2d::new(nx, ny, &x, &y, NufftParams { epsilon: eps, oversampling: 2.0 }, 2).unwrap();
        let mut results = Vec::new();
        for level in [SimdLevel::Baseline, SimdLevel::Avx2Fma, SimdLevel::Avx512] {
            if plan.set_simd_level(level).is_err() {
                assert!(!level.is_supported());
                continue;
            }
            let mut fwd = vec![Complex64::default(); m];
            plan.forward(&f, &mut fwd);
            let mut adj = vec![Complex64::default(); nx * ny];
            plan.adjoint(&c, &mut adj);
            results.push((level, fwd, adj));
        }
        let (_, fwd0, adj0) = &results[0];
        for (level, fwd, adj) in &results[1..] {
            assert!(relative_error(fwd, fwd0) < 1e-13, "{level:?} forward differs at eps {eps:e}");
            assert!(relative_error(adj, adj0) < 1e-13, "{level:?} adjoint differs at eps {eps:e}");
        }
    }
}

#[test]
fn a_windowed_chunked_adjoint_gives_the_direct_sums_and_refuses_points_beyond_its_bound() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let (nx, ny, m) = (96, 64, 3000);
    let bound = 0.8;
    let x: Vec<f64> = (0..m).map(|_| rng.gen_range(-bound..bound)).collect();
    let y: Vec<f64> = (0..m).map(|_| rng.gen_range(-bound..bound)).collect();
    let c = random_complex(m, &mut rng);
    let params = NufftParams { epsilon: 1e-9, oversampling: 2.0 };
    let mut windowed = ChunkedAdjoint::windowed(nx, ny, 2, bound, params, 2).unwrap();
    let plain = ChunkedAdjoint::new(nx, ny, 2, params, 2).unwrap();
    // The window is a part of the grid (here about a quarter of it each way).
    assert!(4 * windowed.grid_bytes() < plain.grid_bytes(), "{} {}", windowed.grid_bytes(), plain.grid_bytes());
    for part in [0..1000, 1000..m] {
        windowed.add(&x[part.clone()], &y[part.clone()], |t, k| if t == 0 { c[part.start + k] } else { c[part.start + k] * 2.0 }).unwrap();
    }
    let images = windowed.finish();
    let truth = direct_adjoint(nx, ny, &x, &y, &c);
    assert!(relative_error(&images[0], &truth) < 1e-8, "{}", relative_error(&images[0], &truth));
    let twice: Vec<Complex64> = truth.iter().map(|t| t * 2.0).collect();
    assert!(relative_error(&images[1], &twice) < 1e-8);
    let mut windowed = ChunkedAdjoint::windowed(nx, ny, 1, bound, params, 1).unwrap();
    let e = windowed.add(&[0.1, 0.9], &[0.0, 0.0], |_, _| Complex64::new(1.0, 0.0)).unwrap_err().to_string();
    assert!(e.contains("beyond the coordinate bound"), "{e}");
    // A bound the whole grid needs: no window.
    assert_eq!(ChunkedAdjoint::windowed(nx, ny, 1, 3.0, params, 1).unwrap().grid_bytes(), ChunkedAdjoint::new(nx, ny, 1, params, 1).unwrap().grid_bytes());
}
