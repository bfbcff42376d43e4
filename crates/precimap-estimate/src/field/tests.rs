use super::solve::solve_field_within;
use super::*;
use crate::tile::cross;
use precimap_core::Parameters;
use std::collections::BTreeMap;

#[test]
fn bilinear_weights_reproduce_linear_functions() {
    let s = 30.0;
    for &(x, y) in &[(500_012.3, 5_400_027.9), (-14.0, 3.0), (60.0, 90.0)] {
        let w = bilinear(x, y, s);
        let total: f64 = w.iter().map(|(_, p)| p).sum();
        assert!((total - 1.0).abs() < 1e-12);
        let fx: f64 = w.iter().map(|((ix, _), p)| p * (*ix as f64) * s).sum();
        let fy: f64 = w.iter().map(|((_, iy), p)| p * (*iy as f64) * s).sum();
        assert!((fx - x).abs() < 1e-6 && (fy - y).abs() < 1e-6, "{fx} {fy}");
    }
}

#[test]
fn accumulator_equals_the_dense_outer_product_and_ignores_a_constant_field() {
    let mut acc = FieldAccumulator::new(10.0);
    let w = [0.6, 0.0, 0.8];
    // Same position for the point and the other passes: the row is zero.
    acc.add(FieldRow {
        vehicle: [3.0, 4.0],
        others: [3.0, 4.0],
        k: 2.0 / 3.0,
        w,
        e: 0.01,
        weight: 5.0,
        lever: [0.0; 3],
        anchored: false,
    });
    let eq = FieldAccumulator::finish(std::mem::replace(&mut acc, FieldAccumulator::new(10.0)));
    assert!(eq.pairs.is_empty() && eq.rhs.iter().all(|r| r == &[0.0; 3]));
    // One row across two cells against a dense computation.
    let (v, o, n, e, weight) = ([3.0, 4.0], [14.0, 4.0], 3.0, 0.02, 2.0);
    acc.add(FieldRow { vehicle: v, others: o, k: n / (n + 1.0), w, e, weight, lever: [0.0; 3], anchored: false });
    let eq = acc.finish();
    let k = n / (n + 1.0);
    let mut row: BTreeMap<FieldNode, f64> = BTreeMap::new();
    for (node, phi) in bilinear(v[0], v[1], 10.0) {
        *row.entry(node).or_default() += k * phi;
    }
    for (node, phi) in bilinear(o[0], o[1], 10.0) {
        *row.entry(node).or_default() -= k * phi;
    }
    for &(a, b, m) in &eq.pairs {
        let (ra, rb) = (row[&eq.nodes[a as usize]], row[&eq.nodes[b as usize]]);
        for r in 0..3 {
            for c in 0..3 {
                assert!((m[3 * r + c] - weight * ra * rb * w[r] * w[c]).abs() < 1e-12);
            }
        }
    }
    for (node, r) in eq.nodes.iter().zip(&eq.rhs) {
        for c in 0..3 {
            assert!((r[c] + weight * row[node] * e * w[c]).abs() < 1e-12);
        }
    }
    // A constant field does not change the row's value: the coefficients sum to zero.
    assert!(row.values().sum::<f64>().abs() < 1e-12);
}

/// The runs give the equations that summing every row's blocks into `H` directly gives
/// (to rounding): runs that leave a cell and come back, rows whose two positions share
/// nodes or a whole cell, normals that change every few rows, and rows on a node line (a
/// zero weight creates no node); with the heading, and with heading and tilt, their row
/// entries too.
#[test]
fn summed_runs_give_the_row_by_row_equations() {
    for axes in [0, 1, 3] {
        summed_runs_match_direct_rows(axes);
    }
}

/// A pair's block over `[t_x, t_y, t_z, ψ, τ_x, τ_y]` from `FieldEquations`' parts (zeros
/// where they are empty).
fn full_block(m: &[f64; 9], x: Option<&[f64; 7]>, y: Option<&[f64; 20]>) -> [[f64; 6]; 6] {
    let mut b = [[0.0; 6]; 6];
    for r in 0..3 {
        for c in 0..3 {
            b[r][c] = m[3 * r + c];
        }
    }
    if let Some(x) = x {
        for c in 0..3 {
            b[c][3] = x[c];
            b[3][c] = x[3 + c];
        }
        b[3][3] = x[6];
    }
    if let Some(y) = y {
        for j in 0..2 {
            for c in 0..3 {
                b[c][4 + j] = y[c * 2 + j];
                b[4 + j][c] = y[6 + j * 3 + c];
            }
            b[3][4 + j] = y[12 + j];
            b[4 + j][3] = y[14 + j];
            for l in 0..2 {
                b[4 + j][4 + l] = y[16 + 2 * j + l];
            }
        }
    }
    b
}

fn summed_runs_match_direct_rows(axes: usize) {
    /// Row by row: merge the row's nodes, then every pair's 6×6 block over
    /// `[t_x, t_y, t_z, ψ, τ_x, τ_y]`.
    struct Direct {
        spacing: f64,
        h: BTreeMap<(FieldNode, FieldNode), [[f64; 6]; 6]>,
        rhs: BTreeMap<FieldNode, [f64; 6]>,
    }
    impl Direct {
        fn add(&mut self, row: FieldRow) {
            let FieldRow { vehicle: v, others: o, k, w, e, weight, lever, anchored } = row;
            // A row against a fixed target has no other passes' part.
            let k_o = if anchored { 0.0 } else { k };
            // The other passes turn about their own mean scan head.
            let d = [v[0] - o[0], v[1] - o[1], 0.0];
            let turn = cross(d, w);
            let lever_o = [lever[0] + turn[0], lever[1] + turn[1], lever[2] + turn[2]];
            let mut row: BTreeMap<FieldNode, [f64; 6]> = BTreeMap::new();
            for (sign, at, arm) in [(k, v, lever), (-k_o, o, lever_o)] {
                for (node, phi) in bilinear(at[0], at[1], self.spacing) {
                    if phi != 0.0 && sign != 0.0 {
                        let entry = row.entry(node).or_default();
                        for c in 0..3 {
                            entry[c] += sign * phi * w[c];
                        }
                        entry[3] += sign * phi * arm[2];
                        entry[4] += sign * phi * arm[0];
                        entry[5] += sign * phi * arm[1];
                    }
                }
            }
            for (&a, &fa) in &row {
                let rhs = self.rhs.entry(a).or_default();
                for c in 0..6 {
                    rhs[c] -= weight * e * fa[c];
                }
                for (&b, &fb) in row.range(a..) {
                    let m = self.h.entry((a, b)).or_default();
                    for r in 0..6 {
                        for c in 0..6 {
                            m[r][c] += weight * fa[r] * fb[c];
                        }
                    }
                }
            }
        }
    }
    let mut seed = 3u64;
    let mut rand = move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let spacing = 10.0;
    let mut acc = match axes {
        0 => FieldAccumulator::new(spacing),
        1 => FieldAccumulator::with_heading(spacing),
        _ => FieldAccumulator::with_tilt(spacing),
    };
    let mut direct = Direct { spacing, h: BTreeMap::new(), rhs: BTreeMap::new() };
    let mut w = [0.0, 0.0, 1.0];
    let mut last_lever = [0.0; 3];
    for i in 0..2000 {
        // Back and forth over three cells; every 7th point on a node line.
        let x = 500_000.0 + 30.0 * (i as f64 * 0.01).sin().abs() + rand();
        let y = if i % 7 == 0 { 5_400_010.0 } else { 5_400_005.0 + 8.0 * rand() };
        // The other passes in the same cell, a neighbouring one (two shared nodes) or farther.
        let o = match i / 50 % 3 {
            0 => [x + 0.1 * rand(), y],
            1 => [x + 12.0 * (rand() - 0.5), y + 3.0 * rand()],
            _ => [x + 25.0, y - 14.0 * rand()],
        };
        // Another normal every few rows, some of them one seen before; façades among them.
        if rand() < 0.3 {
            let (a, b, c) = if rand() < 0.8 {
                [(0.0, 0.0, 1.0), (0.1, -0.05, 1.0), (-0.12, 0.02, 1.0), (1.0, 0.2, 0.05)][(4.0 * rand()) as usize]
            } else {
                (0.3 * (rand() - 0.5), 0.3 * (rand() - 0.5), 1.0)
            };
            let norm = (a * a + b * b + c * c).sqrt();
            w = [a / norm, b / norm, c / norm];
        }
        // The point's own Jacobian for a rotation, `(p − v) × w`, from a lever arm of metres.
        let arm = [20.0 * (rand() - 0.5), 20.0 * (rand() - 0.5), 3.0 * (rand() - 0.5)];
        let lever = cross(arm, w);
        last_lever = lever;
        let (k, e) = (0.5 + 0.4 * rand(), 0.01 * (rand() - 0.5));
        // Every 11th row against a control target.
        let row = FieldRow { vehicle: [x, y], others: o, k, w, e, weight: 5.0, lever, anchored: i % 11 == 0 };
        acc.add(row);
        direct.add(row);
    }
    // The same position for both: no node pair gets a non-zero translation block.
    let same = [500_003.0, 5_400_004.0];
    let row =
        FieldRow { vehicle: same, others: same, k: 0.5, w, e: 0.01, weight: 5.0, lever: last_lever, anchored: false };
    acc.add(row);
    direct.add(row);
    let eq = acc.finish();
    assert_eq!(eq.observations, 2001);
    assert!(eq.nodes.len() >= 12, "{} nodes", eq.nodes.len());
    assert_eq!(eq.nodes, direct.rhs.keys().copied().collect::<Vec<_>>());
    assert_eq!(eq.heading_pairs.len(), if axes > 0 { eq.pairs.len() } else { 0 });
    assert_eq!(eq.heading_rhs.len(), if axes > 0 { eq.nodes.len() } else { 0 });
    assert_eq!(eq.tilt_pairs.len(), if axes == 3 { eq.pairs.len() } else { 0 });
    assert_eq!(eq.tilt_rhs.len(), if axes == 3 { eq.nodes.len() } else { 0 });
    // The unknowns the accumulator sums: translation, heading, tilt.
    let unknowns = 3 + axes;
    let scale = direct.h.values().flatten().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    let mut nonzero = 0;
    for (&(a, b), want) in &direct.h {
        let (ia, ib) = (eq.nodes.binary_search(&a).unwrap() as u32, eq.nodes.binary_search(&b).unwrap() as u32);
        let got = match eq.pairs.iter().position(|p| (p.0, p.1) == (ia, ib)) {
            Some(at) => {
                nonzero += 1;
                full_block(&eq.pairs[at].2, eq.heading_pairs.get(at), eq.tilt_pairs.get(at))
            }
            None => [[0.0; 6]; 6],
        };
        for r in 0..unknowns {
            for c in 0..unknowns {
                assert!(
                    (got[r][c] - want[r][c]).abs() <= 1e-12 * scale,
                    "{a:?} {b:?} ({r}, {c}), {axes} axes: {} against {}",
                    got[r][c],
                    want[r][c]
                );
            }
        }
    }
    assert_eq!(nonzero, eq.pairs.len());
    for (n, (got, want)) in eq.rhs.iter().zip(direct.rhs.values()).enumerate() {
        for c in 0..3 {
            assert!((got[c] - want[c]).abs() <= 1e-12, "{got:?} against {want:?}");
        }
        if axes > 0 {
            assert!((eq.heading_rhs[n] - want[3]).abs() <= 1e-10, "{} against {}", eq.heading_rhs[n], want[3]);
        }
        if axes == 3 {
            for j in 0..2 {
                assert!((eq.tilt_rhs[n][j] - want[4 + j]).abs() <= 1e-10, "{:?} against {want:?}", eq.tilt_rhs[n]);
            }
        }
    }
}

#[test]
fn field_share_of_a_step_is_removed_and_the_rest_kept() {
    // Two passes along the same street; their last step is a smooth shared drift (a field)
    // plus a per-anchor zigzag no field on 20 m nodes can represent.
    let spacing = 20.0;
    let positions: Vec<[f64; 3]> = (0..240).map(|k| [1000.0 + 0.5 * k as f64, 2003.0, 50.0]).collect();
    let drift = |p: &[f64; 3]| [0.002 * (p[0] - 1000.0) / 120.0, -0.001, 0.0005];
    let zigzag = |k: usize| if k.is_multiple_of(2) { 1e-4 } else { -1e-4 };
    let previous = TrajectoryCorrections { first_anchor: 0, values: vec![[0.01, 0.02, 0.0, 0.0, 0.0, 0.0]; 240] };
    let mut current = previous.clone();
    for (k, (v, p)) in current.values.iter_mut().zip(&positions).enumerate() {
        let d = drift(p);
        for c in 0..3 {
            v[c] += d[c];
        }
        v[0] += zigzag(k);
    }
    let trajectories = [
        FieldTrajectory { positions: &positions, corrections: &current, prior: None, curvature: None },
        FieldTrajectory { positions: &positions, corrections: &current, prior: None, curvature: None },
    ];
    let moved = remove_field_share(&trajectories, &[previous.clone(), previous.clone()], spacing, 0).unwrap();
    // Inconsistent inputs are errors, not panics.
    assert!(matches!(
        remove_field_share(&trajectories, std::slice::from_ref(&previous), spacing, 0),
        Err(FieldError::Trajectories { expected: 2, found: 1 })
    ));
    let short = TrajectoryCorrections { first_anchor: 0, values: vec![[0.0; 6]; 10] };
    assert!(matches!(
        remove_field_share(&trajectories, &[previous.clone(), short], spacing, 0),
        Err(FieldError::Positions { trajectory: 1, anchors: 10, .. })
    ));
    for before in &moved {
        for (k, (now, was)) in current.values.iter().zip(&before.values).enumerate() {
            // What momentum would carry: the zigzag only (the ridge leaves a trace of the drift).
            assert!((now[0] - was[0] - zigzag(k)).abs() < 2e-5, "anchor {k}: {}", now[0] - was[0]);
            assert!((now[1] - was[1]).abs() < 2e-5 && (now[2] - was[2]).abs() < 2e-5);
            // Rotations are untouched.
            assert_eq!(now[3..], was[3..]);
        }
    }
}

#[test]
fn without_data_the_prior_takes_a_shared_offset_out() {
    // A straight trajectory whose corrections all carry the same offset: the prior alone
    // decides the field, which then cancels the offset at every anchor.
    let params = Parameters { common_mode_field_m: 20.0, ..Default::default() };
    let positions: Vec<[f64; 3]> = (0..200).map(|k| [1000.0 + 0.5 * k as f64, 2000.0 + 0.1 * k as f64, 50.0]).collect();
    let corrections = TrajectoryCorrections { first_anchor: 0, values: vec![[0.1, -0.2, 0.05, 0.0, 0.0, 0.0]; 200] };
    let tr = [FieldTrajectory { positions: &positions, corrections: &corrections, prior: None, curvature: None }];
    let field = solve_field(std::iter::empty(), &tr, &params).unwrap();
    let shifted = field.apply(&positions, &corrections);
    // Within 1 % (the weak prior on the nodes themselves keeps a trace of it).
    for v in &shifted.values {
        assert!(v[0].abs() < 1e-3 && v[1].abs() < 2e-3 && v[2].abs() < 5e-4, "{v:?}");
    }
    // Every anchor 1 cm nodes apart touches four nodes of its own: 800 anchors, 3,200 nodes,
    // more than the dense solve took. The sparse one solves it (the prior alone takes the
    // offset out again) unless its limit is lower than the factor needs.
    let fine = Parameters { common_mode_field_m: 0.01, ..Default::default() };
    let many: Vec<[f64; 3]> = (0..800).map(|k| [1000.0031 + 0.5 * k as f64, 2000.0047, 50.0]).collect();
    let long = TrajectoryCorrections { first_anchor: 0, values: vec![[0.1, -0.2, 0.05, 0.0, 0.0, 0.0]; 800] };
    let tr_long = [FieldTrajectory { positions: &many, corrections: &long, prior: None, curvature: None }];
    let field = solve_field(std::iter::empty(), &tr_long, &fine).unwrap();
    assert_eq!(field.nodes.len(), 3200);
    // Each node is touched by one anchor only, so the nodes' own weak prior keeps more of the
    // offset (3.4 %) than with 20 m nodes.
    for v in &field.apply(&many, &long).values {
        assert!(v[0].abs() < 5e-3 && v[1].abs() < 1e-2 && v[2].abs() < 2.5e-3, "{v:?}");
    }
    let err = solve_field_within(std::iter::empty(), &tr_long, &fine, 10_000).unwrap_err();
    assert!(matches!(err, FieldError::TooLarge { nodes: 3200, limit: 10_000, .. }), "{err}");
    let short =
        [FieldTrajectory { positions: &positions[..10], corrections: &corrections, prior: None, curvature: None }];
    assert!(matches!(solve_field(std::iter::empty(), &short, &params), Err(FieldError::Positions { .. })));
}

/// Each anchor's own prior weights enter the field's prior: the campaign's weights given per
/// anchor change nothing, and where one pass is held a hundred times tighter the shared
/// offset the field removes is that pass's.
#[test]
fn per_anchor_prior_weights_decide_the_shared_offset() {
    let params = Parameters { common_mode_field_m: 20.0, ..Default::default() };
    let positions: Vec<[f64; 3]> = (0..200).map(|k| [1000.0 + 0.5 * k as f64, 2000.0, 50.0]).collect();
    let a = TrajectoryCorrections { first_anchor: 0, values: vec![[0.1, 0.0, 0.0, 0.0, 0.0, 0.0]; 200] };
    let b = TrajectoryCorrections { first_anchor: 0, values: vec![[-0.1, 0.0, 0.0, 0.0, 0.0, 0.0]; 200] };
    let campaign = vec![crate::campaign_prior_weights(&params); 200];
    let tight = vec![crate::campaign_prior_weights(&params).map(|w| 100.0 * w); 200];
    let solve = |prior_a: Option<&[[f64; 6]]>| {
        let tr = [
            FieldTrajectory { positions: &positions, corrections: &a, prior: prior_a, curvature: None },
            FieldTrajectory { positions: &positions, corrections: &b, prior: None, curvature: None },
        ];
        solve_field(std::iter::empty(), &tr, &params).unwrap()
    };
    let plain = solve(None);
    assert_eq!(solve(Some(&campaign)), plain);
    // Equal priors: the mean offset (zero) goes, each pass keeps its own.
    assert!((plain.apply(&positions, &a).values[100][0] - 0.1).abs() < 1e-3);
    // Pass a held tightly: the field takes nearly all of its offset, b moves with it.
    let held = solve(Some(&tight));
    let moved = held.apply(&positions, &a).values[100][0];
    assert!(moved.abs() < 0.01, "{moved}");
}

/// Two crossing straight trajectories (a T), 200 anchors each, one of them on a 2 % grade.
fn crossing() -> Vec<Vec<[f64; 3]>> {
    vec![
        (0..200).map(|k| [1000.0 + 0.5 * k as f64, 2000.0, 50.0]).collect(),
        (0..200).map(|k| [1050.0, 1950.0 + 0.5 * k as f64, 49.0 + 0.01 * k as f64]).collect(),
    ]
}

/// `solve_field` without data over `positions` with corrections `values`.
fn solve_without_data(
    positions: &[Vec<[f64; 3]>],
    values: &[TrajectoryCorrections],
    params: &Parameters,
) -> FieldSolution {
    let tr: Vec<FieldTrajectory> = positions
        .iter()
        .zip(values)
        .map(|(p, c)| FieldTrajectory { positions: p, corrections: c, prior: None, curvature: None })
        .collect();
    solve_field(std::iter::empty(), &tr, params).unwrap()
}

#[test]
fn the_campaign_motion_takes_a_shared_rigid_motion_out() {
    // Corrections that are one rigid motion of the whole campaign (a 10 mdeg tilt, a yaw
    // and a shift) and nothing else. The field alone takes out only the translation; with
    // the campaign's rotation every anchor's correction returns to zero.
    // The field's heading off: its constant part is a turn about z as well, which the two
    // would share (checked at the end).
    let base = Parameters {
        common_mode_field_m: 20.0,
        campaign_motion: false,
        common_mode_heading: false,
        ..Default::default()
    };
    let positions = crossing();
    let tilt = CampaignMotion { origin: [1030.0, 1990.0, 52.0], rotation: [1.7e-4, -1.2e-4, 3e-4] };
    let corrections: Vec<TrajectoryCorrections> = positions
        .iter()
        .map(|p| TrajectoryCorrections {
            first_anchor: 0,
            values: p
                .iter()
                .map(|&q| {
                    let mut v = tilt.at(q);
                    v[0] += 0.2;
                    v[1] -= 0.1;
                    v[2] += 0.05;
                    v
                })
                .collect(),
        })
        .collect();
    let without = solve_without_data(&positions, &corrections, &base);
    assert_eq!(without.motion, None);
    let with = solve_without_data(&positions, &corrections, &Parameters { campaign_motion: true, ..base.clone() });
    let motion = with.motion.expect("asked for");
    for (a, b) in motion.rotation.iter().zip(&tilt.rotation) {
        assert!((a + b).abs() < 1e-9, "{motion:?}");
    }
    for (p, c) in positions.iter().zip(&corrections) {
        for (x, y) in without.apply(p, c).values.iter().zip(&with.apply(p, c).values) {
            assert!((x[3] - 1.7e-4).abs() < 1e-15 && (x[4] + 1.2e-4).abs() < 1e-15, "{x:?}");
            assert!(y[3..].iter().all(|v| v.abs() < 1e-9), "{y:?}");
            // What is left of the translation is the nodes' own weak prior's share (< 1 %).
            assert!(y[0].abs() < 2e-3 && y[1].abs() < 1e-3 && y[2].abs() < 5e-4, "{y:?}");
        }
    }
    // With the field's heading too (the defaults), the yaw is the motion's and the field's
    // together: the corrections still return to zero.
    let all = solve_without_data(
        &positions,
        &corrections,
        &Parameters { campaign_motion: true, common_mode_heading: true, ..base.clone() },
    );
    // And with its tilt: the field's constant rotation overlaps the motion's on every axis.
    let tilted = solve_without_data(
        &positions,
        &corrections,
        &Parameters { campaign_motion: true, common_mode_heading: true, common_mode_tilt: true, ..base },
    );
    assert_eq!(tilted.tilt.len(), tilted.nodes.len());
    for field in [&all, &tilted] {
        for (p, c) in positions.iter().zip(&corrections) {
            for y in &field.apply(p, c).values {
                assert!(y[3..].iter().all(|v| v.abs() < 1e-8), "{y:?}");
                assert!(y[0].abs() < 2e-3 && y[1].abs() < 1e-3 && y[2].abs() < 5e-4, "{y:?}");
            }
        }
    }
}

#[test]
fn the_campaign_motion_moves_points_rigidly_and_holds_the_mean_attitude() {
    // A point seen from a scan head at an anchor moves, under the motion, as the rotation
    // about the origin moves it: to first order in the rotation.
    let motion = CampaignMotion { origin: [1000.0, 2000.0, 40.0], rotation: [2e-4, -1e-4, 3e-4] };
    let correction = [0.05, -0.02, 0.01, 1e-4, 2e-4, -3e-4];
    let anchor = [1120.0, 1930.0, 52.0];
    let head = anchor;
    let r = [12.0, -7.0, 3.0];
    let before = precimap_core::corrections::apply(head, r, &correction);
    let moved: [f64; 6] = std::array::from_fn(|a| correction[a] + motion.at(anchor)[a]);
    let after = precimap_core::corrections::apply(head, r, &moved);
    let w = motion.rotation;
    let d: [f64; 3] = std::array::from_fn(|a| before[a] - motion.origin[a]);
    let rigid = [
        before[0] + w[1] * d[2] - w[2] * d[1],
        before[1] + w[2] * d[0] - w[0] * d[2],
        before[2] + w[0] * d[1] - w[1] * d[0],
    ];
    // |ω| ≈ 3.7e-4 and distances ≈ 140 m: second-order terms ≈ 2e-5 m, and the correction's
    // own 5 cm shift of the head adds |ω| × 0.05 m.
    for a in 0..3 {
        assert!((after[a] - rigid[a]).abs() < 5e-5, "{a}: {} against {}", after[a], rigid[a]);
    }
    // Attitude corrections that share a mean and differ between trajectories: the rotation
    // prior takes the mean out (the translation terms, at σ 1 m, barely hold it) and leaves
    // the difference.
    let params = Parameters { common_mode_field_m: 20.0, campaign_motion: true, ..Default::default() };
    let positions = crossing();
    let corrections: Vec<TrajectoryCorrections> = (0..2)
        .map(|t| TrajectoryCorrections {
            first_anchor: 0,
            values: vec![[0.0, 0.0, 0.0, 1e-4 + 2e-5 * t as f64, -5e-5, 0.0]; 200],
        })
        .collect();
    let m = solve_without_data(&positions, &corrections, &params).motion.unwrap();
    assert!((m.rotation[0] + 1.1e-4).abs() < 1e-6 && (m.rotation[1] - 5e-5).abs() < 1e-6, "{m:?}");
    assert!(m.rotation[2].abs() < 1e-6, "{m:?}");
}

/// The field's heading: turning every pass and the map together about a point (a constant
/// heading with the translation field `ψ ez × (x − x0)`) changes no residual, so the data
/// give it no curvature, while a heading alone (the passes turning about their own scan
/// heads) does.
#[test]
fn the_heading_sees_no_rigid_turn_of_passes_and_map() {
    rigid_turns_are_invisible(false);
}

/// The field's tilt likewise: every pass and the map tilting together about a point (a
/// constant tilt with the translation field's vertical gradient `τ × (x − x0)`) changes no
/// residual, while a tilt alone (each pass about its own scan head) does; and the whole
/// rotation's sums still see no rigid turn about the vertical.
#[test]
fn the_tilt_sees_no_rigid_tilt_of_passes_and_map() {
    rigid_turns_are_invisible(true);
}

fn rigid_turns_are_invisible(tilt: bool) {
    let spacing = 10.0;
    let mut acc = if tilt { FieldAccumulator::with_tilt(spacing) } else { FieldAccumulator::with_heading(spacing) };
    let mut seed = 11u64;
    let mut rand = move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    for _ in 0..500 {
        let v = [1000.0 + 30.0 * rand(), 2000.0 + 3.0 * rand()];
        let o = [v[0] + 4.0 * (rand() - 0.5), v[1] + 3.0 + rand()];
        // Scan heads at z 0, points below and above them.
        let p = [v[0] + 10.0 * (rand() - 0.5), v[1] + 8.0 * (rand() - 0.5), 4.0 * (rand() - 0.7)];
        // Road-like normals and façade-like ones.
        let (a, b, c) =
            if rand() < 0.5 { (0.2 * (rand() - 0.5), 0.2 * (rand() - 0.5), 1.0) } else { (rand() - 0.5, 1.0, 0.0) };
        let norm = (a * a + b * b + c * c).sqrt();
        let w = [a / norm, b / norm, c / norm];
        // The point's own Jacobian for a rotation: (p − v) × w.
        let lever = cross([p[0] - v[0], p[1] - v[1], p[2]], w);
        acc.add(FieldRow {
            vehicle: v,
            others: o,
            k: 0.5 + 0.4 * rand(),
            w,
            e: 0.0,
            weight: 1.0,
            lever,
            anchored: false,
        });
    }
    let eq = acc.finish();
    // `uᵀ H u` over the unknowns `[t_x, t_y, t_z, ψ, τ_x, τ_y]` per node.
    let quadratic = |u: &dyn Fn(FieldNode) -> [f64; 6]| -> f64 {
        let mut sum = 0.0;
        for (k, &(a, b, m)) in eq.pairs.iter().enumerate() {
            let block = full_block(&m, eq.heading_pairs.get(k), eq.tilt_pairs.get(k));
            let (ua, ub) = (u(eq.nodes[a as usize]), u(eq.nodes[b as usize]));
            let mut term = 0.0;
            for r in 0..6 {
                for c in 0..6 {
                    term += ua[r] * block[r][c] * ub[c];
                }
            }
            // The upper triangle holds each off-diagonal pair once.
            sum += if a == b { term } else { 2.0 * term };
        }
        sum
    };
    let x0 = [1010.0, 1995.0];
    let offset = |(ix, iy): FieldNode| (ix as f64 * spacing - x0[0], iy as f64 * spacing - x0[1]);
    let psi = 1e-3;
    let turned = |node: FieldNode| {
        let (x, y) = offset(node);
        [-psi * y, psi * x, 0.0, psi, 0.0, 0.0]
    };
    let heading_alone = |_: FieldNode| [0.0, 0.0, 0.0, psi, 0.0, 0.0];
    let (rigid, alone) = (quadratic(&turned), quadratic(&heading_alone));
    assert!(alone > 1e-7, "{alone}");
    assert!(rigid.abs() < 1e-9 * alone, "{rigid} against {alone}");
    if tilt {
        // A rotation τ about a horizontal axis through x0 moves a node by τ × (x − x0): only
        // its height, by τ_x·y − τ_y·x.
        let tau = [0.7e-3, -1.1e-3];
        let tilted = |node: FieldNode| {
            let (x, y) = offset(node);
            [0.0, 0.0, tau[0] * y - tau[1] * x, 0.0, tau[0], tau[1]]
        };
        let tilt_alone = |_: FieldNode| [0.0, 0.0, 0.0, 0.0, tau[0], tau[1]];
        let (rigid, alone) = (quadratic(&tilted), quadratic(&tilt_alone));
        assert!(alone > 1e-7, "{alone}");
        assert!(rigid.abs() < 1e-9 * alone, "{rigid} against {alone}");
    }
}

/// Without data, a heading every pass shares over a stretch (a slow bend of 0.05°, no
/// translation) is what only the prior decides: with the field's heading the solve takes it
/// out at once; without, it stays for the per-trajectory solves. (The field is piecewise
/// linear along a street, and the attitude's stiff curvature term resists its kinks: a bend
/// much narrower than this one's 50 m is taken out only in part.)
#[test]
fn the_field_heading_takes_a_shared_bend_out() {
    let positions: Vec<Vec<[f64; 3]>> =
        (0..2).map(|t| (0..400).map(|k| [1000.0 + 0.5 * k as f64, 2000.0 + 3.0 * t as f64, 50.0]).collect()).collect();
    let bend = |x: f64| 0.05f64.to_radians() * (-((x - 1100.0) / 50.0).powi(2)).exp();
    let corrections: Vec<TrajectoryCorrections> = positions
        .iter()
        .map(|p| TrajectoryCorrections {
            first_anchor: 0,
            values: p.iter().map(|q| [0.0, 0.0, 0.0, 0.0, 0.0, bend(q[0])]).collect(),
        })
        .collect();
    let base = Parameters {
        common_mode_field_m: 7.5,
        campaign_motion: false,
        common_mode_heading: false,
        ..Default::default()
    };
    let rms = |field: &FieldSolution| {
        let values: Vec<f64> = positions
            .iter()
            .zip(&corrections)
            .flat_map(|(p, c)| field.apply(p, c).values.into_iter().map(|v| v[5]))
            .collect();
        (values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64).sqrt()
    };
    let without = solve_without_data(&positions, &corrections, &base);
    assert!(without.heading.is_empty());
    let with = solve_without_data(&positions, &corrections, &Parameters { common_mode_heading: true, ..base.clone() });
    let before = rms(&without);
    assert!(before > 1e-4, "{before}");
    assert!(rms(&with) < 0.05 * before, "{} against {before}", rms(&with));
    let heading_deg = with.largest(&positions[..1]).heading_deg;
    assert!(heading_deg > 0.04, "{heading_deg}");
    // With the campaign's rotation as well (its turn about z overlaps the field's constant
    // heading): still solved, still taken out.
    let both = solve_without_data(
        &positions,
        &corrections,
        &Parameters { common_mode_heading: true, campaign_motion: true, ..base },
    );
    assert!(rms(&both) < 0.05 * before, "{} against {before}", rms(&both));
}
