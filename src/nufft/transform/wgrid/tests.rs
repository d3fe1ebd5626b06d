//! W-gridding against the direct sum with the w-term, adjointness, and its reductions.

use super::*;
use crate::nufft::direct::{adjoint_w, forward_w, relative_error};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A field of `fov_deg` on `size` pixels; `m` visibilities uniform in the uv disc that makes
/// the pixel 1/1.5 of the Nyquist size, `w` uniform in `w_range` times the disc radius.
struct Case {
    size: usize,
    pixel: f64,
    u: Vec<f64>,
    v: Vec<f64>,
    w: Vec<f64>,
}

fn case(fov_deg: f64, size: usize, m: usize, w_range: (f64, f64), seed: u64) -> Case {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let pixel = fov_deg.to_radians() / size as f64;
    let max_uv = 1.0 / (1.5 * 2.0 * pixel);
    let (mut u, mut v, mut w) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..m {
        let r = max_uv * rng.gen::<f64>().sqrt();
        let th = 2.0 * PI * rng.gen::<f64>();
        u.push(r * th.cos());
        v.push(r * th.sin());
        w.push(max_uv * rng.gen_range(w_range.0..=w_range.1));
    }
    Case { size, pixel, u, v, w }
}

fn random_complex(n: usize, seed: u64) -> Vec<Complex64> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| Complex64::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0))).collect()
}

fn plan(c: &Case, epsilon: f64, threads: usize) -> WGridPlan {
    WGridPlan::new(c.size, c.pixel, &c.u, &c.v, &c.w, NufftParams { epsilon, oversampling: 2.0 }, threads).unwrap()
}

/// Forward and adjoint errors against the direct sums.
fn errors(c: &Case, epsilon: f64) -> (f64, f64, usize) {
    let p = plan(c, epsilon, 2);
    let f = random_complex(c.size * c.size, 1);
    let vis = random_complex(c.u.len(), 2);
    let fwd = relative_error(&p.forward(&f), &forward_w(c.size, c.pixel, &c.u, &c.v, &c.w, &f));
    let adj = relative_error(&p.adjoint(&vis), &adjoint_w(c.size, c.pixel, &c.u, &c.v, &c.w, &vis));
    (fwd, adj, p.planes())
}

fn check(fov_deg: f64, size: usize, w_range: (f64, f64), epsilon: f64) {
    let c = case(fov_deg, size, 300, w_range, 5);
    let w_max = c.w.iter().fold(0.0f64, |a, w| a.max(w.abs()));
    let (fwd, adj, planes) = errors(&c, epsilon);
    eprintln!(
        "field {fov_deg} deg, {size} px, w in {w_range:?} x |uv|max (w phase {:.1} rad), eps {epsilon:e}: \
         {planes} planes, forward {fwd:.2e}, adjoint {adj:.2e}",
        max_w_phase(size, c.pixel, w_max)
    );
    assert!(fwd <= 2.0 * epsilon, "forward error {fwd:e} > 2 eps ({epsilon:e}), field {fov_deg} deg");
    assert!(adj <= 2.0 * epsilon, "adjoint error {adj:e} > 2 eps ({epsilon:e}), field {fov_deg} deg");
}

#[test]
fn matches_direct_sum_small_field() {
    for eps in [1e-4, 1e-7] {
        check(1.0, 64, (-1.0, 1.0), eps);
    }
}

#[test]
fn matches_direct_sum_wide_field() {
    for eps in [1e-4, 1e-7] {
        check(20.0, 48, (-1.0, 1.0), eps);
        // w of one sign, away from zero: the planes and the phase centre are not at w = 0.
        check(20.0, 48, (0.3, 1.0), eps);
        check(20.0, 48, (-1.0, -0.5), eps);
    }
}

#[test]
fn matches_direct_sum_very_wide_field() {
    for eps in [1e-4, 1e-7, 1e-10] {
        check(60.0, 32, (-1.0, 1.0), eps);
    }
    check(45.0, 40, (-1.0, 1.0), 1e-5);
}

/// Every tabulated w-kernel, forced, meets the accuracy on a wide field; a finer plane
/// spacing reaches fewer planes per point.
#[test]
fn every_w_oversampling_matches_direct_sum() {
    let c = case(20.0, 48, 300, (-1.0, 1.0), 5);
    let f = random_complex(c.size * c.size, 1);
    let vis = random_complex(c.u.len(), 2);
    let (want_fwd, want_adj) = (forward_w(c.size, c.pixel, &c.u, &c.v, &c.w, &f), adjoint_w(c.size, c.pixel, &c.u, &c.v, &c.w, &vis));
    for epsilon in [1e-4, 1e-7] {
        let mut supports = Vec::new();
        for sigma in KernelShape::tabulated_oversamplings() {
            let params = NufftParams { epsilon, oversampling: 2.0 };
            let p = WGridPlan::build(c.size, c.pixel, &c.u, &c.v, &c.w, params, 2, false, Some(sigma)).unwrap();
            let (fwd, adj) = (relative_error(&p.forward(&f), &want_fwd), relative_error(&p.adjoint(&vis), &want_adj));
            eprintln!("eps {epsilon:e}, w oversampling {sigma}: w support {}, {} planes, forward {fwd:.2e}, adjoint {adj:.2e}", p.w_support(), p.planes());
            assert!(fwd <= 2.0 * epsilon && adj <= 2.0 * epsilon, "w oversampling {sigma}: forward {fwd:e}, adjoint {adj:e}");
            supports.push(p.w_support());
        }
        assert!(supports.windows(2).all(|s| s[1] <= s[0]) && supports[supports.len() - 1] < supports[0], "{supports:?}");
    }
}

/// The cost model: on a field whose w range needs few planes, the finest spacing (the
/// narrowest w-kernel, and here even fewer planes); where the w range needs many planes
/// and the points are few, their FFTs dominate and a coarse spacing wins.
#[test]
fn w_kernel_choice_follows_the_cost() {
    // A 512-pixel field of 2.9" pixels (dt 6.5e-6), |w| up to 1.6e4 wavelengths, a 1024 grid.
    let (dt, g, uv_support) = (6.5e-6, 1024, 8);
    let vla = w_kernel_choice(8e-7, 1.6e4, dt, 2_000_000, uv_support, g).unwrap();
    assert_eq!((vla.sigma, vla.shape.support), (6.0, 6));
    let deep_w = w_kernel_choice(8e-7, 1e6, dt, 1000, uv_support, g).unwrap();
    assert!(deep_w.sigma <= 2.0 && deep_w.shape.support > vla.shape.support, "{} {}", deep_w.sigma, deep_w.shape.support);
    // No choice beyond the planes a plan may have; a plan that would need more is an error.
    assert!(w_kernel_choice(8e-7, 1e12, dt, 1000, uv_support, g).is_none());
    let pixel = 20f64.to_radians() / 48.0;
    let e = WGridPlan::new(48, pixel, &[1.0, 2.0], &[1.0, 2.0], &[0.0, 1e9], NufftParams::default(), 1).err().unwrap().to_string();
    assert!(e.contains("w-planes on this field"), "{e}");
}

#[test]
fn forward_and_adjoint_are_adjoint() {
    let c = case(30.0, 48, 2000, (-1.0, 1.0), 8);
    let p = plan(&c, 1e-6, 2);
    assert!(p.planes() > 10, "{} planes: the test should exercise w-gridding", p.planes());
    let f = random_complex(c.size * c.size, 3);
    let vis = random_complex(c.u.len(), 4);
    let lhs: Complex64 = p.forward(&f).iter().zip(&vis).map(|(a, c)| a * c.conj()).sum();
    let rhs: Complex64 = f.iter().zip(&p.adjoint(&vis)).map(|(f, a)| f * a.conj()).sum();
    assert!((lhs - rhs).norm() <= 1e-10 * lhs.norm(), "{lhs} vs {rhs}");
}

#[test]
fn zero_w_is_the_2d_nufft() {
    let mut c = case(20.0, 48, 500, (0.0, 0.0), 6);
    c.w.iter_mut().for_each(|w| *w = 0.0);
    let params = NufftParams { epsilon: 1e-6, oversampling: 2.0 };
    let p = WGridPlan::new(c.size, c.pixel, &c.u, &c.v, &c.w, params, 2).unwrap();
    assert_eq!(p.planes(), 1);
    let x: Vec<f64> = c.u.iter().map(|u| -2.0 * PI * c.pixel * u).collect();
    let y: Vec<f64> = c.v.iter().map(|v| 2.0 * PI * c.pixel * v).collect();
    let nufft = Nufft2d::new(c.size, c.size, &x, &y, params, 2).unwrap();
    let f = random_complex(c.size * c.size, 1);
    let vis = random_complex(c.u.len(), 2);
    let mut fwd = vec![Complex64::default(); c.u.len()];
    nufft.forward(&f, &mut fwd);
    let mut adj = vec![Complex64::default(); c.size * c.size];
    nufft.adjoint(&vis, &mut adj);
    assert!(relative_error(&p.forward(&f), &fwd) < 1e-12);
    assert!(relative_error(&p.adjoint(&vis), &adj) < 1e-12);
}

#[test]
fn negligible_w_term_uses_one_plane_and_stays_accurate() {
    // On a 2 arcsec field, |w| up to 1% of |uv|max changes phases by about 1e-6 rad; a
    // constant w on a wide field is a phase screen, exact on one plane.
    let tiny = case(2.0 / 3600.0, 32, 300, (-0.01, 0.01), 7);
    let constant = case(30.0, 32, 300, (0.7, 0.7), 7);
    for (c, eps) in [(&tiny, 1e-4), (&constant, 1e-8)] {
        let (fwd, adj, planes) = errors(c, eps);
        assert_eq!(planes, 1);
        assert!(fwd <= 2.0 * eps && adj <= 2.0 * eps, "{fwd:e} {adj:e} at eps {eps:e}");
    }
}

#[test]
fn results_do_not_depend_on_threads() {
    let c = case(20.0, 64, 20_000, (-1.0, 1.0), 9);
    let f = random_complex(c.size * c.size, 1);
    let vis = random_complex(c.u.len(), 2);
    let (p1, p2) = (plan(&c, 1e-5, 1), plan(&c, 1e-5, 2));
    assert!(p1.forward(&f) == p2.forward(&f));
    assert!(p1.adjoint(&vis) == p2.adjoint(&vis));
}

#[test]
fn empty_visibilities_give_a_zero_image() {
    let p = WGridPlan::new(16, 1e-3, &[], &[], &[], NufftParams::default(), 1).unwrap();
    assert!(p.adjoint(&[]).iter().all(|v| v.norm() == 0.0));
    assert!(p.forward(&vec![Complex64::new(1.0, 0.0); 256]).is_empty());
}

#[test]
fn bad_inputs_are_clear_errors() {
    let params = NufftParams::default();
    let err = |r: Result<WGridPlan>| r.err().expect("an error").to_string();
    let e = err(WGridPlan::new(16, 1e-3, &[1.0], &[1.0, 2.0], &[0.0], params, 1));
    assert!(e.contains("uvw") && e.contains("length"), "{e}");
    let e = err(WGridPlan::new(16, 1e-3, &[1.0], &[1.0], &[f64::NAN], params, 1));
    assert!(e.contains("uvw") && e.contains("finite"), "{e}");
    let e = err(WGridPlan::new(16, 1e-3, &[f64::INFINITY], &[1.0], &[0.0], params, 1));
    assert!(e.contains("uvw"), "{e}");
    // 16 pixels of 0.1 rad: the corners are at l^2 + m^2 = 1.28.
    let e = err(WGridPlan::new(16, 0.1, &[1.0], &[1.0], &[0.0], params, 1));
    assert!(e.contains("pixel size") && e.contains("sine projection"), "{e}");
    let e = err(WGridPlan::new(15, 1e-3, &[1.0], &[1.0], &[0.0], params, 1));
    assert!(e.contains("image size"), "{e}");
    let e = err(WGridPlan::new(16, -1.0, &[1.0], &[1.0], &[0.0], params, 1));
    assert!(e.contains("pixel size"), "{e}");
}

#[test]
fn max_w_phase_is_the_corner_phase() {
    let (size, pixel) = (100, 1e-3);
    let r2 = 2.0 * (50.0 * pixel) * (50.0f64 * pixel);
    let expected = 2.0 * PI * 1000.0 * (1.0 - (1.0 - r2).sqrt());
    assert!((max_w_phase(size, pixel, 1000.0) - expected).abs() < 1e-12 * expected);
    assert!((max_w_phase(size, pixel, -1000.0) - expected).abs() < 1e-12 * expected);
    assert_eq!(max_w_phase(size, pixel, 0.0), 0.0);
    assert_eq!(max_w_phase(16, 0.1, 1.0), f64::INFINITY);
}

#[test]
fn kernel_transform_interpolant_matches_quadrature() {
    for eps in [1e-3, 1e-7, 1e-13] {
        let shape = KernelShape::for_accuracy(eps, 2.0).unwrap();
        let a = 0.25;
        let fit = Chebyshev::fit(|e| psi_hat(&shape, e), a, PSI_HAT_NODES);
        for k in 0..=100 {
            let eta = -a + 2.0 * a * k as f64 / 100.0;
            let exact = psi_hat(&shape, eta);
            assert!((fit.eval(eta) - exact).abs() <= 1e-13 * psi_hat(&shape, 0.0), "eps {eps:e} eta {eta}");
        }
        // psi_hat at eta = k / n is the 2D correction's coefficient.
        let coeffs = shape.fourier_coefficients(64, 16);
        assert!((psi_hat(&shape, 5.0 / 64.0) - coeffs[5]).abs() < 1e-13 * coeffs[0]);
    }
}

/// Forward and adjoint errors of `p` on the real image `f` and the visibilities `vis`,
/// against the direct sums (the adjoint's real part, what a real plan gives).
fn real_errors(p: &WGridPlan, c: &Case, f: &[f64], vis: &[Complex64]) -> (f64, f64) {
    let as_complex = |x: &[f64]| -> Vec<Complex64> { x.iter().map(|&x| Complex64::new(x, 0.0)).collect() };
    let exact_fwd = forward_w(c.size, c.pixel, &c.u, &c.v, &c.w, &as_complex(f));
    let exact_adj: Vec<Complex64> = adjoint_w(c.size, c.pixel, &c.u, &c.v, &c.w, vis).iter().map(|z| Complex64::new(z.re, 0.0)).collect();
    (relative_error(&p.forward_real(f), &exact_fwd), relative_error(&as_complex(&p.adjoint_real(vis)), &exact_adj))
}

#[test]
fn real_plan_matches_direct_sum_with_fewer_planes() {
    let c = case(20.0, 48, 400, (-1.0, 1.0), 12);
    let eps = 1e-6;
    let params = NufftParams { epsilon: eps, oversampling: 2.0 };
    let complex = plan(&c, eps, 2);
    let real = WGridPlan::new_real(c.size, c.pixel, &c.u, &c.v, &c.w, params, 2).unwrap();
    // Planes beyond the kernel support span the w range, which mirroring halves.
    let span = |p: &WGridPlan| p.planes() - p.w_support();
    assert!(span(&real) <= span(&complex) / 2 + 1, "{} vs {} planes", real.planes(), complex.planes());
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let f: Vec<f64> = (0..c.size * c.size).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let vis = random_complex(c.u.len(), 14);
    for (name, p) in [("real", &real), ("complex", &complex)] {
        let (fwd, adj) = real_errors(p, &c, &f, &vis);
        assert!(fwd <= 2.0 * eps && adj <= 2.0 * eps, "{name} plan: forward {fwd:e}, adjoint {adj:e}");
    }
    // Adjoint for the real inner products.
    let lhs: f64 = real.forward_real(&f).iter().zip(&vis).map(|(a, c)| (a * c.conj()).re).sum();
    let rhs: f64 = f.iter().zip(&real.adjoint_real(&vis)).map(|(f, a)| f * a).sum();
    assert!((lhs - rhs).abs() <= 1e-10 * lhs.abs(), "{lhs} vs {rhs}");
}

#[test]
#[should_panic(expected = "forward_real")]
fn real_plan_refuses_complex_images() {
    let p = WGridPlan::new_real(16, 1e-3, &[1.0], &[1.0], &[-1.0], NufftParams::default(), 1).unwrap();
    p.forward(&[Complex64::default(); 256]);
}

#[test]
fn suggested_oversampling_follows_the_cost() {
    // Few visibilities on a wide field: the plane FFTs dominate, the coarsest grid wins.
    let c = case(15.0, 512, 1000, (-1.0, 1.0), 15);
    assert_eq!(suggested_oversampling(c.size, c.pixel, &c.w, false, 1e-5), 1.25);
    // Without w-planes and with many visibilities per pixel the narrow kernel of the finer
    // grid wins.
    let w = vec![0.0; 2_000_000];
    assert_eq!(suggested_oversampling(64, 1e-4, &w, false, 1e-5), 2.0);
    // An invalid field falls back to the default.
    assert_eq!(suggested_oversampling(16, 0.1, &c.w, false, 1e-5), 2.0);
}

/// The imaging operator's choice: 1.5 where few samples make the plane FFTs dominate, 2 where
/// spreading does; at 1.5 a real plan still reaches the accuracy asked on a wide field.
#[test]
fn operator_oversampling_is_the_cheaper_of_1_5_and_2_and_keeps_the_accuracy() {
    let c = case(15.0, 512, 1000, (-1.0, 1.0), 15);
    assert_eq!(operator_oversampling(c.size, c.pixel, &c.w, 1e-5), 1.5, "1.25, the cost model's own choice here, is left out");
    assert_eq!(operator_oversampling(64, 1e-4, &vec![0.0; 2_000_000], 1e-5), 2.0);
    // Samples not at hand (read again at each update): their number and largest |w| choose
    // alike where their |w| reach from 0.
    let max_abs_w = c.w.iter().fold(0.0f64, |m, w| m.max(w.abs()));
    let from_zero: Vec<f64> = c.w.iter().map(|w| w.abs()).chain([0.0]).collect();
    assert_eq!(operator_oversampling_of(c.size, c.pixel, from_zero.len(), max_abs_w, 1e-5), operator_oversampling(c.size, c.pixel, &from_zero, 1e-5));
    assert_eq!(operator_oversampling_of(c.size, c.pixel, c.w.len(), max_abs_w, 1e-5), 1.5);
    assert_eq!(operator_oversampling_of(64, 1e-4, 2_000_000, 0.0, 1e-5), 2.0);
    let c = case(20.0, 64, 400, (-1.0, 1.0), 16);
    let eps = 1e-6;
    let plan = WGridPlan::new_real(c.size, c.pixel, &c.u, &c.v, &c.w, NufftParams { epsilon: eps, oversampling: 1.5 }, 2).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let f: Vec<f64> = (0..c.size * c.size).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let vis = random_complex(c.u.len(), 18);
    let (fwd, adj) = real_errors(&plan, &c, &f, &vis);
    assert!(fwd <= eps && adj <= eps, "forward {fwd:e}, adjoint {adj:e} at oversampling 1.5");
}

/// The per-cell layout and the pairwise Horner give the fit's polynomials, for an even and an
/// odd number of coefficients per cell.
#[test]
fn w_kernel_cells_evaluate_the_fitted_polynomials() {
    let naive = |coeffs: &[f64], support: usize, b: usize, z: f64| coeffs.chunks_exact(support).fold(0.0, |acc, c| acc * z + c[b]);
    let shape = KernelShape::for_accuracy(1e-6, 2.0).unwrap();
    let fitted = super::super::fit_kernel(&shape, 1e-7);
    let odd: Vec<f64> = (0..5 * 3).map(|i| (i as f64 * 0.37).sin()).collect();
    for (coeffs, support) in [(fitted, shape.support), (odd, 3)] {
        let wk = WKernel::new(support, &coeffs);
        for b in 0..support {
            for z in [-1.0, -0.43, 0.0, 0.2, 0.999] {
                let (want, got) = (naive(&coeffs, support, b, z), wk.cell(b, z));
                assert!((want - got).abs() <= 1e-14 * (1.0 + want.abs()), "cell {b} at {z}: {got} against {want}");
            }
        }
    }
}

/// The normal operator in the plan's order (no permutation, no per-point phase) equals the
/// direct sums' `Re{Phi^H diag(weight) Phi x}`, for real and complex plans, and the plan
/// released into `D` alone gives the same image to the last bit.
#[test]
fn the_normal_operator_in_plan_order_matches_the_direct_sums() {
    let c = case(20.0, 48, 400, (-1.0, 1.0), 21);
    let eps = 1e-6;
    let params = NufftParams { epsilon: eps, oversampling: 2.0 };
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let x: Vec<f64> = (0..c.size * c.size).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let weight: Vec<f64> = (0..c.u.len()).map(|_| rng.gen_range(0.1..2.0)).collect();
    let as_complex: Vec<Complex64> = x.iter().map(|&x| Complex64::new(x, 0.0)).collect();
    let weighted: Vec<Complex64> = forward_w(c.size, c.pixel, &c.u, &c.v, &c.w, &as_complex).iter().zip(&weight).map(|(v, &q)| v * q).collect();
    let exact: Vec<Complex64> = adjoint_w(c.size, c.pixel, &c.u, &c.v, &c.w, &weighted).iter().map(|z| Complex64::new(z.re, 0.0)).collect();
    for real in [true, false] {
        let p = if real { WGridPlan::new_real(c.size, c.pixel, &c.u, &c.v, &c.w, params, 2).unwrap() } else { plan(&c, eps, 2) };
        let d = p.normal_real(&x, &p.to_plan_order(&weight));
        let e = relative_error(&d.iter().map(|&v| Complex64::new(v, 0.0)).collect::<Vec<_>>(), &exact);
        assert!(e <= 4.0 * eps, "real plan {real}: {e:e}");
        let normal = p.into_normal(&weight);
        assert_eq!(normal.len(), c.u.len());
        assert_eq!(normal.apply(&x), d, "real plan {real}");
    }
}
