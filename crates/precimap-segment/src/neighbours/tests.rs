use super::*;

/// Deterministic uniform numbers in [0, 1).
fn uniform(mut seed: u64) -> impl FnMut() -> f64 {
    move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    }
}

struct Cloud {
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
    head: Vec<[f64; 3]>,
    time: Vec<f64>,
    /// Which plane each point was drawn on.
    plane: Vec<usize>,
}

impl Cloud {
    fn geo(&self) -> StripGeometry<'_> {
        StripGeometry { x: &self.x, y: &self.y, z: &self.z, head: &self.head }
    }
}

/// Points in no particular order on a sloped ground `z = 0.05 x − 0.02 y` (x, y in 0..8 m) and a
/// wall `y = 6` standing on it (x in 0..8, height 0.5..3 m), with 3 mm of noise, seen from a head
/// at (4, 2, 10) (an airborne-like view: the wall at grazing incidence from above would be
/// missing, so the head stands beside it).
fn ground_and_wall(points: usize, seed: u64) -> Cloud {
    let mut rand = uniform(seed);
    let mut c = Cloud { x: vec![], y: vec![], z: vec![], head: vec![], time: vec![], plane: vec![] };
    for k in 0..points {
        let noise = 0.003 * (rand() - 0.5) * 2.0;
        let (x, y, z, plane) = if k % 3 == 2 {
            let (x, h) = (8.0 * rand(), 0.5 + 2.5 * rand());
            (x, 6.0 + noise, 0.05 * x - 0.12 + h, 1)
        } else {
            let (x, y) = (8.0 * rand(), 5.8 * rand());
            let n: [f64; 3] = [-0.05, 0.02, 1.0];
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            let z = 0.05 * x - 0.02 * y;
            (x + noise * n[0] / len, y + noise * n[1] / len, z + noise / len, 0)
        };
        c.x.push(x);
        c.y.push(y);
        c.z.push(z);
        c.head.push([4.0, 2.0, 3.0]);
        c.time.push(10.0 + 0.1 * rand());
        c.plane.push(plane);
    }
    c
}

fn angle_deg(a: [f32; 3], b: [f64; 3]) -> f64 {
    let a = a.map(f64::from);
    let len = dot(b, b).sqrt();
    (dot(a, b) / len).clamp(-1.0, 1.0).acos().to_degrees()
}

#[test]
fn unordered_points_get_their_planes_normals_and_one_segment_per_plane() {
    let cloud = ground_and_wall(30_000, 3);
    let params = SegmentParams::default();
    let out = segment_unordered(&cloud.geo(), &cloud.time, &params);
    let truth = [[-0.05, 0.02, 1.0], [0.0, -1.0, 0.0]];
    let (mut with, mut worst_share) = ([0usize; 2], [0usize; 2]);
    let mut count = [0usize; 2];
    for (k, n) in out.segmentation.normals.iter().enumerate() {
        let plane = cloud.plane[k];
        count[plane] += 1;
        let Some(n) = n else { continue };
        with[plane] += 1;
        // Facing the head: the ground up, the wall towards −y.
        let angle = angle_deg(n.normal, truth[plane]);
        if angle > 3.0 {
            worst_share[plane] += 1;
        }
    }
    for p in 0..2 {
        assert!(with[p] as f64 > 0.95 * count[p] as f64, "plane {p}: {} of {} with a normal", with[p], count[p]);
        // Only points near the crease may tilt.
        assert!((worst_share[p] as f64) < 0.05 * with[p] as f64, "plane {p}: {} normals over 3° off", worst_share[p]);
    }
    // The two planes are two segments, each nearly pure and nearly whole.
    let seg = &out.segmentation.segment;
    for p in 0..2 {
        let mut votes = std::collections::BTreeMap::new();
        for k in (0..seg.len()).filter(|&k| cloud.plane[k] == p && seg[k] < crate::DROPPED_SEGMENT) {
            *votes.entry(seg[k]).or_insert(0usize) += 1;
        }
        let (&main, &size) = votes.iter().max_by_key(|(_, c)| **c).expect("a segment");
        assert!(size as f64 > 0.9 * count[p] as f64, "plane {p}: largest segment {size} of {}", count[p]);
        let foreign = (0..seg.len()).filter(|&k| seg[k] == main && cloud.plane[k] != p).count();
        assert!((foreign as f64) < 0.01 * size as f64, "plane {p}: {foreign} points of the other plane");
    }
    // Nearly every point has both tangent links, and they are near neighbours on its own plane.
    let linked = out.links.iter().filter(|l| l[0] != NO_POINT && l[1] != NO_POINT).count();
    assert!(linked as f64 > 0.9 * seg.len() as f64, "{linked} linked");
    for (k, l) in out.links.iter().enumerate() {
        for &j in l.iter().filter(|&&j| j != NO_POINT) {
            assert!(dist(cloud.geo().point(k), cloud.geo().point(j as usize)) < 0.5);
        }
    }
    assert!(out.voxel_m > 0.01 && out.voxel_m < 1.0, "{}", out.voxel_m);
}

/// The same place seen twice, a minute apart and 10 cm apart in height (a strip that drives the
/// same road again): neighbours never join the two views, so neither normals nor segments mix.
#[test]
fn neighbours_stay_within_one_pass() {
    let mut rand = uniform(9);
    let mut c = Cloud { x: vec![], y: vec![], z: vec![], head: vec![], time: vec![], plane: vec![] };
    for k in 0..8000 {
        let pass = k % 2;
        c.x.push(5.0 * rand());
        c.y.push(5.0 * rand());
        c.z.push(0.1 * pass as f64 + 0.002 * rand());
        c.head.push([2.5, 2.5, 2.0]);
        c.time.push(100.0 + 60.0 * pass as f64 + 0.5 * rand());
        c.plane.push(pass);
    }
    let out = segment_unordered(&c.geo(), &c.time, &SegmentParams::default());
    let seg = &out.segmentation.segment;
    let mut pass_of_segment = std::collections::BTreeMap::new();
    for k in 0..seg.len() {
        for &j in out.links[k].iter().filter(|&&j| j != NO_POINT) {
            assert_eq!(c.plane[j as usize], c.plane[k], "point {k} linked across passes");
        }
        if seg[k] < crate::DROPPED_SEGMENT {
            let pass = *pass_of_segment.entry(seg[k]).or_insert(c.plane[k]);
            assert_eq!(pass, c.plane[k], "segment {} holds both passes", seg[k]);
        }
    }
    let segmented = seg.iter().filter(|&&s| s < crate::DROPPED_SEGMENT).count();
    assert!(segmented as f64 > 0.95 * seg.len() as f64, "{segmented}");
    assert!(out.segmentation.stats.segments >= 2);
}

/// Noise without any surface (a volume of points, like foliage) forms no segments: its normals,
/// where the fit finds a thin slab, disagree from point to point.
#[test]
fn a_volume_of_scattered_points_forms_no_segments() {
    let mut rand = uniform(4);
    let mut c = Cloud { x: vec![], y: vec![], z: vec![], head: vec![], time: vec![], plane: vec![] };
    for _ in 0..5000 {
        c.x.push(2.0 * rand());
        c.y.push(2.0 * rand());
        c.z.push(2.0 * rand());
        c.head.push([1.0, 1.0, 10.0]);
        c.time.push(0.0);
        c.plane.push(0);
    }
    let out = segment_unordered(&c.geo(), &c.time, &SegmentParams::default());
    let segmented = out.segmentation.stats.points_segmented;
    assert!((segmented as f64) < 0.1 * c.x.len() as f64, "{segmented} of {} scattered points segmented", c.x.len());
}

#[test]
fn tangent_frames_are_orthonormal() {
    for n in [[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [0.6, 0.0, 0.8], [0.3, 0.4, -0.866]] {
        let len = dot(n, n).sqrt();
        let n = n.map(|v| v / len);
        let (a, b) = tangent_frame(n);
        for (u, v) in [(a, a), (b, b)] {
            assert!((dot(u, v) - 1.0).abs() < 1e-12);
        }
        for (u, v) in [(a, b), (a, n), (b, n)] {
            assert!(dot(u, v).abs() < 1e-12);
        }
    }
}
