//! Ground control as a surveyor sets it out along the driven streets.
//!
//! Stations lie every [`ControlConfig::spacing_m`] along the driven streets (the streets every
//! pass drives, each once, walked in the order the passes first drive them); check stations lie
//! midway between them, or every [`ControlConfig::check_spacing_m`]. At each station a surveyor
//! measures two targets the strips see:
//!
//! - a **road marking**'s corner on the street's centre line, on the road surface alone: it fixes
//!   the map's height;
//! - the nearest **façade corner** (a building's outside corner, 1.5 m above the sidewalk), on two
//!   façades whose wall is whole within 0.5 m and which a vehicle in the lanes sees: it fixes the
//!   horizontal position.
//!
//! Both lie exactly on the town's true surfaces ([`TargetTruth::position_m`]); the manifest states
//! them with a Gaussian survey error of the configured σ per axis, drawn from the campaign's seed
//! by stateless hashes of the target's number, so no other random stream of the campaign moves.

use crate::config::SimConfig;
use crate::drive::Figure8;
use crate::rng;
use crate::scan::Head;
use crate::town::{FacadeCorner, Layout, Town, GROUND_ID};
use crate::truth::SurfaceClass;
use precimap_core::control::ControlRole;
use precimap_formats::manifest::{ControlSpec, ControlTargetSpec, Sigma, MAX_CONTROL_SIGMA_M};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;

/// Stations' default distance along the driven streets, metres.
pub const DEFAULT_SPACING_M: f64 = 150.0;
/// The survey's default standard deviation per axis, metres (a total station or RTK tie-in).
pub const DEFAULT_SIGMA_M: f64 = 0.005;
/// The closest stations may lie: closer, their façade corners would mostly be the same.
pub const MIN_SPACING_M: f64 = 10.0;
/// Height of a façade corner target above the sidewalk, metres.
pub const FACADE_TARGET_HEIGHT_M: f64 = 1.5;
/// A road marking's corner lies this far left of the street's centre line (the edge of a 12 cm
/// centre line), metres.
const MARKING_OFFSET_M: f64 = 0.06;
/// A station's façade corner lies at most this far from it (and at most half the spacing).
const MAX_CORNER_DISTANCE_M: f64 = 60.0;
/// A face is seen from lane positions at most this far away ...
const MAX_VIEW_M: f64 = 40.0;
/// ... at most this far from its normal (degrees) ...
const MAX_INCIDENCE_DEG: f64 = 80.0;
/// ... from at least this many of the positions sampled every [`LANE_STEP_M`].
const MIN_VIEWS: usize = 3;
const LANE_STEP_M: f64 = 2.0;
/// Check stations closer than this to a control station are left out, metres.
const MIN_STATION_GAP_M: f64 = 5.0;
const STREAM_CONTROL: u64 = 0xC047_0000;

/// Ground control of a simulated campaign (`SimConfig::control`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControlConfig {
    /// Distance between control stations along the driven streets, metres.
    pub spacing_m: f64,
    /// The survey's standard deviation: one for every axis, or `[x, y, z]`, metres.
    pub sigma_m: Sigma,
    /// Distance between check stations along the driven streets; by default they lie midway
    /// between the control stations.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub check_spacing_m: Option<f64>,
}

impl Default for ControlConfig {
    fn default() -> Self {
        Self { spacing_m: DEFAULT_SPACING_M, sigma_m: Sigma::All(DEFAULT_SIGMA_M), check_spacing_m: None }
    }
}

impl ControlConfig {
    pub(crate) fn problems(&self, out: &mut Vec<String>) {
        for (name, v) in
            [("control.spacing_m", Some(self.spacing_m)), ("control.check_spacing_m", self.check_spacing_m)]
        {
            if let Some(v) = v.filter(|v| !(v.is_finite() && *v >= MIN_SPACING_M)) {
                out.push(format!("{name} must be at least {MIN_SPACING_M} m, got {v}"));
            }
        }
        if self.sigma_m.per_axis().iter().any(|s| !(s.is_finite() && *s > 0.0 && *s <= MAX_CONTROL_SIGMA_M)) {
            out.push(format!(
                "control.sigma_m must be above 0 and at most {MAX_CONTROL_SIGMA_M} m on every axis, got {:?}",
                self.sigma_m
            ));
        }
    }
}

/// What a target is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TargetKind {
    /// A road marking's corner on the road: observes the height.
    RoadMarking,
    /// A building's outside corner on two façades: observes the horizontal position.
    FacadeCorner,
}

/// A true surface a target lies on.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TargetSurface {
    pub surface_id: u32,
    pub class: &'static str,
    /// World outward unit normal.
    pub normal: [f64; 3],
}

/// One target in `truth.json`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TargetTruth {
    pub id: String,
    pub role: ControlRole,
    pub kind: TargetKind,
    /// Distance of the target's station along the driven streets, metres.
    pub station_m: f64,
    /// True position (absolute coordinates), on every surface of `surfaces`.
    pub position_m: [f64; 3],
    /// The position the manifest states: the true one plus `survey_error_m`.
    pub surveyed_m: [f64; 3],
    pub survey_error_m: [f64; 3],
    pub surfaces: Vec<TargetSurface>,
}

/// How many targets of each role and kind a campaign has.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct TargetCounts {
    pub control_road: usize,
    pub control_facade: usize,
    pub check_road: usize,
    pub check_facade: usize,
}

impl TargetCounts {
    pub fn of(targets: &[TargetTruth]) -> Self {
        let mut c = Self::default();
        for t in targets {
            *match (t.role, t.kind) {
                (ControlRole::Control, TargetKind::RoadMarking) => &mut c.control_road,
                (ControlRole::Control, TargetKind::FacadeCorner) => &mut c.control_facade,
                (ControlRole::Check, TargetKind::RoadMarking) => &mut c.check_road,
                (ControlRole::Check, TargetKind::FacadeCorner) => &mut c.check_facade,
            } += 1;
        }
        c
    }
}

/// The survey error of target number `index` of a campaign with seed `seed`: independent normal
/// errors of standard deviation `sigma_m` per axis.
pub fn survey_error(seed: u64, index: u64, sigma_m: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|a| sigma_m[a] * rng::normal(rng::hash3(seed, STREAM_CONTROL, 3 * index + a as u64)))
}

/// The driven streets: every street between two junctions that a pass of `cfg` drives, once, in
/// the order the passes first drive them; each as its two junctions (local x, y).
pub fn driven_streets(cfg: &SimConfig, layout: &Layout) -> Vec<[[f64; 2]; 2]> {
    let routes = Figure8::all(layout);
    let key = |p: [f64; 2]| ((p[0] * 1e3).round() as i64, (p[1] * 1e3).round() as i64);
    let mut seen = BTreeSet::new();
    let mut out = Vec::new();
    for pass in 0..cfg.drive.passes as usize {
        let w = routes[pass % routes.len()].waypoints(layout);
        for k in 0..w.len() {
            let (a, b) = (w[k], w[(k + 1) % w.len()]);
            let (ka, kb) = (key(a), key(b));
            if ka != kb && seen.insert((ka.min(kb), ka.max(kb))) {
                out.push([a, b]);
            }
        }
    }
    out
}

/// A station: where along the streets, the point on the centre line and the street's direction.
#[derive(Clone, Copy, Debug)]
struct Station {
    s: f64,
    role: ControlRole,
    point: [f64; 2],
    dir: [f64; 2],
}

/// The point at distance `s` along the walk over `streets`.
fn along(streets: &[[[f64; 2]; 2]], mut s: f64) -> Option<([f64; 2], [f64; 2])> {
    for [a, b] in streets {
        let len = (b[0] - a[0]).hypot(b[1] - a[1]);
        if s <= len {
            let dir = [(b[0] - a[0]) / len, (b[1] - a[1]) / len];
            return Some(([a[0] + s * dir[0], a[1] + s * dir[1]], dir));
        }
        s -= len;
    }
    None
}

fn stations(streets: &[[[f64; 2]; 2]], c: &ControlConfig) -> Vec<Station> {
    let total: f64 = streets.iter().map(|[a, b]| (b[0] - a[0]).hypot(b[1] - a[1])).sum();
    let at = |s: f64, role| along(streets, s).map(|(point, dir)| Station { s, role, point, dir });
    let control: Vec<Station> = (0..)
        .map(|k| (k as f64 + 0.5) * c.spacing_m)
        .take_while(|&s| s < total)
        .filter_map(|s| at(s, ControlRole::Control))
        .collect();
    let check_spacing = c.check_spacing_m.unwrap_or(c.spacing_m);
    let checks = (1..)
        .map(|k| k as f64 * check_spacing)
        .take_while(|&s| s < total)
        .filter(|s| control.iter().all(|c| (c.s - s).abs() >= MIN_STATION_GAP_M))
        .filter_map(|s| at(s, ControlRole::Check));
    let mut all: Vec<Station> = control.iter().copied().chain(checks).collect();
    all.sort_by(|a, b| a.s.total_cmp(&b.s));
    all
}

/// Scan-head positions along the lanes of the driven streets (local), both directions.
fn lane_positions(cfg: &SimConfig, town: &Town, streets: &[[[f64; 2]; 2]]) -> Vec<[f64; 3]> {
    let head_z = Head::mounted_on(cfg).iter().map(|h| h.lever_arm(cfg)[2]).fold(0.0, f64::max);
    let lane = cfg.drive.lane_offset_m;
    let mut out = Vec::new();
    for [a, b] in streets {
        let len = (b[0] - a[0]).hypot(b[1] - a[1]);
        let (dx, dy) = ((b[0] - a[0]) / len, (b[1] - a[1]) / len);
        for k in 0..=(len / LANE_STEP_M).floor() as usize {
            let s = k as f64 * LANE_STEP_M;
            for side in [lane, -lane] {
                let (x, y) = (a[0] + s * dx + side * dy, a[1] + s * dy - side * dx);
                out.push([x, y, town.ground_z(x, y) + cfg.drive.body_height_m + head_z]);
            }
        }
    }
    out
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Whether the vehicle sees both faces of `corner` near the corner from enough lane positions.
fn corner_seen(town: &Town, corner: &FacadeCorner, lanes: &[[f64; 3]], key: u64) -> bool {
    let [(_, na), (_, nb)] = corner.faces;
    [(na, nb), (nb, na)].iter().all(|&(n, other)| {
        // A point on the face 0.25 m from the edge: along the face, away from the other face.
        let mut t = [-n[1], n[0], 0.0];
        if dot(t, other) > 0.0 {
            t = [n[1], -n[0], 0.0];
        }
        let len = dot(t, t).sqrt();
        let f = [0, 1, 2].map(|k| corner.position[k] + 0.25 * t[k] / len);
        let cos_max = MAX_INCIDENCE_DEG.to_radians().cos();
        let views = lanes
            .iter()
            .enumerate()
            .filter(|(i, o)| {
                let v = sub(f, **o);
                let dist = dot(v, v).sqrt();
                if dist > MAX_VIEW_M || -dot(v, n) / dist < cos_max {
                    return false;
                }
                let d = v.map(|x| x / dist);
                town.cast(**o, d, dist + 0.05, rng::hash2(key, *i as u64))
                    .is_some_and(|h| (h.t - dist).abs() < 0.01 && dot(h.normal, n) > 0.999)
            })
            .take(MIN_VIEWS)
            .count();
        views >= MIN_VIEWS
    })
}

fn ground_normal(town: &Town) -> [f64; 3] {
    let [a, b] = town.grade();
    let l = (1.0 + a * a + b * b).sqrt();
    [-a / l, -b / l, 1.0 / l]
}

/// The targets of `cfg`'s control in `town`, in station order (none without control).
pub fn place_targets(cfg: &SimConfig, town: &Town) -> Vec<TargetTruth> {
    let Some(c) = &cfg.control else { return Vec::new() };
    let streets = driven_streets(cfg, &town.layout());
    let lanes = lane_positions(cfg, town, &streets);
    let corners = town.facade_corners(cfg.town.curb_height_m + FACADE_TARGET_HEIGHT_M);
    let mut used = vec![false; corners.len()];
    let sigma = c.sigma_m.per_axis();
    let mut out: Vec<TargetTruth> = Vec::new();
    let mut push = |role, kind, station: &Station, local: [f64; 3], surfaces: Vec<TargetSurface>| {
        let position_m = [0, 1, 2].map(|k| cfg.origin[k] + local[k]);
        let survey_error_m = survey_error(cfg.seed, out.len() as u64, sigma);
        let number = out.iter().filter(|t| t.role == role).count() + 1;
        out.push(TargetTruth {
            id: format!("{}-{number:03}", if role == ControlRole::Control { "GCP" } else { "CHK" }),
            role,
            kind,
            station_m: station.s,
            position_m,
            surveyed_m: [0, 1, 2].map(|k| position_m[k] + survey_error_m[k]),
            survey_error_m,
            surfaces,
        });
    };
    for (n, station) in stations(&streets, c).iter().enumerate() {
        let key = rng::hash3(cfg.seed, STREAM_CONTROL + 1, n as u64);
        let [x, y] = [
            station.point[0] - MARKING_OFFSET_M * station.dir[1],
            station.point[1] + MARKING_OFFSET_M * station.dir[0],
        ];
        let marking = [x, y, town.ground_z(x, y)];
        let clear = town.cast([x, y, marking[2] + 2.0], [0.0, 0.0, -1.0], 3.0, key);
        if clear.is_some_and(|h| h.surface_id == GROUND_ID && (h.t - 2.0).abs() < 1e-9) {
            let road =
                TargetSurface { surface_id: GROUND_ID, class: SurfaceClass::Road.name(), normal: ground_normal(town) };
            push(station.role, TargetKind::RoadMarking, station, marking, vec![road]);
        }
        let spacing = match station.role {
            ControlRole::Control => c.spacing_m,
            ControlRole::Check => c.check_spacing_m.unwrap_or(c.spacing_m),
        };
        let reach = MAX_CORNER_DISTANCE_M.min(spacing / 2.0);
        let distance = |k: usize| (corners[k].position[0] - x).hypot(corners[k].position[1] - y);
        let mut near: Vec<usize> = (0..corners.len()).filter(|&k| !used[k] && distance(k) <= reach).collect();
        near.sort_by(|&a, &b| distance(a).total_cmp(&distance(b)));
        if let Some(k) = near.into_iter().find(|&k| corner_seen(town, &corners[k], &lanes, key)) {
            used[k] = true;
            let surfaces = corners[k]
                .faces
                .iter()
                .map(|&(surface_id, normal)| TargetSurface { surface_id, class: SurfaceClass::Facade.name(), normal })
                .collect();
            push(station.role, TargetKind::FacadeCorner, station, corners[k].position, surfaces);
        }
    }
    out
}

/// The manifest's `$.control` of `targets` (their surveyed positions) with σ `sigma_m`, in the
/// campaign's own frame (no CRS).
pub fn manifest_control(targets: &[TargetTruth], sigma_m: Sigma) -> ControlSpec {
    ControlSpec {
        crs: None,
        targets: targets
            .iter()
            .map(|t| ControlTargetSpec {
                id: t.id.clone(),
                position_m: t.surveyed_m,
                sigma_m,
                role: t.role,
                plane: None,
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Scale;

    fn with_control(spacing_m: f64) -> SimConfig {
        let mut cfg = SimConfig::for_scale(Scale::Tiny, 3);
        cfg.control = Some(ControlConfig { spacing_m, ..ControlConfig::default() });
        cfg
    }

    #[test]
    fn targets_lie_on_the_true_surfaces_they_name() {
        for skew_deg in [0.0, 25.0] {
            let mut cfg = with_control(30.0);
            cfg.town.skew_deg = skew_deg;
            let town = Town::build(&cfg.town, cfg.seed);
            let targets = place_targets(&cfg, &town);
            let counts = TargetCounts::of(&targets);
            assert!(counts.control_road >= 6 && counts.check_road >= 6, "{skew_deg}°: {counts:?}");
            assert!(counts.control_facade >= 4 && counts.check_facade >= 2, "{skew_deg}°: {counts:?}");
            for (i, t) in targets.iter().enumerate() {
                let local = [0, 1, 2].map(|k| t.position_m[k] - cfg.origin[k]);
                let expected = match t.kind {
                    TargetKind::RoadMarking => vec![SurfaceClass::Road],
                    TargetKind::FacadeCorner => vec![SurfaceClass::Facade; 2],
                };
                let classes: Vec<_> = t.surfaces.iter().map(|s| town.surface(s.surface_id).unwrap().class).collect();
                assert_eq!(classes, expected, "{t:?}");
                for s in &t.surfaces {
                    let check = town.check_surface(s.surface_id, local, 1e-9).unwrap();
                    assert!(check.distance.abs() < 1e-9 && check.within_bounds, "{t:?}: {check:?}");
                }
                assert_eq!(t.survey_error_m, survey_error(cfg.seed, i as u64, [DEFAULT_SIGMA_M; 3]));
                for k in 0..3 {
                    assert_eq!(t.surveyed_m[k], t.position_m[k] + t.survey_error_m[k]);
                }
            }
            let ids: BTreeSet<&str> = targets.iter().map(|t| t.id.as_str()).collect();
            assert_eq!(ids.len(), targets.len());
            // No façade corner serves two stations.
            let corners: BTreeSet<u32> = targets
                .iter()
                .filter(|t| t.kind == TargetKind::FacadeCorner)
                .map(|t| t.surfaces[0].surface_id)
                .collect();
            assert_eq!(corners.len(), counts.control_facade + counts.check_facade);
        }
    }

    #[test]
    fn stations_alternate_control_and_check_along_the_streets() {
        let cfg = with_control(60.0);
        let layout = Town::build(&cfg.town, cfg.seed).layout();
        let streets = driven_streets(&cfg, &layout);
        // The figure 8 over two blocks: the outer rectangle and the shared street.
        assert_eq!(streets.len(), 7);
        let total: f64 = streets.iter().map(|[a, b]| (b[0] - a[0]).hypot(b[1] - a[1])).sum();
        assert!((total - 7.0 * cfg.town.block_m).abs() < 1e-9);
        let s = stations(&streets, cfg.control.as_ref().unwrap());
        let roles: Vec<_> = s.iter().map(|s| (s.s, s.role)).collect();
        let (c, k) = (ControlRole::Control, ControlRole::Check);
        assert_eq!(
            roles,
            [(30.0, c), (60.0, k), (90.0, c), (120.0, k), (150.0, c), (180.0, k), (210.0, c), (240.0, k)]
        );
    }

    #[test]
    fn survey_errors_have_the_configured_sigma() {
        let sigma = [0.003, 0.005, 0.02];
        let n = 40_000;
        let mut sums = [[0.0; 2]; 3];
        for i in 0..n {
            let e = survey_error(11, i, sigma);
            for a in 0..3 {
                sums[a][0] += e[a];
                sums[a][1] += e[a] * e[a];
            }
        }
        let n = n as f64;
        for a in 0..3 {
            let mean = sums[a][0] / n;
            let sd = (sums[a][1] / n - mean * mean).sqrt();
            assert!(mean.abs() < 4.0 * sigma[a] / n.sqrt(), "axis {a}: mean {mean}");
            assert!((sd / sigma[a] - 1.0).abs() < 0.02, "axis {a}: σ {sd} instead of {}", sigma[a]);
        }
        assert_ne!(survey_error(11, 0, sigma), survey_error(12, 0, sigma));
    }

    #[test]
    fn control_is_optional_and_validated() {
        let cfg = SimConfig::for_scale(Scale::Tiny, 1);
        let json = serde_json::to_value(&cfg).unwrap();
        assert!(json.get("control").is_none());
        let mut with = with_control(150.0);
        let back: SimConfig = serde_json::from_value(serde_json::to_value(&with).unwrap()).unwrap();
        assert_eq!(back, with);
        let mut json = serde_json::to_value(&cfg).unwrap();
        json["control"] = serde_json::json!({"sigma_m": [0.01, 0.01, 0.004]});
        let parsed: SimConfig = serde_json::from_value(json).unwrap();
        assert_eq!(parsed.control.unwrap().spacing_m, DEFAULT_SPACING_M);
        with.control = Some(ControlConfig {
            spacing_m: 2.0,
            sigma_m: Sigma::PerAxis([0.01, 0.0, 0.01]),
            check_spacing_m: Some(f64::NAN),
        });
        let p = with.problems();
        for field in ["control.spacing_m", "control.check_spacing_m", "control.sigma_m"] {
            assert!(p.iter().any(|m| m.starts_with(field)), "{field}: {p:?}");
        }
    }
}
