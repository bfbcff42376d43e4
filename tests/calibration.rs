//! Mounting calibration end to end: boresight, lever-arm and range-offset errors of both scan
//! heads are estimated with the trajectories, the strips then agree as without those errors, and
//! the job framework gives the in-process result.

use precimap_pipeline::{run_campaign, Report, RunOptions};
use std::path::{Path, PathBuf};

/// The simulated heads' calibration errors; the estimate should be their negatives.
fn errors() -> precimap_sim::config::CalibrationErrors {
    precimap_sim::config::CalibrationErrors {
        boresight_left_deg: [0.05, -0.08, 0.1],
        boresight_right_deg: [-0.1, 0.06, -0.07],
        lever_arm_left_m: [0.03, -0.02, 0.05],
        lever_arm_right_m: [-0.04, 0.05, -0.03],
        range_scale_ppm: 0.0,
        range_offset_m: 0.01,
    }
}

/// A tiny campaign with calibration errors, and its manifest estimating `kinds`.
fn simulate_with_errors(dir: &Path, seed: u64, kinds: &[&str]) -> (PathBuf, PathBuf) {
    let campaign = dir.join(format!("calibration-{seed}"));
    let mut config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, seed);
    config.errors.calibration = errors();
    precimap_sim::simulate(&config, &campaign, false).expect("simulate tiny with calibration errors");
    let mut manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(campaign.join("manifest.json")).unwrap()).unwrap();
    manifest["parameters"]["calibration"] = serde_json::json!({ "estimate": kinds });
    let path = campaign.join("manifest-calibrating.json");
    std::fs::write(&path, serde_json::to_vec(&manifest).unwrap()).unwrap();
    (campaign, path)
}

fn run(manifest: &Path, out: &Path) -> Report {
    run_campaign(manifest, &RunOptions { out_dir: out.to_path_buf(), keep_work: false, assignments: false }, &|_| {})
        .unwrap()
}

#[test]
fn boresight_errors_are_recovered_and_the_strips_agree_again() {
    let dir = tempfile::tempdir().unwrap();
    let (campaign, manifest) = simulate_with_errors(dir.path(), 3, &["boresight", "lever_arm", "range_offset"]);
    let (with, without) = (dir.path().join("with"), dir.path().join("without"));
    let report = run(&manifest, &with);
    run(&campaign.join("manifest.json"), &without);
    let calibration = report.calibration.expect("the report's calibration");
    for u in &calibration.unknowns {
        eprintln!(
            "{} {} {:+.4} ± {:.5} {} (separation {:.2})",
            u.scanner, u.name, u.value, u.sigma, u.unit, u.separation
        );
    }
    let estimate = |scanner: &str, name: &str| {
        calibration.unknowns.iter().find(|u| u.scanner == scanner && u.name == name).expect("unknown reported").value
    };
    // Roll and pitch of each head, and the heads' difference in yaw, are what the strips
    // separate from the trajectories' own attitude errors.
    let e = errors();
    for (scanner, truth) in [("left", e.boresight_left_deg), ("right", e.boresight_right_deg)] {
        for (axis, name) in ["boresight_roll", "boresight_pitch"].iter().enumerate() {
            let error = estimate(scanner, name) + truth[axis];
            assert!(error.abs() < 0.01, "{scanner} {name}: {} against {}", estimate(scanner, name), -truth[axis]);
        }
    }
    let yaw_difference = estimate("left", "boresight_yaw") - estimate("right", "boresight_yaw");
    let true_difference = -(e.boresight_left_deg[2] - e.boresight_right_deg[2]);
    assert!((yaw_difference - true_difference).abs() < 0.02, "{yaw_difference} against {true_difference}");
    // The strips agree again (small s1 with these errors: 35 → 0.9 mm same-surface).
    let e_with = precimap_eval::evaluate(&campaign.join("truth"), &with).unwrap();
    let e_without = precimap_eval::evaluate(&campaign.join("truth"), &without).unwrap();
    eprintln!("same surface {:?} against {:?}", e_with.same_surface_spread_m, e_without.same_surface_spread_m);
    assert!(
        e_with.same_surface_spread_m.after < 0.3 * e_without.same_surface_spread_m.after,
        "{:?} against {:?}",
        e_with.same_surface_spread_m,
        e_without.same_surface_spread_m
    );
}

#[test]
fn calibration_gives_the_in_process_result_through_the_framework() {
    let dir = tempfile::tempdir().unwrap();
    let (_, manifest) = simulate_with_errors(dir.path(), 4, &["boresight", "range_offset"]);
    let reference = dir.path().join("in-process");
    let report = run(&manifest, &reference);
    assert!(report.calibration.is_some());
    let embedded = dir.path().join("embedded");
    crate::framework::run_embedded_into(&manifest, &embedded);
    crate::framework::assert_same_results(&reference, &embedded);
    let calibration = |out: &Path| {
        let r: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
        r["calibration"].clone()
    };
    assert_eq!(calibration(&reference), calibration(&embedded));
}
