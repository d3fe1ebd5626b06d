//! A network series trained at T x T run over a larger N x N image in overlapping T x T tiles:
//! the networks are convolutional, but a series sees a field of the size it was trained on
//! (its normalisation, the extent of its sources and sidelobes), so each tile is one such field.
//! The tiles' outputs are blended with weights that fall linearly to zero across the overlap
//! towards a neighbouring tile (1 at the image's own edges), so no tile's border, where its
//! network saw a mirrored edge, shows in the image.

/// Where the tiles lie along one axis, and their blending weights.
#[derive(Clone, Debug, PartialEq)]
pub struct Tiling {
    /// The image's edge, N.
    pub size: usize,
    /// The tiles' edge, T (< N).
    pub tile: usize,
    /// Pixels shared by neighbouring tiles, at least this many.
    pub overlap: usize,
    /// The tiles' first pixels along an axis: from 0 by `tile - overlap`, the last at N - T.
    pub starts: Vec<usize>,
}

impl Tiling {
    /// `None` where one tile covers the image (`tile >= size`).
    pub fn new(size: usize, tile: usize, overlap: usize) -> Option<Tiling> {
        if tile >= size || tile == 0 {
            return None;
        }
        let overlap = overlap.min(tile / 2);
        let stride = tile - overlap;
        let mut starts: Vec<usize> = (0..).map(|k| k * stride).take_while(|&s| s + tile < size).collect();
        starts.push(size - tile);
        Some(Tiling { size, tile, overlap, starts })
    }

    /// Tiles in all (the starts' count squared).
    pub fn count(&self) -> usize {
        self.starts.len() * self.starts.len()
    }

    /// The blending weight of pixel `i` of the tile starting at `start`, along one axis: a
    /// linear ramp over the part it shares with the tile before (after) it, up from (down to)
    /// zero, and 1 elsewhere, the image's edges included.
    fn weight_1d(&self, start: usize, i: usize) -> f64 {
        let k = self.starts.iter().position(|&s| s == start).expect("a tile start");
        let mut w = 1.0f64;
        if k > 0 {
            let shared = self.starts[k - 1] + self.tile - start;
            if i < shared {
                w = w.min((i as f64 + 0.5) / shared as f64);
            }
        }
        if k + 1 < self.starts.len() {
            let shared = start + self.tile - self.starts[k + 1];
            let from_end = self.tile - 1 - i;
            if from_end < shared {
                w = w.min((from_end as f64 + 0.5) / shared as f64);
            }
        }
        w
    }

    /// The T x T tile of the N x N `image` at (`x0`, `y0`).
    pub fn extract(&self, image: &[f64], x0: usize, y0: usize) -> Vec<f64> {
        let (n, t) = (self.size, self.tile);
        (0..t).flat_map(|y| image[(y0 + y) * n + x0..][..t].iter().copied()).collect()
    }

    /// Whether any pixel of the T x T tile of the N x N `mask` at (`x0`, `y0`) is set.
    pub fn any_set(&self, mask: &[bool], x0: usize, y0: usize) -> bool {
        let (n, t) = (self.size, self.tile);
        (0..t).any(|y| mask[(y0 + y) * n + x0..][..t].iter().any(|&inside| inside))
    }

    /// Adds `tile` (at (`x0`, `y0`)) times its blending weights to `sum`, and the weights to
    /// `weights`.
    pub fn accumulate(&self, tile: &[f64], x0: usize, y0: usize, sum: &mut [f64], weights: &mut [f64]) {
        let (n, t) = (self.size, self.tile);
        let wx: Vec<f64> = (0..t).map(|i| self.weight_1d(x0, i)).collect();
        for y in 0..t {
            let wy = self.weight_1d(y0, y);
            let row = (y0 + y) * n + x0;
            for x in 0..t {
                let w = wy * wx[x];
                sum[row + x] += w * tile[y * t + x];
                weights[row + x] += w;
            }
        }
    }

    /// Every tile's origin, row by row.
    pub fn origins(&self) -> Vec<(usize, usize)> {
        self.starts.iter().flat_map(|&y| self.starts.iter().map(move |&x| (x, y))).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_cover_the_image_and_their_weights_sum_to_one_everywhere() {
        for (n, t, o) in [(1024, 512, 128), (2048, 512, 128), (1000, 512, 64), (600, 512, 128), (96, 32, 8)] {
            let tiling = Tiling::new(n, t, o).unwrap();
            assert_eq!(*tiling.starts.last().unwrap(), n - t);
            assert!(tiling.starts.windows(2).all(|w| w[1] > w[0] && w[1] - w[0] <= t - tiling.overlap), "{:?}", tiling.starts);
            let image: Vec<f64> = (0..n * n).map(|k| (k % 97) as f64 - 40.0).collect();
            let (mut sum, mut weights) = (vec![0.0; n * n], vec![0.0; n * n]);
            for (x0, y0) in tiling.origins() {
                let tile = tiling.extract(&image, x0, y0);
                tiling.accumulate(&tile, x0, y0, &mut sum, &mut weights);
            }
            // Every pixel is covered with a positive weight, and blending the image's own tiles
            // gives the image back.
            assert!(weights.iter().all(|&w| w > 0.0));
            let worst = sum.iter().zip(&weights).zip(&image).map(|((s, w), v)| (s / w - v).abs()).fold(0.0, f64::max);
            assert!(worst < 1e-9, "{n}/{t}/{o}: {worst}");
        }
        assert!(Tiling::new(512, 512, 64).is_none());
    }

    #[test]
    fn a_tiles_weight_falls_to_zero_only_towards_a_neighbour() {
        let tiling = Tiling::new(1024, 512, 128).unwrap();
        assert_eq!(tiling.starts, vec![0, 384, 512]);
        // The first tile: 1 at the image's edge, falling over its last shared pixels.
        assert_eq!(tiling.weight_1d(0, 0), 1.0);
        assert!(tiling.weight_1d(0, 511) < 0.01);
        // The last tile: 1 at the image's far edge.
        assert_eq!(tiling.weight_1d(512, 511), 1.0);
        assert!(tiling.weight_1d(512, 0) < 0.01);
    }
}
