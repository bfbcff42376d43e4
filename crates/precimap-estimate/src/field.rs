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
//! by a sparse Cholesky in nested-dissection order, cut straight across the street network at the
//! nodes' grid positions (`precimap_solve::sparse`), whose factor grows about as n log n.
//!
//! With `Parameters::campaign_motion` the same solve also gives one rotation of the whole
//! campaign ([`CampaignMotion`]): with the field's constant part, the rigid motion no residual
//! sees, which only the anchors' prior, smoothness and curvature decide. Three unknowns border
//! the sparse system and are eliminated through its Schur complement.

use precimap_core::corrections::TrajectoryCorrections;

use crate::tile::{cross, dot, normalize};
use precimap_core::geom::{floor, skew, Mat3, Vec3};
use precimap_core::Parameters;
use precimap_solve::sparse::{SparseError, SymmetricSparse};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

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

/// Slots of a row: the four corners of the point's own cell, then the four of the other
/// passes' cell.
const SLOTS: usize = 8;
/// Slot pairs `s ≤ t`, row-major.
const SLOT_PAIRS: usize = SLOTS * (SLOTS + 1) / 2;

/// The field's data normal equations from one tile: `H` as 3×3 blocks over node pairs
/// (`a ≤ b`, indices into `nodes`, row-major), `rhs = −Σ ω·row·e`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FieldEquations {
    pub nodes: Vec<FieldNode>,
    pub pairs: Vec<(u32, u32, [f64; 9])>,
    pub rhs: Vec<[f64; 3]>,
    pub observations: u64,
    /// With the field's heading ([`FieldAccumulator::with_heading`]), one entry per entry of
    /// `pairs` (`a ≤ b`): node `a`'s translation with node `b`'s heading (3), `a`'s heading with
    /// `b`'s translation (3), heading with heading. Empty without.
    #[serde(default)]
    pub heading_pairs: Vec<[f64; 7]>,
    /// With the heading, its right-hand side per node; empty without.
    #[serde(default)]
    pub heading_rhs: Vec<f64>,
    /// With the field's tilt ([`FieldAccumulator::with_tilt`], always with the heading), one
    /// entry per entry of `pairs` (`a ≤ b`; τ the rotations about x and y, ψ the heading),
    /// row-major: `t_a × τ_b` (3×2), `τ_a × t_b` (2×3), `ψ_a × τ_b` (2), `τ_a × ψ_b` (2),
    /// `τ_a × τ_b` (2×2). Empty without.
    #[serde(default)]
    pub tilt_pairs: Vec<[f64; 20]>,
    /// With the tilt, its right-hand side per node (about x, about y); empty without.
    #[serde(default)]
    pub tilt_rhs: Vec<[f64; 2]>,
}

/// Sums observation rows in a tile. A tile's points see a handful of nodes, so the nodes are a
/// short list and `H` is dense over them.
///
/// A row is `r ⊗ w`: per node a scalar `r` (the bilinear weights times `±k`) times the surface
/// normal `w`, so its product is `(r rᵀ) ⊗ (w wᵀ)`. Consecutive points mostly lie on one surface
/// model (one `w`) with both positions in the same two cells, so a *run* of such rows sums only
/// `ω r rᵀ` and `ω r e` over the eight corner slots (44 products a row, where the 3×3 blocks
/// took 216) and multiplies by `w wᵀ` and `w` once, when the run ends. A slot's node is created
/// when the run ends, and only if a row reached it with a non-zero weight.
///
/// A rotation's entry varies with each point's lever arm `(p − v) × w`, so the run sums it per
/// point: the heading alone needs its z component (one number per slot); the whole rotation
/// (heading and tilt) needs the lever's two components in a basis `u₁, u₂` of the plane normal to
/// `w`, where every lever lies, and the run's end turns them into the three axes.
#[derive(Debug)]
pub struct FieldAccumulator {
    spacing: f64,
    nodes: Vec<FieldNode>,
    /// Upper triangles `[xx, xy, xz, yy, yz, zz]` of the 3×3 blocks, row-major over node pairs.
    h: Vec<[f64; 6]>,
    rhs: Vec<[f64; 3]>,
    /// With the heading: its terms per node pair `a ≤ b` as in [`FieldEquations::heading_pairs`]
    /// (row-major like `h`), and its right-hand side per node. `None` without.
    heading: Option<(Vec<[f64; 7]>, Vec<f64>)>,
    /// With the tilt: its terms as in [`FieldEquations::tilt_pairs`], and its right-hand side.
    tilt: Option<TiltSums>,
    observations: u64,
    run: Run,
    /// Per position of a row (the point's scan head, the other passes' mean), the cell it fell
    /// in last and the indices of that cell's four nodes ([`UNKNOWN`] until looked up):
    /// consecutive runs mostly share their cells, and the look-up is a search of `nodes`.
    cells: [(FieldNode, [usize; 4]); 2],
}

/// The tilt's terms per node pair (row-major, as `h`) and its right-hand side per node.
type TiltSums = (Vec<[f64; 20]>, Vec<[f64; 2]>);

/// One observation row of the field: residual `e` and weight `weight`; the point's own scan head
/// at `vehicle`, the mean of the other passes' at `others`, whose share in the latent height is
/// `k` (`n/(n+1)` for `n` other passes); surface normal `w`; `lever` the point's own Jacobian for
/// a rotation, `(p − v) × w`, which only the heading (its z component) and the tilt use. An
/// `anchored` row compares the point with a fixed target (ground control) instead of the other
/// passes: its row is `φ(v)·w` alone (`k` 1, `others` unused).
#[derive(Clone, Copy, Debug)]
pub struct FieldRow {
    pub vehicle: [f64; 2],
    pub others: [f64; 2],
    pub k: f64,
    pub w: [f64; 3],
    pub e: f64,
    pub weight: f64,
    pub lever: [f64; 3],
    pub anchored: bool,
}

/// Most lever components a run sums per slot (the whole rotation's two).
const LEVER_COMPONENTS: usize = 2;
/// Rotation entries of a row: per slot, its lever components.
const ROTATION_ENTRIES: usize = SLOTS * LEVER_COMPONENTS;

/// The rows summed since the surface normal or either cell last changed.
#[derive(Debug)]
struct Run {
    /// Own cell, other passes' cell (their lower-left nodes) and the normal's bits.
    key: Option<(FieldNode, FieldNode, [u64; 3])>,
    w: [f64; 3],
    /// With the tilt, the basis of the plane normal to `w` the levers are summed in.
    basis: [[f64; 3]; LEVER_COMPONENTS],
    /// `Σ ω r_s r_t` over slot pairs `s ≤ t` and `Σ ω r_s e` per slot.
    rr: [f64; SLOT_PAIRS],
    re: [f64; SLOTS],
    /// With a rotation, whose row entries `h_q` (`q = s·m + i`: slot `s`, lever component `i` of
    /// `m`) vary with the point's lever arm: `Σ ω r_s h_q` (row-major over `s` and `q`),
    /// `Σ ω h_q h_q'` over `q ≤ q'` and `Σ ω h_q e`.
    rh: [f64; SLOTS * ROTATION_ENTRIES],
    hh: [f64; ROTATION_ENTRIES * (ROTATION_ENTRIES + 1) / 2],
    he: [f64; ROTATION_ENTRIES],
    /// A row reached the slot with a non-zero weight.
    reached: [bool; SLOTS],
    /// The slot of each corner of the other passes' cell: its own (4 + corner) or, for a node
    /// the two cells share, the point's cell's slot of it.
    slot: [usize; 4],
}

impl Run {
    fn new() -> Self {
        Self {
            key: None,
            w: [0.0; 3],
            basis: [[0.0; 3]; LEVER_COMPONENTS],
            rr: [0.0; SLOT_PAIRS],
            re: [0.0; SLOTS],
            rh: [0.0; SLOTS * ROTATION_ENTRIES],
            hh: [0.0; ROTATION_ENTRIES * (ROTATION_ENTRIES + 1) / 2],
            he: [0.0; ROTATION_ENTRIES],
            reached: [false; SLOTS],
            slot: [4, 5, 6, 7],
        }
    }
}

impl Run {
    /// A row's rotation entries, `M` lever components per slot (1: the heading's z component;
    /// 2: the whole rotation's, in the plane normal to `w`), added to the run's sums. `dv` is
    /// the point's scan head less the other passes' mean, `r` the row's translation weights.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn add_rotation<const M: usize>(
        &mut self,
        own: [f64; 4],
        other: [f64; 4],
        [k, k_others]: [f64; 2],
        r: &[f64; SLOTS],
        dv: [f64; 2],
        lever: [f64; 3],
        e: f64,
        weight: f64,
    ) {
        // Turning a pass by ρ about its scan head `v` moves the point along its normal by
        // ρ·((p − v) × w); the other passes turn about theirs, `v̄`, so their lever adds
        // (v − v̄) × w (horizontal positions: the heads' heights differ little).
        let w = self.w;
        let lever_others = [lever[0] + dv[1] * w[2], lever[1] - dv[0] * w[2], lever[2] + dv[0] * w[1] - dv[1] * w[0]];
        let (mut own_arm, mut other_arm) = ([0.0; M], [0.0; M]);
        if M == 1 {
            (own_arm[0], other_arm[0]) = (lever[2], lever_others[2]);
        } else {
            for i in 0..M {
                own_arm[i] = dot(lever, self.basis[i]);
                other_arm[i] = dot(lever_others, self.basis[i]);
            }
        }
        let mut h = [0.0; ROTATION_ENTRIES];
        for c in 0..4 {
            for i in 0..M {
                h[c * M + i] = k * own[c] * own_arm[i];
            }
        }
        for c in 0..4 {
            let slot = self.slot[c];
            for i in 0..M {
                h[slot * M + i] -= k_others * other[c] * other_arm[i];
            }
        }
        let entries = SLOTS * M;
        for s in 0..SLOTS {
            let ws = weight * r[s];
            for q in 0..entries {
                self.rh[s * entries + q] += ws * h[q];
            }
        }
        let mut pair = 0;
        for q in 0..entries {
            let wh = weight * h[q];
            self.he[q] += wh * e;
            for &hq in &h[q..entries] {
                self.hh[pair] += wh * hq;
                pair += 1;
            }
        }
    }

    /// Empties the sums for the next run, only as far as `M` lever components used them.
    #[inline(always)]
    fn reset<const M: usize>(&mut self) {
        let entries = SLOTS * M;
        self.key = None;
        self.rr = [0.0; SLOT_PAIRS];
        self.re = [0.0; SLOTS];
        self.rh[..SLOTS * entries].fill(0.0);
        self.hh[..entries * (entries + 1) / 2].fill(0.0);
        self.he[..entries].fill(0.0);
        self.reached = [false; SLOTS];
        self.slot = [4, 5, 6, 7];
    }
}

/// `square`, row-major `n × n` with `n = old`, grown to `(n + 1) × (n + 1)` with zeros.
fn grow_square<T: Copy + Default>(square: &mut Vec<T>, old: usize) {
    let new = old + 1;
    let mut grown = vec![T::default(); new * new];
    for a in 0..old {
        grown[a * new..a * new + old].copy_from_slice(&square[a * old..(a + 1) * old]);
    }
    *square = grown;
}

/// A node index not looked up yet.
const UNKNOWN: usize = usize::MAX;

/// The four bilinear weights of [`bilinear`] at `(x, y)` and the lower-left node of its cell.
#[inline]
fn cell_weights(x: f64, y: f64, spacing: f64) -> (FieldNode, [f64; 4]) {
    let weights = bilinear(x, y, spacing);
    (weights[0].0, weights.map(|(_, phi)| phi))
}

/// An orthonormal basis of the plane normal to the unit vector `w`.
fn plane_basis(w: [f64; 3]) -> [[f64; 3]; 2] {
    // Crossed with the axis it is least aligned with, for a well-conditioned first vector.
    let axis = if w[0].abs() <= w[1].abs() && w[0].abs() <= w[2].abs() {
        [1.0, 0.0, 0.0]
    } else if w[1].abs() <= w[2].abs() {
        [0.0, 1.0, 0.0]
    } else {
        [0.0, 0.0, 1.0]
    };
    let u1 = normalize(cross(w, axis));
    [u1, cross(w, u1)]
}

impl FieldAccumulator {
    pub fn new(spacing: f64) -> Self {
        Self {
            spacing,
            nodes: Vec::new(),
            h: Vec::new(),
            rhs: Vec::new(),
            heading: None,
            tilt: None,
            observations: 0,
            run: Run::new(),
            cells: [((i64::MIN, i64::MIN), [UNKNOWN; 4]); 2],
        }
    }

    fn index(&mut self, node: FieldNode) -> usize {
        if let Some(i) = self.nodes.iter().position(|&n| n == node) {
            return i;
        }
        let old = self.nodes.len();
        grow_square(&mut self.h, old);
        if let Some((pairs, rhs)) = self.heading.as_mut() {
            grow_square(pairs, old);
            rhs.push(0.0);
        }
        if let Some((pairs, rhs)) = self.tilt.as_mut() {
            grow_square(pairs, old);
            rhs.push([0.0; 2]);
        }
        self.nodes.push(node);
        self.rhs.push([0.0; 3]);
        old
    }

    /// An accumulator that also sums the field's heading rows (`Parameters::common_mode_heading`).
    pub fn with_heading(spacing: f64) -> Self {
        Self { heading: Some((Vec::new(), Vec::new())), ..Self::new(spacing) }
    }

    /// An accumulator that sums the field's whole rotation, heading and tilt
    /// (`Parameters::common_mode_tilt`).
    pub fn with_tilt(spacing: f64) -> Self {
        Self { tilt: Some((Vec::new(), Vec::new())), ..Self::with_heading(spacing) }
    }

    /// Lever components summed per slot: 0 without a rotation, 1 (the z component) for the
    /// heading alone, 2 (in the plane normal to `w`) for the whole rotation.
    #[inline]
    fn lever_components(&self) -> usize {
        match (self.heading.is_some(), self.tilt.is_some()) {
            (_, true) => 2,
            (true, false) => 1,
            (false, false) => 0,
        }
    }

    /// One observation (see [`FieldRow`]).
    #[inline]
    pub fn add(&mut self, row: FieldRow) {
        // Monomorphised per lever count; the whole rotation's out of line, so that the default's
        // inlined row loop stays as small as before the tilt.
        match self.lever_components() {
            0 => self.add_with::<0>(row),
            1 => self.add_with::<1>(row),
            _ => self.add_with_tilt(row),
        }
    }

    /// [`Self::add_with`] for the whole rotation, kept out of the callers' inlined loops.
    #[inline(never)]
    fn add_with_tilt(&mut self, row: FieldRow) {
        self.add_with::<2>(row);
    }

    #[inline(always)]
    fn add_with<const M: usize>(&mut self, row: FieldRow) {
        let FieldRow { vehicle, others, k, w, e, weight, lever, anchored } = row;
        // A fixed target does not move with the field: the other passes' part vanishes.
        let (others, k_others) = if anchored { (vehicle, 0.0) } else { (others, k) };
        let (own_cell, own) = cell_weights(vehicle[0], vehicle[1], self.spacing);
        let (other_cell, other) = cell_weights(others[0], others[1], self.spacing);
        let key = (own_cell, other_cell, w.map(f64::to_bits));
        if self.run.key != Some(key) {
            self.end_run_with::<M>();
            self.run.key = Some(key);
            self.run.w = w;
            if M == 2 {
                self.run.basis = plane_basis(w);
            }
            // A corner both cells share is one slot, so that the row's two weights there are
            // summed first, as one node's entry (a row whose positions coincide is exactly zero).
            let own_corners = corners(own_cell);
            for (c, node) in corners(other_cell).iter().enumerate() {
                self.run.slot[c] = own_corners.iter().position(|n| n == node).unwrap_or(4 + c);
            }
        }
        let run = &mut self.run;
        let mut r = [0.0; SLOTS];
        for c in 0..4 {
            r[c] = k * own[c];
            run.reached[c] |= own[c] != 0.0;
        }
        for c in 0..4 {
            let slot = run.slot[c];
            r[slot] += -k_others * other[c];
            run.reached[slot] |= k_others != 0.0 && other[c] != 0.0;
        }
        let mut pair = 0;
        for s in 0..SLOTS {
            let ws = weight * r[s];
            run.re[s] += ws * e;
            for &rt in &r[s..] {
                run.rr[pair] += ws * rt;
                pair += 1;
            }
        }
        if M > 0 {
            run.add_rotation::<M>(
                own,
                other,
                [k, k_others],
                &r,
                [vehicle[0] - others[0], vehicle[1] - others[1]],
                lever,
                e,
                weight,
            );
        }
        self.observations += 1;
    }

    /// Adds the current run's sums to `H` and the right-hand side.
    fn end_run(&mut self) {
        // Monomorphised per lever count, so that the default's run ends carry no branches or
        // sizes of the others.
        match self.lever_components() {
            0 => self.end_run_with::<0>(),
            1 => self.end_run_with::<1>(),
            _ => self.end_run_with::<2>(),
        }
    }

    fn end_run_with<const M: usize>(&mut self) {
        let Some((own_cell, other_cell, _)) = self.run.key.take() else { return };
        let mut node = [UNKNOWN; SLOTS];
        for (position, cell) in [own_cell, other_cell].into_iter().enumerate() {
            if self.cells[position].0 != cell {
                self.cells[position] = (cell, [UNKNOWN; 4]);
            }
            for (corner, at) in corners(cell).into_iter().enumerate() {
                let slot = 4 * position + corner;
                if !self.run.reached[slot] {
                    continue;
                }
                let mut i = self.cells[position].1[corner];
                if i == UNKNOWN {
                    i = self.index(at);
                    self.cells[position].1[corner] = i;
                }
                node[slot] = i;
            }
        }
        let n = self.nodes.len();
        let q_count = SLOTS * M;
        let w = self.run.w;
        let ww = [w[0] * w[0], w[0] * w[1], w[0] * w[2], w[1] * w[1], w[1] * w[2], w[2] * w[2]];
        // The whole rotation's sums in the three axes: lever components back through the basis.
        let run = &self.run;
        let to_axes =
            |c: &[f64]| -> [f64; 3] { std::array::from_fn(|j| run.basis[0][j] * c[0] + run.basis[1][j] * c[1]) };
        // `Σ ω h_q h_q'` for any q, q' (stored for q ≤ q').
        let hh = |q: usize, p: usize| {
            let (lo, hi) = (q.min(p), q.max(p));
            run.hh[lo * q_count - lo * (lo.saturating_sub(1)) / 2 + (hi - lo)]
        };
        let mut pair = 0;
        for s in 0..SLOTS {
            let a = node[s];
            if a == UNKNOWN {
                pair += SLOTS - s;
                continue;
            }
            for c in 0..3 {
                self.rhs[a][c] -= run.re[s] * w[c];
            }
            if M > 0 {
                // The rotation's right-hand side in the three axes (the heading alone: z only).
                let he = if M == 1 { [0.0, 0.0, run.he[s]] } else { to_axes(&run.he[2 * s..2 * s + 2]) };
                if let Some((_, rhs)) = self.heading.as_mut() {
                    rhs[a] -= he[2];
                }
                if let Some((_, rhs)) = self.tilt.as_mut() {
                    rhs[a][0] -= he[0];
                    rhs[a][1] -= he[1];
                }
            }
            for t in s..SLOTS {
                let (b, sum) = (node[t], run.rr[pair]);
                pair += 1;
                if b == UNKNOWN {
                    continue;
                }
                let block = &mut self.h[a.min(b) * n + a.max(b)];
                for c in 0..6 {
                    block[c] += sum * ww[c];
                }
                if M > 0 {
                    // Slot s's translation with t's rotation (`w cᵀ`), s's rotation with t's
                    // translation, and rotation with rotation, each in the three axes (the
                    // heading alone: their z parts only).
                    let (st, ts, rr) = if M == 1 {
                        let mut rr = [[0.0; 3]; 3];
                        rr[2][2] = hh(s, t);
                        ([0.0, 0.0, run.rh[s * SLOTS + t]], [0.0, 0.0, run.rh[t * SLOTS + s]], rr)
                    } else {
                        let mut rr = [[0.0; 3]; 3];
                        for (i, ui) in run.basis.iter().enumerate() {
                            for (l, ul) in run.basis.iter().enumerate() {
                                let v = hh(2 * s + i, 2 * t + l);
                                for j in 0..3 {
                                    for o in 0..3 {
                                        rr[j][o] += v * ui[j] * ul[o];
                                    }
                                }
                            }
                        }
                        (
                            to_axes(&run.rh[s * q_count + 2 * t..s * q_count + 2 * t + 2]),
                            to_axes(&run.rh[t * q_count + 2 * s..t * q_count + 2 * s + 2]),
                            rr,
                        )
                    };
                    // The stored pair is (min, max): seen from the smaller node's side.
                    let (first, second, rot) = if a <= b {
                        (st, ts, rr)
                    } else {
                        (ts, st, std::array::from_fn(|j| std::array::from_fn(|o| rr[o][j])))
                    };
                    let at = a.min(b) * n + a.max(b);
                    if let Some((pairs, _)) = self.heading.as_mut() {
                        let x = &mut pairs[at];
                        for c in 0..3 {
                            x[c] += first[2] * w[c];
                            x[3 + c] += second[2] * w[c];
                        }
                        x[6] += rot[2][2];
                    }
                    if let Some((pairs, _)) = self.tilt.as_mut() {
                        let y = &mut pairs[at];
                        for j in 0..2 {
                            for c in 0..3 {
                                y[c * 2 + j] += first[j] * w[c];
                                y[6 + j * 3 + c] += second[j] * w[c];
                            }
                            y[12 + j] += rot[2][j];
                            y[14 + j] += rot[j][2];
                            for l in 0..2 {
                                y[16 + 2 * j + l] += rot[j][l];
                            }
                        }
                    }
                }
            }
        }
        self.run.reset::<M>();
    }

    pub fn finish(mut self) -> FieldEquations {
        self.end_run();
        let n = self.nodes.len();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by_key(|&i| self.nodes[i]);
        let mut rank = vec![0u32; n];
        for (r, &i) in order.iter().enumerate() {
            rank[i] = r as u32;
        }
        let mut pairs = Vec::new();
        for a in 0..n {
            for b in a..n {
                let u = self.h[a * n + b];
                let x = self.heading.as_ref().map_or([0.0; 7], |(h, _)| h[a * n + b]);
                let y = self.tilt.as_ref().map_or([0.0; 20], |(t, _)| t[a * n + b]);
                if u.iter().chain(&x).chain(&y).all(|&v| v == 0.0) {
                    continue;
                }
                // The accumulator kept the upper triangle of each 3×3 (ww is symmetric).
                let m = [u[0], u[1], u[2], u[1], u[3], u[4], u[2], u[4], u[5]];
                let (ra, rb) = (rank[a], rank[b]);
                pairs.push(if ra <= rb { (ra, rb, m, x, y) } else { (rb, ra, m, swap_heading(x), swap_tilt(y)) });
            }
        }
        pairs.sort_by_key(|p| (p.0, p.1));
        let heading = self.heading.is_some();
        let tilt = self.tilt.is_some();
        FieldEquations {
            nodes: order.iter().map(|&i| self.nodes[i]).collect(),
            heading_pairs: if heading { pairs.iter().map(|p| p.3).collect() } else { Vec::new() },
            tilt_pairs: if tilt { pairs.iter().map(|p| p.4).collect() } else { Vec::new() },
            pairs: pairs.into_iter().map(|(a, b, m, _, _)| (a, b, m)).collect(),
            rhs: order.iter().map(|&i| self.rhs[i]).collect(),
            heading_rhs: self
                .heading
                .as_ref()
                .map_or_else(Vec::new, |(_, rhs)| order.iter().map(|&i| rhs[i]).collect()),
            tilt_rhs: self.tilt.as_ref().map_or_else(Vec::new, |(_, rhs)| order.iter().map(|&i| rhs[i]).collect()),
            observations: self.observations,
        }
    }
}

/// A pair's heading terms seen from its other node: the two cross parts trade places.
fn swap_heading(x: [f64; 7]) -> [f64; 7] {
    [x[3], x[4], x[5], x[0], x[1], x[2], x[6]]
}

/// A pair's tilt terms seen from its other node (the pair's block transposed).
fn swap_tilt(y: [f64; 20]) -> [f64; 20] {
    let mut out = [0.0; 20];
    for j in 0..2 {
        for c in 0..3 {
            out[c * 2 + j] = y[6 + j * 3 + c];
            out[6 + j * 3 + c] = y[c * 2 + j];
        }
        out[12 + j] = y[14 + j];
        out[14 + j] = y[12 + j];
        for l in 0..2 {
            out[16 + 2 * j + l] = y[16 + 2 * l + j];
        }
    }
    out
}

/// One trajectory as the field sees it: the position of each anchor of `corrections` (same
/// order; the field acts at the horizontal one, the campaign's rotation about the centre of all
/// of them), the current corrections, and each anchor's prior weights when it has its own (as
/// `crate::solve_trajectory` takes them; `None`: the campaign's).
#[derive(Debug)]
pub struct FieldTrajectory<'a> {
    pub positions: &'a [[f64; 3]],
    pub corrections: &'a TrajectoryCorrections,
    pub prior: Option<&'a [[f64; 6]]>,
}

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

/// The motion's part of the field's normal equations: its coupling to every field unknown
/// (`∂²/∂field ∂ω`, three columns), its own block and right-hand side.
struct MotionTerms {
    origin: [f64; 3],
    coupling: Vec<[f64; 3]>,
    own: Mat3,
    rhs: Vec3,
}

impl MotionTerms {
    /// A translation term: residual `Σ row·field + ω × d + value` of weight `w` per axis.
    fn add(&mut self, row: &[(usize, f64)], per_node: usize, d: [f64; 3], value: [f64; 3], w: [f64; 3]) {
        // `∂(ω × d)/∂ω = −[d]×`.
        let m = -skew(&Vec3::from(d));
        for &(node, phi) in row {
            for c in 0..3 {
                for j in 0..3 {
                    self.coupling[per_node * node + c][j] += w[c] * phi * m[(c, j)];
                }
            }
        }
        let weighted = Mat3::from_fn(|j, c| w[c] * m[(c, j)]);
        self.own += weighted * m;
        self.rhs -= weighted * Vec3::from(value);
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

/// Rotation unknowns per node of the field the parameters ask for: none, the heading (1), or
/// heading and tilt (3).
pub fn rotation_axes(params: &Parameters) -> usize {
    match (params.common_mode_heading, params.common_mode_tilt) {
        (false, _) => 0,
        (true, false) => 1,
        (true, true) => 3,
    }
}

/// Numbers, in grid order, the nodes of `seed` and every node an anchor of `trajectories`
/// touches.
fn number_nodes(
    seed: impl IntoIterator<Item = FieldNode>,
    trajectories: &[FieldTrajectory],
    spacing: f64,
) -> BTreeMap<FieldNode, usize> {
    let mut index: BTreeMap<FieldNode, usize> = seed.into_iter().map(|n| (n, 0)).collect();
    for tr in trajectories {
        for p in tr.positions {
            for (n, phi) in bilinear(p[0], p[1], spacing) {
                if phi > 0.0 {
                    index.insert(n, 0);
                }
            }
        }
    }
    for (i, v) in index.values_mut().enumerate() {
        *v = i;
    }
    index
}

/// The grid position of every unknown, `per_node` consecutive unknowns per node in the order of
/// `index`: what the sparse solve's order cuts the street network by.
fn unknown_positions(index: &BTreeMap<FieldNode, usize>, per_node: usize) -> Vec<[f64; 2]> {
    index.keys().flat_map(|&(x, y)| std::iter::repeat_n([x as f64, y as f64], per_node)).collect()
}

/// `previous` moved so that `current − previous` (the step momentum carries on) loses its
/// least-squares fit by a field on the same nodes: the field re-solves that part itself in the
/// next iteration, so carrying it as well overshoots and the two levels fight.
/// `trajectories` hold the current corrections and their anchors' positions; the field has
/// `rotation_axes` rotations per node as well ([`rotation_axes`]: 0, 1 for the heading, 3 with
/// the tilt).
pub fn remove_field_share(
    trajectories: &[FieldTrajectory],
    previous: &[TrajectoryCorrections],
    spacing: f64,
    rotation_axes: usize,
) -> Result<Vec<TrajectoryCorrections>, FieldError> {
    if previous.len() != trajectories.len() {
        return Err(FieldError::Trajectories { expected: trajectories.len(), found: previous.len() });
    }
    for (t, (tr, before)) in trajectories.iter().zip(previous).enumerate() {
        for anchors in [tr.corrections.values.len(), before.values.len()] {
            if anchors != tr.positions.len() {
                return Err(FieldError::Positions { trajectory: t, positions: tr.positions.len(), anchors });
            }
        }
    }
    let index = number_nodes(std::iter::empty(), trajectories, spacing);
    let nodes = index.len();
    // One scalar system for the three axes: Σ φφᵀ g = Σ φ d, with a small ridge for nodes that
    // anchors touch only at their far corner.
    let mut a = SymmetricSparse::new(nodes);
    // Per node the right-hand sides of x, y, z, the rotation about z (the heading), about x and
    // about y (the tilt).
    let mut b = vec![[0.0f64; 6]; nodes];
    for (tr, before) in trajectories.iter().zip(previous) {
        for ((p, now), was) in tr.positions.iter().zip(&tr.corrections.values).zip(&before.values) {
            let row: Vec<(usize, f64)> = bilinear(p[0], p[1], spacing)
                .iter()
                .filter(|(_, phi)| *phi > 0.0)
                .map(|(n, phi)| (index[n], *phi))
                .collect();
            for &(i, pi) in &row {
                for &(j, pj) in &row {
                    // Each unordered pair once (the row's nodes are distinct).
                    if i >= j {
                        a.add(i, j, pi * pj);
                    }
                }
                for c in 0..3 {
                    b[i][c] += pi * (now[c] - was[c]);
                }
                b[i][3] += pi * (now[5] - was[5]);
                b[i][4] += pi * (now[3] - was[3]);
                b[i][5] += pi * (now[4] - was[4]);
            }
        }
    }
    for i in 0..nodes {
        a.add(i, i, 1e-3);
    }
    let factor = a
        .factorise_at(MAX_FIELD_FACTOR_ENTRIES, &unknown_positions(&index, 1))
        .map_err(|e| FieldError::from_sparse(e, nodes))?;
    let axes = 3 + rotation_axes;
    let per_axis: Vec<Vec<f64>> =
        (0..axes).map(|c| factor.solve(&b.iter().map(|v| v[c]).collect::<Vec<_>>())).collect();
    let fit = FieldSolution {
        spacing_m: spacing,
        nodes: index.keys().copied().collect(),
        values: (0..nodes).map(|i| [per_axis[0][i], per_axis[1][i], per_axis[2][i]]).collect(),
        observations: 0,
        motion: None,
        heading: if rotation_axes > 0 { per_axis[3].clone() } else { Vec::new() },
        tilt: if rotation_axes == 3 {
            (0..nodes).map(|i| [per_axis[4][i], per_axis[5][i]]).collect()
        } else {
            Vec::new()
        },
    };
    Ok(trajectories.iter().zip(previous).map(|(tr, before)| fit.apply(tr.positions, before)).collect())
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FieldError {
    #[error("trajectory {trajectory}: {positions} anchor positions for {anchors} anchors")]
    Positions { trajectory: usize, positions: usize, anchors: usize },
    #[error("{found} trajectories' previous corrections for {expected} trajectories")]
    Trajectories { expected: usize, found: usize },
    #[error("the common-mode field's normal equations are not positive definite ({nodes} nodes)")]
    Singular { nodes: usize },
    #[error(
        "the common-mode field's {nodes} nodes need {entries} factor entries, more than the {limit} \
         (12 bytes each) its solve may use; raise parameters.common_mode_field_m (the node spacing), \
         set parameters.common_mode_tilt to false (a third fewer unknowns) or \
         parameters.common_mode_heading to false (a quarter fewer), or set \
         parameters.common_mode_field_m to 0"
    )]
    TooLarge { nodes: usize, entries: usize, limit: usize },
    /// A system the field built wrongly (a bug, not the data's fault).
    #[error("the common-mode field's solve: {0}")]
    Solve(SparseError),
}

impl FieldError {
    fn from_sparse(e: SparseError, nodes: usize) -> Self {
        match e {
            SparseError::TooLarge { entries, limit } => FieldError::TooLarge { nodes, entries, limit },
            SparseError::NotPositiveDefinite { .. } => FieldError::Singular { nodes },
            e @ (SparseError::OutOfRange { .. } | SparseError::Coordinates { .. }) => FieldError::Solve(e),
        }
    }
}

/// Most factor entries the field's sparse solve may hold (12 bytes each: 1 GiB). After nested
/// dissection a synthetic street network of 248 km² at 15 m nodes needs 82 % of this with three
/// unknowns per node, so the limit lies near 290 km² of such a network; with the heading's
/// fourth, 159 km² needs 89 % and the limit lies near 165 km²; with the tilt's six, 39.7 km²
/// need 2.1× the entries of four and 89.3 km² need 1,096 MiB, so the limit lies near 85 km²
/// (`precimap bench field-solve --blocks N --per-node 3|4|6`; docs/design/estimation.md, "The
/// common-mode field").
pub const MAX_FIELD_FACTOR_ENTRIES: usize = (1 << 30) / 12;

/// Solves the common-mode field from the tiles' data equations plus every anchor's prior,
/// smoothness and curvature terms, linearised about the current corrections.
pub fn solve_field<'a>(
    equations: impl IntoIterator<Item = &'a FieldEquations>,
    trajectories: &[FieldTrajectory],
    params: &Parameters,
) -> Result<FieldSolution, FieldError> {
    solve_field_within(equations, trajectories, params, MAX_FIELD_FACTOR_ENTRIES)
}

/// [`solve_field`] with at most `max_factor_entries` factor entries.
fn solve_field_within<'a>(
    equations: impl IntoIterator<Item = &'a FieldEquations>,
    trajectories: &[FieldTrajectory],
    params: &Parameters,
    max_factor_entries: usize,
) -> Result<FieldSolution, FieldError> {
    let spacing = params.common_mode_field_m;
    for (t, tr) in trajectories.iter().enumerate() {
        if tr.positions.len() != tr.corrections.values.len() {
            return Err(FieldError::Positions {
                trajectory: t,
                positions: tr.positions.len(),
                anchors: tr.corrections.values.len(),
            });
        }
    }
    let equations: Vec<&FieldEquations> = equations.into_iter().collect();
    // Node numbering: every node a tile or an anchor touches.
    let index = number_nodes(equations.iter().flat_map(|e| e.nodes.iter().copied()), trajectories, spacing);
    let nodes = index.len();
    // Unknowns per node: the translation, then with the heading the rotation about z (index 3),
    // with the tilt the rotations about x and y (4 and 5).
    let axes = rotation_axes(params);
    let per_node = 3 + axes;
    let dim = per_node * nodes;
    // The lower triangle is what the factorisation reads: each block pair adds there once.
    let mut h = SymmetricSparse::new(dim);
    let mut rhs = vec![0.0f64; dim];
    let mut observations = 0;
    for e in &equations {
        observations += e.observations;
        let global: Vec<usize> = e.nodes.iter().map(|n| index[n]).collect();
        // Equations summed without the heading (an older field object) leave its data out.
        let heading = axes > 0 && e.heading_pairs.len() == e.pairs.len() && e.heading_rhs.len() == e.nodes.len();
        let tilt = heading && axes == 3 && e.tilt_pairs.len() == e.pairs.len() && e.tilt_rhs.len() == e.nodes.len();
        for (k, &(a, b, m)) in e.pairs.iter().enumerate() {
            let (ga, gb) = (per_node * global[a as usize], per_node * global[b as usize]);
            for r in 0..3 {
                for c in 0..3 {
                    // A node's own block is symmetric: its lower half once.
                    if ga != gb || r >= c {
                        h.add(ga + r, gb + c, m[3 * r + c]);
                    }
                }
            }
            if heading {
                let x = &e.heading_pairs[k];
                for c in 0..3 {
                    h.add(ga + c, gb + 3, x[c]);
                    if ga != gb {
                        h.add(ga + 3, gb + c, x[3 + c]);
                    }
                }
                h.add(ga + 3, gb + 3, x[6]);
            }
            if tilt {
                // As `FieldEquations::tilt_pairs` lays them out; a node's own block adds each of
                // its entries once.
                let y = &e.tilt_pairs[k];
                for j in 0..2 {
                    for c in 0..3 {
                        h.add(ga + c, gb + 4 + j, y[c * 2 + j]);
                        if ga != gb {
                            h.add(ga + 4 + j, gb + c, y[6 + j * 3 + c]);
                        }
                    }
                    h.add(ga + 3, gb + 4 + j, y[12 + j]);
                    if ga != gb {
                        h.add(ga + 4 + j, gb + 3, y[14 + j]);
                    }
                    for l in 0..2 {
                        if ga != gb || j >= l {
                            h.add(ga + 4 + j, gb + 4 + l, y[16 + 2 * j + l]);
                        }
                    }
                }
            }
        }
        if heading {
            for (n, r) in e.heading_rhs.iter().enumerate() {
                rhs[per_node * global[n] + 3] += r;
            }
        }
        if tilt {
            for (n, r) in e.tilt_rhs.iter().enumerate() {
                rhs[per_node * global[n] + 4] += r[0];
                rhs[per_node * global[n] + 5] += r[1];
            }
        }
        for (n, r) in e.rhs.iter().enumerate() {
            for c in 0..3 {
                rhs[per_node * global[n] + c] += r[c];
            }
        }
    }
    // Prior and smoothness act on each axis alike: one scalar weight per node pair.
    let prior = 1.0 / (params.sigma_prior_position_m * params.sigma_prior_position_m);
    let smooth = 1.0 / (params.sigma_smooth_position_m * params.sigma_smooth_position_m);
    let curvature = match params.sigma_curvature_position_m {
        s if s > 0.0 => 1.0 / (s * s),
        _ => 0.0,
    };
    // The campaign's rotation, solved with the field (`Parameters::campaign_motion`).
    let mut motion = params.campaign_motion.then(|| {
        let count = trajectories.iter().map(|tr| tr.positions.len()).sum::<usize>().max(1);
        let sum: Vec3 = trajectories.iter().flat_map(|tr| tr.positions).map(|&p| Vec3::from(p)).sum();
        MotionTerms {
            origin: (sum / count as f64).into(),
            coupling: vec![[0.0; 3]; dim],
            own: Mat3::zeros(),
            rhs: Vec3::zeros(),
        }
    });
    let origin = motion.as_ref().map_or([0.0; 3], |m| m.origin);
    let rotation_weight = |sigma_deg: f64| match sigma_deg.to_radians() {
        s if s > 0.0 => 1.0 / (s * s),
        _ => 0.0,
    };
    let prior_rotation = params.sigma_prior_rotation_axes_deg().map(rotation_weight);
    let (smooth_rotation, curvature_rotation) =
        (rotation_weight(params.sigma_smooth_rotation_deg), rotation_weight(params.sigma_curvature_rotation_deg));
    // An anchor's own prior (translation, rotation weights), else the campaign's.
    let anchor_prior = |tr: &FieldTrajectory, k: usize| match tr.prior.and_then(|p| p.get(k)) {
        Some(w) => ([w[0], w[1], w[2]], [w[3], w[4], w[5]]),
        None => ([prior; 3], prior_rotation),
    };
    // The field's rotation unknowns: (index within the node, axis).
    let rotation_unknowns: &[(usize, usize)] = match axes {
        0 => &[],
        1 => &[(3, 2)],
        _ => &[(3, 2), (4, 0), (5, 1)],
    };
    // One term of an anchor's prior, smoothness or curvature on `value` (a correction, or a
    // difference of them): on the translation, residual `Σ row·field + ω × d + value[..3]` of
    // weight `weight`; with the field's rotation, also on each of its axes, residual
    // `Σ row·ρ + value[3..]` of weight `rotation_weight` (plus the campaign's rotation where
    // `sees_motion`: only the prior sees it, a constant drops out of differences).
    let mut add_term = |row: &[(usize, f64)],
                        d: [f64; 3],
                        value: [f64; 6],
                        weight: [f64; 3],
                        rotation_weight: [f64; 3],
                        sees_motion: bool| {
        for &(a, ra) in row {
            for c in 0..3 {
                rhs[per_node * a + c] -= weight[c] * ra * value[c];
            }
            for &(b, rb) in row {
                // Each unordered pair of nodes once.
                if a >= b {
                    for c in 0..3 {
                        h.add(per_node * a + c, per_node * b + c, weight[c] * ra * rb);
                    }
                }
            }
        }
        if let Some(m) = motion.as_mut() {
            m.add(row, per_node, d, [value[0], value[1], value[2]], weight);
        }
        for &(unknown, axis) in rotation_unknowns {
            let weight = rotation_weight[axis];
            for &(a, ra) in row {
                rhs[per_node * a + unknown] -= weight * ra * value[3 + axis];
                for &(b, rb) in row {
                    if a >= b {
                        h.add(per_node * a + unknown, per_node * b + unknown, weight * ra * rb);
                    }
                }
                if let (true, Some(m)) = (sees_motion, motion.as_mut()) {
                    m.coupling[per_node * a + unknown][axis] += weight * ra;
                }
            }
        }
    };
    let row_at = |p: &[f64; 3]| -> Vec<(usize, f64)> {
        bilinear(p[0], p[1], spacing).iter().filter(|(_, phi)| *phi > 0.0).map(|(n, phi)| (index[n], *phi)).collect()
    };
    for tr in trajectories {
        let values = &tr.corrections.values;
        let rows: Vec<Vec<(usize, f64)>> = tr.positions.iter().map(row_at).collect();
        let d: Vec<[f64; 3]> = tr.positions.iter().map(|p| std::array::from_fn(|a| p[a] - origin[a])).collect();
        for (k, row) in rows.iter().enumerate() {
            let (prior, prior_rotation) = anchor_prior(tr, k);
            add_term(row, d[k], values[k], prior, prior_rotation, true);
            if k + 1 < rows.len() {
                let mut diff = rows[k + 1].clone();
                for &(a, ra) in row {
                    accumulate(&mut diff, a, -ra);
                }
                let dv: [f64; 6] = std::array::from_fn(|c| values[k + 1][c] - values[k][c]);
                let dd = std::array::from_fn(|a| d[k + 1][a] - d[k][a]);
                add_term(&diff, dd, dv, [smooth; 3], [smooth_rotation; 3], false);
            }
            if curvature > 0.0 && k >= 1 && k + 1 < rows.len() {
                let mut second: Vec<(usize, f64)> = Vec::with_capacity(12);
                for (r, f) in [(&rows[k - 1], 1.0), (row, -2.0), (&rows[k + 1], 1.0)] {
                    for &(a, ra) in r {
                        accumulate(&mut second, a, f * ra);
                    }
                }
                let dv: [f64; 6] = std::array::from_fn(|c| values[k - 1][c] - 2.0 * values[k][c] + values[k + 1][c]);
                let dd = std::array::from_fn(|c| d[k - 1][c] - 2.0 * d[k][c] + d[k + 1][c]);
                add_term(&second, dd, dv, [curvature; 3], [curvature_rotation; 3], false);
            }
        }
    }
    // The rotation prior sees the motion's rotation directly: it holds the campaign's mean
    // attitude correction.
    if let Some(m) = motion.as_mut() {
        for tr in trajectories {
            for (k, v) in tr.corrections.values.iter().enumerate() {
                let prior_rotation = anchor_prior(tr, k).1;
                for i in 0..3 {
                    m.own[(i, i)] += prior_rotation[i];
                    m.rhs[i] -= prior_rotation[i] * v[3 + i];
                }
            }
        }
    }
    // A node that only a scan head's lever arm reaches (no anchor near it) may see data in some
    // directions only; a weak prior on the field itself (σ 10 × the anchors') keeps it definite.
    for i in 0..dim {
        let own_prior = match i % per_node {
            3 => prior_rotation[2],
            4 => prior_rotation[0],
            5 => prior_rotation[1],
            _ => prior,
        };
        h.add(i, i, own_prior * 1e-2);
    }
    let factor = h
        .factorise_at(max_factor_entries, &unknown_positions(&index, per_node))
        .map_err(|e| FieldError::from_sparse(e, nodes))?;
    let mut solution = factor.solve(&rhs);
    // The rotation by the Schur complement of the field's block: the field's factor solves the
    // three coupling columns, then the 3×3 system gives the rotation and the field follows.
    let motion = match motion {
        Some(m) => {
            let columns: Vec<Vec<f64>> =
                (0..3).map(|j| factor.solve(&m.coupling.iter().map(|c| c[j]).collect::<Vec<_>>())).collect();
            let mut schur = m.own;
            let mut reduced = m.rhs;
            for i in 0..3 {
                for (k, c) in m.coupling.iter().enumerate() {
                    reduced[i] -= c[i] * solution[k];
                    for j in 0..3 {
                        schur[(i, j)] -= c[i] * columns[j][k];
                    }
                }
            }
            let rotation = schur.cholesky().ok_or(FieldError::Singular { nodes })?.solve(&reduced);
            for (k, x) in solution.iter_mut().enumerate() {
                *x -= (0..3).map(|j| columns[j][k] * rotation[j]).sum::<f64>();
            }
            Some(CampaignMotion { origin: m.origin, rotation: [rotation[0], rotation[1], rotation[2]] })
        }
        None => None,
    };
    Ok(FieldSolution {
        spacing_m: spacing,
        nodes: index.keys().copied().collect(),
        values: (0..nodes).map(|i| std::array::from_fn(|c| solution[per_node * i + c])).collect(),
        observations,
        motion,
        heading: if axes > 0 { (0..nodes).map(|i| solution[per_node * i + 3]).collect() } else { Vec::new() },
        tilt: if axes == 3 {
            (0..nodes).map(|i| [solution[per_node * i + 4], solution[per_node * i + 5]]).collect()
        } else {
            Vec::new()
        },
    })
}

#[cfg(test)]
mod tests;
