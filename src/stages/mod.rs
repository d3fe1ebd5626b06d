//! The built-in stage kinds, registered by their YAML `kind` in [`builtin`]. Each kind is one
//! file: its typed parameters (what the YAML holds, unknown keys refused; re-exported in
//! [`params`]), its stage, and the kind as registered (`KIND`: a `KindFn`, or for a source a
//! `SourceKind`, whose parameters say what the source reads, whether it makes several jobs and
//! what telescope its data come from). The engine's contracts (`crate::pipeline::registry`,
//! `crate::job`) say what a kind declares and how it is built.

mod arrow_ipc;
mod files;
mod final_clean;
mod gridder;
mod gridder_params;
mod mat;
mod memory;
#[cfg(feature = "ms")]
mod ms;
pub mod params;
mod parquet;
mod products;
mod residual;
mod series_field;
mod simulate;
mod step;
mod weighting;
mod writer;

use crate::job::{Built, KindFn, Product, Registry};
use crate::pipeline::{Role, StageParams};
use gridder_params::GridderParams;

/// The gridder (its stage's file is left as it is: the kind is declared here).
const GRIDDER: KindFn = KindFn {
    name: GridderParams::KIND,
    role: Role::Transform,
    consumes: &[Product::Visibilities, Product::Weights],
    produces: &[Product::Imaging, Product::Operator],
    consumes_also: None,
    passes_on: false,
    // The operator (and the visibilities) stay only if a stage downstream consumes them; a form
    // of `D` is made only if one updates a residual (consumes a model): without, the job's
    // products are the dirty image and the PSFs (`r2d2 dirty`).
    build: |c| {
        let keep_operator = c.consumed_downstream(Product::Operator);
        let images_only = !c.consumed_downstream(Product::Model);
        Ok(Built::Stage(Box::new(gridder::GridderStage::new(c.params()?, c.threads, keep_operator, images_only)?)))
    },
};

/// `kind: ms` in an r2d2 built without MeasurementSets: known, and refused saying why.
#[cfg(not(feature = "ms"))]
const NO_MS: KindFn = KindFn {
    name: "ms",
    role: Role::Source,
    consumes: &[],
    produces: &[Product::Visibilities],
    consumes_also: None,
    passes_on: false,
    build: |c| Err(c.error(Some("kind"), "kind 'ms': this r2d2 was built without the `ms` feature")),
};

/// A registry holding the built-in kinds.
pub fn builtin() -> Registry {
    const DISTINCT: &str = "built-in kinds have distinct names";
    let mut registry = Registry::new();
    registry.register(simulate::KIND).expect(DISTINCT);
    registry.register(parquet::KIND).expect(DISTINCT);
    registry.register(mat::KIND).expect(DISTINCT);
    registry.register(arrow_ipc::KIND).expect(DISTINCT);
    registry.register(memory::KIND).expect(DISTINCT);
    #[cfg(feature = "ms")]
    registry.register(ms::KIND).expect(DISTINCT);
    #[cfg(not(feature = "ms"))]
    registry.register(NO_MS).expect(DISTINCT);
    for kind in [weighting::KIND, GRIDDER, step::CLEAN, step::ONNX, step::NATIVE, residual::KIND, final_clean::KIND, writer::KIND, products::KIND] {
        registry.register(kind).expect(DISTINCT);
    }
    registry
}
