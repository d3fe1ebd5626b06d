//! `kind: products`: hands each finished job's products (arrays, header, metrics) to the run's
//! product sink (`Engine::run`), then, with a `to`, passes the job on (to a writer, say).
//! After a native plugin the products are handed over at the run's end, once the plugin has
//! been torn down cleanly (as a writer commits them, `super::writer`).

use super::step::holds_until_finished;
use crate::job::{BuildContext, Built, Emit, ImageContext, Job, KindFn, Product, ProductSink};
use crate::pipeline::{Port, Role, Stage, StageParams};
use crate::job::JobProducts;
use crate::Result;
use serde::{Deserialize, Serialize};

/// `kind: products`: no parameters (the sink is the run's).
#[derive(Clone, Debug, Default, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ProductsParams {}

impl StageParams for ProductsParams {
    const KIND: &'static str = "products";
}

/// The kind, as registered.
pub(super) const KIND: KindFn = KindFn {
    name: ProductsParams::KIND,
    role: Role::Sink,
    consumes: &[Product::Imaging],
    produces: &[],
    consumes_also: None,
    passes_on: true,
    build: |c| Ok(Built::Stage(Box::new(ProductsStage::new(c.params()?, c, holds_until_finished(c))?))),
};

pub struct ProductsStage {
    sink: Option<Box<dyn ProductSink>>,
    passes_on: bool,
    /// Whether products wait for the stage's finish, and those waiting.
    holds: bool,
    held: Vec<JobProducts>,
}

impl ProductsStage {
    /// `holds`: hand the products over at the run's end (see the module).
    pub fn new(_config: ProductsParams, ctx: &BuildContext<'_>, holds: bool) -> Result<ProductsStage> {
        let sink = ctx.take_sink();
        if sink.is_none() && !ctx.validating() {
            return Err(ctx.error(Some("kind"), "kind 'products' delivers to the run's product sink (Engine::run), and the run has none"));
        }
        Ok(ProductsStage { sink, passes_on: ctx.stage.to.is_some(), holds, held: Vec::new() })
    }
}

impl Stage<Job> for ProductsStage {
    fn process(&mut self, mut job: Job, emit: &mut Emit<'_>) -> Result<()> {
        if let Some(sink) = &mut self.sink {
            let products = JobProducts::from_job(&mut job, None)?;
            // A writer after this stage writes the same restored image without making it again.
            job.restored.clone_from(&products.image);
            if self.holds {
                self.held.push(products);
            } else {
                sink.deliver(products)?;
            }
        }
        if self.passes_on {
            emit(Port::Next, job)?;
        }
        Ok(())
    }

    fn finish(&mut self) -> Result<()> {
        if let Some(sink) = &mut self.sink {
            for products in std::mem::take(&mut self.held) {
                sink.deliver(products)?;
            }
        }
        Ok(())
    }
}
