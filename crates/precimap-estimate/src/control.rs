//! Control and check targets as observations of a tile's surfaces (`precimap_core::control`).
//!
//! A point of a strip observes a target when it lies within the target's radius on a surface
//! model whose plane passes through the target (a planar target: on a surface parallel to its
//! plane). Its residual is its distance from the target along the surface normal, `e = w·(p − c)`,
//! and moving its pass moves it exactly as it moves the point's latent-map observation, so the
//! row is the same Jacobian with another target. The target's own error is shared by every point
//! of a pass: a pass of `k` points observes the target with variance `σ_c² + σ_s²/k`, so each of
//! its points gets weight `1/(k·σ_c² + σ_s²)` (`σ_c` the target's σ along `w`, `σ_s`
//! `Parameters::control_point_sigma_m`, the scanner's own precision: unlike the latent map's
//! observations, a target's are few and nothing else observes the datum, so they are weighted as
//! what they are). Check targets are measured alike and never observed.

use precimap_core::control::{ControlRole, ControlSums, ControlTarget};
use precimap_core::hash::FxHashMap;
use precimap_core::{Parameters, TileKey};
use std::collections::BTreeMap;

/// Below this the gate does not shrink with the outlier threshold: a pass still a few
/// centimetres off a target must keep observing it, and 5 cm still tells the road from the top
/// of a kerb (≥ 10 cm).
pub const CONTROL_GATE_MIN_M: f64 = 0.05;

/// How far from a target a surface may pass (and a point lie off it) to observe it at an
/// outlier threshold of `threshold_m`.
pub fn control_gate_m(threshold_m: f64) -> f64 {
    threshold_m.max(CONTROL_GATE_MIN_M)
}

/// Whether points of `tile`'s core can observe `target`: its horizontal position lies within
/// its radius (plus the tile's border) of the core.
pub fn reaches_tile(target: &ControlTarget, tile: TileKey, params: &Parameters) -> bool {
    let (ox, oy) = tile.origin(params.tile_size_m);
    let reach = target.radius_m(params.control_radius_m) + params.tile_overlap_m;
    let [x, y, _] = target.position;
    x >= ox - reach && x < ox + params.tile_size_m + reach && y >= oy - reach && y < oy + params.tile_size_m + reach
}

/// Every target by the tiles it reaches ([`reaches_tile`]), each tile's in the order of
/// `targets`: one pass over the targets instead of one per tile.
pub fn targets_by_tile(targets: &[ControlTarget], params: &Parameters) -> BTreeMap<TileKey, Vec<ControlTarget>> {
    let size = params.tile_size_m;
    let mut by_tile: BTreeMap<TileKey, Vec<ControlTarget>> = BTreeMap::new();
    for t in targets {
        let reach = t.radius_m(params.control_radius_m) + params.tile_overlap_m;
        let [x, y, _] = t.position;
        // The candidates, one tile wider than the reach on every side; the predicate decides.
        let span = |v: f64| ((v - reach) / size).floor() as i32 - 1..=((v + reach) / size).floor() as i32 + 1;
        for tx in span(x) {
            for ty in span(y) {
                let tile = TileKey { tx, ty };
                if reaches_tile(t, tile, params) {
                    by_tile.entry(tile).or_default().push(t.clone());
                }
            }
        }
    }
    by_tile
}

/// One point's observation of a control target.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TargetObservation {
    /// Index of the point in the tile's point order.
    pub point: usize,
    /// Unit normal the residual is measured along.
    pub w: [f64; 3],
    pub e: f64,
    pub weight: f64,
}

/// What a tile's points hold for [`observe_targets`]: positions relative to the tile's
/// south-west corner (heights absolute), and per point its surface model's normal and a point
/// of its plane (`None`: no model, or outside the core) and the strip pass it belongs to.
#[allow(missing_debug_implementations)]
pub struct TilePoints<'a, M, P>
where
    M: Fn(usize) -> Option<([f64; 3], [f64; 3])>,
    P: Fn(usize) -> u32,
{
    pub origin: [f64; 2],
    pub position: &'a [[f64; 3]],
    pub model: M,
    pub pass: P,
}

/// Every observation of the control targets among `targets` (sorted by point) and, for every
/// target, control and check alike, what the points measured there (sorted by id; targets no
/// point observed are left out).
pub fn observe_targets<M, P>(
    targets: &[ControlTarget],
    points: &TilePoints<'_, M, P>,
    params: &Parameters,
    threshold_m: f64,
) -> (Vec<TargetObservation>, Vec<ControlSums>)
where
    M: Fn(usize) -> Option<([f64; 3], [f64; 3])>,
    P: Fn(usize) -> u32,
{
    if targets.is_empty() {
        return (Vec::new(), Vec::new());
    }
    let gate = control_gate_m(threshold_m);
    let cos_group = params.normal_group_angle_deg.to_radians().cos();
    let local: Vec<[f64; 3]> = targets
        .iter()
        .map(|t| [t.position[0] - points.origin[0], t.position[1] - points.origin[1], t.position[2]])
        .collect();
    // (target, point, normal, residual) of every point that sees a target, and points per pass.
    let mut seen: Vec<(usize, usize, [f64; 3], f64)> = Vec::new();
    let mut per_pass: FxHashMap<(usize, u32), u32> = FxHashMap::default();
    for (i, p) in points.position.iter().enumerate() {
        let Some((w, o)) = (points.model)(i) else { continue };
        for (j, (target, c)) in targets.iter().zip(&local).enumerate() {
            let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
            let radius = target.radius_m(params.control_radius_m);
            let (u, observes) = match target.plane {
                None => {
                    let through = dot(w, [c[0] - o[0], c[1] - o[1], c[2] - o[2]]).abs() <= gate;
                    (w, through && dot(d, d) <= radius * radius)
                }
                Some(plane) => {
                    let n = plane.normal;
                    let along = dot(w, n);
                    let u = if along < 0.0 { n.map(|v| -v) } else { n };
                    let off = dot(d, u);
                    (u, along.abs() >= cos_group && dot(d, d) - off * off <= radius * radius)
                }
            };
            if !observes {
                continue;
            }
            let e = dot(u, d);
            if e.abs() <= gate {
                seen.push((j, i, u, e));
                *per_pass.entry((j, (points.pass)(i))).or_default() += 1;
            }
        }
    }
    let sigma_d2 = params.control_point_sigma_m * params.control_point_sigma_m;
    let mut sums: Vec<Option<ControlSums>> = vec![None; targets.len()];
    let mut observations = Vec::new();
    for &(j, i, u, e) in &seen {
        let target = &targets[j];
        let k = f64::from(per_pass[&(j, (points.pass)(i))]);
        let weight = 1.0 / (k * target.variance_along(u) + sigma_d2);
        sums[j].get_or_insert_with(|| ControlSums::new(target.id.clone())).add(u, e, weight);
        if target.role == ControlRole::Control {
            observations.push(TargetObservation { point: i, w: u, e, weight });
        }
    }
    for ((j, _), _) in per_pass {
        if let Some(s) = sums[j].as_mut() {
            s.passes += 1;
        }
    }
    observations.sort_by_key(|o| o.point);
    let mut sums: Vec<ControlSums> = sums.into_iter().flatten().collect();
    sums.sort_by(|a, b| a.id.cmp(&b.id));
    (observations, sums)
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[cfg(test)]
mod tests {
    use super::*;
    use precimap_core::control::ControlPlane;

    fn target(id: &str, position: [f64; 3], role: ControlRole) -> ControlTarget {
        ControlTarget { id: id.into(), position, sigma_m: [0.005; 3], role, plane: None }
    }

    /// Positions, each point's model (normal, a point of its plane) and pass.
    type Street = (Vec<[f64; 3]>, Vec<([f64; 3], [f64; 3])>, Vec<u32>);

    /// A road (z = 0) at heights `z_of(pass)` and a façade (x = 10) along y, two passes.
    fn street(z_of: impl Fn(u32) -> f64) -> Street {
        let (mut position, mut model, mut pass) = (Vec::new(), Vec::new(), Vec::new());
        for p in 0..2u32 {
            for ix in 0..40 {
                for iy in 0..40 {
                    let (x, y) = (8.0 + ix as f64 * 0.05, 4.0 + iy as f64 * 0.05);
                    position.push([x, y, z_of(p)]);
                    model.push(([0.0, 0.0, 1.0], [9.0, 5.0, 0.0]));
                    pass.push(p);
                }
            }
            for iy in 0..40 {
                for iz in 0..40 {
                    position.push([10.0, 4.0 + iy as f64 * 0.05, 0.2 + iz as f64 * 0.05]);
                    model.push(([-1.0, 0.0, 0.0], [10.0, 5.0, 1.0]));
                    pass.push(p);
                }
            }
        }
        (position, model, pass)
    }

    fn observe(targets: &[ControlTarget], street: &Street) -> (Vec<TargetObservation>, Vec<ControlSums>) {
        let (position, model, pass) = street;
        let points = TilePoints { origin: [0.0, 0.0], position, model: |i| Some(model[i]), pass: |i| pass[i] };
        observe_targets(targets, &points, &Parameters::default(), 0.007)
    }

    #[test]
    fn a_road_point_sees_the_road_alone_and_weighs_each_pass_as_one_observation() {
        let s = street(|p| if p == 0 { 0.01 } else { -0.01 });
        let (obs, sums) = observe(&[target("g", [9.0, 5.0, 0.0], ControlRole::Control)], &s);
        assert!(!obs.is_empty());
        assert!(obs.iter().all(|o| o.w == [0.0, 0.0, 1.0]), "the façade lies 1 m away");
        let params = Parameters::default();
        // Per pass the weights add up to one observation of variance σ_c² + σ_d²/k.
        let k = obs.len() as f64 / 2.0;
        let per_pass: f64 = obs.iter().take(k as usize).map(|o| o.weight).sum();
        let want = 1.0 / (0.005f64.powi(2) + params.control_point_sigma_m.powi(2) / k);
        assert!((per_pass - want).abs() < 1e-9 * want, "{per_pass} vs {want}");
        assert_eq!(sums.len(), 1);
        assert_eq!(sums[0].passes, 2);
        let o = sums[0].offset();
        assert!(o.z.unwrap().abs() < 1e-12, "the passes' mean is on the target: {o:?}");
        assert_eq!(o.x, None);
    }

    #[test]
    fn a_facade_corner_at_the_foot_observes_height_and_across_the_facade() {
        let s = street(|_| 0.003);
        let (obs, sums) = observe(&[target("c", [10.0, 5.0, 0.0], ControlRole::Control)], &s);
        assert!(obs.iter().any(|o| o.w[0] != 0.0) && obs.iter().any(|o| o.w[2] != 0.0));
        let o = sums[0].offset();
        assert!((o.z.unwrap() - 0.003).abs() < 1e-9, "{o:?}");
        assert!(o.x.unwrap().abs() < 1e-9, "{o:?}");
        assert_eq!(o.y, None, "nothing faces along the façade");
    }

    #[test]
    fn a_check_target_is_measured_but_never_observed() {
        let s = street(|_| 0.002);
        let (obs, sums) = observe(&[target("k", [9.0, 5.0, 0.0], ControlRole::Check)], &s);
        assert!(obs.is_empty());
        assert!((sums[0].offset().z.unwrap() - 0.002).abs() < 1e-12);
    }

    #[test]
    fn a_surface_off_the_target_by_more_than_the_gate_does_not_observe_it() {
        let s = street(|_| 0.12);
        let (obs, sums) = observe(&[target("g", [9.0, 5.0, 0.0], ControlRole::Control)], &s);
        assert!(obs.is_empty() && sums.is_empty(), "{sums:?}");
    }

    #[test]
    fn a_planar_target_observes_only_parallel_surfaces_within_its_radius() {
        let s = street(|_| 0.0);
        let mut t = target("p", [10.02, 5.0, 1.0], ControlRole::Control);
        t.plane = Some(ControlPlane { normal: [1.0, 0.0, 0.0], radius_m: 0.5 });
        let (obs, sums) = observe(&[t], &s);
        // A disc of radius 0.5 m on the façade at 5 cm spacing, both passes.
        assert!(obs.len() > 2 * 250 && obs.len() < 2 * 340, "{}", obs.len());
        assert!(obs.iter().all(|o| o.w == [-1.0, 0.0, 0.0] && (o.e - 0.02).abs() < 1e-12));
        assert!((sums[0].offset().x.unwrap() + 0.02).abs() < 1e-12);
    }

    #[test]
    fn targets_by_tile_is_the_per_tile_filter() {
        let params = Parameters::default();
        let targets: Vec<ControlTarget> = [[15.2, 3.0], [-0.1, 29.95], [7.0, 7.0], [44.9, -15.1]]
            .iter()
            .enumerate()
            .map(|(i, &[x, y])| target(&format!("t{i}"), [x, y, 0.0], ControlRole::Control))
            .collect();
        let by_tile = targets_by_tile(&targets, &params);
        for tx in -3..5 {
            for ty in -3..5 {
                let tile = TileKey { tx, ty };
                let filtered: Vec<ControlTarget> =
                    targets.iter().filter(|t| reaches_tile(t, tile, &params)).cloned().collect();
                assert_eq!(by_tile.get(&tile).cloned().unwrap_or_default(), filtered, "{tile}");
            }
        }
        // No tile outside the range compared above, and a target on a tile edge in both tiles.
        assert!(by_tile.keys().all(|k| (-3..5).contains(&k.tx) && (-3..5).contains(&k.ty)), "{by_tile:?}");
        assert_eq!(by_tile[&TileKey { tx: 1, ty: 0 }][0].id, "t0");
        assert_eq!(by_tile[&TileKey { tx: 0, ty: 0 }].iter().map(|t| t.id.as_str()).collect::<Vec<_>>(), ["t0", "t2"]);
    }

    #[test]
    fn targets_reach_the_tiles_within_their_radius() {
        let params = Parameters::default();
        let t = target("g", [15.2, 3.0, 0.0], ControlRole::Control);
        assert!(reaches_tile(&t, TileKey { tx: 0, ty: 0 }, &params));
        assert!(reaches_tile(&t, TileKey { tx: 1, ty: 0 }, &params));
        assert!(!reaches_tile(&t, TileKey { tx: 2, ty: 0 }, &params));
        assert!(!reaches_tile(&t, TileKey { tx: 0, ty: 1 }, &params));
    }
}
