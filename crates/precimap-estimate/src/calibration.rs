//! The scanners' mounting calibration in estimation (docs/design/calibration.md): what a tile
//! needs to apply it and to linearise it ([`TileCalibration`]), the cross terms between anchors
//! and calibration unknowns and the calibration's own normal equations an anchor interval's
//! observations add ([`interval_terms`], [`CalibrationNormals`]), and the exact joint solve of
//! the calibration with every trajectory's chain by the Schur complement
//! ([`solve_calibration`]).

use precimap_core::{CalibrationLayout, CalibrationUnknown, ScannerCalibration};
use serde::{Deserialize, Serialize};

/// What a tile task needs of the calibration: the layout of the unknowns, each strip's scanner
/// (by the strip index chunks carry) and the current calibration of every scanner.
#[derive(Clone, Copy, Debug)]
pub struct TileCalibration<'a> {
    pub layout: &'a CalibrationLayout,
    pub scanner_of_strip: &'a [u32],
    pub scanners: &'a [ScannerCalibration],
}

impl TileCalibration<'_> {
    /// The scanner of `strip` and its calibration (`None` for a strip beyond the map, which the
    /// caller reports).
    pub fn of_strip(&self, strip: u32) -> Option<(u32, &ScannerCalibration)> {
        let s = *self.scanner_of_strip.get(strip as usize)?;
        Some((s, self.scanners.get(s as usize)?))
    }
}

/// The calibration's normal equations summed over observations: `H_cc` (full, row-major) and
/// `b_c`, over the campaign's `K` unknowns.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CalibrationNormals {
    pub h: Vec<f64>,
    pub b: Vec<f64>,
}

impl CalibrationNormals {
    pub fn zeros(k: usize) -> Self {
        Self { h: vec![0.0; k * k], b: vec![0.0; k] }
    }

    pub fn len(&self) -> usize {
        self.b.len()
    }

    pub fn is_empty(&self) -> bool {
        self.b.is_empty()
    }

    /// Adds `other` (an empty one adds nothing; one of another size is a caller's error).
    pub fn add(&mut self, other: &CalibrationNormals) {
        if other.is_empty() {
            return;
        }
        if self.is_empty() {
            *self = Self::zeros(other.len());
        }
        for (a, b) in self.h.iter_mut().zip(&other.h) {
            *a += b;
        }
        for (a, b) in self.b.iter_mut().zip(&other.b) {
            *a += b;
        }
    }

    /// One observation of scanner block `offset` with derivatives `gc`, weight `w` and
    /// weighted residual `we`.
    #[cfg(test)]
    pub(crate) fn add_observation(&mut self, offset: usize, gc: &[f64], we: f64, w: f64) {
        let k = self.len();
        for (i, gi) in gc.iter().enumerate() {
            let row = (offset + i) * k + offset;
            for (j, gj) in gc.iter().enumerate() {
                self.h[row + j] += w * gi * gj;
            }
            self.b[offset + i] -= we * gi;
        }
    }
}

/// The boresight's and lever arm's derivatives of an observation as a linear map of its anchor
/// Jacobian row `g = [w, m × w]` (translation, rotation about the scan head): at body attitude
/// `R` they are `Rᵀ(m × w)` and `Rᵀw` ([`CalibrationLayout::jacobian`]), so each is a column of
/// `R` dotted with one half of `g`. One row per such unknown of a scanner's block, in the
/// layout's order (the range offset, last, is not such a map): the half of `g` it reads (0:
/// translation, 3: rotation) and the column of `R`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct AttitudeRows {
    rows: [(usize, [f64; 3]); 6],
    len: usize,
}

impl AttitudeRows {
    pub(crate) fn new(layout: &CalibrationLayout, rotation: &[[f64; 3]; 3]) -> Self {
        let mut rows = [(0, [0.0; 3]); 6];
        let mut len = 0;
        for &kind in &layout.kinds {
            let half = match kind {
                CalibrationUnknown::Boresight => 3,
                CalibrationUnknown::LeverArm => 0,
                CalibrationUnknown::RangeOffset => continue,
            };
            for a in 0..3 {
                rows[len] = (half, [rotation[0][a], rotation[1][a], rotation[2][a]]);
                len += 1;
            }
        }
        Self { rows, len }
    }

    /// The unknowns this map gives (the scanner's block but its range offset).
    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Row `j` of `[L_i, L_i+1]` (this map at anchor `i`, `next` at anchor `i+1`) dotted with
    /// the 12-vector `v` over the two anchors.
    #[inline]
    fn dot(&self, next: &Self, j: usize, v: impl Fn(usize) -> f64) -> f64 {
        let ((half, a), (_, b)) = (self.rows[j], next.rows[j]);
        (0..3).map(|k| a[k] * v(half + k) + b[k] * v(6 + half + k)).sum()
    }
}

/// One anchor interval's calibration terms. Between anchors `i` and `i+1` a point's body
/// attitude is `(1−λ)R_i + λR_i+1` ([`precimap_core::calibration::WorldMounting`]), so the
/// boresight's and lever arm's columns of each of its observations are `L·J` with
/// `L = [L_i, L_i+1]` (`at`, `next`: [`AttitudeRows`]) and `J = [(1−λ)g, λg]` its anchor columns:
/// from the interval's block `K = Σ w·J·Jᵀ` and right-hand side `r = −Σ w·e·J`
/// ([`crate::blocks::IntervalMoments::block`]) the cross terms are `K·Lᵀ`, the calibration's own
/// `L·K·Lᵀ` and `L·r`, exactly and with no product per point. The range offset's column (per
/// point, `m̂·w`) comes as its cross column `range` (`Σ w·J·g_ρ`); its own terms are the
/// caller's. Writes the cross terms into `cross` (12 rows, the scanner's unknowns as columns)
/// and adds the rest to `h` (upper triangle of the scanner's block, row-major) and `b`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn interval_terms(
    block: &[[f64; 12]; 12],
    rhs: &[f64; 12],
    at: &AttitudeRows,
    next: &AttitudeRows,
    range: Option<&[f64; 12]>,
    cross: &mut [[f64; 7]; 12],
    h: &mut [f64; 28],
    b: &mut [f64; 7],
) {
    let n = at.len();
    let k = n + range.is_some() as usize;
    for (c, row) in block.iter().enumerate() {
        for j in 0..n {
            cross[c][j] = at.dot(next, j, |q| row[q]);
        }
        if let Some(range) = range {
            cross[c][n] = range[c];
        }
    }
    let mut index = 0;
    for i in 0..k {
        if i == n {
            // The range offset's own terms are added per point.
            break;
        }
        for j in i..k {
            h[index] += at.dot(next, i, |q| cross[q][j]);
            index += 1;
        }
        b[i] += at.dot(next, i, |q| rhs[q]);
    }
}

/// One trajectory's share of the joint solve. With `C` its cross terms (anchors × unknowns, after
/// the same transformations as its own system) and `H` its system, the solve found
/// `x₀ = H⁻¹b` and `Y = H⁻¹C`; eliminating the trajectory leaves `H_cc − CᵀY` and `b_c − Cᵀx₀`
/// for the calibration, and a calibration step `δc` moves its corrections by `−Y·δc`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationShare {
    /// `H_cc` and `b_c` from this trajectory's observations.
    pub normals: CalibrationNormals,
    /// `CᵀY` (unknowns × unknowns, row-major).
    pub schur: Vec<f64>,
    /// `Cᵀx₀`.
    pub rhs: Vec<f64>,
    pub first_anchor: u32,
    /// `Y` per anchor (6 × unknowns, row-major), anchor after anchor.
    pub y: Vec<f64>,
}

impl CalibrationShare {
    /// From the cross columns `cross[j][k]`, their solutions `solved[j][k]` and the step `x0`.
    pub(crate) fn new(
        normals: CalibrationNormals,
        first_anchor: u32,
        cross: &[Vec<nalgebra::Vector6<f64>>],
        solved: &[Vec<nalgebra::Vector6<f64>>],
        x0: &[nalgebra::Vector6<f64>],
    ) -> Self {
        let k = cross.len();
        let n = x0.len();
        let mut schur = vec![0.0; k * k];
        let mut rhs = vec![0.0; k];
        for i in 0..k {
            for a in 0..n {
                rhs[i] += cross[i][a].dot(&x0[a]);
                for j in 0..k {
                    schur[i * k + j] += cross[i][a].dot(&solved[j][a]);
                }
            }
        }
        let mut y = vec![0.0; n * 6 * k];
        for a in 0..n {
            for r in 0..6 {
                for j in 0..k {
                    y[(a * 6 + r) * k + j] = solved[j][a][r];
                }
            }
        }
        Self { normals, schur, rhs, first_anchor, y }
    }

    /// The unknowns.
    pub fn len(&self) -> usize {
        self.rhs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rhs.is_empty()
    }

    /// Moves `values` (the corrections from `first_anchor` on) by `−Y·δc`.
    pub fn apply(&self, step: &[f64], values: &mut [[f64; 6]]) {
        let k = self.len();
        if k == 0 || step.len() != k {
            return;
        }
        for (a, v) in values.iter_mut().enumerate().take(self.y.len() / (6 * k)) {
            for (r, value) in v.iter_mut().enumerate() {
                let row = &self.y[(a * 6 + r) * k..(a * 6 + r + 1) * k];
                *value -= row.iter().zip(step).map(|(y, d)| y * d).sum::<f64>();
            }
        }
    }
}

/// The calibration's step of one iteration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationStep {
    /// `δc`, what to add to the current calibration.
    pub delta: Vec<f64>,
    /// The posterior covariance of the calibration (unknowns × unknowns, row-major; in the
    /// observations' variance units, the formal precision), zero for an unknown held.
    pub covariance: Vec<f64>,
    /// Per unknown, whether the campaign's geometry determines it within its tolerance; one
    /// that does not is held at the manifest's value.
    pub determined: Vec<bool>,
    /// Per unknown, the share of what the observations say of it that the trajectories'
    /// corrections cannot take up: its information given the others and the trajectories
    /// (`1/(S⁻¹)_jj`, prior left out) over its information from the observations alone
    /// (`H_cc,jj`). Near 0 the corrections mimic it.
    pub separation: Vec<f64>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CalibrationError {
    #[error("the calibration's normal equations are not positive definite ({unknowns} unknowns)")]
    NotPositiveDefinite { unknowns: usize },
    #[error("calibration shares of {found} unknowns where the layout has {expected}")]
    Shape { found: usize, expected: usize },
}

/// The calibration's exact step given every trajectory's share: the Schur complement
/// `Σ(H_cc − CᵀY) + P` and right-hand side `Σ(b_c − Cᵀx₀) − P·c`, with the prior `P` (σ per
/// kind, centred on the manifest's mounting) holding the system regular. An unknown whose
/// posterior σ exceeds its tolerance, or whose separation from the trajectories is below
/// `min_separation`, is held at the manifest's value (its step is `−c`) and the others are solved
/// given it.
pub fn solve_calibration<'a>(
    shares: impl IntoIterator<Item = &'a CalibrationShare>,
    current: &[f64],
    layout: &CalibrationLayout,
    options: &precimap_core::CalibrationOptions,
) -> Result<CalibrationStep, CalibrationError> {
    let k = layout.len();
    if current.len() != k {
        return Err(CalibrationError::Shape { found: current.len(), expected: k });
    }
    let mut s = nalgebra::DMatrix::<f64>::zeros(k, k);
    let mut r = nalgebra::DVector::<f64>::zeros(k);
    let mut direct = vec![0.0; k];
    for share in shares {
        if share.len() != k || share.normals.len() != k {
            return Err(CalibrationError::Shape { found: share.len(), expected: k });
        }
        for i in 0..k {
            direct[i] += share.normals.h[i * k + i];
            r[i] += share.normals.b[i] - share.rhs[i];
            for j in 0..k {
                s[(i, j)] += share.normals.h[i * k + j] - share.schur[i * k + j];
            }
        }
    }
    let per = layout.per_scanner().max(1);
    let mut tolerance = vec![0.0; k];
    for i in 0..k {
        let (prior, tol) = options.prior_and_tolerance(layout.kind_of(i % per).0);
        let w = 1.0 / (prior * prior);
        s[(i, i)] += w;
        r[i] -= w * current[i];
        tolerance[i] = tol;
    }
    // Symmetric by construction up to rounding; the solves below want it exactly.
    let s = (&s + s.transpose()) * 0.5;
    let inverse = s.clone().cholesky().ok_or(CalibrationError::NotPositiveDefinite { unknowns: k })?.inverse();
    let separation: Vec<f64> = (0..k)
        .map(|i| {
            let (prior, _) = options.prior_and_tolerance(layout.kind_of(i % per).0);
            let given = 1.0 / inverse[(i, i)] - 1.0 / (prior * prior);
            if direct[i] > 0.0 {
                (given / direct[i]).clamp(0.0, 1.0)
            } else {
                0.0
            }
        })
        .collect();
    let determined: Vec<bool> =
        (0..k).map(|i| inverse[(i, i)].sqrt() <= tolerance[i] && separation[i] >= options.min_separation).collect();
    let free: Vec<usize> = (0..k).filter(|&i| determined[i]).collect();
    let mut delta: Vec<f64> = (0..k).map(|i| -current[i]).collect();
    let mut covariance = vec![0.0; k * k];
    if !free.is_empty() {
        let m = free.len();
        let sub = nalgebra::DMatrix::from_fn(m, m, |a, b| s[(free[a], free[b])]);
        let rhs = nalgebra::DVector::from_fn(m, |a, _| {
            let i = free[a];
            r[i] - (0..k).filter(|&j| !determined[j]).map(|j| s[(i, j)] * delta[j]).sum::<f64>()
        });
        let chol = sub.cholesky().ok_or(CalibrationError::NotPositiveDefinite { unknowns: m })?;
        let x = chol.solve(&rhs);
        let cov = chol.inverse();
        for (a, &i) in free.iter().enumerate() {
            delta[i] = x[a];
            for (b, &j) in free.iter().enumerate() {
                covariance[i * k + j] = cov[(a, b)];
            }
        }
    }
    Ok(CalibrationStep { delta, covariance, determined, separation })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::blocks::IntervalMoments;
    use precimap_core::calibration::attitude_matrix;
    use precimap_core::CalibrationOptions;

    /// An interval's terms from its moments equal the sums over its observations of their
    /// calibration columns ([`CalibrationLayout::jacobian`]) at the attitude interpolated between
    /// the interval's anchors.
    #[test]
    fn interval_terms_equal_the_sums_over_observations() {
        use CalibrationUnknown::{Boresight, LeverArm, RangeOffset};
        let mut seed = 5u64;
        let mut rand = move || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        for kinds in [vec![Boresight, LeverArm, RangeOffset], vec![Boresight], vec![LeverArm, RangeOffset]] {
            let layout = CalibrationOptions { estimate: kinds, ..Default::default() }.layout(1);
            let k = layout.per_scanner();
            let has_range = layout.kinds.contains(&RangeOffset);
            let (ra, rb) = (attitude_matrix([0.1, -0.2, 2.5]), attitude_matrix([0.13, -0.18, 2.58]));
            let mut moments = IntervalMoments::default();
            let (mut range, mut h_rr, mut b_r) = ([0.0; 12], 0.0, 0.0);
            let (mut cross_direct, mut h_direct, mut b_direct) = ([[0.0; 7]; 12], [[0.0; 7]; 7], [0.0; 7]);
            for _ in 0..25 {
                let m = [rand() * 30.0, rand() * 30.0, rand() * 5.0];
                let w = [rand(), rand(), rand() + 1.0];
                let n = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
                let w = w.map(|v| v / n);
                let (lambda, weight, e) = (rand() + 0.5, 1e4 * (1.0 + rand()), rand() * 0.02);
                let g =
                    [w[0], w[1], w[2], m[1] * w[2] - m[2] * w[1], m[2] * w[0] - m[0] * w[2], m[0] * w[1] - m[1] * w[0]];
                moments.add(&g, e, weight, lambda);
                let r: [[f64; 3]; 3] =
                    std::array::from_fn(|a| std::array::from_fn(|b| (1.0 - lambda) * ra[a][b] + lambda * rb[a][b]));
                let mut gc = [0.0; 7];
                layout.jacobian(&r, m, w, &mut gc[..k]);
                let j: [f64; 12] =
                    std::array::from_fn(|c| if c < 6 { (1.0 - lambda) * g[c] } else { lambda * g[c - 6] });
                for c in 0..12 {
                    for q in 0..k {
                        cross_direct[c][q] += weight * j[c] * gc[q];
                    }
                    if has_range {
                        range[c] += weight * j[c] * gc[k - 1];
                    }
                }
                for a in 0..k {
                    for q in 0..k {
                        h_direct[a][q] += weight * gc[a] * gc[q];
                    }
                    b_direct[a] -= weight * e * gc[a];
                }
                if has_range {
                    h_rr += weight * gc[k - 1] * gc[k - 1];
                    b_r -= weight * e * gc[k - 1];
                }
            }
            let (block, rhs) = moments.block();
            let (mut cross, mut h, mut b) = ([[0.0; 7]; 12], [0.0; 28], [0.0; 7]);
            let (at, next) = (AttitudeRows::new(&layout, &ra), AttitudeRows::new(&layout, &rb));
            interval_terms(&block, &rhs, &at, &next, has_range.then_some(&range), &mut cross, &mut h, &mut b);
            if has_range {
                h[k * (k + 1) / 2 - 1] += h_rr;
                b[k - 1] += b_r;
            }
            let close = |x: f64, y: f64, scale: f64| (x - y).abs() <= 1e-9 * scale;
            let scale = h_direct.iter().flatten().fold(0.0f64, |s, v| s.max(v.abs()));
            for c in 0..12 {
                for q in 0..k {
                    assert!(close(cross[c][q], cross_direct[c][q], scale), "cross {c},{q}");
                }
            }
            let mut index = 0;
            for a in 0..k {
                for q in a..k {
                    assert!(
                        close(h[index], h_direct[a][q], scale),
                        "h {a},{q}: {} against {}",
                        h[index],
                        h_direct[a][q]
                    );
                    index += 1;
                }
                assert!(close(b[a], b_direct[a], scale), "b {a}");
            }
        }
    }
}
