use super::*;
use crate::rng::SplitMix64;
use nalgebra::{DMatrix, DVector, SMatrix};

/// How the random test systems are scaled.
#[derive(Clone, Copy, Debug)]
struct Conditioning {
    /// Prior on every anchor: added to the translation and rotation diagonal entries.
    prior: (f64, f64),
    /// Smoothness between neighbouring anchors (translation, rotation weights), if any.
    smooth: Option<(f64, f64)>,
    /// Observation weights are drawn log-uniformly from `weight.0..weight.1`.
    weight: (f64, f64),
    /// Columns 3..6 (rotations) of each observation row are scaled by this (lever arm).
    lever: f64,
}

const WELL: Conditioning = Conditioning { prior: (1.0, 1.0), smooth: None, weight: (0.5, 2.0), lever: 1.0 };
/// Like real data: σ = 5 mm weights (4e4) times 1–100 points, 30 m lever arms, the default prior
/// (0.3 m, 0.05°) and smoothness (2 cm, 0.003°). Entries span ~1e1..1e10, cond(H) ~1e8.
const REALISTIC: Conditioning =
    Conditioning { prior: (11.1, 1.3e6), smooth: Some((2.5e3, 3.6e8)), weight: (4e4, 4e6), lever: 30.0 };
/// No smoothness, a feeble prior and wild weights: cond(H) up to ~1e15.
const POOR: Conditioning = Conditioning { prior: (1e-6, 1e-6), smooth: None, weight: (1e-2, 1e4), lever: 100.0 };

/// Sums of per-anchor-pair 12×12 PSD contributions `w·aᵀa` (point-to-plane rows spanning two
/// anchors, as real observations do) plus a ridge on the diagonal.
fn random_system(n: usize, seed: u64, c: Conditioning) -> BlockTridiagonal {
    let mut rng = SplitMix64::new(seed);
    let mut sys = BlockTridiagonal::zeros(n);
    let log_w = (c.weight.0.ln(), c.weight.1.ln());
    let row = |rng: &mut SplitMix64| {
        let mut a = SMatrix::<f64, 1, 6>::from_fn(|_, _| rng.normal());
        for k in 3..6 {
            a[k] *= c.lever;
        }
        (a, rng.range(log_w.0, log_w.1).exp())
    };
    let diag6 = |(a, b): (f64, f64)| Mat6::from_diagonal(&Vec6::new(a, a, a, b, b, b));
    for i in 0..n {
        sys.diag[i] += diag6(c.prior);
        sys.rhs[i] = Vec6::from_fn(|_, _| rng.normal() * 100.0);
        if let (Some(s), true) = (c.smooth, i + 1 < n) {
            sys.diag[i] += diag6(s);
            sys.diag[i + 1] += diag6(s);
            sys.upper[i] -= diag6(s);
        }
    }
    if n == 1 {
        for _ in 0..4 {
            let (a, w) = row(&mut rng);
            sys.diag[0] += a.transpose() * a * w;
        }
    }
    for i in 0..n.saturating_sub(1) {
        // 0..12 rows per interval: few rows leave single intervals rank-deficient, as real gaps do.
        let rows = (rng.next_u64() % 13) as usize;
        for _ in 0..rows {
            let (g, w) = row(&mut rng);
            let lambda = rng.uniform();
            let mut a = SMatrix::<f64, 1, 12>::zeros();
            a.fixed_view_mut::<1, 6>(0, 0).copy_from(&(g * (1.0 - lambda)));
            a.fixed_view_mut::<1, 6>(0, 6).copy_from(&(g * lambda));
            let contrib = a.transpose() * a * w;
            sys.diag[i] += contrib.fixed_view::<6, 6>(0, 0);
            sys.upper[i] += contrib.fixed_view::<6, 6>(0, 6);
            sys.diag[i + 1] += contrib.fixed_view::<6, 6>(6, 6);
        }
    }
    sys
}

fn stack(x: &[Vec6]) -> DVector<f64> {
    DVector::from_iterator(6 * x.len(), x.iter().flat_map(|v| v.iter().copied()))
}

fn rel_residual(sys: &BlockTridiagonal, x: &[Vec6]) -> f64 {
    let hx = stack(&sys.multiply(x).unwrap());
    let b = sys.rhs_dense();
    (hx - &b).norm() / b.norm()
}

fn rel_err(a: &DVector<f64>, b: &DVector<f64>) -> f64 {
    (a - b).norm() / b.norm()
}

/// Checks x and (for small n, or a sample of blocks) Σ_ii against the dense Cholesky solution.
fn check_against_dense(sys: &BlockTridiagonal, x_tol: f64, cov_tol: f64) {
    let n = sys.len();
    let dense = sys.to_dense();
    assert!((&dense - dense.transpose()).norm() == 0.0);
    let chol = nalgebra::Cholesky::new(dense.clone()).expect("test system is SPD");
    let x_dense = chol.solve(&sys.rhs_dense());
    let (x, cov) = solve_with_covariance(sys).unwrap();
    let e = rel_err(&stack(&x), &x_dense);
    assert!(e < x_tol, "n={n}: x relative error {e:e} ≥ {x_tol:e}");
    let r = rel_residual(sys, &x);
    assert!(r < 1e-9, "n={n}: relative residual {r:e}");
    // Σ_ii from the dense factor, one 6-column block at a time (no full inverse for large n).
    let blocks: Vec<usize> = if n <= 50 { (0..n).collect() } else { vec![0, 1, n / 2, n - 2, n - 1] };
    for i in blocks {
        let mut e_i = DMatrix::zeros(6 * n, 6);
        for k in 0..6 {
            e_i[(6 * i + k, k)] = 1.0;
        }
        let cols = chol.solve(&e_i);
        let want = cols.fixed_view::<6, 6>(6 * i, 0).into_owned();
        let err = (cov[i] - want).norm() / want.norm();
        assert!(err < cov_tol, "n={n}: Σ_{i},{i} relative error {err:e} ≥ {cov_tol:e}");
        assert_eq!(cov[i], cov[i].transpose());
    }
}

#[test]
fn matches_dense_solve_well_conditioned() {
    for (seed, &n) in [1usize, 2, 3, 7, 50, 500].iter().enumerate() {
        check_against_dense(&random_system(n, seed as u64 + 11, WELL), 1e-12, 1e-11);
    }
}

#[test]
fn matches_dense_solve_realistic_scaling() {
    for (seed, &n) in [1usize, 2, 3, 7, 50, 500].iter().enumerate() {
        check_against_dense(&random_system(n, seed as u64 + 101, REALISTIC), 1e-9, 1e-9);
    }
}

#[test]
fn matches_dense_solve_poorly_conditioned() {
    // cond(H) up to ~1e15 here: forward errors of ~cond·ε and residuals of ~cond·ε·‖b‖ are
    // expected from any method. What must hold is backward stability: the normwise backward error
    // ‖Hx − b‖ / (‖H‖‖x‖ + ‖b‖) stays at rounding level, and the answer agrees with the dense one.
    for (seed, &n) in [1usize, 2, 3, 7, 50].iter().enumerate() {
        let sys = random_system(n, seed as u64 + 1001, POOR);
        let dense = sys.to_dense();
        let b = sys.rhs_dense();
        let x_dense = nalgebra::Cholesky::new(dense.clone()).unwrap().solve(&b);
        let x = stack(&solve(&sys).unwrap());
        let backward = (&dense * &x - &b).norm() / (dense.norm() * x.norm() + b.norm());
        assert!(backward < 1e-14, "n={n}: backward error {backward:e}");
        assert!(rel_err(&x, &x_dense) < 1e-3, "n={n}");
    }
}

#[test]
fn recovers_known_solution() {
    let mut sys = random_system(40, 7, REALISTIC);
    let truth: Vec<Vec6> = (0..40).map(|i| Vec6::from_fn(|k, _| (i * 6 + k) as f64 * 0.01 - 1.0)).collect();
    sys.rhs = sys.multiply(&truth).unwrap();
    let x = solve(&sys).unwrap();
    assert!(rel_err(&stack(&x), &stack(&truth)) < 1e-9);
}

#[test]
fn factorisation_is_reusable_for_other_right_hand_sides() {
    let sys = random_system(20, 8, WELL);
    let f = BlockLdlt::factor(&sys).unwrap();
    assert_eq!(f.len(), 20);
    let other: Vec<Vec6> = (0..20).map(|i| Vec6::repeat(i as f64)).collect();
    let x = f.solve(&other).unwrap();
    let hx = sys.multiply(&x).unwrap();
    assert!(rel_err(&stack(&hx), &stack(&other)) < 1e-12);
    assert!(matches!(f.solve(&other[..3]), Err(SolveError::Shape { rhs: 3, .. })));
}

#[test]
fn reports_the_block_where_positive_definiteness_fails() {
    for k in [0, 1, 6, 29] {
        let mut sys = random_system(30, 21, WELL);
        sys.diag[k][(2, 2)] = -1.0;
        assert_eq!(solve(&sys).unwrap_err(), SolveError::NotPositiveDefinite { block: k });
    }
    // Each block fine on its own, the coupling makes H indefinite: found at the second block.
    let mut sys = BlockTridiagonal::zeros(3);
    for d in &mut sys.diag {
        *d = Mat6::identity();
    }
    sys.upper[0] = Mat6::identity() * 2.0;
    assert_eq!(solve(&sys).unwrap_err(), SolveError::NotPositiveDefinite { block: 1 });
    // No prior, no observations: singular at once.
    assert_eq!(solve(&BlockTridiagonal::zeros(4)).unwrap_err(), SolveError::NotPositiveDefinite { block: 0 });
    // Singular up to rounding (an exactly repeated unknown) is rejected too, not solved into noise.
    let mut sys = BlockTridiagonal::zeros(2);
    let a = SMatrix::<f64, 1, 6>::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0);
    sys.diag[0] = Mat6::identity();
    sys.diag[1] = a.transpose() * a * 1e6;
    assert_eq!(solve(&sys).unwrap_err(), SolveError::NotPositiveDefinite { block: 1 });
    assert!(SolveError::NotPositiveDefinite { block: 1 }.to_string().contains("block 1"));
}

#[test]
fn shape_and_non_finite_errors() {
    let mut sys = random_system(5, 3, WELL);
    sys.rhs.pop();
    assert_eq!(solve(&sys).unwrap_err(), SolveError::Shape { diag: 5, upper: 4, rhs: 4 });
    let mut sys = random_system(5, 3, WELL);
    sys.upper.push(Mat6::zeros());
    assert_eq!(solve(&sys).unwrap_err(), SolveError::Shape { diag: 5, upper: 5, rhs: 5 });
    let sys = BlockTridiagonal { diag: vec![], upper: vec![Mat6::zeros()], rhs: vec![] };
    assert!(matches!(solve(&sys), Err(SolveError::Shape { .. })));
    let mut sys = random_system(5, 3, WELL);
    sys.rhs[3][1] = f64::NAN;
    assert_eq!(solve(&sys).unwrap_err(), SolveError::NonFinite { block: 3, part: "right-hand side" });
    let mut sys = random_system(5, 3, WELL);
    sys.upper[2][(0, 5)] = f64::INFINITY;
    assert_eq!(solve(&sys).unwrap_err(), SolveError::NonFinite { block: 2, part: "upper block" });
    let mut sys = random_system(5, 3, WELL);
    sys.diag[4][(3, 3)] = f64::NAN;
    assert_eq!(solve(&sys).unwrap_err(), SolveError::NonFinite { block: 4, part: "diagonal block" });
}

#[test]
fn empty_and_zeros() {
    let sys = BlockTridiagonal::zeros(0);
    assert!(sys.is_empty() && sys.upper.is_empty());
    assert!(solve(&sys).unwrap().is_empty());
    let (x, cov) = solve_with_covariance(&sys).unwrap();
    assert!(x.is_empty() && cov.is_empty());
    assert_eq!(sys.to_dense().nrows(), 0);
    let sys = BlockTridiagonal::zeros(3);
    assert_eq!((sys.len(), sys.upper.len(), sys.rhs.len()), (3, 2, 3));
    assert_eq!(sys.to_dense().shape(), (18, 18));
}
