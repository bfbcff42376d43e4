//! End-to-end: a tiny campaign folder and result folder with known offsets, every metric checked
//! against values worked out by hand.

use super::*;
use precimap_core::Vec3;
use precimap_formats::{write_trajectory_csv, NewPoint, StripWriter};
use precimap_sim::truth::{TruthPoint, TruthWriter};
use std::fs;

/// Tile (36653, 386893) of 15 m starts exactly here.
const X0: f64 = 549_795.0;
const Y0: f64 = 5_803_395.0;
const UP: [f32; 3] = [0.0, 0.0, 1.0];
/// The facade plane y = Y0 + 12 faces south, towards the road.
const SOUTH: [f32; 3] = [0.0, -1.0, 0.0];

fn road(tile: usize, n: usize) -> Vec<TruthPoint> {
    (0..n)
        .map(|i| TruthPoint {
            position: [X0 + 15.0 * tile as f64 + 1.0 + (i % 20) as f64 * 0.5, Y0 + 1.0 + (i / 20) as f64 * 0.5, 50.0],
            normal: UP,
            surface_id: 1,
            class: SurfaceClass::Road,
        })
        .collect()
}

fn facade(n: usize) -> Vec<TruthPoint> {
    (0..n)
        .map(|i| TruthPoint {
            position: [X0 + 1.0 + (i % 20) as f64 * 0.5, Y0 + 12.0, 50.5 + (i / 20) as f64 * 0.25],
            normal: SOUTH,
            surface_id: 2,
            class: SurfaceClass::Facade,
        })
        .collect()
}

fn foliage(n: usize) -> Vec<TruthPoint> {
    (0..n)
        .map(|i| TruthPoint {
            position: [X0 + 7.0 + i as f64 * 0.1, Y0 + 7.0, 55.0 + i as f64 * 0.05],
            normal: UP,
            surface_id: 3,
            class: SurfaceClass::Foliage,
        })
        .collect()
}

/// Strip a: T1 300 road + 60 facade + 20 foliage, T2 250 road, T3 220 road (830 surface points).
fn truth_a() -> Vec<TruthPoint> {
    [road(0, 300), facade(60), foliage(20), road(1, 250), road(2, 220)].concat()
}

/// Strip b: T1 300 road + 60 facade + 20 foliage, T2 150 road (510 surface points).
fn truth_b() -> Vec<TruthPoint> {
    [road(0, 300), facade(60), foliage(20), road(1, 150)].concat()
}

fn gps_time(i: usize) -> f64 {
    1000.0 + i as f64 * 1e-4
}

fn write_strip(path: &Path, truth: &[TruthPoint], offset: [f64; 3], times: impl Fn(usize) -> f64) {
    let mut w = StripWriter::create(path, [X0, Y0, 0.0], 0.001, "precimap-eval test", "precimap-eval").unwrap();
    for (i, t) in truth.iter().enumerate() {
        let p = t.position;
        w.push(&NewPoint {
            position: [p[0] + offset[0], p[1] + offset[1], p[2] + offset[2]],
            gps_time: times(i),
            ..Default::default()
        })
        .unwrap();
    }
    w.finish().unwrap();
}

fn write_truth(path: &Path, truth: &[TruthPoint]) {
    let mut w = TruthWriter::create(path).unwrap();
    for t in truth {
        w.push(t).unwrap();
    }
    w.finish().unwrap();
}

/// 50 samples at 200 Hz along +x at 10 m/s; `y` tells the two trajectories apart.
fn write_trajectory(path: &Path, y: f64, shift: [f64; 3], yaw_deg: f64) {
    let times: Vec<f64> = (0..50).map(|i| 1000.0 + i as f64 * 0.005).collect();
    let positions: Vec<Vec3> = times
        .iter()
        .map(|t| Vec3::new(X0 + (t - 1000.0) * 10.0 + shift[0], Y0 + y + shift[1], 52.0 + shift[2]))
        .collect();
    let rpy = vec![[0.2, -0.4, yaw_deg]; times.len()];
    write_trajectory_csv(path, &times, &positions, &rpy).unwrap();
}

const BEFORE_A: [f64; 3] = [0.01, -0.03, 0.02];
const BEFORE_B: [f64; 3] = [0.0, 0.01, -0.02];
const AFTER_A: [f64; 3] = [0.0, 0.0, 0.003];
const AFTER_B: [f64; 3] = [0.0, 0.0, 0.001];

/// Writes `CAMP` and `OUT` under `root`; returns (truth dir, result dir).
fn write_fixture(root: &Path) -> (PathBuf, PathBuf) {
    let camp = root.join("camp");
    let out = root.join("out");
    for d in [camp.join("strips"), camp.join("trajectories"), camp.join("truth/trajectories")] {
        fs::create_dir_all(d).unwrap();
    }
    for d in [out.join("strips"), out.join("trajectories")] {
        fs::create_dir_all(d).unwrap();
    }
    let manifest = serde_json::json!({
        "name": "eval-test",
        "scanners": {"left": {"lever_arm_m": [-0.6, 0.35, 0.45], "boresight_deg": [0, 0, 0]}},
        "trajectories": [{"id": "p01", "uri": "trajectories/p01.csv"}, {"id": "p02", "uri": "trajectories/p02.csv"}],
        "strips": [
            {"id": "a", "trajectory": "p01", "scanner": "left", "uri": "strips/a.las"},
            {"id": "b", "trajectory": "p02", "scanner": "left", "uri": "strips/b.laz"}
        ]
    });
    fs::write(camp.join("manifest.json"), serde_json::to_string_pretty(&manifest).unwrap()).unwrap();

    let (ta, tb) = (truth_a(), truth_b());
    write_truth(&camp.join("truth/a.truth"), &ta);
    write_truth(&camp.join("truth/b.truth"), &tb);
    write_strip(&camp.join("strips/a.las"), &ta, BEFORE_A, gps_time);
    write_strip(&camp.join("strips/b.laz"), &tb, BEFORE_B, gps_time);
    write_strip(&out.join("strips/a.laz"), &ta, AFTER_A, gps_time);
    write_strip(&out.join("strips/b.las"), &tb, AFTER_B, gps_time);

    write_trajectory(&camp.join("truth/trajectories/p01.csv"), 5.0, [0.0; 3], 0.0);
    write_trajectory(&camp.join("truth/trajectories/p02.csv"), 8.0, [0.0; 3], 0.0);
    write_trajectory(&camp.join("trajectories/p01.csv"), 5.0, [0.05, 0.0, 0.0], 0.02);
    write_trajectory(&camp.join("trajectories/p02.csv"), 8.0, [0.0, 0.03, 0.04], 0.0);
    write_trajectory(&out.join("trajectories/p01.csv"), 5.0, [0.001, 0.0, 0.0], 0.0);
    write_trajectory(&out.join("trajectories/p02.csv"), 8.0, [0.0; 3], 0.0);

    let report = serde_json::json!({
        "iterations": [{"points_used": 100, "max_change_m": 0.1}, {"points_used": 1206, "max_change_m": 0.001}],
        "points_total": 1380
    });
    fs::write(out.join("report.json"), report.to_string()).unwrap();
    (camp.join("truth"), out)
}

#[track_caller]
fn assert_close(got: f64, want: f64, tol: f64) {
    assert!((got - want).abs() <= tol, "got {got}, want {want} (±{tol})");
}

#[track_caller]
fn assert_metric(m: &Metric, before: f64, after: f64) {
    // Coordinates pass through 1 mm LAS quantisation exactly (all values are whole mm), so only
    // f64 rounding at 5.8e6 m remains.
    assert_close(m.before, before, 1e-9);
    assert_close(m.after, after, 1e-9);
}

#[test]
fn end_to_end_metrics_match_hand_computed_values() {
    let dir = tempfile::tempdir().unwrap();
    let (truth, out) = write_fixture(dir.path());
    let e = evaluate(&truth, &out).unwrap();

    assert_eq!((e.strips, e.points, e.surface_points), (2, 850 + 530, 830 + 510));
    // Only tile T1 has two strips with ≥ 200 surface points (T2: b has 150; T3: a only).
    assert_eq!(e.tile_strip_pairs, 2);
    // Before, T1: a's mean (300·20 mm + 60·30 mm)/360, b's (300·−20 mm + 60·−10 mm)/360; they
    // differ by 40 mm, so each deviates 20 mm from the tile mean. After: 2.5 mm vs 0.833 mm.
    assert_metric(&e.strip_offset_spread_m, 0.02, 1.0 / 1200.0);
    // Surface errors: road = δz, facade (normal −y) = −δy, foliage ignored.
    // Before: a 770 road at 20 mm, 60 facade at 30 mm; b 450 road at −20 mm, 60 facade at −10 mm.
    // After: a 770 road at 3 mm, facade 0; b 450 road at 1 mm, facade 0.
    let n = 1340.0f64;
    let rms_before = ((770.0 * 4e-4 + 60.0 * 9e-4 + 450.0 * 4e-4 + 60.0 * 1e-4) / n).sqrt();
    let rms_after = ((770.0 * 9e-6 + 450.0 * 1e-6) / n).sqrt();
    assert_metric(&e.surface_error_rms_m, rms_before, rms_after);
    assert_metric(&e.surface_error_mean_m, 7.6 / n, (770.0 * 0.003 + 450.0 * 0.001) / n);
    // |error| 95th percentile, rank 1273 of 1340: 20 mm before (60 at 10, 1220 at 20, 60 at 30),
    // 3 mm after (120 at 0, 450 at 1, 770 at 3); the histogram is exact to ±0.25 %.
    assert_close(e.surface_error_p95_abs_m.before, 0.02, 0.02 * 0.0025);
    assert_close(e.surface_error_p95_abs_m.after, 0.003, 0.003 * 0.0025);

    // Trajectories: p01 +5 cm in x and +0.02° yaw before, +1 mm after; p02 (3, 4) cm before,
    // exact after; 50 samples each.
    assert_eq!(e.trajectory_samples, 100);
    assert_metric(&e.trajectory_error_rms_m, 0.05, (50.0 * 1e-6 / 100.0f64).sqrt());
    assert_close(e.trajectory_rotation_error_rms_deg.before, (50.0 * 0.02f64.powi(2) / 100.0).sqrt(), 1e-7);
    assert_close(e.trajectory_rotation_error_rms_deg.after, 0.0, 1e-7);
    let p01 = &e.per_trajectory[0];
    assert_eq!((p01.id.as_str(), p01.samples_before, p01.samples_after, p01.samples_outside_truth), ("p01", 50, 50, 0));
    assert_metric(&p01.position_rms_m, 0.05, 0.001);
    assert_metric(&e.per_trajectory[1].position_rms_m, 0.05, 0.0);

    // Report: last iteration used 1206 of 1340 surface points.
    assert_eq!(e.points_used_last_iteration, Some(1206));
    assert_close(e.surface_points_used_share.unwrap(), 0.9, 1e-12);

    // Per class and per strip.
    assert_eq!(e.per_class.keys().collect::<Vec<_>>(), ["facade", "road"]);
    let road = &e.per_class["road"];
    assert_eq!(road.points, 1220);
    assert_metric(&road.rms_m, 0.02, ((770.0 * 9e-6 + 450.0 * 1e-6) / 1220.0f64).sqrt());
    assert_metric(&road.mean_m, (770.0 - 450.0) * 0.02 / 1220.0, (770.0 * 0.003 + 450.0 * 0.001) / 1220.0);
    let fac = &e.per_class["facade"];
    assert_eq!(fac.points, 120);
    assert_metric(&fac.rms_m, 5e-4f64.sqrt(), 0.0);
    assert_metric(&fac.mean_m, 0.01, 0.0);
    // Per-class spreads (≥ 50 points): the road in T1 and T2 (a +20 / b −20 mm before, +3 / +1
    // after), the facade in T1 (+30 / −10 mm before, 0 / 0 after).
    assert_metric(&road.spread_m, 0.02, 0.001);
    assert_metric(&road.same_surface_spread_m, 0.02, 0.001);
    assert_eq!(road.tile_strip_pairs, 4);
    assert_metric(&fac.spread_m, 0.02, 0.0);
    // Without the campaign's shift: after, the least-squares shift of all points is (0, 0, 2.2 mm)
    // ((770·3 + 450·1)/1220 on the road; the facade, at 0, does not see z), so the road's strips
    // are at +0.8 / −1.2 mm, still 1 mm from their tile means.
    assert_close(road.spread_without_campaign_shift_m.after, 0.001, 1e-9);
    assert_close(fac.spread_without_campaign_shift_m.after, 0.0, 1e-9);
    assert_eq!(fac.tile_strip_pairs, 2);
    let a = &e.per_strip[0];
    assert_eq!((a.id.as_str(), a.points, a.surface_points), ("a", 850, 830));
    assert_metric(&a.rms_m, ((770.0 * 4e-4 + 60.0 * 9e-4) / 830.0f64).sqrt(), (770.0 * 9e-6 / 830.0f64).sqrt());
    let b = &e.per_strip[1];
    assert_eq!((b.id.as_str(), b.points, b.surface_points), ("b", 530, 510));
    assert_metric(&b.mean_m, (-450.0 * 0.02 - 60.0 * 0.01) / 510.0, 450.0 * 0.001 / 510.0);

    // Serialises (NaN-free here) and summarises.
    let json = serde_json::to_value(&e).unwrap();
    assert_eq!(json["tile_strip_pairs"], 2);
    assert!(json["strip_offset_spread_m"]["before"].as_f64().is_some());
    // A run that estimated no calibration adds neither a JSON key nor a line.
    assert!(json.get("calibration").is_none() && e.calibration.is_none());
    let text = e.summary();
    assert!(text.contains("strip offset spread") && text.contains("20.000") && text.contains("road"), "{text}");

    // Without report.json there is no share; everything else stands.
    fs::remove_file(out.join("report.json")).unwrap();
    let e2 = evaluate(&truth, &out).unwrap();
    assert_eq!((e2.surface_points_used_share, e2.points_used_last_iteration), (None, None));
    assert_eq!(e2.surface_error_rms_m, e.surface_error_rms_m);
}

#[test]
fn result_with_a_missing_point_is_rejected_naming_the_strip() {
    let dir = tempfile::tempdir().unwrap();
    let (truth, out) = write_fixture(dir.path());
    let mut tb = truth_b();
    tb.pop();
    write_strip(&out.join("strips/b.las"), &tb, AFTER_B, gps_time);
    let err = evaluate(&truth, &out).unwrap_err();
    assert!(
        matches!(&err, EvalError::PointCount { strip, which: "result", found: 529, expected: 530, .. } if strip == "b"),
        "{err}"
    );
    let msg = err.to_string();
    assert!(msg.contains("strip b") && msg.contains("529") && msg.contains("530"), "{msg}");
}

#[test]
fn missing_or_reordered_results_and_bad_inputs_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let (truth, out) = write_fixture(dir.path());

    // Points out of order: their GPS times no longer match the input's.
    write_strip(&out.join("strips/b.las"), &truth_b(), AFTER_B, |i| gps_time(if i == 7 { 8 } else { i }));
    let err = evaluate(&truth, &out).unwrap_err();
    assert!(matches!(&err, EvalError::PointOrder { strip, index: 7, .. } if strip == "b"), "{err}");

    fs::remove_file(out.join("strips/b.las")).unwrap();
    let err = evaluate(&truth, &out).unwrap_err();
    assert!(matches!(&err, EvalError::MissingResultStrip { strip, .. } if strip == "b"), "{err}");
    write_strip(&out.join("strips/b.las"), &truth_b(), AFTER_B, gps_time);

    fs::remove_file(out.join("trajectories/p02.csv")).unwrap();
    let err = evaluate(&truth, &out).unwrap_err();
    assert!(matches!(&err, EvalError::MissingResultTrajectory { trajectory, .. } if trajectory == "p02"), "{err}");
    write_trajectory(&out.join("trajectories/p02.csv"), 8.0, [0.0; 3], 0.0);

    fs::write(out.join("report.json"), "{ not json").unwrap();
    assert!(matches!(evaluate(&truth, &out), Err(EvalError::Report { .. })));
    fs::write(out.join("report.json"), r#"{"iterations": []}"#).unwrap();
    assert_eq!(evaluate(&truth, &out).unwrap().surface_points_used_share, None);

    // The input strip disagrees with its truth.
    let camp = truth.parent().unwrap();
    write_strip(&camp.join("strips/a.las"), &truth_a()[..10], BEFORE_A, gps_time);
    let err = evaluate(&truth, &out).unwrap_err();
    assert!(matches!(&err, EvalError::PointCount { strip, which: "input", .. } if strip == "a"), "{err}");

    assert!(matches!(evaluate(&dir.path().join("nowhere"), &out), Err(EvalError::TruthDir { .. })));
    fs::remove_file(camp.join("manifest.json")).unwrap();
    assert!(matches!(evaluate(&truth, &out), Err(EvalError::Manifest(_))));
}
