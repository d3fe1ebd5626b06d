//! Runtime choice of the instruction set for the gridding inner loops.
//!
//! The crate is compiled for the baseline target (SSE2 on x86-64), where a kernel row of 14
//! reals takes 7 two-lane operations and multiply-adds are two instructions. The inner loops
//! are therefore also compiled with AVX2 + FMA and with AVX-512 enabled, and the widest one
//! the CPU supports is picked when a plan is made. Same source, same results up to the
//! rounding of fused multiply-adds.

/// Instruction set of the gridding inner loops.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimdLevel {
    /// The compilation target's baseline (SSE2 on x86-64), separate multiply and add.
    Baseline,
    /// x86-64 AVX2 with fused multiply-add.
    Avx2Fma,
    /// x86-64 AVX-512 (F, VL, DQ) with fused multiply-add.
    Avx512,
}

impl SimdLevel {
    /// The widest level this CPU supports, unless `R2D2_SIMD` (`baseline`, `avx2`,
    /// `avx512`) asks for a narrower one (benchmarks and tests).
    pub fn detect() -> SimdLevel {
        let best = Self::best_supported();
        match std::env::var("R2D2_SIMD").ok().as_deref() {
            Some("baseline") => SimdLevel::Baseline,
            Some("avx2") if best != SimdLevel::Baseline => SimdLevel::Avx2Fma,
            _ => best,
        }
    }

    /// Whether this CPU can run code compiled for `self`.
    pub fn is_supported(self) -> bool {
        match self {
            SimdLevel::Baseline => true,
            SimdLevel::Avx2Fma => Self::best_supported() != SimdLevel::Baseline,
            SimdLevel::Avx512 => Self::best_supported() == SimdLevel::Avx512,
        }
    }

    #[cfg(target_arch = "x86_64")]
    fn best_supported() -> SimdLevel {
        let avx2 = is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma");
        let avx512 = avx2
            && is_x86_feature_detected!("avx512f")
            && is_x86_feature_detected!("avx512vl")
            && is_x86_feature_detected!("avx512dq");
        if avx512 {
            SimdLevel::Avx512
        } else if avx2 {
            SimdLevel::Avx2Fma
        } else {
            SimdLevel::Baseline
        }
    }

    #[cfg(not(target_arch = "x86_64"))]
    fn best_supported() -> SimdLevel {
        SimdLevel::Baseline
    }
}

/// `a * b + c`, fused when `FMA` (only instantiated with `FMA = true` inside functions
/// compiled with the `fma` target feature: elsewhere `mul_add` would be a library call).
#[inline(always)]
pub fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// Define `$name(level, args..)` calling the `#[inline(always)]` generic function `$body`
/// (with const parameters `W, W2, L` and a trailing `FMA: bool`) compiled for `level`.
macro_rules! multiversion {
    (
        $(#[$meta:meta])*
        fn $name:ident<const W: usize, const W2: usize, const L: usize>($($arg:ident: $ty:ty),* $(,)?) => $body:ident
    ) => {
        $(#[$meta])*
        fn $name<const W: usize, const W2: usize, const L: usize>(level: $crate::nufft::simd::SimdLevel, $($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            fn avx2<const W: usize, const W2: usize, const L: usize>($($arg: $ty),*) {
                $body::<W, W2, L, true>($($arg),*)
            }
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512dq")]
            fn avx512<const W: usize, const W2: usize, const L: usize>($($arg: $ty),*) {
                $body::<W, W2, L, true>($($arg),*)
            }
            match level {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: a plan only holds a level that `SimdLevel::is_supported` confirmed
                // on this CPU (`detect` / `Nufft2d::set_simd_level`), so the target features
                // these functions are compiled with are present.
                $crate::nufft::simd::SimdLevel::Avx2Fma => unsafe { avx2::<W, W2, L>($($arg),*) },
                #[cfg(target_arch = "x86_64")]
                // SAFETY: as above.
                $crate::nufft::simd::SimdLevel::Avx512 => unsafe { avx512::<W, W2, L>($($arg),*) },
                _ => $body::<W, W2, L, false>($($arg),*),
            }
        }
    };
}
pub(crate) use multiversion;
