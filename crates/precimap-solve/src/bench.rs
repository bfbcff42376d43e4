//! A realistic synthetic system and a micro benchmark the CLI's `bench` command can call.

use crate::rng::SplitMix64;
use crate::{solve, BlockTridiagonal, Mat6, Vec6};
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
