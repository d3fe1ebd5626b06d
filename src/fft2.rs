//! Two-dimensional complex FFTs on row-major arrays, by rows then columns with rustfft.
//! Columns are transposed in blocks so each FFT runs on contiguous memory.

use num_complex::Complex64;
use rayon::prelude::*;
use rustfft::{Fft, FftDirection, FftPlanner};
use std::sync::Arc;

/// Plans for `ny x nx` transforms in one direction (unnormalised, like rustfft).
pub struct Fft2 {
    nx: usize,
    ny: usize,
    rows: Arc<dyn Fft<f64>>,
    cols: Arc<dyn Fft<f64>>,
}

impl Fft2 {
    pub fn new(ny: usize, nx: usize, direction: FftDirection) -> Fft2 {
        let mut planner = FftPlanner::new();
        Fft2 { nx, ny, rows: planner.plan_fft(nx, direction), cols: planner.plan_fft(ny, direction) }
    }

    /// Transform `data` (`ny * nx`, row-major) in place, using the current rayon pool.
    pub fn process(&self, data: &mut [Complex64]) {
        assert_eq!(data.len(), self.nx * self.ny);
        self.transform_rows(data);
        self.transform_columns(data, &mut vec![Complex64::default(); data.len()]);
    }

    /// [`Fft2::process`] of data whose rows from `nonzero_rows` on are zero (a zero-padded
    /// image), their row transforms skipped, leaving the spectrum transposed in `data` (`nx x
    /// ny`: frequency `(ky, kx)` at `kx * ny + ky`): the transpose back is skipped too. A
    /// convolution multiplies spectra pointwise, in any layout, and [`Fft2::process_transposed_to_rows`]
    /// takes the product back: two of the four transposes of a convolution are saved.
    /// `scratch` (as long as `data`) is exchanged with `data`.
    pub fn process_from_rows_transposed(&self, data: &mut Vec<Complex64>, nonzero_rows: usize, scratch: &mut Vec<Complex64>) {
        assert_eq!(data.len(), self.nx * self.ny);
        assert_eq!(scratch.len(), data.len(), "scratch size");
        self.transform_rows(&mut data[..nonzero_rows.min(self.ny) * self.nx]);
        transpose(data, scratch, self.ny, self.nx);
        self.transform_contiguous_columns(scratch);
        std::mem::swap(data, scratch);
    }

    /// [`Fft2::process`] of a spectrum laid out as [`Fft2::process_from_rows_transposed`]
    /// leaves it, where only rows `first_row..` of the result are used: the result in `data` is
    /// row-major (`ny x nx`), right in those rows only (columns first, then only those rows are
    /// transposed back and transformed; the 2D transform is separable).
    /// `scratch` (as long as `data`) is exchanged with `data`.
    pub fn process_transposed_to_rows(&self, data: &mut Vec<Complex64>, first_row: usize, scratch: &mut Vec<Complex64>) {
        assert_eq!(data.len(), self.nx * self.ny);
        assert_eq!(scratch.len(), data.len(), "scratch size");
        let first_row = first_row.min(self.ny);
        self.transform_contiguous_columns(data);
        transpose_from(data, scratch, self.nx, self.ny, first_row);
        self.transform_rows(&mut scratch[first_row * self.nx..]);
        std::mem::swap(data, scratch);
    }

    /// Column transforms of a transposed array (`nx` contiguous columns of `ny`).
    fn transform_contiguous_columns(&self, transposed: &mut [Complex64]) {
        transposed.par_chunks_mut(self.ny).for_each_init(
            || vec![Complex64::default(); self.cols.get_inplace_scratch_len()],
            |scratch, col| self.cols.process_with_scratch(col, scratch),
        );
    }

    fn transform_rows(&self, rows: &mut [Complex64]) {
        rows.par_chunks_mut(self.nx).for_each_init(
            || vec![Complex64::default(); self.rows.get_inplace_scratch_len()],
            |scratch, row| self.rows.process_with_scratch(row, scratch),
        );
    }

    fn transform_columns(&self, data: &mut [Complex64], transposed: &mut [Complex64]) {
        let (nx, ny) = (self.nx, self.ny);
        assert_eq!(transposed.len(), nx * ny, "scratch size");
        transpose(data, transposed, ny, nx);
        self.transform_contiguous_columns(transposed);
        transpose(transposed, data, nx, ny);
    }
}

/// `dst (cols x rows) = src (rows x cols)^T`, in cache-sized blocks, rows of `dst` in parallel.
pub fn transpose<T: Copy + Send + Sync>(src: &[T], dst: &mut [T], rows: usize, cols: usize) {
    transpose_from(src, dst, rows, cols, 0);
}

/// [`transpose`] of columns `first_col..` of `src` only (rows `first_col..` of `dst`; the
/// others are left as they were).
fn transpose_from<T: Copy + Send + Sync>(src: &[T], dst: &mut [T], rows: usize, cols: usize, first_col: usize) {
    const B: usize = 16;
    assert_eq!(src.len(), rows * cols);
    assert_eq!(dst.len(), rows * cols);
    dst[first_col * rows..].par_chunks_mut(rows * B).enumerate().for_each(|(block, chunk)| {
        // `chunk` holds rows c0 .. c0+B of dst, i.e. columns c0 .. c0+B of src.
        let c0 = first_col + block * B;
        let nc = chunk.len() / rows;
        for r0 in (0..rows).step_by(B) {
            for r in r0..(r0 + B).min(rows) {
                let src_row = &src[r * cols + c0..r * cols + c0 + nc];
                for (c, v) in src_row.iter().enumerate() {
                    chunk[c * rows + r] = *v;
                }
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_direct_2d_dft() {
        let (ny, nx) = (6, 10);
        let data: Vec<Complex64> =
            (0..nx * ny).map(|k| Complex64::new((k as f64 * 0.37).sin(), (k as f64 * 0.11).cos())).collect();
        let mut out = data.clone();
        Fft2::new(ny, nx, FftDirection::Forward).process(&mut out);
        for ky in 0..ny {
            for kx in 0..nx {
                let mut s = Complex64::default();
                for y in 0..ny {
                    for x in 0..nx {
                        let ph = -2.0 * std::f64::consts::PI * ((kx * x) as f64 / nx as f64 + (ky * y) as f64 / ny as f64);
                        s += data[y * nx + x] * Complex64::from_polar(1.0, ph);
                    }
                }
                assert!((s - out[ky * nx + kx]).norm() < 1e-12);
            }
        }
    }

    #[test]
    fn a_convolution_through_transposed_spectra_is_the_one_through_row_major_spectra() {
        let (ny, nx) = (12, 10);
        let image = |seed: f64| -> Vec<Complex64> {
            (0..nx * ny).map(|k| if k < 5 * nx { Complex64::new((k as f64 * seed).sin(), 0.0) } else { Complex64::default() }).collect()
        };
        let (forward, inverse) = (Fft2::new(ny, nx, FftDirection::Forward), Fft2::new(ny, nx, FftDirection::Inverse));
        let (mut x, mut kernel) = (image(0.37), image(0.91));
        let mut x_t = x.clone();
        let mut kernel_t = kernel.clone();
        forward.process(&mut x);
        forward.process(&mut kernel);
        let mut scratch = vec![Complex64::default(); nx * ny];
        forward.process_from_rows_transposed(&mut x_t, 5, &mut scratch);
        forward.process_from_rows_transposed(&mut kernel_t, ny, &mut scratch);
        for ky in 0..ny {
            for kx in 0..nx {
                assert!((x[ky * nx + kx] - x_t[kx * ny + ky]).norm() < 1e-12, "the transposed spectrum at ({ky}, {kx})");
            }
        }
        x.iter_mut().zip(&kernel).for_each(|(a, k)| *a *= k);
        x_t.iter_mut().zip(&kernel_t).for_each(|(a, k)| *a *= k);
        inverse.process(&mut x);
        inverse.process_transposed_to_rows(&mut x_t, 7, &mut scratch);
        for k in 7 * nx..nx * ny {
            assert!((x[k] - x_t[k]).norm() < 1e-10, "pixel {k}: {} against {}", x_t[k], x[k]);
        }
    }

    #[test]
    fn transpose_non_square() {
        let (rows, cols) = (37, 21);
        let src: Vec<Complex64> = (0..rows * cols).map(|k| Complex64::new(k as f64, 0.0)).collect();
        let mut dst = vec![Complex64::default(); rows * cols];
        transpose(&src, &mut dst, rows, cols);
        for r in 0..rows {
            for c in 0..cols {
                assert_eq!(dst[c * rows + r], src[r * cols + c]);
            }
        }
    }
}
