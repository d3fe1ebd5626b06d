//! One observation imaged in parts that are read where they live (Dask workers, say): each
//! part is summarised, its weighting density gridded, its images and normal-operator
//! products made on its own, and the sums handed to the engine as a [`PartedObservation`].
//! The protocol is the one `r2d2_imaging.dask.image_parts` drives; a part that is not a file
//! implements [`LocalParts`].

pub use crate::operator::toeplitz::{WToeplitzBuilder, WToeplitzPlan};
pub use crate::vis::data::VisSummary;
pub use crate::vis::memory::memory_table;
pub use crate::vis::open::{open_pass, open_source};
pub use crate::vis::parted::{PartImages, PartPass, PartPasses, PartedObservation};
pub use crate::vis::parts::{part_apply_normal, part_density, part_images, w_toeplitz_images, LocalParts};
pub use crate::vis::split::{split_rows, SplitBy, SplitRows};
pub use crate::vis::stream::{PartCheck, VisSource};
pub use crate::weighting::{DensityGrid, WeightRule};
