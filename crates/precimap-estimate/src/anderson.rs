//! Anderson acceleration of the settling iterations (`Parameters::anderson_depth`).
//!
//! A settling iteration is a pure map `G` from the corrections `x` it starts from to the ones it
//! ends with. Its fixed point is slow to reach: a common-mode shift the map moves along with is
//! relaxed by a few per cent per pass. Anderson (type II) keeps the last `m + 1` pairs
//! `(xⱼ, G(xⱼ))`, finds the combination of their steps `fⱼ = G(xⱼ) − xⱼ` that cancels best,
//! `γ = argmin ‖fₖ − ΔF γ‖`, and starts the next iteration from `G(xₖ) − ΔG γ` (ΔF, ΔG: the
//! differences of consecutive entries). On a linear map it is GMRES in disguise; the fixed point
//! is unchanged. One set of coefficients serves the whole campaign (the slow modes are shared by
//! every pass at a place), so the least-squares problem sums over every trajectory.
//!
//! Both drivers keep an [`AndersonHistory`] (of corrections in-process, of object keys in the
//! framework) and call [`accelerate`] with the same trajectories in the same order, so their
//! results stay byte-identical.

use crate::solve::CHANGE_RANGE_M;
use precimap_core::{IterationStep, Parameters, TrajectoryCorrections};
use serde::{Deserialize, Serialize};

/// Relative ridge on the coefficients' normal equations: consecutive steps of a nearly
/// converged iteration are nearly parallel.
const RIDGE: f64 = 1e-8;

/// One accelerated iteration: every trajectory's corrections at its start and at its end, in
/// trajectory order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AndersonEntry<T> {
    pub starts: Vec<T>,
    pub results: Vec<T>,
}

/// The accelerated iterations since the history last had to be cleared, oldest first.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AndersonHistory<T> {
    pub entries: Vec<AndersonEntry<T>>,
    /// The settings of the newest entry's step.
    pub step: Option<IterationStep>,
}

impl<T> Default for AndersonHistory<T> {
    fn default() -> Self {
        Self { entries: Vec::new(), step: None }
    }
}

impl<T> AndersonHistory<T> {
    /// Records a finished iteration and returns whether the next one should start from
    /// [`accelerate`] over the history instead of from `results`. Iterations that do not
    /// accelerate ([`IterationStep::accelerates`]) clear the history, and so does a change of
    /// unknowns or cells ([`IterationStep::continues_history`]). `results` is called only for an
    /// iteration that is kept: the drivers copy their corrections for the history, and only then.
    pub fn record(
        &mut self,
        params: &Parameters,
        step: &IterationStep,
        momentum_carried: bool,
        starts: Vec<T>,
        results: impl FnOnce() -> Vec<T>,
    ) -> bool {
        if !step.accelerates(momentum_carried, params) {
            self.entries.clear();
            self.step = None;
            return false;
        }
        if !self.step.is_some_and(|s| step.continues_history(&s, params)) {
            self.entries.clear();
        }
        self.step = Some(*step);
        self.entries.push(AndersonEntry { starts, results: results() });
        let keep = params.anderson_depth + 1;
        if self.entries.len() > keep {
            self.entries.drain(..self.entries.len() - keep);
        }
        self.entries.len() >= 2
    }

    /// Trajectory `t`'s history, oldest first: `(starts, results)`.
    pub fn trajectory(&self, t: usize) -> (Vec<&T>, Vec<&T>) {
        self.entries.iter().map(|e| (&e.starts[t], &e.results[t])).unzip()
    }
}

impl AndersonHistory<TrajectoryCorrections> {
    /// [`accelerate`] over every trajectory of the recorded corrections: the in-process
    /// driver's history, or the framework task's as read from its objects.
    pub fn accelerate(&self) -> Result<Acceleration, AndersonError> {
        let trajectories = self.entries.first().map_or(0, |e| e.results.len());
        for e in &self.entries {
            let named = e.starts.len().min(e.results.len());
            if e.starts.len() != trajectories || e.results.len() != trajectories {
                return Err(AndersonError::Shape {
                    trajectory: named,
                    detail: format!("an entry names {named} trajectories where the first names {trajectories}"),
                });
            }
        }
        let histories: Vec<TrajectoryHistory> = (0..trajectories)
            .map(|t| {
                let (starts, results) = self.trajectory(t);
                TrajectoryHistory { starts, results }
            })
            .collect();
        accelerate(&histories)
    }
}

/// One trajectory's history, oldest first (as many starts as results, at least two).
#[derive(Debug)]
pub struct TrajectoryHistory<'a> {
    pub starts: Vec<&'a TrajectoryCorrections>,
    pub results: Vec<&'a TrajectoryCorrections>,
}

/// The next iteration's start for every trajectory, and the coefficients `γ` (oldest
/// difference first) that made it.
#[derive(Clone, Debug, PartialEq)]
pub struct Acceleration {
    pub coefficients: Vec<f64>,
    pub corrections: Vec<TrajectoryCorrections>,
}

/// A share of the coefficients' least-squares problem: `ΔFᵀΔF` (row-major, `k × k`) and
/// `ΔFᵀfₖ` over some trajectories' anchors. One trajectory's share is small (`k ≤ 10`), so a
/// campaign's coefficients need every trajectory's share but never every trajectory's history
/// at once: the framework computes the shares in one task per trajectory and sums them in the
/// planner.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AndersonMoments {
    pub gram: Vec<f64>,
    pub rhs: Vec<f64>,
}

impl AndersonMoments {
    /// The empty sum over `k` differences.
    pub fn zeros(k: usize) -> Self {
        Self { gram: vec![0.0; k * k], rhs: vec![0.0; k] }
    }

    /// The number of differences `k`.
    pub fn differences(&self) -> usize {
        self.rhs.len()
    }

    /// Adds trajectory `trajectory`'s share (element by element: summing the trajectories'
    /// shares in trajectory order gives the same bits wherever it is done).
    pub fn add(&mut self, trajectory: usize, other: &Self) -> Result<(), AndersonError> {
        let k = self.differences();
        if other.rhs.len() != k || other.gram.len() != k * k || self.gram.len() != k * k {
            return Err(AndersonError::Shape {
                trajectory,
                detail: format!("its share is over {} differences where the others' are over {k}", other.rhs.len()),
            });
        }
        for (a, b) in self.gram.iter_mut().zip(&other.gram) {
            *a += b;
        }
        for (a, b) in self.rhs.iter_mut().zip(&other.rhs) {
            *a += b;
        }
        Ok(())
    }
}

/// Why a history cannot be combined.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AndersonError {
    #[error("trajectory {trajectory}: {detail}")]
    Shape { trajectory: usize, detail: String },
}

/// Combines every trajectory's history (see the module documentation): [`trajectory_moments`]
/// summed in trajectory order, [`coefficients`], then [`combine`] per trajectory, the three
/// steps the framework runs as tasks and in its planner. A history of one entry, or steps whose
/// differences are all zero, give `G(xₖ)` unchanged.
pub fn accelerate(histories: &[TrajectoryHistory<'_>]) -> Result<Acceleration, AndersonError> {
    let entries = histories.first().map_or(0, |h| h.results.len());
    let mut total = AndersonMoments::zeros(entries.saturating_sub(1));
    for (t, h) in histories.iter().enumerate() {
        if h.results.len() != entries || h.starts.len() != entries {
            return Err(AndersonError::Shape {
                trajectory: t,
                detail: format!(
                    "{} starts and {} results where every trajectory has {entries}",
                    h.starts.len(),
                    h.results.len()
                ),
            });
        }
        total.add(t, &trajectory_moments(t, h)?)?;
    }
    let coefficients = coefficients(&total);
    let corrections =
        histories.iter().enumerate().map(|(t, h)| combine(t, &h.results, &coefficients)).collect::<Result<_, _>>()?;
    Ok(Acceleration { coefficients, corrections })
}

/// Trajectory `trajectory`'s share of the coefficients' problem (the index only names it in
/// errors). The history must hold at least one entry, as many starts as results, all over the
/// same anchors, and finite steps.
pub fn trajectory_moments(trajectory: usize, h: &TrajectoryHistory<'_>) -> Result<AndersonMoments, AndersonError> {
    let shape = |detail: String| AndersonError::Shape { trajectory, detail };
    let entries = h.results.len();
    if entries == 0 {
        return Err(shape("the history is empty".into()));
    }
    if h.starts.len() != entries {
        return Err(shape(format!("{} starts and {entries} results", h.starts.len())));
    }
    same_anchors(trajectory, h.starts.iter().chain(&h.results))?;
    let k = entries - 1;
    let steps: Vec<Vec<f64>> = h.starts.iter().zip(&h.results).map(|(x, g)| weighted_step(x, g)).collect();
    if steps.iter().flatten().any(|v| !v.is_finite()) {
        return Err(shape("the history holds corrections that are not finite numbers".into()));
    }
    let diffs: Vec<Vec<f64>> = steps.windows(2).map(|w| w[1].iter().zip(&w[0]).map(|(a, b)| a - b).collect()).collect();
    let mut moments = AndersonMoments::zeros(k);
    for i in 0..k {
        for j in 0..=i {
            let d = dot(&diffs[i], &diffs[j]);
            moments.gram[i * k + j] = d;
            moments.gram[j * k + i] = d;
        }
        moments.rhs[i] = dot(&diffs[i], &steps[k]);
    }
    Ok(moments)
}

/// The coefficients `γ` from the summed shares: the `k × k` normal equations with a relative
/// ridge, by Cholesky; all zero where the steps did not change (or the system is singular).
pub fn coefficients(total: &AndersonMoments) -> Vec<f64> {
    let k = total.differences();
    if total.gram.len() != k * k {
        return vec![0.0; k];
    }
    let mut gram = nalgebra::DMatrix::<f64>::from_row_slice(k, k, &total.gram);
    let rhs = nalgebra::DVector::<f64>::from_column_slice(&total.rhs);
    let scale = (0..k).map(|i| gram[(i, i)]).fold(0.0, f64::max);
    if !(scale > 0.0 && scale.is_finite()) {
        return vec![0.0; k];
    }
    for i in 0..k {
        gram[(i, i)] += RIDGE * scale;
    }
    gram.cholesky().map_or_else(|| vec![0.0; k], |c| c.solve(&rhs).iter().copied().collect())
}

/// One trajectory's next start `G(xₖ) − ΔG γ` from its results, oldest first (one more than
/// there are coefficients, all over the same anchors).
pub fn combine(
    trajectory: usize,
    results: &[&TrajectoryCorrections],
    coefficients: &[f64],
) -> Result<TrajectoryCorrections, AndersonError> {
    let shape = |detail: String| AndersonError::Shape { trajectory, detail };
    let k = coefficients.len();
    let Some(newest) = results.last().filter(|_| results.len() == k + 1) else {
        return Err(shape(format!("{} results for {k} coefficients (expected {})", results.len(), k + 1)));
    };
    same_anchors(trajectory, results)?;
    let values = (0..newest.values.len())
        .map(|a| {
            std::array::from_fn(|c| {
                let mut v = newest.values[a][c];
                for (j, gamma) in coefficients.iter().enumerate() {
                    v -= gamma * (results[j + 1].values[a][c] - results[j].values[a][c]);
                }
                v
            })
        })
        .collect();
    Ok(TrajectoryCorrections { first_anchor: newest.first_anchor, values })
}

/// Whether every one of a trajectory's recorded corrections covers the same anchors.
fn same_anchors<'a>(
    trajectory: usize,
    history: impl IntoIterator<Item = &'a &'a TrajectoryCorrections>,
) -> Result<(), AndersonError> {
    let mut span = None;
    for c in history {
        if *span.get_or_insert((c.first_anchor, c.values.len())) != (c.first_anchor, c.values.len()) {
            return Err(AndersonError::Shape {
                trajectory,
                detail: "the history's corrections cover different anchors".into(),
            });
        }
    }
    Ok(())
}

/// `G(x) − x` with rotations as displacements at [`CHANGE_RANGE_M`], as the convergence test
/// reads a change.
fn weighted_step(start: &TrajectoryCorrections, result: &TrajectoryCorrections) -> Vec<f64> {
    start
        .values
        .iter()
        .zip(&result.values)
        .flat_map(|(x, g)| (0..6).map(move |c| (g[c] - x[c]) * if c >= 3 { CHANGE_RANGE_M } else { 1.0 }))
        .collect()
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn corrections(first: u32, values: &[[f64; 6]]) -> TrajectoryCorrections {
        TrajectoryCorrections { first_anchor: first, values: values.to_vec() }
    }

    /// A linear contraction over two trajectories of two anchors each: `G(x) = A x + b`.
    fn linear_map(x: &[TrajectoryCorrections]) -> Vec<TrajectoryCorrections> {
        let flat: Vec<f64> = x.iter().flat_map(|t| t.values.iter().flatten().copied()).collect();
        let n = flat.len();
        let out: Vec<f64> = (0..n)
            .map(|i| {
                // A slow shared mode (0.9 on the mean), a fast local one, and a coupling.
                let mean = flat.iter().sum::<f64>() / n as f64;
                0.9 * mean + 0.3 * (flat[i] - mean) + 0.05 * flat[(i + 7) % n] + 0.01 * (i as f64 + 1.0)
            })
            .collect();
        let mut i = 0;
        x.iter()
            .map(|t| {
                let values = t
                    .values
                    .iter()
                    .map(|_| {
                        let v = std::array::from_fn(|c| out[i + c]);
                        i += 6;
                        v
                    })
                    .collect();
                TrajectoryCorrections { first_anchor: t.first_anchor, values }
            })
            .collect()
    }

    fn largest_step(x: &[TrajectoryCorrections]) -> f64 {
        let g = linear_map(x);
        x.iter()
            .zip(&g)
            .flat_map(|(a, b)| a.values.iter().zip(&b.values).flat_map(|(p, q)| (0..6).map(|c| (q[c] - p[c]).abs())))
            .fold(0.0, f64::max)
    }

    fn run(depth: usize, iterations: usize) -> f64 {
        let mut x = vec![corrections(3, &[[0.0; 6]; 2]), corrections(10, &[[0.0; 6]; 2])];
        let mut history: Vec<(Vec<TrajectoryCorrections>, Vec<TrajectoryCorrections>)> = Vec::new();
        for _ in 0..iterations {
            let g = linear_map(&x);
            history.push((x.clone(), g.clone()));
            if history.len() > depth + 1 {
                history.remove(0);
            }
            x = if depth > 0 && history.len() >= 2 {
                let per: Vec<TrajectoryHistory> = (0..2)
                    .map(|t| TrajectoryHistory {
                        starts: history.iter().map(|(s, _)| &s[t]).collect(),
                        results: history.iter().map(|(_, r)| &r[t]).collect(),
                    })
                    .collect();
                accelerate(&per).unwrap().corrections
            } else {
                g
            };
        }
        largest_step(&x)
    }

    /// On a linear map Anderson reaches the fixed point far sooner than plain iteration.
    #[test]
    fn anderson_converges_a_linear_map_much_faster_than_plain_iteration() {
        let plain = run(0, 12);
        let accelerated = run(5, 12);
        assert!(plain > 1e-3, "plain iteration is slow on the shared mode: {plain}");
        assert!(accelerated < plain * 1e-3, "Anderson {accelerated} against plain {plain}");
    }

    /// With two entries the combination is the one-coefficient secant step, computed by hand.
    #[test]
    fn two_entries_give_the_secant_step() {
        let x0 = corrections(0, &[[0.0; 6]]);
        let g0 = corrections(0, &[[1.0, 0.0, 0.0, 0.0, 0.0, 0.0]]);
        let x1 = g0.clone();
        let g1 = corrections(0, &[[1.5, 0.0, 0.0, 0.0, 0.0, 0.0]]);
        // f0 = 1, f1 = 0.5: γ = f1·Δf / Δf² = 0.5 · (−0.5) / 0.25 = −1; x = g1 − γ (g1 − g0) = 2.
        let out = accelerate(&[TrajectoryHistory { starts: vec![&x0, &x1], results: vec![&g0, &g1] }]).unwrap();
        assert!((out.coefficients[0] + 1.0).abs() < 1e-6, "{:?}", out.coefficients);
        assert!((out.corrections[0].values[0][0] - 2.0).abs() < 1e-6, "{:?}", out.corrections);
    }

    #[test]
    fn no_change_between_entries_leaves_the_newest_result() {
        let x = corrections(0, &[[0.1; 6]]);
        let g = corrections(0, &[[0.2; 6]]);
        let out = accelerate(&[TrajectoryHistory { starts: vec![&x, &x], results: vec![&g, &g] }]).unwrap();
        assert_eq!(out.coefficients, vec![0.0]);
        assert_eq!(out.corrections[0], g);
    }

    #[test]
    fn mismatched_histories_are_errors_not_panics() {
        let a = corrections(0, &[[0.0; 6]]);
        let b = corrections(1, &[[0.0; 6]]);
        let err = accelerate(&[TrajectoryHistory { starts: vec![&a, &b], results: vec![&a, &a] }]).unwrap_err();
        assert!(err.to_string().contains("different anchors"), "{err}");
        let err = accelerate(&[
            TrajectoryHistory { starts: vec![&a, &a], results: vec![&a, &a] },
            TrajectoryHistory { starts: vec![&a], results: vec![&a] },
        ])
        .unwrap_err();
        assert!(err.to_string().starts_with("trajectory 1"), "{err}");
        // Recorded entries that name different numbers of trajectories.
        let uneven = AndersonHistory {
            entries: vec![
                AndersonEntry { starts: vec![a.clone(), a.clone()], results: vec![a.clone(), a.clone()] },
                AndersonEntry { starts: vec![a.clone()], results: vec![a.clone()] },
            ],
            step: None,
        };
        let err = uneven.accelerate().unwrap_err();
        assert!(err.to_string().contains("names 1 trajectories where the first names 2"), "{err}");
        let err = accelerate(&[TrajectoryHistory { starts: vec![], results: vec![] }]).unwrap_err();
        assert!(err.to_string().contains("empty"), "{err}");
        assert!(accelerate(&[]).unwrap().corrections.is_empty());
    }

    /// The shares add up to the campaign's problem: two trajectories give the coefficients of
    /// one trajectory holding both's anchors, and each trajectory's combination is its part of
    /// that one's.
    #[test]
    fn per_trajectory_shares_add_up_to_the_campaign_problem() {
        let step = |t: usize, e: usize, a: usize, c: usize| ((t * 7 + e * 3 + a * 5 + c) as f64 * 0.37).sin() * 1e-3;
        let make = |t: usize, e: usize, first: u32| {
            corrections(first, &(0..3).map(|a| std::array::from_fn(|c| step(t, e, a, c))).collect::<Vec<_>>())
        };
        // Three entries per trajectory; results are the next entry's starts, as in a run.
        let starts: Vec<Vec<TrajectoryCorrections>> = (0..2).map(|t| (0..3).map(|e| make(t, e, 4)).collect()).collect();
        let results: Vec<Vec<TrajectoryCorrections>> =
            (0..2).map(|t| (1..4).map(|e| make(t, e, 4)).collect()).collect();
        let per: Vec<TrajectoryHistory> = (0..2)
            .map(|t| TrajectoryHistory { starts: starts[t].iter().collect(), results: results[t].iter().collect() })
            .collect();
        let both = accelerate(&per).unwrap();
        let joined = |set: &Vec<Vec<TrajectoryCorrections>>, e: usize| TrajectoryCorrections {
            first_anchor: 4,
            values: set[0][e].values.iter().chain(&set[1][e].values).copied().collect(),
        };
        let (js, jr): (Vec<_>, Vec<_>) = (0..3).map(|e| (joined(&starts, e), joined(&results, e))).unzip();
        let one =
            accelerate(&[TrajectoryHistory { starts: js.iter().collect(), results: jr.iter().collect() }]).unwrap();
        assert_eq!(both.coefficients.len(), 2);
        for (a, b) in both.coefficients.iter().zip(&one.coefficients) {
            assert!((a - b).abs() < 1e-9 * (1.0 + b.abs()), "{:?} against {:?}", both.coefficients, one.coefficients);
        }
        let split: Vec<[f64; 6]> = both.corrections.iter().flat_map(|c| c.values.iter().copied()).collect();
        for (a, b) in split.iter().flatten().zip(one.corrections[0].values.iter().flatten()) {
            assert!((a - b).abs() < 1e-12, "{a} against {b}");
        }
        // The shares' sum is what `accelerate` solved.
        let mut total = AndersonMoments::zeros(2);
        for (t, h) in per.iter().enumerate() {
            total.add(t, &trajectory_moments(t, h).unwrap()).unwrap();
        }
        assert_eq!(coefficients(&total), both.coefficients);
    }

    #[test]
    fn shares_and_combinations_of_the_wrong_shape_are_errors() {
        let a = corrections(0, &[[0.0; 6]]);
        let mut two = AndersonMoments::zeros(2);
        let err = two.add(1, &AndersonMoments::zeros(3)).unwrap_err();
        assert!(
            err.to_string().contains("trajectory 1: its share is over 3 differences where the others' are over 2"),
            "{err}"
        );
        let err = combine(4, &[&a, &a], &[0.5, 0.5]).unwrap_err();
        assert!(err.to_string().starts_with("trajectory 4: 2 results for 2 coefficients"), "{err}");
        let nan = corrections(0, &[[f64::NAN; 6]]);
        let err =
            trajectory_moments(1, &TrajectoryHistory { starts: vec![&a, &a], results: vec![&a, &nan] }).unwrap_err();
        assert!(err.to_string().contains("not finite"), "{err}");
    }

    #[test]
    fn history_keeps_depth_plus_one_settling_entries_and_clears_elsewhere() {
        let params = Parameters { anderson_depth: 2, ..Default::default() };
        let settle = params.schedule[17];
        let momentum_step = params.schedule[10];
        let mut h = AndersonHistory::<u32>::default();
        assert!(!h.record(&params, &settle, false, vec![1], || vec![2]), "one entry is not enough");
        assert!(h.record(&params, &settle, false, vec![2], || vec![3]));
        assert!(h.record(&params, &settle, false, vec![3], || vec![4]));
        assert!(h.record(&params, &settle, false, vec![4], || vec![5]));
        assert_eq!(h.entries.len(), 3);
        assert_eq!(h.trajectory(0), (vec![&2, &3, &4], vec![&3, &4, &5]));
        // A step momentum carries into clears it.
        assert!(!h.record(&params, &momentum_step, true, vec![5], || vec![6]));
        assert!(h.entries.is_empty());
        // So does a change of unknowns.
        assert!(!h.record(&params, &settle, false, vec![6], || vec![7]));
        let translation_only = IterationStep { rotation: false, ..settle };
        assert!(!h.record(&params, &translation_only, false, vec![7], || vec![8]));
        assert_eq!(h.entries.len(), 1);
        // Depth 0 turns it off.
        let off = Parameters { anderson_depth: 0, ..Default::default() };
        let mut h = AndersonHistory::<u32>::default();
        assert!(!h.record(&off, &settle, false, vec![1], || vec![2]));
        assert!(!h.record(&off, &settle, false, vec![2], || vec![3]));
        assert!(h.entries.is_empty());
    }
}
