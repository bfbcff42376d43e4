//! `precimap bench solve` and `precimap bench field-solve`: the block-tridiagonal trajectory
//! solver and the common-mode field's sparse solver on synthetic systems shaped like real ones.

use crate::rng::SplitMix64;
use precimap_solve::sparse::{SparseError, SymmetricSparse};
use precimap_solve::{solve, BlockTridiagonal, Mat6, Vec6};
use serde::Serialize;
use std::time::Instant;

/// A system shaped like real normal equations of one trajectory with `n` anchors (deterministic
/// for a given `seed`): per anchor interval a few point-to-plane observations standing for ~500
/// points at σ = 5 mm (ranges 3–30 m, so rotation entries reach ~1e10), the paper's default
/// prior (0.3 m, 0.05°) and smoothness (2 cm, 0.003°), and an occasional interval without
/// observations. Entries span roughly 1e1..1e10.
pub fn synthetic_system(n: usize, seed: u64) -> BlockTridiagonal {
    let mut rng = SplitMix64::new(seed);
    let mut sys = BlockTridiagonal::zeros(n);
    let prior = diag6(1.0 / 0.3f64.powi(2), 1.0 / 0.05f64.to_radians().powi(2));
    let smooth = diag6(1.0 / 0.02f64.powi(2), 1.0 / 0.003f64.to_radians().powi(2));
    let weight = 1.0 / 0.005f64.powi(2);
    for i in 0..n {
        sys.diag[i] += prior;
        // The prior is on the total correction: b gets −P x̄ for the current estimate x̄.
        let xbar = Vec6::from_fn(|k, _| if k < 3 { 0.1 * rng.normal() } else { 1e-3 * rng.normal() });
        sys.rhs[i] -= prior * xbar;
    }
    for i in 0..n.saturating_sub(1) {
        sys.diag[i] += smooth;
        sys.diag[i + 1] += smooth;
        sys.upper[i] -= smooth;
        if rng.uniform() < 0.05 {
            continue; // a gap: this interval is held by prior and smoothness alone
        }
        for _ in 0..5 {
            let w = random_unit(&mut rng);
            let r = random_unit(&mut rng) * rng.range(3.0, 30.0);
            let g = Vec6::new(w.x, w.y, w.z, 0.0, 0.0, 0.0) + {
                let c = r.cross(&w);
                Vec6::new(0.0, 0.0, 0.0, c.x, c.y, c.z)
            };
            let lambda = rng.uniform();
            let wt = weight * 100.0; // one representative for ~100 points
            let ggt = g * g.transpose() * wt;
            let e = 0.02 * rng.normal();
            sys.diag[i] += ggt * (1.0 - lambda).powi(2);
            sys.upper[i] += ggt * (lambda * (1.0 - lambda));
            sys.diag[i + 1] += ggt * lambda.powi(2);
            sys.rhs[i] -= g * (wt * e * (1.0 - lambda));
            sys.rhs[i + 1] -= g * (wt * e * lambda);
        }
    }
    sys
}

fn diag6(a: f64, b: f64) -> Mat6 {
    Mat6::from_diagonal(&Vec6::new(a, a, a, b, b, b))
}

fn random_unit(rng: &mut SplitMix64) -> nalgebra::Vector3<f64> {
    loop {
        let v = nalgebra::Vector3::new(rng.normal(), rng.normal(), rng.normal());
        let len = v.norm();
        if len > 1e-6 {
            return v / len;
        }
    }
}

/// Solves a [`synthetic_system`] of `n` anchors `repeats` times on the calling thread and returns
/// the throughput in anchors per second (factorisation plus solve; building the system is not
/// timed). Returns 0 when nothing was solved or the system could not be solved.
pub fn bench_solve(n: usize, repeats: usize) -> f64 {
    let sys = synthetic_system(n, 0x5EED);
    let start = Instant::now();
    for _ in 0..repeats {
        match solve(std::hint::black_box(&sys)) {
            Ok(x) => {
                std::hint::black_box(x);
            }
            Err(_) => return 0.0,
        }
    }
    let secs = start.elapsed().as_secs_f64();
    if n == 0 || repeats == 0 || secs <= 0.0 {
        return 0.0;
    }
    (n * repeats) as f64 / secs
}

/// A field-like system over a street network: nodes on a square grid of `blocks` × `blocks` city
/// blocks, five nodes of block between streets two nodes wide (15 m nodes: 30 m streets, 75 m
/// blocks), `per_node` unknowns per node (3: the translation; 4 with the field's heading), each
/// node coupled to its eight grid neighbours on the streets by a random positive semi-definite
/// block, plus a weak prior on every unknown. Returns the system and a right-hand side.
pub fn street_network_system(blocks: usize, per_node: usize, seed: u64) -> (SymmetricSparse, Vec<f64>) {
    let mut rng = SplitMix64::new(seed);
    let side = 7 * blocks + 2;
    let street = |x: usize, y: usize| x % 7 < 2 || y % 7 < 2;
    let mut index = vec![usize::MAX; side * side];
    let mut nodes = 0;
    for y in 0..side {
        for x in 0..side {
            if street(x, y) {
                index[y * side + x] = nodes;
                nodes += 1;
            }
        }
    }
    let mut m = SymmetricSparse::new(per_node * nodes);
    for y in 0..side {
        for x in 0..side {
            let a = index[y * side + x];
            if a == usize::MAX {
                continue;
            }
            for (dx, dy) in [(1, 0), (0, 1), (1, 1), (-1, 1)] {
                let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                if nx < 0 || nx >= side as i64 || ny >= side as i64 {
                    continue;
                }
                let b = index[ny as usize * side + nx as usize];
                if b == usize::MAX {
                    continue;
                }
                // w (e_a − e_b)(e_a − e_b)ᵀ ⊗ u uᵀ with a random direction u.
                let u: Vec<f64> = (0..per_node).map(|_| rng.uniform() - 0.5).collect();
                let w = 1.0 + 1e3 * rng.uniform();
                for r in 0..per_node {
                    for c in 0..per_node {
                        let v = w * u[r] * u[c];
                        if r >= c {
                            m.add(per_node * a + r, per_node * a + c, v);
                            m.add(per_node * b + r, per_node * b + c, v);
                        }
                        m.add(per_node * a + r, per_node * b + c, -v);
                    }
                }
            }
        }
    }
    for i in 0..per_node * nodes {
        m.add(i, i, 1.0);
    }
    let rhs = (0..per_node * nodes).map(|_| rng.uniform() - 0.5).collect();
    (m, rhs)
}

/// Figures of [`bench_street_network`].
#[derive(Clone, Debug, Serialize)]
pub struct SparseBench {
    pub blocks: usize,
    pub unknowns: usize,
    /// Stored entries of the matrix's lower triangle.
    pub stored: usize,
    /// Stored entries of the factor (8 bytes each).
    pub factor_entries: usize,
    /// Ordering, factorisation and solve, seconds on the calling thread.
    pub sparse_s: f64,
    /// nalgebra's dense Cholesky of the same system, where it has at most 6,000 unknowns.
    pub dense_s: Option<f64>,
    /// Largest difference between the two solutions over the largest entry.
    pub dense_relative_difference: Option<f64>,
}

/// Solves [`street_network_system`] with the sparse Cholesky, and with a dense Cholesky where it
/// is small enough to form.
pub fn bench_street_network(blocks: usize, per_node: usize) -> Result<SparseBench, SparseError> {
    let (m, rhs) = street_network_system(blocks, per_node, 0x5EED);
    let n = m.unknowns();
    let start = std::time::Instant::now();
    let factor = m.factorise(usize::MAX)?;
    let x = std::hint::black_box(factor.solve(&rhs));
    let sparse_s = start.elapsed().as_secs_f64();
    let (mut dense_s, mut dense_relative_difference) = (None, None);
    if n <= 6_000 {
        let mut dense = nalgebra::DMatrix::<f64>::zeros(n, n);
        for (i, j, v) in m.lower_entries() {
            dense[(i, j)] = v;
            dense[(j, i)] = v;
        }
        let b = nalgebra::DVector::from_vec(rhs);
        let start = std::time::Instant::now();
        let chol = nalgebra::Cholesky::new(dense).ok_or(SparseError::NotPositiveDefinite { pivot: 0, unknowns: n })?;
        let y = std::hint::black_box(chol.solve(&b));
        dense_s = Some(start.elapsed().as_secs_f64());
        let scale = y.amax().max(f64::MIN_POSITIVE);
        dense_relative_difference =
            Some(x.iter().zip(y.iter()).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max) / scale);
    }
    Ok(SparseBench {
        blocks,
        unknowns: n,
        stored: m.stored(),
        factor_entries: factor.entries(),
        sparse_s,
        dense_s,
        dense_relative_difference,
    })
}

impl SparseBench {
    /// The figures for a terminal; `per_node` as given to [`bench_street_network`].
    pub fn text(&self, per_node: usize) -> String {
        let blocks = self.blocks;
        let area_km2 = (blocks as f64 * 7.0 * 15.0 / 1000.0).powi(2);
        let mut out = format!(
            "field solve, {blocks} × {blocks} blocks ({area_km2:.2} km², {} nodes, {} unknowns):\n",
            self.unknowns / per_node,
            self.unknowns
        );
        out.push_str(&format!(
            "  sparse Cholesky (AMD order, supernodal): {:.3} s ({:.0} k unknowns/s per core), {} factor entries ({:.1} MiB; dense: {:.1} MiB)\n",
            self.sparse_s,
            self.unknowns as f64 / self.sparse_s.max(1e-9) / 1e3,
            self.factor_entries,
            self.factor_entries as f64 * 8.0 / 1048576.0,
            (self.unknowns as f64).powi(2) * 8.0 / 1048576.0
        ));
        match (self.dense_s, self.dense_relative_difference) {
            (Some(d), Some(diff)) => out.push_str(&format!(
                "  dense Cholesky: {d:.3} s → sparse {:.1}× faster; solutions differ by {diff:.1e} (relative)",
                d / self.sparse_s
            )),
            _ => out.push_str("  dense Cholesky: not run (more than 6,000 unknowns)"),
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use precimap_solve::solve_with_covariance;

    /// ‖H x − b‖ / ‖b‖.
    fn relative_residual(sys: &BlockTridiagonal, x: &[Vec6]) -> f64 {
        let stacked =
            |v: &[Vec6]| nalgebra::DVector::from_iterator(6 * v.len(), v.iter().flat_map(|b| b.iter().copied()));
        let b = sys.rhs_dense();
        (stacked(&sys.multiply(x).unwrap()) - &b).norm() / b.norm()
    }

    #[test]
    fn synthetic_real_like_systems_solve_accurately() {
        for (n, seed) in [(1, 1), (2, 2), (200, 3), (5000, 4)] {
            let sys = synthetic_system(n, seed);
            let (x, cov) = solve_with_covariance(&sys).unwrap();
            let r = relative_residual(&sys, &x);
            assert!(r < 1e-9, "n={n}: relative residual {r:e}");
            for s in &cov {
                assert!((0..6).all(|k| s[(k, k)] > 0.0));
            }
            if n <= 200 {
                let dense = nalgebra::Cholesky::new(sys.to_dense()).expect("the system is SPD").solve(&sys.rhs_dense());
                let x = nalgebra::DVector::from_iterator(6 * n, x.iter().flat_map(|b| b.iter().copied()));
                let e = (&x - &dense).norm() / dense.norm();
                assert!(e < 1e-9, "n={n}: relative error {e:e} against the dense solve");
            }
        }
    }

    #[test]
    fn street_network_system_solves_like_the_dense_solve() {
        let (sparse, rhs) = street_network_system(3, 4, 11);
        let n = sparse.unknowns();
        let mut dense = nalgebra::DMatrix::<f64>::zeros(n, n);
        for i in 0..n {
            for j in 0..=i {
                let v = sparse.get(i, j);
                dense[(i, j)] = v;
                dense[(j, i)] = v;
            }
        }
        let x = sparse.solve(&rhs, usize::MAX).unwrap();
        let r = &dense * nalgebra::DVector::from_vec(x) - nalgebra::DVector::from_vec(rhs.clone());
        assert!(r.amax() < 1e-9, "residual {}", r.amax());
    }

    #[test]
    fn the_benchmarks_measure_and_compare() {
        assert!(bench_solve(200, 2) > 0.0);
        assert_eq!(bench_solve(0, 2), 0.0);
        let b = bench_street_network(2, 4).unwrap();
        assert_eq!(b.unknowns % 4, 0);
        assert!(b.dense_relative_difference.unwrap() < 1e-9, "{b:?}");
        assert!(b.text(4).contains("dense Cholesky"));
    }
}
