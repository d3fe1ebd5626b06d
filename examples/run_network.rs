//! Runs one ONNX network of a series the way the engine does (its checks, then ONNX Runtime or
//! tract), on a raw float32 `[1, 2, N, N]` input, and prints the load and best inference
//! seconds and the largest difference from an expected output, for benches/reference_import.py.
//!
//!     cargo run --release --example run_network -- NET.onnx N ort|tract INPUT.f32 [EXPECTED.f32] [REPEATS]

use r2d2_imaging::models::{use_onnx_runtime, LoadedNetwork};
use r2d2_imaging::BackendChoice;
use std::path::PathBuf;
use std::time::Instant;

// The command line's lookup of native ONNX Runtime, which the library leaves to its caller.
#[path = "../src/cli/onnx_runtime.rs"]
mod onnx_runtime;

fn read_f32(path: &str) -> Vec<f32> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

fn main() -> r2d2_imaging::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: run_network NET.onnx N ort|tract INPUT.f32 [EXPECTED.f32] [REPEATS]";
    let path = PathBuf::from(args.first().expect(usage));
    let size: usize = args.get(1).and_then(|s| s.parse().ok()).expect(usage);
    let backend = match args.get(2).map(String::as_str) {
        Some("ort") => BackendChoice::Ort,
        Some("tract") => BackendChoice::Tract,
        _ => panic!("{usage}"),
    };
    let input = read_f32(args.get(3).expect(usage));
    let expected = args.get(4).filter(|s| !s.is_empty()).map(|p| read_f32(p));
    let repeats: usize = args.get(5).and_then(|s| s.parse().ok()).unwrap_or(1);
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let started = Instant::now();
    if !matches!(backend, BackendChoice::Tract) {
        if let Ok(library) = onnx_runtime::find_onnxruntime() {
            use_onnx_runtime(&library)?;
        }
    }
    let mut network = LoadedNetwork::load(&path, size, backend, threads)?;
    let load = started.elapsed().as_secs_f64();
    let mut best = f64::INFINITY;
    let mut output = Vec::new();
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        output = network.run(&input)?;
        best = best.min(t.elapsed().as_secs_f64());
    }
    let relative = expected.map(|e| {
        let peak = e.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        output.iter().zip(&e).fold(0.0f32, |m, (a, b)| m.max((a - b).abs())) / peak
    });
    println!(
        "{{\"load_seconds\": {load:.3}, \"inference_seconds\": {best:.3}, \"relative_error\": {}}}",
        relative.map_or("null".to_string(), |r| format!("{r:e}"))
    );
    Ok(())
}
