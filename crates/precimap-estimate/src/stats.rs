//! Tile statistics and residual histograms (QC), mergeable across tiles.

use precimap_core::TileKey;
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
        let k = ((e - self.min_m) / self.bin_m).floor();
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
    pub pixels: u64,
    pub pixels_shared: u64,
    /// Sum over shared pixels of the standard deviation of the strips' heights.
    pub pixel_std_sum_m: f64,
    /// Distances of all modelled points (before the threshold).
    pub histogram: ResidualHistogram,
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
