//! A trajectory's process model: the σ of the curvature term (second differences of the
//! corrections over three neighbouring anchors) on each of its six axes, estimated from the
//! trajectory's own solves where the campaign asks for it (`Parameters::process_model`).
//!
//! The curvature term is a prior on how GNSS/IMU errors bend. Smooth errors (sums of slow
//! sinusoids) bend little and want a stiff term; Gauss–Markov and random-walk errors change
//! slope from one anchor to the next and want a loose one; no single σ serves both. Each σ is
//! therefore a variance component of the trajectory's own solve, estimated by
//!
//! ```text
//! σ² ← (1/m) Σ_i [ (Δ²x̂_i)² + Var(Δ²x_i) ]        over the m interior anchors, per axis
//! ```
//!
//! (the M-step of EM; its fixed point is Förstner's `σ² = Σ(Δ²x̂)² / r` with the redundancy
//! `r = m − Σ Var(Δ²x)/σ²`), where `x̂` is the solve's posterior mean and `Var` comes from the
//! band of its posterior covariance. Where the data say little about the curvature, the
//! posterior variance is the prior's own and the σ stays; where they say much, it follows the
//! curvature the data show. The state is carried from iteration to iteration and moved halfway
//! (in log space) towards each estimate, between the campaign's σ and `√2 ×` the smoothness σ:
//! re-estimating it within a solve, several rounds at a time, destabilises the alternation with
//! the latent map.

use precimap_core::Parameters;
use serde::{Deserialize, Serialize};

/// Per-axis sums over a trajectory's interior anchors that estimate its curvature σ's:
/// `squares` of the posterior mean's second differences and their posterior `variances`
/// (x, y, z in m², rotations about x, y, z in rad²).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CurvatureMoments {
    pub squares: [f64; 6],
    pub variances: [f64; 6],
    /// Interior anchors summed.
    pub terms: u64,
}

impl CurvatureMoments {
    /// The variance-component estimate of each axis's curvature σ² (see the module), `None`
    /// without an interior anchor.
    pub fn estimate(&self) -> Option<[f64; 6]> {
        (self.terms > 0).then(|| std::array::from_fn(|a| (self.squares[a] + self.variances[a]) / self.terms as f64))
    }
}

/// A trajectory's curvature σ per axis (x, y, z in m, rotations about x, y, z in rad).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CurvatureModel {
    pub sigma: [f64; 6],
}

impl CurvatureModel {
    /// The campaign's σ's, where every trajectory starts; `None` when the curvature terms are off.
    pub fn from_params(params: &Parameters) -> Option<Self> {
        let [p, r] = [params.sigma_curvature_position_m, params.sigma_curvature_rotation_deg.to_radians()];
        (p > 0.0 && r > 0.0).then_some(Self { sigma: [p, p, p, r, r, r] })
    }

    /// The term's weights `1/σ²`.
    pub fn weights(&self) -> [f64; 6] {
        self.sigma.map(|s| 1.0 / (s * s))
    }

    /// The σ's in the report's units: x, y, z in m, rotations in degrees.
    pub fn sigma_m_deg(&self) -> [f64; 6] {
        std::array::from_fn(|a| if a < 3 { self.sigma[a] } else { self.sigma[a].to_degrees() })
    }

    /// The range each σ is kept in: the campaign's σ below, and above the second difference of a
    /// random walk whose steps have the smoothness σ (`√2 σ_smooth`), beyond which the curvature
    /// term holds less than the smoothness term already does.
    pub fn bounds(params: &Parameters) -> Option<([f64; 6], [f64; 6])> {
        let floor = Self::from_params(params)?.sigma;
        let [p, r] = [params.sigma_smooth_position_m, params.sigma_smooth_rotation_deg.to_radians()];
        let cap = [p, p, p, r, r, r];
        Some((floor, std::array::from_fn(|a| (std::f64::consts::SQRT_2 * cap[a]).max(floor[a]))))
    }

    /// Moves each σ halfway in log space towards the estimate of `moments`, within
    /// [`Self::bounds`]. Axes without an estimate keep their σ.
    pub fn update(&mut self, moments: &CurvatureMoments, params: &Parameters) {
        let (Some(estimate), Some((floor, cap))) = (moments.estimate(), Self::bounds(params)) else { return };
        for a in 0..6 {
            let target = estimate[a].sqrt();
            if !(target.is_finite() && target > 0.0) {
                continue;
            }
            let damped = (self.sigma[a] * target).sqrt();
            self.sigma[a] = damped.clamp(floor[a], cap[a]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn updates_are_damped_and_bounded() {
        let params = Parameters::default();
        let start = CurvatureModel::from_params(&params).unwrap();
        let (floor, cap) = CurvatureModel::bounds(&params).unwrap();
        assert!((cap[0] - 0.005 * std::f64::consts::SQRT_2).abs() < 1e-12);
        // An estimate 16× the σ moves it 4× (halfway in log space).
        let sixteen = |s: f64| 256.0 * s * s;
        let moments = CurvatureMoments { squares: start.sigma.map(sixteen), variances: [0.0; 6], terms: 1 };
        let mut model = start;
        model.update(&moments, &params);
        for a in 0..6 {
            assert!((model.sigma[a] / start.sigma[a] - 4.0).abs() < 1e-9, "axis {a}");
        }
        // Far above the cap, or below the floor: clamped.
        let huge = CurvatureMoments { squares: [1.0; 6], variances: [0.0; 6], terms: 1 };
        model.update(&huge, &params);
        assert_eq!(model.sigma, cap);
        let none = CurvatureMoments { squares: [0.0; 6], variances: [1e-30; 6], terms: 1 };
        for _ in 0..100 {
            model.update(&none, &params);
        }
        assert_eq!(model.sigma, floor);
        // No interior anchor: unchanged; curvature off: no model.
        model.update(&CurvatureMoments::default(), &params);
        assert_eq!(model.sigma, floor);
        let off = Parameters { sigma_curvature_position_m: 0.0, sigma_curvature_rotation_deg: 0.0, ..params };
        assert!(CurvatureModel::from_params(&off).is_none());
    }
}
