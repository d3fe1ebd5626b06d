//! The parameters of the built-in stage kinds, typed: what a Rust program writes instead of a
//! stage's YAML mapping.
//!
//! ```
//! use r2d2_imaging::params::{GridderParams, WeightingParams, WeightingScheme};
//! use r2d2_imaging::StageSpec;
//!
//! let weights = StageSpec::typed("weights", &WeightingParams { scheme: WeightingScheme::Uniform, ..Default::default() })?.to("grid");
//! let grid = StageSpec::typed("grid", &GridderParams { epsilon: 1e-5, ..Default::default() })?.to("step");
//! # Ok::<(), r2d2_imaging::Error>(())
//! ```
//!
//! Each type is the kind's own configuration: the stage reads its YAML into it (unknown keys
//! refused), so a field, its default and its documentation are those of the YAML key. A type
//! whose YAML has a required key has a `new` taking it (`ParquetParams::new(files)`); the others
//! are `Default`, with the YAML's defaults.
//!
//! A [`StageSpec`](crate::StageSpec) keeps a stage's kind and parameters as a YAML mapping:
//! the open transport, since the registry takes kinds the engine does not know. These types
//! are the checked front for the kinds it does. There is deliberately no closed enum of the
//! built-in kinds (`#[serde(tag = "kind")]`): it would list the kinds a second time beside the
//! registry, could not hold an embedding program's kinds, and serde reads an internally tagged
//! enum through a buffer that loses the YAML's line and column in errors.

pub use crate::vis::SplitBy;
#[cfg(feature = "ms")]
pub use crate::ms::FieldSelector;
pub use crate::steps::clean::CleanConfig as CleanParams;
pub use crate::steps::native::{Isolation, NativeConfig as NativeParams};
pub use crate::steps::onnx::runtime::{BackendChoice, GraphOptimization};
pub use crate::steps::onnx::{OnnxConfig as OnnxParams, ValidityMode};
pub use crate::weighting::WeightingScheme;

use crate::nufft::NufftParams;
pub use crate::operator::WTermMode;
use crate::pipeline::StageParams;
use crate::weighting::{Weighting, DEFAULT_GRID_FACTOR};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

impl StageParams for CleanParams {
    const KIND: &'static str = "clean";
}

impl StageParams for OnnxParams {
    const KIND: &'static str = "onnx";
}

impl StageParams for NativeParams {
    const KIND: &'static str = "native";
}

impl OnnxParams {
    /// The series (a directory, a name `r2d2 models` lists, or `auto`: the one trained for the
    /// image size) with the defaults of the other keys.
    pub fn new(series: impl Into<PathBuf>) -> OnnxParams {
        OnnxParams {
            series: series.into(),
            backend: BackendChoice::default(),
            threads: 0,
            networks: None,
            prefetch: true,
            graph_optimization: GraphOptimization::default(),
            realisation: None,
            validity: ValidityMode::default(),
        }
    }
}

impl NativeParams {
    /// The plugin library and the series length, with the defaults of the other keys.
    pub fn new(library: impl Into<PathBuf>, iterations: usize) -> NativeParams {
        NativeParams { library: library.into(), iterations, positivity: true, config: None, isolation: Isolation::default(), timeout: 600.0 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::de::DeserializeOwned;
    use std::fmt::Debug;

    /// `params` as the stage reads the YAML mapping `yaml` (its required keys only).
    fn reads<P: StageParams + PartialEq + Debug>(yaml: &str, params: P) {
        let read: P = serde_yaml::from_str(yaml).unwrap_or_else(|e| panic!("{}: {yaml}: {e}", P::KIND));
        assert_eq!(read, params, "{}: the defaults in code differ from the YAML's", P::KIND);
        // And back: what `StageSpec::typed` writes reads as the same parameters.
        let spec = crate::StageSpec::typed("s", &params).unwrap();
        assert_eq!(spec.kind, P::KIND);
        assert_eq!(from_value::<P>(spec.params().clone()), params, "{}: does not survive a round trip", P::KIND);
    }

    fn from_value<P: DeserializeOwned>(value: serde_yaml::Value) -> P {
        serde_yaml::from_value(value).unwrap()
    }

    #[test]
    fn defaults_in_code_are_the_yaml_defaults() {
        reads("{}", SimulateParams::default());
        reads("files: a.parquet", ParquetParams::new(Files::One("a.parquet".into())));
        reads("path: '-'", ArrowIpcParams::new("-"));
        reads("{}", ArrowParams::default());
        #[cfg(feature = "ms")]
        reads("path: a.ms", MsParams::new("a.ms"));
        reads("scheme: briggs", WeightingParams::default());
        reads("{}", GridderParams::default());
        reads("{}", CleanParams::default());
        reads("series: auto", OnnxParams::new("auto"));
        reads("{library: a.so, iterations: 3}", NativeParams::new("a.so", 3));
        reads("{}", ResidualParams::default());
        reads("{}", FinalCleanParams::default());
        reads("{}", WriterParams::default());
        reads("{}", ProductsParams::default());
    }

    #[test]
    fn every_builtin_kind_has_its_typed_parameters() {
        let typed = [
            SimulateParams::KIND,
            ParquetParams::KIND,
            ArrowIpcParams::KIND,
            ArrowParams::KIND,
            "ms", // MsParams::KIND, when built with MeasurementSets
            WeightingParams::KIND,
            GridderParams::KIND,
            CleanParams::KIND,
            OnnxParams::KIND,
            NativeParams::KIND,
            ResidualParams::KIND,
            FinalCleanParams::KIND,
            WriterParams::KIND,
            ProductsParams::KIND,
        ];
        let mut registered = crate::stages::builtin().names().into_iter().map(str::to_string).collect::<Vec<_>>();
        registered.sort();
        let mut typed: Vec<String> = typed.iter().map(|k| k.to_string()).collect();
        typed.sort();
        assert_eq!(registered, typed);
    }

    #[test]
    fn weighting_params_from_a_weighting() {
        let w = WeightingParams::new(crate::Weighting::Briggs { robust: -0.5 });
        assert_eq!((w.scheme, w.robust), (WeightingScheme::Briggs, -0.5));
        assert_eq!(WeightingParams::new(crate::Weighting::Natural).scheme, WeightingScheme::Natural);
    }
}

// ---- kind: arrow-ipc

/// `kind: arrow-ipc`: an Arrow IPC stream or file.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ArrowIpcParams {
    /// An IPC stream or file, or `-` for standard input (stream format).
    pub path: String,
    /// Job id (default: the file name without extension; `stdin` for standard input).
    #[serde(default)]
    pub id: Option<String>,
    /// Ground truth (FITS, Jy/pixel, same grid as the image) for SNR/logSNR per iteration.
    #[serde(default)]
    pub truth: Option<PathBuf>,
    /// Split the table into several jobs by a column.
    #[serde(default)]
    pub split_by: Option<SplitBy>,
    /// Image a stream that ends without its end-of-stream marker (a sender that stopped
    /// between batches), with a warning, instead of failing.
    #[serde(default)]
    pub allow_truncated: bool,
}

impl ArrowIpcParams {
    /// `path` with the defaults of the other keys.
    pub fn new(path: impl Into<String>) -> ArrowIpcParams {
        ArrowIpcParams { path: path.into(), id: None, truth: None, split_by: None, allow_truncated: false }
    }
}

impl StageParams for ArrowIpcParams {
    const KIND: &'static str = "arrow-ipc";
}

// ---- kind: gridder

/// `kind: gridder`: the NUFFT's accuracy, and whether it includes the w-term.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct GridderParams {
    /// NUFFT relative accuracy; default 1e-6.
    pub epsilon: f64,
    /// Oversampling of the NUFFT's grid; default 2.
    pub oversampling: f64,
    /// The w-term: `auto` (default: included by w-gridding where it turns a phase by more
    /// than `epsilon` over the field), `on` or `off` (coplanar, for comparison).
    pub w_term: WTermMode,
    /// Most memory (MB) the samples of a job read from a file may take held in an operator
    /// (the residual update through the operator: `method: nufft`, or the w-term where its
    /// Toeplitz form is not built); above it they are read again from the file at every
    /// update instead (or, for the w-term's Taylor series, once per kernel and for the final
    /// residual), in chunks as large as this allows. The Taylor series' kernels take at most
    /// this much too. With the w-term's Toeplitz form, the
    /// gridding pass's chunks take what this leaves beside the kernels' grids. Default 256.
    pub hold_mb: f64,
    /// Samples per chunk of a pass over the data: what gridding holds beside its grids (about
    /// 100 bytes a sample). Default 1048576.
    pub chunk_rows: usize,
}

/// The default of [`GridderParams::hold_mb`].
pub const DEFAULT_HOLD_MB: f64 = 256.0;

/// The default of [`GridderParams::chunk_rows`]: large enough that a chunk's fixed cost
/// (sorting, merging its tiles into the grids, a w-gridded chunk's plane FFTs) is small beside
/// its spreading, small enough to be little beside the images.
pub const DEFAULT_CHUNK_ROWS: usize = 1 << 20;

impl Default for GridderParams {
    fn default() -> Self {
        let NufftParams { epsilon, oversampling } = NufftParams::default();
        GridderParams { epsilon, oversampling, w_term: WTermMode::Auto, hold_mb: DEFAULT_HOLD_MB, chunk_rows: DEFAULT_CHUNK_ROWS }
    }
}

impl StageParams for GridderParams {
    const KIND: &'static str = "gridder";
}

// ---- kind: arrow

/// `kind: arrow`: the run's in-memory inputs.
#[derive(Clone, Debug, Default, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct ArrowParams {
    /// Ground truth (FITS, Jy/pixel, same grid as the image) for SNR/logSNR per iteration.
    pub truth: Option<PathBuf>,
    /// Split each input into several jobs by a column.
    pub split_by: Option<SplitBy>,
}

impl StageParams for ArrowParams {
    const KIND: &'static str = "arrow";
}

// ---- kind: ms

#[cfg(feature = "ms")]
/// `kind: ms`: a MeasurementSet.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct MsParams {
    /// The MeasurementSet (a directory).
    pub path: PathBuf,
    /// Job id (default: the MS name without its extension).
    #[serde(default)]
    pub id: Option<String>,
    /// The complex column to image (default `auto`: CORRECTED_DATA when the MS has it, else
    /// DATA, as WSClean chooses; or a name: DATA, CORRECTED_DATA, MODEL_DATA, ...).
    #[serde(default = "crate::ms::default_data_column")]
    pub data_column: String,
    /// Field id or name; required when the MS holds several fields (unless split by field).
    #[serde(default)]
    pub field: Option<FieldSelector>,
    /// Spectral windows to read (default: all).
    #[serde(default)]
    pub spw: Option<Vec<usize>>,
    /// Channel range `[start, end)` of every window.
    #[serde(default)]
    pub channels: Option<[usize; 2]>,
    /// Samples per batch (a chunk of rows).
    #[serde(default = "crate::vis::default_batch_rows")]
    pub batch_rows: usize,
    /// Ground truth (FITS, Jy/pixel, same grid as the image) for SNR/logSNR per iteration.
    #[serde(default)]
    pub truth: Option<PathBuf>,
    /// Split into several jobs: `{column: time, window: S}`, `{column: frequency}`,
    /// `{column: spw}`, `{column: field}`, or another numeric column of the batches.
    #[serde(default)]
    pub split_by: Option<SplitBy>,
}

#[cfg(feature = "ms")]
impl MsParams {
    /// `path` with the defaults of the other keys.
    pub fn new(path: impl Into<PathBuf>) -> MsParams {
        MsParams {
            path: path.into(),
            id: None,
            data_column: crate::ms::default_data_column(),
            field: None,
            spw: None,
            channels: None,
            batch_rows: crate::vis::default_batch_rows(),
            truth: None,
            split_by: None,
        }
    }
}

#[cfg(feature = "ms")]
impl StageParams for MsParams {
    const KIND: &'static str = "ms";
}

// ---- kind: parquet

/// One file (or glob pattern) or a list of them.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(untagged)]
pub enum Files {
    One(String),
    Many(Vec<String>),
}

/// `kind: parquet`: Parquet visibility tables, one job per file.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ParquetParams {
    /// A file, a list of files, or glob patterns (relative to the working directory).
    pub files: Files,
    /// Rows per record batch read.
    #[serde(default = "crate::vis::default_batch_rows")]
    pub batch_rows: usize,
    /// Ground truth (FITS, Jy/pixel, same grid as the image) for SNR/logSNR per iteration.
    #[serde(default)]
    pub truth: Option<PathBuf>,
    /// Split each file into several jobs by a column.
    #[serde(default)]
    pub split_by: Option<SplitBy>,
}

impl ParquetParams {
    /// `files` with the defaults of the other keys.
    pub fn new(files: Files) -> ParquetParams {
        ParquetParams { files, batch_rows: crate::vis::default_batch_rows(), truth: None, split_by: None }
    }
}

impl StageParams for ParquetParams {
    const KIND: &'static str = "parquet";
}

// ---- kind: products

/// `kind: products`: no parameters (the sink is the run's).
#[derive(Clone, Debug, Default, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ProductsParams {}

impl StageParams for ProductsParams {
    const KIND: &'static str = "products";
}

// ---- kind: residual

/// How the residual update computes `D x`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ResidualMethod {
    /// A convolution with the 2N PSF: memory no longer grows with the visibilities.
    #[default]
    Toeplitz,
    /// The exact NUFFT round trip through the visibilities, which the gridder then keeps.
    Nufft,
}

/// `kind: residual`: the residual update and the loop's exit.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct ResidualParams {
    /// Default `toeplitz`.
    pub method: ResidualMethod,
    /// Stop early by the reference v2 criterion (the residual ratio changes by less than
    /// `tolerance`, or rises at two consecutive iterations) instead of running the whole
    /// series; default true.
    pub early_stop: bool,
    /// Relative change of the residual ratio below which the loop stops (`early_stop`);
    /// default 1e-4.
    pub tolerance: f64,
    /// Stop a series whose residual ratio rises above 1 (its model explains the data worse
    /// than an empty image) or rises at two consecutive iterations, keep the iterate of lowest
    /// residual ratio as the model (the empty model if none is below 1), and warn; default
    /// true.
    pub divergence_guard: bool,
}

impl Default for ResidualParams {
    fn default() -> Self {
        ResidualParams { method: ResidualMethod::Toeplitz, early_stop: true, tolerance: 1e-4, divergence_guard: true }
    }
}

impl StageParams for ResidualParams {
    const KIND: &'static str = "residual";
}

// ---- kind: final_clean

/// `kind: final_clean`: after the imaging loop, CLEAN major cycles on what the step's model
/// leaves in the residual (components of both signs, with the PSF, each major cycle's residual
/// the exact `x_d - D x`), so that the model's fluxes are what the data say: a network series
/// leaves its compact sources too bright, with negative bowls in the residual, that the
/// stopping rule does not see. A cycle that does not lower the residual is undone.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct FinalCleanParams {
    /// Most major cycles; default 20. 0 turns the stage into a pass-through.
    pub major_cycles: usize,
    /// Minor-cycle loop gain; default 0.1.
    pub gain: f64,
    /// Fraction of the residual's peak each major cycle cleans away (WSClean's `-mgain`);
    /// default 0.8.
    pub major_gain: f64,
    /// Clean the whole image down to this many times the residual's robust noise, then only
    /// where components were taken (WSClean's `-auto-mask`); default 5.
    pub auto_mask: f64,
    /// Inside that mask, stop at this many times the residual's robust noise (WSClean's
    /// `-auto-threshold`); default 2. Noise peaks elsewhere stay in the residual, where they
    /// belong, instead of becoming model components.
    pub auto_threshold: f64,
    /// Most components per major cycle; default 10 000.
    pub components_per_cycle: usize,
    /// Islands of the step's model (connected positive pixels) no larger than this many PSF
    /// main lobes are taken out of the model before the cycles and cleaned afresh; default 4,
    /// 0 keeps every island. A network series draws a point source as a blob wider than
    /// the PSF, which components added on top correct in flux only with a ring of negative
    /// ones around it; CLEAN's own components give a point source a point.
    pub compact_beams: f64,
    /// Around those islands, stop at this many times the residual's robust noise; default 1.
    /// A point source's flux is then what the data measure to a fraction of the noise, while
    /// extended emission keeps `auto_threshold` (deeper there, noise becomes model).
    pub compact_threshold: f64,
}

impl Default for FinalCleanParams {
    fn default() -> Self {
        FinalCleanParams {
            major_cycles: 20,
            gain: 0.1,
            major_gain: crate::steps::clean::DEFAULT_MAJOR_GAIN,
            auto_mask: 5.0,
            auto_threshold: 2.0,
            components_per_cycle: 10_000,
            compact_beams: 4.0,
            compact_threshold: 1.0,
        }
    }
}

impl StageParams for FinalCleanParams {
    const KIND: &'static str = "final_clean";
}

// ---- kind: simulate

/// `kind: simulate`: simulated observations of procedural skies.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimulateParams {
    /// Number of jobs (seeds `seed`, `seed + 1`, ...); default 1.
    pub jobs: usize,
    /// Default 7.
    pub seed: u64,
    /// Of the procedural sky; default 1e4.
    pub dynamic_range: f64,
    /// A telescope of `data/telescopes/telescopes.yaml`; default `vla`.
    pub telescope: String,
    /// Its configurations; default its typical observation's (`[a, c]` for the VLA).
    pub configurations: Option<Vec<String>>,
    /// Hours per configuration; default its typical observation's (`[6, 2]` for the VLA).
    pub hours: Option<Vec<f64>>,
    /// Declination of the phase centre; default the telescope's typical observation's (40
    /// degrees for the VLA, -30 for MeerKAT).
    pub dec_deg: Option<f64>,
    /// Default 180 degrees.
    pub ra_deg: f64,
    /// Seconds per sample; default the typical observation's (VLA 30, MeerKAT 8).
    pub integration_s: Option<f64>,
    /// Frequency channels and the lowest frequency; default the typical observation's (VLA
    /// 1 at 1400 MHz, MeerKAT 4 from 856 MHz).
    pub channels: Option<usize>,
    pub frequency_mhz: Option<f64>,
    /// Highest to lowest channel frequency; default the typical observation's (VLA 1, MeerKAT 2).
    pub frequency_ratio: Option<f64>,
    /// Fraction of the samples flagged; default 0.
    pub flag_fraction: f64,
    /// Weighting the noise level is defined for; default Briggs, robust 0.
    pub noise_weighting: WeightingScheme,
    pub robust: f64,
}

impl Default for SimulateParams {
    fn default() -> Self {
        SimulateParams {
            jobs: 1,
            seed: 7,
            dynamic_range: 1e4,
            telescope: "vla".into(),
            configurations: None,
            hours: None,
            dec_deg: None,
            ra_deg: 180.0,
            integration_s: None,
            channels: None,
            frequency_mhz: None,
            frequency_ratio: None,
            flag_fraction: 0.0,
            noise_weighting: WeightingScheme::Briggs,
            robust: 0.0,
        }
    }
}

impl StageParams for SimulateParams {
    const KIND: &'static str = "simulate";
}

// ---- kind: weighting

/// `kind: weighting`: how each visibility is weighted. `scheme` has no default in YAML (a
/// pipeline says which it uses); `WeightingParams::default()` is `r2d2 image`'s, Briggs with
/// robust 0.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct WeightingParams {
    /// natural, uniform or briggs.
    pub scheme: WeightingScheme,
    /// Briggs robustness (-2: close to uniform, 2: close to natural); default 0.
    #[serde(default)]
    pub robust: f64,
    /// Uniform and Briggs weights count the visibilities in a uv grid of `grid_factor x size`
    /// cells per axis.
    #[serde(default = "grid_factor")]
    pub grid_factor: f64,
}

impl StageParams for WeightingParams {
    const KIND: &'static str = "weighting";
}

impl Default for WeightingParams {
    fn default() -> Self {
        WeightingParams::new(Weighting::Briggs { robust: 0.0 })
    }
}

impl WeightingParams {
    /// The stage for `weighting`, with the default grid factor.
    pub fn new(weighting: Weighting) -> WeightingParams {
        let (scheme, robust) = match weighting {
            Weighting::Natural => (WeightingScheme::Natural, 0.0),
            Weighting::Uniform => (WeightingScheme::Uniform, 0.0),
            Weighting::Briggs { robust } => (WeightingScheme::Briggs, robust),
            Weighting::Given => (WeightingScheme::Given, 0.0),
        };
        WeightingParams { scheme, robust, grid_factor: grid_factor() }
    }
}

fn grid_factor() -> f64 {
    DEFAULT_GRID_FACTOR
}

// ---- kind: writer

/// `kind: writer`: where and what a job's products are written.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct WriterParams {
    /// Output prefix; `{job}` is replaced by the job id. Default `{job}`.
    pub prefix: String,
    /// A PNG preview (log scale, colour bar) beside each FITS product; default true.
    pub previews: bool,
    /// Decades shown by the previews' log scale; default: the dynamic range of the truth
    /// or of the simulated sky when known, else 1e3.
    pub preview_dynamic_range: Option<f64>,
    /// Predict the final model's visibilities into this column of the input MeasurementSet
    /// (`kind: ms` jobs), e.g. MODEL_DATA; created when missing.
    pub model_column: Option<String>,
}

impl Default for WriterParams {
    fn default() -> Self {
        WriterParams { prefix: "{job}".into(), previews: true, preview_dynamic_range: None, model_column: None }
    }
}

impl StageParams for WriterParams {
    const KIND: &'static str = "writer";
}
