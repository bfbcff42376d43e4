use super::*;

fn flat_town() -> Town {
    let cfg = TownConfig { grade: [0.0, 0.0], ..TownConfig::default() };
    Town::build(&cfg, 3)
}

#[test]
fn straight_down_hits_the_road() {
    let t = flat_town();
    // Street centre between the two driven blocks (x = 0 is a street line).
    let h = t.cast([0.0, 0.0, 2.0], [0.0, 0.0, -1.0], 70.0, 1).unwrap();
    assert!((h.t - 2.0).abs() < 1e-12);
    assert_eq!(h.surface_id, GROUND_ID);
    assert_eq!(h.class, SurfaceClass::Road);
    assert_eq!(h.normal, [0.0, 0.0, 1.0]);
}

#[test]
fn sloped_ground_hits_and_normal() {
    let cfg = TownConfig { grade: [0.02, -0.01], ..TownConfig::default() };
    let t = Town::build(&cfg, 3);
    let o = [0.3, 0.2, t.ground_z(0.3, 0.2) + 2.0];
    let h = t.cast(o, [0.0, 0.0, -1.0], 70.0, 1).unwrap();
    assert!((h.t - 2.0).abs() < 1e-12);
    let n = h.normal;
    let l = (1.0f64 + 0.0004 + 0.0001).sqrt();
    assert!((n[0] + 0.02 / l).abs() < 1e-12 && (n[1] - 0.01 / l).abs() < 1e-12);
    let p = [o[0], o[1], o[2] - h.t];
    assert!(t.check_surface(h.surface_id, p, 1e-9).unwrap().distance.abs() < 1e-12);
}

#[test]
fn horizontal_ray_hits_curb_or_something_solid_with_consistent_truth() {
    for skew_deg in [0.0, 30.0] {
        rays_hit_with_consistent_truth(&TownConfig { skew_deg, ..TownConfig::default() });
    }
}

/// Rays from above the middle street in all directions: every hit lies on its surface, its normal
/// faces the ray, and nothing is nearer.
fn rays_hit_with_consistent_truth(cfg: &TownConfig) {
    let t = Town::build(cfg, 11);
    let skew = cfg.skew_deg.to_radians().tan();
    let mut classes = std::collections::HashSet::new();
    let mut hits = 0;
    for k in 0..20_000u64 {
        // Rays from 2 m above the middle street in all directions.
        let az = rng::unit(k * 3) * std::f64::consts::TAU;
        let el = (rng::unit(k * 3 + 1) * 2.0 - 1.0).asin();
        let d = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
        let y = (rng::unit(k * 3 + 2) - 0.5) * 40.0;
        let o = [skew * y, y, t.ground_z(skew * y, y) + 2.2];
        if let Some(h) = t.cast(o, d, 70.0, k) {
            hits += 1;
            classes.insert(h.class);
            let p = [o[0] + h.t * d[0], o[1] + h.t * d[1], o[2] + h.t * d[2]];
            let c = t.check_surface(h.surface_id, p, 1e-6).unwrap();
            let n = h.normal;
            assert!(((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt() - 1.0).abs() < 1e-9);
            if h.class.is_surface() {
                assert!(c.distance.abs() < 1e-7 && c.within_bounds, "{h:?} {c:?}");
                assert!(n[0] * d[0] + n[1] * d[1] + n[2] * d[2] < 1e-9, "normal faces away from ray: {h:?}");
            } else {
                assert!(c.within_bounds && c.distance <= 1e-9, "foliage outside its crown: {c:?}");
            }
            // The brute-force nearest over all surfaces cannot be closer: re-cast from just
            // before the hit must hit the same surface at the remaining distance.
            let back = h.t - 1e-3;
            let o2 = [o[0] + back * d[0], o[1] + back * d[1], o[2] + back * d[2]];
            if h.class.is_surface() {
                let h2 = t.cast(o2, d, 1.0, k).unwrap();
                assert!((h2.t - 1e-3).abs() < 1e-7);
            }
        }
    }
    assert!(hits > 10_000);
    for c in [SurfaceClass::Road, SurfaceClass::Facade, SurfaceClass::Pole, SurfaceClass::Car, SurfaceClass::Foliage] {
        assert!(classes.contains(&c), "{c:?} never hit");
    }
}

#[test]
fn grid_walk_agrees_with_brute_force() {
    let t = flat_town();
    for k in 0..3_000u64 {
        let az = rng::unit(k * 5) * std::f64::consts::TAU;
        let el = (rng::unit(k * 5 + 1) * 1.6 - 0.8).asin();
        let d = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
        let o = [(rng::unit(k * 5 + 2) - 0.5) * 4.0, (rng::unit(k * 5 + 3) - 0.5) * 40.0, 2.2];
        let fast = t.cast(o, d, 70.0, k);
        // Brute force: every primitive.
        let op = t.shear(o);
        let dp = d;
        let inv = [1.0 / dp[0], 1.0 / dp[1], 1.0 / dp[2]];
        let mut best = Best { t: 70.0, what: HitRef::None };
        if dp[2] < 0.0 && -op[2] / dp[2] < 70.0 {
            best = Best { t: -op[2] / dp[2], what: HitRef::Ground };
        }
        for i in 0..t.boxes.len() as u32 {
            t.hit_box(i, &op, &dp, &inv, &mut best);
        }
        for i in 0..t.cyls.len() as u32 {
            t.hit_cylinder(i, &op, &dp, &mut best);
        }
        for i in 0..t.crowns.len() as u32 {
            t.hit_crown(i, &op, &dp, k, &mut best);
        }
        match (fast, best.what) {
            (None, HitRef::None) => {}
            (Some(h), _) => assert!((h.t - best.t).abs() < 1e-9, "ray {k}: grid {} brute {}", h.t, best.t),
            (None, w) => panic!("ray {k}: grid missed {w:?} at {}", best.t),
        }
    }
}

#[test]
fn deterministic_per_seed() {
    let cfg = TownConfig::default();
    let (a, b, c) = (Town::build(&cfg, 5), Town::build(&cfg, 5), Town::build(&cfg, 6));
    assert_eq!(a.stats(), b.stats());
    assert_eq!(a.boxes.len(), b.boxes.len());
    assert!(a.boxes.iter().zip(&b.boxes).all(|(x, y)| x.min == y.min && x.max == y.max));
    assert!(a.stats() != c.stats() || a.boxes.iter().zip(&c.boxes).any(|(x, y)| x.min != y.min));
    let s = a.stats();
    assert!(s.buildings > 20 && s.cars > 5 && s.poles > 5 && s.trees > 3, "{s:?}");
}
