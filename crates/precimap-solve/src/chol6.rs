//! Cholesky factorisation of one 6×6 pivot block, hand-rolled so the positive-definiteness test
//! can be relative to the original diagonal (nalgebra only rejects pivots ≤ 0).

// Index loops mirror the textbook triangular recurrences; iterator chains would hide them.
#![allow(clippy::needless_range_loop)]

use crate::{Mat6, Vec6};

/// A pivot `s_j` is accepted when `s_j > REL_PIVOT_TOL · H_jj`. Every pivot of the elimination is
/// at least `λ_min` of the Jacobi-scaled `H` times `H_jj`, and the GNSS/IMU prior keeps that ratio
/// above ~1e-9 in real systems; below 1e-13 the unknown is determined by rounding noise only.
const REL_PIVOT_TOL: f64 = 1e-13;

/// Lower-triangular `L` with `D = L·Lᵀ`, row-major, plus the reciprocals of its diagonal.
#[derive(Clone, Debug)]
pub(crate) struct Chol6 {
    l: [[f64; 6]; 6],
    inv_diag: [f64; 6],
}

impl Chol6 {
    /// Factorises the symmetric `d` (lower triangle read). `reference` is the block of the
    /// original matrix `d` was reduced from; its diagonal scales the pivot test.
    pub(crate) fn factor(d: &Mat6, reference: &Mat6) -> Option<Self> {
        let mut l = [[0.0; 6]; 6];
        let mut inv_diag = [0.0; 6];
        for j in 0..6 {
            let mut s = d[(j, j)];
            for k in 0..j {
                s -= l[j][k] * l[j][k];
            }
            let h = reference[(j, j)];
            // `!(s > …)` also rejects NaN.
            if !(h > 0.0 && s > REL_PIVOT_TOL * h && s.is_finite()) {
                return None;
            }
            let ljj = s.sqrt();
            l[j][j] = ljj;
            let inv = 1.0 / ljj;
            inv_diag[j] = inv;
            for i in j + 1..6 {
                let mut v = d[(i, j)];
                for k in 0..j {
                    v -= l[i][k] * l[j][k];
                }
                l[i][j] = v * inv;
            }
        }
        Some(Self { l, inv_diag })
    }

    #[inline]
    fn solve_in_place(&self, b: &mut [f64; 6]) {
        // L y = b
        for i in 0..6 {
            let mut v = b[i];
            for k in 0..i {
                v -= self.l[i][k] * b[k];
            }
            b[i] = v * self.inv_diag[i];
        }
        // Lᵀ x = y
        for i in (0..6).rev() {
            let mut v = b[i];
            for k in i + 1..6 {
                v -= self.l[k][i] * b[k];
            }
            b[i] = v * self.inv_diag[i];
        }
    }

    /// `D⁻¹ b`.
    pub(crate) fn solve_vec(&self, b: &Vec6) -> Vec6 {
        let mut v = [b[0], b[1], b[2], b[3], b[4], b[5]];
        self.solve_in_place(&mut v);
        Vec6::from(v)
    }

    /// `D⁻¹ B`, column by column.
    pub(crate) fn solve_mat(&self, b: &Mat6) -> Mat6 {
        let mut out = Mat6::zeros();
        for c in 0..6 {
            let mut v = [b[(0, c)], b[(1, c)], b[(2, c)], b[(3, c)], b[(4, c)], b[(5, c)]];
            self.solve_in_place(&mut v);
            for (r, x) in v.into_iter().enumerate() {
                out[(r, c)] = x;
            }
        }
        out
    }

    /// `D⁻¹`.
    pub(crate) fn inverse(&self) -> Mat6 {
        self.solve_mat(&Mat6::identity())
    }
}
