//! `kind: products`: hands each finished job's products (arrays, header, metrics) to the run's
//! product sink (`Engine::run`), then, with a `to`, passes the job on (to a writer, say).
//! After a native plugin the products are handed over at the run's end, once the plugin has
//! been torn down cleanly (as a writer commits them, `super::writer`).

use super::params::ProductsParams;
use crate::job::{BuildContext, Emit, ImageContext, Job, ProductSink};
use crate::pipeline::{Port, Stage};
use crate::job::JobProducts;
use crate::Result;

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
