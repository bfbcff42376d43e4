//! A run of the field's observation rows that share a surface normal and both cells ([`Run`]).

use super::accumulator::{SLOTS, SLOT_PAIRS};
use super::FieldNode;
use crate::tile::dot;

/// Most lever components a run sums per slot (the whole rotation's two).
pub(super) const LEVER_COMPONENTS: usize = 2;
/// Rotation entries of a row: per slot, its lever components.
pub(super) const ROTATION_ENTRIES: usize = SLOTS * LEVER_COMPONENTS;

/// The rows summed since the surface normal or either cell last changed.
#[derive(Debug)]
pub(super) struct Run {
    /// Own cell, other passes' cell (their lower-left nodes) and the normal's bits.
    pub(super) key: Option<(FieldNode, FieldNode, [u64; 3])>,
    pub(super) w: [f64; 3],
    /// With the tilt, the basis of the plane normal to `w` the levers are summed in.
    pub(super) basis: [[f64; 3]; LEVER_COMPONENTS],
    /// `Σ ω r_s r_t` over slot pairs `s ≤ t` and `Σ ω r_s e` per slot.
    pub(super) rr: [f64; SLOT_PAIRS],
    pub(super) re: [f64; SLOTS],
    /// With a rotation, whose row entries `h_q` (`q = s·m + i`: slot `s`, lever component `i` of
    /// `m`) vary with the point's lever arm: `Σ ω r_s h_q` (row-major over `s` and `q`),
    /// `Σ ω h_q h_q'` over `q ≤ q'` and `Σ ω h_q e`.
    pub(super) rh: [f64; SLOTS * ROTATION_ENTRIES],
    pub(super) hh: [f64; ROTATION_ENTRIES * (ROTATION_ENTRIES + 1) / 2],
    pub(super) he: [f64; ROTATION_ENTRIES],
    /// A row reached the slot with a non-zero weight.
    pub(super) reached: [bool; SLOTS],
    /// The slot of each corner of the other passes' cell: its own (4 + corner) or, for a node
    /// the two cells share, the point's cell's slot of it.
    pub(super) slot: [usize; 4],
}

impl Run {
    pub(super) fn new() -> Self {
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
    pub(super) fn add_rotation<const M: usize>(
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
    pub(super) fn reset<const M: usize>(&mut self) {
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
