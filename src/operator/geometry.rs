//! The image's geometry: its size and pixel, and the one decision of the pixel size from the
//! data's longest baseline ([`PixelScale::geometry`]), which every imaging path goes through.

use crate::{Error, Result};

/// The super-resolution factor where neither the request nor a series gives one: the
/// reference's usual setting.
pub const DEFAULT_SUPERRESOLUTION: f64 = 1.5;

/// How the pixel size is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PixelScale {
    /// `pixel = 1 / (SR * 2 * max_uv)` (the reference's super-resolution factor).
    SuperResolution(f64),
    /// A fixed pixel size in arcseconds.
    Arcsec(f64),
}

impl Default for PixelScale {
    fn default() -> Self {
        PixelScale::SuperResolution(DEFAULT_SUPERRESOLUTION)
    }
}

impl PixelScale {
    /// The geometry of a `size`-pixel image of samples whose longest baseline is `max_uv`
    /// wavelengths (a fixed pixel size does not depend on it).
    pub fn geometry(self, size: usize, max_uv: f64) -> Result<ImageGeometry> {
        match self {
            PixelScale::SuperResolution(sr) => ImageGeometry::from_superresolution(size, sr, max_uv),
            PixelScale::Arcsec(p) => ImageGeometry::from_arcsec(size, p),
        }
    }
}

/// Image size and pixel scale.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageGeometry {
    /// Pixels per side (even).
    pub size: usize,
    /// Pixel size in radians.
    pub pixel_rad: f64,
}

impl ImageGeometry {
    /// Pixel size from the super-resolution factor: `pixel = 1 / (SR * 2 * max_uv)` radians
    /// (max_uv in wavelengths), i.e. the longest baseline is sampled SR times finer than
    /// Nyquist.
    pub fn from_superresolution(size: usize, superresolution: f64, max_uv: f64) -> Result<ImageGeometry> {
        if !(superresolution >= 1.0) || !superresolution.is_finite() {
            return Err(Error::parameter(
                "superresolution",
                format!("expected a factor >= 1 (pixel no coarser than Nyquist), got {superresolution}"),
            ));
        }
        if !(max_uv > 0.0) || !max_uv.is_finite() {
            return Err(Error::parameter("uv coverage", "no baseline longer than zero: cannot derive a pixel size"));
        }
        Self::new(size, 1.0 / (superresolution * 2.0 * max_uv))
    }

    pub fn from_arcsec(size: usize, pixel_arcsec: f64) -> Result<ImageGeometry> {
        Self::new(size, pixel_arcsec.to_radians() / 3600.0)
    }

    pub fn new(size: usize, pixel_rad: f64) -> Result<ImageGeometry> {
        if size < crate::limits::MIN_IMAGE_SIZE || !size.is_multiple_of(2) {
            return Err(Error::parameter("size", format!("expected an even image size of at least {} pixels, got {size}", crate::limits::MIN_IMAGE_SIZE)));
        }
        if !(pixel_rad > 0.0) || !pixel_rad.is_finite() {
            return Err(Error::parameter("pixel size", format!("expected a positive pixel size, got {pixel_rad} rad")));
        }
        // The sine projection holds where l^2 + m^2 < 1: at the image's corners, a field
        // (N x pixel) under sqrt(2) rad, about 81 deg.
        let field = pixel_rad * size as f64;
        if 2.0 * (0.5 * field).powi(2) >= 1.0 {
            return Err(Error::parameter(
                "pixel size",
                format!(
                    "a field of {size} x {:.4} deg = {:.1} deg is wider than the sine projection allows (l^2 + m^2 < 1 at the corners: under {:.1} deg): use fewer or smaller pixels",
                    pixel_rad.to_degrees(),
                    field.to_degrees(),
                    std::f64::consts::SQRT_2.to_degrees()
                ),
            ));
        }
        Ok(ImageGeometry { size, pixel_rad })
    }

    pub fn pixel_arcsec(&self) -> f64 {
        self.pixel_rad.to_degrees() * 3600.0
    }

    /// The super-resolution factor of this pixel for samples whose longest baseline is `max_uv`
    /// wavelengths (the inverse of [`from_superresolution`](Self::from_superresolution));
    /// `None` without a baseline longer than zero.
    pub fn superresolution(&self, max_uv: f64) -> Option<f64> {
        (max_uv > 0.0).then(|| 1.0 / (2.0 * max_uv * self.pixel_rad))
    }

    pub fn pixels(&self) -> usize {
        self.size * self.size
    }

    /// The operator's uv coordinates in radians per pixel, `(x, y) = (-2 pi u dl, 2 pi v dl)`:
    /// the sign of x makes RA increase towards lower pixel index.
    pub fn uv_to_phase(&self, u: f64, v: f64) -> (f64, f64) {
        let s = 2.0 * std::f64::consts::PI * self.pixel_rad;
        (-s * u, s * v)
    }

    /// The same geometry with twice the field of view (for the 2N PSF).
    pub fn doubled(&self) -> ImageGeometry {
        ImageGeometry { size: 2 * self.size, pixel_rad: self.pixel_rad }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pixel_scale_gives_the_geometry_and_the_geometry_its_superresolution() {
        let g = PixelScale::SuperResolution(1.5).geometry(64, 1000.0).unwrap();
        assert_eq!(g, ImageGeometry::from_superresolution(64, 1.5, 1000.0).unwrap());
        assert!((g.superresolution(1000.0).unwrap() - 1.5).abs() < 1e-12);
        assert_eq!(g.superresolution(0.0), None);
        let fixed = PixelScale::Arcsec(2.0).geometry(64, 1000.0).unwrap();
        assert_eq!(fixed, PixelScale::Arcsec(2.0).geometry(64, 10.0).unwrap());
        assert!((fixed.pixel_arcsec() - 2.0).abs() < 1e-12);
    }
}
