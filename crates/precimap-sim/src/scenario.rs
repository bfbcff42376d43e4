//! Named scenes and error models that modify a [`SimConfig`]: the building blocks of the
//! accuracy matrix (`precimap bench accuracy`) and of `precimap simulate --scene/--errors`.

use crate::config::{CalibrationErrors, ErrorProcess, SimConfig};
use std::fmt;
use std::str::FromStr;

/// Lean of the oblique scene's streets: they cross at 65° and 115°.
const OBLIQUE_SKEW_DEG: f64 = 25.0;

/// What stands along the streets and how the streets run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Scene {
    /// The right-angled street grid with mixed buildings, trees, cars and poles.
    Grid,
    /// Streets crossing at 65° and 115° (no right angles).
    Oblique,
    /// An open road: few buildings, mostly ground, curbs and street lights, almost no trees.
    OpenRoad,
    /// Narrow streets between continuous tall façades.
    Downtown,
}

impl Scene {
    pub const ALL: [Scene; 4] = [Scene::Grid, Scene::Oblique, Scene::OpenRoad, Scene::Downtown];

    pub fn name(self) -> &'static str {
        match self {
            Scene::Grid => "grid",
            Scene::Oblique => "oblique",
            Scene::OpenRoad => "open_road",
            Scene::Downtown => "downtown",
        }
    }

    /// Changes the town (and the turn radius) of `cfg`; block size and counts stay the caller's.
    pub fn apply(self, cfg: &mut SimConfig) {
        let t = &mut cfg.town;
        match self {
            Scene::Grid => {}
            Scene::Oblique => {
                t.skew_deg = OBLIQUE_SKEW_DEG;
                // The shear narrows the leaning streets by cos(skew): widen them back.
                let cos = OBLIQUE_SKEW_DEG.to_radians().cos();
                t.road_half_width_m /= cos;
                t.sidewalk_width_m /= cos;
                // Acute corners reach farther into the junction: keep parked cars and poles back.
                t.corner_clearance_m = t.corner_clearance_m.max(15.0);
            }
            Scene::OpenRoad => {
                t.gap_probability = 0.85;
                t.gap_width_m = [10.0, 25.0];
                t.building_height_m = [4.0, 8.0];
                t.tree_probability = 0.05;
                t.car_probability = 0.05;
                t.pole_spacing_m = 15.0;
            }
            Scene::Downtown => {
                // A 6.6 m carriageway: the van in a 1.6 m lane clears the cars parked half on
                // the sidewalk.
                t.road_half_width_m = 3.3;
                cfg.drive.lane_offset_m = 1.6;
                t.sidewalk_width_m = 2.0;
                t.building_height_m = [18.0, 35.0];
                t.building_width_m = [8.0, 16.0];
                t.gap_probability = 0.02;
                t.tree_probability = 0.15;
                t.car_probability = 0.3;
            }
        }
    }
}

/// The GNSS/IMU and calibration errors of a campaign.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorModel {
    /// Sums of sinusoids of periods 20–120 s (position) and 5–60 s (attitude): the presets'.
    Sinusoids,
    /// First-order Gauss–Markov, σ 10 cm with τ 25 s (position), σ 0.01°/0.01°/0.02° with τ 20 s
    /// (roll, pitch, heading).
    GaussMarkov,
    /// The same σ with slow correlation: τ 120 s (position), 60 s (attitude).
    GaussMarkovSlow,
    /// Random walks: 1.3 cm/√s (position), 0.0013°/√s roll and pitch, 0.0026°/√s heading.
    RandomWalk,
    /// White noise at every 200 Hz pose: 3 mm (position), 0.003° (attitude).
    WhiteNoise,
    /// Gauss–Markov as above plus a GNSS outage of 15–20 s on one pass, drifting 20–30 cm.
    Outage,
    /// Sinusoid sums plus constant boresight (0.005–0.02°) and lever-arm (5–10 mm) errors per
    /// head and a range error of 50 ppm plus 3 mm.
    Calibration,
}

impl ErrorModel {
    pub const ALL: [ErrorModel; 7] = [
        ErrorModel::Sinusoids,
        ErrorModel::GaussMarkov,
        ErrorModel::GaussMarkovSlow,
        ErrorModel::RandomWalk,
        ErrorModel::WhiteNoise,
        ErrorModel::Outage,
        ErrorModel::Calibration,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ErrorModel::Sinusoids => "sinusoids",
            ErrorModel::GaussMarkov => "gauss_markov",
            ErrorModel::GaussMarkovSlow => "gauss_markov_slow",
            ErrorModel::RandomWalk => "random_walk",
            ErrorModel::WhiteNoise => "white_noise",
            ErrorModel::Outage => "outage",
            ErrorModel::Calibration => "calibration",
        }
    }

    /// Sets the errors of `cfg` (the outage goes to the last pass).
    pub fn apply(self, cfg: &mut SimConfig) {
        let gauss_markov = |position_tau: f64, attitude_tau: f64| ErrorProcess::GaussMarkov {
            position_sigma_m: [0.1; 3],
            position_tau_s: [position_tau; 3],
            attitude_sigma_deg: [0.01, 0.01, 0.02],
            attitude_tau_s: [attitude_tau; 3],
        };
        let e = &mut cfg.errors;
        e.outage_pass = None;
        e.process = ErrorProcess::Sinusoids;
        e.calibration = CalibrationErrors::default();
        match self {
            ErrorModel::Sinusoids => {}
            ErrorModel::GaussMarkov => e.process = gauss_markov(25.0, 20.0),
            ErrorModel::GaussMarkovSlow => e.process = gauss_markov(120.0, 60.0),
            ErrorModel::RandomWalk => {
                e.process = ErrorProcess::RandomWalk {
                    position_m_per_sqrt_s: [0.013; 3],
                    attitude_deg_per_sqrt_s: [0.0013, 0.0013, 0.0026],
                }
            }
            ErrorModel::WhiteNoise => {
                e.process = ErrorProcess::WhiteNoise { position_sigma_m: [0.003; 3], attitude_sigma_deg: [0.003; 3] }
            }
            ErrorModel::Outage => {
                e.process = gauss_markov(25.0, 20.0);
                e.outage_pass = Some(cfg.drive.passes.saturating_sub(1));
            }
            ErrorModel::Calibration => {
                e.calibration = CalibrationErrors {
                    boresight_left_deg: [0.01, -0.005, 0.02],
                    boresight_right_deg: [-0.01, 0.008, -0.015],
                    lever_arm_left_m: [0.01, -0.005, 0.008],
                    lever_arm_right_m: [-0.008, 0.006, -0.01],
                    range_scale_ppm: 50.0,
                    range_offset_m: 0.003,
                }
            }
        }
    }
}

macro_rules! named {
    ($t:ty, $what:literal) => {
        impl fmt::Display for $t {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(self.name())
            }
        }

        impl FromStr for $t {
            type Err = String;
            fn from_str(s: &str) -> Result<Self, Self::Err> {
                let wanted = s.trim().replace('-', "_");
                <$t>::ALL.into_iter().find(|k| k.name().eq_ignore_ascii_case(&wanted)).ok_or_else(|| {
                    let names: Vec<&str> = <$t>::ALL.iter().map(|k| k.name()).collect();
                    format!("unknown {} `{s}`; expected one of {}", $what, names.join(", "))
                })
            }
        }
    };
}

named!(Scene, "scene");
named!(ErrorModel, "error model");

/// Rings of the accuracy matrix's multi-beam head.
pub const MULTIBEAM_RINGS: u32 = 32;
/// Its firings per revolution (3.6°): a sparse azimuth, as the matrix's profile heads are sparse
/// (about 30 k shots per second against their 10 k).
pub const MULTIBEAM_FIRINGS: u32 = 100;

/// One campaign of the accuracy matrix: scene, errors, passes per street and heads per vehicle
/// (profile heads, or one multi-beam head on the roof).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
pub struct Scenario {
    pub scene: Scene,
    pub errors: ErrorModel,
    pub passes: u32,
    pub heads: u32,
    /// One multi-beam head ([`MULTIBEAM_RINGS`] rings at 10 Hz) instead of the profile heads.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub multibeam: bool,
}

impl Scenario {
    pub fn new(scene: Scene, errors: ErrorModel, passes: u32, heads: u32) -> Self {
        Self { scene, errors, passes, heads, multibeam: false }
    }

    /// The same campaign scanned by one multi-beam head on the roof.
    pub fn multibeam(self) -> Self {
        Self { heads: 1, multibeam: true, ..self }
    }

    /// `scene/errors/Np` with `/1h` for a single head, `/mb32` for a 32-ring multi-beam head.
    pub fn name(&self) -> String {
        let heads = if self.multibeam {
            format!("/mb{MULTIBEAM_RINGS}")
        } else if self.heads == 1 {
            "/1h".to_string()
        } else {
            String::new()
        };
        format!("{}/{}/{}p{heads}", self.scene.name(), self.errors.name(), self.passes)
    }

    /// The campaign: two blocks of `block_m` (a figure 8 whose every street is driven on every
    /// pass) at a scanner density of `revolutions_per_s × points_per_revolution`.
    pub fn config(&self, seed: u64, block_m: f64, revolutions_per_s: f64, points_per_revolution: u32) -> SimConfig {
        let mut cfg = SimConfig::for_scale(crate::Scale::Small, seed);
        cfg.name = format!("accuracy-{}-{seed}", self.name().replace('/', "-"));
        cfg.town.block_m = block_m;
        cfg.drive.passes = self.passes;
        cfg.drive.stop_pass = Some(0);
        cfg.scanner.heads = self.heads;
        cfg.scanner.revolutions_per_s = revolutions_per_s;
        cfg.scanner.points_per_revolution = points_per_revolution;
        if self.multibeam {
            cfg.scanner.multibeam = Some(crate::MultiBeamConfig {
                rings: MULTIBEAM_RINGS,
                firings_per_revolution: MULTIBEAM_FIRINGS,
                ..crate::MultiBeamConfig::default()
            });
        }
        self.scene.apply(&mut cfg);
        self.errors.apply(&mut cfg);
        cfg
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_and_every_combination_is_a_valid_campaign() {
        assert_eq!("open-road".parse::<Scene>(), Ok(Scene::OpenRoad));
        assert_eq!("Gauss_Markov_slow".parse::<ErrorModel>(), Ok(ErrorModel::GaussMarkovSlow));
        assert!("town".parse::<Scene>().unwrap_err().contains("grid, oblique"));
        let mb = Scenario::new(Scene::Grid, ErrorModel::GaussMarkov, 4, 2).multibeam();
        assert_eq!(mb.name(), "grid/gauss_markov/4p/mb32");
        assert_eq!(mb.config(1, 48.0, 30.0, 200).scanner.multibeam.map(|m| m.rings), Some(32));
        for scene in Scene::ALL {
            for errors in ErrorModel::ALL {
                for (passes, heads, multibeam) in [(2, 1, false), (4, 2, false), (8, 2, false), (4, 1, true)] {
                    let s = Scenario::new(scene, errors, passes, heads);
                    let s = if multibeam { s.multibeam() } else { s };
                    let cfg = s.config(1, 48.0, 30.0, 200);
                    assert!(cfg.problems().is_empty(), "{}: {:?}", s.name(), cfg.problems());
                    let json = serde_json::to_string(&cfg).unwrap();
                    assert_eq!(serde_json::from_str::<SimConfig>(&json).unwrap(), cfg, "{}", s.name());
                }
            }
        }
    }
}
