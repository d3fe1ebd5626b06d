//! Images checked where they are made: finite and within a bound no sky reaches, so that a
//! value blown up by the data, a network or a plugin is named where it appears (stage,
//! iteration, which image) rather than at the writer, which cannot say where it came from.

use crate::{Error, Result};

/// Largest magnitude accepted in a dirty image, model or residual. Brighter than any radio
/// source by many orders, and far enough below the float32 range of the FITS products (3.4e38)
/// that a restored image (the model convolved with the beam) cannot overflow it.
pub const MAX_ABS: f64 = 1e30;

/// Ok when every value of `image` (N x N, `n` = N) is finite and at most [`MAX_ABS`] in
/// magnitude; otherwise an error naming `what` (e.g. "the model after step 3") and the first
/// bad pixel, with `cause` saying what usually makes it.
pub fn check_image(image: &[f64], n: usize, what: &str, cause: &str) -> Result<()> {
    let out_of_bounds = |v: &f64| v.is_nan() || v.abs() > MAX_ABS;
    let Some(k) = image.iter().position(out_of_bounds) else {
        return Ok(());
    };
    let bad = image.iter().filter(|v| out_of_bounds(v)).count();
    Err(Error::parameter(
        what.to_string(),
        format!(
            "{bad} pixel(s) are not finite or exceed {MAX_ABS:e} in magnitude, the first {:e} at pixel (x {}, y {}): {cause}",
            image[k],
            k % n.max(1),
            k / n.max(1)
        ),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_the_first_bad_pixel_and_counts_them() {
        assert!(check_image(&[0.0, -1e30, 1e30, 5.0], 2, "x", "y").is_ok());
        let e = check_image(&[0.0, 2e30, f64::NAN, 1.0], 2, "model after step 3", "diverged").unwrap_err().to_string();
        assert!(e.contains("invalid model after step 3") && e.contains("2 pixel(s)") && e.contains("2e30 at pixel (x 1, y 0)") && e.contains("diverged"), "{e}");
        assert!(check_image(&[f64::INFINITY], 1, "x", "y").is_err());
    }
}
