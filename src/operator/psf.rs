//! The PSF and the convolution form of the normal operator: the dirty image, PSF, `kappa` and
//! 2N PSF of samples gridded in chunks (no operator held, so memory does not grow with their
//! number), and `D` as a linear convolution with the 2N PSF ([`PsfConvolution`]), exact to the
//! NUFFT's accuracy for coplanar data.

use super::geometry::ImageGeometry;
use super::measurement::{check_points, Visibility};
use crate::fft2::Fft2;
use crate::nufft::{ChunkedAdjoint, NufftParams};
use crate::{Error, Result};
use num_complex::Complex64;
use rayon::prelude::*;
use rustfft::FftDirection;

/// Points per chunk of [`grid_in_chunks`]: a sixteenth of the points, so that the chunk's
/// sorting and values (about 70 bytes a point) stay small beside the caller's arrays, but no
/// fewer than 2^16, below which merging the tiles into the grid would cost more than spreading
/// the points, and no more than 2^20, beyond which larger chunks no longer save time.
/// Points per chunk when `n` points are gridded in chunks (also what the gridder bench times).
pub(crate) fn chunk_points(n: usize) -> usize {
    (n / 16).clamp(1 << 16, 1 << 20)
}

/// `Re{Phi_raw^H c_t}` on `geometry` for each `t < transforms`, `c_t[k] = value(t, k)`, gridded
/// in chunks of points (see [`crate::nufft::ChunkedAdjoint`]): no plan for all the points is
/// ever held, so beside the caller's arrays memory is the grids and one chunk.
#[allow(clippy::too_many_arguments)]
fn grid_in_chunks(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    transforms: usize,
    value: impl Fn(usize, usize) -> Complex64 + Sync,
    nufft: NufftParams,
    threads: usize,
    chunk: usize,
) -> Result<Vec<Vec<f64>>> {
    check_points(geometry, u, v, weight)?;
    let mut gridder = ChunkedAdjoint::new(geometry.size, geometry.size, transforms, nufft, threads)?;
    add_in_steps(&mut gridder, geometry, u, v, chunk, value)?;
    Ok(gridder.finish().into_iter().map(|image| image.into_iter().map(|c| c.re).collect()).collect())
}

/// Adds the samples at `(u, v)` (wavelengths) to `gridder`, `step` at a time (each step's
/// sorting is its memory), `value(t, k)` for transform `t` of sample `k`.
fn add_in_steps(
    gridder: &mut ChunkedAdjoint,
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    step: usize,
    value: impl Fn(usize, usize) -> Complex64 + Sync,
) -> Result<()> {
    for start in (0..u.len()).step_by(step) {
        let end = (start + step).min(u.len());
        let (x, y): (Vec<f64>, Vec<f64>) =
            u[start..end].iter().zip(&v[start..end]).map(|(&u, &v)| geometry.uv_to_phase(u, v)).unzip();
        gridder.add(&x, &y, |t, k| value(t, start + k))?;
    }
    Ok(())
}

/// The dirty image, PSF and `kappa` of [`MeasurementOperator`](super::MeasurementOperator)
/// (to the NUFFT's accuracy; the sums run in another order), for callers that need no
/// operator afterwards: the points are gridded in chunks, so memory beyond the caller's arrays
/// does not grow with their number.
#[cfg(test)]
pub fn dirty_and_psf(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    vis: &[impl Visibility],
    nufft: NufftParams,
    threads: usize,
) -> Result<DirtyAndPsf> {
    dirty_and_psf_in_chunks(geometry, u, v, weight, vis, nufft, threads, chunk_points(u.len()))
}

#[allow(clippy::too_many_arguments)]
#[cfg(test)]
fn dirty_and_psf_in_chunks(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    vis: &[impl Visibility],
    nufft: NufftParams,
    threads: usize,
    chunk: usize,
) -> Result<DirtyAndPsf> {
    if vis.len() != weight.len() {
        return Err(Error::parameter("visibilities", "visibility and weight arrays differ in length"));
    }
    let value = |t: usize, k: usize| if t == 0 { vis[k].to_c64() * weight[k] } else { Complex64::new(weight[k], 0.0) };
    let [mut dirty, mut psf]: [Vec<f64>; 2] = grid_in_chunks(geometry, u, v, weight, 2, value, nufft, threads, chunk)?
        .try_into()
        .expect("two transforms");
    let kappa = normalise_by_psf_peak(geometry.size, &mut dirty, &mut psf)?;
    Ok(DirtyAndPsf { dirty, psf, kappa })
}

/// Scales `dirty` and the `n x n` `psf` by `kappa = 1 / psf peak` (at `(n/2, n/2)`) and returns
/// it; an error where the peak is not positive (every weight zero).
pub fn normalise_by_psf_peak(n: usize, dirty: &mut [f64], psf: &mut [f64]) -> Result<f64> {
    let peak = psf.get((n / 2) * n + n / 2).copied().unwrap_or(0.0);
    if !(peak > 0.0) {
        return Err(Error::parameter("weight", "all visibilities have zero weight: nothing to image"));
    }
    let kappa = 1.0 / peak;
    dirty.iter_mut().chain(psf.iter_mut()).for_each(|p| *p *= kappa);
    Ok(kappa)
}

/// What [`dirty_and_psf`] gives.
#[cfg(test)]
pub struct DirtyAndPsf {
    /// `kappa Re{Phi_raw^H (omega y)}`.
    pub dirty: Vec<f64>,
    /// `kappa Re{Phi^H Phi delta}`, peak 1 at `(N/2, N/2)`.
    pub psf: Vec<f64>,
    pub kappa: f64,
}

/// The PSF over twice the field of view (`2N x 2N`, centre at `(N, N)`) for the same
/// visibilities, scaled by `kappa` of the N x N operator: the kernel of the Toeplitz form of D.
/// Gridded in chunks (see [`dirty_and_psf`]).
pub fn doubled_psf(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    kappa: f64,
    nufft: NufftParams,
    threads: usize,
) -> Result<Vec<f64>> {
    doubled_psf_of(geometry, u, v, weight, |_| Complex64::new(1.0, 0.0), kappa, nufft, threads)
}

/// [`doubled_psf`] of the samples' weights times `factor(k)` (complex: the real part of the
/// transform is kept, as for the PSF): the kernels of [`crate::operator::taylor`].
#[allow(clippy::too_many_arguments)]
pub fn doubled_psf_of(
    geometry: ImageGeometry,
    u: &[f64],
    v: &[f64],
    weight: &[f64],
    factor: impl Fn(usize) -> Complex64 + Sync,
    kappa: f64,
    nufft: NufftParams,
    threads: usize,
) -> Result<Vec<f64>> {
    let value = |_, k: usize| factor(k) * (weight[k] * kappa);
    let [psf]: [Vec<f64>; 1] = grid_in_chunks(geometry.doubled(), u, v, weight, 1, value, nufft, threads, chunk_points(u.len()))?
        .try_into()
        .expect("one transform");
    Ok(psf)
}

/// [`doubled_psf_of`] of samples given a chunk at a time, as a table is read (the kernels of
/// [`crate::operator::taylor`] where the samples are not held): memory is the grid and one chunk.
pub struct DoubledKernelGridder {
    geometry: ImageGeometry,
    adjoint: ChunkedAdjoint,
}

impl DoubledKernelGridder {
    pub fn new(geometry: ImageGeometry, nufft: NufftParams, threads: usize) -> Result<DoubledKernelGridder> {
        let doubled = geometry.doubled();
        Ok(DoubledKernelGridder { geometry, adjoint: ChunkedAdjoint::new(doubled.size, doubled.size, 1, nufft, threads)? })
    }

    /// Adds samples at `(u, v)` (wavelengths) with total weights `weight`, each times
    /// `factor(k)`. Baselines beyond the image's Nyquist limit are refused.
    pub fn add(&mut self, u: &[f64], v: &[f64], weight: &[f64], factor: impl Fn(usize) -> Complex64 + Sync) -> Result<()> {
        check_points(self.geometry, u, v, weight)?;
        // As ImageGridder::add: the caller's chunk whole, up to where larger ones save no time.
        add_in_steps(&mut self.adjoint, self.geometry, u, v, u.len().clamp(1, 1 << 20), |_, k| factor(k) * weight[k])
    }

    /// The kernel (`2N x 2N`, centre at `(N, N)`), scaled by `kappa`.
    pub fn finish(self, kappa: f64) -> Vec<f64> {
        self.adjoint.finish().into_iter().next().unwrap_or_default().into_iter().map(|c| c.re * kappa).collect()
    }
}

/// The dirty image, the PSF, the 2N PSF and `kappa` of samples given a chunk at a time, as a
/// table is read: one pass over the data makes every image the imaging needs, and memory is
/// the grids and one chunk, whatever the number of samples. The same sums as [`dirty_and_psf`]
/// and [`doubled_psf`] (to the order of floating-point additions).
pub struct ImageGridder {
    geometry: ImageGeometry,
    /// `None`: the 2N PSF only (the dirty image is made elsewhere: with the w-term).
    dirty: Option<ChunkedAdjoint>,
    psf_2n: ChunkedAdjoint,
    samples: usize,
}

impl ImageGridder {
    pub fn new(geometry: ImageGeometry, nufft: NufftParams, threads: usize) -> Result<ImageGridder> {
        let n = geometry.size;
        Ok(ImageGridder {
            geometry,
            dirty: Some(ChunkedAdjoint::new(n, n, 2, nufft, threads)?),
            psf_2n: ChunkedAdjoint::new(2 * n, 2 * n, 1, nufft, threads)?,
            samples: 0,
        })
    }

    /// A gridder of the (coplanar) 2N PSF alone.
    pub fn doubled_psf_only(geometry: ImageGeometry, nufft: NufftParams, threads: usize) -> Result<ImageGridder> {
        let n = geometry.size;
        Ok(ImageGridder { geometry, dirty: None, psf_2n: ChunkedAdjoint::new(2 * n, 2 * n, 1, nufft, threads)?, samples: 0 })
    }

    /// Adds samples at `(u, v)` (wavelengths) with total weights `weight` and values `vis`.
    /// Baselines beyond the image's Nyquist limit are refused (see
    /// [`MeasurementOperator::new`](super::MeasurementOperator::new)).
    pub fn add(&mut self, u: &[f64], v: &[f64], weight: &[f64], vis: &[impl Visibility]) -> Result<()> {
        check_points(self.geometry, u, v, weight)?;
        if vis.len() != weight.len() {
            return Err(Error::parameter("visibilities", "visibility and weight arrays differ in length"));
        }
        // The caller's chunk is gridded whole (its size sets the sorting's memory), up to the
        // size beyond which larger chunks no longer save time.
        let step = u.len().clamp(1, 1 << 20);
        for start in (0..u.len()).step_by(step) {
            let end = (start + step).min(u.len());
            let (x, y): (Vec<f64>, Vec<f64>) =
                u[start..end].iter().zip(&v[start..end]).map(|(&u, &v)| self.geometry.uv_to_phase(u, v)).unzip();
            if let Some(dirty) = &mut self.dirty {
                let value = |t: usize, k: usize| if t == 0 { vis[start + k].to_c64() * weight[start + k] } else { Complex64::new(weight[start + k], 0.0) };
                dirty.add(&x, &y, value)?;
            }
            self.psf_2n.add(&x, &y, |_, k| Complex64::new(weight[start + k], 0.0))?;
        }
        self.samples += u.len();
        Ok(())
    }

    /// The dirty image, PSF and 2N PSF as gridded, not normalised (empty dirty image and PSF
    /// for a gridder of the 2N PSF alone): one part of images summed over parts.
    pub fn unnormalised(self) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let real = |image: Vec<Complex64>| -> Vec<f64> { image.into_iter().map(|c| c.re).collect() };
        let (dirty, psf) = match self.dirty {
            Some(d) => {
                let mut images = d.finish().into_iter().map(real);
                (images.next().unwrap_or_default(), images.next().unwrap_or_default())
            }
            None => (Vec::new(), Vec::new()),
        };
        let psf_2n = real(self.psf_2n.finish().into_iter().next().unwrap_or_default());
        (dirty, psf, psf_2n)
    }
}

/// `D x = kappa Re{Phi^H Phi x}` as a linear convolution with the 2N x 2N PSF, by FFT:
/// `crop(IFFT(FFT(pad(x)) FFT(psf_2N)))`. Exact (to NUFFT accuracy) for coplanar data, and
/// once built its cost no longer depends on the number of visibilities.
pub struct PsfConvolution {
    size: usize,
    /// FFT of the 2N x 2N PSF, divided by (2N)^2 for the unnormalised inverse FFT, transposed
    /// as the image's spectrum is (`Fft2::process_from_rows_transposed`).
    kernel_hat: Vec<Complex64>,
    forward: Fft2,
    inverse: Fft2,
    /// The padded image and the transposes' scratch, kept from one application to the next
    /// (made afresh, their pages were mapped and zeroed at every update).
    buffers: std::sync::Mutex<(Vec<Complex64>, Vec<Complex64>)>,
}

impl PsfConvolution {
    /// `psf_2n`: the doubled PSF (`2N x 2N`, centre at `(N, N)`).
    pub fn new(size: usize, psf_2n: &[f64]) -> Result<PsfConvolution> {
        let m = 2 * size;
        if psf_2n.len() != m * m {
            return Err(Error::parameter("psf", format!("expected a {m} x {m} PSF for a {size} x {size} image, got {} pixels", psf_2n.len())));
        }
        let forward = Fft2::new(m, m, FftDirection::Forward);
        let inverse = Fft2::new(m, m, FftDirection::Inverse);
        let scale = 1.0 / (m * m) as f64;
        let mut kernel_hat: Vec<Complex64> = psf_2n.iter().map(|&p| Complex64::new(p * scale, 0.0)).collect();
        forward.process_from_rows_transposed(&mut kernel_hat, m, &mut vec![Complex64::default(); m * m]);
        Ok(PsfConvolution { size, kernel_hat, forward, inverse, buffers: Default::default() })
    }

    pub fn size(&self) -> usize {
        self.size
    }

    /// `D x` for an N x N image.
    pub fn apply(&self, x: &[f64]) -> Vec<f64> {
        let (n, m) = (self.size, 2 * self.size);
        assert_eq!(x.len(), n * n, "image size");
        // A poisoned lock only means an earlier application panicked: its arrays are rewritten here.
        let mut buffers = self.buffers.lock().unwrap_or_else(|e| e.into_inner());
        let (padded, scratch) = &mut *buffers;
        padded.resize(m * m, Complex64::default());
        scratch.resize(m * m, Complex64::default());
        padded.par_chunks_mut(m).enumerate().for_each(|(iy, row)| {
            if iy < n {
                row[..n].iter_mut().zip(&x[iy * n..][..n]).for_each(|(p, &v)| *p = Complex64::new(v, 0.0));
                row[n..].fill(Complex64::default());
            } else {
                row.fill(Complex64::default());
            }
        });
        // The image fills the first N rows; the result is read from the last N.
        self.forward.process_from_rows_transposed(padded, n, scratch);
        padded.par_iter_mut().zip(self.kernel_hat.par_iter()).for_each(|(a, k)| *a *= k);
        self.inverse.process_transposed_to_rows(padded, n, scratch);
        // Linear convolution with a kernel centred at (N, N): output pixel p sits at p + N.
        let mut out = vec![0.0; n * n];
        out.par_chunks_mut(n).enumerate().for_each(|(iy, row)| {
            row.iter_mut().zip(&padded[(iy + n) * m + n..][..n]).for_each(|(o, p)| *o = p.re);
        });
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::operator::measurement::tests::{dot, random_image, setup};

    #[test]
    fn dirty_and_psf_in_chunks_match_the_operator() {
        let (g, u, v, w, op) = setup(1e-9);
        let vis: Vec<Complex64> = u.iter().zip(&v).map(|(&u, &v)| Complex64::new((u * 1e-3).cos(), (v * 2e-3).sin())).collect();
        let nufft = NufftParams { epsilon: 1e-9, oversampling: 2.0 };
        let (dirty, psf) = (op.dirty_image(&vis), op.psf());
        // One chunk, several of uneven size (the last one short), and one point per chunk.
        for chunk in [u.len(), 999, 1] {
            let chunked = dirty_and_psf_in_chunks(g, &u, &v, &w, &vis, nufft, 2, chunk).unwrap();
            let max_diff = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(max_diff(&chunked.dirty, &dirty) < 1e-12, "chunk {chunk}: dirty differs by {}", max_diff(&chunked.dirty, &dirty));
            assert!(max_diff(&chunked.psf, &psf) < 1e-12, "chunk {chunk}: psf differs by {}", max_diff(&chunked.psf, &psf));
            assert!((chunked.kappa / op.kappa() - 1.0).abs() < 1e-13);
        }
        let err = dirty_and_psf(g, &u, &v, &vec![0.0; w.len()], &vis, nufft, 2).err().unwrap().to_string();
        assert!(err.contains("zero weight"), "{err}");
        let err = dirty_and_psf(g, &u, &v, &w, &vis[1..], nufft, 2).err().unwrap().to_string();
        assert!(err.contains("differ in length"), "{err}");
    }

    #[test]
    fn toeplitz_and_nufft_normal_operators_agree_and_are_symmetric() {
        let (g, u, v, w, op) = setup(1e-9);
        let psf2 = doubled_psf(g, &u, &v, &w, op.kappa(), NufftParams { epsilon: 1e-9, oversampling: 2.0 }, 2).unwrap();
        let conv = PsfConvolution::new(g.size, &psf2).unwrap();
        let x = random_image(g.pixels(), 5);
        let y = random_image(g.pixels(), 6);
        let d_nufft = op.apply_normal(&x);
        let d_toeplitz = conv.apply(&x);
        let diff = d_nufft.iter().zip(&d_toeplitz).map(|(a, b)| (a - b) * (a - b)).sum::<f64>().sqrt();
        let norm = d_nufft.iter().map(|a| a * a).sum::<f64>().sqrt();
        assert!(diff / norm <= 1e-6, "relative difference {}", diff / norm);
        let by_nufft = |x: &[f64]| op.apply_normal(x);
        let by_fft = |x: &[f64]| conv.apply(x);
        let forms: [&dyn Fn(&[f64]) -> Vec<f64>; 2] = [&by_nufft, &by_fft];
        for apply in forms {
            let lhs = dot(&apply(&x), &y);
            let rhs = dot(&x, &apply(&y));
            assert!((lhs - rhs).abs() <= 1e-9 * lhs.abs(), "<Dx,y> {lhs} vs <x,Dy> {rhs}");
        }
        // D applied to a centred delta is the PSF.
        let n = g.size;
        let mut delta = vec![0.0; n * n];
        delta[(n / 2) * n + n / 2] = 1.0;
        let psf = op.psf();
        let d_delta = conv.apply(&delta);
        assert!(psf.iter().zip(&d_delta).all(|(a, b)| (a - b).abs() < 1e-7));
    }
}
