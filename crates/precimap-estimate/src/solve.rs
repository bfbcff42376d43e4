//! `solve_trajectory`: the reduce task of one iteration (paper Eq. 6). Sums the
//! blocks all tiles emitted for one trajectory, adds the prior on the total correction (Eq. 2)
//! and the smoothness between neighbouring anchors (Eq. 3), and solves the block-tridiagonal
//! Gauss–Newton system exactly in linear time.

use crate::blocks::{sym_index, AnchorBlock};
use crate::calibration::{CalibrationNormals, CalibrationShare};
use precimap_core::corrections::{AnchorCovariance, ChangeHistogram, TrajectoryCorrections};
use precimap_core::Parameters;
use precimap_solve::{BlockTridiagonal, Mat6, Vec6};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectorySolution {
    pub corrections: TrajectoryCorrections,
    /// Largest change since the iteration started (see [`solve_trajectory`]'s `change_from`),
    /// as the displacement of a point at 10 m.
    pub max_change_m: f64,
    /// The anchor of that largest change.
    #[serde(default)]
    pub max_change_anchor: u32,
    /// Every anchor's change, measured the same way.
    #[serde(default)]
    pub change_histogram: ChangeHistogram,
    /// Anchors with at least one observation.
    pub anchors_observed: u32,
    pub observations: u64,
    /// Posterior covariance per anchor (position m, rotation rad, world frame), when requested:
    /// given the latent map this iteration held fixed, so it says how well the pass fits the
    /// map, not how far the map itself is from the truth.
    pub covariance: Option<Vec<AnchorCovariance>>,
    /// The trajectory's share of the joint solve with the scanners' calibration, where the
    /// campaign estimates it: its corrections above are those of an unchanged calibration, and
    /// [`CalibrationShare::apply`] moves them by the calibration's step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<CalibrationShare>,
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
fn filter_weak_directions(sys: &mut BlockTridiagonal, dims: usize, ratio: f64, extra: &mut [Vec<Vec6>]) {
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
            for column in extra.iter_mut() {
                column[k] = r.transpose() * column[k];
            }
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
fn freeze_rotation(sys: &mut BlockTridiagonal, mut skip: Option<&mut Vec<Mat6>>) {
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
                if let Some(skip) = skip.as_deref_mut() {
                    if k + 2 < n {
                        skip[k][(a, b)] = 0.0;
                    }
                    if k >= 2 {
                        skip[k - 2][(b, a)] = 0.0;
                    }
                }
            }
            sys.diag[k][(a, a)] = 1.0;
            sys.rhs[k][a] = 0.0;
        }
    }
}

/// Weights of the curvature terms, `None` when they are off.
fn curvature_weights(params: &Parameters) -> Option<Vec6> {
    let p = params.sigma_curvature_position_m;
    let r = params.sigma_curvature_rotation_deg.to_radians();
    (p > 0.0 && r > 0.0)
        .then(|| Vec6::new(1.0 / (p * p), 1.0 / (p * p), 1.0 / (p * p), 1.0 / (r * r), 1.0 / (r * r), 1.0 / (r * r)))
}

/// Adds `(x_{i−1} − 2x_i + x_{i+1})ᵀ P (…)` for every interior anchor, linearised about the
/// current corrections. Returns the blocks `H_{i,i+2}` the term couples.
fn add_curvature(sys: &mut BlockTridiagonal, current: &[[f64; 6]], weight: &Vec6) -> Vec<Mat6> {
    let n = sys.len();
    let mut skip = vec![Mat6::zeros(); n.saturating_sub(2)];
    for i in 1..n.saturating_sub(1) {
        let d: [f64; 6] = std::array::from_fn(|a| current[i - 1][a] - 2.0 * current[i][a] + current[i + 1][a]);
        for a in 0..6 {
            let w = weight[a];
            sys.diag[i - 1][(a, a)] += w;
            sys.diag[i][(a, a)] += 4.0 * w;
            sys.diag[i + 1][(a, a)] += w;
            sys.upper[i - 1][(a, a)] -= 2.0 * w;
            sys.upper[i][(a, a)] -= 2.0 * w;
            skip[i - 1][(a, a)] += w;
            sys.rhs[i - 1][a] -= w * d[a];
            sys.rhs[i][a] += 2.0 * w * d[a];
            sys.rhs[i + 1][a] -= w * d[a];
        }
    }
    skip
}

type Mat12 = nalgebra::SMatrix<f64, 12, 12>;
type Vec12 = nalgebra::SVector<f64, 12>;

/// Solves the system with couplings up to two anchors apart exactly: anchor pairs
/// `(2j, 2j+1)` form 12×12 super-blocks, which makes it block-tridiagonal again.
#[allow(clippy::type_complexity)]
fn solve_pairs(
    sys: &BlockTridiagonal,
    skip: &[Mat6],
    with_sigma: bool,
    extra: &[Vec<Vec6>],
) -> Result<(Vec<Vec6>, Option<Vec<Mat6>>, Vec<Vec<Vec6>>), precimap_solve::SolveError> {
    let n = sys.len();
    let m = n.div_ceil(2);
    let block = |i: usize, j: usize| -> Mat6 {
        // H_{i,j} for i ≤ j, zero outside the band or the range.
        if i >= n || j >= n {
            return if i == j { Mat6::identity() } else { Mat6::zeros() };
        }
        match j - i {
            0 => sys.diag[i],
            1 => sys.upper[i],
            2 => skip[i],
            _ => Mat6::zeros(),
        }
    };
    let put = |target: &mut Mat12, r: usize, c: usize, b: &Mat6| target.view_mut((r, c), (6, 6)).copy_from(b);
    let mut diag = Vec::with_capacity(m);
    let mut upper = Vec::with_capacity(m.saturating_sub(1));
    let mut rhs = Vec::with_capacity(m);
    for j in 0..m {
        let (a, b) = (2 * j, 2 * j + 1);
        let mut d = Mat12::zeros();
        put(&mut d, 0, 0, &block(a, a));
        put(&mut d, 6, 6, &block(b, b));
        let ab = block(a, b);
        put(&mut d, 0, 6, &ab);
        put(&mut d, 6, 0, &ab.transpose());
        diag.push(d);
        let mut r = Vec12::zeros();
        r.rows_mut(0, 6).copy_from(&sys.rhs[a]);
        if b < n {
            r.rows_mut(6, 6).copy_from(&sys.rhs[b]);
        }
        rhs.push(r);
        if j + 1 < m {
            let (c, e) = (2 * j + 2, 2 * j + 3);
            let mut u = Mat12::zeros();
            put(&mut u, 0, 0, &block(a, c));
            put(&mut u, 0, 6, &block(a, e));
            put(&mut u, 6, 0, &block(b, c));
            put(&mut u, 6, 6, &block(b, e));
            upper.push(u);
        }
    }
    let factor = precimap_solve::generic::BlocksLdlt::factor(&diag, &upper)?;
    let x = factor.solve(&rhs)?;
    let cov = with_sigma.then(|| factor.marginal_covariances());
    let unpair = |x: &[Vec12]| -> Vec<Vec6> {
        (0..n).map(|i| Vec6::from_iterator(x[i / 2].rows((i % 2) * 6, 6).iter().copied())).collect()
    };
    let delta = unpair(&x);
    let sigma =
        cov.map(|c| (0..n).map(|i| Mat6::from_fn(|r, k| c[i / 2][((i % 2) * 6 + r, (i % 2) * 6 + k)])).collect());
    let mut solved = Vec::with_capacity(extra.len());
    for column in extra {
        let paired: Vec<Vec12> = (0..m)
            .map(|j| {
                let mut r = Vec12::zeros();
                r.rows_mut(0, 6).copy_from(&column[2 * j]);
                if 2 * j + 1 < n {
                    r.rows_mut(6, 6).copy_from(&column[2 * j + 1]);
                }
                r
            })
            .collect();
        solved.push(unpair(&factor.solve(&paired)?));
    }
    Ok((delta, sigma, solved))
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
    let [rx, ry, rz] = params.sigma_prior_rotation_axes_deg().map(f64::to_radians);
    let dp = params.sigma_smooth_position_m;
    let dr = params.sigma_smooth_rotation_deg.to_radians();
    let prior =
        Vec6::new(1.0 / (sp * sp), 1.0 / (sp * sp), 1.0 / (sp * sp), 1.0 / (rx * rx), 1.0 / (ry * ry), 1.0 / (rz * rz));
    let smooth =
        Vec6::new(1.0 / (dp * dp), 1.0 / (dp * dp), 1.0 / (dp * dp), 1.0 / (dr * dr), 1.0 / (dr * dr), 1.0 / (dr * dr));
    (prior, smooth)
}

/// `corrections` continued over `range` (which holds their anchors): each anchor beyond their
/// ends takes the value the smoothness and curvature terms give it with the estimated anchors
/// held. With the curvature term the correction's trend carries on, fading over about
/// σ_smooth / σ_curvature anchors (50 for the position, 13 for the attitude by default); without
/// it the end value is held. Run once after the iterations, on the trajectory's run-up and
/// run-out before its first and after its last scan, so that those unobserved anchors neither
/// take part in the estimation nor in its convergence test.
///
/// Not the prior: it holds each anchor's total correction independently, a simplification for
/// errors correlated over hundreds of metres, and would pull the attitude back towards the
/// uncorrected one within a few anchors (its σ is tight against the smoothness). Measured on
/// small s1: attitude error 13.146 mdeg with the prior, 13.132 without, positions equal.
pub fn extend_corrections(
    corrections: &TrajectoryCorrections,
    range: (u32, u32),
    params: &Parameters,
) -> TrajectoryCorrections {
    let (first, last) = (corrections.first_anchor, corrections.last_anchor());
    let before = first.saturating_sub(range.0) as usize;
    let after = range.1.saturating_sub(last) as usize;
    if before == 0 && after == 0 {
        return corrections.clone();
    }
    let (_, smooth) = weights(params);
    let curvature = curvature_weights(params).unwrap_or_else(Vec6::zeros);
    let values = &corrections.values;
    let n = values.len();
    let mut head = vec![[0.0; 6]; before];
    let mut tail = vec![[0.0; 6]; after];
    for a in 0..6 {
        let weights = ProfileWeights { smooth: smooth[a], curvature: curvature[a] };
        // The run-up mirrored: its first unknown next to the first estimated anchor.
        let run_up = continue_profile(values.get(1).map(|v| v[a]), values[0][a], before, &weights);
        for (k, v) in run_up.into_iter().enumerate() {
            head[before - 1 - k][a] = v;
        }
        let run_out = continue_profile(n.checked_sub(2).map(|i| values[i][a]), values[n - 1][a], after, &weights);
        for (k, v) in run_out.into_iter().enumerate() {
            tail[k][a] = v;
        }
    }
    let mut out = Vec::with_capacity(before + n + after);
    out.extend(head);
    out.extend_from_slice(values);
    out.extend(tail);
    TrajectoryCorrections { first_anchor: first - before as u32, values: out }
}

/// One unknown's weights in the smoothness and curvature terms.
struct ProfileWeights {
    smooth: f64,
    curvature: f64,
}

/// The `m` values `y₁…y_m` after the known `x₋₁` (absent for a single anchor) and `x₀` that
/// minimise `Σ smooth·(first differences)² + Σ curvature·(second differences)²` over every term
/// that holds an unknown. The normal matrix is pentadiagonal and positive definite (the chain of
/// first differences is tied to `x₀`): a banded Cholesky solves it in O(m).
fn continue_profile(x_before_end: Option<f64>, x_end: f64, m: usize, w: &ProfileWeights) -> Vec<f64> {
    if m == 0 {
        return Vec::new();
    }
    // Band storage: `band[i] = [A(i,i), A(i,i−1), A(i,i−2)]`.
    let mut band = vec![[0.0f64; 3]; m];
    let mut rhs = vec![0.0f64; m];
    // Terms over the full chain x₋₁, x₀, y₁…y_m, index j: 0 = x₋₁, 1 = x₀, j ≥ 2 = y_{j−1}.
    let known = |j: usize| if j == 0 { x_before_end.unwrap_or(0.0) } else { x_end };
    let mut add_term = |coeffs: &[(usize, f64)], weight: f64| {
        let constant: f64 = coeffs.iter().filter(|&&(j, _)| j < 2).map(|&(j, c)| c * known(j)).sum();
        for &(j, cj) in coeffs.iter().filter(|&&(j, _)| j >= 2) {
            let r = j - 2;
            rhs[r] -= weight * cj * constant;
            for &(k, ck) in coeffs.iter().filter(|&&(k, _)| k >= 2 && k <= j) {
                band[r][j - k] += weight * cj * ck;
            }
        }
    };
    for j in 2..m + 2 {
        add_term(&[(j - 1, -1.0), (j, 1.0)], w.smooth);
        if w.curvature > 0.0 && (j >= 3 || x_before_end.is_some()) {
            add_term(&[(j - 2, 1.0), (j - 1, -2.0), (j, 1.0)], w.curvature);
        }
    }
    // Banded Cholesky A = L Lᵀ in place (L in `band`, same layout), then the two triangles.
    for i in 0..m {
        for d in (0..3).rev() {
            let Some(j) = i.checked_sub(d) else { continue };
            let mut sum = band[i][d];
            for k in j.saturating_sub(2).max(i.saturating_sub(2))..j {
                sum -= band[i][i - k] * band[j][j - k];
            }
            band[i][d] = if d == 0 { sum.sqrt() } else { sum / band[j][0] };
        }
    }
    for i in 0..m {
        let mut sum = rhs[i];
        for k in i.saturating_sub(2)..i {
            sum -= band[i][i - k] * rhs[k];
        }
        rhs[i] = sum / band[i][0];
    }
    for i in (0..m).rev() {
        let mut sum = rhs[i];
        for k in i + 1..(i + 3).min(m) {
            sum -= band[k][k - i] * rhs[k];
        }
        rhs[i] = sum / band[i][0];
    }
    rhs
}

/// The campaign's prior weights on an anchor's total correction (1/σ²: x, y, z in m⁻², rotations
/// about x, y, z in rad⁻²), what every anchor gets without a per-anchor prior.
pub fn campaign_prior_weights(params: &Parameters) -> [f64; 6] {
    weights(params).0.into()
}

/// One Gauss–Newton step for one trajectory. `blocks` are the summed tile blocks (any order,
/// duplicates of an anchor are added); `current` fixes the anchor range. With `previous` (the
/// corrections before `current`) the step adds `params.momentum × (current − previous)`.
///
/// The reported change is measured from `change_from` (default `current`): the corrections the
/// iteration started from. In steps that solve the common-mode field the solve starts from them
/// plus the field, and the field and the solve can move the same shared shift back and forth by
/// a constant amount while the corrections themselves settle: measured from the solve's own
/// start, the change never falls below that amount (small seed 1: 0.42 mm in every one of 30
/// extra iterations while the trajectories moved 2 mm in all). The convergence test and the
/// report want the change between iterations.
///
/// `prior[k]` (weights as [`campaign_prior_weights`]) is anchor `current.first_anchor + k`'s
/// prior; `None`, or an anchor beyond the slice, takes the campaign's.
///
/// With `calibration` (the calibration's normal equations this trajectory's observations
/// summed, in steps that estimate it) the blocks' cross terms are solved for as well and the
/// solution carries the trajectory's [`CalibrationShare`].
#[allow(clippy::too_many_arguments)]
pub fn solve_trajectory<'a>(
    blocks: impl IntoIterator<Item = &'a AnchorBlock>,
    current: &TrajectoryCorrections,
    previous: Option<&TrajectoryCorrections>,
    change_from: Option<&TrajectoryCorrections>,
    params: &Parameters,
    prior: Option<&[[f64; 6]]>,
    estimate_rotation: bool,
    with_sigma: bool,
    calibration: Option<&CalibrationNormals>,
) -> Result<TrajectorySolution, precimap_solve::SolveError> {
    let n = current.values.len();
    let first = current.first_anchor;
    let mut sys = BlockTridiagonal::zeros(n);
    let mut observed = vec![false; n];
    let mut observations = 0u64;
    // The cross terms `H_xc`, one column of right-hand sides per calibration unknown.
    let unknowns = calibration.map_or(0, CalibrationNormals::len);
    let mut cross = vec![vec![Vec6::zeros(); n]; unknowns];
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
        if b.cross.len() == 6 * unknowns {
            for (j, column) in cross.iter_mut().enumerate() {
                for a in 0..6 {
                    column[k][a] += b.cross[a * unknowns + j];
                }
            }
        }
        if b.observations > 0 {
            observed[k] = true;
            observations += b.observations as u64;
        }
    }
    filter_weak_directions(&mut sys, if estimate_rotation { 6 } else { 3 }, params.weak_information_ratio, &mut cross);
    let (campaign_prior, smooth) = weights(params);
    let x = |k: usize| Vec6::from_column_slice(&current.values[k]);
    for k in 0..n {
        let xk = x(k);
        let prior = prior.and_then(|p| p.get(k)).map_or(campaign_prior, |w| Vec6::from(*w));
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
        // Rotations frozen: so are their couplings with the calibration.
        cross.iter_mut().flatten().for_each(|v| v.fixed_rows_mut::<3>(3).fill(0.0));
    }
    let curvature = curvature_weights(params);
    let (delta, marginals, solved) = match curvature {
        None => {
            if !estimate_rotation {
                freeze_rotation(&mut sys, None);
            }
            let factor = precimap_solve::BlockLdlt::factor(&sys)?;
            let d = factor.solve(&sys.rhs)?;
            let solved = cross.iter().map(|c| factor.solve(c)).collect::<Result<Vec<_>, _>>()?;
            (d, with_sigma.then(|| factor.marginal_covariances()), solved)
        }
        Some(weight) => {
            let mut skip = add_curvature(&mut sys, &current.values, &weight);
            if !estimate_rotation {
                freeze_rotation(&mut sys, Some(&mut skip));
            }
            solve_pairs(&sys, &skip, with_sigma, &cross)?
        }
    };
    let calibration = calibration.map(|normals| CalibrationShare::new(normals.clone(), first, &cross, &solved, &delta));
    let covariance = marginals.map(|cov| cov.iter().map(|c| AnchorCovariance::from_fn(|a, b| c[(a, b)])).collect());
    let beta = if previous.is_some() { params.momentum } else { 0.0 };
    let values: Vec<[f64; 6]> = current
        .values
        .iter()
        .zip(&delta)
        .enumerate()
        .map(|(k, (x, d))| {
            let before = previous.map_or(*x, |p| *p.anchor(first + k as u32));
            // Rotations stay frozen in translation-only steps, momentum included.
            std::array::from_fn(|a| {
                let carried = if a >= 3 && !estimate_rotation { 0.0 } else { beta * (x[a] - before[a]) };
                x[a] + d[a] + carried
            })
        })
        .collect();
    let corrections = TrajectoryCorrections { first_anchor: first, values };
    let change_from = change_from.unwrap_or(current);
    let changes = corrections.changes(change_from, CHANGE_RANGE_M);
    Ok(TrajectorySolution {
        corrections,
        max_change_m: changes.max_m,
        max_change_anchor: changes.max_anchor,
        change_histogram: changes.histogram,
        anchors_observed: observed.iter().filter(|&&o| o).count() as u32,
        observations,
        covariance,
        calibration,
    })
}

/// Moves a solution by the calibration's step `delta` (its share's `−Y·δc`) and measures its
/// change again from `change_from` (as [`solve_trajectory`] did).
pub fn apply_calibration_step(solution: &mut TrajectorySolution, delta: &[f64], change_from: &TrajectoryCorrections) {
    let Some(share) = &solution.calibration else { return };
    share.apply(delta, &mut solution.corrections.values);
    let changes = solution.corrections.changes(change_from, CHANGE_RANGE_M);
    solution.max_change_m = changes.max_m;
    solution.max_change_anchor = changes.max_anchor;
    solution.change_histogram = changes.histogram;
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};

    fn random_system(n: usize, seed: &mut u64) -> BlockTridiagonal {
        let mut rand = || {
            *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((*seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let mut sys = BlockTridiagonal::zeros(n);
        for i in 0..n {
            for _ in 0..10 {
                let g = Vec6::from_fn(|_, _| rand());
                let l = rand() + 0.5;
                sys.diag[i] += g * g.transpose() * (1.0 - l) * (1.0 - l);
                if i + 1 < n {
                    sys.upper[i] += g * g.transpose() * l * (1.0 - l);
                    sys.diag[i + 1] += g * g.transpose() * l * l;
                }
            }
            sys.diag[i] += Mat6::identity();
            sys.rhs[i] = Vec6::from_fn(|_, _| rand());
        }
        sys
    }

    /// The anchor-pair solve of a system with a two-anchor band equals a dense solve.
    #[test]
    fn pair_solve_with_curvature_matches_dense() {
        let mut seed = 3;
        for n in [1usize, 2, 3, 4, 7, 30] {
            let mut sys = random_system(n, &mut seed);
            let current: Vec<[f64; 6]> = (0..n).map(|i| std::array::from_fn(|a| (i * 6 + a) as f64 * 1e-3)).collect();
            let skip = add_curvature(&mut sys, &current, &Vec6::repeat(50.0));
            let mut dense = DMatrix::<f64>::zeros(6 * n, 6 * n);
            let mut b = DVector::<f64>::zeros(6 * n);
            for i in 0..n {
                dense.view_mut((6 * i, 6 * i), (6, 6)).copy_from(&sys.diag[i]);
                b.rows_mut(6 * i, 6).copy_from(&sys.rhs[i]);
                if i + 1 < n {
                    dense.view_mut((6 * i, 6 * i + 6), (6, 6)).copy_from(&sys.upper[i]);
                    dense.view_mut((6 * i + 6, 6 * i), (6, 6)).copy_from(&sys.upper[i].transpose());
                }
                if i + 2 < n {
                    dense.view_mut((6 * i, 6 * i + 12), (6, 6)).copy_from(&skip[i]);
                    dense.view_mut((6 * i + 12, 6 * i), (6, 6)).copy_from(&skip[i].transpose());
                }
            }
            let chol = dense.cholesky().expect("SPD");
            let exact = chol.solve(&b);
            let inverse = chol.inverse();
            let (x, cov, _) = solve_pairs(&sys, &skip, true, &[]).unwrap();
            let cov = cov.unwrap();
            for i in 0..n {
                for a in 0..6 {
                    assert!((x[i][a] - exact[6 * i + a]).abs() < 1e-9, "n {n}, anchor {i}");
                    assert!((cov[i][(a, a)] - inverse[(6 * i + a, 6 * i + a)]).abs() < 1e-9);
                }
            }
        }
    }

    /// The attitude prior holds the heading (rotation about the vertical) with its own σ when
    /// `sigma_prior_heading_deg` is set, the tilt with `sigma_prior_rotation_deg`: one anchor
    /// without data has exactly the prior's covariance.
    #[test]
    fn the_heading_prior_has_its_own_sigma() {
        let current = TrajectoryCorrections { first_anchor: 7, values: vec![[0.0; 6]] };
        let sigma = |params: &Parameters| {
            let solution =
                solve_trajectory(std::iter::empty(), &current, None, None, params, None, true, true, None).unwrap();
            solution.covariance.unwrap()[0].sigma()
        };
        let tilt = 0.02f64.to_radians();
        for (heading, expected) in [(0.0, tilt), (0.05, 0.05f64.to_radians())] {
            let params =
                Parameters { sigma_prior_rotation_deg: 0.02, sigma_prior_heading_deg: heading, ..Default::default() };
            let s = sigma(&params);
            for (a, want) in [(0, 1.0), (1, 1.0), (2, 1.0), (3, tilt), (4, tilt), (5, expected)] {
                assert!((s[a] / want - 1.0).abs() < 1e-9, "heading {heading}: σ {a} is {}, expected {want}", s[a]);
            }
        }
    }

    /// Momentum adds β × the previous step to the Gauss–Newton step, except to rotations a
    /// translation-only step holds fixed; without `previous` the step is plain.
    #[test]
    fn momentum_adds_beta_times_the_previous_step() {
        let n = 5;
        let params = Parameters { momentum: 0.5, weak_information_ratio: 0.0, ..Default::default() };
        let current =
            TrajectoryCorrections { first_anchor: 3, values: vec![[0.02, -0.01, 0.005, 1e-4, -2e-4, 3e-4]; n] };
        let previous = TrajectoryCorrections { first_anchor: 3, values: vec![[0.01, 0.0, 0.0, 0.0, 0.0, 1e-4]; n] };
        let plain =
            solve_trajectory(std::iter::empty(), &current, None, None, &params, None, true, false, None).unwrap();
        let carried =
            solve_trajectory(std::iter::empty(), &current, Some(&previous), None, &params, None, true, false, None)
                .unwrap();
        for k in 0..n {
            for a in 0..6 {
                let expected = plain.corrections.values[k][a] + 0.5 * (current.values[k][a] - previous.values[k][a]);
                assert!((carried.corrections.values[k][a] - expected).abs() < 1e-15, "anchor {k}, unknown {a}");
            }
        }
        let frozen =
            solve_trajectory(std::iter::empty(), &current, Some(&previous), None, &params, None, false, false, None)
                .unwrap();
        for k in 0..n {
            assert_eq!(frozen.corrections.values[k][5], current.values[k][5], "rotation must stay fixed");
            assert!((frozen.corrections.values[k][0] - plain.corrections.values[k][0] - 0.005).abs() < 1e-9);
        }
    }

    /// `extend_corrections` gives the unobserved anchors what `solve_trajectory` gives them
    /// with the estimated anchors pinned by observations and the prior made negligible,
    /// curvature on and off; the trend carries on with curvature and the end is held without it.
    #[test]
    fn extended_corrections_match_the_solve_with_the_estimated_anchors_pinned() {
        let slope = [0.002, -0.001, 0.0005, 2e-6, -1e-6, 3e-6];
        let estimated: Vec<[f64; 6]> = (0..8)
            .map(|i| {
                std::array::from_fn(|a| {
                    0.1 * (a as f64 - 2.0) + slope[a] * i as f64 + 1e-4 * (i * i) as f64 * (a % 2) as f64
                })
            })
            .collect();
        let corrections = TrajectoryCorrections { first_anchor: 30, values: estimated.clone() };
        let with = Parameters {
            weak_information_ratio: 0.0,
            sigma_prior_position_m: 1e6,
            sigma_prior_rotation_deg: 1e6,
            // The heading's too (0: the tilt's).
            sigma_prior_heading_deg: 0.0,
            ..Default::default()
        };
        let without = Parameters { sigma_curvature_position_m: 0.0, sigma_curvature_rotation_deg: 0.0, ..with.clone() };
        for params in [&with, &without] {
            let range = (17, 51);
            let extended = extend_corrections(&corrections, range, params);
            assert_eq!((extended.first_anchor, extended.last_anchor()), range);
            assert_eq!(&extended.values[13..21], &estimated[..], "estimated anchors unchanged");
            // The same problem through the trajectory solve: the estimated anchors pinned by
            // observations a million times stiffer than the curvature term.
            let blocks: Vec<AnchorBlock> = (0..8)
                .map(|i| {
                    let mut b = AnchorBlock::new(30 + i as u32);
                    for a in 0..6 {
                        let w = if a < 3 { 1e16 } else { 1e20 };
                        b.diag[sym_index(a, a)] = w;
                        b.rhs[a] = w * estimated[i][a];
                    }
                    b.observations = 1;
                    b
                })
                .collect();
            let current = TrajectoryCorrections::zeros(range.0, range.1);
            let solved =
                solve_trajectory(&blocks, &current, None, None, params, None, true, false, None).unwrap().corrections;
            for (k, (e, s)) in extended.values.iter().zip(&solved.values).enumerate() {
                for a in 0..6 {
                    let scale = if a < 3 { 1e-6 } else { 1e-9 };
                    assert!(
                        (e[a] - s[a]).abs() < scale,
                        "anchor {}, unknown {a}: {} against {}",
                        range.0 + k as u32,
                        e[a],
                        s[a]
                    );
                }
            }
            let run_out = extended.values[34][0] - extended.values[20][0];
            if params.sigma_curvature_position_m > 0.0 {
                // The end's slope (0.002 per anchor in unknown 0) carries on, fading slowly.
                assert!(run_out > 0.8 * 14.0 * 0.002 && run_out < 14.0 * 0.002, "run-out {run_out}");
            } else {
                assert!(run_out.abs() < 1e-9, "run-out {run_out}");
            }
        }
        // Nothing to extend, or a single anchor: held ends.
        assert_eq!(extend_corrections(&corrections, (30, 37), &with), corrections);
        // A single anchor has no slope to carry: it is held, the attitude too (the default
        // attitude prior, tight against the smoothness, does not pull it back).
        let single = TrajectoryCorrections { first_anchor: 5, values: vec![[0.01, 0.01, 0.01, 1e-5, 1e-5, 1e-5]] };
        let extended = extend_corrections(&single, (0, 9), &Parameters::default());
        assert_eq!(extended.values.len(), 10);
        for v in &extended.values {
            assert!(v.iter().zip(&single.values[0]).all(|(x, y)| (x - y).abs() < 1e-9 * y.abs()), "{extended:?}");
        }
    }

    /// Each anchor's own prior: the campaign's weights given per anchor change nothing, and
    /// anchors held tighter move less far towards what their data say.
    #[test]
    fn per_anchor_prior_weights_replace_the_campaigns() {
        let params = Parameters { weak_information_ratio: 0.0, ..Default::default() };
        let current = TrajectoryCorrections { first_anchor: 7, values: vec![[0.0; 6]; 41] };
        // Data at every anchor asking for 0.5 m in x, as firmly as the campaign's prior.
        let w = campaign_prior_weights(&params)[0];
        let blocks: Vec<AnchorBlock> = (7..48)
            .map(|anchor| {
                let mut b = AnchorBlock::new(anchor);
                b.diag[sym_index(0, 0)] = w;
                b.rhs[0] = w * 0.5;
                b.observations = 1;
                b
            })
            .collect();
        let solve = |prior: Option<&[[f64; 6]]>| {
            solve_trajectory(blocks.iter(), &current, None, None, &params, prior, true, true, None).unwrap()
        };
        let plain = solve(None);
        let campaign = vec![campaign_prior_weights(&params); 41];
        assert_eq!(solve(Some(&campaign)), plain);
        assert!((plain.corrections.values[0][0] - 0.25).abs() < 1e-9, "{:?}", plain.corrections.values[0]);
        let mut tighter = campaign.clone();
        for w in &mut tighter[20..] {
            w[0] *= 100.0;
        }
        let held = solve(Some(&tighter));
        for k in 0..41 {
            let (p, h) = (plain.corrections.values[k][0], held.corrections.values[k][0]);
            assert!(h <= p + 1e-12, "anchor {k}: {h} vs {p}");
        }
        // Where the weights are a hundred times larger the data barely move the anchors (the
        // smoothness to the looser ones adds a little).
        for k in 25..41 {
            assert!(held.corrections.values[k][0] < 0.02, "anchor {k}: {:?}", held.corrections.values[k]);
        }
        // The posterior σ follows the prior.
        let sigma = |s: &TrajectorySolution, k: usize| s.covariance.as_ref().unwrap()[k].sigma()[0];
        assert!(sigma(&held, 40) < 0.5 * sigma(&plain, 40), "{} vs {}", sigma(&held, 40), sigma(&plain, 40));
    }

    /// Without observations, the curvature term removes a kink from a correction profile.
    #[test]
    fn curvature_removes_a_kink() {
        let n = 9;
        let params = Parameters { weak_information_ratio: 0.0, ..Default::default() };
        let straight: Vec<[f64; 6]> = (0..n).map(|i| [0.01 * i as f64, 0.0, 0.0, 0.0, 0.0, 0.0]).collect();
        // No observations: only prior, smoothness and curvature act.
        let mut kinked = straight;
        kinked[4][0] += 0.05;
        let current_kinked = TrajectoryCorrections { first_anchor: 0, values: kinked };
        let sol_kinked =
            solve_trajectory(std::iter::empty(), &current_kinked, None, None, &params, None, true, false, None)
                .unwrap();
        let second = |v: &[[f64; 6]], i: usize| v[i - 1][0] - 2.0 * v[i][0] + v[i + 1][0];
        assert!(second(&current_kinked.values, 4).abs() > 0.09);
        assert!(second(&sol_kinked.corrections.values, 4).abs() < 0.001, "kink not removed");
    }

    /// The joint solve of two trajectories with shared calibration unknowns — each trajectory's
    /// share, the calibration's Schur step and the shares moved by it — equals a dense solve of
    /// the whole bordered system, prior, smoothness and curvature included.
    #[test]
    fn joint_calibration_solve_matches_the_dense_bordered_system() {
        use crate::calibration::{solve_calibration, CalibrationNormals};
        use precimap_core::{CalibrationOptions, CalibrationUnknown};
        let mut seed = 11u64;
        let mut rand = move || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let options = CalibrationOptions {
            estimate: vec![CalibrationUnknown::Boresight],
            tolerance_boresight_deg: 1e9,
            ..Default::default()
        };
        let layout = options.layout(1);
        let k = layout.len();
        let params = Parameters { weak_information_ratio: 0.0, ..Default::default() };
        let n = 5;
        let mut trajectories = Vec::new();
        for t in 0..2 {
            let mut blocks: Vec<AnchorBlock> = (0..n as u32).map(AnchorBlock::new).collect();
            let mut normals = CalibrationNormals::zeros(k);
            for b in &mut blocks {
                b.cross = vec![0.0; 6 * k];
            }
            for i in 0..n - 1 {
                for _ in 0..12 {
                    let g: [f64; 6] = std::array::from_fn(|a| rand() * if a < 3 { 1.0 } else { 10.0 });
                    let gc: Vec<f64> = (0..k).map(|_| rand() * 10.0).collect();
                    let (l, e, w) = (rand() + 0.5, rand() * 0.01, 1e3 * (1.0 + t as f64));
                    for a in 0..6 {
                        for c in a..6 {
                            let q = w * g[a] * g[c];
                            blocks[i].diag[sym_index(a, c)] += (1.0 - l) * (1.0 - l) * q;
                            blocks[i].next[sym_index(a, c)] += l * (1.0 - l) * q;
                            blocks[i + 1].diag[sym_index(a, c)] += l * l * q;
                        }
                        blocks[i].rhs[a] -= w * (1.0 - l) * g[a] * e;
                        blocks[i + 1].rhs[a] -= w * l * g[a] * e;
                        for j in 0..k {
                            blocks[i].cross[a * k + j] += w * (1.0 - l) * g[a] * gc[j];
                            blocks[i + 1].cross[a * k + j] += w * l * g[a] * gc[j];
                        }
                    }
                    normals.add_observation(0, &gc, w * e, w);
                }
            }
            trajectories.push((blocks, normals));
        }
        let current = TrajectoryCorrections { first_anchor: 0, values: vec![[0.0; 6]; n] };
        let solve = |blocks: &[AnchorBlock], normals: Option<&CalibrationNormals>| {
            solve_trajectory(blocks, &current, None, None, &params, None, true, false, normals).unwrap()
        };
        let mut solutions: Vec<_> = trajectories.iter().map(|(b, c)| solve(b, Some(c))).collect();
        let step = solve_calibration(
            solutions.iter().map(|s| s.calibration.as_ref().unwrap()),
            &vec![0.0; k],
            &layout,
            &options,
        )
        .unwrap();
        assert!(step.determined.iter().all(|&d| d));
        for s in &mut solutions {
            apply_calibration_step(s, &step.delta, &current);
        }
        // The dense reference: each trajectory's matrix from its solves of unit right-hand sides.
        let m = 6 * n;
        let total = 2 * m + k;
        let mut dense = DMatrix::<f64>::zeros(total, total);
        let mut rhs = DVector::<f64>::zeros(total);
        for (t, (blocks, normals)) in trajectories.iter().enumerate() {
            let mut inverse = DMatrix::<f64>::zeros(m, m);
            for col in 0..m {
                let mut probe: Vec<AnchorBlock> =
                    blocks.iter().map(|b| AnchorBlock { rhs: [0.0; 6], cross: Vec::new(), ..b.clone() }).collect();
                probe[col / 6].rhs[col % 6] = 1.0;
                let x = solve(&probe, None).corrections.values;
                for row in 0..m {
                    inverse[(row, col)] = x[row / 6][row % 6];
                }
            }
            let h = inverse.try_inverse().unwrap();
            dense.view_mut((t * m, t * m), (m, m)).copy_from(&h);
            for (a, b) in blocks.iter().enumerate() {
                for r in 0..6 {
                    rhs[t * m + a * 6 + r] = b.rhs[r];
                    for j in 0..k {
                        dense[(t * m + a * 6 + r, 2 * m + j)] = b.cross[r * k + j];
                        dense[(2 * m + j, t * m + a * 6 + r)] = b.cross[r * k + j];
                    }
                }
            }
            for i in 0..k {
                rhs[2 * m + i] += normals.b[i];
                for j in 0..k {
                    dense[(2 * m + i, 2 * m + j)] += normals.h[i * k + j];
                }
            }
        }
        let prior = 1.0 / options.prior_boresight_deg.to_radians().powi(2);
        for i in 0..k {
            dense[(2 * m + i, 2 * m + i)] += prior;
        }
        let exact = dense.lu().solve(&rhs).unwrap();
        for i in 0..k {
            let want = exact[2 * m + i];
            assert!(
                (step.delta[i] - want).abs() < 1e-9 * want.abs().max(1e-6),
                "unknown {i}: {} against {want}",
                step.delta[i]
            );
        }
        for (t, s) in solutions.iter().enumerate() {
            for a in 0..n {
                for r in 0..6 {
                    let want = exact[t * m + a * 6 + r];
                    let got = s.corrections.values[a][r];
                    assert!(
                        (got - want).abs() < 1e-9 * want.abs().max(1e-6),
                        "trajectory {t} anchor {a}: {got} against {want}"
                    );
                }
            }
        }
    }
}
