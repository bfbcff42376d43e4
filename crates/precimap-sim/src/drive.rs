//! Vehicle passes: figure-8 routes over the street grid with rounded corners, a smooth speed
//! profile (slow in turns, an optional stop at a traffic light) and the true 200 Hz trajectory
//! with heading, slope-following pitch and roll, and suspension sway.

use crate::config::{DriveConfig, SimConfig};
use crate::rng::Rng;
use crate::town::{Layout, Town};
use precimap_core::Vec3;
use serde::Serialize;
use std::f64::consts::{PI, TAU};

const STREAM_PASS: u64 = 0x9A55_0000;
/// Shortest speed change, seconds (limits the jerk of small changes).
const MIN_CHANGE_S: f64 = 1.5;

/// A figure 8 over two neighbouring blocks: `(i, j)` and `(i + 1, j)`, or `(i, j + 1)` when
/// `vertical`. The shared street is driven twice per loop.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct Figure8 {
    pub i: i32,
    pub j: i32,
    pub vertical: bool,
}

impl Figure8 {
    /// Every figure 8 of the driven blocks, interleaved so that consecutive passes cover
    /// different parts of the town.
    pub fn all(layout: &Layout) -> Vec<Figure8> {
        let (bx, by) = (layout.blocks_x as i32, layout.blocks_y as i32);
        let mut h = Vec::new();
        let mut v = Vec::new();
        for j in 0..by {
            for i in 0..bx - 1 {
                h.push(Figure8 { i, j, vertical: false });
            }
        }
        for i in 0..bx {
            for j in 0..by - 1 {
                v.push(Figure8 { i, j, vertical: true });
            }
        }
        let mut out = Vec::with_capacity(h.len() + v.len());
        let n = h.len().max(v.len());
        for k in 0..n {
            out.extend(h.get(k));
            out.extend(v.get(k));
        }
        out
    }

    /// Street junctions in driving order (cyclic): up the shared street, around the first block
    /// turning left, up the shared street again, around the second block turning right.
    pub fn waypoints(&self, layout: &Layout) -> Vec<[f64; 2]> {
        let pattern = [(1, 0), (1, 1), (0, 1), (0, 0), (1, 0), (1, 1), (2, 1), (2, 0)];
        pattern
            .iter()
            .map(|&(a, b)| {
                layout.to_world(if self.vertical {
                    [layout.street_x(self.i + b), layout.street_y(self.j + a)]
                } else {
                    [layout.street_x(self.i + a), layout.street_y(self.j + b)]
                })
            })
            .collect()
    }
}

/// A point of a planar path: position, heading (radians, counter-clockwise from +x) and signed
/// curvature (positive turning left).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathPoint {
    pub pos: [f64; 2],
    pub heading: f64,
    pub curvature: f64,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Segment {
    Line { p: [f64; 2], dir: [f64; 2], len: f64 },
    Arc { c: [f64; 2], r: f64, a0: f64, sign: f64, len: f64 },
}

impl Segment {
    pub fn len(&self) -> f64 {
        match *self {
            Segment::Line { len, .. } | Segment::Arc { len, .. } => len,
        }
    }

    pub fn is_line(&self) -> bool {
        matches!(self, Segment::Line { .. })
    }

    fn eval(&self, s: f64) -> PathPoint {
        match *self {
            Segment::Line { p, dir, .. } => {
                PathPoint { pos: [p[0] + s * dir[0], p[1] + s * dir[1]], heading: dir[1].atan2(dir[0]), curvature: 0.0 }
            }
            Segment::Arc { c, r, a0, sign, .. } => {
                let a = a0 + sign * s / r;
                PathPoint {
                    pos: [c[0] + r * a.cos(), c[1] + r * a.sin()],
                    heading: a + sign * PI / 2.0,
                    curvature: sign / r,
                }
            }
        }
    }
}

/// A closed path of lines and circular arcs.
#[derive(Clone, Debug)]
pub struct Route {
    segs: Vec<Segment>,
    starts: Vec<f64>,
    length: f64,
}

fn norm2(v: [f64; 2]) -> [f64; 2] {
    let l = (v[0] * v[0] + v[1] * v[1]).sqrt();
    [v[0] / l, v[1] / l]
}

impl Route {
    /// The closed polyline through `w` with every corner rounded to radius `radius`, offset
    /// `right` metres to the right of the driving direction (a lane). Segment 0 is the line
    /// leaving `w[0]`.
    pub fn from_waypoints(w: &[[f64; 2]], radius: f64, right: f64) -> Route {
        let n = w.len();
        let dir = |k: usize| norm2([w[(k + 1) % n][0] - w[k][0], w[(k + 1) % n][1] - w[k][1]]);
        let rightof = |d: [f64; 2]| [d[1], -d[0]];
        // Per corner k: tangent points (centre line) and the arc.
        let mut t_in = vec![[0.0; 2]; n];
        let mut t_out = vec![[0.0; 2]; n];
        let mut arcs = vec![None; n];
        for k in 0..n {
            let din = dir((k + n - 1) % n);
            let dout = dir(k);
            let cross = din[0] * dout[1] - din[1] * dout[0];
            let dot = din[0] * dout[0] + din[1] * dout[1];
            let theta = cross.atan2(dot);
            if theta.abs() < 1e-9 {
                t_in[k] = w[k];
                t_out[k] = w[k];
                continue;
            }
            let tl = radius * (theta.abs() / 2.0).tan();
            t_in[k] = [w[k][0] - tl * din[0], w[k][1] - tl * din[1]];
            t_out[k] = [w[k][0] + tl * dout[0], w[k][1] + tl * dout[1]];
            let sign = theta.signum();
            let c = [t_in[k][0] - sign * radius * din[1], t_in[k][1] + sign * radius * din[0]];
            let r = radius + sign * right;
            let rd = rightof(din);
            let start = [t_in[k][0] + right * rd[0] - c[0], t_in[k][1] + right * rd[1] - c[1]];
            arcs[k] = Some(Segment::Arc { c, r, a0: start[1].atan2(start[0]), sign, len: r * theta.abs() });
        }
        let mut segs = Vec::with_capacity(2 * n);
        for k in 0..n {
            let d = dir(k);
            let rd = rightof(d);
            let a = t_out[k];
            let b = t_in[(k + 1) % n];
            let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            segs.push(Segment::Line { p: [a[0] + right * rd[0], a[1] + right * rd[1]], dir: d, len });
            if let Some(arc) = arcs[(k + 1) % n] {
                segs.push(arc);
            }
        }
        let mut starts = Vec::with_capacity(segs.len());
        let mut s = 0.0;
        for g in &segs {
            starts.push(s);
            s += g.len();
        }
        Route { segs, starts, length: s }
    }

    pub fn length(&self) -> f64 {
        self.length
    }

    pub fn segments(&self) -> &[Segment] {
        &self.segs
    }

    /// Arc length where segment `k` starts.
    pub fn segment_start(&self, k: usize) -> f64 {
        self.starts[k]
    }

    /// Point at arc length `s` (taken modulo the route length).
    pub fn eval(&self, s: f64) -> PathPoint {
        let s = s.rem_euclid(self.length);
        let k = self.starts.partition_point(|&x| x <= s).saturating_sub(1);
        self.segs[k].eval(s - self.starts[k])
    }
}

/// `v(t) = v0 + (v1 − v0)·S(t/dur)` with the smoothstep `S(u) = 3u² − 2u³`: acceleration is
/// continuous and zero at both ends.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Phase {
    t0: f64,
    dur: f64,
    s0: f64,
    v0: f64,
    v1: f64,
}

/// Speed along the pass as a function of time.
#[derive(Clone, Debug)]
pub struct SpeedProfile {
    phases: Vec<Phase>,
    duration: f64,
    distance: f64,
    /// Standstill window (seconds since the pass start).
    stop: Option<(f64, f64)>,
}

/// Distance, speed and acceleration at time `t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Motion {
    pub s: f64,
    pub v: f64,
    pub a: f64,
}

impl SpeedProfile {
    pub fn duration(&self) -> f64 {
        self.duration
    }

    pub fn distance(&self) -> f64 {
        self.distance
    }

    pub fn stop(&self) -> Option<(f64, f64)> {
        self.stop
    }

    /// Motion at time `t` (clamped to the profile).
    pub fn at(&self, t: f64) -> Motion {
        let k = self.phases.partition_point(|p| p.t0 <= t).saturating_sub(1);
        let p = &self.phases[k];
        let tau = (t - p.t0).clamp(0.0, p.dur);
        let u = tau / p.dur;
        let dv = p.v1 - p.v0;
        Motion {
            s: p.s0 + p.v0 * tau + dv * p.dur * (u * u * u - 0.5 * u * u * u * u),
            v: p.v0 + dv * u * u * (3.0 - 2.0 * u),
            a: dv / p.dur * 6.0 * u * (1.0 - u),
        }
    }
}

struct ProfileBuilder {
    phases: Vec<Phase>,
    t: f64,
    s: f64,
}

impl ProfileBuilder {
    fn push(&mut self, dur: f64, v0: f64, v1: f64) {
        if dur <= 1e-12 {
            return;
        }
        self.phases.push(Phase { t0: self.t, dur, s0: self.s, v0, v1 });
        self.t += dur;
        self.s += 0.5 * (v0 + v1) * dur;
    }

    /// A straight of length `len` entered at `v_in` and left at `v_out`, as fast as `v_max` and
    /// the mean acceleration `a` allow. Every speed change takes at least `MIN_CHANGE_S`, which
    /// bounds the jerk of small changes. If the ends cannot be met at all, one change straight
    /// from `v_in` to `v_out` covers the length exactly.
    fn straight(&mut self, len: f64, v_in: f64, v_out: f64, v_max: f64, a: f64) {
        // Duration and distance of a change from v0 to v1.
        let change = |v0: f64, v1: f64| {
            if (v1 - v0).abs() < 1e-12 {
                return (0.0, 0.0);
            }
            let dur = ((v1 - v0).abs() / a).max(MIN_CHANGE_S);
            (dur, 0.5 * (v0 + v1) * dur)
        };
        let need = |vp: f64| change(v_in, vp).1 + change(vp, v_out).1;
        let lo = v_in.max(v_out);
        if need(lo) > len {
            self.push(2.0 * len / (v_in + v_out), v_in, v_out);
            return;
        }
        // The fastest peak that fits (the distance needed grows with the peak).
        let vp = if need(v_max.max(lo)) <= len {
            v_max.max(lo)
        } else {
            let (mut a_, mut b_) = (lo, v_max);
            for _ in 0..60 {
                let m = 0.5 * (a_ + b_);
                if need(m) <= len {
                    a_ = m;
                } else {
                    b_ = m;
                }
            }
            a_
        };
        let (t_acc, d_acc) = change(v_in, vp);
        let (t_dec, d_dec) = change(vp, v_out);
        if vp > v_in {
            self.push(t_acc, v_in, vp);
        }
        let cruise = len - if vp > v_in { d_acc } else { 0.0 } - if vp > v_out { d_dec } else { 0.0 };
        if cruise > 1e-9 {
            self.push(cruise / vp, vp, vp);
        }
        if vp > v_out {
            self.push(t_dec, vp, v_out);
        }
    }
}

/// Everything that defines one pass before its trajectory is sampled.
#[derive(Clone, Debug, Serialize)]
pub struct PassPlan {
    pub index: u32,
    pub id: String,
    pub figure8: Figure8,
    pub reverse: bool,
    pub other_lane: bool,
    pub cruise_speed_m_s: f64,
    pub turn_speed_m_s: f64,
    /// Route segment (a straight) in whose middle the pass starts.
    pub start_segment: usize,
    pub stops: bool,
    /// GPS time of the first trajectory sample.
    pub t0: f64,
}

impl PassPlan {
    pub fn new(cfg: &SimConfig, layout: &Layout, index: u32) -> PassPlan {
        let d = &cfg.drive;
        let mut rng = Rng::new(cfg.seed, STREAM_PASS + index as u64);
        let routes = Figure8::all(layout);
        let figure8 = routes[index as usize % routes.len()];
        let n = d.other_lane_every;
        let cruise = rng.within(d.cruise_speed_m_s);
        let turn = rng.within(d.turn_speed_m_s).min(cruise);
        // 8 straights per figure 8, at even segment indices.
        let start_segment = 2 * (rng.next_u64() % 8) as usize;
        PassPlan {
            index,
            id: format!("v{:02}", index + 1),
            figure8,
            reverse: index % 2 == 1,
            other_lane: n > 0 && index % n == n - 1,
            cruise_speed_m_s: cruise,
            turn_speed_m_s: turn,
            start_segment,
            stops: d.stop_pass == Some(index),
            t0: d.gps_time_base_s + index as f64 * d.pass_time_step_s,
        }
    }

    pub fn route(&self, cfg: &DriveConfig, layout: &Layout) -> Route {
        let mut w = self.figure8.waypoints(layout);
        if self.reverse {
            w[1..].reverse();
        }
        let lane = if self.other_lane { -cfg.lane_offset_m } else { cfg.lane_offset_m };
        Route::from_waypoints(&w, cfg.turn_radius_m, lane)
    }

    /// The speed profile over one full loop plus `overlap_m`, starting mid-straight.
    pub fn profile(&self, cfg: &DriveConfig, route: &Route) -> SpeedProfile {
        let segs = route.segments();
        let n = segs.len();
        let a = cfg.accel_m_s2;
        let (vt, vmax) = (self.turn_speed_m_s, self.cruise_speed_m_s);
        // Unrolled pieces: (is_line, length).
        let total = route.length() + cfg.overlap_m;
        let mut pieces = Vec::new();
        let first = segs[self.start_segment];
        let mut left = total;
        let mut k = self.start_segment;
        let mut len = first.len() / 2.0;
        while left > 1e-9 {
            let l = len.min(left);
            pieces.push((segs[k].is_line(), l));
            left -= l;
            k = (k + 1) % n;
            len = segs[k].len();
        }
        // The stop: on the straight nearest the middle of the pass that is long enough to brake
        // from and accelerate back to turn speed.
        let need = vt * vt / (2.0 * a);
        let mut stop_piece = None;
        if self.stops {
            let mut s = 0.0;
            let mut best = f64::INFINITY;
            for (idx, &(line, l)) in pieces.iter().enumerate() {
                let mid = s + l / 2.0;
                if line
                    && idx > 0
                    && idx + 1 < pieces.len()
                    && l >= 2.0 * need + 1.0
                    && (mid - total / 2.0).abs() < best
                {
                    best = (mid - total / 2.0).abs();
                    stop_piece = Some(idx);
                }
                s += l;
            }
        }
        let mut b = ProfileBuilder { phases: Vec::new(), t: 0.0, s: 0.0 };
        let mut stop = None;
        let last = pieces.len() - 1;
        let mut v = vt;
        for (idx, &(line, l)) in pieces.iter().enumerate() {
            if !line {
                b.push(l / vt, vt, vt);
                v = vt;
                continue;
            }
            let v_out = if idx == last { vmax.min((v * v + 2.0 * a * l).sqrt()) } else { vt };
            let v_in = if idx == 0 { vmax.min((v_out * v_out + 2.0 * a * l).sqrt()) } else { v };
            if stop_piece == Some(idx) {
                let x = (0.7 * l).clamp(need + 0.5 * (l - 2.0 * need), l - need);
                b.straight(x, v_in, 0.0, vmax, a);
                let t_stop = b.t;
                b.push(cfg.stop_duration_s, 0.0, 0.0);
                stop = Some((t_stop, b.t));
                b.straight(l - x, 0.0, v_out, vmax, a);
            } else {
                b.straight(l, v_in, v_out, vmax, a);
            }
            v = v_out;
        }
        SpeedProfile { duration: b.t, distance: b.s, phases: b.phases, stop }
    }
}

/// The true trajectory of one pass, sampled at the trajectory rate.
#[derive(Clone, Debug)]
pub struct TruePass {
    pub plan: PassPlan,
    /// GPS seconds.
    pub times: Vec<f64>,
    /// Absolute coordinates.
    pub positions: Vec<Vec3>,
    pub rpy_deg: Vec<[f64; 3]>,
    /// Speed at each sample, m/s.
    pub speeds: Vec<f64>,
    pub length_m: f64,
    /// Standstill window, GPS seconds.
    pub stop: Option<(f64, f64)>,
}

/// Slowly varying sum of sinusoids (road roughness).
struct Wobble {
    terms: Vec<(f64, f64, f64)>,
}

impl Wobble {
    fn new(rng: &mut Rng, amplitude: f64, periods: [f64; 2], count: usize) -> Self {
        let a = amplitude * (2.0 / count as f64).sqrt();
        Wobble { terms: (0..count).map(|_| (a, TAU / rng.within(periods), rng.range(0.0, TAU))).collect() }
    }

    fn at(&self, t: f64) -> f64 {
        self.terms.iter().map(|&(a, w, p)| a * (w * t + p).sin()).sum()
    }
}

/// Samples the true trajectory of `plan`.
pub fn true_pass(cfg: &SimConfig, town: &Town, plan: PassPlan) -> TruePass {
    let d = &cfg.drive;
    let route = plan.route(d, &town.layout());
    let profile = plan.profile(d, &route);
    let s_start = route.segment_start(plan.start_segment) + route.segments()[plan.start_segment].len() / 2.0;
    let mut rng = Rng::new(cfg.seed, STREAM_PASS + 0x8000 + plan.index as u64);
    let roll_wobble = Wobble::new(&mut rng, d.sway_deg, [0.5, 2.5], 3);
    let pitch_wobble = Wobble::new(&mut rng, d.sway_deg, [0.5, 2.5], 3);
    let heave = Wobble::new(&mut rng, d.heave_m, [0.4, 2.0], 3);
    let dt = 1.0 / d.trajectory_rate_hz;
    let n = (profile.duration() / dt).floor() as usize + 1;
    let [a, b] = town.grade();
    let origin = cfg.origin;
    let k_lpf = 1.0 - (-dt / d.suspension_time_constant_s.max(1e-6)).exp();
    let (mut lat, mut lon) = (None::<f64>, None::<f64>);
    let mut out = TruePass {
        times: Vec::with_capacity(n),
        positions: Vec::with_capacity(n),
        rpy_deg: Vec::with_capacity(n),
        speeds: Vec::with_capacity(n),
        length_m: profile.distance(),
        stop: profile.stop().map(|(s, e)| (plan.t0 + s, plan.t0 + e)),
        plan,
    };
    for i in 0..n {
        let t = i as f64 * dt;
        let m = profile.at(t);
        let pp = route.eval(s_start + m.s);
        // Suspension: first-order response to lateral and longitudinal acceleration.
        let a_lat = m.v * m.v * pp.curvature;
        let lat_f = *lat.insert(lat.map_or(a_lat, |y| y + (a_lat - y) * k_lpf));
        let lon_f = *lon.insert(lon.map_or(m.a, |y| y + (m.a - y) * k_lpf));
        // Roughness only while moving: a standing vehicle is still.
        let rough = (m.v / 8.0).min(1.0);
        let [x, y] = pp.pos;
        let z = a * x + b * y + d.body_height_m + rough * heave.at(t);
        let yaw = pp.heading;
        let (sy, cy) = yaw.sin_cos();
        let pitch = -(a * cy + b * sy).atan() - (d.pitch_per_accel_deg * lon_f).to_radians()
            + (rough * pitch_wobble.at(t)).to_radians();
        let roll = (-a * sy + b * cy).atan()
            + (d.roll_per_lateral_accel_deg * lat_f).to_radians()
            + (rough * roll_wobble.at(t)).to_radians();
        out.times.push(out.plan.t0 + t);
        out.positions.push(Vec3::new(origin[0] + x, origin[1] + y, origin[2] + z));
        out.rpy_deg.push([roll.to_degrees(), pitch.to_degrees(), precimap_core::geom::wrap_deg(yaw.to_degrees())]);
        out.speeds.push(m.v);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Scale;

    #[test]
    fn route_is_closed_and_continuous() {
        let layout = Layout::square(2, 1, 60.0);
        for f in Figure8::all(&layout) {
            for right in [1.75, -1.75] {
                let w = f.waypoints(&layout);
                let r = Route::from_waypoints(&w, 9.0, right);
                assert_eq!(r.segments().len(), 16);
                // 8 legs of 60 m, each corner replaces 2R of polyline by a quarter circle; the
                // lane offsets cancel (4 left and 4 right turns).
                let expect = 8.0 * 60.0 - 8.0 * (2.0 * 9.0 - PI / 2.0 * 9.0);
                assert!((r.length() - expect).abs() < 1e-9, "{} vs {expect}", r.length());
                let mut prev = r.eval(0.0);
                let step = 0.05;
                let mut s = step;
                while s <= r.length() + 1e-9 {
                    let p = r.eval(s);
                    let jump = ((p.pos[0] - prev.pos[0]).powi(2) + (p.pos[1] - prev.pos[1]).powi(2)).sqrt();
                    assert!(jump <= step + 1e-9 && jump > step * 0.99, "position jumps at s = {s}");
                    let dh = (p.heading - prev.heading + PI).rem_euclid(TAU) - PI;
                    assert!(dh.abs() < step / 6.0, "heading jumps at s = {s}");
                    prev = p;
                    s += step;
                }
            }
        }
    }

    #[test]
    fn lane_is_right_of_the_centre_line() {
        let layout = Layout::square(2, 1, 60.0);
        let w = Figure8 { i: 0, j: 0, vertical: false }.waypoints(&layout);
        let r = Route::from_waypoints(&w, 9.0, 1.75);
        // Segment 0 drives north on x = 0: the right lane is at x = +1.75.
        let p = r.eval(10.0);
        assert!((p.pos[0] - 1.75).abs() < 1e-12 && (p.heading - PI / 2.0).abs() < 1e-12);
    }

    #[test]
    fn speed_profile_is_smooth_and_stops() {
        let cfg = SimConfig::for_scale(Scale::Small, 4);
        let layout = Layout::square(2, 1, 60.0);
        let plan = PassPlan::new(&cfg, &layout, cfg.drive.stop_pass.unwrap());
        assert!(plan.stops);
        let route = plan.route(&cfg.drive, &layout);
        let prof = plan.profile(&cfg.drive, &route);
        assert!((prof.distance() - route.length() - cfg.drive.overlap_m).abs() < 1e-6);
        let (s0, s1) = prof.stop().unwrap();
        assert!((s1 - s0 - cfg.drive.stop_duration_s).abs() < 1e-9);
        let mid = prof.at(0.5 * (s0 + s1));
        assert_eq!(mid.v, 0.0);
        let dt = 0.005;
        let mut prev = prof.at(0.0);
        let mut t = dt;
        let mut vmax: f64 = 0.0;
        while t < prof.duration() {
            let m = prof.at(t);
            assert!(m.v >= 0.0 && m.s >= prev.s - 1e-12);
            assert!(m.a.abs() <= 1.5 * 1.5 * cfg.drive.accel_m_s2 + 1e-9, "accel {} at {t}", m.a);
            assert!((m.a - prev.a).abs() < 0.05, "acceleration jumps at {t}: {prev:?} {m:?} {:?}", prof.phases);
            assert!((m.s - prev.s - 0.5 * (m.v + prev.v) * dt).abs() < 1e-6);
            vmax = vmax.max(m.v);
            prev = m;
            t += dt;
        }
        assert!(vmax > 8.0 && vmax <= plan.cruise_speed_m_s + 1e-9);
        // In turns the vehicle drives turn speed.
        let segs = route.segments();
        assert!(!segs[1].is_line());
    }

    #[test]
    fn true_attitude_follows_heading_and_slope() {
        let cfg = SimConfig::for_scale(Scale::Tiny, 9);
        let town = Town::build(&cfg.town, cfg.seed);
        let plan = PassPlan::new(&cfg, &town.layout(), 1);
        let tp = true_pass(&cfg, &town, plan);
        assert!(tp.times.windows(2).all(|w| w[1] > w[0]));
        for i in (0..tp.times.len() - 1).step_by(50) {
            let (p, q) = (tp.positions[i], tp.positions[i + 1]);
            let v = q - p;
            if v.norm() < 1e-3 {
                continue;
            }
            let heading = v.y.atan2(v.x).to_degrees();
            let dh = precimap_core::geom::wrap_deg(heading - tp.rpy_deg[i][2]);
            assert!(dh.abs() < 1.0, "heading off by {dh}° at {i}");
            let local_z = p.z - cfg.origin[2] - town.ground_z(p.x - cfg.origin[0], p.y - cfg.origin[1]);
            assert!((local_z - cfg.drive.body_height_m).abs() < 0.02);
            assert!(tp.rpy_deg[i][0].abs() < 2.0 && tp.rpy_deg[i][1].abs() < 2.0);
        }
    }

    #[test]
    fn vehicles_drive_through_free_space() {
        let mut configs: Vec<(String, SimConfig)> =
            [Scale::Tiny, Scale::Small, Scale::Medium].map(|s| (s.to_string(), SimConfig::for_scale(s, 21))).into();
        for scene in crate::Scene::ALL {
            let scenario = crate::Scenario::new(scene, crate::ErrorModel::Sinusoids, 4, 2);
            configs.push((scenario.name(), scenario.config(21, 40.0, 10.0, 100)));
        }
        for (scale, cfg) in configs {
            let town = Town::build(&cfg.town, cfg.seed);
            for p in 0..cfg.drive.passes {
                let tp = true_pass(&cfg, &town, PassPlan::new(&cfg, &town.layout(), p));
                for i in (0..tp.times.len()).step_by(10) {
                    let c = tp.positions[i] - Vec3::from(cfg.origin);
                    let yaw = tp.rpy_deg[i][2].to_radians();
                    let (fx, fy) = (yaw.cos(), yaw.sin());
                    // Body box of a van: 2.5 m ahead, 2.5 m behind, 1.05 m to each side, up to the heads.
                    for (along, across) in
                        [(2.5, 1.05), (2.5, -1.05), (-2.5, 1.05), (-2.5, -1.05), (0.0, 1.05), (0.0, -1.05)]
                    {
                        for dz in [-1.4, 0.0, 0.5] {
                            let x = c.x + along * fx - across * fy;
                            let y = c.y + along * fy + across * fx;
                            let hit = town.solid_at([x, y, c.z + dz]);
                            assert!(
                                hit.is_none(),
                                "{scale} pass {p}: vehicle corner ({along}, {across}, {dz}) inside {:?} at sample {i} {c:?} yaw {}",
                                hit.and_then(|id| town.surface(id)),
                                tp.rpy_deg[i][2]
                            );
                        }
                    }
                }
            }
        }
    }
}
