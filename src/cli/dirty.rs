//! `r2d2 dirty`: dirty image and PSF, named like WSClean's products, through `Engine::dirty`
//! (the source, weighting and gridder stages `r2d2 image` runs, with no step); its options are
//! the library's `DirtyRequest`.

use crate::{DirtyRequest, Result};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Visibilities (Parquet, Arrow IPC, a .mat observation) or a MeasurementSet.
    input: PathBuf,
    #[command(flatten)]
    request: DirtyRequest,
}

pub fn run(args: Args) -> Result<()> {
    let mut request = args.request;
    request.name.get_or_insert_with(|| super::DEFAULT_NAME.to_string());
    let (engine, _bar) = super::engine::engine(request.grid.threads, false)?;
    let engine = engine.with_cancel(super::run::cancel_on_ctrl_c());
    if request.ms.channels_out.is_some_and(|n| n > 1) {
        let groups = engine.dirty_channels(args.input.as_path(), &request)?;
        log::info!("{}: {} channel groups, {} x {} images", args.input.display(), groups.channels.len(), request.grid.size, request.grid.size);
        return Ok(());
    }
    let products = engine.dirty(args.input.as_path(), &request)?;
    let weighting = products.header.iter().find(|(key, _)| key == "WEIGHT").map_or(String::new(), |(_, w)| format!(", {w} weighting"));
    log::info!("{}: {} x {} image, {:.4} arcsec pixels{weighting}", args.input.display(), products.size, products.size, products.pixel_arcsec);
    Ok(())
}
