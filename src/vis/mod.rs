//! Visibilities as the imaging works on them ([`Visibilities`]: baselines in wavelengths,
//! weights, samples), what is known of the observation ([`ObservationMeta`]), and every table
//! format they are read from behind one reader contract ([`TableReader`]): Parquet and Arrow
//! (`table`), Arrow IPC (`ipc`), record batches in memory (`memory`), MeasurementSets
//! (`crate::ms`), opened by content with [`open`].

mod convert;
mod data;
mod error;
mod guard;
mod ipc;
mod mat;
mod memory;
mod normal;
mod open;
mod operator;
mod parquet;
mod parted;
mod parts;
mod reader;
mod split;
mod spill;
mod stream;
mod table;
mod times;

pub use data::*;
pub use error::TableError;
pub use ipc::IpcReader;
pub use mat::MatReader;
pub use memory::{memory_table, MemoryInput, MemoryTable};
pub use normal::{grid_planned, GriddedForm};
pub use open::{format_of, open, open_pass, open_source, read_table, telescope_of, write_parquet_from, OpenOptions, TableFormat};
pub use reader::{TableReader, STDIN};
pub use operator::{check_gridded_samples, source_images, weight_rule, weighting_problem, DataOperator, StreamedGridding, StreamedOperator};
pub use parted::{NormalisedImages, PartImages, PartPass, PartPasses, PartedObservation};
pub use parts::{chunk_weights, part_apply_normal, part_density, part_images, w_toeplitz_images, LocalParts};
pub use spill::spill_dir;
pub use stream::{Reopen, StreamedTable, VisSource};
pub use split::{nothing_to_image, read_parts, split_rows, Part, SplitBy, SplitRows, MAX_SPLIT_PARTS};
pub use convert::*;
pub(crate) use guard::*;
pub use parquet::*;
pub use table::*;
pub use times::{ObservedTimes, TRACK_GAP_S};
