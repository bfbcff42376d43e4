//! Mounting calibration as campaign-wide unknowns: per scanner, a boresight (three small angles
//! about the vehicle body's axes), a lever-arm offset (body frame) and a range offset, each
//! shared by every strip of that scanner (docs/design/calibration.md).
//!
//! A point measured with body attitude `R` from the scan head `t0 = c + R·ℓ` at `p = t0 + r`
//! has the body-frame beam `r_b = Rᵀ·r`. With calibration `(β, δℓ, δρ)` it is
//! `p' = t0 + R·δℓ + R·Exp(β)·(r_b + δρ·r̂_b)`: the range grows along the beam, the beam turns
//! about the head, and the head moves in the body frame. Its derivatives, for an observation
//! `w·p` with `m` the world-frame beam, are `Rᵀ(m × w)` (boresight), `Rᵀw` (lever arm) and
//! `m̂·w` (range offset).

use crate::geom::SmallRotation;
use serde::{Deserialize, Serialize};

/// A kind of calibration unknown ([`CalibrationOptions::estimate`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CalibrationUnknown {
    /// Roll, pitch and yaw of the scanner against the body (three unknowns).
    Boresight,
    /// The scan head's offset in the body frame (three unknowns).
    LeverArm,
    /// A constant added to every range (one unknown).
    RangeOffset,
}

impl CalibrationUnknown {
    pub fn count(self) -> usize {
        match self {
            Self::Boresight | Self::LeverArm => 3,
            Self::RangeOffset => 1,
        }
    }

    /// The unknowns' names, as the report lists them.
    pub fn names(self) -> &'static [&'static str] {
        match self {
            Self::Boresight => &["boresight_roll", "boresight_pitch", "boresight_yaw"],
            Self::LeverArm => &["lever_arm_x", "lever_arm_y", "lever_arm_z"],
            Self::RangeOffset => &["range_offset"],
        }
    }
}

/// What a campaign estimates of its scanners' mounting, and how firmly it must be determined.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CalibrationOptions {
    /// The kinds to estimate per scanner; empty (the default) estimates none and takes the
    /// manifest's mounting as exact.
    pub estimate: Vec<CalibrationUnknown>,
    /// σ of the prior on each kind, centred on the manifest's values: loose, it only keeps the
    /// system regular where the strips say nothing.
    pub prior_boresight_deg: f64,
    pub prior_lever_arm_m: f64,
    pub prior_range_offset_m: f64,
    /// An unknown whose posterior σ exceeds its tolerance is not determined by the campaign's
    /// geometry (a lever arm without turns, a boresight yaw along straight streets only): it is
    /// held at the manifest's value and the report says why.
    pub tolerance_boresight_deg: f64,
    pub tolerance_lever_arm_m: f64,
    pub tolerance_range_offset_m: f64,
    /// An unknown of which the trajectories' corrections can take up all but this share of what
    /// the observations say of it (the report's `separation`) is not
    /// separated from the trajectories' errors, and is held at the manifest's value too.
    pub min_separation: f64,
}

impl Default for CalibrationOptions {
    fn default() -> Self {
        Self {
            estimate: Vec::new(),
            prior_boresight_deg: 0.5,
            prior_lever_arm_m: 0.1,
            prior_range_offset_m: 0.05,
            tolerance_boresight_deg: 0.005,
            tolerance_lever_arm_m: 0.005,
            tolerance_range_offset_m: 0.005,
            min_separation: 0.05,
        }
    }
}

impl CalibrationOptions {
    pub fn is_empty(&self) -> bool {
        self.estimate.is_empty()
    }

    /// The prior's σ and the tolerance of one kind, in radians or metres.
    pub fn prior_and_tolerance(&self, kind: CalibrationUnknown) -> (f64, f64) {
        match kind {
            CalibrationUnknown::Boresight => {
                (self.prior_boresight_deg.to_radians(), self.tolerance_boresight_deg.to_radians())
            }
            CalibrationUnknown::LeverArm => (self.prior_lever_arm_m, self.tolerance_lever_arm_m),
            CalibrationUnknown::RangeOffset => (self.prior_range_offset_m, self.tolerance_range_offset_m),
        }
    }

    /// The layout of the unknowns for `scanners` scanners.
    pub fn layout(&self, scanners: usize) -> CalibrationLayout {
        let mut kinds = self.estimate.clone();
        kinds.sort();
        kinds.dedup();
        CalibrationLayout { kinds, scanners }
    }
}

/// Where each unknown sits in the campaign's calibration vector: scanner after scanner, each
/// with its kinds in [`CalibrationUnknown`] order.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CalibrationLayout {
    pub kinds: Vec<CalibrationUnknown>,
    pub scanners: usize,
}

impl CalibrationLayout {
    /// Unknowns per scanner.
    pub fn per_scanner(&self) -> usize {
        self.kinds.iter().map(|k| k.count()).sum()
    }

    /// All unknowns.
    pub fn len(&self) -> usize {
        self.per_scanner() * self.scanners
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The kind and the component (0–2) of unknown `j` of a scanner's block.
    pub fn kind_of(&self, j: usize) -> (CalibrationUnknown, usize) {
        let mut start = 0;
        for &k in &self.kinds {
            if j < start + k.count() {
                return (k, j - start);
            }
            start += k.count();
        }
        panic!("calibration unknown {j} beyond the {} of a scanner", self.per_scanner())
    }

    /// Writes the derivatives of an observation `w·p` of a point with world-frame beam `m`
    /// (from its scan head) and body attitude `rotation` into `out` (one per scanner unknown).
    #[inline]
    pub fn jacobian(&self, rotation: &[[f64; 3]; 3], m: [f64; 3], w: [f64; 3], out: &mut [f64]) {
        let mut j = 0;
        for &k in &self.kinds {
            match k {
                CalibrationUnknown::Boresight => {
                    let mw = cross(m, w);
                    for a in 0..3 {
                        out[j + a] = rotation[0][a] * mw[0] + rotation[1][a] * mw[1] + rotation[2][a] * mw[2];
                    }
                    j += 3;
                }
                CalibrationUnknown::LeverArm => {
                    for a in 0..3 {
                        out[j + a] = rotation[0][a] * w[0] + rotation[1][a] * w[1] + rotation[2][a] * w[2];
                    }
                    j += 3;
                }
                CalibrationUnknown::RangeOffset => {
                    let n = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
                    out[j] = if n > 0.0 { (m[0] * w[0] + m[1] * w[1] + m[2] * w[2]) / n } else { 0.0 };
                    j += 1;
                }
            }
        }
    }
}

/// One scanner's mounting correction: what is added to the manifest's mounting.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ScannerCalibration {
    /// Roll, pitch, yaw about the body axes, radians.
    pub boresight_rad: [f64; 3],
    pub lever_arm_m: [f64; 3],
    pub range_offset_m: f64,
}

impl ScannerCalibration {
    pub fn is_zero(&self) -> bool {
        *self == Self::default()
    }

    /// Reads the scanner's block of a calibration vector laid out by `layout`.
    pub fn from_block(layout: &CalibrationLayout, block: &[f64]) -> Self {
        let mut s = Self::default();
        for (j, &v) in block.iter().enumerate().take(layout.per_scanner()) {
            match layout.kind_of(j) {
                (CalibrationUnknown::Boresight, a) => s.boresight_rad[a] = v,
                (CalibrationUnknown::LeverArm, a) => s.lever_arm_m[a] = v,
                (CalibrationUnknown::RangeOffset, _) => s.range_offset_m = v,
            }
        }
        s
    }

    /// The scanner's block of a calibration vector laid out by `layout`.
    pub fn to_block(&self, layout: &CalibrationLayout) -> Vec<f64> {
        (0..layout.per_scanner())
            .map(|j| match layout.kind_of(j) {
                (CalibrationUnknown::Boresight, a) => self.boresight_rad[a],
                (CalibrationUnknown::LeverArm, a) => self.lever_arm_m[a],
                (CalibrationUnknown::RangeOffset, _) => self.range_offset_m,
            })
            .collect()
    }

    /// `v` (a world-frame direction, e.g. a normal) turned by the boresight alone.
    #[inline]
    pub fn turn(&self, rotation: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
        let body: [f64; 3] =
            std::array::from_fn(|a| rotation[0][a] * v[0] + rotation[1][a] * v[1] + rotation[2][a] * v[2]);
        let turned = SmallRotation::new(self.boresight_rad).apply(body);
        std::array::from_fn(|a| rotation[a][0] * turned[0] + rotation[a][1] * turned[1] + rotation[a][2] * turned[2])
    }

    /// The calibrated scan head's shift and beam of a point measured with body attitude
    /// `rotation` along the world-frame beam `r` (both from the manifest's mounting).
    #[inline]
    pub fn apply(&self, rotation: &[[f64; 3]; 3], r: [f64; 3]) -> ([f64; 3], [f64; 3]) {
        let mul_t = |v: [f64; 3]| -> [f64; 3] {
            std::array::from_fn(|a| rotation[0][a] * v[0] + rotation[1][a] * v[1] + rotation[2][a] * v[2])
        };
        let mul = |v: [f64; 3]| -> [f64; 3] {
            std::array::from_fn(|a| rotation[a][0] * v[0] + rotation[a][1] * v[1] + rotation[a][2] * v[2])
        };
        let mut body = mul_t(r);
        let range = (body[0] * body[0] + body[1] * body[1] + body[2] * body[2]).sqrt();
        if range > 0.0 {
            let scale = 1.0 + self.range_offset_m / range;
            body = body.map(|v| v * scale);
        }
        let beam = mul(SmallRotation::new(self.boresight_rad).apply(body));
        (mul(self.lever_arm_m), beam)
    }
}

impl ScannerCalibration {
    /// The calibration at body attitude `rotation`, in the world frame.
    pub fn in_world(&self, rotation: &[[f64; 3]; 3]) -> WorldMounting {
        let turn = SmallRotation::new(self.boresight_rad);
        let mul_t = |v: [f64; 3]| -> [f64; 3] {
            std::array::from_fn(|a| rotation[0][a] * v[0] + rotation[1][a] * v[1] + rotation[2][a] * v[2])
        };
        let mul = |v: [f64; 3]| -> [f64; 3] {
            std::array::from_fn(|a| rotation[a][0] * v[0] + rotation[a][1] * v[1] + rotation[a][2] * v[2])
        };
        let columns: [[f64; 3]; 3] =
            std::array::from_fn(|b| mul(turn.apply(mul_t(std::array::from_fn(|a| (a == b) as u8 as f64)))));
        WorldMounting {
            turn: std::array::from_fn(|a| std::array::from_fn(|b| columns[b][a])),
            head: mul(self.lever_arm_m),
            range_offset_m: self.range_offset_m,
        }
    }
}

/// A scanner's calibration at one body attitude `R`, in the world frame: the beam's turn
/// `R·Exp(β)·Rᵀ` (rows), the scan head's shift `R·δℓ` and the range offset. A point between two
/// anchors takes the linear interpolation of the two anchors' values ([`Self::lerp`]), as it
/// does of their corrections: per point no trigonometry and no attitude, and the boresight's
/// and lever arm's derivatives are those of [`CalibrationLayout::jacobian`] at the interpolated
/// attitude `(1−λ)R_i + λR_i+1`, linear in `λ` (docs/design/calibration.md).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldMounting {
    pub turn: [[f64; 3]; 3],
    pub head: [f64; 3],
    pub range_offset_m: f64,
}

impl WorldMounting {
    /// `(1−λ)·self + λ·next`.
    #[inline]
    pub fn lerp(&self, next: &Self, lambda: f64) -> Self {
        let mix = |a: f64, b: f64| a + (b - a) * lambda;
        Self {
            turn: std::array::from_fn(|r| std::array::from_fn(|c| mix(self.turn[r][c], next.turn[r][c]))),
            head: std::array::from_fn(|a| mix(self.head[a], next.head[a])),
            range_offset_m: self.range_offset_m,
        }
    }

    /// `v` (a world-frame direction, e.g. a normal) turned by the boresight alone.
    #[inline]
    pub fn turn(&self, v: [f64; 3]) -> [f64; 3] {
        let t = &self.turn;
        std::array::from_fn(|a| t[a][0] * v[0] + t[a][1] * v[1] + t[a][2] * v[2])
    }

    /// The calibrated scan head's shift and beam of a point along the world-frame beam `r` (both
    /// from the manifest's mounting), as [`ScannerCalibration::apply`].
    #[inline]
    pub fn apply(&self, r: [f64; 3]) -> ([f64; 3], [f64; 3]) {
        let range = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
        let scale = if range > 0.0 { 1.0 + self.range_offset_m / range } else { 1.0 };
        (self.head, self.turn(r).map(|v| v * scale))
    }
}

/// The body attitude of a rotation vector (`Exp(θ)`) as rows.
#[inline]
pub fn attitude_matrix(theta: [f32; 3]) -> [[f64; 3]; 3] {
    let rotation = SmallRotation::new(theta.map(f64::from));
    let columns = [rotation.apply([1.0, 0.0, 0.0]), rotation.apply([0.0, 1.0, 0.0]), rotation.apply([0.0, 0.0, 1.0])];
    std::array::from_fn(|a| std::array::from_fn(|b| columns[b][a]))
}

#[inline]
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout_all() -> CalibrationLayout {
        CalibrationOptions {
            estimate: vec![
                CalibrationUnknown::RangeOffset,
                CalibrationUnknown::Boresight,
                CalibrationUnknown::LeverArm,
            ],
            ..Default::default()
        }
        .layout(2)
    }

    /// The derivatives equal the finite differences of the calibrated point, projected on `w`.
    #[test]
    fn jacobian_matches_finite_differences() {
        let layout = layout_all();
        assert_eq!(layout.per_scanner(), 7);
        assert_eq!(layout.len(), 14);
        let rotation = attitude_matrix([0.1, -0.2, 2.5]);
        let r = [3.0, -12.0, -1.5];
        let w = [0.3f64, -0.2, 0.93];
        let n = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
        let w = w.map(|v| v / n);
        let mut g = vec![0.0; 7];
        layout.jacobian(&rotation, r, w, &mut g);
        let point = |block: &[f64]| {
            let (head, beam) = ScannerCalibration::from_block(&layout, block).apply(&rotation, r);
            (0..3).map(|a| (head[a] + beam[a]) * w[a]).sum::<f64>()
        };
        let h = 1e-6;
        for j in 0..7 {
            let mut plus = vec![0.0; 7];
            let mut minus = vec![0.0; 7];
            plus[j] = h;
            minus[j] = -h;
            let numeric = (point(&plus) - point(&minus)) / (2.0 * h);
            assert!((numeric - g[j]).abs() < 1e-6, "unknown {j}: {numeric} against {}", g[j]);
        }
    }

    /// At an anchor the world-frame form corrects a point as the body-frame one does.
    #[test]
    fn world_mounting_equals_the_body_frame_form() {
        let s = ScannerCalibration {
            boresight_rad: [1e-3, -2e-3, 3e-3],
            lever_arm_m: [0.01, 0.02, -0.03],
            range_offset_m: 0.004,
        };
        let rotation = attitude_matrix([0.1, -0.2, 2.5]);
        let (r, n) = ([3.0, -12.0, -1.5], [0.3, -0.2, 0.93]);
        let world = s.in_world(&rotation);
        let ((head, beam), (h2, b2)) = (s.apply(&rotation, r), world.apply(r));
        for a in 0..3 {
            assert!((head[a] - h2[a]).abs() < 1e-15 && (beam[a] - b2[a]).abs() < 1e-12, "{beam:?} {b2:?}");
            assert!((s.turn(&rotation, n)[a] - world.turn(n)[a]).abs() < 1e-15);
        }
        // Half-way between two attitudes: the mean of the two.
        let next = s.in_world(&attitude_matrix([0.1, -0.2, 2.6]));
        let half = world.lerp(&next, 0.5);
        for a in 0..3 {
            assert!((half.head[a] - 0.5 * (world.head[a] + next.head[a])).abs() < 1e-15);
        }
    }

    #[test]
    fn blocks_round_trip_and_zero_changes_nothing() {
        let layout = layout_all();
        let s = ScannerCalibration {
            boresight_rad: [1e-3, -2e-3, 3e-3],
            lever_arm_m: [0.01, 0.02, -0.03],
            range_offset_m: 0.004,
        };
        assert_eq!(ScannerCalibration::from_block(&layout, &s.to_block(&layout)), s);
        let rotation = attitude_matrix([0.0, 0.0, 1.0]);
        let r = [1.0, 2.0, 3.0];
        let (head, beam) = ScannerCalibration::default().apply(&rotation, r);
        assert_eq!(head, [0.0; 3]);
        for a in 0..3 {
            assert!((beam[a] - r[a]).abs() < 1e-12);
        }
        // The range offset lengthens the beam by itself.
        let longer = ScannerCalibration { range_offset_m: 0.01, ..Default::default() }.apply(&rotation, r).1;
        let length = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        assert!((length(longer) - length(r) - 0.01).abs() < 1e-12);
    }
}
