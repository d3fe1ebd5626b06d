//! Embeds the engine: simulates an observation, hands it to `Engine::image` as Arrow record
//! batches and prints what comes back; nothing is read from or written to files.
//!
//! `cargo run --release --example embed`

use r2d2_imaging::imaging::PixelScale;
use r2d2_imaging::NufftParams;
use r2d2_imaging::simulate::ObservationSpec;
use r2d2_imaging::simulate::{simulate, SimulationRequest, SkyModel};
use r2d2_imaging::vis::to_record_batches;
use r2d2_imaging::{Engine, EngineOptions, ImageRequest, MemoryInput, Weighting};

fn main() -> r2d2_imaging::Result<()> {
    let size = 128;
    let observation = simulate(&SimulationRequest {
        observation: ObservationSpec {
            telescope: "vla".into(),
            configurations: vec![("c".into(), 2.0)],
            dec_deg: 40.0,
            integration_s: 60.0,
            frequencies_hz: vec![1.4e9],
            flag_fraction: 0.0,
            random_rotation: false,
            seed: 1,
        },
        sky: SkyModel::Procedural { seed: 1 },
        size,
        pixel: PixelScale::SuperResolution(1.5),
        dynamic_range: 1e3,
        noise_weighting: Weighting::Briggs { robust: 0.0 },
        phase_centre_deg: (150.0, 40.0),
        nufft: NufftParams::default(),
        threads: 0,
    })?;
    let (schema, batches) = to_record_batches(&observation.table, &observation.meta, 65_536)?;
    let engine = Engine::new(EngineOptions::default())?;
    let mut params = ImageRequest::default();
    (params.grid.size, params.step.step, params.step.iterations) = (size, "clean".into(), Some(3));
    let products = engine.image(MemoryInput::from_batches("sim", schema, batches), &params)?;
    println!("job {}: {} x {} pixels, {} iterations", products.id, products.size, products.size, products.iterations);
    for m in &products.metrics {
        println!("  iteration {}: residual ratio {:.4e}", m.iteration, m.residual_ratio);
    }
    let peak = products.model.as_ref().map_or(0.0, |m| m.iter().cloned().fold(f32::MIN, f32::max));
    println!("  model peak {peak:.4e} Jy/pixel; header: {} keywords", products.header.len());
    Ok(())
}
