//! Gathering the latent map as a product ([`LatentMapGrid`]) and its QC σ map, from the samples
//! the latent-height routes of [`crate::tile`] produce under every core point.

use crate::stats::LatentStdMap;
use crate::tile::dominant_axis;
use precimap_core::geom::floor;
use precimap_core::hash::FxHashMap;
use precimap_core::LatentMapPoint;

/// The latent surface under one core point of a tile.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LatentSample {
    /// The point moved along its surface model's normal onto the latent surface: tile-local x
    /// and y (the core is `[0, tile size)²`), absolute z.
    pub position: [f64; 3],
    /// The surface model's unit normal.
    pub normal: [f64; 3],
    /// The point's own height above the latent surface (its residual before the threshold).
    pub residual_m: f64,
    /// Standard deviation of the strip passes' heights about the latent surface.
    pub std_m: f64,
    /// Strip passes (or, on the raster route, surface contributions) the latent height averages.
    pub passes: u32,
    /// Whether the latent height is used (the sampled route leaves out steep covering surfaces);
    /// the σ map counts every sample, the exported map only used ones.
    pub used: bool,
}

/// Where the latent map's samples go. The estimation's iterations pass `()`, which compiles to
/// nothing: gathering inside every iteration made the covering loop 5–9 % slower through its
/// code generation alone, so only the iterations whose map is kept run the recording
/// copy.
pub(crate) trait LatentSink {
    const RECORDS: bool;
    fn add(&mut self, sample: &LatentSample);
}

impl LatentSink for () {
    const RECORDS: bool = false;
    #[inline(always)]
    fn add(&mut self, _: &LatentSample) {}
}

/// What a recording iteration keeps: the σ map (QC), the exported map, or both.
#[derive(Debug, Default)]
pub(crate) struct LatentRecord {
    pub std: Option<LatentStdMap>,
    pub map: Option<LatentMapGrid>,
}

impl LatentSink for LatentRecord {
    const RECORDS: bool = true;
    #[inline]
    fn add(&mut self, s: &LatentSample) {
        if let Some(std) = &mut self.std {
            std.add(s.position[0], s.position[1], s.std_m);
        }
        if let Some(map) = &mut self.map {
            map.add(s);
        }
    }
}

/// The latent map of one tile thinned to voxels of `cell_m`: per voxel and side of the surface
/// (the normal's dominant signed axis, so that the two faces of a wall or a curb's face and the
/// road beside it stay apart), the mean of the used samples within the outlier threshold.
#[derive(Clone, Debug)]
pub struct LatentMapGrid {
    cell_m: f64,
    threshold_m: f64,
    cells: FxHashMap<[i64; 4], VoxelSums>,
}

#[derive(Clone, Copy, Debug, Default)]
struct VoxelSums {
    count: u32,
    passes: u32,
    position: [f64; 3],
    normal: [f64; 3],
    variance: f64,
}

impl LatentMapGrid {
    pub fn new(cell_m: f64, threshold_m: f64) -> Self {
        Self { cell_m, threshold_m, cells: FxHashMap::default() }
    }

    /// Adds a sample; unused ones, those beyond the threshold (not observations) and non-finite
    /// ones are left out.
    #[inline]
    pub fn add(&mut self, s: &LatentSample) {
        let finite = s.position.iter().chain(&s.normal).all(|v| v.is_finite()) && s.std_m.is_finite();
        if !(s.used && finite && s.residual_m.abs() <= self.threshold_m) {
            return;
        }
        let n = s.normal;
        let axis = dominant_axis(&n);
        let side = 2 * axis as i64 + (n[axis] < 0.0) as i64;
        let inv = 1.0 / self.cell_m;
        let key = [
            floor(s.position[1] * inv) as i64,
            floor(s.position[0] * inv) as i64,
            floor(s.position[2] * inv) as i64,
            side,
        ];
        let v = self.cells.entry(key).or_default();
        v.count += 1;
        v.passes = v.passes.max(s.passes);
        for k in 0..3 {
            v.position[k] += s.position[k];
            v.normal[k] += n[k];
        }
        v.variance += s.std_m * s.std_m;
    }

    /// The map's points in absolute coordinates (`origin`: the tile's south-west corner), in a
    /// fixed order (south to north, west to east, bottom to top, then side).
    pub fn finish(self, origin: [f64; 2]) -> Vec<LatentMapPoint> {
        let mut cells: Vec<([i64; 4], VoxelSums)> = self.cells.into_iter().collect();
        cells.sort_unstable_by_key(|(k, _)| *k);
        cells
            .into_iter()
            .map(|(_, v)| {
                let c = v.count as f64;
                let len = (v.normal[0] * v.normal[0] + v.normal[1] * v.normal[1] + v.normal[2] * v.normal[2]).sqrt();
                let normal = if len > 0.0 { v.normal.map(|x| (x / len) as f32) } else { [0.0; 3] };
                LatentMapPoint {
                    position: [v.position[0] / c + origin[0], v.position[1] / c + origin[1], v.position[2] / c],
                    normal,
                    std_m: (v.variance / c).sqrt() as f32,
                    observations: v.count,
                    passes: v.passes.min(u16::MAX as u32) as u16,
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(position: [f64; 3], normal: [f64; 3], residual_m: f64) -> LatentSample {
        LatentSample { position, normal, residual_m, std_m: 0.002, passes: 3, used: true }
    }

    /// Voxels average their samples; the two sides of a thin wall stay two points; samples that
    /// are not observations are left out.
    #[test]
    fn voxels_keep_surface_sides_apart_and_only_observations() {
        let mut g = LatentMapGrid::new(0.1, 0.01);
        g.add(&sample([1.01, 2.02, 100.03], [0.0, 0.0, 1.0], 0.0));
        g.add(&sample([1.03, 2.04, 100.05], [0.0, 0.0, 1.0], 0.005));
        // The wall's other face in the same voxel.
        g.add(&sample([1.02, 2.03, 100.04], [0.0, 0.0, -1.0], 0.0));
        // Beyond the threshold, unused, non-finite: none counts.
        g.add(&sample([1.02, 2.03, 100.04], [0.0, 0.0, 1.0], 0.02));
        g.add(&LatentSample { used: false, ..sample([1.02, 2.03, 100.04], [0.0, 0.0, 1.0], 0.0) });
        g.add(&sample([f64::NAN, 2.03, 100.04], [0.0, 0.0, 1.0], 0.0));
        let points = g.finish([500_000.0, 5_000_000.0]);
        assert_eq!(points.len(), 2, "{points:?}");
        let up = points.iter().find(|p| p.normal[2] > 0.0).unwrap();
        let down = points.iter().find(|p| p.normal[2] < 0.0).unwrap();
        assert_eq!(up.observations, 2);
        assert_eq!(down.observations, 1);
        for (got, want) in up.position.iter().zip([500_001.02, 5_000_002.03, 100.04]) {
            assert!((got - want).abs() < 1e-9, "{:?}", up.position);
        }
        assert!((up.std_m - 0.002).abs() < 1e-7);
        assert_eq!(up.passes, 3);
    }
}
