//! The latent map as a product: the surface all corrected strips agree on, thinned to one point
//! per small voxel and surface side (what `precimap run` writes to `OUT/latent/`).

use serde::{Deserialize, Serialize};

/// One point of the exported latent map: the mean of the latent surface's samples in one voxel
/// whose normals face one way (a thin wall seen from both sides gives two points).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LatentMapPoint {
    /// Absolute coordinates (metres, the campaign's projection).
    pub position: [f64; 3],
    /// Unit normal of the local surface model, facing the scanners.
    pub normal: [f32; 3],
    /// Root mean square, over the samples, of the strip passes' standard deviation about the
    /// latent surface (metres): how well the strips agree here.
    pub std_m: f32,
    /// Observations (core points within the outlier threshold) averaged into the point.
    pub observations: u32,
    /// Most strip passes any of those observations' latent heights averaged.
    pub passes: u16,
}
