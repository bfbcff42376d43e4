//! Strips whose acquisition pattern makes no scan image still get normals (from 3-D neighbours)
//! and are adjusted; strips that cannot be adjusted stop the run with a message that names them.

use precimap_pipeline::{run_campaign, PipelineError, RunOptions};
use std::path::{Path, PathBuf};

fn simulate_tiny(dir: &Path, seed: u64) -> PathBuf {
    let campaign = dir.join("campaign");
    let config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, seed);
    precimap_sim::simulate(&config, &campaign, false).expect("simulate tiny");
    campaign
}

fn run(manifest: &Path, out: &Path) -> Result<precimap_pipeline::Report, PipelineError> {
    run_campaign(manifest, &RunOptions { out_dir: out.to_path_buf(), keep_work: false, assignments: false }, &|_| {})
}

fn manifest(campaign: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(campaign.join("manifest.json")).unwrap()).unwrap()
}

fn write_manifest(campaign: &Path, name: &str, manifest: &serde_json::Value) -> PathBuf {
    let path = campaign.join(format!("manifest-{name}.json"));
    std::fs::write(&path, serde_json::to_vec(manifest).unwrap()).unwrap();
    path
}

/// The strip files the manifest names, in its order.
fn strip_paths(campaign: &Path) -> Vec<PathBuf> {
    let loaded = precimap_pipeline::Campaign::load(&campaign.join("manifest.json")).unwrap();
    loaded.strips.iter().map(|s| s.path.clone()).collect()
}

/// Rewrites a strip with the same points but scan angles that follow no rotating head (a
/// pseudo-random angle per point, as an unordered or merged file might carry), on one channel.
fn scramble_scan_angles(path: &Path) {
    let points = precimap_formats::read_strip(path).unwrap();
    let tmp = path.with_extension("scrambled.las");
    // Offsets near the points: 0.1 mm units must fit 32 bits.
    let offset = [points.x[0].round(), points.y[0].round(), points.z[0].round()];
    let mut writer = precimap_formats::StripWriter::create(&tmp, offset, 1e-4, "test", "test").unwrap();
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    for k in 0..points.len() {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let angle = ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 180.0;
        writer
            .push(&precimap_formats::NewPoint {
                position: [points.x[k], points.y[k], points.z[k]],
                gps_time: points.gps_time[k],
                scan_angle_deg: angle as f32,
                channel: 0,
                intensity: 100,
                return_number: 1,
                number_of_returns: 1,
                point_source_id: 1,
                classification: 0,
            })
            .unwrap();
    }
    writer.finish().unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

/// Strips whose scan angles follow no pattern: `normals: auto` takes their normals from 3-D
/// neighbours, and the campaign is adjusted (the strips agree far better than before).
#[test]
fn strips_of_an_unknown_pattern_are_adjusted_with_neighbour_normals() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = simulate_tiny(dir.path(), 3);
    for path in strip_paths(&campaign) {
        scramble_scan_angles(&path);
    }
    let out = dir.path().join("out");
    let report = run(&campaign.join("manifest.json"), &out).expect("the campaign runs");
    for s in &report.strips {
        assert_eq!(s.normal_source, precimap_core::NormalSource::Neighbours, "strip {}", s.id);
        assert!(
            s.points_usable as f64 > 0.5 * s.points as f64,
            "strip {}: {} of {} usable",
            s.id,
            s.points_usable,
            s.points
        );
    }
    let last = report.iterations.last().unwrap();
    assert!(last.points_used > 0);
    let e = precimap_eval::evaluate(&campaign.join("truth"), &out).unwrap();
    eprintln!("{}", e.summary());
    assert_eq!(e.points, report.points_total);
    assert!(
        e.strip_offset_spread_m.after < 0.25 * e.strip_offset_spread_m.before,
        "spread {:?}",
        e.strip_offset_spread_m
    );
    assert!(
        e.same_surface_spread_m.after < 0.1 * e.same_surface_spread_m.before,
        "same-surface spread {:?}",
        e.same_surface_spread_m
    );
}

/// A strip that cannot be adjusted stops the run with its name and the reason; with
/// `allow_low_usable_share` the run goes on.
#[test]
fn an_unusable_strip_stops_the_run_with_its_name_and_reason() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = simulate_tiny(dir.path(), 5);
    let mut m = manifest(&campaign);
    m["parameters"] = serde_json::json!({ "min_usable_share": 0.5, "normals": "scan_image" });
    let strict = write_manifest(&campaign, "strict", &m);
    // Raise the share beyond what any strip reaches: every strip is named.
    m["parameters"]["min_usable_share"] = serde_json::json!(0.999);
    let too_strict = write_manifest(&campaign, "too-strict", &m);
    let out = dir.path().join("out");
    run(&strict, &out).expect("the simulated strips are usable");
    let err = run(&too_strict, &out).unwrap_err().to_string();
    assert!(err.contains("strip ") && err.contains("usable") && err.contains("min_usable_share"), "{err}");
    m["parameters"]["allow_low_usable_share"] = serde_json::json!(true);
    let warned = write_manifest(&campaign, "warned", &m);
    run(&warned, &out).expect("a warning only");
}

/// A campaign of which nothing is usable (every point beyond `max_range_m`) stops with the
/// strips' names; with `allow_low_usable_share` it runs, observes nothing and is not converged
/// (no "0 tiles, 0 iterations" success).
#[test]
fn a_campaign_with_nothing_usable_stops_or_is_not_converged() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = simulate_tiny(dir.path(), 6);
    let mut m = manifest(&campaign);
    m["parameters"] = serde_json::json!({ "max_range_m": 0.5 });
    let none = write_manifest(&campaign, "none", &m);
    let out = dir.path().join("out");
    let err = run(&none, &out).unwrap_err().to_string();
    // Strips are prepared in parallel: the error names whichever failed first.
    let ids: Vec<String> =
        m["strips"].as_array().unwrap().iter().map(|s| s["id"].as_str().unwrap().to_string()).collect();
    assert!(ids.iter().any(|id| err.contains(&format!("strip {id} "))) && err.contains("usable"), "{err}");
    m["parameters"]["allow_low_usable_share"] = serde_json::json!(true);
    let warned = write_manifest(&campaign, "none-warned", &m);
    let report = run(&warned, &out).expect("warnings only");
    assert_eq!(report.tiles, 0);
    assert!(!report.converged, "a campaign that observed nothing is not converged");
}
