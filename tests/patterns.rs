//! Strips whose acquisition pattern makes no scan image still get normals (from 3-D neighbours)
//! and are adjusted; a multi-beam head's strips get theirs from the ring image; strips that
//! cannot be adjusted stop the run with a message that names them.

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

/// Evaluates the result `out` of `campaign` against its truth: the strips agree far better
/// than before (spread below a quarter, same-surface spread below a tenth).
fn assert_strips_agree_far_better(campaign: &Path, out: &Path) -> precimap_eval::Evaluation {
    let e = precimap_eval::evaluate(&campaign.join("truth"), out).unwrap();
    eprintln!("{}", e.summary());
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
    e
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
    let e = assert_strips_agree_far_better(&campaign, &out);
    assert_eq!(e.points, report.points_total);
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

/// A tiny multi-beam campaign: 12 rings over −25°…−3° at 5 Hz and 3.6° per firing, in a town
/// of 24 m blocks, so that it runs in seconds in a debug build.
fn simulate_tiny_multibeam(dir: &Path, seed: u64) -> PathBuf {
    let campaign = dir.join("campaign");
    let mut config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, seed);
    config.town.block_m = 24.0;
    config.scanner.multibeam = Some(precimap_sim::MultiBeamConfig {
        rings: 12,
        elevation_deg: [-25.0, -3.0],
        revolutions_per_s: 5.0,
        firings_per_revolution: 100,
        ..precimap_sim::MultiBeamConfig::default()
    });
    precimap_sim::simulate(&config, &campaign, false).expect("simulate tiny multi-beam");
    campaign
}

/// A multi-beam head's strips, whose manifest names the ring's field: `normals: auto` takes
/// the ring image, which gives >= 90 % of the surface points a normal, and the campaign is
/// adjusted.
#[test]
fn multibeam_strips_get_ring_image_normals_and_are_adjusted() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = simulate_tiny_multibeam(dir.path(), 4);
    let loaded = precimap_pipeline::Campaign::load(&campaign.join("manifest.json")).unwrap();
    assert_eq!(loaded.params.ring, Some(precimap_core::RingSource::UserData));
    let segment = precimap_estimate::SegmentParams::default();
    let prepared = precimap_pipeline::tasks::prepare_strip_in_memory(&loaded, 0, &segment).unwrap();
    assert_eq!(prepared.stats.normal_source, precimap_core::NormalSource::RingImage);
    let truth_path = campaign.join("truth").join(format!("{}.truth", loaded.strips[0].id));
    let truth = precimap_sim::TruthReader::open(&truth_path).unwrap().read_all().unwrap();
    assert_eq!(truth.len(), prepared.normals.len());
    // Surface points (not foliage) of the revolutions in the image (not dropped at standstill).
    let (mut surface, mut with_normal) = (0u64, 0u64);
    for ((t, n), &s) in truth.iter().zip(&prepared.normals).zip(&prepared.segment) {
        if t.class.is_surface() && s != precimap_estimate::DROPPED_SEGMENT {
            surface += 1;
            with_normal += u64::from(n.is_some());
        }
    }
    let share = with_normal as f64 / surface as f64;
    eprintln!("{with_normal} of {surface} surface points have a ring-image normal ({:.1} %)", 100.0 * share);
    assert!(share >= 0.9, "{with_normal} of {surface} surface points have a normal");

    // Without the ring source, the profile scan image is refused and the 3-D neighbours serve.
    let mut without = loaded;
    without.params.ring = None;
    let prepared = precimap_pipeline::tasks::prepare_strip_in_memory(&without, 0, &segment).unwrap();
    assert_eq!(prepared.stats.normal_source, precimap_core::NormalSource::Neighbours);
    let refused = prepared.stats.scan_image_refused.unwrap_or_default();
    assert!(refused.contains("points per pixel") && refused.contains("parameters.ring"), "{refused}");

    let out = dir.path().join("out");
    let report = run(&campaign.join("manifest.json"), &out).expect("the campaign runs");
    for s in &report.strips {
        assert_eq!(s.normal_source, precimap_core::NormalSource::RingImage, "strip {}", s.id);
    }
    assert!(report.iterations.last().unwrap().points_used > 0);
    assert_strips_agree_far_better(&campaign, &out);
}
