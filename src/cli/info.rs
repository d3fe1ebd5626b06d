//! `r2d2 info`: what this build and machine will use (inference backend, SIMD level, threads).

use super::onnx_runtime::find_onnxruntime;
use crate::steps::runtime::{use_onnx_runtime, BackendChoice, Runtime};
use crate::Result;

#[derive(clap::Args)]
pub struct Args {}

pub fn run(_args: Args) -> Result<()> {
    out!("r2d2 {}", env!("CARGO_PKG_VERSION"))?;
    out!("gridder SIMD: {:?}", crate::nufft::simd::SimdLevel::detect())?;
    out!("threads: {} available", std::thread::available_parallelism().map_or(1, |n| n.get()))?;
    match find_onnxruntime() {
        Ok(lib) => {
            out!("ONNX Runtime library: {}", lib.display())?;
            use_onnx_runtime(&lib)?;
        }
        Err(why) => out!("ONNX Runtime library: not found ({why})")?,
    }
    let runtime = Runtime::select(BackendChoice::Auto, 0)?;
    out!("ONNX inference (backend: auto): {}", runtime.describe())?;
    Ok(())
}
