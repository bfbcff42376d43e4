//! Every knob of a simulated campaign, with presets per [`Scale`]. All randomness derives from
//! `seed`, so a config fully determines the output bytes.

pub use crate::control::ControlConfig;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// Campaign size presets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Scale {
    /// < 300 k points, seconds in a debug build: unit and integration tests.
    Tiny,
    /// A few million points: the README demo.
    Small,
    /// 20–30 M points: benchmarks.
    Medium,
    /// ≥ 200 M points: the paper's order of magnitude, streamed to disk.
    Large,
}

impl Scale {
    pub const ALL: [Scale; 4] = [Scale::Tiny, Scale::Small, Scale::Medium, Scale::Large];

    pub fn name(self) -> &'static str {
        match self {
            Scale::Tiny => "tiny",
            Scale::Small => "small",
            Scale::Medium => "medium",
            Scale::Large => "large",
        }
    }
}

impl fmt::Display for Scale {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown scale `{0}`; expected tiny, small, medium or large")]
pub struct ParseScaleError(pub String);

impl FromStr for Scale {
    type Err = ParseScaleError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Scale::ALL
            .into_iter()
            .find(|k| k.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| ParseScaleError(s.into()))
    }
}

/// The whole campaign.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    /// Campaign name written to the manifest.
    pub name: String,
    /// The preset this config started from (informational).
    pub scale: Scale,
    pub seed: u64,
    /// Absolute coordinates of the town's local origin (centre of the street grid, road level).
    pub origin: [f64; 3],
    pub town: TownConfig,
    pub drive: DriveConfig,
    pub scanner: ScannerConfig,
    pub errors: ErrorConfig,
    /// Surveyed ground control and check targets along the driven streets (none by default).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub control: Option<ControlConfig>,
}

/// The street grid and what stands along the streets. Ranges `[lo, hi]` are drawn uniformly.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TownConfig {
    /// Blocks enclosed by driven streets, west–east and south–north. One ring of blocks more is
    /// built around them so every driven street has buildings on both sides.
    pub blocks_x: u32,
    pub blocks_y: u32,
    /// Distance between street centre lines.
    pub block_m: f64,
    /// Half the carriageway (two lanes).
    pub road_half_width_m: f64,
    pub curb_height_m: f64,
    pub sidewalk_width_m: f64,
    /// Ground slope: `z = grade[0]·x + grade[1]·y` (local metres). Implemented as a shear, so every
    /// box stays axis-aligned in the sheared frame.
    pub grade: [f64; 2],
    pub building_depth_m: f64,
    pub building_width_m: [f64; 2],
    pub building_height_m: [f64; 2],
    /// Probability that a gap (no building) comes next along a block side.
    pub gap_probability: f64,
    pub gap_width_m: [f64; 2],
    pub floor_height_m: [f64; 2],
    /// Window axis spacing along the façade.
    pub bay_m: [f64; 2],
    pub window_width_m: [f64; 2],
    pub window_height_m: [f64; 2],
    /// Windows sit this far behind the wall plane.
    pub window_recess_m: [f64; 2],
    /// Pilasters and oriels protrude this far in front of the wall plane.
    pub relief_m: [f64; 2],
    pub pole_spacing_m: f64,
    pub pole_height_m: [f64; 2],
    pub pole_radius_m: f64,
    /// Spacing of tree slots along the sidewalk; each slot is planted with `tree_probability`.
    pub tree_spacing_m: f64,
    pub tree_probability: f64,
    pub trunk_radius_m: [f64; 2],
    pub crown_radius_m: [f64; 2],
    /// Height of the crown centre above the sidewalk.
    pub crown_height_m: [f64; 2],
    /// Mean free path of a laser ray inside a crown.
    pub foliage_mean_free_path_m: f64,
    /// Probability that a 6.5 m parking slot along the curb holds a car (parked half on the sidewalk).
    pub car_probability: f64,
    /// No poles, trees or cars this close to a block corner (junctions stay clear).
    pub corner_clearance_m: f64,
    /// Cell edge of the 2D ray-casting grid.
    pub grid_cell_m: f64,
    /// Angle by which the south–north streets lean from the perpendicular (degrees, |·| < 60):
    /// the street grid becomes a grid of parallelograms whose streets cross at 90° − skew and
    /// 90° + skew. 0 keeps the right-angled grid.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub skew_deg: f64,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn is_two(v: &u32) -> bool {
    *v == 2
}

fn two() -> u32 {
    2
}

/// Vehicle passes: routes, speeds, the traffic-light stop and body motion.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveConfig {
    /// Number of passes (one trajectory and two strips each).
    pub passes: u32,
    /// Radius of the rounded corners of the street centre lines.
    pub turn_radius_m: f64,
    /// Lane centre distance from the road centre line (right-hand traffic).
    pub lane_offset_m: f64,
    /// Every pass whose index `p` has `p % other_lane_every == other_lane_every − 1` drives in the
    /// other (left) lane; 0 disables.
    pub other_lane_every: u32,
    pub cruise_speed_m_s: [f64; 2],
    pub turn_speed_m_s: [f64; 2],
    /// Mean acceleration and deceleration (the peak of the smooth profile is 1.5× this).
    pub accel_m_s2: f64,
    /// Distance driven beyond one full figure 8, so a pass overlaps its own beginning.
    pub overlap_m: f64,
    /// The pass (0-based) that stops at a traffic light.
    pub stop_pass: Option<u32>,
    pub stop_duration_s: f64,
    /// Body origin above the road surface.
    pub body_height_m: f64,
    pub trajectory_rate_hz: f64,
    /// GPS time of the first pass; each further pass starts `pass_time_step_s` later.
    pub gps_time_base_s: f64,
    pub pass_time_step_s: f64,
    /// Strips start this long after their trajectory starts and end this long before it ends.
    pub strip_margin_s: f64,
    /// Body roll per lateral acceleration (leaning out of turns).
    pub roll_per_lateral_accel_deg: f64,
    /// Body pitch per longitudinal acceleration (nose dips when braking).
    pub pitch_per_accel_deg: f64,
    /// Time constant of the suspension's response to accelerations.
    pub suspension_time_constant_s: f64,
    /// Amplitude of road-roughness roll/pitch sway.
    pub sway_deg: f64,
    /// Amplitude of road-roughness heave.
    pub heave_m: f64,
}

/// Two VMX-250-like scan heads.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScannerConfig {
    pub revolutions_per_s: f64,
    /// Measurements per revolution; dividing 60000 makes every scan angle exact in LAS's 0.006° units.
    pub points_per_revolution: u32,
    /// Scan planes contain the body z axis and the horizontal direction at ±this azimuth from the
    /// driving direction (+ left head, − right head).
    pub azimuth_deg: f64,
    pub lever_arm_left_m: [f64; 3],
    pub lever_arm_right_m: [f64; 3],
    pub max_range_m: f64,
    pub min_range_m: f64,
    /// σ of the range noise.
    pub range_noise_m: f64,
    /// Scan heads per vehicle: 2 (left and right) or 1 (the left head alone).
    #[serde(default = "two", skip_serializing_if = "is_two")]
    pub heads: u32,
    /// A multi-beam spinning head on the roof instead of the profile heads (`heads`,
    /// `revolutions_per_s`, `points_per_revolution`, `azimuth_deg` and their lever arms then
    /// do not apply).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub multibeam: Option<MultiBeamConfig>,
}

/// A Velodyne/Ouster/Hesai-style head: `rings` lasers at fixed elevations spin about the body's
/// z axis; each firing measures all rings at the same azimuth and GPS time. The LAS files carry
/// the laser number in the user-data byte; the lasers are numbered alternately from the lower
/// and the upper half of the field of view, as many real heads number them, not by elevation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MultiBeamConfig {
    /// Lasers, spread evenly over `elevation_deg`; 2–255.
    pub rings: u32,
    /// Elevation of the lowest and the highest ring above the body's x–y plane, degrees.
    pub elevation_deg: [f64; 2],
    pub revolutions_per_s: f64,
    /// Firings per revolution; dividing 60000 makes every firing's azimuth, written as the scan
    /// angle, exact in LAS's 0.006° units.
    pub firings_per_revolution: u32,
    pub lever_arm_m: [f64; 3],
}

impl Default for MultiBeamConfig {
    /// 32 rings over −25°…+15° at 10 Hz and 0.36° per firing, on the roof.
    fn default() -> Self {
        Self {
            rings: 32,
            elevation_deg: [-25.0, 15.0],
            revolutions_per_s: 10.0,
            firings_per_revolution: 1000,
            lever_arm_m: [-0.3, 0.0, 0.55],
        }
    }
}

impl MultiBeamConfig {
    /// Elevation of laser `laser` (degrees): even lasers take the lower half of the rings from
    /// the bottom up, odd lasers the upper half.
    pub fn elevation_deg(&self, laser: u32) -> f64 {
        let lower = self.rings.div_ceil(2);
        let ring = if laser.is_multiple_of(2) { laser / 2 } else { lower + laser / 2 };
        let [lo, hi] = self.elevation_deg;
        lo + (hi - lo) * ring as f64 / (self.rings - 1).max(1) as f64
    }

    fn problems(&self, out: &mut Vec<String>) {
        if !(2..=255).contains(&self.rings) {
            out.push(format!("scanner.multibeam.rings must be 2–255 (the LAS user-data byte), got {}", self.rings));
        }
        let [lo, hi] = self.elevation_deg;
        if !(lo.is_finite() && hi.is_finite() && -90.0 < lo && lo < hi && hi < 90.0) {
            out.push(format!(
                "scanner.multibeam.elevation_deg must be [lo, hi] with −90 < lo < hi < 90, got {:?}",
                self.elevation_deg
            ));
        }
        if !(self.revolutions_per_s.is_finite() && self.revolutions_per_s > 0.0) {
            out.push(format!(
                "scanner.multibeam.revolutions_per_s must be a positive number, got {}",
                self.revolutions_per_s
            ));
        }
        if self.firings_per_revolution < 8 || 60_000 % self.firings_per_revolution != 0 {
            out.push(format!(
                "scanner.multibeam.firings_per_revolution ({}) must be at least 8 and divide 60000 (e.g. 400, 1000, \
                 1200, 2000)",
                self.firings_per_revolution
            ));
        }
        if self.lever_arm_m.iter().any(|v| !v.is_finite()) {
            out.push("scanner.multibeam.lever_arm_m must hold finite numbers".into());
        }
    }
}

/// GNSS/IMU error processes (per pass). σ ranges `[lo, hi]` are drawn per pass and axis; the
/// realised RMS over the pass equals the drawn σ exactly.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ErrorConfig {
    pub position_sigma_m: [f64; 2],
    pub position_period_s: [f64; 2],
    pub roll_pitch_sigma_deg: [f64; 2],
    pub heading_sigma_deg: [f64; 2],
    pub attitude_period_s: [f64; 2],
    /// Sinusoids per error channel.
    pub components: u32,
    /// The error clock advances at `floor + (1 − floor)·min(v / nominal_speed, 1)` per second
    /// (zero-velocity updates keep a standing vehicle's error nearly constant).
    pub zupt_floor: f64,
    pub nominal_speed_m_s: f64,
    /// The pass (0-based) with a GNSS outage.
    pub outage_pass: Option<u32>,
    pub outage_duration_s: [f64; 2],
    /// Peak of the horizontal drift bump at the end of the outage.
    pub outage_drift_m: [f64; 2],
    /// Vertical drift as a fraction of the horizontal peak.
    pub outage_vertical_fraction: f64,
    /// Extra heading drift at the end of the outage.
    pub outage_heading_drift_deg: f64,
    /// After the outage the bump decays smoothly over this time.
    pub outage_decay_s: f64,
    /// The random process of the pose errors. The default, sums of sinusoids, is drawn from the
    /// fields above; the others carry their own parameters.
    #[serde(default, skip_serializing_if = "ErrorProcess::is_sinusoids")]
    pub process: ErrorProcess,
    /// Constant calibration errors of the scan heads (none by default).
    #[serde(default, skip_serializing_if = "CalibrationErrors::is_none")]
    pub calibration: CalibrationErrors,
}

/// The random process of the GNSS/IMU pose errors of every pass, per position axis (world x,
/// y, z) and attitude angle (roll, pitch, heading). All are driven by the pass's own random
/// stream, so a campaign is a pure function of its seed.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ErrorProcess {
    /// Sums of random-phase sinusoids of the error clock (`ErrorConfig`'s σ and period ranges).
    #[default]
    Sinusoids,
    /// First-order Gauss–Markov: stationary, variance σ², autocorrelation `exp(−|Δt|/τ)`.
    GaussMarkov {
        position_sigma_m: [f64; 3],
        position_tau_s: [f64; 3],
        attitude_sigma_deg: [f64; 3],
        attitude_tau_s: [f64; 3],
    },
    /// Random walk from zero at the pass's start: variance grows as `q²·t`.
    RandomWalk { position_m_per_sqrt_s: [f64; 3], attitude_deg_per_sqrt_s: [f64; 3] },
    /// Independent normal errors at every trajectory sample.
    WhiteNoise { position_sigma_m: [f64; 3], attitude_sigma_deg: [f64; 3] },
}

impl ErrorProcess {
    pub fn is_sinusoids(&self) -> bool {
        matches!(self, ErrorProcess::Sinusoids)
    }

    /// Short name (`sinusoids`, `gauss_markov`, `random_walk`, `white_noise`).
    pub fn name(&self) -> &'static str {
        match self {
            ErrorProcess::Sinusoids => "sinusoids",
            ErrorProcess::GaussMarkov { .. } => "gauss_markov",
            ErrorProcess::RandomWalk { .. } => "random_walk",
            ErrorProcess::WhiteNoise { .. } => "white_noise",
        }
    }

    fn problems(&self, out: &mut Vec<String>) {
        let mut check = |name: &str, v: [f64; 3], positive: bool| {
            if v.iter().any(|x| !x.is_finite() || *x < 0.0 || (positive && *x <= 0.0)) {
                let what = if positive { "positive" } else { "zero or positive" };
                out.push(format!("errors.process.{name} must be three {what} numbers, got {v:?}"));
            }
        };
        match self {
            ErrorProcess::Sinusoids => {}
            ErrorProcess::GaussMarkov { position_sigma_m, position_tau_s, attitude_sigma_deg, attitude_tau_s } => {
                check("position_sigma_m", *position_sigma_m, false);
                check("position_tau_s", *position_tau_s, true);
                check("attitude_sigma_deg", *attitude_sigma_deg, false);
                check("attitude_tau_s", *attitude_tau_s, true);
            }
            ErrorProcess::RandomWalk { position_m_per_sqrt_s, attitude_deg_per_sqrt_s } => {
                check("position_m_per_sqrt_s", *position_m_per_sqrt_s, false);
                check("attitude_deg_per_sqrt_s", *attitude_deg_per_sqrt_s, false);
            }
            ErrorProcess::WhiteNoise { position_sigma_m, attitude_sigma_deg } => {
                check("position_sigma_m", *position_sigma_m, false);
                check("attitude_sigma_deg", *attitude_sigma_deg, false);
            }
        }
    }
}

/// Constant errors of the scan heads' calibration: the manifest states the nominal lever arms and
/// zero boresight, the points are measured with these added. Angles rotate the head's frame
/// about the body's x, y and z axes (roll, pitch, yaw).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CalibrationErrors {
    pub boresight_left_deg: [f64; 3],
    pub boresight_right_deg: [f64; 3],
    pub lever_arm_left_m: [f64; 3],
    pub lever_arm_right_m: [f64; 3],
    /// Range scale error, parts per million: the measured range is `ρ·(1 + s·10⁻⁶) + offset`.
    pub range_scale_ppm: f64,
    pub range_offset_m: f64,
}

impl CalibrationErrors {
    pub fn is_none(&self) -> bool {
        *self == CalibrationErrors::default()
    }
}

impl SimConfig {
    /// The preset for `scale`.
    pub fn for_scale(scale: Scale, seed: u64) -> Self {
        let mut town = TownConfig::default();
        let mut drive = DriveConfig::default();
        let mut scanner = ScannerConfig::default();
        let mut errors = ErrorConfig::default();
        match scale {
            Scale::Tiny => {
                town.block_m = 36.0;
                drive.passes = 2;
                drive.turn_radius_m = 8.0;
                drive.stop_pass = Some(0);
                errors.outage_pass = Some(1);
                scanner.revolutions_per_s = 15.0;
                scanner.points_per_revolution = 100;
            }
            Scale::Small => {
                town.block_m = 60.0;
                drive.passes = 4;
                drive.stop_pass = Some(1);
                errors.outage_pass = Some(2);
                scanner.revolutions_per_s = 40.0;
                scanner.points_per_revolution = 240;
            }
            Scale::Medium => {
                town.blocks_x = 3;
                town.blocks_y = 2;
                town.block_m = 70.0;
                drive.passes = 8;
                drive.stop_pass = Some(2);
                errors.outage_pass = Some(5);
                scanner.revolutions_per_s = 100.0;
                scanner.points_per_revolution = 250;
            }
            Scale::Large => {
                town.blocks_x = 4;
                town.blocks_y = 3;
                town.block_m = 80.0;
                drive.passes = 48;
                drive.stop_pass = Some(3);
                errors.outage_pass = Some(10);
                scanner.revolutions_per_s = 100.0;
                scanner.points_per_revolution = 400;
            }
        }
        drive.pass_time_step_s = 3600.0;
        SimConfig {
            name: format!("sim-{}-{seed}", scale.name()),
            scale,
            seed,
            origin: [549_800.0, 5_803_400.0, 55.0],
            town,
            drive,
            scanner,
            errors,
            control: None,
        }
    }

    /// Problems that make the config unusable, each as a sentence.
    pub fn problems(&self) -> Vec<String> {
        let mut out = Vec::new();
        let mut positive = |name: &str, v: f64| {
            if !(v.is_finite() && v > 0.0) {
                out.push(format!("{name} must be a positive number, got {v}"));
            }
        };
        let (t, d, s, e) = (&self.town, &self.drive, &self.scanner, &self.errors);
        positive("town.block_m", t.block_m);
        positive("town.road_half_width_m", t.road_half_width_m);
        positive("town.grid_cell_m", t.grid_cell_m);
        positive("town.foliage_mean_free_path_m", t.foliage_mean_free_path_m);
        positive("town.pole_spacing_m", t.pole_spacing_m);
        positive("town.tree_spacing_m", t.tree_spacing_m);
        positive("drive.turn_radius_m", d.turn_radius_m);
        positive("drive.accel_m_s2", d.accel_m_s2);
        positive("drive.trajectory_rate_hz", d.trajectory_rate_hz);
        positive("drive.turn_speed_m_s[0]", d.turn_speed_m_s[0]);
        positive("scanner.revolutions_per_s", s.revolutions_per_s);
        positive("scanner.max_range_m", s.max_range_m);
        positive("errors.nominal_speed_m_s", e.nominal_speed_m_s);
        let mut ranges = vec![
            ("town.building_width_m", t.building_width_m),
            ("town.building_height_m", t.building_height_m),
            ("town.floor_height_m", t.floor_height_m),
            ("town.bay_m", t.bay_m),
            ("drive.cruise_speed_m_s", d.cruise_speed_m_s),
            ("drive.turn_speed_m_s", d.turn_speed_m_s),
            ("errors.position_period_s", e.position_period_s),
            ("errors.attitude_period_s", e.attitude_period_s),
        ];
        ranges.extend([("errors.position_sigma_m", e.position_sigma_m), ("town.crown_radius_m", t.crown_radius_m)]);
        for (name, r) in ranges {
            if !(r[0].is_finite() && r[1].is_finite() && r[0] > 0.0 && r[0] <= r[1]) {
                out.push(format!("{name} must be a range [lo, hi] with 0 < lo ≤ hi, got {r:?}"));
            }
        }
        if t.blocks_x == 0 || t.blocks_y == 0 || t.blocks_x + t.blocks_y < 3 {
            out.push("town needs at least two blocks side by side (blocks_x + blocks_y ≥ 3) for a figure 8".into());
        }
        let straight = t.block_m - 2.0 * d.turn_radius_m;
        if straight < 2.0 {
            out.push(format!(
                "town.block_m ({}) leaves no straight between turns of radius {}",
                t.block_m, d.turn_radius_m
            ));
        }
        if d.turn_radius_m <= d.lane_offset_m.abs() + 1.0 {
            out.push("drive.turn_radius_m must exceed the lane offset by more than 1 m".into());
        }
        let interior = t.block_m - 2.0 * (t.road_half_width_m + t.sidewalk_width_m);
        if interior < 8.0 {
            out.push(format!("town.block_m ({}) leaves only {interior:.1} m of building land per block", t.block_m));
        }
        if d.passes == 0 {
            out.push("drive.passes must be at least 1".into());
        }
        if s.points_per_revolution < 8 {
            out.push("scanner.points_per_revolution must be at least 8".into());
        } else if 60_000 % s.points_per_revolution != 0 {
            out.push(format!(
                "scanner.points_per_revolution ({}) must divide 60000: LAS stores scan angles in 0.006° units, so \
                 only then is every measurement's angle exact (e.g. 240, 600, 1200, 1500, 2000, 3000)",
                s.points_per_revolution
            ));
        }
        if !(s.min_range_m >= 0.0 && s.min_range_m < s.max_range_m) {
            out.push("scanner.min_range_m must be in [0, max_range_m)".into());
        }
        if !(s.range_noise_m >= 0.0 && s.range_noise_m.is_finite()) {
            out.push("scanner.range_noise_m must be zero or positive".into());
        }
        e.process.problems(&mut out);
        let c = &e.calibration;
        let calibration = [c.boresight_left_deg, c.boresight_right_deg, c.lever_arm_left_m, c.lever_arm_right_m];
        if calibration.iter().flatten().chain([&c.range_scale_ppm, &c.range_offset_m]).any(|v| !v.is_finite()) {
            out.push("errors.calibration must hold finite numbers only".into());
        }
        if let Some(m) = &s.multibeam {
            m.problems(&mut out);
        }
        if let Some(c) = &self.control {
            c.problems(&mut out);
        }
        if !(s.heads == 1 || s.heads == 2) {
            out.push(format!("scanner.heads must be 1 or 2, got {}", s.heads));
        }
        if !(t.skew_deg.is_finite() && t.skew_deg.abs() < 60.0) {
            out.push(format!("town.skew_deg must lie between −60 and 60 degrees, got {}", t.skew_deg));
        }
        if e.components == 0 {
            out.push("errors.components must be at least 1".into());
        }
        if !(d.strip_margin_s.is_finite() && d.strip_margin_s >= 0.0) {
            out.push("drive.strip_margin_s must be zero or positive".into());
        }
        for (name, p) in [("stop_pass", d.stop_pass), ("outage_pass", e.outage_pass)] {
            if let Some(p) = p {
                if p >= d.passes {
                    out.push(format!("{name} {p} does not exist (there are {} passes)", d.passes));
                }
            }
        }
        out
    }
}

impl Default for TownConfig {
    fn default() -> Self {
        Self {
            blocks_x: 2,
            blocks_y: 1,
            block_m: 60.0,
            road_half_width_m: 3.5,
            curb_height_m: 0.12,
            sidewalk_width_m: 3.0,
            grade: [0.012, 0.008],
            building_depth_m: 10.0,
            building_width_m: [8.0, 20.0],
            building_height_m: [8.0, 20.0],
            gap_probability: 0.12,
            gap_width_m: [2.0, 5.0],
            floor_height_m: [3.0, 3.6],
            bay_m: [2.6, 3.6],
            window_width_m: [1.1, 1.6],
            window_height_m: [1.3, 1.8],
            window_recess_m: [0.08, 0.15],
            relief_m: [0.10, 0.30],
            pole_spacing_m: 20.0,
            pole_height_m: [5.0, 7.0],
            pole_radius_m: 0.1,
            tree_spacing_m: 10.0,
            tree_probability: 0.5,
            trunk_radius_m: [0.12, 0.2],
            crown_radius_m: [2.0, 3.0],
            crown_height_m: [3.0, 7.0],
            foliage_mean_free_path_m: 1.0,
            car_probability: 0.45,
            corner_clearance_m: 9.0,
            grid_cell_m: 4.0,
            skew_deg: 0.0,
        }
    }
}

impl Default for DriveConfig {
    fn default() -> Self {
        Self {
            passes: 4,
            turn_radius_m: 9.0,
            lane_offset_m: 1.75,
            other_lane_every: 3,
            cruise_speed_m_s: [8.0, 10.0],
            turn_speed_m_s: [4.0, 5.0],
            accel_m_s2: 1.5,
            overlap_m: 15.0,
            stop_pass: None,
            stop_duration_s: 5.0,
            body_height_m: 1.8,
            trajectory_rate_hz: 200.0,
            gps_time_base_s: 4.0e8,
            pass_time_step_s: 3600.0,
            strip_margin_s: 0.5,
            roll_per_lateral_accel_deg: 0.3,
            pitch_per_accel_deg: 0.3,
            suspension_time_constant_s: 0.3,
            sway_deg: 0.03,
            heave_m: 0.004,
        }
    }
}

impl Default for ScannerConfig {
    fn default() -> Self {
        Self {
            revolutions_per_s: 100.0,
            points_per_revolution: 500,
            azimuth_deg: 45.0,
            lever_arm_left_m: [-0.6, 0.35, 0.45],
            lever_arm_right_m: [-0.6, -0.35, 0.45],
            max_range_m: 70.0,
            min_range_m: 1.0,
            range_noise_m: 0.005,
            heads: 2,
            multibeam: None,
        }
    }
}

impl Default for ErrorConfig {
    fn default() -> Self {
        Self {
            position_sigma_m: [0.1, 0.3],
            position_period_s: [20.0, 120.0],
            roll_pitch_sigma_deg: [0.008, 0.012],
            heading_sigma_deg: [0.016, 0.024],
            attitude_period_s: [5.0, 60.0],
            components: 4,
            zupt_floor: 0.05,
            nominal_speed_m_s: 8.0,
            outage_pass: None,
            outage_duration_s: [15.0, 20.0],
            outage_drift_m: [0.2, 0.3],
            outage_vertical_fraction: 0.4,
            outage_heading_drift_deg: 0.01,
            outage_decay_s: 20.0,
            process: ErrorProcess::Sinusoids,
            calibration: CalibrationErrors::default(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scale_parses_and_presets_are_valid() {
        assert_eq!("Small".parse::<Scale>().unwrap(), Scale::Small);
        assert!("huge".parse::<Scale>().unwrap_err().to_string().contains("tiny, small"));
        for scale in Scale::ALL {
            let c = SimConfig::for_scale(scale, 1);
            assert!(c.problems().is_empty(), "{scale}: {:?}", c.problems());
            let json = serde_json::to_string(&c).unwrap();
            assert_eq!(serde_json::from_str::<SimConfig>(&json).unwrap(), c);
        }
        let mut c = SimConfig::for_scale(Scale::Tiny, 1);
        c.drive.passes = 0;
        c.town.block_m = 10.0;
        let p = c.problems();
        assert!(p.iter().any(|m| m.contains("passes")) && p.iter().any(|m| m.contains("block_m")), "{p:?}");
        // `simulate --points-per-revolution`: real scanners' 0.3° and 0.12° steps are exact in
        // LAS's 0.006° units, 1,100 measurements per revolution are not.
        let mut c = SimConfig::for_scale(Scale::Small, 1);
        for (n, exact) in [(1_200, true), (3_000, true), (1_100, false)] {
            c.scanner.points_per_revolution = n;
            let p = c.problems();
            assert_eq!(p.is_empty(), exact, "{n}: {p:?}");
            assert!(exact || p[0].contains("must divide 60000"), "{p:?}");
        }
    }
}
