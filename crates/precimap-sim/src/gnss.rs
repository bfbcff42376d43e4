//! GNSS/IMU errors of one pass: time-correlated position and attitude errors (by default smooth
//! sums of sinusoids, nearly frozen while the vehicle stands thanks to zero-velocity updates; or
//! one of the processes of [`crate::process`]), plus an optional GNSS outage that lets a drift
//! bump grow and then decay once satellites are back.

use crate::config::ErrorConfig;
use crate::rng::Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

const STREAM_ERRORS: u64 = 0xE880_0000;

/// A GNSS outage of one pass.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Outage {
    /// GPS seconds.
    pub start: f64,
    pub end: f64,
    /// The bump has decayed completely at `end + decay_s`.
    pub decay_s: f64,
    /// Drift at the end of the outage (x, y, z metres).
    pub peak_m: [f64; 3],
    pub peak_heading_deg: f64,
}

impl Outage {
    /// Bump weight in [0, 1]: smooth rise over the outage, smooth decay after it.
    pub fn weight(&self, t: f64) -> f64 {
        if t <= self.start {
            0.0
        } else if t <= self.end {
            smoothstep((t - self.start) / (self.end - self.start))
        } else {
            1.0 - smoothstep((t - self.end) / self.decay_s)
        }
    }
}

fn smoothstep(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    u * u * (3.0 - 2.0 * u)
}

/// Error statistics of one pass (measured minus true), over all trajectory samples.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ErrorStats {
    /// σ of the process per axis: for sinusoid sums drawn per pass (the realised RMS over the
    /// pass equals it), for Gauss–Markov and white noise the configured one, for a random walk
    /// its realised RMS over the pass.
    pub sigma_position_m: [f64; 3],
    /// σ drawn for roll, pitch, heading.
    pub sigma_attitude_deg: [f64; 3],
    /// RMS of the total error (process plus outage bump) per axis.
    pub rms_position_m: [f64; 3],
    pub rms_position_3d_m: f64,
    pub max_position_3d_m: f64,
    pub rms_attitude_deg: [f64; 3],
    pub max_attitude_deg: [f64; 3],
    /// Mean of the total error per axis (a constant part the data cannot tell from the map).
    pub mean_position_m: [f64; 3],
}

/// Errors at every trajectory sample.
#[derive(Clone, Debug)]
pub struct PassErrors {
    /// Added to the true positions (metres, world x, y, z).
    pub position: Vec<[f64; 3]>,
    /// Added to the true roll, pitch, yaw (degrees).
    pub rpy_deg: Vec<[f64; 3]>,
    pub outage: Option<Outage>,
    pub stats: ErrorStats,
}

/// Error "clock": advances at `floor + (1 − floor)·min(v/v_nom, 1)` per second, so a standing
/// vehicle's error stays nearly constant.
pub fn error_clock(cfg: &ErrorConfig, times: &[f64], speeds: &[f64]) -> Vec<f64> {
    let rate = |v: f64| cfg.zupt_floor + (1.0 - cfg.zupt_floor) * (v / cfg.nominal_speed_m_s).clamp(0.0, 1.0);
    let mut tau = Vec::with_capacity(times.len());
    let mut acc = 0.0;
    for i in 0..times.len() {
        if i > 0 {
            acc += (times[i] - times[i - 1]) * 0.5 * (rate(speeds[i - 1]) + rate(speeds[i]));
        }
        tau.push(acc);
    }
    tau
}

/// One error channel: a sum of random-phase sinusoids of the error clock, scaled so the RMS over
/// the pass is exactly `sigma`.
fn channel(rng: &mut Rng, tau: &[f64], sigma: f64, periods: [f64; 2], components: u32) -> Vec<f64> {
    // Log-uniform periods: as many slow as fast components per octave.
    let terms: Vec<(f64, f64, f64)> = (0..components)
        .map(|_| {
            let p = (periods[0].ln() + rng.f64() * (periods[1].ln() - periods[0].ln())).exp();
            (rng.range(0.5, 1.0), TAU / p, rng.range(0.0, TAU))
        })
        .collect();
    let mut e: Vec<f64> = tau.iter().map(|&t| terms.iter().map(|&(a, w, ph)| a * (w * t + ph).sin()).sum()).collect();
    let rms = (e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64).sqrt();
    if rms > 0.0 {
        let k = sigma / rms;
        e.iter_mut().for_each(|v| *v *= k);
    }
    e
}

/// Errors for pass `pass` at the given samples (GPS seconds, speeds in m/s).
pub fn pass_errors(cfg: &ErrorConfig, seed: u64, pass: u32, times: &[f64], speeds: &[f64]) -> PassErrors {
    let mut rng = Rng::new(seed, STREAM_ERRORS + pass as u64);
    let n = times.len();
    let (pos, att, sig_p, sig_a) = match crate::process::channels(&cfg.process, seed, pass, times) {
        Some(([x, y, z, roll, pitch, heading], s)) => {
            (vec![x, y, z], vec![roll, pitch, heading], [s[0], s[1], s[2]], [s[3], s[4], s[5]])
        }
        None => {
            let tau = error_clock(cfg, times, speeds);
            let sig_p =
                [rng.within(cfg.position_sigma_m), rng.within(cfg.position_sigma_m), rng.within(cfg.position_sigma_m)];
            let sig_a = [
                rng.within(cfg.roll_pitch_sigma_deg),
                rng.within(cfg.roll_pitch_sigma_deg),
                rng.within(cfg.heading_sigma_deg),
            ];
            let pos: Vec<Vec<f64>> =
                sig_p.iter().map(|&s| channel(&mut rng, &tau, s, cfg.position_period_s, cfg.components)).collect();
            let att: Vec<Vec<f64>> =
                sig_a.iter().map(|&s| channel(&mut rng, &tau, s, cfg.attitude_period_s, cfg.components)).collect();
            (pos, att, sig_p, sig_a)
        }
    };
    // Drawn for every pass, so choosing the outage pass changes nothing else.
    let frac = rng.range(0.3, 0.45);
    let dur = rng.within(cfg.outage_duration_s);
    let mag = rng.within(cfg.outage_drift_m);
    let dir = rng.range(0.0, TAU);
    let up = if rng.chance(0.5) { 1.0 } else { -1.0 };
    let head = if rng.chance(0.5) { 1.0 } else { -1.0 };
    let outage = (cfg.outage_pass == Some(pass)).then(|| {
        let (t0, t1) = (times[0], times[n - 1]);
        let start = t0 + frac * (t1 - t0);
        Outage {
            start,
            end: start + dur,
            decay_s: cfg.outage_decay_s,
            peak_m: [mag * dir.cos(), mag * dir.sin(), up * cfg.outage_vertical_fraction * mag],
            peak_heading_deg: head * cfg.outage_heading_drift_deg,
        }
    });
    let mut position = Vec::with_capacity(n);
    let mut rpy_deg = Vec::with_capacity(n);
    for i in 0..n {
        let w = outage.map_or(0.0, |o| o.weight(times[i]));
        let bump =
            outage.map_or([0.0; 4], |o| [o.peak_m[0] * w, o.peak_m[1] * w, o.peak_m[2] * w, o.peak_heading_deg * w]);
        position.push([pos[0][i] + bump[0], pos[1][i] + bump[1], pos[2][i] + bump[2]]);
        rpy_deg.push([att[0][i], att[1][i], att[2][i] + bump[3]]);
    }
    let stats = statistics(&position, &rpy_deg, sig_p, sig_a);
    PassErrors { position, rpy_deg, outage, stats }
}

fn statistics(pos: &[[f64; 3]], att: &[[f64; 3]], sig_p: [f64; 3], sig_a: [f64; 3]) -> ErrorStats {
    let n = pos.len() as f64;
    let rms = |v: &[[f64; 3]], k: usize| (v.iter().map(|e| e[k] * e[k]).sum::<f64>() / n).sqrt();
    let maxabs = |v: &[[f64; 3]], k: usize| v.iter().map(|e| e[k].abs()).fold(0.0, f64::max);
    let rms_p = [rms(pos, 0), rms(pos, 1), rms(pos, 2)];
    ErrorStats {
        sigma_position_m: sig_p,
        sigma_attitude_deg: sig_a,
        rms_position_m: rms_p,
        rms_position_3d_m: (rms_p[0].powi(2) + rms_p[1].powi(2) + rms_p[2].powi(2)).sqrt(),
        max_position_3d_m: pos.iter().map(|e| (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt()).fold(0.0, f64::max),
        rms_attitude_deg: [rms(att, 0), rms(att, 1), rms(att, 2)],
        max_attitude_deg: [maxabs(att, 0), maxabs(att, 1), maxabs(att, 2)],
        mean_position_m: [0, 1, 2].map(|k| pos.iter().map(|e| e[k]).sum::<f64>() / n),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn samples(seconds: f64, stop: (f64, f64)) -> (Vec<f64>, Vec<f64>) {
        let n = (seconds * 200.0) as usize;
        let times: Vec<f64> = (0..n).map(|i| 4.0e8 + i as f64 * 0.005).collect();
        let speeds =
            times.iter().map(|&t| if t - 4.0e8 >= stop.0 && t - 4.0e8 <= stop.1 { 0.0 } else { 9.0 }).collect();
        (times, speeds)
    }

    #[test]
    fn process_hits_sigma_is_smooth_and_freezes_when_standing() {
        let cfg = ErrorConfig::default();
        let (times, speeds) = samples(90.0, (40.0, 46.0));
        let e = pass_errors(&cfg, 1, 0, &times, &speeds);
        assert!(e.outage.is_none());
        for k in 0..3 {
            assert!((e.stats.rms_position_m[k] - e.stats.sigma_position_m[k]).abs() < 1e-12);
            assert!((0.1..=0.3).contains(&e.stats.sigma_position_m[k]));
            assert!((e.stats.rms_attitude_deg[k] - e.stats.sigma_attitude_deg[k]).abs() < 1e-12);
        }
        // Smooth: over 0.5 m of driving (~0.06 s) the error changes by far less than σ.
        let step = 11;
        for i in (0..times.len() - step).step_by(7) {
            for k in 0..3 {
                let de = (e.position[i + step][k] - e.position[i][k]).abs();
                assert!(de < 0.03, "position error jumps by {de} m at sample {i}");
            }
        }
        // Standing 6 s: the clock runs at 5 %, so the error moves as in 0.3 s of driving.
        let (a, b) = (200 * 40 + 10, 200 * 46 - 10);
        let tau = error_clock(&cfg, &times, &speeds);
        assert!((tau[b] - tau[a] - 0.05 * (times[b] - times[a])).abs() < 1e-6);
        let moved = (0..3).map(|k| (e.position[b][k] - e.position[a][k]).abs()).fold(0.0, f64::max);
        assert!(moved < 0.02, "error drifted {moved} m while standing");
    }

    #[test]
    fn outage_bump_rises_and_decays() {
        let cfg = ErrorConfig { outage_pass: Some(3), ..ErrorConfig::default() };
        let (times, speeds) = samples(120.0, (-1.0, -1.0));
        let with = pass_errors(&cfg, 5, 3, &times, &speeds);
        let without = pass_errors(&ErrorConfig { outage_pass: None, ..cfg.clone() }, 5, 3, &times, &speeds);
        let o = with.outage.unwrap();
        assert!((15.0..=20.0).contains(&(o.end - o.start)));
        let peak = (o.peak_m[0].powi(2) + o.peak_m[1].powi(2)).sqrt();
        assert!((0.2..=0.3).contains(&peak));
        for (i, &t) in times.iter().enumerate() {
            let d: Vec<f64> = (0..3).map(|k| with.position[i][k] - without.position[i][k]).collect();
            let w = o.weight(t);
            assert!((d[0] - w * o.peak_m[0]).abs() < 1e-12);
            if t <= o.start || t >= o.end + o.decay_s {
                assert!(d.iter().all(|v| v.abs() < 1e-12));
            }
        }
        assert_eq!(o.weight(o.end), 1.0);
    }
}
