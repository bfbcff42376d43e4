use super::*;

/// A straight drive over flat ground scanned by one rotating head: the scan image must have
/// the simulated rows and columns, and normals must point up.
#[test]
fn scan_image_links_and_normals_on_flat_ground() {
    let speed = 10.0;
    let times: Vec<f64> = (0..=400).map(|i| 1000.0 + i as f64 * 0.005).collect();
    let positions = times.iter().map(|t| Vec3::new((t - 1000.0) * speed, 0.0, 2.0)).collect();
    let traj = Trajectory::new(times, positions, vec![[0.0; 3]; 401]).unwrap();
    let rows = 360u32;
    let rate = 50.0;
    let (mut x, mut y, mut z, mut t, mut a) = (vec![], vec![], vec![], vec![], vec![]);
    for rev in 0..60 {
        for j in 0..rows {
            let phi = -180.0 + j as f64 * 360.0 / rows as f64;
            let time = 1000.1 + rev as f64 / rate + j as f64 / (rate * rows as f64);
            let c = (time - 1000.0) * speed;
            // Beam in the y–z plane; only downward beams hit the ground (z = 0).
            let dir = Vec3::new(0.0, phi.to_radians().sin(), phi.to_radians().cos());
            if dir.z > -0.3 {
                continue;
            }
            let s = -2.0 / dir.z;
            x.push(c);
            y.push(dir.y * s);
            z.push(0.0);
            t.push(time);
            a.push(phi as f32);
        }
    }
    let channel = vec![0u8; x.len()];
    let samples = StripSamples { x: &x, y: &y, z: &z, gps_time: &t, scan_angle_deg: &a, channel: &channel, ring: &[] };
    let params = Parameters::default();
    let segment = SegmentParams::default();
    let ctx = StripContext {
        strip: 3,
        trajectory: 1,
        trajectory_data: &traj,
        lever_arm: Vec3::zeros(),
        params: &params,
        segment: &segment,
    };
    let prepared = prepare_strip(&samples, &ctx).unwrap();
    assert_eq!(prepared.stats.rows_per_revolution, rows);
    assert_eq!(prepared.stats.revolutions, 60);
    assert!((prepared.stats.revolution_period_s - 0.02).abs() < 1e-9);
    // Interior points all get upward normals; only the image border loses some. Flat ground
    // is one segment.
    assert!(prepared.stats.points_with_normal as f64 > 0.9 * prepared.stats.points as f64);
    let sizes: Vec<usize> = (0..prepared.stats.segmentation.segments as u32)
        .map(|s| prepared.segment.iter().filter(|&&x| x == s).count())
        .collect();
    assert_eq!(prepared.stats.segmentation.segments, 1, "{sizes:?} {:?}", prepared.stats.segmentation);
    assert!(prepared.segment.iter().filter(|&&s| s == 0).count() as f64 > 0.9 * prepared.stats.points as f64);
    for chunk in &prepared.chunks {
        for nrm in &chunk.normal {
            assert!(nrm[2] > 0.999, "{nrm:?}");
        }
        assert!(chunk.right.iter().filter(|&&r| r != NO_NEIGHBOUR).count() > chunk.len() / 2);
    }
    // The anchor coordinate follows arc length: first point at 1 m → anchor 2.
    assert_eq!(prepared.stats.first_anchor, 2);
}

/// A strip without scan angles (all 0) gets its scan image from the beam directions: with the
/// scan plane turned 30° in the vehicle and the vehicle heading 20°, the image has the same
/// size, the same points get normals and the ground is still one segment.
#[test]
fn strip_without_scan_angles_gets_its_rows_from_the_beam_directions() {
    let speed = 10.0;
    let heading = 20f64.to_radians();
    let times: Vec<f64> = (0..=400).map(|i| 1000.0 + i as f64 * 0.005).collect();
    let positions =
        times.iter().map(|t| Vec3::new(heading.cos(), heading.sin(), 0.0) * ((t - 1000.0) * speed)).collect();
    let traj = Trajectory::new(times, positions, vec![[0.0, 0.0, 20.0]; 401]).unwrap();
    let rows = 300u32;
    let rate = 40.0;
    let turn = 30f64.to_radians();
    let (mut x, mut y, mut z, mut t, mut a) = (vec![], vec![], vec![], vec![], vec![]);
    for rev in 0..50 {
        for j in 0..rows {
            let phi = -180.0 + j as f64 * 360.0 / rows as f64;
            let time = 1000.1 + rev as f64 / rate + j as f64 / (rate * rows as f64);
            let pose = traj.pose_at(time).unwrap();
            let (sp, cp) = phi.to_radians().sin_cos();
            // The plane of (0, sin φ, cos φ) turned about the body's z axis.
            let body = Vec3::new(-turn.sin() * sp, turn.cos() * sp, cp);
            let dir = pose.rotation * body;
            // Only downward beams hit the ground (z = 0); the head is 2 m up.
            if dir.z > -0.3 {
                continue;
            }
            let p = pose.position + dir * (-2.0 / dir.z);
            x.push(p.x);
            y.push(p.y);
            z.push(0.0);
            t.push(time);
            a.push(phi as f32);
        }
    }
    let traj_head = Trajectory::new(
        traj.times().to_vec(),
        traj.positions().iter().map(|p| p + Vec3::new(0.0, 0.0, 2.0)).collect(),
        traj.rpy_deg().to_vec(),
    )
    .unwrap();
    let channel = vec![0u8; x.len()];
    let zeros = vec![0f32; x.len()];
    let params = Parameters::default();
    let segment = SegmentParams::default();
    let ctx = StripContext {
        strip: 0,
        trajectory: 0,
        trajectory_data: &traj_head,
        lever_arm: Vec3::zeros(),
        params: &params,
        segment: &segment,
    };
    let with = StripSamples { x: &x, y: &y, z: &z, gps_time: &t, scan_angle_deg: &a, channel: &channel, ring: &[] };
    let without = StripSamples { scan_angle_deg: &zeros, ..with };
    let known = prepare_strip(&with, &ctx).unwrap();
    let rebuilt = prepare_strip(&without, &ctx).unwrap();
    assert!(!known.stats.scan_angles_reconstructed && rebuilt.stats.scan_angles_reconstructed);
    assert_eq!(known.stats.rows_per_revolution, rows);
    assert_eq!(rebuilt.stats.rows_per_revolution, rows);
    // The simulated angle wraps at the nadir, inside the ground fan; the reconstruction puts
    // the seam in the sky, so its first and last revolutions are halves: one column more.
    assert_eq!(rebuilt.stats.revolutions, known.stats.revolutions + 1);
    assert!(known.stats.points_with_normal as f64 > 0.9 * known.stats.points as f64);
    assert!(rebuilt.stats.points_with_normal as f64 >= 0.99 * known.stats.points_with_normal as f64);
    assert_eq!(rebuilt.stats.segmentation.segments, 1);
    // Same angular steps between consecutive beams; columns advance only at the seam.
    let (known_image, rebuilt_image) = (known.image.as_ref().unwrap(), rebuilt.image.as_ref().unwrap());
    for k in 0..x.len() - 1 {
        let step = |image: &ScanImage| (image.row[k + 1] + rows - image.row[k]) % rows;
        if known_image.column[k + 1] == known_image.column[k] {
            assert_eq!(step(rebuilt_image), step(known_image), "point {k}");
        }
        let advance = rebuilt_image.column[k + 1] - rebuilt_image.column[k];
        assert!(advance <= 1, "point {k}: {advance}");
    }
}

/// Beams that do not lie in one plane are not a rotating scanner's: no angles are made up.
#[test]
fn scattered_beams_give_no_reconstructed_angles() {
    let times: Vec<f64> = (0..=10).map(|i| i as f64 * 0.1).collect();
    let positions = times.iter().map(|t| Vec3::new(*t, 0.0, 0.0)).collect();
    let traj = Trajectory::new(times, positions, vec![[0.0; 3]; 11]).unwrap();
    let mut cursor = GeometryCursor::new(&traj, &Vec3::zeros(), 0.5);
    let (mut x, mut y, mut z, mut t) = (vec![], vec![], vec![], vec![]);
    let mut head = vec![];
    for k in 0..500 {
        let time = k as f64 * 0.001;
        // Directions spread over a sphere (golden-angle spiral).
        let h = 1.0 - 2.0 * (k as f64 + 0.5) / 500.0;
        let r = (1.0 - h * h).sqrt();
        let phi = k as f64 * 2.399_963;
        let p = [time + 5.0 * r * phi.cos(), 5.0 * r * phi.sin(), 5.0 * h];
        head.push(cursor.at(time, p).unwrap().t0);
        x.push(p[0]);
        y.push(p[1]);
        z.push(p[2]);
        t.push(time);
    }
    let zeros = vec![0f32; x.len()];
    let channel = vec![0u8; x.len()];
    let samples =
        StripSamples { x: &x, y: &y, z: &z, gps_time: &t, scan_angle_deg: &zeros, channel: &channel, ring: &[] };
    assert!(scan_angles_missing(&zeros));
    assert!(reconstructed_scan_angles(&head, &samples, &traj).is_none());
}

/// The cursor gives what the full interpolation gives (pose at t, rotation times lever arm,
/// arc length), in time order, backwards, at sample times and at both ends; outside the span
/// nothing.
#[test]
fn geometry_cursor_matches_the_interpolated_pose() {
    let times: Vec<f64> = (0..50).map(|i| 100.0 + i as f64 * 0.01 + (i % 3) as f64 * 0.002).collect();
    let positions = times.iter().map(|t| Vec3::new((t - 100.0) * 12.0, (t * 3.0).sin(), 0.1 * t)).collect();
    // Mostly 0.3° per sample (the series branch), every fifth sample a 3° jump (closed form).
    let rpy = (0..50)
        .map(|i| [(i as f64 * 0.3).sin() * 0.2, i as f64 * 0.05, i as f64 * 0.3 + if i % 5 == 0 { 3.0 } else { 0.0 }])
        .collect();
    let traj = Trajectory::new(times.clone(), positions, rpy).unwrap();
    let lever = Vec3::new(0.8, -0.4, 1.9);
    let mut ts: Vec<f64> = (0..2000).map(|k| 100.0 + k as f64 * 0.000_26).filter(|t| *t <= times[49]).collect();
    ts.extend(times.iter().copied());
    ts.extend([times[49], times[0], 100.2345, 100.0001, times[49]]);
    let mut cursor = GeometryCursor::new(&traj, &lever, 0.5);
    let p = [3.0, 4.0, 5.0];
    for &t in &ts {
        let g = cursor.at(t, p).unwrap();
        let pose = traj.pose_at(t).unwrap();
        let t0 = pose.position + pose.rotation * lever;
        for k in 0..3 {
            assert!((g.t0[k] - t0[k]).abs() < 1e-12, "t {t}: {:?} vs {t0:?}", g.t0);
            assert!((g.r[k] - (p[k] - t0[k])).abs() < 1e-12);
        }
        let u = traj.arc_length_at(t).unwrap() / 0.5;
        assert_eq!(g.anchor, u.floor() as u32, "t {t}");
        assert!((g.lambda as f64 - u.fract()).abs() < 1e-6, "t {t}");
    }
    assert!(cursor.at(times[0] - 1e-9, p).is_none());
    assert!(cursor.at(times[49] + 1e-9, p).is_none());
    assert!(cursor.at(f64::NAN, p).is_none());
    assert!(cursor.at(100.3, p).is_some());
}

#[test]
fn uncovered_and_unordered_points_are_reported() {
    let traj =
        Trajectory::new(vec![0.0, 1.0], vec![Vec3::zeros(), Vec3::new(1.0, 0.0, 0.0)], vec![[0.0; 3]; 2]).unwrap();
    let params = Parameters::default();
    let segment = SegmentParams::default();
    let ctx = StripContext {
        strip: 0,
        trajectory: 0,
        trajectory_data: &traj,
        lever_arm: Vec3::zeros(),
        params: &params,
        segment: &segment,
    };
    let xs = [0.0, 0.0];
    let ch = [0u8, 0];
    let samples = StripSamples {
        x: &xs,
        y: &xs,
        z: &xs,
        gps_time: &[0.5, 2.0],
        scan_angle_deg: &[0.0, 1.0],
        channel: &ch,
        ring: &[],
    };
    assert_eq!(
        prepare_strip(&samples, &ctx).unwrap_err(),
        PrepareError::NotCovered { index: 1, time: 2.0, start: 0.0, end: 1.0 }
    );
    let samples = StripSamples {
        x: &xs,
        y: &xs,
        z: &xs,
        gps_time: &[0.5, 0.4],
        scan_angle_deg: &[0.0, 1.0],
        channel: &ch,
        ring: &[],
    };
    assert!(matches!(prepare_strip(&samples, &ctx).unwrap_err(), PrepareError::NotInOrder { index: 1, .. }));
    let samples = StripSamples {
        x: &[0.0, f64::NAN],
        y: &xs,
        z: &xs,
        gps_time: &[0.5, 0.6],
        scan_angle_deg: &[0.0, 1.0],
        channel: &ch,
        ring: &[],
    };
    assert_eq!(prepare_strip(&samples, &ctx).unwrap_err(), PrepareError::NotFinite { index: 1, field: "x" });
    // A ring image needs ring numbers, one per point.
    let ring_image = Parameters { normals: NormalSource::RingImage, ..Parameters::default() };
    let ctx = StripContext { params: &ring_image, ..ctx };
    let samples = StripSamples { gps_time: &[0.5, 0.6], ..samples };
    let samples = StripSamples { x: &xs, ..samples };
    assert_eq!(prepare_strip(&samples, &ctx).unwrap_err(), PrepareError::NoRing);
    let samples = StripSamples { ring: &[3], ..samples };
    assert!(matches!(prepare_strip(&samples, &ctx).unwrap_err(), PrepareError::Shape(_)));
}

/// A drive over flat ground whose points carry scan angles of no rotating head (pseudo-random):
/// `auto` refuses the scan image and takes the normals from 3-D neighbours; they point up, most
/// points are usable, and the chunks carry mesh links.
#[test]
fn a_strip_without_a_scan_pattern_gets_normals_from_neighbours() {
    let speed = 10.0;
    let times: Vec<f64> = (0..=400).map(|i| 1000.0 + i as f64 * 0.005).collect();
    let positions = times.iter().map(|t| Vec3::new((t - 1000.0) * speed, 0.0, 2.0)).collect();
    let traj = Trajectory::new(times, positions, vec![[0.0; 3]; 401]).unwrap();
    let (mut x, mut y, mut z, mut t, mut a) = (vec![], vec![], vec![], vec![], vec![]);
    let mut state = 99u64;
    let mut rand = move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    for k in 0..40_000 {
        let time = 1000.1 + k as f64 * 1.5 / 40_000.0;
        let c = (time - 1000.0) * speed;
        x.push(c + 0.5 * (rand() - 0.5));
        y.push(8.0 * (rand() - 0.5));
        z.push(0.002 * (rand() - 0.5));
        t.push(time);
        a.push((180.0 * (rand() - 0.5)) as f32);
    }
    let channel = vec![0u8; x.len()];
    let samples = StripSamples { x: &x, y: &y, z: &z, gps_time: &t, scan_angle_deg: &a, channel: &channel, ring: &[] };
    let params = Parameters::default();
    let segment = SegmentParams::default();
    let ctx = StripContext {
        strip: 0,
        trajectory: 0,
        trajectory_data: &traj,
        lever_arm: Vec3::zeros(),
        params: &params,
        segment: &segment,
    };
    let prepared = prepare_strip(&samples, &ctx).unwrap();
    let stats = &prepared.stats;
    assert_eq!(stats.normal_source, NormalSource::Neighbours);
    assert!(stats.scan_image_refused.is_some() && prepared.image.is_none());
    assert!(stats.points_with_normal as f64 > 0.95 * stats.points as f64, "{stats:?}");
    assert!(stats.points_usable as f64 > 0.9 * stats.points as f64, "{stats:?}");
    assert!(usable_share_problem(stats, params.min_usable_share).is_none());
    for chunk in &prepared.chunks {
        for nrm in &chunk.normal {
            assert!(nrm[2] > 0.99, "{nrm:?}");
        }
        let linked = (0..chunk.len()).filter(|&k| chunk.right[k] != NO_NEIGHBOUR && chunk.down[k] != NO_NEIGHBOUR);
        assert!(linked.count() as f64 > 0.8 * chunk.len() as f64);
    }
}

/// The reason a strip is not usable enough is named after what its statistics show.
#[test]
fn usable_share_problems_name_their_reason() {
    let base = PrepareStats {
        points: 1000,
        points_with_normal: 900,
        points_usable: 800,
        time_start: 0.0,
        time_end: 100.0,
        ..Default::default()
    };
    assert!(usable_share_problem(&base, 0.5).is_none());
    assert!(usable_share_problem(&base, 0.9).unwrap().contains("regions under the minimum segment size"));
    let gaps = PrepareStats { points_usable: 10, time_in_gaps_s: 80.0, ..base.clone() };
    assert!(usable_share_problem(&gaps, 0.5).unwrap().contains("time gaps: 80 s of its 100 s"));
    let refused = PrepareStats {
        points_with_normal: 20,
        points_usable: 10,
        scan_image_refused: Some("its scan angles make no scan image".into()),
        ..base.clone()
    };
    let message = usable_share_problem(&refused, 0.5).unwrap();
    assert!(message.contains("scan pattern not recognised") && message.contains("1.0 %"), "{message}");
    let few = PrepareStats { points_with_normal: 20, points_usable: 10, ..base };
    assert!(usable_share_problem(&few, 0.5).unwrap().contains("too few normals: 2.0 %"));
}
