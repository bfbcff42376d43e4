//! A synthetic street scanned by one rotating head: cambered road, curbs, sidewalks, façades and
//! a tree crown, extruded along the driving direction.

use super::*;

/// Surface ids of the synthetic profile.
const ROAD: u32 = 0;
const FOLIAGE: u32 = 99;

struct Scan {
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
    head: Vec<[f64; 3]>,
    angle: Vec<f32>,
    time: Vec<f64>,
    truth: Vec<u32>,
    /// True normal (for the surface points).
    normal: Vec<[f64; 3]>,
}

/// Profile polyline in (y, z) with a surface id per piece.
fn profile() -> Vec<([f64; 2], [f64; 2], u32)> {
    let road = |y: f64| -0.01 * y * y;
    let mut out = vec![];
    for i in 0..12 {
        let (y0, y1) = (-3.0 + i as f64 * 0.5, -2.5 + i as f64 * 0.5);
        out.push(([y0, road(y0)], [y1, road(y1)], ROAD));
    }
    for (s, id) in [(-1.0, 1u32), (1.0, 2)] {
        out.push(([3.0 * s, road(3.0)], [3.0 * s, 0.15], id));
        out.push(([3.0 * s, 0.15], [8.0 * s, 0.15], id + 2));
        out.push(([8.0 * s, 0.15], [8.0 * s, 12.0], id + 4));
    }
    out
}

fn scan(revolutions: usize) -> Scan {
    scan_rows(revolutions, 360)
}

/// [`scan`] with `rows` measurements per revolution.
fn scan_rows(revolutions: usize, rows: usize) -> Scan {
    let pieces = profile();
    let mut s = Scan {
        x: vec![],
        y: vec![],
        z: vec![],
        head: vec![],
        angle: vec![],
        time: vec![],
        truth: vec![],
        normal: vec![],
    };
    let mut seed = 5u64;
    let mut rand = move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    for rev in 0..revolutions {
        for j in 0..rows {
            let phi = -180.0 + j as f64 * 360.0 / rows as f64;
            let t = rev as f64 * 0.01 + j as f64 * 0.01 / rows as f64;
            let hx = t * 8.0;
            let head = [hx, 0.0, 2.0];
            let dir = [phi.to_radians().sin(), -phi.to_radians().cos()];
            // Tree crown on the left, in front of the façade, for a stretch of the drive.
            let crown = (60..120).contains(&rev) && (-75.0..-55.0).contains(&phi);
            let (hit, id, nrm) = if crown && rand() < 0.8 {
                let range = 4.0 + 1.5 * rand();
                ([dir[0] * range, 2.0 + dir[1] * range], FOLIAGE, [0.0, 0.0])
            } else {
                let mut best: Option<(f64, [f64; 2], u32, [f64; 2])> = None;
                for &(a, b, id) in &pieces {
                    // Solve head + ρ·dir = a + u·(b − a).
                    let e = [b[0] - a[0], b[1] - a[1]];
                    let det = dir[0] * -e[1] + e[0] * dir[1];
                    if det.abs() < 1e-12 {
                        continue;
                    }
                    let rhs = [a[0] - 0.0, a[1] - 2.0];
                    let rho = (rhs[0] * -e[1] + e[0] * rhs[1]) / det;
                    let u = (dir[0] * rhs[1] - dir[1] * rhs[0]) / det;
                    if rho > 0.5 && (0.0..=1.0).contains(&u) && best.is_none_or(|b| rho < b.0) {
                        let len = (e[0] * e[0] + e[1] * e[1]).sqrt();
                        let mut n = [-e[1] / len, e[0] / len];
                        if n[0] * dir[0] + n[1] * dir[1] > 0.0 {
                            n = [-n[0], -n[1]];
                        }
                        best = Some((rho, [dir[0] * rho, 2.0 + dir[1] * rho], id, n));
                    }
                }
                match best {
                    Some((rho, _, id, n)) if rho < 30.0 => {
                        let rho = rho + 0.003 * (rand() - 0.5) * 2.0;
                        ([dir[0] * rho, 2.0 + dir[1] * rho], id, n)
                    }
                    _ => continue,
                }
            };
            s.x.push(hx);
            s.y.push(hit[0]);
            s.z.push(hit[1]);
            s.head.push(head);
            s.angle.push(phi as f32);
            s.time.push(t);
            s.truth.push(id);
            s.normal.push([0.0, nrm[0], nrm[1]]);
        }
    }
    s
}

fn angle_deg(a: [f32; 3], b: [f64; 3]) -> f64 {
    let c = a[0] as f64 * b[0] + a[1] as f64 * b[1] + a[2] as f64 * b[2];
    c.clamp(-1.0, 1.0).acos().to_degrees()
}

#[test]
fn street_segments_are_pure_and_foliage_goes() {
    let s = scan(200);
    let geo = StripGeometry { x: &s.x, y: &s.y, z: &s.z, head: &s.head };
    let mut image = ScanImage::build(&s.angle, &s.time, &vec![0; s.x.len()]);
    assert_eq!(image.rows, 360);
    image.thin_standstill(&s.head, 0.03);
    let seg = segment_strip(&geo, &image, &SegmentParams::default());
    // Purity: share of each segment's points on its dominant true surface.
    let mut counts: std::collections::BTreeMap<u32, std::collections::BTreeMap<u32, u64>> = Default::default();
    for (k, &id) in seg.segment.iter().enumerate() {
        if id != NO_SEGMENT {
            *counts.entry(id).or_default().entry(s.truth[k]).or_default() += 1;
        }
    }
    let total: u64 = counts.values().flat_map(|m| m.values()).sum();
    let dominant: u64 = counts.values().map(|m| m.values().max().copied().unwrap_or(0)).sum();
    let purity = dominant as f64 / total as f64;
    assert!(purity > 0.98, "purity {purity}");
    // The cambered road is one segment (its largest holds nearly all road points).
    let road_total = s.truth.iter().filter(|&&t| t == ROAD).count() as f64;
    let road_best = counts.values().map(|m| m.get(&ROAD).copied().unwrap_or(0)).max().unwrap_or(0) as f64;
    assert!(road_best > 0.9 * road_total, "largest road segment {road_best} of {road_total}");
    // Foliage removed, surfaces kept.
    let share_removed = |pred: &dyn Fn(u32) -> bool| {
        let all: Vec<usize> = (0..s.truth.len()).filter(|&k| pred(s.truth[k])).collect();
        all.iter().filter(|&&k| seg.segment[k] == NO_SEGMENT).count() as f64 / all.len() as f64
    };
    let foliage_removed = share_removed(&|t| t == FOLIAGE);
    let surface_removed = share_removed(&|t| t != FOLIAGE);
    assert!(foliage_removed > 0.8, "foliage removed {foliage_removed}");
    assert!(surface_removed < 0.05, "surface removed {surface_removed}");
    assert!(seg.stats.segments < 30, "{:?}", seg.stats);
}

/// Road points next to the curb: RANSAC keeps the road normal, a least-squares fit over the
/// window tilts towards the curb face.
#[test]
fn ransac_keeps_curb_edges_sharp() {
    let s = scan(60);
    let geo = StripGeometry { x: &s.x, y: &s.y, z: &s.z, head: &s.head };
    let image = ScanImage::build(&s.angle, &s.time, &vec![0; s.x.len()]);
    let grid = image.grid();
    let errors = |method| {
        let params = SegmentParams { method, ..Default::default() };
        let normals = estimate_normals(&geo, &image, &grid, &params);
        let mut e = vec![];
        for k in 0..s.x.len() {
            // Road and sidewalk points within 15 cm (horizontally) of a curb.
            let near = (0.03..0.2).contains(&(s.y[k].abs() - 3.0).abs());
            if near && s.truth[k] != FOLIAGE && s.truth[k] > 2 || (near && s.truth[k] == ROAD) {
                if let Some(n) = normals[k] {
                    e.push(angle_deg(n.normal, s.normal[k]));
                }
            }
        }
        assert!(e.len() > 50, "{} edge points", e.len());
        e.iter().sum::<f64>() / e.len() as f64
    };
    let ransac = errors(NormalMethod::Ransac);
    let ls = errors(NormalMethod::LeastSquares);
    eprintln!("mean normal error 3–20 cm from the curbs: RANSAC {ransac:.2}°, least squares {ls:.2}°");
    assert!(ransac < 3.0, "RANSAC mean error at curbs {ransac:.2}°");
    assert!(ls > 2.0 * ransac && ls > 5.0, "least squares {ls:.2}° vs RANSAC {ransac:.2}°");
}

/// At fine angular steps (0.1°, 3600 rows, as real mobile-mapping scanners) neighbouring
/// measurements of a profile are millimetres apart, less than the noise tilts a plane across: a
/// window a few rows long along the profile holds a blob. The window's stride along the profile
/// keeps the road's normals (without it, 36 % of these road points got none, the rest a mean
/// error of 3.7°).
#[test]
fn fine_angular_steps_still_give_road_normals() {
    let s = scan_rows(24, 3600);
    let geo = StripGeometry { x: &s.x, y: &s.y, z: &s.z, head: &s.head };
    let image = ScanImage::build(&s.angle, &s.time, &vec![0; s.x.len()]);
    assert_eq!(image.rows, 3600);
    let normals = estimate_normals(&geo, &image, &image.grid(), &SegmentParams::default());
    // Road points away from the image's first and last revolutions (no neighbours across there).
    let road: Vec<usize> =
        (0..s.x.len()).filter(|&k| s.truth[k] == ROAD && (2..22).contains(&(image.column[k] as usize))).collect();
    let with: Vec<f64> = road.iter().filter_map(|&k| normals[k].map(|n| angle_deg(n.normal, s.normal[k]))).collect();
    let share = with.len() as f64 / road.len() as f64;
    let mean = with.iter().sum::<f64>() / with.len().max(1) as f64;
    eprintln!("0.1° steps: {} road points, {:.1} % with a normal, mean error {mean:.2}°", road.len(), share * 100.0);
    assert!(share > 0.95, "only {:.1} % of the road points have a normal", share * 100.0);
    assert!(mean < 2.0, "mean road normal error {mean:.2}°");
}
