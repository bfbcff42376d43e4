//! Exact linear-time solver for the block-tridiagonal normal equations of one trajectory, and
//! ([`sparse`]) an exact sparse solver for the common-mode field's normal equations.
//!
//! With the latent map held fixed (paper Eq. 6), the unknowns of one trajectory are the 6-vectors
//! of pose corrections at its anchors, and every observation, prior and smoothness term couples at
//! most two neighbouring anchors. The normal matrix `H` is therefore symmetric positive definite
//! and block-tridiagonal with 6×6 blocks. [`BlockLdlt`] eliminates it exactly in O(n) time and
//! memory by a block LDLᵀ (Thomas) sweep,
//!
//! ```text
//! D_0 = H_00,   G_i = D_i⁻¹ U_i,   D_{i+1} = H_{i+1,i+1} − U_iᵀ G_i        (U_i = H_{i,i+1})
//! y_0 = b_0,    y_{i+1} = b_{i+1} − G_iᵀ y_i
//! x_{n−1} = D_{n−1}⁻¹ y_{n−1},     x_i = D_i⁻¹ y_i − G_i x_{i+1}
//! ```
//!
//! which is algebraically the Rauch–Tung–Striebel smoother the paper uses (forward filter,
//! backward smoother). The marginal covariances `Σ_ii` (diagonal blocks of `H⁻¹`) follow from the
//! backward recursion `Σ_{n−1} = D_{n−1}⁻¹`, `Σ_i = D_i⁻¹ + G_i Σ_{i+1} G_iᵀ`. Nothing larger than a
//! 6×6 matrix is ever formed.

mod chol6;
pub mod generic;
#[cfg(test)]
mod rng;
pub mod sparse;

use chol6::Chol6;

pub type Mat6 = nalgebra::Matrix6<f64>;
pub type Vec6 = nalgebra::Vector6<f64>;

/// A symmetric block-tridiagonal system `H x = b` with 6×6 blocks.
///
/// `diag[i]` is `H_ii` (symmetric; the solver reads its lower triangle), `upper[i]` is
/// `H_{i,i+1}`, so `H_{i+1,i} = upper[i]ᵀ`, and `rhs[i]` is `b_i`. A system of `n` blocks has `n`
/// diagonal blocks, `n − 1` upper blocks (none when `n = 0`) and `n` right-hand sides.
#[derive(Clone, Debug, PartialEq)]
pub struct BlockTridiagonal {
    pub diag: Vec<Mat6>,
    pub upper: Vec<Mat6>,
    pub rhs: Vec<Vec6>,
}

impl BlockTridiagonal {
    /// An all-zero system of `n` blocks, ready to accumulate normal-equation contributions.
    pub fn zeros(n: usize) -> Self {
        Self {
            diag: vec![Mat6::zeros(); n],
            upper: vec![Mat6::zeros(); n.saturating_sub(1)],
            rhs: vec![Vec6::zeros(); n],
        }
    }

    /// Number of 6×6 diagonal blocks (anchors).
    pub fn len(&self) -> usize {
        self.diag.len()
    }

    pub fn is_empty(&self) -> bool {
        self.diag.is_empty()
    }

    /// The dense `6n × 6n` matrix (for tests and debugging only: it is quadratic in `n`).
    pub fn to_dense(&self) -> nalgebra::DMatrix<f64> {
        let n = self.len();
        let mut m = nalgebra::DMatrix::zeros(6 * n, 6 * n);
        for (i, d) in self.diag.iter().enumerate() {
            m.fixed_view_mut::<6, 6>(6 * i, 6 * i).copy_from(d);
        }
        for (i, u) in self.upper.iter().enumerate().take(n.saturating_sub(1)) {
            m.fixed_view_mut::<6, 6>(6 * i, 6 * (i + 1)).copy_from(u);
            m.fixed_view_mut::<6, 6>(6 * (i + 1), 6 * i).copy_from(&u.transpose());
        }
        m
    }

    /// The right-hand side stacked into one `6n` vector (for tests and debugging).
    pub fn rhs_dense(&self) -> nalgebra::DVector<f64> {
        nalgebra::DVector::from_iterator(6 * self.rhs.len(), self.rhs.iter().flat_map(|v| v.iter().copied()))
    }

    /// `H·x` in O(n), e.g. to check a residual `‖Hx − b‖`. `x` must have [`len`](Self::len) blocks.
    pub fn multiply(&self, x: &[Vec6]) -> Result<Vec<Vec6>, SolveError> {
        self.check_shape()?;
        if x.len() != self.len() {
            return Err(SolveError::Shape { diag: self.len(), upper: self.upper.len(), rhs: x.len() });
        }
        let mut y: Vec<Vec6> = self.diag.iter().zip(x).map(|(d, xi)| d * xi).collect();
        for (i, u) in self.upper.iter().enumerate() {
            y[i] += u * x[i + 1];
            y[i + 1] += u.tr_mul(&x[i]);
        }
        Ok(y)
    }

    fn check_shape(&self) -> Result<(), SolveError> {
        let n = self.diag.len();
        if self.upper.len() != n.saturating_sub(1) || self.rhs.len() != n {
            return Err(SolveError::Shape { diag: n, upper: self.upper.len(), rhs: self.rhs.len() });
        }
        Ok(())
    }

    fn check_finite(&self) -> Result<(), SolveError> {
        let bad = |block, part| Err(SolveError::NonFinite { block, part });
        for (i, d) in self.diag.iter().enumerate() {
            if !d.iter().all(|v| v.is_finite()) {
                return bad(i, "diagonal block");
            }
        }
        for (i, u) in self.upper.iter().enumerate() {
            if !u.iter().all(|v| v.is_finite()) {
                return bad(i, "upper block");
            }
        }
        for (i, b) in self.rhs.iter().enumerate() {
            if !b.iter().all(|v| v.is_finite()) {
                return bad(i, "right-hand side");
            }
        }
        Ok(())
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolveError {
    /// Elimination met a non-positive (or numerically zero) pivot in this diagonal block: the
    /// unknowns up to that anchor are not determined, e.g. no prior and no observations.
    #[error("normal matrix is not positive definite: elimination failed at diagonal block {block} (anchor offset {block}); are prior and smoothness weights set?")]
    NotPositiveDefinite { block: usize },
    #[error("inconsistent block-tridiagonal system: {diag} diagonal blocks, {upper} upper blocks and {rhs} right-hand sides (expected n, n−1 and n)")]
    Shape { diag: usize, upper: usize, rhs: usize },
    #[error("non-finite value (NaN or infinity) in the {part} of block {block}")]
    NonFinite { block: usize, part: &'static str },
}

/// The block LDLᵀ factorisation of a [`BlockTridiagonal`] matrix: per block, the Cholesky factor of
/// the pivot `D_i` and the gain `G_i = D_i⁻¹ H_{i,i+1}`. Two 6×6 matrices per anchor.
#[derive(Clone, Debug)]
pub struct BlockLdlt {
    pivots: Vec<Chol6>,
    gains: Vec<Mat6>,
}

impl BlockLdlt {
    /// Factorises the matrix of `sys` (its right-hand side is ignored but must have the right
    /// length). Fails with the index of the first block whose pivot is not positive definite.
    pub fn factor(sys: &BlockTridiagonal) -> Result<Self, SolveError> {
        sys.check_shape()?;
        sys.check_finite()?;
        let n = sys.len();
        let mut pivots = Vec::with_capacity(n);
        let mut gains = Vec::with_capacity(n.saturating_sub(1));
        let mut schur = Mat6::zeros(); // U_{i−1}ᵀ G_{i−1}, what earlier blocks take from H_ii
        for i in 0..n {
            let h = &sys.diag[i];
            let d = h - schur;
            // Pivots are judged against H_ii's own diagonal, so the test is scale-invariant per unknown.
            let chol = Chol6::factor(&d, h).ok_or(SolveError::NotPositiveDefinite { block: i })?;
            if i + 1 < n {
                let u = &sys.upper[i];
                let g = chol.solve_mat(u);
                schur = u.tr_mul(&g);
                gains.push(g);
            }
            pivots.push(chol);
        }
        Ok(Self { pivots, gains })
    }

    pub fn len(&self) -> usize {
        self.pivots.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pivots.is_empty()
    }

    /// Solves `H x = rhs` with the factorised `H`.
    pub fn solve(&self, rhs: &[Vec6]) -> Result<Vec<Vec6>, SolveError> {
        let n = self.len();
        if rhs.len() != n {
            return Err(SolveError::Shape { diag: n, upper: self.gains.len(), rhs: rhs.len() });
        }
        if let Some(i) = rhs.iter().position(|b| !b.iter().all(|v| v.is_finite())) {
            return Err(SolveError::NonFinite { block: i, part: "right-hand side" });
        }
        // Forward: z_i = D_i⁻¹ y_i with y_i = b_i − G_{i−1}ᵀ y_{i−1} (G_{i−1}ᵀ = U_{i−1}ᵀ D_{i−1}⁻¹).
        let mut x = Vec::with_capacity(n);
        let mut y_prev = Vec6::zeros();
        for i in 0..n {
            let y = if i == 0 { rhs[0] } else { rhs[i] - self.gains[i - 1].tr_mul(&y_prev) };
            x.push(self.pivots[i].solve_vec(&y));
            y_prev = y;
        }
        // Backward: x_i = z_i − G_i x_{i+1}.
        for i in (0..n.saturating_sub(1)).rev() {
            let next = x[i + 1];
            x[i] -= self.gains[i] * next;
        }
        if let Some(i) = x.iter().position(|v| !v.iter().all(|c| c.is_finite())) {
            return Err(SolveError::NonFinite { block: i, part: "solution" });
        }
        Ok(x)
    }

    /// Diagonal blocks `Σ_ii` of `H⁻¹`: the covariance of each anchor's correction (in units of
    /// the observations' variance factor), by the RTS backward recursion.
    pub fn marginal_covariances(&self) -> Vec<Mat6> {
        let n = self.len();
        let mut out = vec![Mat6::zeros(); n];
        for i in (0..n).rev() {
            let mut s = self.pivots[i].inverse();
            if i + 1 < n {
                let g = &self.gains[i];
                s += g * out[i + 1] * g.transpose();
            }
            // Keep it exactly symmetric so standard deviations and later products stay consistent.
            out[i] = (s + s.transpose()) * 0.5;
        }
        out
    }
}

/// Solves `H x = b` exactly in O(n).
pub fn solve(sys: &BlockTridiagonal) -> Result<Vec<Vec6>, SolveError> {
    BlockLdlt::factor(sys)?.solve(&sys.rhs)
}

/// Solves `H x = b` and returns `x` with the marginal covariance blocks `Σ_ii` of `H⁻¹`.
pub fn solve_with_covariance(sys: &BlockTridiagonal) -> Result<(Vec<Vec6>, Vec<Mat6>), SolveError> {
    let f = BlockLdlt::factor(sys)?;
    let x = f.solve(&sys.rhs)?;
    Ok((x, f.marginal_covariances()))
}

#[cfg(test)]
mod tests;
