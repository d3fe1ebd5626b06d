//! The NUFFT plans: [`Nufft2d`] (a plan over fixed points, both directions) and
//! [`ChunkedAdjoint`] (gridding points given a chunk at a time).


use crate::{Error, Result};
use super::kernel::{KernelShape, PolynomialKernel, SymKernel};
use super::permute::Permutation;
use super::simd::{madd, multiversion, SimdLevel};
use num_complex::Complex64;
use rayon::prelude::*;
use rustfft::{Fft, FftDirection, FftPlanner};
use std::sync::Arc;


/// Accuracy and oversampling of a NUFFT plan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NufftParams {
    /// Requested relative accuracy (1e-2 .. 1e-12 supported; 1e-14 at oversampling 2).
    pub epsilon: f64,
    /// Grid size over image size (1.25 .. 4; 2 by default).
    pub oversampling: f64,
}

/// The accuracy imaging asks for unless told otherwise: well below the thermal noise of any
/// real image, at a kernel cost the gridder's speed is measured at.
pub const DEFAULT_EPSILON: f64 = 1e-6;

/// The grid over the image, per axis, unless told otherwise (the usual NUFFT choice).
pub const DEFAULT_OVERSAMPLING: f64 = 2.0;

impl Default for NufftParams {
    fn default() -> Self {
        NufftParams { epsilon: DEFAULT_EPSILON, oversampling: DEFAULT_OVERSAMPLING }
    }
}

/// Grid tile edge in cells: tiles of 32 x 32 complex (16 KiB) plus the kernel margin stay in L1/L2.
const TILE: usize = 32;

/// Largest accepted point coordinate magnitude (radians per pixel).
const MAX_COORDINATE: f64 = 1e12;

/// Where one point falls on the padded grid, and its sub-cell kernel variables, packed in
/// 16 bytes (24 as plain fields): per axis, the first covered cell in padded coordinates
/// (grid index + support, below 2^16) in the top 16 bits and the sub-cell fraction
/// `frac in [0, 1)` of the kernel variable `z = 2 frac - 1` (see [`PolynomialKernel`]) as a
/// 48-bit fixed-point number. The fraction's rounding, below `2^-49`, moves kernel values by
/// less than `1e-15`; the smaller array makes plans faster to build and gridding read less.
#[derive(Clone, Copy, Debug, Default)]
struct GridPosition {
    x: u64,
    y: u64,
}

/// Fraction bits of a [`GridPosition`] axis.
const FRAC_BITS: u32 = 48;
const FRAC_MASK: u64 = (1 << FRAC_BITS) - 1;

impl GridPosition {
    #[inline(always)]
    fn px(&self) -> usize {
        (self.x >> FRAC_BITS) as usize
    }
    #[inline(always)]
    fn py(&self) -> usize {
        (self.y >> FRAC_BITS) as usize
    }
    #[inline(always)]
    fn zx(&self) -> f64 {
        Self::z(self.x)
    }
    #[inline(always)]
    fn zy(&self) -> f64 {
        Self::z(self.y)
    }
    #[inline(always)]
    fn z(axis: u64) -> f64 {
        // Through i64: the value fits, and the signed conversion is one instruction.
        ((axis & FRAC_MASK) as i64 as f64) * (2.0 / (1u64 << FRAC_BITS) as f64) - 1.0
    }
}

/// Largest padded grid edge a [`GridPosition`] can address.
const MAX_PADDED_GRID: usize = 1 << 16;

/// A contiguous run of sorted points covering whole tiles, processed by one task.
#[derive(Clone, Debug)]
struct Task {
    /// Range in the sorted point order.
    points: std::ops::Range<usize>,
    /// The tiles in it, as (tile x, tile y, point range).
    tiles: Vec<(usize, usize, std::ops::Range<usize>)>,
}

/// A plan: image size, kernel, and the points sorted for cache-friendly (de)gridding.
pub struct Nufft2d {
    nx: usize,
    ny: usize,
    grid_nx: usize,
    grid_ny: usize,
    shape: KernelShape,
    /// Polynomial kernel, `(degree + 1) * support` coefficients, highest degree first.
    kernel_coeffs: Vec<f64>,
    /// `1 / psi_hat` per image column and row.
    correction_x: Vec<f64>,
    correction_y: Vec<f64>,
    /// Points in tile order, with `order[k]` = caller's index of sorted point k.
    positions: Vec<GridPosition>,
    order: Vec<u32>,
    tasks: Vec<Task>,
    /// `order` organised for cache-friendly moves to and from the caller's order.
    perm: Permutation,
    /// Grid rows (0 .. grid_ny) touched by any point's kernel: other rows stay zero.
    row_used: Vec<bool>,
    fft_x: Arc<dyn Fft<f64>>,
    fft_y: Arc<dyn Fft<f64>>,
    ifft_x: Arc<dyn Fft<f64>>,
    ifft_y: Arc<dyn Fft<f64>>,
    /// The shared pool of the plan's size (`crate::parallel`).
    pool: std::sync::Arc<rayon::ThreadPool>,
    /// Instruction set of the gridding inner loops.
    simd: SimdLevel,
}

/// Smallest even number >= `n` whose only prime factors are 2, 3, 5 and 7 (fast FFT sizes).
pub fn good_fft_size(n: usize) -> usize {
    let mut m = n.max(2);
    loop {
        if m % 2 == 0 {
            let mut r = m;
            for p in [2, 3, 5, 7] {
                while r % p == 0 {
                    r /= p;
                }
            }
            if r == 1 {
                return m;
            }
        }
        m += 1;
    }
}

impl Nufft2d {
    /// Plan transforms between an `nx x ny` image and the points `(x[k], y[k])` (radians per
    /// pixel), run on `threads` threads (0: all cores).
    pub fn new(nx: usize, ny: usize, x: &[f64], y: &[f64], params: NufftParams, threads: usize) -> Result<Nufft2d> {
        if x.len() != y.len() {
            return Err(Error::parameter("points", "x and y coordinate arrays differ in length"));
        }
        if x.len() > u32::MAX as usize {
            return Err(Error::parameter("points", "more than 2^32 points in one plan"));
        }
        if nx < 2 || ny < 2 || nx % 2 != 0 || ny % 2 != 0 {
            return Err(Error::parameter("image size", format!("expected even sizes >= 2, got {nx} x {ny}")));
        }
        let shape = KernelShape::for_accuracy(params.epsilon, params.oversampling)?;
        Self::with_kernel(nx, ny, x, y, shape, params, threads)
    }

    /// Like [`Nufft2d::new`] with an explicit kernel shape (for kernel tuning and tests).
    pub fn with_kernel(
        nx: usize,
        ny: usize,
        x: &[f64],
        y: &[f64],
        shape: KernelShape,
        params: NufftParams,
        threads: usize,
    ) -> Result<Nufft2d> {
        if x.len() != y.len() {
            return Err(Error::parameter("points", "x and y coordinate arrays differ in length"));
        }
        let w = shape.support;
        let grid_nx = good_fft_size(((nx as f64) * params.oversampling).ceil() as usize).max(2 * w);
        let grid_ny = good_fft_size(((ny as f64) * params.oversampling).ceil() as usize).max(2 * w);
        Self::with_grid((nx, ny), (grid_nx, grid_ny), (x, y), shape, params, threads)
    }

    /// Like [`Nufft2d::with_kernel`] on a grid of `grid_nx x grid_ny` cells given by the
    /// caller (a window of a larger grid: [`ChunkedAdjoint::windowed`]).
    fn with_grid((nx, ny): (usize, usize), (grid_nx, grid_ny): (usize, usize), (x, y): (&[f64], &[f64]), shape: KernelShape, params: NufftParams, threads: usize) -> Result<Nufft2d> {
        let w = shape.support;
        if grid_nx.max(grid_ny) + 2 * w > MAX_PADDED_GRID {
            return Err(Error::parameter(
                "image size",
                format!("{nx} x {ny} needs a {grid_nx} x {grid_ny} grid; at most {} cells a side are supported", MAX_PADDED_GRID - 2 * w),
            ));
        }
        // The polynomial's error stays well below the NUFFT's.
        let kernel_coeffs = fit_kernel(&shape, params.epsilon / 20.0);
        let psi_x = shape.fourier_coefficients(grid_nx, nx / 2);
        let psi_y = shape.fourier_coefficients(grid_ny, ny / 2);
        let correction_x = (0..nx).map(|i| 1.0 / psi_x[(i as isize - nx as isize / 2).unsigned_abs()]).collect();
        let correction_y = (0..ny).map(|i| 1.0 / psi_y[(i as isize - ny as isize / 2).unsigned_abs()]).collect();

        let pool = crate::parallel::shared_pool(threads)?;

        let mut planner = FftPlanner::new();
        let mut plan = Nufft2d {
            nx,
            ny,
            grid_nx,
            grid_ny,
            fft_x: planner.plan_fft(grid_nx, FftDirection::Forward),
            fft_y: planner.plan_fft(grid_ny, FftDirection::Forward),
            ifft_x: planner.plan_fft(grid_nx, FftDirection::Inverse),
            ifft_y: planner.plan_fft(grid_ny, FftDirection::Inverse),
            shape,
            kernel_coeffs,
            correction_x,
            correction_y,
            positions: Vec::new(),
            order: Vec::new(),
            tasks: Vec::new(),
            perm: Permutation::default(),
            row_used: Vec::new(),
            pool,
            simd: SimdLevel::detect(),
        };
        plan.sort_points(x, y, true)?;
        Ok(plan)
    }

    pub fn grid_size(&self) -> (usize, usize) {
        (self.grid_nx, self.grid_ny)
    }
    pub fn kernel_shape(&self) -> &KernelShape {
        &self.shape
    }
    pub fn len(&self) -> usize {
        self.order.len()
    }
    /// `order()[k]` is the caller's index of the k-th point in the plan's internal order.
    pub fn order(&self) -> &[u32] {
        &self.order
    }
    /// Run the inner loops with another instruction set (for comparisons); an error if this
    /// CPU does not support it.
    #[cfg(test)]
    pub fn set_simd_level(&mut self, level: SimdLevel) -> Result<()> {
        if !level.is_supported() {
            return Err(Error::parameter("simd level", format!("{level:?} is not supported by this CPU")));
        }
        self.simd = level;
        Ok(())
    }
    /// Run `f` on this plan's thread pool.
    pub fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.pool.install(f)
    }

    /// Compute each point's padded grid position and sort the points by tile (counting sort).
    ///
    /// Pass 1 (parallel) computes each point's tile; a histogram and prefix sum give every
    /// tile's output range; pass 2 runs one task per group of consecutive tiles (so each task
    /// owns a contiguous part of the output): it scans the tile numbers, recomputes the
    /// positions of its own points and writes them in order.
    ///
    /// `permutation`: also organise the order for moves to and from the caller's order
    /// ([`Permutation`]), which only the unsorted transforms need.
    fn sort_points(&mut self, x: &[f64], y: &[f64], permutation: bool) -> Result<()> {
        let w = self.shape.support;
        let (gx, gy) = (self.grid_nx, self.grid_ny);
        let padded_x = gx + 2 * w;
        let padded_y = gy + 2 * w;
        let tiles_x = padded_x.div_ceil(TILE);
        let tiles_y = padded_y.div_ceil(TILE);
        let ntiles = tiles_x * tiles_y;
        let (sx, sy) = (gx as f64 / (2.0 * std::f64::consts::PI), gy as f64 / (2.0 * std::f64::consts::PI));
        let (inv_gx, inv_gy) = (1.0 / gx as f64, 1.0 / gy as f64);
        let position = |xk: f64, yk: f64| -> GridPosition {
            GridPosition { x: grid_position(xk * sx, gx, inv_gx, w), y: grid_position(yk * sy, gy, inv_gy, w) }
        };
        let tile_of = |p: &GridPosition| ((p.py() / TILE) * tiles_x + p.px() / TILE) as u32;
        let threads = self.pool.current_num_threads().max(1);
        let npoints = x.len();
        let chunk = npoints.div_ceil(4 * threads).max(1 << 14);
        let (tile, counts) = self.pool.install(|| {
            let mut tile = vec![0u32; npoints];
            let counts = tile
                .par_chunks_mut(chunk)
                .zip(x.par_chunks(chunk).zip(y.par_chunks(chunk)))
                .map(|(t, (x, y))| {
                    let mut counts = vec![0usize; ntiles];
                    for ((t, &xk), &yk) in t.iter_mut().zip(x).zip(y) {
                        // Also rejects NaN; keeps the integer conversions below in range.
                        if !(xk.abs() <= MAX_COORDINATE && yk.abs() <= MAX_COORDINATE) {
                            return None;
                        }
                        *t = tile_of(&position(xk, yk));
                        counts[*t as usize] += 1;
                    }
                    Some(counts)
                })
                .try_reduce(
                    || vec![0usize; ntiles],
                    |mut a, b| {
                        a.iter_mut().zip(&b).for_each(|(a, b)| *a += b);
                        Some(a)
                    },
                );
            (tile, counts)
        });
        let counts = counts.ok_or_else(|| Error::parameter(
                "points",
                format!("expected finite point coordinates of magnitude <= {MAX_COORDINATE:e} radians per pixel"),
            ))?;
        let mut starts = vec![0usize; ntiles + 1];
        for t in 0..ntiles {
            starts[t + 1] = starts[t] + counts[t];
        }
        // Groups of consecutive tiles with about equal point counts, one output part each.
        let groups = if npoints < 1 << 16 { 1 } else { threads };
        let mut bounds = vec![0usize];
        for g in 1..groups {
            let target = npoints * g / groups;
            let t = starts.partition_point(|&s| s < target).min(ntiles);
            bounds.push(t.max(*bounds.last().expect("not empty")));
        }
        bounds.push(ntiles);
        let mut order = vec![0u32; npoints];
        let mut positions = par_filled(GridPosition::default(), npoints);
        let mut parts = Vec::with_capacity(groups);
        {
            let (mut rest_o, mut rest_p) = (order.as_mut_slice(), positions.as_mut_slice());
            for g in 0..groups {
                let (t0, t1) = (bounds[g], bounds[g + 1]);
                let len = starts[t1] - starts[t0];
                let (o, ro) = std::mem::take(&mut rest_o).split_at_mut(len);
                let (p, rp) = std::mem::take(&mut rest_p).split_at_mut(len);
                rest_o = ro;
                rest_p = rp;
                parts.push((t0..t1, o, p));
            }
        }
        self.pool.install(|| {
            parts.into_par_iter().for_each(|(tiles, order, positions)| {
                let base = starts[tiles.start];
                let mut cursor: Vec<usize> = starts[tiles.start..tiles.end].iter().map(|s| s - base).collect();
                let (t0, t1) = (tiles.start as u32, tiles.end as u32);
                for (k, &t) in tile.iter().enumerate() {
                    if t >= t0 && t < t1 {
                        let c = &mut cursor[(t - t0) as usize];
                        order[*c] = k as u32;
                        positions[*c] = position(x[k], y[k]);
                        *c += 1;
                    }
                }
            })
        });
        // Rows touched by some kernel footprint, in grid coordinates.
        let mut row_used = vec![false; gy];
        let mut tile_row_used = vec![false; tiles_y];
        for ty in 0..tiles_y {
            tile_row_used[ty] = starts[ty * tiles_x] != starts[(ty + 1) * tiles_x];
        }
        for (ty, used) in tile_row_used.iter().enumerate() {
            if *used {
                for q in ty * TILE..((ty + 1) * TILE + w).min(padded_y) {
                    row_used[(q + gy - w) % gy] = true;
                }
            }
        }
        // Split into tasks of whole tiles, about 8 per thread for load balance.
        let target = (npoints / (8 * threads)).max(4096);
        let mut tasks = Vec::new();
        let mut current = Task { points: 0..0, tiles: Vec::new() };
        for ty in 0..tiles_y {
            for tx in 0..tiles_x {
                let t = ty * tiles_x + tx;
                let range = starts[t]..starts[t + 1];
                if range.is_empty() {
                    continue;
                }
                current.points.end = range.end;
                current.tiles.push((tx, ty, range));
                if current.points.len() >= target {
                    let end = current.points.end;
                    tasks.push(std::mem::replace(&mut current, Task { points: end..end, tiles: Vec::new() }));
                }
            }
        }
        if !current.tiles.is_empty() {
            tasks.push(current);
        }
        drop(tile);
        self.perm = if permutation {
            let ranges: Vec<_> = tasks.iter().map(|t| t.points.clone()).collect();
            self.pool.install(|| Permutation::new(&order, &ranges))
        } else {
            Permutation::default()
        };
        self.positions = positions;
        self.order = order;
        self.tasks = tasks;
        self.row_used = row_used;
        Ok(())
    }

    /// Type 2 (image to points): `out[k] = sum_j image[j] exp(+i (x_k jx + y_k jy))`, with
    /// points in the caller's order.
    pub fn forward(&self, image: &[Complex64], out: &mut [Complex64]) {
        assert_eq!(image.len(), self.nx * self.ny, "image size");
        assert_eq!(out.len(), self.len(), "number of points");
        self.pool.install(|| {
            let padded = self.image_to_padded_grid(image);
            let mut slots = par_filled(Complex64::default(), self.len());
            let sinks = self.perm.task_segments_mut(&mut slots).into_iter().map(Sink::parts).collect();
            dispatch_support!(self.shape.support, W, W2, L => self.degrid::<W, W2, L>(&padded, sinks));
            self.perm.scatter(&slots, out);
        });
    }

    /// Type 1 (points to image): `out[j] = sum_k c[k] exp(-i (x_k jx + y_k jy))`, with points
    /// in the caller's order.
    pub fn adjoint(&self, c: &[Complex64], out: &mut [Complex64]) {
        assert_eq!(c.len(), self.len(), "number of points");
        assert_eq!(out.len(), self.nx * self.ny, "image size");
        self.pool.install(|| {
            let slots = self.perm.gather(c);
            let sources = self.perm.task_segments(&slots).into_iter().map(Source::parts).collect();
            let mut grid = par_filled(Complex64::default(), self.grid_nx * self.grid_ny);
            dispatch_support!(self.shape.support, W, W2, L => self.grid::<W, W2, L>(sources, &mut grid));
            self.grid_to_image(grid, &self.row_used, out);
        });
    }

    /// [`Nufft2d::forward`] with points in the plan's order ([`Nufft2d::order`]).
    pub fn forward_sorted(&self, image: &[Complex64], out: &mut [Complex64]) {
        assert_eq!(image.len(), self.nx * self.ny, "image size");
        assert_eq!(out.len(), self.len(), "number of points");
        self.pool.install(|| {
            let padded = self.image_to_padded_grid(image);
            // One sink per task, for the task's range of points.
            let mut sinks = Vec::with_capacity(self.tasks.len());
            let mut rest = out;
            for task in &self.tasks {
                let (head, tail) = std::mem::take(&mut rest).split_at_mut(task.points.len());
                sinks.push(Sink::Sorted(head));
                rest = tail;
            }
            dispatch_support!(self.shape.support, W, W2, L => self.degrid::<W, W2, L>(&padded, sinks));
        });
    }

    /// [`Nufft2d::adjoint`] with points in the plan's order ([`Nufft2d::order`]).
    pub fn adjoint_sorted(&self, c: &[Complex64], out: &mut [Complex64]) {
        assert_eq!(c.len(), self.len(), "number of points");
        assert_eq!(out.len(), self.nx * self.ny, "image size");
        self.pool.install(|| {
            let sources = self.tasks.iter().map(|task| Source::Sorted(&c[task.points.clone()])).collect();
            let mut grid = par_filled(Complex64::default(), self.grid_nx * self.grid_ny);
            dispatch_support!(self.shape.support, W, W2, L => self.grid::<W, W2, L>(sources, &mut grid));
            self.grid_to_image(grid, &self.row_used, out);
        });
    }

    /// The adjoint's grid-to-image step (FFT and correction) alone, on a zero grid (benchmarks).
    pub(crate) fn time_grid_to_image(&self) {
        let mut out = vec![Complex64::default(); self.nx * self.ny];
        self.pool.install(|| self.grid_to_image(vec![Complex64::default(); self.grid_nx * self.grid_ny], &self.row_used, &mut out));
    }

    /// The forward transform's image-to-grid step (correction and FFT) alone (benchmarks).
    pub(crate) fn time_image_to_grid(&self) {
        let image = vec![Complex64::default(); self.nx * self.ny];
        self.pool.install(|| drop(self.image_to_padded_grid(&image)));
    }

    fn kernel<const W: usize, const W2: usize, const L: usize>(&self) -> SymKernel<W, W2, L> {
        SymKernel::new(&PolynomialKernel::<W> {
            coeffs: self.kernel_coeffs.chunks_exact(W).map(|c| c.try_into().expect("chunk of W")).collect(),
        })
    }

    /// Spread all points onto the (unpadded) oversampled grid.
    ///
    /// Each tile is accumulated in a private buffer of `(TILE + W)^2` cells stored as
    /// interleaved `f64` pairs, so that one kernel row of a point is a contiguous run of
    /// `2 W` reals updated by a single multiply-add loop (`re, im, re, im, ...` times the x
    /// kernel duplicated), which vectorises without shuffles.
    ///
    /// `sources[j]` gives the values of task `j`'s points.
    fn grid<const W: usize, const W2: usize, const L: usize>(&self, sources: Vec<Source>, grid: &mut [Complex64]) {
        let (gx, gy) = (self.grid_nx, self.grid_ny);
        let kernel = self.kernel::<W, W2, L>();
        let bw = TILE + W;
        let bw2 = 2 * bw;
        // Tasks spread their tiles in parallel, a batch of tasks at a time (a task reads its
        // values with per-part cursors, so its tiles go in order), and the tile buffers are
        // added to the grid in task and tile order: the floating-point sums, hence the
        // images, do not depend on thread scheduling (simulations are bit-for-bit
        // reproducible from their seed).
        assert_eq!(grid.len(), gx * gy, "grid size");
        let batch = 4 * self.pool.current_num_threads().max(1);
        let mut sources: Vec<Option<Source>> = sources.into_iter().map(Some).collect();
        let mut spare: Vec<Vec<f64>> = Vec::new();
        for (chunk, chunk_sources) in self.tasks.chunks(batch).zip(sources.chunks_mut(batch)) {
            let pool = std::sync::Mutex::new(std::mem::take(&mut spare));
            let take_buffer = || {
                let reused = pool.lock().expect("no task panics while holding the pool").pop();
                reused.map_or_else(|| vec![0.0f64; bw * bw2], |mut b| {
                    b.iter_mut().for_each(|v| *v = 0.0);
                    b
                })
            };
            let spread: Vec<Vec<Vec<f64>>> = chunk
                .par_iter()
                .zip(chunk_sources.par_iter_mut())
                .map(|(task, source)| {
                    let mut source = source.take().expect("each source is used once");
                    task.tiles
                        .iter()
                        .map(|(tx, ty, range)| {
                            let mut buf = take_buffer();
                            let origin = ((tx * TILE) as u32, (ty * TILE) as u32);
                            let positions = &self.positions[range.clone()];
                            let local = range.start - task.points.start..range.end - task.points.start;
                            let order = &self.order[range.clone()];
                            spread_tile::<W, W2, L>(self.simd, &kernel, positions, &mut source, local, order, self.perm.shift, &mut buf, bw2, origin);
                            buf
                        })
                        .collect()
                })
                .collect();
            spare = pool.into_inner().expect("no task panics while holding the pool");
            for (task, buffers) in chunk.iter().zip(spread) {
                for ((tx, ty, _), buf) in task.tiles.iter().zip(buffers) {
                    // Add the tile to the grid, wrapping padded coordinates periodically.
                    for r in 0..bw {
                        let gyi = ((ty * TILE + r) + gy - W) % gy;
                        let src = &buf[r * bw2..(r + 1) * bw2];
                        let dst = &mut grid[gyi * gx..(gyi + 1) * gx];
                        let start = (tx * TILE + gx - W) % gx;
                        if start + bw <= gx {
                            for (d, s) in dst[start..start + bw].iter_mut().zip(src.chunks_exact(2)) {
                                *d += Complex64::new(s[0], s[1]);
                            }
                        } else {
                            for (i, s) in src.chunks_exact(2).enumerate() {
                                dst[(start + i) % gx] += Complex64::new(s[0], s[1]);
                            }
                        }
                    }
                    spare.push(buf);
                }
            }
        }
    }

    /// Interpolate the padded grid (interleaved `re, im` reals) at every point (sorted order):
    /// sum the `W` kernel rows weighted by the y kernel into `2 W` reals, then contract with
    /// the x kernel.
    ///
    /// `sinks[j]` receives the values of task `j`'s points.
    fn degrid<const W: usize, const W2: usize, const L: usize>(&self, padded: &[f64], sinks: Vec<Sink>) {
        let pw2 = 2 * (self.grid_nx + 2 * W);
        let kernel = self.kernel::<W, W2, L>();
        self.tasks.par_iter().zip(sinks).for_each(|(task, mut sink)| {
            let (positions, order) = (&self.positions[task.points.clone()], &self.order[task.points.clone()]);
            interp_points::<W, W2, L>(self.simd, &kernel, positions, padded, pw2, &mut sink, order, self.perm.shift);
        });
    }

    /// Grid -> image: FFT rows (only those `row_used`, the others are zero), FFT the columns
    /// holding image modes, crop the modes and apply the kernel correction.
    fn grid_to_image(&self, mut grid: Vec<Complex64>, row_used: &[bool], out: &mut [Complex64]) {
        let (gx, gy, nx, ny) = (self.grid_nx, self.grid_ny, self.nx, self.ny);
        grid.par_chunks_mut(gx).zip(row_used.par_iter()).for_each_init(
            || vec![Complex64::default(); self.fft_x.get_inplace_scratch_len()],
            |scratch, (row, &used)| {
                if used {
                    self.fft_x.process_with_scratch(row, scratch)
                }
            },
        );
        // Columns holding modes jx in [-nx/2, nx/2), gathered in blocks of 8, FFT'd along y,
        // kept in column-major order `cols[ix * ny + iy]` (only the rows holding image modes).
        const B: usize = 8;
        let mut cols = par_filled(Complex64::default(), nx * ny);
        cols.par_chunks_mut(ny * B).enumerate().for_each_init(
            || (vec![Complex64::default(); gy * B], vec![Complex64::default(); self.fft_y.get_inplace_scratch_len()]),
            |(block, scratch), (bi, dst)| {
                let ncols = dst.len() / ny;
                let gcol = |ix: usize| (ix + gx - nx / 2) % gx;
                for r in 0..gy {
                    for c in 0..ncols {
                        block[c * gy + r] = grid[r * gx + gcol(bi * B + c)];
                    }
                }
                for c in 0..ncols {
                    let col = &mut block[c * gy..(c + 1) * gy];
                    self.fft_y.process_with_scratch(col, scratch);
                    let corr_x = self.correction_x[bi * B + c];
                    for iy in 0..ny {
                        let r = (iy + gy - ny / 2) % gy;
                        dst[c * ny + iy] = col[r] * (corr_x * self.correction_y[iy]);
                    }
                }
            },
        );
        crate::fft2::transpose(&cols, out, nx, ny);
    }

    /// Image -> padded grid: correct, place modes, inverse FFT the image columns, then the
    /// rows, writing each grid row into the padded layout (with periodic margins of width
    /// `support` on every side) so degridding needs no wrap-around logic.
    fn image_to_padded_grid(&self, image: &[Complex64]) -> Vec<f64> {
        let (gx, gy, nx, ny) = (self.grid_nx, self.grid_ny, self.nx, self.ny);
        let w = self.shape.support;
        // Column-major corrected image columns, each inverse-FFT'd along y: cols[ix * gy + r].
        let mut cols = par_filled(Complex64::default(), nx * gy);
        cols.par_chunks_mut(gy).enumerate().for_each_init(
            || vec![Complex64::default(); self.ifft_y.get_inplace_scratch_len()],
            |scratch, (ix, col)| {
                let corr_x = self.correction_x[ix];
                for iy in 0..ny {
                    col[(iy + gy - ny / 2) % gy] = image[iy * nx + ix] * (corr_x * self.correction_y[iy]);
                }
                self.ifft_y.process_with_scratch(col, scratch);
            },
        );
        let (pw, ph) = (gx + 2 * w, gy + 2 * w);
        let mut padded = vec![0.0f64; 2 * pw * ph];
        padded.par_chunks_mut(2 * pw).enumerate().for_each_init(
            || (vec![Complex64::default(); gx], vec![Complex64::default(); self.ifft_x.get_inplace_scratch_len()]),
            |(row, scratch), (q, dst)| {
                let r = (q + gy - w) % gy;
                if !self.row_used[r] {
                    return;
                }
                row.iter_mut().for_each(|v| *v = Complex64::default());
                for ix in 0..nx {
                    row[(ix + gx - nx / 2) % gx] = cols[ix * gy + r];
                }
                self.ifft_x.process_with_scratch(row, scratch);
                for (i, d) in dst.chunks_exact_mut(2).enumerate() {
                    let v = row[(i + gx - w) % gx];
                    d[0] = v.re;
                    d[1] = v.im;
                }
            },
        );
        padded
    }
}

/// Type 1 transforms ([`Nufft2d::adjoint`]) of several sets of values at the same points, the
/// points given a chunk at a time: what the caller holds is all that grows with the number of
/// points, since sorting, positions and values in plan order are only ever held for one chunk.
/// The grids accumulate over the chunks; the images are the sums over all points, equal to
/// one transform of all points up to the order of floating-point additions.
pub struct ChunkedAdjoint {
    /// The plan the points are spread with: the image's own, or a window's.
    plan: Nufft2d,
    grids: Vec<Vec<Complex64>>,
    /// Grid rows touched by any chunk's points.
    row_used: Vec<bool>,
    /// Where the grids are a window of the image's grid: that grid.
    window: Option<GridWindow>,
}

/// The image's grid of a windowed [`ChunkedAdjoint`], whose grids hold only the cells within a
/// window around the origin of it: cell `s` (signed) of the image's grid is cell `s mod g'` of
/// the window's `g'`, the same cell for every point whose kernel stays within `|s| < g'/2`.
/// Points are spread on the window's plan at coordinates scaled by `g / g'`, so that they fall
/// on the same cells; at the end the window is put back in the image's grid, which is
/// transformed and corrected as the image's.
struct GridWindow {
    full: Nufft2d,
    /// Largest point coordinate magnitude (radians per pixel) the window holds.
    max_phase: f64,
}

impl ChunkedAdjoint {
    /// `transforms` sums on an `nx x ny` image (see [`Nufft2d::new`]).
    pub fn new(nx: usize, ny: usize, transforms: usize, params: NufftParams, threads: usize) -> Result<ChunkedAdjoint> {
        let plan = Nufft2d::new(nx, ny, &[], &[], params, threads)?;
        Ok(Self::on_plan(plan, transforms, None))
    }

    /// As [`new`](Self::new) for points of coordinates `|x|, |y| <= max_phase` (radians per
    /// pixel) only: the grids hold the window of the image's grid that their kernels reach
    /// (the data of a small uv extent on a finely sampled image occupy a small part of its
    /// grid), so they take less memory; the images are the same (to rounding).
    pub fn windowed(nx: usize, ny: usize, transforms: usize, max_phase: f64, params: NufftParams, threads: usize) -> Result<ChunkedAdjoint> {
        let full = Nufft2d::new(nx, ny, &[], &[], params, threads)?;
        let Some((wx, wy)) = Self::window(&full, max_phase)? else {
            return Ok(Self::on_plan(full, transforms, None));
        };
        let plan = Nufft2d::with_grid((2, 2), (wx, wy), (&[], &[]), full.shape.clone(), params, threads)?;
        Ok(Self::on_plan(plan, transforms, Some(GridWindow { full, max_phase })))
    }

    /// Bytes the grids of [`windowed`](Self::windowed) would take, and one grid of the
    /// image's (what finishing adds), allocating no grid.
    pub fn windowed_grid_bytes(nx: usize, ny: usize, transforms: usize, max_phase: f64, params: NufftParams) -> Result<(f64, f64)> {
        let full = Nufft2d::new(nx, ny, &[], &[], params, 0)?;
        let (gx, gy) = Self::window(&full, max_phase)?.unwrap_or((full.grid_nx, full.grid_ny));
        let cell = std::mem::size_of::<Complex64>() as f64;
        Ok((transforms as f64 * (gx * gy) as f64 * cell, (full.grid_nx * full.grid_ny) as f64 * cell))
    }

    /// The window of `full`'s grid that points of coordinates up to `max_phase` reach with
    /// their kernels (all apart); `None` where that is the whole grid.
    fn window(full: &Nufft2d, max_phase: f64) -> Result<Option<(usize, usize)>> {
        if !(max_phase >= 0.0 && max_phase.is_finite()) {
            return Err(Error::parameter("points", format!("expected a finite coordinate bound, got {max_phase}")));
        }
        let support = full.shape.support;
        // Cells (signed) a point's kernel reaches, and the window holding them all apart.
        let window = |g: usize| {
            let reach = (max_phase * g as f64 / (2.0 * std::f64::consts::PI)).ceil() as usize + support / 2 + 2;
            good_fft_size(2 * reach + 2).max(2 * support)
        };
        let (wx, wy) = (window(full.grid_nx), window(full.grid_ny));
        Ok((wx < full.grid_nx && wy < full.grid_ny).then_some((wx, wy)))
    }

    fn on_plan(plan: Nufft2d, transforms: usize, window: Option<GridWindow>) -> ChunkedAdjoint {
        let cells = plan.grid_nx * plan.grid_ny;
        let grids = plan.install(|| (0..transforms).map(|_| par_filled(Complex64::default(), cells)).collect());
        let row_used = vec![false; plan.grid_ny];
        ChunkedAdjoint { plan, grids, row_used, window }
    }

    /// Bytes of the grids.
    #[cfg(test)]
    pub fn grid_bytes(&self) -> usize {
        self.grids.len() * self.plan.grid_nx * self.plan.grid_ny * std::mem::size_of::<Complex64>()
    }

    /// Adds the points `(x[k], y[k])` (as in [`Nufft2d::new`]) with value `value(t, k)` in
    /// transform `t`.
    pub fn add(&mut self, x: &[f64], y: &[f64], value: impl Fn(usize, usize) -> Complex64 + Sync) -> Result<()> {
        self.add_in_order(x, y, |order| order.to_vec(), |order, t, i| value(t, order[i] as usize))
    }

    /// As [`add`](Self::add), with the values in the plan's order: `prepare` is given the
    /// caller's index of each point in that order (once per chunk), and `value(prepared, t, i)`
    /// is the `i`-th point's value in transform `t`. What each point needs is then gathered
    /// once, not once per transform.
    pub fn add_in_order<S: Send + Sync>(
        &mut self,
        x: &[f64],
        y: &[f64],
        prepare: impl FnOnce(&[u32]) -> S + Send,
        value: impl Fn(&S, usize, usize) -> Complex64 + Sync,
    ) -> Result<()> {
        if x.len() > u32::MAX as usize {
            return Err(Error::parameter("points", "more than 2^32 points in one chunk"));
        }
        match &self.window {
            None => self.plan.sort_points(x, y, false)?,
            Some(window) => {
                let bound = window.max_phase;
                if let Some(k) = (0..x.len()).find(|&k| !(x[k].abs() <= bound && y[k].abs() <= bound)) {
                    return Err(Error::parameter(
                        "points",
                        format!("point ({}, {}) lies beyond the coordinate bound {bound} its gridder was made for", x[k], y[k]),
                    ));
                }
                let sx = window.full.grid_nx as f64 / self.plan.grid_nx as f64;
                let sy = window.full.grid_ny as f64 / self.plan.grid_ny as f64;
                let xs: Vec<f64> = x.iter().map(|&x| x * sx).collect();
                let ys: Vec<f64> = y.iter().map(|&y| y * sy).collect();
                self.plan.sort_points(&xs, &ys, false)?
            }
        }
        let plan = &self.plan;
        let prepared = plan.install(|| prepare(&plan.order));
        for (t, grid) in self.grids.iter_mut().enumerate() {
            plan.install(|| {
                let sorted: Vec<Complex64> = (0..plan.order.len()).into_par_iter().map(|i| value(&prepared, t, i)).collect();
                let sources = plan.tasks.iter().map(|task| Source::Sorted(&sorted[task.points.clone()])).collect();
                dispatch_support!(plan.shape.support, W, W2, L => plan.grid::<W, W2, L>(sources, grid));
            });
        }
        self.row_used.iter_mut().zip(&self.plan.row_used).for_each(|(all, &chunk)| *all |= chunk);
        Ok(())
    }

    /// The transforms' images, in the order of the values' `t`.
    pub fn finish(self) -> Vec<Vec<Complex64>> {
        let mut images = Vec::new();
        self.finish_each(|_, image| images.push(image));
        images
    }

    /// Hands each transform's image to `f` (with its `t`) as soon as it is made, each grid
    /// released as it is transformed.
    pub fn finish_each(self, mut f: impl FnMut(usize, Vec<Complex64>)) {
        let ChunkedAdjoint { plan, grids, row_used, window } = self;
        let Some(GridWindow { full, .. }) = window else {
            for (t, grid) in grids.into_iter().enumerate() {
                let mut out = vec![Complex64::default(); plan.nx * plan.ny];
                plan.install(|| plan.grid_to_image(grid, &row_used, &mut out));
                f(t, out);
            }
            return;
        };
        let (wx, wy, gx, gy) = (plan.grid_nx, plan.grid_ny, full.grid_nx, full.grid_ny);
        // Window cell -> the image grid's cell of the same signed index.
        let to_full = |c: usize, w: usize, g: usize| if c < w / 2 { c } else { c + g - w };
        let mut full_row_used = vec![false; gy];
        for (r, &used) in row_used.iter().enumerate() {
            full_row_used[to_full(r, wy, gy)] = used;
        }
        for (t, grid) in grids.into_iter().enumerate() {
            let mut cells = full.install(|| par_filled(Complex64::default(), gx * gy));
            for r in (0..wy).filter(|&r| row_used[r]) {
                let dst = &mut cells[to_full(r, wy, gy) * gx..][..gx];
                let src = &grid[r * wx..][..wx];
                dst[..wx / 2].copy_from_slice(&src[..wx / 2]);
                dst[gx - (wx - wx / 2)..].copy_from_slice(&src[wx / 2..]);
            }
            drop(grid);
            let mut out = vec![Complex64::default(); full.nx * full.ny];
            full.install(|| full.grid_to_image(cells, &full_row_used, &mut out));
            f(t, out);
        }
    }
}

multiversion! {
    /// Spread the points of one tile into its buffer: interleaved `re, im` reals in rows of
    /// `bw2`, the tile's padded origin at `origin`. The points are `local` in the task's
    /// range (for `Source::Sorted`), with caller indices `order` (for `Source::Parts`).
    fn spread_tile<const W: usize, const W2: usize, const L: usize>(
        kernel: &SymKernel<W, W2, L>,
        positions: &[GridPosition],
        source: &mut Source,
        local: std::ops::Range<usize>,
        order: &[u32],
        shift: u32,
        buf: &mut [f64],
        bw2: usize,
        origin: (u32, u32),
    ) => spread_tile_impl
}

#[inline(always)]
fn spread_tile_impl<const W: usize, const W2: usize, const L: usize, const FMA: bool>(
    kernel: &SymKernel<W, W2, L>,
    positions: &[GridPosition],
    source: &mut Source,
    local: std::ops::Range<usize>,
    order: &[u32],
    shift: u32,
    buf: &mut [f64],
    bw2: usize,
    (x0, y0): (u32, u32),
) {
    for (k, p) in positions.iter().enumerate() {
        let v = match source {
            Source::Sorted(values) => values[local.start + k],
            Source::Parts { segments, cursor } => {
                let part = (order[k] >> shift) as usize;
                let c = &mut cursor[part];
                let v = segments[part][*c];
                *c += 1;
                v
            }
        };
        let kxy = kernel.eval::<FMA>(p.zx(), p.zy());
        let (kx, ky) = kxy.split_at(W);
        let base = (p.py() - y0 as usize) * bw2 + 2 * (p.px() - x0 as usize);
        spread_point::<W, W2, FMA>(v, kx, ky, &mut buf[base..], bw2);
    }
}

/// Add `v kx[b] ky[a]` to the `W x W` footprint whose first cell starts `footprint`
/// (interleaved `re, im` reals in rows of `bw2`).
#[inline(always)]
fn spread_point<const W: usize, const W2: usize, const FMA: bool>(v: Complex64, kx: &[f64], ky: &[f64], footprint: &mut [f64], bw2: usize) {
    let mut vk = [0.0f64; W2];
    for b in 0..W {
        vk[2 * b] = v.re * kx[b];
        vk[2 * b + 1] = v.im * kx[b];
    }
    let footprint = &mut footprint[..(W - 1) * bw2 + W2];
    for (a, &kya) in ky.iter().enumerate() {
        let row = &mut footprint[a * bw2..a * bw2 + W2];
        for (cell, &vkj) in row.iter_mut().zip(&vk) {
            *cell = madd::<FMA>(vkj, kya, *cell);
        }
    }
}

multiversion! {
    /// [`spread_tile`] of two values per point (`a[k]`, `b[k]`, the tile's points in order)
    /// into two buffers of the same layout: the kernel is evaluated once for both.
    fn spread_tile_pair<const W: usize, const W2: usize, const L: usize>(
        kernel: &SymKernel<W, W2, L>,
        positions: &[GridPosition],
        a: &[Complex64],
        b: &[Complex64],
        buf_a: &mut [f64],
        buf_b: &mut [f64],
        bw2: usize,
        origin: (u32, u32),
    ) => spread_tile_pair_impl
}

#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn spread_tile_pair_impl<const W: usize, const W2: usize, const L: usize, const FMA: bool>(
    kernel: &SymKernel<W, W2, L>,
    positions: &[GridPosition],
    a: &[Complex64],
    b: &[Complex64],
    buf_a: &mut [f64],
    buf_b: &mut [f64],
    bw2: usize,
    (x0, y0): (u32, u32),
) {
    for ((p, &va), &vb) in positions.iter().zip(a).zip(b) {
        let kxy = kernel.eval::<FMA>(p.zx(), p.zy());
        let (kx, ky) = kxy.split_at(W);
        let base = (p.py() - y0 as usize) * bw2 + 2 * (p.px() - x0 as usize);
        spread_point::<W, W2, FMA>(va, kx, ky, &mut buf_a[base..], bw2);
        spread_point::<W, W2, FMA>(vb, kx, ky, &mut buf_b[base..], bw2);
    }
}

multiversion! {
    /// Interpolate the padded grid (interleaved `re, im` reals in rows of `pw2`) at the
    /// points: sum the `W` kernel rows weighted by the y kernel into `2 W` reals, then
    /// contract with the x kernel.
    fn interp_points<const W: usize, const W2: usize, const L: usize>(
        kernel: &SymKernel<W, W2, L>,
        positions: &[GridPosition],
        padded: &[f64],
        pw2: usize,
        sink: &mut Sink,
        order: &[u32],
        shift: u32,
    ) => interp_points_impl
}

#[inline(always)]
fn interp_points_impl<const W: usize, const W2: usize, const L: usize, const FMA: bool>(
    kernel: &SymKernel<W, W2, L>,
    positions: &[GridPosition],
    padded: &[f64],
    pw2: usize,
    sink: &mut Sink,
    order: &[u32],
    shift: u32,
) {
    for (k, p) in positions.iter().enumerate() {
        let kxy = kernel.eval::<FMA>(p.zx(), p.zy());
        let (kx, ky) = kxy.split_at(W);
        let base = p.py() * pw2 + 2 * p.px();
        let footprint = &padded[base..base + (W - 1) * pw2 + W2];
        let mut acc = [0.0f64; W2];
        for (a, &kya) in ky.iter().enumerate() {
            let row = &footprint[a * pw2..a * pw2 + W2];
            for (s, &cell) in acc.iter_mut().zip(row) {
                *s = madd::<FMA>(cell, kya, *s);
            }
        }
        let (mut re, mut im) = (0.0, 0.0);
        for b in 0..W {
            re = madd::<FMA>(acc[2 * b], kx[b], re);
            im = madd::<FMA>(acc[2 * b + 1], kx[b], im);
        }
        let v = Complex64::new(re, im);
        match sink {
            Sink::Sorted(out) => out[k] = v,
            Sink::Parts { segments, cursor } => {
                let part = (order[k] >> shift) as usize;
                let c = &mut cursor[part];
                segments[part][*c] = v;
                *c += 1;
            }
        }
    }
}

/// The values of one task's points, for gridding.
enum Source<'a> {
    /// In plan order.
    Sorted(&'a [Complex64]),
    /// The task's segments of the parts (see [`Permutation`]), read in plan order with one
    /// cursor per part.
    Parts { segments: Vec<&'a [Complex64]>, cursor: Vec<usize> },
}

impl<'a> Source<'a> {
    fn parts(segments: Vec<&'a [Complex64]>) -> Self {
        let cursor = vec![0; segments.len()];
        Source::Parts { segments, cursor }
    }
}

/// Where one task's interpolated values go.
enum Sink<'a> {
    /// In plan order.
    Sorted(&'a mut [Complex64]),
    /// The task's segments of the parts, written in plan order with one cursor per part.
    Parts { segments: Vec<&'a mut [Complex64]>, cursor: Vec<usize> },
}

impl<'a> Sink<'a> {
    fn parts(segments: Vec<&'a mut [Complex64]>) -> Self {
        let cursor = vec![0; segments.len()];
        Sink::Parts { segments, cursor }
    }
}

/// `vec![value; n]` written by the current thread pool: the first touch of fresh pages (and
/// the page faults it costs) is shared by the threads, and `vec!` of a non-primitive type
/// would write it all on one thread.
fn par_filled<T: Clone + Send>(value: T, n: usize) -> Vec<T> {
    let mut v = Vec::with_capacity(n);
    v.par_extend(rayon::iter::repeat_n(value, n));
    v
}

/// `1.5 * 2^52`: adding and subtracting it rounds an `f64` of magnitude below `2^51` to the
/// nearest integer, and after adding it the low mantissa bits hold that integer.
const ROUND_MAGIC: f64 = 6755399441055744.0;

/// Padded grid position of a point at grid coordinate `t` (magnitude below `2^50`), one axis
/// of a [`GridPosition`]: the first covered cell `i0 + w` and the fraction `frac = i0 - s`
/// (kernel variable `z = 2 frac - 1`) with `s = (t mod n) - w/2` and `i0 = ceil(s)` (see
/// [`PolynomialKernel`]).
///
/// Floor and ceiling use [`ROUND_MAGIC`]: the baseline x86-64 target has no SSE4.1 rounding
/// instruction (`f64::floor` is a library call there) and `as` casts saturate, which costs
/// several instructions each; this keeps the whole computation to a few float operations.
#[inline(always)]
fn grid_position(t: f64, n: usize, inv_n: f64, w: usize) -> u64 {
    let n_f = n as f64;
    let q = t * inv_n;
    let mut fq = (q + ROUND_MAGIC) - ROUND_MAGIC;
    if fq > q {
        fq -= 1.0;
    }
    // t mod n, in [0, n) up to rounding: a result just below 0 only moves i0 by one cell
    // within the padding, a result of n is folded back.
    let mut t = t - n_f * fq;
    if t >= n_f {
        t -= n_f;
    }
    let s = t - w as f64 / 2.0;
    let mut i0 = (s + ROUND_MAGIC) - ROUND_MAGIC;
    if i0 < s {
        i0 += 1.0;
    }
    let frac = i0 - s; // in [0, 1)
    // i0 + w is a small non-negative integer, frac * 2^48 rounded one below 2^51: read them
    // off the mantissa.
    let cell = (i0 + w as f64 + ROUND_MAGIC).to_bits() & 0xffff;
    let frac = ((frac * (1u64 << FRAC_BITS) as f64 + ROUND_MAGIC).to_bits() & ((1 << 51) - 1)).min(FRAC_MASK);
    cell << FRAC_BITS | frac
}

fn fit_kernel(shape: &KernelShape, tolerance: f64) -> Vec<f64> {
    dispatch_support!(shape.support, W => {
        PolynomialKernel::<W>::fit(shape, tolerance).coeffs.iter().flatten().copied().collect()
    })
}

// After `dispatch_support!`, which it uses.
pub mod wgrid;

#[cfg(test)]
mod tests;
