//! End-to-end checks of a tiny simulated campaign, read back through the public formats only.

use precimap_core::{Mat3, Trajectory, Vec3};
use precimap_formats::{load_manifest, read_strip, read_trajectory_csv};
use precimap_sim::{simulate, Scale, SimConfig, SimError, Town, TruthReader};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(p.strip_prefix(dir).unwrap().to_path_buf(), std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

/// Body-frame direction of scan angle `phi` for a head at `azimuth` (the simulator's convention).
fn body_direction(phi_deg: f64, azimuth_deg: f64) -> Vec3 {
    let (s, c) = phi_deg.to_radians().sin_cos();
    let a = azimuth_deg.to_radians();
    Vec3::new(s * a.cos(), s * a.sin(), -c)
}

#[test]
fn tiny_campaign_is_consistent() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = SimConfig::for_scale(Scale::Tiny, 7);
    let summary = simulate(&cfg, dir.path(), false).unwrap();
    assert!(summary.points > 100_000 && summary.points < 300_000, "tiny has {} points", summary.points);
    assert_eq!((summary.strips, summary.trajectories), (4, 2));

    // Manifest: valid for the formats crate, relative URIs, DESIGN's lever arms, default parameters.
    let manifest = load_manifest(&dir.path().join("manifest.json")).unwrap();
    assert_eq!(manifest.scanners["left"].lever_arm_m, [-0.6, 0.35, 0.45]);
    assert_eq!(manifest.scanners["right"].lever_arm_m, [-0.6, -0.35, 0.45]);
    let ids: Vec<_> = manifest.strips.iter().map(|s| s.id.as_str()).collect();
    assert_eq!(ids, ["v01-left", "v01-right", "v02-left", "v02-right"]);
    assert_eq!(manifest.trajectories[1].uri, "trajectories/v02.csv");
    assert_eq!(manifest.parameters, precimap_core::Parameters::default());
    let raw: Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join("manifest.json")).unwrap()).unwrap();
    assert!(raw.get("parameters").is_none());

    let truth: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("truth/truth.json")).unwrap()).unwrap();
    let cfg_back: SimConfig = serde_json::from_value(truth["config"].clone()).unwrap();
    assert_eq!(cfg_back, cfg);
    assert_eq!(truth["seed"], 7);
    let sigma = truth["range_noise_sigma_m"].as_f64().unwrap();
    assert_eq!(sigma, 0.005);
    let town = Town::build(&cfg.town, cfg.seed);
    let origin = Vec3::from(cfg.origin);

    let mut class_counts: BTreeMap<&str, u64> = BTreeMap::new();
    let mut total = 0u64;
    let mut trajectories: BTreeMap<String, (Trajectory, Trajectory)> = BTreeMap::new();
    for t in &manifest.trajectories {
        let measured = read_trajectory_csv(&dir.path().join(&t.uri)).unwrap();
        let true_ = read_trajectory_csv(&dir.path().join(format!("truth/trajectories/{}.csv", t.id))).unwrap();
        assert_eq!(measured.times(), true_.times());
        assert!(measured.times().windows(2).all(|w| (w[1] - w[0] - 0.005).abs() < 1e-6), "not 200 Hz");
        assert!(measured.times()[0] >= 4.0e8);
        trajectories.insert(t.id.clone(), (true_, measured));
    }

    for (k, strip) in manifest.strips.iter().enumerate() {
        let (true_traj, meas_traj) = &trajectories[&strip.trajectory];
        let pts = read_strip(&dir.path().join(&strip.uri)).unwrap();
        let truths =
            TruthReader::open(&dir.path().join(format!("truth/{}.truth", strip.id))).unwrap().read_all().unwrap();
        assert_eq!(pts.len(), truths.len(), "{}", strip.id);
        let head_left = strip.scanner == "left";
        let lever = Vec3::from(manifest.scanners[&strip.scanner].lever_arm_m);
        let azimuth = if head_left { cfg.scanner.azimuth_deg } else { -cfg.scanner.azimuth_deg };
        let n_rev = cfg.scanner.points_per_revolution as f64;
        let mut range_diff = Vec::with_capacity(pts.len());
        let mut back_err = Vec::with_capacity(pts.len());
        let mut error_effect = Vec::with_capacity(pts.len());
        for (i, tp) in truths.iter().enumerate() {
            let t = pts.gps_time[i];
            if i > 0 {
                assert!(t > pts.gps_time[i - 1], "{}: GPS time not increasing at {i}", strip.id);
            }
            assert!(true_traj.covers(t) && meas_traj.covers(t), "{}: trajectory does not cover {t}", strip.id);
            assert_eq!(pts.channel[i], if head_left { 0 } else { 1 });
            let phi = pts.scan_angle_deg[i] as f64;
            let j = (phi + 180.0) * n_rev / 360.0;
            assert!((j - j.round()).abs() < 1e-3 && (-180.0..180.0).contains(&phi), "scan angle {phi}");
            // The f32 read back carries ~1e-6° of rounding; the row of the scan image is exact.
            let phi = -180.0 + j.round() * 360.0 / n_rev;

            let p_true = Vec3::from(tp.position);
            let p_rec = Vec3::new(pts.x[i], pts.y[i], pts.z[i]);
            let pt = true_traj.pose_at(t).unwrap();
            let pm = meas_traj.pose_at(t).unwrap();
            let o_true = pt.position + pt.rotation * lever;
            let o_meas = pm.position + pm.rotation * lever;
            let r_true = p_true - o_true;
            let r_meas = p_rec - o_meas;
            let rho = r_true.norm();
            assert!(rho >= cfg.scanner.min_range_m - 1e-9 && rho <= cfg.scanner.max_range_m + 1e-9);
            // The measurement direction is the scan angle's, in the body frame of either pose.
            let d = body_direction(phi, azimuth);
            assert!((pt.rotation.transpose() * r_true / rho - d).norm() < 1e-9, "{}: true ray off at {i}", strip.id);
            assert!((pm.rotation.transpose() * r_meas / r_meas.norm() - d).norm() < 2e-4, "recorded ray off at {i}");
            range_diff.push(r_meas.norm() - rho);
            // The exact inverse pose correction maps the recorded point back onto the truth.
            let correction: Mat3 = pt.rotation * pm.rotation.transpose();
            let back = o_true + correction * r_meas;
            back_err.push((back - p_true).norm());
            error_effect.push((p_rec - p_true).norm());

            // The true point lies on its surface; normals are unit and face the scanner.
            let s = town.surface(tp.surface_id).unwrap();
            assert_eq!(s.class, tp.class);
            let local = p_true - origin;
            let c = town.check_surface(tp.surface_id, [local.x, local.y, local.z], 1e-6).unwrap();
            let n = Vec3::new(tp.normal[0] as f64, tp.normal[1] as f64, tp.normal[2] as f64);
            assert!((n.norm() - 1.0).abs() < 1e-6);
            if tp.class.is_surface() {
                assert!(c.distance.abs() < 1e-6 && c.within_bounds, "{}: point {i} off its surface: {c:?}", strip.id);
                assert!(n.dot(&r_true) < 0.0, "{}: normal of point {i} faces away from the scanner", strip.id);
            } else {
                assert!(c.within_bounds, "{}: foliage point {i} outside its crown", strip.id);
            }
            *class_counts.entry(tp.class.name()).or_default() += 1;
        }
        total += pts.len() as u64;
        // Range noise: σ as configured, nothing else between the two georeferencings.
        let s = rms(&range_diff);
        assert!((s - sigma).abs() < 0.05 * sigma, "{}: range noise RMS {s}", strip.id);
        let worst = back_err.iter().copied().fold(0.0, f64::max);
        assert!(worst < 5.5 * sigma + 2e-4, "{}: inverse correction leaves {worst} m", strip.id);
        assert!((rms(&back_err) - sigma).abs() < 0.05 * sigma);
        // ...while the pose errors move points by decimetres.
        let moved = rms(&error_effect);
        assert!(moved > 0.05 && moved < 1.0, "{}: pose errors move points by {moved} m RMS", strip.id);
        assert_eq!(truth["strips"][k]["points"], pts.len() as u64);
        assert_eq!(truth["strips"][k]["point_source_id"], k as u64 + 1);
        // The attributes read_strip does not return, through the las crate.
        let mut reader = las::Reader::from_path(dir.path().join(&strip.uri)).unwrap();
        assert_eq!(reader.header().point_format().to_u8().unwrap(), 6);
        let data = reader.read_points(5000).unwrap();
        assert!(data.point_source_id().all(|id| id == k as u16 + 1));
        assert!(data.return_number().zip(data.number_of_returns()).all(|r| r == (1, 1)));
        let intensities: std::collections::HashSet<u16> = data.intensity().collect();
        assert!(!intensities.contains(&0));
        assert!(intensities.len() > 1000, "intensity hardly varies");
    }
    assert_eq!(total, summary.points);

    // Classes: everything a street has; foliage is present but clutter, not the scene.
    for class in ["road", "sidewalk", "curb", "facade", "pole", "car", "foliage"] {
        assert!(class_counts.get(class).copied().unwrap_or(0) > 0, "no {class} points: {class_counts:?}");
        assert_eq!(truth["points_per_class"][class], class_counts[class]);
    }
    let foliage = class_counts["foliage"] as f64 / total as f64;
    assert!(foliage < 0.1, "foliage is {:.1} % of the points", 100.0 * foliage);
    assert!(class_counts["facade"] > class_counts["pole"]);

    check_trajectory_errors(&truth, &trajectories);
    check_stop_and_outage(&truth, &trajectories);
}

/// Trajectory errors: the measured CSV differs from the truth by the error processes, whose
/// statistics truth.json reports.
fn check_trajectory_errors(truth: &Value, trajectories: &BTreeMap<String, (Trajectory, Trajectory)>) {
    for (k, (id, (true_, meas))) in trajectories.iter().enumerate() {
        let stats = &truth["trajectories"][k]["errors"];
        assert_eq!(truth["trajectories"][k]["id"], id.as_str());
        for axis in 0..3 {
            let d: Vec<f64> =
                (0..true_.len()).map(|i| meas.positions()[i][axis] - true_.positions()[i][axis]).collect();
            let reported = stats["rms_position_m"][axis].as_f64().unwrap();
            assert!((rms(&d) - reported).abs() < 1e-6, "{id} axis {axis}: {} vs {reported}", rms(&d));
            let s = stats["sigma_position_m"][axis].as_f64().unwrap();
            assert!((0.1..=0.3).contains(&s), "{id}: σ_pos {s}");
            let a: Vec<f64> = (0..true_.len())
                .map(|i| precimap_core::geom::wrap_deg(meas.rpy_deg()[i][axis] - true_.rpy_deg()[i][axis]))
                .collect();
            let reported = stats["rms_attitude_deg"][axis].as_f64().unwrap();
            assert!((rms(&a) - reported).abs() < 1e-9);
            let (lo, hi) = if axis < 2 { (0.005, 0.015) } else { (0.01, 0.03) };
            let s = stats["sigma_attitude_deg"][axis].as_f64().unwrap();
            assert!((lo..=hi).contains(&s), "{id}: σ_att[{axis}] {s}");
        }
    }
}

/// The stop: the vehicle stands ~5 s and its error (ZUPT) barely moves; the outage lasts 15–20 s.
fn check_stop_and_outage(truth: &Value, trajectories: &BTreeMap<String, (Trajectory, Trajectory)>) {
    let stop = &truth["stop"];
    let (t0, t1) = (stop["start"].as_f64().unwrap(), stop["end"].as_f64().unwrap());
    assert!((t1 - t0 - 5.0).abs() < 1e-6);
    let (true_, meas) = &trajectories[stop["trajectory"].as_str().unwrap()];
    let a = true_.pose_at(t0 + 0.1).unwrap();
    let b = true_.pose_at(t1 - 0.1).unwrap();
    assert!((a.position - b.position).norm() < 1e-9, "the vehicle moves while stopped");
    let ea = meas.pose_at(t0 + 0.1).unwrap().position - a.position;
    let eb = meas.pose_at(t1 - 0.1).unwrap().position - b.position;
    // Compared with the largest change over any 5 s of the pass, the standing error is frozen.
    let err = |i: usize| meas.positions()[i] - true_.positions()[i];
    let max_5s = (0..true_.len() - 1000).step_by(20).map(|i| (err(i + 1000) - err(i)).norm()).fold(0.0, f64::max);
    let standing = (ea - eb).norm();
    assert!(
        standing < 0.15 * max_5s && standing < 0.03,
        "error drifts {standing} m during the stop ({max_5s} m per 5 s)"
    );
    let outage = &truth["outage"];
    let dur = outage["end"].as_f64().unwrap() - outage["start"].as_f64().unwrap();
    assert!((15.0..=20.0).contains(&dur));
    assert_ne!(outage["trajectory"], stop["trajectory"]);
}

#[test]
fn deterministic_for_a_seed_whatever_the_threads() {
    let cfg = SimConfig::for_scale(Scale::Tiny, 11);
    let (a, b, c) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let three = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
    one.install(|| simulate(&cfg, a.path(), false)).unwrap();
    three.install(|| simulate(&cfg, b.path(), false)).unwrap();
    let (fa, fb) = (files(a.path()), files(b.path()));
    assert_eq!(fa.keys().collect::<Vec<_>>(), fb.keys().collect::<Vec<_>>());
    // manifest, 4 strips, 2 trajectories, 4 truth files, 2 true trajectories, truth.json
    assert_eq!(fa.len(), 14, "{:?}", fa.keys());
    for (name, bytes) in &fa {
        assert!(bytes == &fb[name], "{} differs between runs", name.display());
    }
    // Another seed: another town, other errors, other points.
    simulate(&SimConfig::for_scale(Scale::Tiny, 12), c.path(), false).unwrap();
    let fc = files(c.path());
    for name in ["strips/v01-left.las", "trajectories/v01.csv", "truth/v01-left.truth"] {
        assert_ne!(fa[Path::new(name)], fc[Path::new(name)], "{name} does not depend on the seed");
    }
}

/// Ground control changes nothing but the manifest's `control` and truth.json's `control` (and
/// the config it echoes): every strip, trajectory and truth file is byte for byte the same. The
/// strips see every target: points of each of its surfaces lie within 0.5 m of it.
#[test]
fn control_targets_are_seen_and_disturb_nothing_else() {
    let plain = SimConfig::for_scale(Scale::Tiny, 7);
    let mut cfg = plain.clone();
    cfg.control = Some(precimap_sim::ControlConfig { spacing_m: 40.0, ..Default::default() });
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    simulate(&plain, a.path(), false).unwrap();
    let summary = simulate(&cfg, b.path(), false).unwrap();
    let (fa, fb) = (files(a.path()), files(b.path()));
    assert_eq!(fa.keys().collect::<Vec<_>>(), fb.keys().collect::<Vec<_>>());
    let json = |bytes: &[u8]| serde_json::from_slice::<Value>(bytes).unwrap();
    for (name, bytes) in &fa {
        match name.to_str().unwrap() {
            "manifest.json" => {
                let (x, mut y) = (json(bytes), json(&fb[name]));
                assert!(x.get("control").is_none());
                assert!(y.as_object_mut().unwrap().remove("control").is_some());
                assert_eq!(x, y);
            }
            "truth/truth.json" => {
                let (x, mut y) = (json(bytes), json(&fb[name]));
                assert!(x.get("control").is_none() && x["config"].get("control").is_none());
                assert!(y.as_object_mut().unwrap().remove("control").is_some());
                assert!(y["config"].as_object_mut().unwrap().remove("control").is_some());
                assert_eq!(x, y);
            }
            _ => assert!(bytes == &fb[name], "{} differs with control", name.display()),
        }
    }

    let manifest = load_manifest(&b.path().join("manifest.json")).unwrap();
    let control = manifest.control.unwrap();
    let truth = json(&fb[Path::new("truth/truth.json")]);
    let targets = truth["control"].as_array().unwrap();
    assert_eq!(targets.len(), control.targets.len());
    let c = summary.control_targets;
    assert!(c.control_road >= 2 && c.control_facade >= 2 && c.check_road >= 1 && c.check_facade >= 1, "{c:?}");
    for ((t, counts), spec) in targets.iter().zip(points_on_target_surfaces(b.path(), &truth)).zip(&control.targets) {
        assert_eq!(t["id"], spec.id.as_str());
        // Tiny's 3.6° scan step leaves a few points per face within 0.5 m (2–12 on seed 7).
        assert!(counts.iter().all(|&n| n >= 1), "{}: points on its surfaces within 0.5 m: {counts:?}", t["id"]);
        assert_eq!(spec.position_m, vec3(&t["surveyed_m"]));
    }
}

fn vec3(v: &Value) -> [f64; 3] {
    [0, 1, 2].map(|k| v[k].as_f64().unwrap())
}

/// Per target of `truth.json` (`truth`) of the campaign in `dir`, per surface it lies on: the
/// true points of every strip within 0.5 m of it on that surface's plane, facing its way.
fn points_on_target_surfaces(dir: &Path, truth: &Value) -> Vec<Vec<u64>> {
    let targets = truth["control"].as_array().unwrap();
    let mut seen: Vec<Vec<u64>> = targets.iter().map(|t| vec![0; t["surfaces"].as_array().unwrap().len()]).collect();
    for strip in truth["strips"].as_array().unwrap() {
        let path = dir.join(strip["truth_uri"].as_str().unwrap());
        for tp in TruthReader::open(&path).unwrap().read_all().unwrap() {
            for (t, counts) in targets.iter().zip(&mut seen) {
                let p = vec3(&t["position_m"]);
                let d = [0, 1, 2].map(|k| tp.position[k] - p[k]);
                if d.iter().map(|x| x * x).sum::<f64>() > 0.25 {
                    continue;
                }
                for (count, s) in counts.iter_mut().zip(t["surfaces"].as_array().unwrap()) {
                    let n = vec3(&s["normal"]);
                    let along = (0..3).map(|k| d[k] * n[k]).sum::<f64>();
                    let aligned = (0..3).map(|k| tp.normal[k] as f64 * n[k]).sum::<f64>();
                    if along.abs() < 1e-6 && aligned > 0.999 {
                        *count += 1;
                    }
                }
            }
        }
    }
    seen
}

#[test]
fn laz_output_reads_back_identically() {
    let mut cfg = SimConfig::for_scale(Scale::Tiny, 3);
    cfg.drive.passes = 1;
    cfg.errors.outage_pass = None;
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    simulate(&cfg, a.path(), false).unwrap();
    simulate(&cfg, b.path(), true).unwrap();
    let las = read_strip(&a.path().join("strips/v01-right.las")).unwrap();
    let laz = read_strip(&b.path().join("strips/v01-right.laz")).unwrap();
    assert_eq!(las, laz);
    let m = load_manifest(&b.path().join("manifest.json")).unwrap();
    assert_eq!(m.strips[1].uri, "strips/v01-right.laz");
}

#[test]
fn invalid_config_is_rejected_with_every_problem() {
    let mut cfg = SimConfig::for_scale(Scale::Tiny, 1);
    cfg.drive.passes = 0;
    cfg.scanner.revolutions_per_s = -1.0;
    let dir = tempfile::tempdir().unwrap();
    let e = simulate(&cfg, dir.path(), false).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, SimError::Config(ref p) if p.len() >= 2), "{msg}");
    assert!(msg.contains("passes") && msg.contains("revolutions_per_s"), "{msg}");
}

/// Throughput figure: `cargo test --release -p precimap-sim --test tiny -- --ignored --nocapture`.
#[test]
#[ignore]
fn small_throughput() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = SimConfig::for_scale(Scale::Small, 1);
    let s = simulate(&cfg, dir.path(), false).unwrap();
    println!(
        "small: {} points ({} shots) in {:.2} s wall = {:.2} M points/s on {} threads",
        s.points,
        s.measurements,
        s.wall_seconds,
        s.points as f64 / s.wall_seconds / 1e6,
        rayon::current_num_threads()
    );
    assert!(s.points > 2_000_000 && s.points < 5_000_000);
}

/// Ground control on the small campaign, how many true points lie on each target's surfaces
/// within 0.5 m: `cargo test --release -p precimap-sim --test tiny -- --ignored --nocapture`.
#[test]
#[ignore]
fn small_control_targets() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = SimConfig::for_scale(Scale::Small, 1);
    cfg.control = Some(precimap_sim::ControlConfig::default());
    let s = simulate(&cfg, dir.path(), false).unwrap();
    println!("small, spacing 150 m: {:?}", s.control_targets);
    let truth: Value = serde_json::from_slice(&std::fs::read(dir.path().join("truth/truth.json")).unwrap()).unwrap();
    for (t, counts) in truth["control"].as_array().unwrap().iter().zip(points_on_target_surfaces(dir.path(), &truth)) {
        println!("{} {} at {:.0} m: points per surface within 0.5 m {counts:?}", t["id"], t["kind"], t["station_m"]);
    }
}
