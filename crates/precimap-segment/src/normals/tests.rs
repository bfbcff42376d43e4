use super::*;

#[test]
fn closed_form_eigenvector_of_a_plane_scatter() {
    // Points on the plane z = 0.1·x + 0.2·y, scattered along two directions.
    let mut pts = vec![];
    for i in -3..=3 {
        for j in -3..=3 {
            let (x, y) = (i as f32 * 0.1, j as f32 * 0.07);
            pts.push([x, y, 0.1 * x + 0.2 * y]);
        }
    }
    let n = plane_fit(pts.iter().copied()).unwrap();
    let expect = [-0.1, -0.2, 1.0];
    let len = norm(expect);
    assert!((dot(n, expect).abs() / len - 1.0).abs() < 1e-9, "{n:?}");
    // A line is not a plane.
    let line: Vec<[f32; 3]> = (1..6).map(|i| [i as f32, 2.0 * i as f32, 0.0]).collect();
    assert!(plane_fit(line.iter().copied()).is_none());
    // Eigenvalues of a diagonal matrix.
    let (l0, l1, _, v) = smallest_eigen([3.0, 0.0, 0.0, 1.0, 0.0, 2.0]).unwrap();
    assert!((l0 - 1.0).abs() < 1e-12 && (l1 - 2.0).abs() < 1e-12 && (v[1].abs() - 1.0).abs() < 1e-12);
}

/// Two planes through the centre hold as many neighbours within the tolerance: the pixel's own
/// plane exactly, a plane tilted across a step loosely. MSAC takes the tight one although the
/// loose one is tried first; by the inlier count alone the first one found would win.
#[test]
fn of_two_planes_with_as_many_inliers_msac_takes_the_tighter() {
    let mut cand = Candidates::new();
    let points: [[f32; 3]; 8] = [
        // On both planes (the step's edge line).
        [0.3, 0.0, 0.0],
        [-0.3, 0.0, 0.0],
        // The pixel's own plane z = 0.
        [0.0, -0.3, 0.0],
        [0.3, -0.3, 0.0],
        [-0.3, -0.3, 0.0],
        // Beyond the step: about z = 0.3 y, scattered by up to 6 mm.
        [0.0, 0.3, 0.096],
        [0.3, 0.3, 0.084],
        [-0.3, 0.3, 0.09],
    ];
    for (i, q) in points.iter().enumerate() {
        (cand.x[i], cand.y[i], cand.z[i]) = (q[0], q[1], q[2]);
        cand.len2[i] = q[0] * q[0] + q[1] * q[1] + q[2] * q[2];
        cand.slot[i] = i as u8;
    }
    cand.m = points.len();
    cand.close();
    let tol = 0.02;
    // The tie: both planes hold the centre and five neighbours.
    assert_eq!(cand.inliers_counted([0.0, 0.0, 1.0], tol).1, 6);
    assert_eq!(cand.inliers_counted([0.0, -0.32, 1.0], tol).1, 6);
    let budget = Budget::new();
    // First the tilted plane (two neighbours beyond the step), then the own plane.
    let pairs = [(6, 7), (2, 0)];
    for seed in 0..50 {
        let n = ransac(&cand, tol, seed, 6, &budget, &pairs).expect("a plane");
        let angle = n[2].abs().min(1.0).acos().to_degrees();
        assert!(angle < 0.5, "seed {seed}: normal {n:?} is {angle:.1}° off the pixel's own plane");
    }
}

/// Deterministic uniform numbers in [−0.5, 0.5).
fn uniform(mut seed: u64) -> impl FnMut() -> f64 {
    move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    }
}

#[test]
fn lane_groups_score_as_the_neighbour_by_neighbour_test() {
    let mut uniform = uniform(11);
    let mut rand = move || uniform() as f32;
    for m in 1..=MAX_NEIGHBOURS {
        let mut cand = Candidates::new();
        // Junk everywhere first: what the gathering leaves behind the last kept neighbour.
        for i in 0..MAX_NEIGHBOURS {
            (cand.x[i], cand.y[i], cand.z[i]) = (3.0 * rand(), 3.0 * rand(), 3.0 * rand());
        }
        for i in 0..m {
            cand.z[i] = 0.02 * rand();
        }
        cand.m = m;
        cand.close();
        for trial in 0..20 {
            let n = [0.05 * rand(), 0.05 * rand(), 1.0 + rand()];
            let tol = 0.002 * (1 + trial % 5) as f32;
            let (inliers, cost) = cand.scored(n, tol);
            let (mask, count) = cand.inliers_counted(n, tol);
            assert_eq!(inliers, count, "m {m}, trial {trial}");
            assert_eq!(count, 1 + mask.count_ones());
            let norm2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
            let limit = tol * tol * norm2;
            let expected: f64 = (0..m)
                .map(|i| {
                    let d = n[0] * cand.x[i] + n[1] * cand.y[i] + n[2] * cand.z[i];
                    f64::from((d * d).min(limit))
                })
                .sum::<f64>()
                / f64::from(norm2);
            assert!((f64::from(cost) - expected).abs() <= 1e-5 * expected + 1e-12, "m {m}: {cost} against {expected}");
        }
    }
}

/// The all-inlier shortcut of [`ransac`] sums every neighbour without a mask: the same sums,
/// bit for bit, as the mask with every bit set (the normals must not change with it).
#[test]
fn scatter_of_all_neighbours_equals_the_full_mask() {
    let mut uniform = uniform(5);
    for m in 1..=MAX_NEIGHBOURS {
        let mut cand = Candidates::new();
        for i in 0..m {
            (cand.x[i], cand.y[i], cand.z[i]) = (uniform() as f32, uniform() as f32, 0.01 * uniform() as f32);
        }
        cand.m = m;
        let (all, masked) = (cand.scatter_all(), cand.scatter((1u64 << m) - 1));
        assert_eq!(all.count.to_bits(), masked.count.to_bits(), "m {m}");
        assert_eq!(all.s.map(f64::to_bits), masked.s.map(f64::to_bits), "m {m}");
        assert_eq!(all.ss.map(f64::to_bits), masked.ss.map(f64::to_bits), "m {m}");
    }
}

/// The fit works on the scatter as it is, unscaled: a window of millimetres and one of
/// metres give the same plane and the same planarity verdict.
#[test]
fn plane_fit_does_not_depend_on_the_window_scale() {
    let pts: Vec<[f32; 3]> = (0..15)
        .map(|i| {
            let (a, b) = ((i % 5) as f32 - 2.0, (i / 5) as f32 - 1.0);
            [a, b, 0.1 * a - 0.2 * b + 0.01 * ((i * 7 % 5) as f32 - 2.0)]
        })
        .collect();
    let line: Vec<[f32; 3]> = (1..8).map(|i| [i as f32, 2.0 * i as f32, 0.001 * (i % 2) as f32]).collect();
    let fit = |pts: &[[f32; 3]], scale: f32| {
        let mut sums = Scatter::new();
        for q in pts {
            sums.add(q.map(|v| v * scale));
        }
        sums.plane_from([0.0, 0.0, 1.0])
    };
    let reference = fit(&pts, 1.0).expect("a plane");
    for scale in [1e-3, 1e-2, 10.0, 1e3] {
        let n = fit(&pts, scale).expect("a plane at every scale");
        assert!(dot(n, reference) > 1.0 - 1e-9, "scale {scale}: {n:?} against {reference:?}");
        assert!(fit(&line, scale).is_none(), "scale {scale}: a line is no plane");
    }
}

/// The inverse iteration of the RANSAC refinement lands on the closed-form least-squares
/// normal from a start 20° off, on noisy planar scatters, and rejects lines and blobs as the
/// closed form does.
#[test]
fn inverse_iteration_matches_the_closed_form() {
    let mut rand = uniform(7);
    let mut worst = 0.0f64;
    for trial in 0..200 {
        let true_n = [rand(), rand(), rand() + 1.0];
        let (u, v) = (cross(true_n, [1.0, 0.0, 0.0]), cross(true_n, [0.0, 1.0, 0.0]));
        let (u, v) = (u.map(|x| x / norm(u)), v.map(|x| x / norm(v)));
        let nl = norm(true_n);
        let noise = 0.002 * (1 + trial % 4) as f64;
        let mut sums = Scatter::new();
        let mut pts = vec![];
        for _ in 0..12 {
            let (a, b, e) = (0.3 * rand(), 0.1 * rand(), noise * rand());
            let q = [0, 1, 2].map(|k| (a * u[k] + b * v[k] + e * true_n[k] / nl) as f32);
            sums.add(q);
            pts.push(q);
        }
        let exact = plane_fit(pts.iter().copied());
        // Start 20° off the true normal.
        let tilt = cross(true_n, u).map(|x| x / norm(cross(true_n, u)));
        let (s, c) = 20f64.to_radians().sin_cos();
        let start = [0, 1, 2].map(|k| c * true_n[k] / nl + s * tilt[k]);
        let fast = sums.plane_from(start);
        match (exact, fast) {
            (Some(a), Some(b)) => worst = worst.max(dot(a, b).abs().min(1.0).acos().to_degrees()),
            (a, b) => assert_eq!(a.is_some(), b.is_some(), "trial {trial}"),
        }
    }
    assert!(worst < 0.01, "worst {worst}°");
    // A line and a blob are no planes.
    let mut line = Scatter::new();
    for i in 1..6 {
        line.add([i as f32, 2.0 * i as f32, 0.0]);
    }
    assert!(line.plane_from([0.0, 0.0, 1.0]).is_none());
    let mut blob = Scatter::new();
    for q in [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]] {
        blob.add(q);
    }
    assert!(blob.plane_from([0.0, 0.0, 1.0]).is_none());
}
