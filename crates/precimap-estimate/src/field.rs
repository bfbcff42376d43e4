//! The common-mode field: the coarse level of a two-level estimation (docs/design/estimation.md,
//! "The common-mode field").
//!
//! Alternating least squares moves a correction that every pass at a place shares by only a
//! few per cent per iteration: the latent map follows the strips, so only the GNSS/IMU prior and
//! the small disagreement between scan heads that see a place from different vehicle positions
//! resist it. The field is that mode made explicit: a translation `c(x, y)`, bilinear between
//! nodes on a square grid, added to every trajectory's correction at its anchors' horizontal
//! positions. Its least-squares problem eliminates the map exactly: moving every pass by the
//! field moves a point's latent height by the mean of the passes that build it, so a point's
//! observation row is `n/(n+1) · (φ(v) − φ(v̄))·w` (`v` its scan head's position, `v̄` the mean
//! of the other passes' positions there, `n` their count, `w` the surface normal). A constant
//! field therefore has no data term at all and only the prior decides it, as it must.
//!
//! [`FieldAccumulator`] sums these rows in a tile ([`FieldEquations`], part of the map task's
//! output); [`solve_field`] adds the prior, smoothness and curvature terms of every anchor's
//! translation (exact: they are quadratic in the corrections) and solves the whole field at
//! once. The per-trajectory solves then run on the shifted corrections as the smoother of the
//! two-level method, with the data blocks of the same map task: the map moves with the field,
//! so a point's residual barely changes.
//!
//! With `Parameters::common_mode_heading` the field also has a heading `ψ(x, y)` on the same
//! nodes, added to every anchor's rotation about the vertical: every pass at a place turning
//! with the map (a constant `ψ` with the translation `ψ ez × (x − x0)`) is just as invisible to
//! the strips. A point's heading entry is `k·(φ(v)·((p − v) × w)_z − φ(v̄)·((p − v̄) × w)_z)`,
//! each pass turning about its own scan head.
//!
//! The field has three unknowns per node (four with the heading), nodes every
//! `common_mode_field_m` where anchors or observations reach, each coupled only to the nodes
//! near it: its normal equations are solved
//! by a sparse Cholesky in approximate-minimum-degree order (`precimap_solve::sparse`, faer),
//! whose factor grows about as n log n on a street network.
//!
//! With `Parameters::campaign_motion` the same solve also gives one rotation of the whole
//! campaign ([`CampaignMotion`]): with the field's constant part, the rigid motion no residual
//! sees, which only the anchors' prior, smoothness and curvature decide. Three unknowns border
//! the sparse system and are eliminated through its Schur complement.

use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::geom::floor;

mod accumulator;
mod run;
mod solution;
mod solve;

pub use accumulator::{FieldAccumulator, FieldEquations, FieldRow};
pub use solution::{CampaignMotion, FieldLargest, FieldSolution};
pub use solve::{remove_field_share, rotation_axes, solve_field, FieldError, MAX_FIELD_FACTOR_ENTRIES};

/// Grid index of a field node: the node sits at `(ix · spacing, iy · spacing)` (absolute
/// coordinates).
pub type FieldNode = (i64, i64);

/// Bilinear weights of the four nodes around `(x, y)`.
#[inline]
pub fn bilinear(x: f64, y: f64, spacing: f64) -> [(FieldNode, f64); 4] {
    let (fx, fy) = (x / spacing, y / spacing);
    let (ix, iy) = (floor(fx), floor(fy));
    let (tx, ty) = (fx - ix, fy - iy);
    let [n00, n10, n01, n11] = corners((ix as i64, iy as i64));
    [(n00, (1.0 - tx) * (1.0 - ty)), (n10, tx * (1.0 - ty)), (n01, (1.0 - tx) * ty), (n11, tx * ty)]
}

/// The four nodes of the cell with lower-left node `cell`, in the order of [`bilinear`]'s
/// weights.
#[inline]
fn corners(cell: FieldNode) -> [FieldNode; 4] {
    [cell, (cell.0 + 1, cell.1), (cell.0, cell.1 + 1), (cell.0 + 1, cell.1 + 1)]
}

/// Adds `value` to node `index` of a sparse row (a handful of entries, so a linear search).
#[inline]
fn accumulate(row: &mut Vec<(usize, f64)>, index: usize, value: f64) {
    match row.iter_mut().find(|(j, _)| *j == index) {
        Some((_, v)) => *v += value,
        None => row.push((index, value)),
    }
}

/// One trajectory as the field sees it: the position of each anchor of `corrections` (same
/// order; the field acts at the horizontal one, the campaign's rotation about the centre of all
/// of them), the current corrections, and each anchor's prior weights when it has its own (as
/// `crate::solve_trajectory` takes them; `None`: the campaign's), and its own curvature σ's
/// where the campaign estimates them (`None`: the campaign's).
#[derive(Debug)]
pub struct FieldTrajectory<'a> {
    pub positions: &'a [[f64; 3]],
    pub corrections: &'a TrajectoryCorrections,
    pub prior: Option<&'a [[f64; 6]]>,
    pub curvature: Option<&'a crate::CurvatureModel>,
}

#[cfg(test)]
mod tests;
