//! A simulated campaign run twice: in its local frame, and as it comes from the field (SBET in
//! geographic coordinates with a wander angle and GPS week seconds, LAZ in WGS 84 / UTM zone 32N
//! with adjusted standard GPS time). The adjusted points agree point for point. With its SMRMSG
//! accuracy files the field campaign's prior follows the simulated errors, through both drivers
//! alike.

use precimap_formats::gps_time::TimeConvention;
use precimap_formats::{load_manifest, read_strip, read_trajectory_csv, strip_info, TrajectoryRef};
use precimap_pipeline::{run_campaign, PipelineError, RunOptions};
use std::path::Path;

fn run(manifest: &Path, out: &Path) -> Result<precimap_pipeline::Report, PipelineError> {
    run_campaign(manifest, &RunOptions { out_dir: out.to_path_buf(), keep_work: false, assignments: false }, &|_| {})
}

/// The field manifest without its accuracy files (`no-accuracy.json` beside it): the prior is the
/// campaign's, as in the local-frame campaign.
fn without_accuracy(field: &Path) -> std::path::PathBuf {
    let mut manifest = load_manifest(&field.join("manifest.json")).unwrap();
    assert!(manifest.trajectories.iter().all(|t| t.accuracy_uri.is_some()), "the simulator writes SMRMSG files");
    manifest.trajectories.iter_mut().for_each(|t| t.accuracy_uri = None);
    let path = field.join("no-accuracy.json");
    std::fs::write(&path, serde_json::to_string(&manifest).unwrap()).unwrap();
    path
}

#[test]
fn a_field_campaign_matches_its_local_frame_run() {
    let dir = tempfile::tempdir().unwrap();
    let local = dir.path().join("local");
    let field = dir.path().join("field");
    let config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, 3);
    precimap_sim::simulate(&config, &local, false).unwrap();
    precimap_sim::field::write_field_campaign(&local, &field, config.origin, true).unwrap();
    let (out_local, out_field) = (dir.path().join("out-local"), dir.path().join("out-field"));
    let report_local = run(&local.join("manifest.json"), &out_local).unwrap();
    let report_field = run(&without_accuracy(&field), &out_field).unwrap();
    assert_eq!(report_local.points_total, report_field.points_total);
    assert_eq!(report_local.iterations.len(), report_field.iterations.len());

    let manifest = load_manifest(&field.join("manifest.json")).unwrap();
    let georef = manifest.crs.as_ref().unwrap().georeference().unwrap();
    let mut worst = 0.0f64;
    for s in &manifest.strips {
        let path = out_field.join(format!("strips/{}.laz", s.id));
        let info = strip_info(&path).unwrap();
        assert_eq!(info.crs.as_ref().and_then(|c| c.epsg), Some(32632), "{}: {:?}", s.id, info.crs);
        assert_eq!(info.time_convention, TimeConvention::AdjustedStandard);
        let a = read_strip(&out_local.join(format!("strips/{}.las", s.id))).unwrap();
        let b = read_strip(&path).unwrap();
        assert_eq!(a.len(), b.len());
        for i in 0..a.len() {
            assert_eq!(a.gps_time[i], b.gps_time[i], "{} point {i}", s.id);
            let p = georef.local_from_strip([b.x[i], b.y[i], b.z[i]]).unwrap();
            let d = ((p[0] - a.x[i]).powi(2) + (p[1] - a.y[i]).powi(2) + (p[2] - a.z[i]).powi(2)).sqrt();
            worst = worst.max(d);
        }
    }
    eprintln!("largest difference of an adjusted point, field vs local run: {:.4} mm", worst * 1e3);
    assert!(worst <= 0.5e-3, "{worst} m");

    // The exported trajectories are in the grid, their CRS beside them; read back with that CRS
    // they are the local run's poses.
    let frame = &georef.frame;
    for t in &manifest.trajectories {
        let prj = std::fs::read_to_string(out_field.join(format!("trajectories/{}.prj", t.id))).unwrap();
        assert_eq!(prj, frame.crs().wkt());
        let spec = TrajectoryRef { crs: Some(32632), ..TrajectoryRef::csv(&t.id, "x.csv") };
        let csv = out_field.join(format!("trajectories/{}.csv", t.id));
        let grid = precimap_formats::trajectory::load_trajectory(&csv, &spec, None, Some(frame), None).unwrap();
        let want = read_trajectory_csv(&out_local.join(format!("trajectories/{}.csv", t.id))).unwrap();
        let mut worst = (0.0f64, 0.0f64);
        for i in 0..want.len() {
            worst.0 = worst.0.max((grid.trajectory.positions()[i] - want.positions()[i]).norm());
            let r = grid.trajectory.rotations()[i].transpose() * want.rotations()[i];
            worst.1 = worst.1.max(precimap_core::geom::so3_log(&r).norm().to_degrees());
        }
        assert!(worst.0 < 0.5e-3 && worst.1 < 1e-4, "trajectory {}: {worst:?}", t.id);
    }
}

#[test]
fn a_strip_in_another_crs_or_time_is_refused_naming_both() {
    let dir = tempfile::tempdir().unwrap();
    let local = dir.path().join("local");
    let field = dir.path().join("field");
    let mut config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, 5);
    config.drive.passes = 2;
    precimap_sim::simulate(&config, &local, false).unwrap();
    precimap_sim::field::write_field_campaign(&local, &field, config.origin, false).unwrap();
    let mut manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(field.join("manifest.json")).unwrap()).unwrap();
    manifest["crs"]["strips"] = serde_json::Value::from(25832);
    std::fs::write(field.join("other-crs.json"), manifest.to_string()).unwrap();
    let e = run(&field.join("other-crs.json"), &dir.path().join("o1")).unwrap_err().to_string();
    assert!(e.contains("EPSG:32632") && e.contains("EPSG:25832") && e.contains("ETRS89 / UTM zone 32N"), "{e}");

    // The SBET of pass 1 under the strips of pass 0: the times do not overlap.
    manifest["crs"].as_object_mut().unwrap().remove("strips");
    let uri = manifest["trajectories"][1]["uri"].clone();
    manifest["trajectories"][0]["uri"] = uri;
    std::fs::write(field.join("other-time.json"), manifest.to_string()).unwrap();
    let e = run(&field.join("other-time.json"), &dir.path().join("o2")).unwrap_err().to_string();
    assert!(e.contains("s of GPS week") && e.contains("adjusted standard GPS time"), "{e}");
    assert!(e.matches("GPS week").count() >= 2, "both ranges in both conventions: {e}");
}

/// The measurement behind processing in a local Cartesian frame rather than in the projected grid
/// (docs/design/field-inputs.md): the same field campaign run with its grid coordinates taken as
/// if they were metric (trajectories as grid CSV, strips as they are, no `crs`), its adjusted
/// points mapped back and compared with the local-frame run. Run with
/// `cargo test -p precimap-cli --test system field:: -- --ignored --nocapture`.
#[test]
#[ignore]
fn processing_in_the_grid_instead_costs_this_much() {
    let dir = tempfile::tempdir().unwrap();
    let local = dir.path().join("local");
    let field = dir.path().join("field");
    let config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, 3);
    precimap_sim::simulate(&config, &local, false).unwrap();
    precimap_sim::field::write_field_campaign(&local, &field, config.origin, false).unwrap();
    let manifest = load_manifest(&field.join("manifest.json")).unwrap();
    let georef = manifest.crs.as_ref().unwrap().georeference().unwrap();
    // The grid campaign: trajectories as grid CSV, the field strips, no CRS.
    let mut grid = manifest.clone();
    grid.crs = None;
    for t in &mut grid.trajectories {
        let data = read_trajectory_csv(&local.join(format!("trajectories/{}.csv", t.id))).unwrap();
        let (mut positions, mut rpy) = (Vec::new(), Vec::new());
        for (p, r) in data.positions().iter().zip(data.rotations()) {
            let (g, a) = precimap_formats::navigation::grid_pose(&georef.frame, p, r).unwrap();
            positions.push(precimap_core::Vec3::from(g));
            rpy.push(a);
        }
        t.uri = format!("trajectories/{}-grid.csv", t.id);
        t.format = precimap_formats::TrajectoryFormat::Csv;
        precimap_formats::write_trajectory_csv(&field.join(&t.uri), data.times(), &positions, &rpy).unwrap();
    }
    std::fs::write(field.join("grid.json"), serde_json::to_string(&grid).unwrap()).unwrap();
    let (out_local, out_grid) = (dir.path().join("out-local"), dir.path().join("out-grid"));
    run(&local.join("manifest.json"), &out_local).unwrap();
    run(&field.join("grid.json"), &out_grid).unwrap();
    let mut diffs = Vec::new();
    for s in &manifest.strips {
        let a = read_strip(&out_local.join(format!("strips/{}.las", s.id))).unwrap();
        let b = read_strip(&out_grid.join(format!("strips/{}.las", s.id))).unwrap();
        // The input strips differ by the grid's distortion already; compare the adjustments.
        let ia = read_strip(&local.join(format!("strips/{}.las", s.id))).unwrap();
        let ib = read_strip(&field.join(format!("strips/{}.las", s.id))).unwrap();
        for i in 0..a.len() {
            let pb = georef.local_from_strip([b.x[i], b.y[i], b.z[i]]).unwrap();
            let qb = georef.local_from_strip([ib.x[i], ib.y[i], ib.z[i]]).unwrap();
            let moved_grid = [pb[0] - qb[0], pb[1] - qb[1], pb[2] - qb[2]];
            let moved_local = [a.x[i] - ia.x[i], a.y[i] - ia.y[i], a.z[i] - ia.z[i]];
            let d = (0..3).map(|k| (moved_grid[k] - moved_local[k]).powi(2)).sum::<f64>().sqrt();
            diffs.push(d);
        }
    }
    diffs.sort_by(f64::total_cmp);
    let q = |f: f64| diffs[((diffs.len() - 1) as f64 * f) as usize] * 1e3;
    eprintln!(
        "grid processing vs local frame, difference of the adjustment per point: median {:.3} mm, 95% {:.3} mm, \
         max {:.3} mm ({} points)",
        q(0.5),
        q(0.95),
        q(1.0),
        diffs.len()
    );
}

/// The embedded job framework (SQLite and a local store, as `precimap run` runs) gives the
/// in-process result byte for byte for a field campaign with accuracy files: strips and
/// trajectories in the grid with their CRS, the latent map and QC in the same CRS.
#[test]
fn a_field_campaign_through_the_framework_matches_in_process() {
    let dir = tempfile::tempdir().unwrap();
    let (local, field) = (dir.path().join("local"), dir.path().join("field"));
    let mut config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, 3);
    config.drive.passes = 2;
    precimap_sim::simulate(&config, &local, false).unwrap();
    precimap_sim::field::write_field_campaign(&local, &field, config.origin, false).unwrap();
    let manifest = field.join("manifest.json");
    let reference = dir.path().join("in-process");
    run(&manifest, &reference).unwrap();
    let embedded = dir.path().join("embedded");
    crate::framework::run_embedded_into(&manifest, &embedded);
    crate::framework::assert_same_results(&reference, &embedded);
    // The latent map and the QC plots state the processing CRS, as the strips and trajectories.
    let tile = std::fs::read_dir(reference.join("latent")).unwrap().next().unwrap().unwrap().path();
    let declared = strip_info(&tile).unwrap().crs;
    assert_eq!(declared.as_ref().and_then(|c| c.epsg), Some(32632), "{}: {declared:?}", tile.display());
    // Grid coordinates: back in the frame they lie in their tile (15 m, 0.3 m border), and they
    // are not the frame's own coordinates.
    let georef = load_manifest(&manifest).unwrap().crs.unwrap().georeference().unwrap();
    let key: precimap_core::TileKey = tile.file_stem().unwrap().to_str().unwrap().parse().unwrap();
    let mut moved = 0.0f64;
    for p in precimap_formats::read_latent_map(&tile).unwrap() {
        let l = georef.frame.local_from_grid(p.position).unwrap();
        let (x0, y0) = (f64::from(key.tx) * 15.0, f64::from(key.ty) * 15.0);
        assert!(l.x > x0 - 0.5 && l.x < x0 + 15.5 && l.y > y0 - 0.5 && l.y < y0 + 15.5, "{l:?} outside {key}");
        moved = moved.max((l - precimap_core::Vec3::from(p.position)).norm());
    }
    assert!(moved > 1e-3, "the map is in the grid, {moved} m from the frame");
    let qc = std::fs::read_to_string(reference.join("qc/latent-std-last.svg")).unwrap();
    assert!(qc.contains("processing frame of EPSG:32632 (WGS 84 / UTM zone 32N)"));
}

/// The accuracy files' prior against the campaign's on the same field campaign (seed 3: a GNSS
/// outage on pass v02), both results evaluated in the local frame against the truth as
/// `precimap evaluate` does. Run with `cargo test -p precimap-cli --test system
/// field::the_accuracy -- --nocapture` for the figures.
#[test]
fn the_accuracy_files_prior_does_not_hurt() {
    let dir = tempfile::tempdir().unwrap();
    let (local, field) = (dir.path().join("local"), dir.path().join("field"));
    let config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, 3);
    precimap_sim::simulate(&config, &local, false).unwrap();
    let week = precimap_sim::field::write_field_campaign(&local, &field, config.origin, false).unwrap();
    // The SMRMSG of the outage pass reports its drift.
    let v02 = precimap_formats::sbet::read_smrmsg(&field.join("trajectories/v02.smrmsg")).unwrap();
    let horizontal: Vec<f64> = v02.position_sigma_m.iter().map(|s| s[0].hypot(s[1])).collect();
    let largest = horizontal.iter().copied().fold(0.0, f64::max);
    assert!(largest > 1.4 * horizontal[0], "{largest} vs {}", horizontal[0]);
    let mut figures = Vec::new();
    for (name, manifest) in [("campaign σ", without_accuracy(&field)), ("SMRMSG σ", field.join("manifest.json"))] {
        let out = dir.path().join(format!("out-{}", figures.len()));
        run(&manifest, &out).unwrap();
        let in_local = dir.path().join(format!("local-{}", figures.len()));
        precimap_sim::field::result_to_local(&out, &in_local, config.origin, week).unwrap();
        let e = precimap_eval::evaluate(&local.join("truth"), &in_local).unwrap();
        let d = &e.trajectory_error_without_datum_rms_m;
        let row = [
            e.same_surface_spread_m.after * 1e3,
            e.trajectory_error_rms_m.after * 1e3,
            d.along_track.after * 1e3,
            d.across_track.after * 1e3,
            d.vertical.after * 1e3,
            e.trajectory_rotation_error_rms_deg.after * 1e3,
        ];
        eprintln!(
            "{name}: same-surface spread {:.3} mm, trajectory position RMS {:.2} mm, along/across/vertical w/o the \
             datum {:.3}/{:.3}/{:.3} mm, attitude RMS {:.3} mdeg",
            row[0], row[1], row[2], row[3], row[4], row[5]
        );
        figures.push(row);
    }
    let (campaign, smrmsg) = (figures[0], figures[1]);
    assert_ne!(campaign, smrmsg, "the accuracy files reached the solves");
    for (k, what) in ["same-surface spread", "position", "along", "across", "vertical", "attitude"].iter().enumerate() {
        assert!(
            smrmsg[k] <= 1.05 * campaign[k],
            "{what}: {} with the SMRMSG prior, {} without",
            smrmsg[k],
            campaign[k]
        );
    }
}

/// An accuracy file with a zero σ stops both drivers with an error naming the file as the
/// manifest does and the record.
#[test]
fn a_nonsense_accuracy_file_is_refused_by_both_drivers() {
    let dir = tempfile::tempdir().unwrap();
    let (local, field) = (dir.path().join("local"), dir.path().join("field"));
    let mut config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, 5);
    config.drive.passes = 2;
    precimap_sim::simulate(&config, &local, false).unwrap();
    precimap_sim::field::write_field_campaign(&local, &field, config.origin, false).unwrap();
    let path = field.join("trajectories/v02.smrmsg");
    let mut bytes = std::fs::read(&path).unwrap();
    // Record 3's down σ (field 3 of 10 f64).
    bytes[3 * 80 + 3 * 8..3 * 80 + 4 * 8].copy_from_slice(&0f64.to_le_bytes());
    std::fs::write(&path, bytes).unwrap();
    let manifest = field.join("manifest.json");
    let e = run(&manifest, &dir.path().join("in-process")).unwrap_err().to_string();
    assert!(e.contains("v02.smrmsg") && e.contains("record 3") && e.contains("down σ is 0 m"), "{e}");
    let options =
        precimap_framework::EmbeddedOptions { out_dir: dir.path().join("embedded"), concurrency: 2, keep_state: false };
    let rt = tokio::runtime::Runtime::new().unwrap();
    let e = rt.block_on(precimap_framework::run_embedded(&manifest, &options, |_| {})).unwrap_err().to_string();
    assert!(e.contains("trajectories/v02.smrmsg: record 3") && e.contains("down σ is 0 m"), "{e}");
    assert!(!e.contains("inputs/"), "named as the manifest names it: {e}");
}
