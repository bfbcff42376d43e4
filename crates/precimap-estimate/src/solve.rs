//! `solve_trajectory`: the reduce task of one iteration (paper Eq. 6, DESIGN §2). Sums the
//! blocks all tiles emitted for one trajectory, adds the prior on the total correction (Eq. 2)
//! and the smoothness between neighbouring anchors (Eq. 3), and solves the block-tridiagonal
//! Gauss–Newton system exactly in linear time.

use crate::blocks::{sym_index, AnchorBlock};
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::Parameters;
use precimap_solve::{BlockTridiagonal, Mat6, Vec6};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectorySolution {
    pub corrections: TrajectoryCorrections,
    /// Largest change against the previous corrections, as the displacement of a point at 10 m.
    pub max_change_m: f64,
    /// Anchors with at least one observation.
    pub anchors_observed: u32,
    pub observations: u64,
    /// Posterior standard deviations per anchor (position m, rotation rad), when requested.
    pub sigma: Option<Vec<[f64; 6]>>,
}

/// Nominal range at which a rotation change is expressed as a displacement.
pub const CHANGE_RANGE_M: f64 = 10.0;

/// Range at which rotations are compared with translations (radians → metres).
const ROTATION_SCALE_M: f64 = 10.0;

/// Removes from the data part of the normal equations every direction that an anchor's own
/// observations barely constrain (e.g. along-track translation in a featureless street, or a
/// standstill seen by two fixed scan lines). Points are far from independent — they share
/// surfaces and pixels — so such directions are determined to far worse than their formal
/// precision, and small biases in other directions leak into them amplified. Filtered
/// directions follow their neighbours through the smoothness term instead.
///
/// With `T = diag(1, 1, 1, 1/L, 1/L, 1/L)` (rotations as displacements at range L), each
/// anchor's data block `D` gives `M = T D T = V Λ Vᵀ`; keeping the eigenvectors with
/// `λ ≥ ratio·λ_max` defines the projector `P`, and `R = T P T⁻¹` maps the data terms to
/// `Rᵀ D R`, `R_iᵀ U R_{i+1}`, `Rᵀ b` — a congruence, so the system stays positive semidefinite.
///
/// Only the first `dims` unknowns (3: translation, when the step holds rotation fixed) are
/// considered; the others keep their data terms.
fn filter_weak_directions(sys: &mut BlockTridiagonal, dims: usize, ratio: f64) {
    let n = sys.len();
    let t = Vec6::new(1.0, 1.0, 1.0, 1.0 / ROTATION_SCALE_M, 1.0 / ROTATION_SCALE_M, 1.0 / ROTATION_SCALE_M);
    let projections: Vec<Option<Mat6>> = (0..n)
        .map(|k| {
            let d = &sys.diag[k];
            let m = nalgebra::DMatrix::from_fn(dims, dims, |a, b| t[a] * d[(a, b)] * t[b]);
            let eig = nalgebra::SymmetricEigen::new(m);
            let max = eig.eigenvalues.max();
            if max <= 0.0 {
                return None;
            }
            let mut p = Mat6::identity();
            p.view_mut((0, 0), (dims, dims)).fill(0.0);
            let mut dropped = false;
            for (j, &lambda) in eig.eigenvalues.iter().enumerate() {
                if lambda >= ratio * max {
                    let v = eig.eigenvectors.column(j);
                    let mut outer = p.view_mut((0, 0), (dims, dims));
                    outer += v * v.transpose();
                } else {
                    dropped = true;
                }
            }
            dropped.then(|| Mat6::from_fn(|a, b| t[a] * p[(a, b)] / t[b]))
        })
        .collect();
    for k in 0..n {
        if let Some(r) = &projections[k] {
            sys.diag[k] = r.transpose() * sys.diag[k] * r;
            sys.rhs[k] = r.transpose() * sys.rhs[k];
        }
        if k + 1 < n && (projections[k].is_some() || projections[k + 1].is_some()) {
            let left = projections[k].unwrap_or_else(Mat6::identity);
            let right = projections[k + 1].unwrap_or_else(Mat6::identity);
            sys.upper[k] = left.transpose() * sys.upper[k] * right;
        }
    }
}

/// Eliminates the rotation unknowns exactly: their rows and columns become the identity with a
/// zero right-hand side, so the step solves for translation with the attitude held fixed.
fn freeze_rotation(sys: &mut BlockTridiagonal) {
    let n = sys.len();
    for k in 0..n {
        for a in 3..6 {
            for b in 0..6 {
                sys.diag[k][(a, b)] = 0.0;
                sys.diag[k][(b, a)] = 0.0;
                if k + 1 < n {
                    sys.upper[k][(a, b)] = 0.0;
                }
                if k > 0 {
                    sys.upper[k - 1][(b, a)] = 0.0;
                }
            }
            sys.diag[k][(a, a)] = 1.0;
            sys.rhs[k][a] = 0.0;
        }
    }
}

fn sym_to_mat(s: &[f64; 21]) -> Mat6 {
    let mut m = Mat6::zeros();
    for i in 0..6 {
        for j in i..6 {
            let v = s[sym_index(i, j)];
            m[(i, j)] = v;
            m[(j, i)] = v;
        }
    }
    m
}

/// Weights of the prior and the smoothness as diagonal 6×6 matrices.
fn weights(params: &Parameters) -> (Vec6, Vec6) {
    let sp = params.sigma_prior_position_m;
    let sr = params.sigma_prior_rotation_deg.to_radians();
    let dp = params.sigma_smooth_position_m;
    let dr = params.sigma_smooth_rotation_deg.to_radians();
    let prior =
        Vec6::new(1.0 / (sp * sp), 1.0 / (sp * sp), 1.0 / (sp * sp), 1.0 / (sr * sr), 1.0 / (sr * sr), 1.0 / (sr * sr));
    let smooth =
        Vec6::new(1.0 / (dp * dp), 1.0 / (dp * dp), 1.0 / (dp * dp), 1.0 / (dr * dr), 1.0 / (dr * dr), 1.0 / (dr * dr));
    (prior, smooth)
}

/// One Gauss–Newton step for one trajectory. `blocks` are the summed tile blocks (any order,
/// duplicates of an anchor are added); `current` fixes the anchor range.
pub fn solve_trajectory<'a>(
    blocks: impl IntoIterator<Item = &'a AnchorBlock>,
    current: &TrajectoryCorrections,
    params: &Parameters,
    estimate_rotation: bool,
    with_sigma: bool,
) -> Result<TrajectorySolution, precimap_solve::SolveError> {
    let n = current.values.len();
    let first = current.first_anchor;
    let mut sys = BlockTridiagonal::zeros(n);
    let mut observed = vec![false; n];
    let mut observations = 0u64;
    for b in blocks {
        // Blocks outside the range cannot occur for a consistent campaign; clamping keeps the
        // system well-formed if they do (e.g. a point exactly at the last anchor).
        let Some(k) = (b.anchor as usize).checked_sub(first as usize).filter(|&k| k < n) else { continue };
        sys.diag[k] += sym_to_mat(&b.diag);
        if k + 1 < n {
            sys.upper[k] += sym_to_mat(&b.next);
        }
        for a in 0..6 {
            sys.rhs[k][a] += b.rhs[a];
        }
        if b.observations > 0 {
            observed[k] = true;
            observations += b.observations as u64;
        }
    }
    filter_weak_directions(&mut sys, if estimate_rotation { 6 } else { 3 }, params.weak_information_ratio);
    let (prior, smooth) = weights(params);
    let x = |k: usize| Vec6::from_column_slice(&current.values[k]);
    for k in 0..n {
        let xk = x(k);
        for a in 0..6 {
            sys.diag[k][(a, a)] += prior[a];
            sys.rhs[k][a] -= prior[a] * xk[a];
        }
        if k + 1 < n {
            let d = x(k + 1) - xk;
            for a in 0..6 {
                sys.diag[k][(a, a)] += smooth[a];
                sys.diag[k + 1][(a, a)] += smooth[a];
                sys.upper[k][(a, a)] -= smooth[a];
                sys.rhs[k][a] += smooth[a] * d[a];
                sys.rhs[k + 1][a] -= smooth[a] * d[a];
            }
        }
    }
    if !estimate_rotation {
        freeze_rotation(&mut sys);
    }
    let (delta, sigma) = if with_sigma {
        let (d, cov) = precimap_solve::solve_with_covariance(&sys)?;
        let sigma = cov.iter().map(|c| std::array::from_fn(|a| c[(a, a)].max(0.0).sqrt())).collect();
        (d, Some(sigma))
    } else {
        (precimap_solve::solve(&sys)?, None)
    };
    let values: Vec<[f64; 6]> =
        current.values.iter().zip(&delta).map(|(x, d)| std::array::from_fn(|a| x[a] + d[a])).collect();
    let corrections = TrajectoryCorrections { first_anchor: first, values };
    let max_change_m = corrections.max_change_m(current, CHANGE_RANGE_M);
    Ok(TrajectorySolution {
        corrections,
        max_change_m,
        anchors_observed: observed.iter().filter(|&&o| o).count() as u32,
        observations,
        sigma,
    })
}
