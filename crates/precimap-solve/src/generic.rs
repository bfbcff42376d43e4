//! The same exact block-tridiagonal elimination for any fixed block size N (e.g. 12×12 blocks
//! of anchor pairs, which keep a system with second-difference terms block-tridiagonal).
//! Uses nalgebra's fixed-size Cholesky for the pivots.

use crate::SolveError;
use nalgebra::{SMatrix, SVector};

/// `H x = b` with diagonal blocks `diag[i]`, `upper[i] = H_{i,i+1}`; returns `x` and, when
/// asked, the diagonal blocks of `H⁻¹`.
#[allow(clippy::type_complexity)]
pub fn solve_blocks<const N: usize>(
    diag: &[SMatrix<f64, N, N>],
    upper: &[SMatrix<f64, N, N>],
    rhs: &[SVector<f64, N>],
    with_covariance: bool,
) -> Result<(Vec<SVector<f64, N>>, Option<Vec<SMatrix<f64, N, N>>>), SolveError> {
    let n = diag.len();
    if rhs.len() != n || upper.len() != n.saturating_sub(1) {
        return Err(SolveError::Shape { diag: n, upper: upper.len(), rhs: rhs.len() });
    }
    let factor = BlocksLdlt::factor(diag, upper)?;
    let x = factor.solve(rhs)?;
    Ok((x, with_covariance.then(|| factor.marginal_covariances())))
}

/// The block LDLᵀ factorisation of a block-tridiagonal matrix with N×N blocks: per block the
/// Cholesky factor of the pivot and the gain `D_i⁻¹ H_{i,i+1}`, for solves with many right-hand
/// sides.
#[derive(Clone, Debug)]
pub struct BlocksLdlt<const N: usize> {
    chol: Vec<nalgebra::Cholesky<f64, nalgebra::Const<N>>>,
    gain: Vec<SMatrix<f64, N, N>>,
}

impl<const N: usize> BlocksLdlt<N> {
    pub fn factor(diag: &[SMatrix<f64, N, N>], upper: &[SMatrix<f64, N, N>]) -> Result<Self, SolveError> {
        let n = diag.len();
        if upper.len() != n.saturating_sub(1) {
            return Err(SolveError::Shape { diag: n, upper: upper.len(), rhs: n });
        }
        let mut chol = Vec::with_capacity(n);
        let mut gain: Vec<SMatrix<f64, N, N>> = Vec::with_capacity(n.saturating_sub(1));
        let mut pivot = diag.first().copied().unwrap_or_else(SMatrix::zeros);
        for i in 0..n {
            let c = nalgebra::Cholesky::new(pivot).ok_or(SolveError::NotPositiveDefinite { block: i })?;
            if i + 1 < n {
                let g = c.solve(&upper[i]);
                pivot = diag[i + 1] - upper[i].transpose() * g;
                gain.push(g);
            }
            chol.push(c);
        }
        Ok(Self { chol, gain })
    }

    pub fn len(&self) -> usize {
        self.chol.len()
    }

    pub fn is_empty(&self) -> bool {
        self.chol.is_empty()
    }

    /// Solves `H x = rhs`.
    pub fn solve(&self, rhs: &[SVector<f64, N>]) -> Result<Vec<SVector<f64, N>>, SolveError> {
        let n = self.len();
        if rhs.len() != n {
            return Err(SolveError::Shape { diag: n, upper: self.gain.len(), rhs: rhs.len() });
        }
        let mut y = Vec::with_capacity(n);
        let mut carry = rhs.first().copied().unwrap_or_else(SVector::zeros);
        for i in 0..n {
            y.push(carry);
            if i + 1 < n {
                carry = rhs[i + 1] - self.gain[i].transpose() * carry;
            }
        }
        let mut x = vec![SVector::<f64, N>::zeros(); n];
        for i in (0..n).rev() {
            let mut xi = self.chol[i].solve(&y[i]);
            if i + 1 < n {
                xi -= self.gain[i] * x[i + 1];
            }
            x[i] = xi;
        }
        Ok(x)
    }

    /// The diagonal blocks of `H⁻¹`.
    pub fn marginal_covariances(&self) -> Vec<SMatrix<f64, N, N>> {
        let n = self.len();
        let mut cov = vec![SMatrix::<f64, N, N>::zeros(); n];
        for i in (0..n).rev() {
            let mut s = self.chol[i].inverse();
            if i + 1 < n {
                s += self.gain[i] * cov[i + 1] * self.gain[i].transpose();
            }
            cov[i] = s;
        }
        cov
    }

    /// The block band of `H⁻¹`: its diagonal blocks `Σ_ii` and the neighbours' `Σ_{i,i+1}`
    /// (`Σ_{i+1,i}` is its transpose), by the backward recursion `Σ_{i,i+1} = −G_i Σ_{i+1,i+1}`,
    /// `Σ_ii = D_i⁻¹ − Σ_{i,i+1} G_iᵀ`. The covariance of anything the band's unknowns form
    /// linearly over two neighbouring blocks, e.g. a difference between them.
    #[allow(clippy::type_complexity)]
    pub fn covariance_band(&self) -> (Vec<SMatrix<f64, N, N>>, Vec<SMatrix<f64, N, N>>) {
        let n = self.len();
        let mut cov = vec![SMatrix::<f64, N, N>::zeros(); n];
        let mut next = vec![SMatrix::<f64, N, N>::zeros(); n.saturating_sub(1)];
        for i in (0..n).rev() {
            let mut s = self.chol[i].inverse();
            if i + 1 < n {
                let cross = -self.gain[i] * cov[i + 1];
                s -= cross * self.gain[i].transpose();
                next[i] = cross;
            }
            cov[i] = (s + s.transpose()) * 0.5;
        }
        (cov, next)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    #[test]
    fn twelve_by_twelve_blocks_match_a_dense_solve() {
        const N: usize = 12;
        let mut seed = 7u64;
        let mut rand = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        for n in [1usize, 2, 5, 40] {
            let mut diag = vec![SMatrix::<f64, N, N>::zeros(); n];
            let mut upper = vec![SMatrix::<f64, N, N>::zeros(); n.saturating_sub(1)];
            // Sums of PSD contributions over neighbouring blocks plus a diagonal: SPD.
            for i in 0..n {
                for _ in 0..30 {
                    let a = SVector::<f64, N>::from_fn(|_, _| rand());
                    let b = SVector::<f64, N>::from_fn(|_, _| rand());
                    diag[i] += a * a.transpose();
                    if i + 1 < n {
                        diag[i] += b * b.transpose() * 0.5;
                        diag[i + 1] += a * a.transpose();
                        upper[i] += b * a.transpose() * 0.3;
                    }
                }
                diag[i] += SMatrix::<f64, N, N>::identity() * 50.0;
            }
            let rhs: Vec<_> = (0..n).map(|_| SVector::<f64, N>::from_fn(|_, _| rand())).collect();
            let mut dense = DMatrix::<f64>::zeros(n * N, n * N);
            let mut b = nalgebra::DVector::<f64>::zeros(n * N);
            for i in 0..n {
                dense.view_mut((i * N, i * N), (N, N)).copy_from(&diag[i]);
                b.rows_mut(i * N, N).copy_from(&rhs[i]);
                if i + 1 < n {
                    dense.view_mut((i * N, (i + 1) * N), (N, N)).copy_from(&upper[i]);
                    dense.view_mut(((i + 1) * N, i * N), (N, N)).copy_from(&upper[i].transpose());
                }
            }
            let chol = dense.clone().cholesky().expect("test system is SPD");
            let exact = chol.solve(&b);
            let inverse = chol.inverse();
            let (band, next) = BlocksLdlt::factor(&diag, &upper).unwrap().covariance_band();
            for i in 0..n {
                for a in 0..N {
                    for c in 0..N {
                        assert!((band[i][(a, c)] - inverse[(i * N + a, i * N + c)]).abs() < 1e-10);
                        if i + 1 < n {
                            assert!((next[i][(a, c)] - inverse[(i * N + a, (i + 1) * N + c)]).abs() < 1e-10);
                        }
                    }
                }
            }
            // The neighbours' covariances are not negligible beside the marginals.
            assert!(next.iter().all(|m| m.amax() > 0.001 * band[0].amax()), "n {n}");
            let (x, cov) = solve_blocks(&diag, &upper, &rhs, true).unwrap();
            let cov = cov.unwrap();
            for i in 0..n {
                for a in 0..N {
                    assert!((x[i][a] - exact[i * N + a]).abs() < 1e-10, "n {n} block {i}");
                    for c in 0..N {
                        assert!((cov[i][(a, c)] - inverse[(i * N + a, i * N + c)]).abs() < 1e-10);
                    }
                }
            }
        }
    }
}
