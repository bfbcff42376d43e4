use super::*;
use nalgebra::{DMatrix, DVector};

fn random_system(n: usize, seed: &mut u64) -> BlockTridiagonal {
    let mut rand = || {
        *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
    };
    let mut sys = BlockTridiagonal::zeros(n);
    for i in 0..n {
        for _ in 0..10 {
            let g = Vec6::from_fn(|_, _| rand());
            let l = rand() + 0.5;
            sys.diag[i] += g * g.transpose() * (1.0 - l) * (1.0 - l);
            if i + 1 < n {
                sys.upper[i] += g * g.transpose() * l * (1.0 - l);
                sys.diag[i + 1] += g * g.transpose() * l * l;
            }
        }
        sys.diag[i] += Mat6::identity();
        sys.rhs[i] = Vec6::from_fn(|_, _| rand());
    }
    sys
}

/// The anchor-pair solve of a system with a two-anchor band equals a dense solve.
#[test]
fn pair_solve_with_curvature_matches_dense() {
    let mut seed = 3;
    for n in [1usize, 2, 3, 4, 7, 30] {
        let mut sys = random_system(n, &mut seed);
        let current: Vec<[f64; 6]> = (0..n).map(|i| std::array::from_fn(|a| (i * 6 + a) as f64 * 1e-3)).collect();
        let skip = add_curvature(&mut sys, &current, &Vec6::repeat(50.0));
        let mut dense = DMatrix::<f64>::zeros(6 * n, 6 * n);
        let mut b = DVector::<f64>::zeros(6 * n);
        for i in 0..n {
            dense.view_mut((6 * i, 6 * i), (6, 6)).copy_from(&sys.diag[i]);
            b.rows_mut(6 * i, 6).copy_from(&sys.rhs[i]);
            if i + 1 < n {
                dense.view_mut((6 * i, 6 * i + 6), (6, 6)).copy_from(&sys.upper[i]);
                dense.view_mut((6 * i + 6, 6 * i), (6, 6)).copy_from(&sys.upper[i].transpose());
            }
            if i + 2 < n {
                dense.view_mut((6 * i, 6 * i + 12), (6, 6)).copy_from(&skip[i]);
                dense.view_mut((6 * i + 12, 6 * i), (6, 6)).copy_from(&skip[i].transpose());
            }
        }
        let chol = dense.cholesky().expect("SPD");
        let exact = chol.solve(&b);
        let inverse = chol.inverse();
        let solution = solve_pairs(&sys, &skip, true, &[], true).unwrap();
        // The band of the inverse holds every covariance between anchors up to two apart.
        let band = solution.band.unwrap();
        for i in 0..n {
            for j in i..(i + 3).min(n) {
                for a in 0..6 {
                    let dense = inverse[(6 * i + a, 6 * j + a)];
                    assert!((band.covariance(i, j, a) - dense).abs() < 1e-9, "n {n}, anchors {i} {j}");
                }
            }
        }
        let (x, cov) = (solution.delta, solution.sigma.unwrap());
        for i in 0..n {
            for a in 0..6 {
                assert!((x[i][a] - exact[6 * i + a]).abs() < 1e-9, "n {n}, anchor {i}");
                assert!((cov[i][(a, a)] - inverse[(6 * i + a, 6 * i + a)]).abs() < 1e-9);
            }
        }
    }
}

/// The attitude prior holds the heading (rotation about the vertical) with its own σ when
/// `sigma_prior_heading_deg` is set, the tilt with `sigma_prior_rotation_deg`: one anchor
/// without data has exactly the prior's covariance.
#[test]
fn the_heading_prior_has_its_own_sigma() {
    let current = TrajectoryCorrections { first_anchor: 7, values: vec![[0.0; 6]] };
    let sigma = |params: &Parameters| {
        let solution =
            solve_trajectory(std::iter::empty(), &current, None, None, params, None, true, true, None, None).unwrap();
        solution.covariance.unwrap()[0].sigma()
    };
    let tilt = 0.02f64.to_radians();
    for (heading, expected) in [(0.0, tilt), (0.05, 0.05f64.to_radians())] {
        let params =
            Parameters { sigma_prior_rotation_deg: 0.02, sigma_prior_heading_deg: heading, ..Default::default() };
        let s = sigma(&params);
        for (a, want) in [(0, 1.0), (1, 1.0), (2, 1.0), (3, tilt), (4, tilt), (5, expected)] {
            assert!((s[a] / want - 1.0).abs() < 1e-9, "heading {heading}: σ {a} is {}, expected {want}", s[a]);
        }
    }
}

/// Momentum adds β × the previous step to the Gauss–Newton step, except to rotations a
/// translation-only step holds fixed; without `previous` the step is plain.
#[test]
fn momentum_adds_beta_times_the_previous_step() {
    let n = 5;
    let params = Parameters { momentum: 0.5, weak_information_ratio: 0.0, ..Default::default() };
    let current = TrajectoryCorrections { first_anchor: 3, values: vec![[0.02, -0.01, 0.005, 1e-4, -2e-4, 3e-4]; n] };
    let previous = TrajectoryCorrections { first_anchor: 3, values: vec![[0.01, 0.0, 0.0, 0.0, 0.0, 1e-4]; n] };
    let plain =
        solve_trajectory(std::iter::empty(), &current, None, None, &params, None, true, false, None, None).unwrap();
    let carried =
        solve_trajectory(std::iter::empty(), &current, Some(&previous), None, &params, None, true, false, None, None)
            .unwrap();
    for k in 0..n {
        for a in 0..6 {
            let expected = plain.corrections.values[k][a] + 0.5 * (current.values[k][a] - previous.values[k][a]);
            assert!((carried.corrections.values[k][a] - expected).abs() < 1e-15, "anchor {k}, unknown {a}");
        }
    }
    let frozen =
        solve_trajectory(std::iter::empty(), &current, Some(&previous), None, &params, None, false, false, None, None)
            .unwrap();
    for k in 0..n {
        assert_eq!(frozen.corrections.values[k][5], current.values[k][5], "rotation must stay fixed");
        assert!((frozen.corrections.values[k][0] - plain.corrections.values[k][0] - 0.005).abs() < 1e-9);
    }
}

/// `extend_corrections` gives the unobserved anchors what `solve_trajectory` gives them
/// with the estimated anchors pinned by observations and the prior made negligible,
/// curvature on and off; the trend carries on with curvature and the end is held without it.
#[test]
fn extended_corrections_match_the_solve_with_the_estimated_anchors_pinned() {
    let slope = [0.002, -0.001, 0.0005, 2e-6, -1e-6, 3e-6];
    let estimated: Vec<[f64; 6]> = (0..8)
        .map(|i| {
            std::array::from_fn(|a| {
                0.1 * (a as f64 - 2.0) + slope[a] * i as f64 + 1e-4 * (i * i) as f64 * (a % 2) as f64
            })
        })
        .collect();
    let corrections = TrajectoryCorrections { first_anchor: 30, values: estimated.clone() };
    let with = Parameters {
        weak_information_ratio: 0.0,
        sigma_prior_position_m: 1e6,
        sigma_prior_rotation_deg: 1e6,
        // The heading's too (0: the tilt's).
        sigma_prior_heading_deg: 0.0,
        ..Default::default()
    };
    let without = Parameters { sigma_curvature_position_m: 0.0, sigma_curvature_rotation_deg: 0.0, ..with.clone() };
    for params in [&with, &without] {
        let range = (17, 51);
        let extended = extend_corrections(&corrections, range, params);
        assert_eq!((extended.first_anchor, extended.last_anchor()), range);
        assert_eq!(&extended.values[13..21], &estimated[..], "estimated anchors unchanged");
        // The same problem through the trajectory solve: the estimated anchors pinned by
        // observations a million times stiffer than the curvature term.
        let blocks: Vec<AnchorBlock> = (0..8)
            .map(|i| {
                let mut b = AnchorBlock::new(30 + i as u32);
                for a in 0..6 {
                    let w = if a < 3 { 1e16 } else { 1e20 };
                    b.diag[sym_index(a, a)] = w;
                    b.rhs[a] = w * estimated[i][a];
                }
                b.observations = 1;
                b
            })
            .collect();
        let current = TrajectoryCorrections::zeros(range.0, range.1);
        let solved =
            solve_trajectory(&blocks, &current, None, None, params, None, true, false, None, None).unwrap().corrections;
        for (k, (e, s)) in extended.values.iter().zip(&solved.values).enumerate() {
            for a in 0..6 {
                let scale = if a < 3 { 1e-6 } else { 1e-9 };
                assert!(
                    (e[a] - s[a]).abs() < scale,
                    "anchor {}, unknown {a}: {} against {}",
                    range.0 + k as u32,
                    e[a],
                    s[a]
                );
            }
        }
        let run_out = extended.values[34][0] - extended.values[20][0];
        if params.sigma_curvature_position_m > 0.0 {
            // The end's slope (0.002 per anchor in unknown 0) carries on, fading slowly.
            assert!(run_out > 0.8 * 14.0 * 0.002 && run_out < 14.0 * 0.002, "run-out {run_out}");
        } else {
            assert!(run_out.abs() < 1e-9, "run-out {run_out}");
        }
    }
    // Nothing to extend, or a single anchor: held ends.
    assert_eq!(extend_corrections(&corrections, (30, 37), &with), corrections);
    // A single anchor has no slope to carry: it is held, the attitude too (the default
    // attitude prior, tight against the smoothness, does not pull it back).
    let single = TrajectoryCorrections { first_anchor: 5, values: vec![[0.01, 0.01, 0.01, 1e-5, 1e-5, 1e-5]] };
    let extended = extend_corrections(&single, (0, 9), &Parameters::default());
    assert_eq!(extended.values.len(), 10);
    for v in &extended.values {
        assert!(v.iter().zip(&single.values[0]).all(|(x, y)| (x - y).abs() < 1e-9 * y.abs()), "{extended:?}");
    }
}

/// Each anchor's own prior: the campaign's weights given per anchor change nothing, and
/// anchors held tighter move less far towards what their data say.
#[test]
fn per_anchor_prior_weights_replace_the_campaigns() {
    let params = Parameters { weak_information_ratio: 0.0, ..Default::default() };
    let current = TrajectoryCorrections { first_anchor: 7, values: vec![[0.0; 6]; 41] };
    // Data at every anchor asking for 0.5 m in x, as firmly as the campaign's prior.
    let w = campaign_prior_weights(&params)[0];
    let blocks: Vec<AnchorBlock> = (7..48)
        .map(|anchor| {
            let mut b = AnchorBlock::new(anchor);
            b.diag[sym_index(0, 0)] = w;
            b.rhs[0] = w * 0.5;
            b.observations = 1;
            b
        })
        .collect();
    let solve = |prior: Option<&[[f64; 6]]>| {
        solve_trajectory(blocks.iter(), &current, None, None, &params, prior, true, true, None, None).unwrap()
    };
    let plain = solve(None);
    let campaign = vec![campaign_prior_weights(&params); 41];
    assert_eq!(solve(Some(&campaign)), plain);
    assert!((plain.corrections.values[0][0] - 0.25).abs() < 1e-9, "{:?}", plain.corrections.values[0]);
    let mut tighter = campaign.clone();
    for w in &mut tighter[20..] {
        w[0] *= 100.0;
    }
    let held = solve(Some(&tighter));
    for k in 0..41 {
        let (p, h) = (plain.corrections.values[k][0], held.corrections.values[k][0]);
        assert!(h <= p + 1e-12, "anchor {k}: {h} vs {p}");
    }
    // Where the weights are a hundred times larger the data barely move the anchors (the
    // smoothness to the looser ones adds a little).
    for k in 25..41 {
        assert!(held.corrections.values[k][0] < 0.02, "anchor {k}: {:?}", held.corrections.values[k]);
    }
    // The posterior σ follows the prior.
    let sigma = |s: &TrajectorySolution, k: usize| s.covariance.as_ref().unwrap()[k].sigma()[0];
    assert!(sigma(&held, 40) < 0.5 * sigma(&plain, 40), "{} vs {}", sigma(&held, 40), sigma(&plain, 40));
}

/// Without observations, the curvature term removes a kink from a correction profile.
#[test]
fn curvature_removes_a_kink() {
    let n = 9;
    let params = Parameters { weak_information_ratio: 0.0, ..Default::default() };
    let straight: Vec<[f64; 6]> = (0..n).map(|i| [0.01 * i as f64, 0.0, 0.0, 0.0, 0.0, 0.0]).collect();
    // No observations: only prior, smoothness and curvature act.
    let mut kinked = straight;
    kinked[4][0] += 0.05;
    let current_kinked = TrajectoryCorrections { first_anchor: 0, values: kinked };
    let sol_kinked =
        solve_trajectory(std::iter::empty(), &current_kinked, None, None, &params, None, true, false, None, None)
            .unwrap();
    let second = |v: &[[f64; 6]], i: usize| v[i - 1][0] - 2.0 * v[i][0] + v[i + 1][0];
    assert!(second(&current_kinked.values, 4).abs() > 0.09);
    assert!(second(&sol_kinked.corrections.values, 4).abs() < 0.001, "kink not removed");
}

/// The joint solve of two trajectories with shared calibration unknowns — each trajectory's
/// share, the calibration's Schur step and the shares moved by it — equals a dense solve of
/// the whole bordered system, prior, smoothness and curvature included.
#[test]
fn joint_calibration_solve_matches_the_dense_bordered_system() {
    use crate::calibration::{solve_calibration, CalibrationNormals};
    use precimap_core::{CalibrationOptions, CalibrationUnknown};
    let mut seed = 11u64;
    let mut rand = move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
    };
    let options = CalibrationOptions {
        estimate: vec![CalibrationUnknown::Boresight],
        tolerance_boresight_deg: 1e9,
        ..Default::default()
    };
    let layout = options.layout(1);
    let k = layout.len();
    let params = Parameters { weak_information_ratio: 0.0, ..Default::default() };
    let n = 5;
    let mut trajectories = Vec::new();
    for t in 0..2 {
        let mut blocks: Vec<AnchorBlock> = (0..n as u32).map(AnchorBlock::new).collect();
        let mut normals = CalibrationNormals::zeros(k);
        for b in &mut blocks {
            b.cross = vec![0.0; 6 * k];
        }
        for i in 0..n - 1 {
            for _ in 0..12 {
                let g: [f64; 6] = std::array::from_fn(|a| rand() * if a < 3 { 1.0 } else { 10.0 });
                let gc: Vec<f64> = (0..k).map(|_| rand() * 10.0).collect();
                let (l, e, w) = (rand() + 0.5, rand() * 0.01, 1e3 * (1.0 + t as f64));
                for a in 0..6 {
                    for c in a..6 {
                        let q = w * g[a] * g[c];
                        blocks[i].diag[sym_index(a, c)] += (1.0 - l) * (1.0 - l) * q;
                        blocks[i].next[sym_index(a, c)] += l * (1.0 - l) * q;
                        blocks[i + 1].diag[sym_index(a, c)] += l * l * q;
                    }
                    blocks[i].rhs[a] -= w * (1.0 - l) * g[a] * e;
                    blocks[i + 1].rhs[a] -= w * l * g[a] * e;
                    for j in 0..k {
                        blocks[i].cross[a * k + j] += w * (1.0 - l) * g[a] * gc[j];
                        blocks[i + 1].cross[a * k + j] += w * l * g[a] * gc[j];
                    }
                }
                normals.add_observation(0, &gc, w * e, w);
            }
        }
        trajectories.push((blocks, normals));
    }
    let current = TrajectoryCorrections { first_anchor: 0, values: vec![[0.0; 6]; n] };
    let solve = |blocks: &[AnchorBlock], normals: Option<&CalibrationNormals>| {
        solve_trajectory(blocks, &current, None, None, &params, None, true, false, normals, None).unwrap()
    };
    let mut solutions: Vec<_> = trajectories.iter().map(|(b, c)| solve(b, Some(c))).collect();
    let step =
        solve_calibration(solutions.iter().map(|s| s.calibration.as_ref().unwrap()), &vec![0.0; k], &layout, &options)
            .unwrap();
    assert!(step.determined.iter().all(|&d| d));
    for s in &mut solutions {
        apply_calibration_step(s, &step.delta, &current);
    }
    // The dense reference: each trajectory's matrix from its solves of unit right-hand sides.
    let m = 6 * n;
    let total = 2 * m + k;
    let mut dense = DMatrix::<f64>::zeros(total, total);
    let mut rhs = DVector::<f64>::zeros(total);
    for (t, (blocks, normals)) in trajectories.iter().enumerate() {
        let mut inverse = DMatrix::<f64>::zeros(m, m);
        for col in 0..m {
            let mut probe: Vec<AnchorBlock> =
                blocks.iter().map(|b| AnchorBlock { rhs: [0.0; 6], cross: Vec::new(), ..b.clone() }).collect();
            probe[col / 6].rhs[col % 6] = 1.0;
            let x = solve(&probe, None).corrections.values;
            for row in 0..m {
                inverse[(row, col)] = x[row / 6][row % 6];
            }
        }
        let h = inverse.try_inverse().unwrap();
        dense.view_mut((t * m, t * m), (m, m)).copy_from(&h);
        for (a, b) in blocks.iter().enumerate() {
            for r in 0..6 {
                rhs[t * m + a * 6 + r] = b.rhs[r];
                for j in 0..k {
                    dense[(t * m + a * 6 + r, 2 * m + j)] = b.cross[r * k + j];
                    dense[(2 * m + j, t * m + a * 6 + r)] = b.cross[r * k + j];
                }
            }
        }
        for i in 0..k {
            rhs[2 * m + i] += normals.b[i];
            for j in 0..k {
                dense[(2 * m + i, 2 * m + j)] += normals.h[i * k + j];
            }
        }
    }
    let prior = 1.0 / options.prior_boresight_deg.to_radians().powi(2);
    for i in 0..k {
        dense[(2 * m + i, 2 * m + i)] += prior;
    }
    let exact = dense.lu().solve(&rhs).unwrap();
    for i in 0..k {
        let want = exact[2 * m + i];
        assert!(
            (step.delta[i] - want).abs() < 1e-9 * want.abs().max(1e-6),
            "unknown {i}: {} against {want}",
            step.delta[i]
        );
    }
    for (t, s) in solutions.iter().enumerate() {
        for a in 0..n {
            for r in 0..6 {
                let want = exact[t * m + a * 6 + r];
                let got = s.corrections.values[a][r];
                assert!(
                    (got - want).abs() < 1e-9 * want.abs().max(1e-6),
                    "trajectory {t} anchor {a}: {got} against {want}"
                );
            }
        }
    }
}

/// A standard normal deviate per call (Box–Muller over a linear congruential generator).
fn normal_deviates(mut seed: u64) -> impl FnMut() -> f64 {
    let mut uniform = move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((seed >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    move || (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos()
}

/// The estimated process model recovers the σ of a simulated random walk of the slope (white
/// second differences) from noisy observations of every anchor, on every axis, starting from
/// the campaign's stiffer σ, within the few per cent a 1000-anchor sample allows.
#[test]
fn estimated_curvature_recovers_a_random_walk_of_the_slope() {
    // Prior and smoothness loose, so that the curvature term is the process model.
    let params = Parameters {
        weak_information_ratio: 0.0,
        sigma_prior_position_m: 1e4,
        sigma_prior_rotation_deg: 1e3,
        sigma_prior_heading_deg: 0.0,
        sigma_smooth_position_m: 1.0,
        sigma_smooth_rotation_deg: 10.0,
        ..Default::default()
    };
    let truth_sigma = [5e-4, 5e-4, 5e-4, 2e-5, 2e-5, 2e-5];
    let noise = [2e-3, 2e-3, 2e-3, 1e-4, 1e-4, 1e-4];
    let n = 1000;
    let mut normal = normal_deviates(5);
    let mut truth = vec![[0.0f64; 6]; n];
    let mut slope = [0.0f64; 6];
    for i in 1..n {
        for a in 0..6 {
            slope[a] += truth_sigma[a] * normal();
            truth[i][a] = truth[i - 1][a] + slope[a];
        }
    }
    let observed: Vec<[f64; 6]> = truth.iter().map(|t| std::array::from_fn(|a| t[a] + noise[a] * normal())).collect();
    let mut model = CurvatureModel::from_params(&params).unwrap();
    let mut current = TrajectoryCorrections { first_anchor: 0, values: vec![[0.0; 6]; n] };
    for _ in 0..40 {
        let blocks: Vec<AnchorBlock> = (0..n)
            .map(|i| {
                let mut b = AnchorBlock::new(i as u32);
                for a in 0..6 {
                    let w = 1.0 / (noise[a] * noise[a]);
                    b.diag[sym_index(a, a)] = w;
                    b.rhs[a] = w * (observed[i][a] - current.values[i][a]);
                }
                b.observations = 1;
                b
            })
            .collect();
        let solution =
            solve_trajectory(&blocks, &current, None, None, &params, None, true, false, None, Some(&model)).unwrap();
        let moments = solution.curvature_moments.expect("moments with a process model");
        assert_eq!(moments.terms, n as u64 - 2);
        model.update(&moments, &params);
        current = solution.corrections;
    }
    for a in 0..6 {
        let ratio = model.sigma[a] / truth_sigma[a];
        assert!((0.85..1.15).contains(&ratio), "axis {a}: σ {} against {}", model.sigma[a], truth_sigma[a]);
    }
    // The campaign's σ alone (no process model) reports no moments.
    let short = TrajectoryCorrections { first_anchor: 0, values: vec![[0.0; 6]; 5] };
    let defaults = Parameters::default();
    let plain =
        solve_trajectory(std::iter::empty(), &short, None, None, &defaults, None, true, false, None, None).unwrap();
    assert!(plain.curvature_moments.is_none());
}
