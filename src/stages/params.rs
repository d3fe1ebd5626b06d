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
//! Each type is the kind's own configuration, defined in the kind's own file beside its stage
//! and re-exported here: the stage reads its YAML into it (unknown keys refused), so a field,
//! its default and its documentation are those of the YAML key. A type whose YAML has a
//! required key has a `new` taking it (`ParquetParams::new(files)`); the others are `Default`,
//! with the YAML's defaults.
//!
//! A [`StageSpec`](crate::StageSpec) keeps a stage's kind and parameters as a YAML mapping:
//! the open transport, since the registry takes kinds the engine does not know. These types
//! are the checked front for the kinds it does. There is deliberately no closed enum of the
//! built-in kinds (`#[serde(tag = "kind")]`): it would list the kinds a second time beside the
//! registry, could not hold an embedding program's kinds, and serde reads an internally tagged
//! enum through a buffer that loses the YAML's line and column in errors.

pub use super::arrow_ipc::ArrowIpcParams;
pub use super::files::Files;
pub use super::final_clean::FinalCleanParams;
pub use super::gridder_params::{GridderParams, RestoringBeam, DEFAULT_CHUNK_ROWS, DEFAULT_HOLD_MB, DEFAULT_KERNEL_MB};
pub use super::mat::MatParams;
pub use super::memory::ArrowParams;
#[cfg(feature = "ms")]
pub use super::ms::MsParams;
pub use super::parquet::ParquetParams;
pub use super::products::ProductsParams;
pub use super::residual::{ResidualMethod, ResidualParams};
pub use super::simulate::SimulateParams;
pub use super::weighting::WeightingParams;
pub use super::writer::WriterParams;
#[cfg(feature = "ms")]
pub use crate::ms::{FieldSelector, MsSelection};
pub use crate::job::ProductSet;
pub use crate::operator::WTermMode;
pub use crate::steps::clean::CleanConfig as CleanParams;
pub use crate::steps::native::{Isolation, NativeConfig as NativeParams};
pub use crate::steps::onnx::runtime::{BackendChoice, GraphOptimization};
pub use crate::steps::onnx::{OnnxConfig as OnnxParams, ValidityMode};
pub use crate::vis::split::SplitBy;
pub use crate::weighting::WeightingScheme;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::StageParams;
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
        reads("files: [a.mat]", MatParams(ParquetParams::new(Files::Many(vec!["a.mat".into()]))));
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
            MatParams::KIND,
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
