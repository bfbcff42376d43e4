//! The settings of precimap's sparse Cholesky (`precimap_solve::sparse`: faer, AMD order,
//! fundamental supernodes) against faer's default supernode amalgamation, on the street-network
//! systems of `precimap bench field-solve`. Single-threaded: the field solve runs on one
//! thread, and faer is built without rayon. Indices are 32-bit, as precimap's are.

use crate::alloc::peak_during;
use crate::thread_cpu_s;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholeskyRaw, SymmetricOrdering,
};
use faer::sparse::linalg::SymbolicSupernodalParams;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Conj, Mat, Par, Side, Spec};
use precimap_bench::solve::street_network_system;
use precimap_solve::sparse::SymmetricSparse;

/// One solver's figures on one system.
struct Run {
    /// Least CPU seconds over the repeats: ordering, conversion, factorisation and solve.
    seconds: f64,
    /// Stored factor entries (faer's supernodal blocks count in full, as they are stored).
    entries: usize,
    /// Peak heap bytes added during one ordering + factorisation + solve.
    peak: usize,
    x: Vec<f64>,
    /// "simplicial" or "supernodal" for faer.
    kind: &'static str,
}

fn ours(m: &SymmetricSparse, rhs: &[f64]) -> Run {
    let ((x, entries), peak) = peak_during(|| {
        let factor = m.factorise(usize::MAX).expect("the system is SPD");
        (factor.solve(rhs), factor.entries())
    });
    Run { seconds: 0.0, entries, peak, x, kind: "product" }
}

/// faer's LLᵀ in AMD order; `relax`: faer's default supernode amalgamation (explicit zeros
/// stored for denser blocks) or none (fundamental supernodes: the least memory).
fn faer_llt(m: &SymmetricSparse, rhs: &[f64], relax: bool) -> Run {
    let n = m.unknowns();
    let ((x, entries, kind), peak) = peak_during(|| {
        let triplets: Vec<Triplet<u32, u32, f64>> =
            m.lower_entries().map(|(row, col, val)| Triplet { row: row as u32, col: col as u32, val }).collect();
        let a = SparseColMat::<u32, f64>::try_new_from_triplets(n, n, &triplets).expect("valid entries");
        drop(triplets);
        let ordering = SymmetricOrdering::Amd;
        let mut params = CholeskySymbolicParams::default();
        if !relax {
            params.supernodal_params = SymbolicSupernodalParams { relax: None };
        }
        let symbolic =
            factorize_symbolic_cholesky(a.symbolic(), Side::Lower, ordering, params).expect("symbolic factorisation");
        let kind = match symbolic.raw() {
            SymbolicCholeskyRaw::Simplicial(_) => "simplicial",
            SymbolicCholeskyRaw::Supernodal(_) => "supernodal",
        };
        let mut values = vec![0.0f64; symbolic.len_val()];
        let par = Par::Seq;
        let mut scratch = MemBuffer::new(
            symbolic
                .factorize_numeric_llt_scratch::<f64>(par, Spec::default())
                .or(symbolic.solve_in_place_scratch::<f64>(1, par)),
        );
        let llt = symbolic
            .factorize_numeric_llt(
                &mut values,
                a.as_ref(),
                Side::Lower,
                LltRegularization::default(),
                par,
                MemStack::new(&mut scratch),
                Spec::default(),
            )
            .expect("the system is SPD");
        let mut b = Mat::<f64>::from_fn(n, 1, |i, _| rhs[i]);
        llt.solve_in_place_with_conj(Conj::No, b.as_mut(), par, MemStack::new(&mut scratch));
        ((0..n).map(|i| b[(i, 0)]).collect::<Vec<f64>>(), symbolic.len_val(), kind)
    });
    Run { seconds: 0.0, entries, peak, x, kind }
}

/// Runs each solver `repeats` times, round robin (a change of the machine's load falls on all
/// of them), and keeps each one's least CPU time and its first run's figures.
fn timed(repeats: usize, solvers: &mut [&mut dyn FnMut() -> Run]) -> Vec<Run> {
    let mut runs: Vec<Option<Run>> = solvers.iter().map(|_| None).collect();
    let mut best = vec![f64::INFINITY; solvers.len()];
    for _ in 0..repeats {
        for (k, solve) in solvers.iter_mut().enumerate() {
            let start = thread_cpu_s();
            let run = solve();
            best[k] = best[k].min(thread_cpu_s() - start);
            runs[k].get_or_insert(run);
        }
    }
    runs.into_iter().zip(best).map(|(run, s)| Run { seconds: s, ..run.expect("at least one repeat") }).collect()
}

/// ‖A x − b‖ / ‖b‖ with A given by its lower triangle.
fn relative_residual(m: &SymmetricSparse, x: &[f64], b: &[f64]) -> f64 {
    let mut r: Vec<f64> = b.iter().map(|v| -v).collect();
    for (i, j, v) in m.lower_entries() {
        r[i] += v * x[j];
        if i != j {
            r[j] += v * x[i];
        }
    }
    let norm = |v: &[f64]| v.iter().map(|a| a * a).sum::<f64>().sqrt();
    norm(&r) / norm(b)
}

pub fn run(blocks: &[usize], per_node: usize, repeats: usize) {
    println!("# sparse Cholesky: precimap's settings (faer, AMD, fundamental supernodes) vs faer's defaults, one thread, least CPU-seconds of {repeats}");
    println!(
        "blocks unknowns | solver                 kind      CPU-seconds speed-up  factor-entries  peak-MiB  rel-residual  max|x-x_ours|/max|x_ours|"
    );
    for &b in blocks {
        let (m, rhs) = street_network_system(b, per_node, 0x5EED);
        let n = m.unknowns();
        let runs = timed(
            repeats,
            &mut [
                &mut || ours(&m, &rhs),
                &mut || faer_llt(&m, &rhs, true),
                &mut || faer_llt(&m, &rhs, false),
            ],
        );
        let [base, amd, amd_tight] = <[Run; 3]>::try_from(runs).ok().expect("three solvers");
        let scale = base.x.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        for (name, run) in [
            ("precimap", &base),
            ("faer, AMD", &amd),
            ("faer, AMD, no relaxing", &amd_tight),
        ] {
            let diff = run.x.iter().zip(&base.x).fold(0.0f64, |a, (p, q)| a.max((p - q).abs())) / scale;
            println!(
                "{b:>6} {n:>8} | {name:<22} {:<10} {:>8.3} {:>8.2}x {:>15} {:>9.1} {:>13.1e} {:>13.1e}",
                run.kind,
                run.seconds,
                base.seconds / run.seconds,
                run.entries,
                run.peak as f64 / 1048576.0,
                relative_residual(&m, &run.x, &rhs),
                diff
            );
        }
    }
}
