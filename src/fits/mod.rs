//! FITS images: writing sky images the way WSClean does, and reading them back.
//!
//! Images are written with the layout and keywords WSClean uses (BITPIX -32; axes RA,
//! Dec, FREQ, STOKES; SIN projection about the phase centre, which sits on pixel
//! (nx/2, ny/2) counted from 0), so that viewers, astropy and comparison scripts place
//! our images on the sky exactly like WSClean's and the two can be compared pixel by
//! pixel.
//!
//! Pixel arrays are row-major `image[iy * nx + ix]` with `ix` along FITS axis 1 (RA,
//! fastest varying) and `iy` along axis 2 (Dec). That is FITS storage order, so nothing
//! is transposed on the way in or out. RA increases towards smaller `ix` (east is left,
//! as on the sky seen from the ground), Dec towards larger `iy`.

mod error;
mod image;

pub use crate::deconv::Beam;
pub use error::FitsError;
pub use image::{read_image, write_image, BrightnessUnit, FitsImage, ImageWcs, Pixels};
pub(crate) use image::*;
