//! The field's data equations of one tile: observation rows summed by [`FieldAccumulator`] into
//! [`FieldEquations`].

use super::run::Run;
use super::{bilinear, corners, FieldNode};
use crate::tile::{cross, normalize};
use serde::{Deserialize, Serialize};

/// Slots of a row: the four corners of the point's own cell, then the four of the other
/// passes' cell.
pub(super) const SLOTS: usize = 8;
/// Slot pairs `s ≤ t`, row-major.
pub(super) const SLOT_PAIRS: usize = SLOTS * (SLOTS + 1) / 2;

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
pub(super) type TiltSums = (Vec<[f64; 20]>, Vec<[f64; 2]>);

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

/// `square`, row-major `n × n` with `n = old`, grown to `(n + 1) × (n + 1)` with zeros.
pub(super) fn grow_square<T: Copy + Default>(square: &mut Vec<T>, old: usize) {
    let new = old + 1;
    let mut grown = vec![T::default(); new * new];
    for a in 0..old {
        grown[a * new..a * new + old].copy_from_slice(&square[a * old..(a + 1) * old]);
    }
    *square = grown;
}

/// A node index not looked up yet.
pub(super) const UNKNOWN: usize = usize::MAX;

/// The four bilinear weights of [`bilinear`] at `(x, y)` and the lower-left node of its cell.
#[inline]
pub(super) fn cell_weights(x: f64, y: f64, spacing: f64) -> (FieldNode, [f64; 4]) {
    let weights = bilinear(x, y, spacing);
    (weights[0].0, weights.map(|(_, phi)| phi))
}

/// An orthonormal basis of the plane normal to the unit vector `w`.
pub(super) fn plane_basis(w: [f64; 3]) -> [[f64; 3]; 2] {
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
pub(super) fn swap_heading(x: [f64; 7]) -> [f64; 7] {
    [x[3], x[4], x[5], x[0], x[1], x[2], x[6]]
}

/// A pair's tilt terms seen from its other node (the pair's block transposed).
pub(super) fn swap_tilt(y: [f64; 20]) -> [f64; 20] {
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
