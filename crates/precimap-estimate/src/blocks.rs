//! Normal-equation blocks of one trajectory, keyed by anchor (the values a tile's map task emits
//! and a trajectory's reduce task sums).
//!
//! Each observation adds `w·JJᵀ` with `J = [(1−λ)g, λg]` to the 12×12 block of anchors i, i+1.
//! Because `ggᵀ` is symmetric all three 6×6 blocks are symmetric, so they travel as their 21
//! upper-triangle entries (row-major).

use serde::{Deserialize, Serialize};

pub use precimap_core::corrections::{sym_index, Sym6};

/// Contributions to anchor `anchor`: `H_ii` (`diag`), `H_i,i+1` (`next`), `b_i` (`rhs`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnchorBlock {
    pub anchor: u32,
    pub diag: Sym6,
    pub next: Sym6,
    pub rhs: [f64; 6],
    /// Observations whose interval starts at this anchor.
    pub observations: u32,
    /// `H_i,c`: the coupling of this anchor's six unknowns with the campaign's calibration
    /// unknowns (6 × K, row-major); empty without calibration.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cross: Vec<f64>,
}

impl AnchorBlock {
    pub fn new(anchor: u32) -> Self {
        Self { anchor, diag: [0.0; 21], next: [0.0; 21], rhs: [0.0; 6], observations: 0, cross: Vec::new() }
    }

    pub fn add(&mut self, other: &AnchorBlock) {
        for k in 0..21 {
            self.diag[k] += other.diag[k];
            self.next[k] += other.next[k];
        }
        for k in 0..6 {
            self.rhs[k] += other.rhs[k];
        }
        self.observations += other.observations;
        if !other.cross.is_empty() {
            if self.cross.is_empty() {
                self.cross.resize(other.cross.len(), 0.0);
            }
            for (a, b) in self.cross.iter_mut().zip(&other.cross) {
                *a += b;
            }
        }
    }
}

/// All blocks one tile contributes to one trajectory, sorted by anchor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryBlocks {
    pub trajectory: u32,
    pub blocks: Vec<AnchorBlock>,
    /// The calibration's own normal equations from this trajectory's observations in the tile.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<crate::calibration::CalibrationNormals>,
}

/// Per-interval moment sums while a tile is processed: with `S_m = Σ w λ^m ggᵀ` and
/// `v_m = Σ w λ^m g e`, the interval adds `S0 − 2S1 + S2` to `H_ii`, `S1 − S2` to `H_i,i+1`,
/// `S2` to `H_i+1,i+1`, `−(v0 − v1)` to `b_i` and `−v1` to `b_i+1`.
#[derive(Clone, Debug)]
pub(crate) struct IntervalMoments {
    s0: Sym6,
    s1: Sym6,
    s2: Sym6,
    v0: [f64; 6],
    v1: [f64; 6],
    count: u32,
}

impl Default for IntervalMoments {
    fn default() -> Self {
        Self { s0: [0.0; 21], s1: [0.0; 21], s2: [0.0; 21], v0: [0.0; 6], v1: [0.0; 6], count: 0 }
    }
}

impl IntervalMoments {
    /// Adds one observation with Jacobian row `g` (6), residual `e`, weight `w`, fraction `lambda`.
    #[inline]
    pub(crate) fn add(&mut self, g: &[f64; 6], e: f64, w: f64, lambda: f64) {
        self.add_weighted(g, w * e, w, lambda, 1);
    }

    /// [`Self::add`] with the weighted residual `we = w·e` given: `observations` that share a
    /// Jacobian row and fraction add as one with their weights and weighted residuals summed.
    #[inline]
    pub(crate) fn add_weighted(&mut self, g: &[f64; 6], we: f64, w: f64, lambda: f64, observations: u32) {
        let wl = w * lambda;
        let wll = wl * lambda;
        let wel = we * lambda;
        let mut k = 0;
        for i in 0..6 {
            let gi = g[i];
            for &gj in &g[i..] {
                let q = gi * gj;
                self.s0[k] += w * q;
                self.s1[k] += wl * q;
                self.s2[k] += wll * q;
                k += 1;
            }
            self.v0[i] += we * gi;
            self.v1[i] += wel * gi;
        }
        self.count += observations;
    }

    /// Adds this interval's contribution to the blocks of anchors `i` (`at`) and `i+1` (`after`).
    pub(crate) fn scatter(&self, at: &mut AnchorBlock, after: &mut AnchorBlock) {
        for k in 0..21 {
            at.diag[k] += self.s0[k] - 2.0 * self.s1[k] + self.s2[k];
            at.next[k] += self.s1[k] - self.s2[k];
            after.diag[k] += self.s2[k];
        }
        for k in 0..6 {
            at.rhs[k] -= self.v0[k] - self.v1[k];
            after.rhs[k] -= self.v1[k];
        }
        at.observations += self.count;
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The interval's 12×12 block over anchors `i`, `i+1` and its right-hand side: what
    /// [`Self::scatter`] adds (`H_i,i+1` given whole, both ways).
    pub(crate) fn block(&self) -> ([[f64; 12]; 12], [f64; 12]) {
        let mut h = [[0.0; 12]; 12];
        let mut rhs = [0.0; 12];
        for i in 0..6 {
            for j in i..6 {
                let k = sym_index(i, j);
                let (diag, next, after) =
                    (self.s0[k] - 2.0 * self.s1[k] + self.s2[k], self.s1[k] - self.s2[k], self.s2[k]);
                for (r, c, v) in [(i, j, diag), (i, 6 + j, next), (j, 6 + i, next), (6 + i, 6 + j, after)] {
                    h[r][c] = v;
                    h[c][r] = v;
                }
            }
            rhs[i] = -(self.v0[i] - self.v1[i]);
            rhs[6 + i] = -self.v1[i];
        }
        (h, rhs)
    }
}

/// Merges many block lists of one trajectory into one sorted list.
pub fn merge_blocks<'a>(lists: impl IntoIterator<Item = &'a [AnchorBlock]>) -> Vec<AnchorBlock> {
    let mut map: std::collections::BTreeMap<u32, AnchorBlock> = std::collections::BTreeMap::new();
    for list in lists {
        for b in list {
            map.entry(b.anchor).or_insert_with(|| AnchorBlock::new(b.anchor)).add(b);
        }
    }
    map.into_values().collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two observations with one Jacobian row and fraction, added as one with their weights and
    /// weighted residuals summed, give the moments of adding them one by one (to rounding), and
    /// count as two.
    #[test]
    fn observations_sharing_a_row_add_as_one() {
        let g = [0.2, -0.3, 0.93, 1.7, -0.4, 2.2];
        let (lambda, (w1, e1), (w2, e2)) = (0.3, (4.0e4, 0.004), (1.3e4, -0.011));
        let mut apart = IntervalMoments::default();
        apart.add(&g, e1, w1, lambda);
        apart.add(&g, e2, w2, lambda);
        let mut joined = IntervalMoments::default();
        joined.add_weighted(&g, w1 * e1 + w2 * e2, w1 + w2, lambda, 2);
        assert_eq!(joined.count, 2);
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1.0);
        for (a, b) in [(&apart.s0, &joined.s0), (&apart.s1, &joined.s1), (&apart.s2, &joined.s2)] {
            assert!(a.iter().zip(b).all(|(x, y)| close(*x, *y)), "{a:?} against {b:?}");
        }
        for (a, b) in [(&apart.v0, &joined.v0), (&apart.v1, &joined.v1)] {
            assert!(a.iter().zip(b).all(|(x, y)| close(*x, *y)), "{a:?} against {b:?}");
        }
    }

    #[test]
    fn sym_index_covers_upper_triangle_once() {
        let mut seen = [false; 21];
        for i in 0..6 {
            for j in i..6 {
                let k = sym_index(i, j);
                assert!(!seen[k]);
                seen[k] = true;
            }
        }
        assert!(seen.iter().all(|&s| s));
    }

    /// The moment form equals adding `w·JJᵀ` and `−w·J·e` directly.
    #[test]
    fn moments_equal_direct_accumulation() {
        let obs =
            [([1.0, 0.2, -0.3, 4.0, 5.0, -6.0], 0.01, 2.0, 0.3), ([0.0, 1.0, 0.5, -2.0, 1.0, 3.0], -0.02, 1.0, 0.8)];
        let mut m = IntervalMoments::default();
        let mut direct = [[0.0f64; 12]; 12];
        let mut rhs = [0.0f64; 12];
        for (g, e, w, l) in obs {
            m.add(&g, e, w, l);
            let mut j = [0.0; 12];
            for k in 0..6 {
                j[k] = (1.0 - l) * g[k];
                j[6 + k] = l * g[k];
            }
            for a in 0..12 {
                for b in 0..12 {
                    direct[a][b] += w * j[a] * j[b];
                }
                rhs[a] -= w * j[a] * e;
            }
        }
        let (mut at, mut after) = (AnchorBlock::new(0), AnchorBlock::new(1));
        m.scatter(&mut at, &mut after);
        for i in 0..6 {
            for j in i..6 {
                let k = sym_index(i, j);
                assert!((at.diag[k] - direct[i][j]).abs() < 1e-12);
                assert!((at.next[k] - direct[i][6 + j]).abs() < 1e-12);
                assert!((at.next[k] - direct[j][6 + i]).abs() < 1e-12, "H_i,i+1 is symmetric");
                assert!((after.diag[k] - direct[6 + i][6 + j]).abs() < 1e-12);
            }
            assert!((at.rhs[i] - rhs[i]).abs() < 1e-12);
            assert!((after.rhs[i] - rhs[6 + i]).abs() < 1e-12);
        }
    }
}
