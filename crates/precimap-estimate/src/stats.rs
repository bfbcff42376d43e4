//! Tile statistics and residual histograms (QC), mergeable across tiles.

use precimap_core::geom::floor;
use precimap_core::{ControlSums, TileKey};
use serde::{Deserialize, Serialize};

/// Signed point-to-latent-map distances in 0.5 mm bins over ±50 mm, plus under/overflow.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualHistogram {
    pub bin_m: f64,
    pub min_m: f64,
    pub counts: Vec<u64>,
    pub below: u64,
    pub above: u64,
}

impl Default for ResidualHistogram {
    fn default() -> Self {
        Self { bin_m: 0.0005, min_m: -0.05, counts: vec![0; 200], below: 0, above: 0 }
    }
}

impl ResidualHistogram {
    #[inline]
    pub fn add(&mut self, e: f64) {
        let k = floor((e - self.min_m) / self.bin_m);
        if k < 0.0 {
            self.below += 1;
        } else if k >= self.counts.len() as f64 {
            self.above += 1;
        } else {
            self.counts[k as usize] += 1;
        }
    }

    pub fn merge(&mut self, other: &Self) {
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
        self.below += other.below;
        self.above += other.above;
    }

    /// Robust σ of the distances: 1.4826 × the median of |e| (linear within a bin). `None` when
    /// the histogram is empty or the median lies beyond its range.
    pub fn robust_sigma_m(&self) -> Option<f64> {
        let total = self.total();
        if total == 0 {
            return None;
        }
        let zero = -self.min_m / self.bin_m;
        // Bins are symmetric about zero: |e| in [j·b, (j+1)·b) gathers bins zero + j and zero − 1 − j.
        let centre = zero.round() as usize;
        if (zero - centre as f64).abs() > 1e-9 || centre == 0 || centre >= self.counts.len() {
            return None;
        }
        let half = total as f64 / 2.0;
        let mut below = 0.0;
        for j in 0..centre.min(self.counts.len() - centre) {
            let n = (self.counts[centre + j] + self.counts[centre - 1 - j]) as f64;
            if below + n >= half && n > 0.0 {
                let median = (j as f64 + (half - below) / n) * self.bin_m;
                return Some(1.4826 * median);
            }
            below += n;
        }
        None
    }

    pub fn total(&self) -> u64 {
        self.counts.iter().sum::<u64>() + self.below + self.above
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileStats {
    pub tile: TileKey,
    /// Points whose corrected position lies in the tile's core.
    pub points: u64,
    /// Of those, points on a latent-map pixel shared by two or more strip passes.
    pub points_modelled: u64,
    /// Of those, points within the outlier threshold (the observations).
    pub points_used: u64,
    pub residual_sum_m: f64,
    pub residual_sum2_m2: f64,
    pub surface_models: u64,
    /// Raster pixels; in point-sampled steps the sampled core points, so that `pixels_shared` and
    /// `pixel_std_sum_m` describe the latent surface under the points.
    pub pixels: u64,
    pub pixels_shared: u64,
    /// Sum over shared pixels of the standard deviation of the strips' heights.
    pub pixel_std_sum_m: f64,
    /// Distances of all modelled points (before the threshold).
    pub histogram: ResidualHistogram,
    /// What the points measured at each control and check target near the tile, sorted by id.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub control: Vec<ControlSums>,
}

impl TileStats {
    pub fn new(tile: TileKey) -> Self {
        Self {
            tile,
            points: 0,
            points_modelled: 0,
            points_used: 0,
            residual_sum_m: 0.0,
            residual_sum2_m2: 0.0,
            surface_models: 0,
            pixels: 0,
            pixels_shared: 0,
            pixel_std_sum_m: 0.0,
            histogram: ResidualHistogram::default(),
            control: Vec::new(),
        }
    }

    pub fn merge(&mut self, o: &Self) {
        self.points += o.points;
        self.points_modelled += o.points_modelled;
        self.points_used += o.points_used;
        self.residual_sum_m += o.residual_sum_m;
        self.residual_sum2_m2 += o.residual_sum2_m2;
        self.surface_models += o.surface_models;
        self.pixels += o.pixels;
        self.pixels_shared += o.pixels_shared;
        self.pixel_std_sum_m += o.pixel_std_sum_m;
        self.histogram.merge(&o.histogram);
        for sums in &o.control {
            match self.control.binary_search_by(|c| c.id.cmp(&sums.id)) {
                Ok(i) => self.control[i].merge(sums),
                Err(i) => self.control.insert(i, sums.clone()),
            }
        }
    }

    pub fn residual_mean_m(&self) -> f64 {
        if self.points_used == 0 {
            return 0.0;
        }
        self.residual_sum_m / self.points_used as f64
    }

    pub fn residual_std_m(&self) -> f64 {
        if self.points_used < 2 {
            return 0.0;
        }
        let n = self.points_used as f64;
        let mean = self.residual_sum_m / n;
        ((self.residual_sum2_m2 / n - mean * mean).max(0.0) * n / (n - 1.0)).sqrt()
    }
}

/// The latent map's standard deviation (the spread of the strips' surface heights about it) under
/// a tile's core points, per square cell of the tile's core seen from above: what the paper's
/// Figures 11–12 colour. `count[c]` points fell in cell `c` (row-major from the tile's south-west
/// corner, x fastest), `std_sum_m[c]` sums the standard deviation under each.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LatentStdMap {
    pub cell_m: f64,
    /// Cells along each side of the tile.
    pub side: u32,
    pub count: Vec<u32>,
    pub std_sum_m: Vec<f64>,
}

impl LatentStdMap {
    /// Cell edge of the QC map: fine enough to show a street's lanes and façades apart, small
    /// enough (225 cells per 15 m tile) to travel as one object per tile.
    pub const CELL_M: f64 = 1.0;

    pub fn new(tile_size_m: f64) -> Self {
        let side = (tile_size_m / Self::CELL_M).ceil().max(1.0) as u32;
        let cells = (side * side) as usize;
        Self { cell_m: Self::CELL_M, side, count: vec![0; cells], std_sum_m: vec![0.0; cells] }
    }

    /// One point at tile-local `(x, y)` (in the core: `[0, tile size)`) with standard deviation
    /// `std_m` of the latent map under it; points outside the grid or with a non-finite value are
    /// not counted.
    #[inline]
    pub fn add(&mut self, x: f64, y: f64, std_m: f64) {
        let (i, j) = (floor(x / self.cell_m), floor(y / self.cell_m));
        let side = self.side as f64;
        if !(i >= 0.0 && j >= 0.0 && i < side && j < side && std_m.is_finite()) {
            return;
        }
        let c = j as usize * self.side as usize + i as usize;
        self.count[c] += 1;
        self.std_sum_m[c] += std_m;
    }

    /// Mean standard deviation of cell `(i, j)`; `None` where no point fell.
    pub fn mean_m(&self, i: u32, j: u32) -> Option<f64> {
        let c = j as usize * self.side as usize + i as usize;
        (self.count[c] > 0).then(|| self.std_sum_m[c] / self.count[c] as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The robust σ of Gaussian samples is their σ, unmoved by a few gross outliers.
    #[test]
    fn robust_sigma_of_gaussian_with_outliers() {
        let mut h = ResidualHistogram::default();
        assert_eq!(h.robust_sigma_m(), None);
        let mut seed = 5u64;
        let mut uniform = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        for _ in 0..200_000 {
            // Box–Muller, σ 4 mm.
            let (a, b) = (uniform(), uniform());
            h.add(0.004 * (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos());
        }
        for k in 0..2_000 {
            h.add(if k % 2 == 0 { 0.5 } else { -0.03 });
        }
        let sigma = h.robust_sigma_m().unwrap();
        assert!((sigma - 0.004).abs() < 0.0001, "{sigma}");
        // A median beyond the histogram's range is not guessed.
        let mut wide = ResidualHistogram::default();
        for _ in 0..10 {
            wide.add(1.0);
        }
        assert_eq!(wide.robust_sigma_m(), None);
    }
}
