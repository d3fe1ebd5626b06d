//! `kind: products`: hands each finished job's products (arrays, header, metrics) to the run's
//! product sink (`Engine::run`), then, with a `to`, passes the job on (to a writer, say).

use crate::pipeline::registry::BuildContext;
use crate::pipeline::{Emit, Job, Port, ProductSink, Stage, StageParams};
use crate::products::JobProducts;
use crate::Result;
use serde::{Deserialize, Serialize};

/// `kind: products`: no parameters (the sink is the run's).
#[derive(Clone, Debug, Default, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ProductsParams {}

impl StageParams for ProductsParams {
    const KIND: &'static str = "products";
}

pub struct ProductsStage {
    sink: Option<Box<dyn ProductSink>>,
    passes_on: bool,
}

impl ProductsStage {
    pub fn new(_config: ProductsParams, ctx: &BuildContext<'_>) -> Result<ProductsStage> {
        let sink = ctx.take_sink();
        if sink.is_none() && !ctx.validating() {
            return Err(ctx.error(Some("kind"), "kind 'products' delivers to the run's product sink (Engine::run), and the run has none"));
        }
        Ok(ProductsStage { sink, passes_on: ctx.stage.to.is_some() })
    }
}

impl Stage for ProductsStage {
    fn process(&mut self, job: Job, emit: &mut Emit<'_>) -> Result<()> {
        if let Some(sink) = &mut self.sink {
            sink.deliver(JobProducts::from_job(&job, None)?)?;
        }
        if self.passes_on {
            emit(Port::Next, job)?;
        }
        Ok(())
    }
}
