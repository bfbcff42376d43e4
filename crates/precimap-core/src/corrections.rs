//! Pose corrections at anchors (docs/design/estimation.md, "Unknowns"). Anchor `i` sits at arc
//! length `i·Δ` along its trajectory; a measurement at anchor coordinate `u = s/Δ` takes the
//! linear interpolation of the corrections at `⌊u⌋` and `⌊u⌋+1`. A correction moves a point as
//! `p' = t0 + δt + Exp(δθ)·r` (t0 scan-head position, r measurement vector).

use crate::geom::rotate_small;
use crate::histogram::LogBins;
use serde::{Deserialize, Serialize};

/// `[δtx, δty, δtz, δθx, δθy, δθz]`: translation in metres, rotation vector in radians, world frame.
pub type Correction = [f64; 6];

/// Upper triangle of a symmetric 6×6 matrix, row-major: how normal-equation blocks travel and
/// how [`AnchorCovariance`] is stored.
pub type Sym6 = [f64; 21];

/// Index of (i, j), i ≤ j, in a [`Sym6`].
#[inline]
pub const fn sym_index(i: usize, j: usize) -> usize {
    // Rows hold 6, 5, 4, 3, 2, 1 entries.
    i * 6 - i * (i + 1) / 2 + j
}

/// The posterior covariance of one anchor's correction (`[δt; δθ]`, metres and radians, world
/// frame): the upper triangle of the symmetric 6×6 matrix, row by row (21 values).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnchorCovariance(pub Sym6);

impl AnchorCovariance {
    /// Index of entry (a, b), either order.
    #[inline]
    fn index(a: usize, b: usize) -> usize {
        sym_index(a.min(b), a.max(b))
    }

    /// From a full symmetric matrix given by `entry(a, b)`; only a ≤ b is read.
    pub fn from_fn(mut entry: impl FnMut(usize, usize) -> f64) -> Self {
        let mut out = [0.0; 21];
        for a in 0..6 {
            for b in a..6 {
                out[Self::index(a, b)] = entry(a, b);
            }
        }
        Self(out)
    }

    /// Standard deviations alone: a covariance without correlations.
    pub fn from_sigma(sigma: [f64; 6]) -> Self {
        Self::from_fn(|a, b| if a == b { sigma[a] * sigma[a] } else { 0.0 })
    }

    #[inline]
    pub fn get(&self, a: usize, b: usize) -> f64 {
        self.0[Self::index(a, b)]
    }

    /// The world frame's standard deviations (`√` of the diagonal, negative rounding clamped).
    pub fn sigma(&self) -> [f64; 6] {
        std::array::from_fn(|a| self.get(a, a).max(0.0).sqrt())
    }

    /// Standard deviations along three unit axes, of the translation (`offset` 0) or of the
    /// rotation (`offset` 3): `√(eᵀ Σ e)` for each axis `e` (world-frame components).
    pub fn sigma_along(&self, offset: usize, axes: &[[f64; 3]; 3]) -> [f64; 3] {
        std::array::from_fn(|k| {
            let e = axes[k];
            let mut v = 0.0;
            for a in 0..3 {
                for b in 0..3 {
                    v += e[a] * self.get(offset + a, offset + b) * e[b];
                }
            }
            v.max(0.0).sqrt()
        })
    }
}

/// Corrections of one trajectory for the contiguous anchor range `first_anchor..first_anchor+len`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryCorrections {
    pub first_anchor: u32,
    pub values: Vec<Correction>,
}

impl TrajectoryCorrections {
    /// All-zero corrections for anchors `first..=last`.
    pub fn zeros(first: u32, last: u32) -> Self {
        Self { first_anchor: first, values: vec![[0.0; 6]; (last - first + 1) as usize] }
    }

    pub fn last_anchor(&self) -> u32 {
        self.first_anchor + self.values.len() as u32 - 1
    }

    /// Correction at anchor `i` (clamped to the range: beyond its ends a trajectory keeps the
    /// end anchor's correction).
    #[inline]
    pub fn anchor(&self, i: u32) -> &Correction {
        let k = i.saturating_sub(self.first_anchor) as usize;
        &self.values[k.min(self.values.len() - 1)]
    }

    /// Interpolated correction at anchor `i` plus fraction `lambda`.
    #[inline]
    pub fn at(&self, i: u32, lambda: f32) -> Correction {
        let a = self.anchor(i);
        let b = self.anchor(i + 1);
        let l = lambda as f64;
        let mut out = [0.0; 6];
        for k in 0..6 {
            out[k] = a[k] + (b[k] - a[k]) * l;
        }
        out
    }

    /// Largest change between two correction sets of the same trajectory, as the displacement of
    /// a point at `range_m` from the scan head: `|Δδt| + range·|Δδθ|`.
    pub fn max_change_m(&self, other: &Self, range_m: f64) -> f64 {
        self.changes(other, range_m).max_m
    }

    /// Every anchor's change against `other` (as [`Self::max_change_m`]), over the anchors of
    /// both sets, summarised in one pass: the largest, where it is, and the histogram.
    pub fn changes(&self, other: &Self, range_m: f64) -> Changes {
        let first = self.first_anchor.min(other.first_anchor);
        let last = self.last_anchor().max(other.last_anchor());
        let mut out = Changes { max_m: 0.0, max_anchor: first, histogram: ChangeHistogram::default() };
        for i in first..=last {
            let (a, b) = (self.anchor(i), other.anchor(i));
            let dt = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
            let dr = ((a[3] - b[3]).powi(2) + (a[4] - b[4]).powi(2) + (a[5] - b[5]).powi(2)).sqrt();
            let change = dt + range_m * dr;
            // A NaN change never becomes the largest (as `f64::max` ignores it); the histogram
            // counts it as the largest bin.
            if change > out.max_m {
                (out.max_m, out.max_anchor) = (change, i);
            }
            out.histogram.add(change);
        }
        out
    }
}

/// The per-anchor changes between two correction sets ([`TrajectoryCorrections::changes`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Changes {
    pub max_m: f64,
    /// The first anchor with the largest change; the first anchor of either set when nothing
    /// changed.
    pub max_anchor: u32,
    pub histogram: ChangeHistogram,
}

/// Distribution of the per-anchor change between two iterations (the displacement of a point at
/// the nominal range, as [`TrajectoryCorrections::max_change_m`]), in logarithmic bins of a tenth
/// of a decade from 1 µm to 10 m. Mergeable across trajectories, so the job framework's planner
/// reports the same quantiles as the in-process driver. The maximum alone cannot tell a few
/// wandering anchors (a trajectory's end) from a whole campaign still drifting; the median can.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChangeHistogram {
    /// `counts[0]`: below 1 µm; `counts[k]` for k ≥ 1: `[10^((k−1)/10), 10^(k/10))` µm; the last
    /// bin also holds everything larger. Empty until the first value.
    pub counts: Vec<u64>,
}

impl ChangeHistogram {
    /// 1 µm … 10 m in tenths of a decade: 72 bins, few enough to travel in every solve result.
    fn bins() -> LogBins {
        LogBins::spanning(1e-6, 10.0, 10f64.powf(0.1))
    }

    pub fn add(&mut self, change_m: f64) {
        let bins = Self::bins();
        if self.counts.is_empty() {
            self.counts = vec![0; bins.count];
        }
        // A non-finite change is as bad as the largest.
        self.counts[bins.index(if change_m.is_nan() { f64::INFINITY } else { change_m })] += 1;
    }

    pub fn merge(&mut self, other: &ChangeHistogram) {
        if other.counts.is_empty() {
            return;
        }
        if self.counts.is_empty() {
            self.counts = vec![0; Self::bins().count];
        }
        LogBins::merge(&mut self.counts, &other.counts);
    }

    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// Upper edge of the bin holding the `q`-quantile (0 ≤ q ≤ 1): at most 26 % above the true
    /// quantile, never below it. 0 when empty.
    pub fn quantile_m(&self, q: f64) -> f64 {
        LogBins::quantile_bin(&self.counts, q).map_or(0.0, |k| Self::bins().upper_edge(k))
    }
}

impl TrajectoryCorrections {
    /// Per-anchor changes against `other` (see [`Self::max_change_m`]) as a histogram.
    pub fn change_histogram(&self, other: &Self, range_m: f64) -> ChangeHistogram {
        self.changes(other, range_m).histogram
    }
}

/// Applies a correction: `t0 + δt + Exp(δθ)·r`.
#[inline]
pub fn apply(t0: [f64; 3], r: [f64; 3], c: &Correction) -> [f64; 3] {
    let rr = rotate_small([c[3], c[4], c[5]], r);
    [t0[0] + c[0] + rr[0], t0[1] + c[1] + rr[1], t0[2] + c[2] + rr[2]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_anchor_covariance_is_read_in_any_frame() {
        // Translation: σ 1 mm in x, 3 mm in y, 2 mm in z, x and y correlated by ρ = 0.5.
        let mut full = [[0.0; 6]; 6];
        full[0][0] = 1e-6;
        full[1][1] = 9e-6;
        full[2][2] = 4e-6;
        full[0][1] = 0.5 * 1e-3 * 3e-3;
        full[1][0] = full[0][1];
        full[5][5] = 0.25e-8;
        full[3][5] = 0.7;
        full[5][3] = 0.7;
        let c = AnchorCovariance::from_fn(|a, b| full[a][b]);
        for a in 0..6 {
            for b in 0..6 {
                assert_eq!(c.get(a, b), full[a][b], "({a}, {b})");
            }
        }
        let s = c.sigma();
        assert!((s[0] - 1e-3).abs() < 1e-15 && (s[1] - 3e-3).abs() < 1e-15 && (s[5] - 0.5e-4).abs() < 1e-15);
        // Along the world axes: the diagonal. Along the diagonal of x and y: (σx² + σy² + 2ρσxσy)/2.
        let world = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(c.sigma_along(0, &world), [s[0], s[1], s[2]]);
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let turned = c.sigma_along(0, &[[h, h, 0.0], [-h, h, 0.0], [0.0, 0.0, 1.0]]);
        let expect = |cross: f64| ((1e-6 + 9e-6 + cross) / 2.0f64).sqrt();
        assert!((turned[0] - expect(2.0 * full[0][1])).abs() < 1e-15, "{turned:?}");
        assert!((turned[1] - expect(-2.0 * full[0][1])).abs() < 1e-15, "{turned:?}");
        assert_eq!(AnchorCovariance::from_sigma(s).sigma(), s);
    }

    #[test]
    fn interpolation_and_clamping() {
        let c = TrajectoryCorrections { first_anchor: 10, values: vec![[0.0; 6], [1.0, 2.0, 0.0, 0.0, 0.0, 0.1]] };
        let v = c.at(10, 0.25);
        assert!((v[0] - 0.25).abs() < 1e-12 && (v[1] - 0.5).abs() < 1e-12 && (v[5] - 0.025).abs() < 1e-9);
        assert_eq!(c.at(11, 0.5)[0], 1.0);
        assert_eq!(c.at(3, 0.5)[0], 0.0);
        let z = TrajectoryCorrections::zeros(10, 11);
        assert!((c.max_change_m(&z, 10.0) - (5f64.sqrt() + 1.0)).abs() < 1e-12);
        let changes = c.changes(&z, 10.0);
        let (largest, at) = (changes.max_m, changes.max_anchor);
        assert_eq!(largest, c.max_change_m(&z, 10.0));
        assert!(at >= c.first_anchor && at <= c.last_anchor());
        let moved = c.anchor(at);
        let dt = (moved[0].powi(2) + moved[1].powi(2) + moved[2].powi(2)).sqrt();
        let dr = (moved[3].powi(2) + moved[4].powi(2) + moved[5].powi(2)).sqrt();
        assert_eq!(dt + 10.0 * dr, largest);
    }

    #[test]
    fn change_quantiles_bound_the_true_ones_from_above() {
        let mut h = ChangeHistogram::default();
        assert_eq!(h.quantile_m(0.5), 0.0);
        // 1, 2, …, 100 mm.
        for k in 1..=100 {
            h.add(k as f64 * 1e-3);
        }
        let mut other = ChangeHistogram::default();
        other.add(f64::NAN);
        other.add(0.0);
        h.merge(&other);
        assert_eq!(h.total(), 102);
        for (q, truth) in [(0.5, 0.050), (0.9, 0.091), (0.005, 0.0)] {
            let got = h.quantile_m(q);
            assert!(got >= truth && got <= truth.max(1e-6) * 1.26, "q {q}: {got} for {truth}");
        }
        // The NaN counts as the largest change.
        assert!(h.quantile_m(1.0) > 1.0);
        let c = TrajectoryCorrections { first_anchor: 0, values: vec![[0.0; 6], [0.01, 0.0, 0.0, 0.0, 0.0, 0.0]] };
        let z = TrajectoryCorrections::zeros(0, 1);
        let hz = c.change_histogram(&z, 10.0);
        assert_eq!(hz.total(), 2);
        assert!(hz.quantile_m(1.0) >= 0.01 && hz.quantile_m(1.0) < 0.0126);
        assert_eq!(hz.quantile_m(0.5), 1e-6);
    }

    #[test]
    fn apply_rotates_about_scan_head() {
        let c = [0.1, 0.0, 0.0, 0.0, 0.0, std::f64::consts::FRAC_PI_2];
        let p = apply([10.0, 0.0, 0.0], [1.0, 0.0, 0.0], &c);
        assert!((p[0] - 10.1).abs() < 1e-12 && (p[1] - 1.0).abs() < 1e-12);
    }
}
