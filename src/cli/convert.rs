//! `r2d2 convert OBS.ms OBS.parquet` (a MeasurementSet's Stokes I samples as a Parquet
//! visibility table) and back.

use crate::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// A MeasurementSet (written as Parquet), a Parquet table (written as an MS), or another
    /// table (Arrow IPC, a MATLAB .mat observation; written as Parquet).
    input: PathBuf,
    /// The Parquet table or MeasurementSet to write (replaced whole).
    output: PathBuf,
    #[command(flatten)]
    ms: crate::MsOptions,
}

pub fn run(args: Args) -> Result<()> {
    use crate::vis::TableFormat;
    // `-` names standard output elsewhere; a conversion writes a file or an MS directory.
    if args.output.as_os_str() == "-" {
        return Err(crate::Error::parameter(
            "output",
            "`-` (standard output): convert writes a Parquet file or a MeasurementSet directory, not a stream; give a path (./- for a file named -)",
        ));
    }
    match crate::vis::format_of(&args.input)? {
        #[cfg(feature = "ms")]
        TableFormat::MeasurementSet => {
            let (counts, samples) = crate::ms::convert_ms_to_parquet(&args.input, &args.ms.selection()?, &args.output)?;
            log::info!("{}: {counts}; wrote {samples} samples to {}", args.input.display(), args.output.display());
        }
        #[cfg(feature = "ms")]
        TableFormat::Parquet => {
            let made = crate::ms::convert_parquet_to_ms(&args.input, &args.output, &layout_antennas)?;
            log::info!(
                "{}: wrote {} samples as {} rows x {} channels (XX, YY) to {}",
                args.input.display(),
                made.samples,
                made.rows,
                made.channels,
                args.output.display()
            );
        }
        #[cfg(not(feature = "ms"))]
        TableFormat::MeasurementSet | TableFormat::Parquet => {
            return Err(crate::Error::input(&args.input, "converting to or from a MeasurementSet needs the `ms` feature, which this r2d2 was built without"));
        }
        // Every other format becomes the Parquet format, batch by batch.
        format => {
            #[cfg(feature = "ms")]
            crate::ms::check_conversion_output(&args.input, &args.output, false)?;
            #[cfg(not(feature = "ms"))]
            if let Some(input) = crate::staging::destroys_input(&args.output, &[args.input.as_path()]) {
                return Err(crate::Error::input(&args.output, format!("the output would replace or lie inside the input {}: choose another output path", input.display())));
            }
            let mut reader = crate::vis::open(&args.input, &crate::vis::OpenOptions::default())?;
            let mut meta = reader.meta().clone();
            meta.extra.insert("converted_from".to_string(), args.input.display().to_string());
            let samples = crate::vis::write_parquet_from(reader.as_mut(), &meta, &args.output)?;
            log::info!("{} ({}): wrote {samples} samples to {}", args.input.display(), format.name(), args.output.display());
        }
    }
    Ok(())
}

/// The antennas of the configurations a simulated table's metadata name (`configurations`, of
/// its `telescope` in the registry), in the order `r2d2 simulate` numbers them: each
/// configuration's after the earlier ones'. Named by station, with the configuration where
/// there are several (the VLA's pads differ between them); an error says what is unknown.
#[cfg(feature = "ms")]
fn layout_antennas(meta: &crate::vis::ObservationMeta) -> std::result::Result<Vec<crate::ms::AntennaRow>, String> {
    use crate::vis::CONFIGURATIONS_KEY;
    let configurations = meta
        .extra
        .get(CONFIGURATIONS_KEY)
        .ok_or_else(|| format!("no `{CONFIGURATIONS_KEY}` in its metadata, which `r2d2 simulate` writes"))?;
    let telescope = crate::simulate::telescope::telescope(&meta.telescope)
        .map_err(|_| format!("metadata `telescope` {:?} is not a telescope of data/telescopes/telescopes.yaml", meta.telescope))?;
    let names: Vec<&str> = configurations.split(',').map(str::trim).collect();
    let mut rows = Vec::new();
    for config in &names {
        let array = telescope.array(config).map_err(|e| format!("metadata `{CONFIGURATIONS_KEY}` {configurations:?}: {e}"))?;
        for k in 0..array.n_antennas() {
            let station = array.stations[k].clone();
            rows.push(crate::ms::AntennaRow {
                name: if names.len() > 1 { format!("{station}-{config}") } else { station.clone() },
                station,
                position_m: array.positions_itrf[k],
                dish_diameter_m: array.dish_diameter_m[k],
            });
        }
    }
    Ok(rows)
}
