//! Visibilities as the imaging works on them ([`Visibilities`]: baselines in wavelengths,
//! weights, samples), what is known of the observation ([`ObservationMeta`]), and every table
//! format they are read from behind one reader contract ([`TableReader`]): Parquet and Arrow
//! (`table`), Arrow IPC (`ipc`), record batches in memory (`memory`), MeasurementSets
//! (`crate::ms`), opened by content with [`open`].

mod convert;
pub(crate) mod data;
mod error;
mod guard;
mod ipc;
mod mat;
pub(crate) mod memory;
mod normal;
pub(crate) mod open;
mod operator;
mod parquet;
pub(crate) mod parted;
pub(crate) mod parts;
mod reader;
pub(crate) mod split;
mod spill;
pub(crate) mod stream;
mod table;
mod times;

pub(crate) use data::*;
pub(crate) use ipc::IpcReader;
pub(crate) use memory::MemoryTable;
pub(crate) use normal::grid_planned;
pub(crate) use open::{format_of, open, telescope_of, write_parquet_from, TableFormat};
pub(crate) use reader::{TableReader, STDIN};
pub(crate) use operator::{weight_rule, DataOperator};
pub(crate) use parted::PartedObservation;
pub(crate) use parts::chunk_weights;
pub(crate) use spill::spill_dir;
pub(crate) use stream::{StreamedTable, VisSource};
pub(crate) use split::{nothing_to_image, read_parts, Part, SplitBy};
pub(crate) use times::ObservedTimes;
pub(crate) use convert::*;
pub(crate) use guard::*;
pub(crate) use parquet::*;

// The public surface: visibility tables in and out.
pub use data::{ObservationMeta, Visibilities, SPEED_OF_LIGHT};
pub use error::TableError;
pub use memory::MemoryInput;
pub use open::{read_table, OpenOptions};
pub use parquet::read_parquet;
pub use table::{to_record_batches, write_parquet, VisTable};
