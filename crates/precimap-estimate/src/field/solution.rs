//! The solved field ([`FieldSolution`]) and the campaign's rigid motion ([`CampaignMotion`]), as
//! the corrections take them.

use super::bilinear;
use super::FieldNode;
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::geom::Vec3;
use serde::{Deserialize, Serialize};

/// The solved field: a translation per node.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldSolution {
    pub spacing_m: f64,
    pub nodes: Vec<FieldNode>,
    pub values: Vec<[f64; 3]>,
    /// Data observations summed over all tiles.
    pub observations: u64,
    /// The campaign's rigid motion on top of the field (`Parameters::campaign_motion`).
    #[serde(default)]
    pub motion: Option<CampaignMotion>,
    /// The heading per node (radians, about the vertical; `Parameters::common_mode_heading`),
    /// empty when not solved.
    #[serde(default)]
    pub heading: Vec<f64>,
    /// The tilt per node (radians, about x and y; `Parameters::common_mode_tilt`), empty when
    /// not solved.
    #[serde(default)]
    pub tilt: Vec<[f64; 2]>,
}

/// A rotation of the whole campaign about `origin`, to first order: every anchor's rotation gains
/// `rotation`, its translation `rotation × (p − origin)` (`p` its position). With the field's
/// constant part (a translation) it makes every rigid motion of the campaign, which the strips'
/// agreement cannot see.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CampaignMotion {
    pub origin: [f64; 3],
    /// Rotation vector (radians).
    pub rotation: [f64; 3],
}

impl CampaignMotion {
    /// The correction the motion adds at position `p`.
    pub fn at(&self, p: [f64; 3]) -> [f64; 6] {
        let w = Vec3::from(self.rotation);
        let t = w.cross(&(Vec3::from(p) - Vec3::from(self.origin)));
        [t.x, t.y, t.z, w.x, w.y, w.z]
    }
}

impl FieldSolution {
    /// The field's translation at `(x, y)` and its rotation there (radians about x, y, z; the
    /// tilt and heading, zero where not solved); zero at nodes it does not hold. One look-up of
    /// the four nodes for both.
    pub fn at(&self, x: f64, y: f64) -> ([f64; 3], [f64; 3]) {
        let (mut out, mut rotation) = ([0.0; 3], [0.0; 3]);
        for (node, phi) in bilinear(x, y, self.spacing_m) {
            if let Ok(i) = self.nodes.binary_search(&node) {
                for (c, v) in out.iter_mut().zip(&self.values[i]) {
                    *c += phi * v;
                }
                if let Some(h) = self.heading.get(i) {
                    rotation[2] += phi * h;
                }
                if let Some(t) = self.tilt.get(i) {
                    rotation[0] += phi * t[0];
                    rotation[1] += phi * t[1];
                }
            }
        }
        (out, rotation)
    }

    /// `corrections` with the field added to every anchor's translation (and the campaign's
    /// motion, when solved, to every anchor's correction).
    pub fn apply(&self, positions: &[[f64; 3]], corrections: &TrajectoryCorrections) -> TrajectoryCorrections {
        let mut out = corrections.clone();
        for (v, p) in out.values.iter_mut().zip(positions) {
            let (c, rotation) = self.at(p[0], p[1]);
            for a in 0..3 {
                v[a] += c[a];
            }
            if !self.heading.is_empty() {
                v[5] += rotation[2];
            }
            if !self.tilt.is_empty() {
                v[3] += rotation[0];
                v[4] += rotation[1];
            }
            if let Some(motion) = &self.motion {
                for (value, m) in v.iter_mut().zip(motion.at(*p)) {
                    *value += m;
                }
            }
        }
        out
    }

    /// The campaign's rotation (degrees; zero when not solved).
    pub fn rotation_deg(&self) -> [f64; 3] {
        self.motion.map_or([0.0; 3], |m| m.rotation.map(f64::to_degrees))
    }

    /// Largest translation (metres), heading and tilt (degrees; the tilt as the angle of its
    /// rotation about a horizontal axis) the field gives any anchor of `trajectories` (each a
    /// list of anchor positions): what the reports show.
    pub fn largest<P: AsRef<[[f64; 3]]>>(&self, trajectories: &[P]) -> FieldLargest {
        let mut largest = FieldLargest::default();
        for p in trajectories.iter().flat_map(|t| t.as_ref()) {
            let (v, rotation) = self.at(p[0], p[1]);
            largest.translation_m = largest.translation_m.max((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt());
            largest.heading_deg = largest.heading_deg.max(rotation[2].abs().to_degrees());
            largest.tilt_deg = largest.tilt_deg.max(rotation[0].hypot(rotation[1]).to_degrees());
        }
        largest
    }
}

/// What [`FieldSolution::largest`] finds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FieldLargest {
    pub translation_m: f64,
    pub heading_deg: f64,
    pub tilt_deg: f64,
}
