//! MeasurementSets (casacore tables), read through casacure (a pure-Rust casacore table
//! reader and writer: StandardStMan, IncrementalStMan, TiledColumnStMan).
//!
//! An MS is read into the Parquet format's record batches (`crate::vis`: one Stokes I sample
//! per row, baselines in metres), so everything downstream of a table reader (exclusion
//! counting, `split_by`, conversion to Parquet) is shared with the other sources:
//!
//! - samples: one per (main-table row, selected channel); the visibility is the data column
//!   (as WSClean: `CORRECTED_DATA` when present, else `DATA`, unless `data_column` names one)
//!   combined into Stokes I from the correlations
//!   the `POLARIZATION` table declares: `I` itself, or `(XX + YY) / 2`, or `(RR + LL) / 2`;
//! - a sample is flagged when `FLAG_ROW` or either hand's `FLAG` is set;
//! - its weight is that of I from the hands' weights (`WEIGHT_SPECTRUM`, else `WEIGHT`, else
//!   `1 / SIGMA^2`): `4 / (1/wA + 1/wB)`, the inverse variance of `(A + B) / 2`;
//! - frequencies from `SPECTRAL_WINDOW.CHAN_FREQ` through `DATA_DESCRIPTION`; the phase centre
//!   from `FIELD.PHASE_DIR`; the telescope from `OBSERVATION.TELESCOPE_NAME`;
//! - autocorrelations (`ANTENNA1 == ANTENNA2`) and rows outside the field and window
//!   selection are not samples: they are skipped and counted in [`MsCounts`].
//!
//! Batches also carry `time` (MS `TIME`, seconds), `antenna1`, `antenna2`, `field` and `spw`,
//! so `split_by` can use them.

mod convert;
mod copy;
mod error;
mod from_parquet;
mod lock;
mod model;
mod reader;
mod table;

pub use convert::convert_ms_to_parquet;
pub use error::MsError;
pub use from_parquet::{convert_parquet_to_ms, AntennaRow};
pub use lock::{check_conversion_output, check_model_write};
pub use model::{write_model_column, ModelReport, ModelTarget};
pub use reader::{batch_schema, fields_with_rows, MsCounts, MsReader};

pub use table::{telescope_name, AUTO_DATA_COLUMN, FieldSelector, MsSelection, ORIGIN_KEY, Origin, is_measurement_set};
pub(crate) use table::{Layout, SampleColumns, StokesI, TempDir, Window, array_f64, as_f64, as_i64, casacore, column_index, combine_weights, describe, field_names, invalid, open_table, optional_column, read_cells};
