//! The scanners' mounting calibration in estimation (docs/design/calibration.md): what a tile
//! needs to apply it and to linearise it ([`TileCalibration`]), the cross terms between anchors
//! and calibration unknowns its observations add ([`CrossMoments`]), the calibration's own
//! normal equations ([`CalibrationNormals`]), and the exact joint solve of the calibration with
//! every trajectory's chain by the Schur complement ([`solve_calibration`]).

use precimap_core::{CalibrationLayout, ScannerCalibration};
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

/// Per anchor interval of one chunk (one scanner): `Σ w·g·gcᵀ` and `Σ w·λ·g·gcᵀ` (6 × the
/// scanner's unknowns, at most 7, row-major), from which anchor `i` gets `(1−λ)` and anchor
/// `i+1` `λ`.
#[derive(Clone, Debug)]
pub(crate) struct CrossMoments {
    per_scanner: usize,
    m0: Vec<[f64; 42]>,
    m1: Vec<[f64; 42]>,
}

impl CrossMoments {
    pub(crate) fn new(intervals: usize, per_scanner: usize) -> Self {
        assert!(per_scanner <= 7, "at most 7 calibration unknowns per scanner");
        Self { per_scanner, m0: vec![[0.0; 42]; intervals], m1: vec![[0.0; 42]; intervals] }
    }

    #[inline]
    pub(crate) fn add(&mut self, interval: usize, g: &[f64; 6], gc: &[f64], w: f64, lambda: f64) {
        let k = self.per_scanner;
        let (m0, m1) = (&mut self.m0[interval], &mut self.m1[interval]);
        let wl = w * lambda;
        for (a, ga) in g.iter().enumerate() {
            let (wa, wla) = (w * ga, wl * ga);
            for (j, gj) in gc.iter().enumerate().take(k) {
                m0[a * 7 + j] += wa * gj;
                m1[a * 7 + j] += wla * gj;
            }
        }
    }

    /// Adds interval `interval`'s terms to the cross blocks (6 × `total` unknowns, row-major)
    /// of anchors `i` (`at`) and `i+1` (`after`), at the scanner's columns from `offset`.
    pub(crate) fn scatter(
        &self,
        interval: usize,
        offset: usize,
        total: usize,
        at: &mut Vec<f64>,
        after: &mut Vec<f64>,
    ) {
        let k = self.per_scanner;
        let (m0, m1) = (&self.m0[interval], &self.m1[interval]);
        for block in [&mut *at, &mut *after] {
            if block.is_empty() {
                block.resize(6 * total, 0.0);
            }
        }
        for a in 0..6 {
            for j in 0..k {
                at[a * total + offset + j] += m0[a * 7 + j] - m1[a * 7 + j];
                after[a * total + offset + j] += m1[a * 7 + j];
            }
        }
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
