//! Same-surface agreement split by the surface's orientation to the direction of travel: for
//! every true surface patch (a surface within a 15 m tile) that two or more strips saw, how far
//! each strip's points of that patch lie from the strips' mean there, and how many of the points
//! the estimation kept as observations.
//!
//! Only surfaces that face the direction of travel (pole sides, façade returns, street ends) see
//! a pose's along-track error; up-facing ones see the vertical, the façades along the street the
//! across-track. Splitting the figures this way tells which error direction is left.

use crate::stats::ClassSurfaceStripMeans;
use serde::Serialize;

/// Where a surface point's true normal faces, relative to the scanning vehicle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Orientation {
    /// Within 45° of vertical (road, sidewalks, roofs, car tops).
    Up = 0,
    /// Horizontal normal within 45° of the direction of travel (either way).
    FacingTravel = 1,
    /// Horizontal normal within 45° of across the direction of travel.
    FacingAcross = 2,
}

impl Orientation {
    pub const ALL: [Orientation; 3] = [Orientation::Up, Orientation::FacingTravel, Orientation::FacingAcross];

    /// The orientation of unit normal `n` for a vehicle travelling along `travel` (world,
    /// horizontal part used; `None` when unknown counts as across).
    pub fn of(n: [f64; 3], travel: Option<[f64; 3]>) -> Orientation {
        if n[2].abs() >= std::f64::consts::FRAC_1_SQRT_2 {
            return Orientation::Up;
        }
        let Some(v) = travel else {
            return Orientation::FacingAcross;
        };
        let along = (n[0] * v[0] + n[1] * v[1]).abs();
        let across = (n[0] * v[1] - n[1] * v[0]).abs();
        if along > across {
            Orientation::FacingTravel
        } else {
            Orientation::FacingAcross
        }
    }
}

/// Distances of strips from their patches' means (metres).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Spread {
    /// RMS over (patch, strip) pairs.
    pub rms_m: f64,
    pub p95_m: f64,
    pub max_m: f64,
    /// (patch, strip) pairs measured.
    pub pairs: usize,
}

impl Spread {
    /// The figures of sorted distances; NaN without any.
    pub fn of_sorted(d: &[f64]) -> Spread {
        if d.is_empty() {
            return Spread { rms_m: f64::NAN, p95_m: f64::NAN, max_m: f64::NAN, pairs: 0 };
        }
        let n = d.len();
        let rms = (d.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
        let p95 = d[((0.95 * n as f64).ceil() as usize).clamp(1, n) - 1];
        Spread { rms_m: rms, p95_m: p95, max_m: d[n - 1], pairs: n }
    }
}

/// [`Spread`] before (input) and after (result).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SpreadMetric {
    pub before: Spread,
    pub after: Spread,
}

/// Share of surface points the last iteration used as observations (0–1), per orientation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct UsedShares {
    pub all: f64,
    pub up: f64,
    pub facing_travel: f64,
    pub facing_across: f64,
}

/// The same-surface agreement of a campaign, overall and per orientation. Strips take part in a
/// patch with at least [`crate::CLASS_SPREAD_MIN_POINTS`] points there; the campaign's shift
/// (`campaign_shift_m`, which no strip's agreement reveals) is removed from every point first.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SurfaceAgreement {
    pub all: SpreadMetric,
    pub up: SpreadMetric,
    pub facing_travel: SpreadMetric,
    pub facing_across: SpreadMetric,
    /// From `OUT/assignments` (`precimap run --in-process --assignments`); `None` without it.
    pub points_used: Option<UsedShares>,
}

/// Per strip: the patch means keyed by (orientation, tile, surface) and, with assignments, the
/// surface points and used points per orientation.
#[derive(Clone, Debug, Default)]
pub struct AgreementTally {
    pub means: [ClassSurfaceStripMeans; 2],
    pub points: [u64; 3],
    pub used: [u64; 3],
}

impl AgreementTally {
    pub fn merge(&mut self, other: AgreementTally) {
        for (total, part) in self.means.iter_mut().zip(other.means) {
            total.merge(part);
        }
        (0..3).for_each(|k| {
            self.points[k] += other.points[k];
            self.used[k] += other.used[k];
        });
    }

    /// The figures, removing `shifts` (before, after) from every point; `with_assignments` when
    /// every strip had its assignment file.
    pub fn evaluate(&self, shifts: [[f64; 3]; 2], with_assignments: bool) -> SurfaceAgreement {
        let min = crate::CLASS_SPREAD_MIN_POINTS;
        let spread = |keep: &dyn Fn(u8) -> bool| SpreadMetric {
            before: Spread::of_sorted(&self.means[0].deviations_without_shift(min, |g| keep(g.0), shifts[0])),
            after: Spread::of_sorted(&self.means[1].deviations_without_shift(min, |g| keep(g.0), shifts[1])),
        };
        let share = |used: u64, points: u64| if points > 0 { used as f64 / points as f64 } else { f64::NAN };
        SurfaceAgreement {
            all: spread(&|_| true),
            up: spread(&|o| o == Orientation::Up as u8),
            facing_travel: spread(&|o| o == Orientation::FacingTravel as u8),
            facing_across: spread(&|o| o == Orientation::FacingAcross as u8),
            points_used: with_assignments.then(|| UsedShares {
                all: share(self.used.iter().sum(), self.points.iter().sum()),
                up: share(self.used[0], self.points[0]),
                facing_travel: share(self.used[1], self.points[1]),
                facing_across: share(self.used[2], self.points[2]),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use precimap_core::TileKey;

    #[test]
    fn orientation_follows_the_direction_of_travel() {
        let east = Some([1.0, 0.0, 0.0]);
        assert_eq!(Orientation::of([0.0, 0.0, 1.0], east), Orientation::Up);
        assert_eq!(Orientation::of([0.6, 0.0, -0.8], east), Orientation::Up);
        assert_eq!(Orientation::of([-1.0, 0.0, 0.0], east), Orientation::FacingTravel);
        assert_eq!(Orientation::of([0.0, 1.0, 0.0], east), Orientation::FacingAcross);
        assert_eq!(Orientation::of([0.0, 1.0, 0.0], Some([0.0, -1.0, 0.0])), Orientation::FacingTravel);
        assert_eq!(Orientation::of([1.0, 0.0, 0.0], None), Orientation::FacingAcross);
    }

    #[test]
    fn spread_figures_per_orientation() {
        // Two strips on an up-facing patch 2 mm apart (±1 mm from its mean), two on a patch
        // facing travel 20 mm apart (±10 mm); a third strip alone on another patch is left out.
        let mut t = AgreementTally::default();
        let tile = TileKey::of(1.0, 1.0, 15.0);
        for (orientation, surface, strip, e) in
            [(0u8, 5u32, 0u32, 0.001), (0, 5, 1, -0.001), (1, 6, 0, 0.01), (1, 6, 1, -0.01), (2, 7, 2, 0.5)]
        {
            for _ in 0..60 {
                t.means[1].add((orientation, tile, surface), strip, e);
            }
        }
        let a = t.evaluate([[0.0; 3]; 2], false);
        assert_eq!(a.all.after.pairs, 4);
        assert!((a.up.after.rms_m - 0.001).abs() < 1e-12);
        assert!((a.facing_travel.after.max_m - 0.01).abs() < 1e-12);
        assert!((a.all.after.p95_m - 0.01).abs() < 1e-12);
        assert!((a.all.after.rms_m - (0.0101f64 / 2.0 * 0.01).sqrt()).abs() < 1e-9);
        assert!(a.facing_across.after.rms_m.is_nan() && a.points_used.is_none());
    }
}
