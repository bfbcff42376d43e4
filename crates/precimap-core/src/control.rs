//! Ground control: surveyed points and planes the adjusted map must pass through.
//!
//! Strips alone fix their agreement, not their place: a shift or turn of the whole campaign
//! changes no residual between strips. A control target observes the latent map's surfaces at a
//! surveyed position. A **point** lies on whatever surfaces surround it (a road-marking corner on
//! the road, a façade corner on both façades): every surface within `control_radius_m` of it
//! whose plane passes through it observes the offset along its normal, so a point on the road
//! fixes the height and a façade corner also the horizontal position. A **plane** (a surveyed
//! planar patch) observes only surfaces parallel to it, within its own radius.
//!
//! A **check** target is measured the same way but never enters the adjustment: its residuals
//! are the independent accuracy figures of the result (RMSE per axis, as in the ASPRS positional
//! accuracy standard).

use serde::{Deserialize, Serialize};

/// What a target does.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ControlRole {
    /// Observed by the adjustment: it fixes the datum.
    #[default]
    Control,
    /// Kept out of the adjustment and reported.
    Check,
}

/// The plane of a planar target: its unit normal and the radius of the patch.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControlPlane {
    pub normal: [f64; 3],
    pub radius_m: f64,
}

/// One surveyed target in the processing frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControlTarget {
    pub id: String,
    pub position: [f64; 3],
    /// Standard deviation per axis (x, y, z), metres.
    pub sigma_m: [f64; 3],
    pub role: ControlRole,
    /// `Some` for a planar patch, `None` for a point.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plane: Option<ControlPlane>,
}

impl ControlTarget {
    /// The target's variance along the unit direction `w`.
    pub fn variance_along(&self, w: [f64; 3]) -> f64 {
        (0..3).map(|a| (w[a] * self.sigma_m[a]).powi(2)).sum()
    }

    /// How far from the target the adjusted surfaces are observed: its patch's radius, or
    /// `point_radius_m` for a point.
    pub fn radius_m(&self, point_radius_m: f64) -> f64 {
        self.plane.map_or(point_radius_m, |p| p.radius_m)
    }
}

/// What one iteration measured at one target: the normal equations of the map's offset `d`
/// from the target (map minus target) over the points that observe it, `Σ ω w wᵀ` and `Σ ω w e`
/// (`e = w·(p − c)`), their weighted square sum, and counts. Sums over tiles add.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ControlSums {
    pub id: String,
    /// Upper triangle `[xx, xy, xz, yy, yz, zz]` of `Σ ω w wᵀ`.
    pub normal: [f64; 6],
    pub rhs: [f64; 3],
    pub weighted_square: f64,
    pub weight: f64,
    pub points: u64,
    /// Strip passes that observed it.
    pub passes: u32,
}

impl ControlSums {
    pub fn new(id: impl Into<String>) -> Self {
        Self { id: id.into(), ..Self::default() }
    }

    /// Adds one observation: residual `e` along unit normal `w`, weight `omega`.
    pub fn add(&mut self, w: [f64; 3], e: f64, omega: f64) {
        let mut k = 0;
        for a in 0..3 {
            for b in a..3 {
                self.normal[k] += omega * w[a] * w[b];
                k += 1;
            }
            self.rhs[a] += omega * w[a] * e;
        }
        self.weighted_square += omega * e * e;
        self.weight += omega;
        self.points += 1;
    }

    /// Adds another tile's sums of the same target.
    pub fn merge(&mut self, other: &ControlSums) {
        for (a, b) in self.normal.iter_mut().zip(&other.normal) {
            *a += b;
        }
        for (a, b) in self.rhs.iter_mut().zip(&other.rhs) {
            *a += b;
        }
        self.weighted_square += other.weighted_square;
        self.weight += other.weight;
        self.points += other.points;
        self.passes += other.passes;
    }

    /// The map's offset from the target per axis, where the observing surfaces determine it.
    pub fn offset(&self) -> ControlOffset {
        offset_of(&self.normal, &self.rhs)
    }
}

/// The map's offset from a target (map minus target, metres) per axis, `None` on an axis the
/// surfaces at the target do not observe (a point on flat ground has no horizontal offset).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ControlOffset {
    pub x: Option<f64>,
    pub y: Option<f64>,
    pub z: Option<f64>,
}

/// An axis counts as observed when its direction lies within ~18° of the observed subspace.
const OBSERVED_AXIS_SHARE: f64 = 0.9;
/// Directions whose weight is below this share of the largest are not observed: a façade seen
/// at 60° off its normal by the road's slope still counts, a road's 1 % cross-fall does not
/// make its height a horizontal observation.
const OBSERVED_DIRECTION_SHARE: f64 = 0.05;

/// Least squares for `d` in `N d = r` restricted to the directions `N` observes.
fn offset_of(upper: &[f64; 6], rhs: &[f64; 3]) -> ControlOffset {
    let [xx, xy, xz, yy, yz, zz] = *upper;
    let n = nalgebra::Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz);
    let eigen = n.symmetric_eigen();
    let largest = eigen.eigenvalues.iter().cloned().fold(0.0, f64::max);
    if largest <= 0.0 {
        return ControlOffset::default();
    }
    let r = nalgebra::Vector3::from(*rhs);
    let mut d = nalgebra::Vector3::zeros();
    let mut projector = nalgebra::Matrix3::zeros();
    for i in 0..3 {
        let lambda = eigen.eigenvalues[i];
        if lambda > OBSERVED_DIRECTION_SHARE * largest {
            let v = eigen.eigenvectors.column(i);
            d += v * (v.dot(&r) / lambda);
            projector += v * v.transpose();
        }
    }
    let axis = |a: usize| (projector[(a, a)] >= OBSERVED_AXIS_SHARE).then_some(d[a]);
    ControlOffset { x: axis(0), y: axis(1), z: axis(2) }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn observe(sums: &mut ControlSums, w: [f64; 3], offset: [f64; 3]) {
        let e = w[0] * offset[0] + w[1] * offset[1] + w[2] * offset[2];
        sums.add(w, e, 1.0);
    }

    #[test]
    fn a_point_on_flat_ground_observes_its_height_alone() {
        let mut s = ControlSums::new("g");
        for _ in 0..10 {
            observe(&mut s, [0.0, 0.0, 1.0], [0.03, -0.02, 0.007]);
        }
        let o = s.offset();
        assert_eq!((o.x, o.y), (None, None));
        assert!((o.z.unwrap() - 0.007).abs() < 1e-12);
    }

    #[test]
    fn a_facade_corner_with_the_road_observes_every_axis() {
        let truth = [0.011, -0.004, 0.006];
        let mut s = ControlSums::new("c");
        let s2 = std::f64::consts::FRAC_1_SQRT_2;
        for w in [[1.0, 0.0, 0.0], [s2, s2, 0.0], [0.0, 0.0, 1.0]] {
            for _ in 0..5 {
                observe(&mut s, w, truth);
            }
        }
        let o = s.offset();
        for (got, want) in [o.x, o.y, o.z].into_iter().zip(truth) {
            assert!((got.unwrap() - want).abs() < 1e-12, "{got:?} vs {want}");
        }
    }

    #[test]
    fn one_facade_observes_only_its_normal_axis() {
        let mut s = ControlSums::new("f");
        for _ in 0..5 {
            observe(&mut s, [0.0, 1.0, 0.0], [0.5, 0.012, 0.3]);
        }
        let o = s.offset();
        assert_eq!((o.x, o.z), (None, None));
        assert!((o.y.unwrap() - 0.012).abs() < 1e-12);
    }

    #[test]
    fn sums_of_two_tiles_merge_to_the_sums_of_one() {
        let (mut a, mut b, mut both) = (ControlSums::new("m"), ControlSums::new("m"), ControlSums::new("m"));
        for (i, w) in [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]].iter().enumerate() {
            let e = 0.001 * i as f64;
            if i == 0 { a.add(*w, e, 2.0) } else { b.add(*w, e, 2.0) }
            both.add(*w, e, 2.0);
        }
        a.merge(&b);
        assert_eq!(a, both);
    }

    #[test]
    fn variance_along_a_direction_mixes_the_axes() {
        let t = ControlTarget {
            id: "t".into(),
            position: [0.0; 3],
            sigma_m: [0.01, 0.01, 0.005],
            role: ControlRole::Control,
            plane: None,
        };
        assert!((t.variance_along([0.0, 0.0, 1.0]) - 0.005f64.powi(2)).abs() < 1e-18);
        assert!((t.variance_along([1.0, 0.0, 0.0]) - 1e-4).abs() < 1e-18);
    }
}
