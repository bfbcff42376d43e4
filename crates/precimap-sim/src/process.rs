//! Stochastic pose-error processes sampled at the trajectory's time stamps: first-order
//! Gauss–Markov, random walk and white noise. Each channel draws from its own random stream, so
//! one channel's parameters never change another's realisation.

use crate::config::ErrorProcess;
use crate::rng::Rng;

/// Stream base of the processes (distinct from the sinusoid sums' stream).
const STREAM_PROCESS: u64 = 0x9C0C_0000;

/// Exact discretisation of the first-order Gauss–Markov process with variance `sigma²` and
/// correlation time `tau`: `x[k+1] = φ·x[k] + σ·√(1 − φ²)·w`, `φ = exp(−Δt/τ)`, started from its
/// stationary distribution, so it is stationary at any sampling.
pub fn gauss_markov(rng: &mut Rng, times: &[f64], sigma: f64, tau: f64) -> Vec<f64> {
    let mut out = Vec::with_capacity(times.len());
    let mut x = sigma * rng.normal();
    for (k, &t) in times.iter().enumerate() {
        if k > 0 {
            let phi = (-(t - times[k - 1]) / tau).exp();
            x = phi * x + sigma * (1.0 - phi * phi).max(0.0).sqrt() * rng.normal();
        }
        out.push(x);
    }
    out
}

/// Random walk from 0 at the first sample: increments `q·√Δt·w`.
pub fn random_walk(rng: &mut Rng, times: &[f64], q: f64) -> Vec<f64> {
    let mut out = Vec::with_capacity(times.len());
    let mut x = 0.0;
    for (k, &t) in times.iter().enumerate() {
        if k > 0 {
            x += q * (t - times[k - 1]).max(0.0).sqrt() * rng.normal();
        }
        out.push(x);
    }
    out
}

/// Independent normal samples of standard deviation `sigma`.
pub fn white_noise(rng: &mut Rng, times: &[f64], sigma: f64) -> Vec<f64> {
    times.iter().map(|_| sigma * rng.normal()).collect()
}

/// The six channels (x, y, z metres; roll, pitch, heading degrees) of `process` for pass `pass`,
/// with the σ each channel was drawn for (a random walk's: its RMS over the pass). `None` for the
/// sinusoid sums, which [`crate::gnss`] draws itself.
pub fn channels(process: &ErrorProcess, seed: u64, pass: u32, times: &[f64]) -> Option<([Vec<f64>; 6], [f64; 6])> {
    let stream = |channel: u64| Rng::new(seed, STREAM_PROCESS + ((pass as u64) << 4) + channel);
    let series: [Vec<f64>; 6] = match process {
        ErrorProcess::Sinusoids => return None,
        ErrorProcess::GaussMarkov { position_sigma_m, position_tau_s, attitude_sigma_deg, attitude_tau_s } => {
            std::array::from_fn(|c| {
                let (sigma, tau) = if c < 3 {
                    (position_sigma_m[c], position_tau_s[c])
                } else {
                    (attitude_sigma_deg[c - 3], attitude_tau_s[c - 3])
                };
                gauss_markov(&mut stream(c as u64), times, sigma, tau)
            })
        }
        ErrorProcess::RandomWalk { position_m_per_sqrt_s, attitude_deg_per_sqrt_s } => std::array::from_fn(|c| {
            let q = if c < 3 { position_m_per_sqrt_s[c] } else { attitude_deg_per_sqrt_s[c - 3] };
            random_walk(&mut stream(c as u64), times, q)
        }),
        ErrorProcess::WhiteNoise { position_sigma_m, attitude_sigma_deg } => std::array::from_fn(|c| {
            let sigma = if c < 3 { position_sigma_m[c] } else { attitude_sigma_deg[c - 3] };
            white_noise(&mut stream(c as u64), times, sigma)
        }),
    };
    let sigma: [f64; 6] = std::array::from_fn(|c| match process {
        ErrorProcess::GaussMarkov { position_sigma_m, attitude_sigma_deg, .. }
        | ErrorProcess::WhiteNoise { position_sigma_m, attitude_sigma_deg } => {
            if c < 3 {
                position_sigma_m[c]
            } else {
                attitude_sigma_deg[c - 3]
            }
        }
        _ => (series[c].iter().map(|v| v * v).sum::<f64>() / series[c].len().max(1) as f64).sqrt(),
    });
    Some((series, sigma))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn times(n: usize, dt: f64) -> Vec<f64> {
        (0..n).map(|i| 4.0e8 + i as f64 * dt).collect()
    }

    fn autocorrelation(x: &[f64], lag: usize) -> f64 {
        let n = x.len() - lag;
        let var = x.iter().map(|v| v * v).sum::<f64>() / x.len() as f64;
        (0..n).map(|i| x[i] * x[i + lag]).sum::<f64>() / n as f64 / var
    }

    #[test]
    fn gauss_markov_has_its_variance_and_autocorrelation() {
        // 4000 correlation times at 10 samples per τ: the variance estimate's relative
        // standard error is about √(2τ/T) ≈ 2 %, the lag-τ autocorrelation's about 2 % too.
        let (sigma, tau, dt) = (0.1, 25.0, 2.5);
        let t = times(40_000, dt);
        let x = gauss_markov(&mut Rng::new(3, 1), &t, sigma, tau);
        let var = x.iter().map(|v| v * v).sum::<f64>() / x.len() as f64;
        assert!((var.sqrt() / sigma - 1.0).abs() < 0.06, "σ {}", var.sqrt());
        let lag = (tau / dt) as usize;
        let r = autocorrelation(&x, lag);
        assert!((r - (-1.0f64).exp()).abs() < 0.06, "ρ(τ) {r}");
        let r3 = autocorrelation(&x, 3 * lag);
        assert!((r3 - (-3.0f64).exp()).abs() < 0.06, "ρ(3τ) {r3}");
        // Deterministic from the seed, different across seeds.
        assert_eq!(x, gauss_markov(&mut Rng::new(3, 1), &t, sigma, tau));
        assert_ne!(x[5], gauss_markov(&mut Rng::new(4, 1), &t, sigma, tau)[5]);
    }

    #[test]
    fn random_walk_variance_grows_linearly() {
        // Variance at time T over 2000 independent walks: q²·T.
        let (q, dt, steps) = (0.02, 0.5, 400);
        let t = times(steps + 1, dt);
        let mut rng = Rng::new(9, 2);
        let ends: Vec<f64> = (0..2000).map(|_| *random_walk(&mut rng, &t, q).last().unwrap()).collect();
        let var = ends.iter().map(|v| v * v).sum::<f64>() / ends.len() as f64;
        let expected = q * q * dt * steps as f64;
        assert!((var / expected - 1.0).abs() < 0.1, "variance {var} against {expected}");
        assert_eq!(random_walk(&mut Rng::new(1, 1), &t, q)[0], 0.0);
    }

    #[test]
    fn white_noise_is_uncorrelated_with_its_sigma() {
        let t = times(50_000, 0.005);
        let x = white_noise(&mut Rng::new(5, 3), &t, 0.03);
        let var = x.iter().map(|v| v * v).sum::<f64>() / x.len() as f64;
        assert!((var.sqrt() / 0.03 - 1.0).abs() < 0.02);
        assert!(autocorrelation(&x, 1).abs() < 0.02);
    }

    #[test]
    fn channels_are_independent_streams() {
        let t = times(1000, 0.005);
        let gm = |sx: f64| ErrorProcess::GaussMarkov {
            position_sigma_m: [sx, 0.1, 0.1],
            position_tau_s: [25.0; 3],
            attitude_sigma_deg: [0.01; 3],
            attitude_tau_s: [20.0; 3],
        };
        let (a, sa) = channels(&gm(0.1), 1, 0, &t).unwrap();
        let (b, _) = channels(&gm(0.2), 1, 0, &t).unwrap();
        assert_eq!(a[1], b[1]);
        assert!((b[0][10] - 2.0 * a[0][10]).abs() < 1e-15);
        assert_eq!(sa[0], 0.1);
        assert_ne!(channels(&gm(0.1), 1, 1, &t).unwrap().0[0], a[0]);
        assert!(channels(&ErrorProcess::Sinusoids, 1, 0, &t).is_none());
    }
}
