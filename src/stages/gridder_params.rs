//! `kind: gridder`'s parameters. They belong beside the gridder stage (`gridder.rs`), which
//! reads them as `super::params::GridderParams`; they stand in a file of their own until that
//! stage takes them in.

use crate::nufft::NufftParams;
use crate::operator::WTermMode;
use crate::pipeline::StageParams;
use serde::{Deserialize, Serialize};

/// `kind: gridder`: the NUFFT's accuracy, and whether it includes the w-term.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct GridderParams {
    /// NUFFT relative accuracy; default 1e-6.
    pub epsilon: f64,
    /// Oversampling of the NUFFT's grid. Unset (the default): 2, except for an operator that
    /// corrects the w-term, applied at every residual update (its samples held or read again),
    /// which takes the cheaper of 1.5 and 2 for its data (`nufft::wgrid::operator_oversampling`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub oversampling: Option<f64>,
    /// The w-term: `auto` (default: included by w-gridding where it turns a phase by more
    /// than `epsilon` over the field), `on` or `off` (coplanar, for comparison).
    pub w_term: WTermMode,
    /// Most memory (MB) the samples of a job read from a file may take held in an operator
    /// (the residual update through the operator: `method: nufft`, or the w-term where its
    /// Toeplitz form is not built); above it they are read again from the file at every
    /// update instead (or, for the w-term's Taylor series, once per kernel and for the final
    /// residual), in chunks as large as this allows. Held, `D` alone takes about 56 bytes a
    /// sample (100 where the exact round trip keeps the operator with its samples); building
    /// it takes about 150 a sample once, while the dirty image and the PSF are made. With the
    /// w-term's Toeplitz form, the gridding pass's chunks take what half of this leaves beside
    /// the kernels' grids. Default 1024.
    pub hold_mb: f64,
    /// Most memory (MB) the kernels of a convolution form of the w-term's residual update may
    /// take: the w-aware Toeplitz form's grids while gridding (unless the samples held would
    /// take more), the Taylor series' kernels. Default 256.
    pub kernel_mb: f64,
    /// Samples per chunk of a pass over the data: what gridding holds beside its grids (about
    /// 100 bytes a sample). Default 1048576.
    pub chunk_rows: usize,
    /// The restoring beam: `fit` (default: an elliptical Gaussian fitted to the PSF's main
    /// lobe), `fit_circular` (one width fitted to it), `theoretic` (circular, 1 / the longest
    /// baseline kept, or the Gaussian taper's width where that is wider) or
    /// `{given: {major_arcsec, minor_arcsec, pa_deg}}`.
    pub restoring_beam: RestoringBeam,
}

/// How the restoring beam is chosen (WSClean's `-fit-beam`, `-circular-beam`,
/// `-no-fit-beam`/`-theoretic-beam`, `-beam-shape`/`-beam-size`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum RestoringBeam {
    /// An elliptical Gaussian fitted to the PSF's main lobe.
    #[default]
    Fit,
    /// A circular Gaussian fitted to the PSF's main lobe.
    FitCircular,
    /// Circular, FWHM 1 / the longest baseline kept (radians), or the Gaussian taper's FWHM
    /// where that is wider: no PSF fit.
    Theoretic,
    /// Given: FWHM of the axes in arcsec, position angle in degrees east of north.
    Given { major_arcsec: f64, minor_arcsec: f64, pa_deg: f64 },
}

impl RestoringBeam {
    /// `Err` names `field` and what was expected, for a given beam that is not one.
    pub fn check(&self, field: &str) -> crate::Result<()> {
        if let RestoringBeam::Given { major_arcsec, minor_arcsec, pa_deg } = *self {
            if !(major_arcsec > 0.0 && major_arcsec.is_finite() && minor_arcsec > 0.0 && minor_arcsec.is_finite()) {
                return Err(crate::Error::parameter(field, format!("expected positive beam widths in arcsec, got {major_arcsec} x {minor_arcsec}")));
            }
            if minor_arcsec > major_arcsec {
                return Err(crate::Error::parameter(field, format!("the minor axis ({minor_arcsec} arcsec) is wider than the major axis ({major_arcsec} arcsec): give the major axis first")));
            }
            if !pa_deg.is_finite() {
                return Err(crate::Error::parameter(field, format!("expected a finite position angle in degrees, got {pa_deg}")));
            }
        }
        Ok(())
    }
}

/// The default of [`GridderParams::hold_mb`]: an 8 h MeerKAT track of 4 channels averaged to
/// 20 s (about 12 million samples, 650 MB as `D` alone) is held; read again at each update,
/// each chunk of it would pay its own w-planes' FFTs and its own planning.
pub const DEFAULT_HOLD_MB: f64 = 1024.0;

/// The default of [`GridderParams::kernel_mb`]: apart from the samples' budget, so that
/// holding more samples does not let a w-aware Toeplitz form (two FFTs per w-plane at each
/// update) displace a Taylor series of low order on a field of a few hundred pixels, where the
/// series' updates are several times cheaper.
pub const DEFAULT_KERNEL_MB: f64 = 256.0;

/// The default of [`GridderParams::chunk_rows`]: large enough that a chunk's fixed cost
/// (sorting, merging its tiles into the grids, a w-gridded chunk's plane FFTs) is small beside
/// its spreading, small enough to be little beside the images.
pub const DEFAULT_CHUNK_ROWS: usize = 1 << 20;

impl Default for GridderParams {
    fn default() -> Self {
        let NufftParams { epsilon, .. } = NufftParams::default();
        GridderParams { epsilon, oversampling: None, w_term: WTermMode::Auto, hold_mb: DEFAULT_HOLD_MB, kernel_mb: DEFAULT_KERNEL_MB, chunk_rows: DEFAULT_CHUNK_ROWS, restoring_beam: RestoringBeam::Fit }
    }
}

impl StageParams for GridderParams {
    const KIND: &'static str = "gridder";
}
