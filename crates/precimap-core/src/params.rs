//! Estimation parameters. Every field has the paper's default (§5, §6.2, §7.1); a manifest's
//! `parameters` object overrides single fields and may not name unknown ones.

use crate::calibration::CalibrationOptions;
use serde::{Deserialize, Serialize};

/// One step of the iteration schedule: the latent map's pixel size and the outlier threshold.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IterationStep {
    pub grid_m: f64,
    pub threshold_m: f64,
    /// Estimate attitude corrections in this step. The first, coarse steps solve for translation
    /// only: while strips are decimetres apart, coarse pixels and wrong associations would be
    /// absorbed by rotations, which the alternating map then locks in.
    #[serde(default = "default_true")]
    pub rotation: bool,
    /// Latent-map cell edge for this step; `None` uses `cell_size_m`. Coarse first steps use
    /// larger cells so that strips decimetres apart still fall into the same cell.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cell_m: Option<f64>,
    /// Capture cells: columns unbounded along the dominant axis of each point's normal (vertical
    /// for a road, horizontal for a façade), with surfaces told apart by normal only, so strips
    /// decimetres apart along a surface's normal are never split by a cell face. Vertical
    /// columns split the passes over a façade that lay near a cell face, and those groups then
    /// never met (docs/design/estimation.md, "The latent map").
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub column_cells: bool,
    /// Momentum ([`Parameters::momentum`]) may carry the previous step into this one. Heavy-ball
    /// momentum speeds up the slow common mode but keeps the fast modes ringing (√β ≈ 0.92 per
    /// iteration); steps without it settle. The default schedule's last six steps (thresholds
    /// under 2 cm) settle: with the consistent gradient, the largest anchor change of the last
    /// iteration falls 2.2–2.6 → 0.4–0.8 mm (median 0.40 → 0.13 mm) on small seeds 1, 2 and
    /// medium, the spreads within −6 … +5 % (docs/design/estimation.md, "Momentum and settling").
    #[serde(default = "default_true")]
    pub momentum: bool,
}

fn default_true() -> bool {
    true
}

impl IterationStep {
    /// Fields a schedule step must name; the others have defaults.
    pub const REQUIRED_FIELDS: [&'static str; 2] = ["grid_m", "threshold_m"];

    pub fn new(grid_m: f64, threshold_m: f64) -> Self {
        Self { grid_m, threshold_m, rotation: true, cell_m: None, column_cells: false, momentum: true }
    }

    /// The cell edge this step uses.
    pub fn cell_size(&self, params: &Parameters) -> f64 {
        self.cell_m.unwrap_or(params.cell_size_m)
    }

    /// Whether this step solves the common-mode field before the per-trajectory solves: every
    /// step but the capture steps (column cells), where one alternation nearly closes the gap
    /// anyway (measured on small seeds 1 and 2: solving it there too moved anchors by ~0.5 m in
    /// the first step and changed the final spreads by < 0.02 mm).
    pub fn solves_field(&self, params: &Parameters) -> bool {
        params.common_mode_field_m > 0.0 && !self.column_cells
    }

    /// Whether Anderson acceleration ([`Parameters::anderson_depth`]) records this iteration: a
    /// point-sampled step that no momentum carries into. Only there is an iteration a pure map
    /// of the corrections it starts from; extrapolating the momentum steps' sequence, which
    /// carries the last step on, made small seed 1's last change 2.61 mm instead of 0.44.
    pub fn accelerates(&self, momentum_carried: bool, params: &Parameters) -> bool {
        params.anderson_depth > 0 && !momentum_carried && self.grid_m < params.point_latent_below_grid_m
    }

    /// Whether the trajectories' estimated process model ([`Parameters::process_model`]) is
    /// updated after an iteration on this step: a point-sampled step that estimates the
    /// attitude, where the corrections are near their final shape and every axis is solved, and
    /// that allows momentum. The settling steps (no momentum, where Anderson acceleration
    /// combines iterations as one fixed map of the corrections) keep the σ's: a process model
    /// still moving there keeps the corrections moving to the last iteration.
    pub fn updates_process_model(&self, params: &Parameters) -> bool {
        params.process_model == ProcessModel::Estimated
            && self.rotation
            && self.momentum
            && self.grid_m < params.point_latent_below_grid_m
    }

    /// Whether an accelerated iteration with `previous`'s settings and this one belong to one
    /// history: the same unknowns and cells. Grid and threshold may differ (clearing the history
    /// at the 2 cm → 1 cm change left small seed 1 at 0.18 mm in iteration 18 instead of 0.13).
    pub fn continues_history(&self, previous: &IterationStep, params: &Parameters) -> bool {
        self.same_unknowns_and_cells(previous, params)
    }

    /// Both steps estimate the same unknowns (rotation or not) on the same cells.
    fn same_unknowns_and_cells(&self, other: &IterationStep, params: &Parameters) -> bool {
        self.rotation == other.rotation
            && self.column_cells == other.column_cells
            && self.cell_size(params) == other.cell_size(params)
    }

    /// Whether momentum carries `previous`'s correction step into this one: both steps evaluate
    /// the latent surface exactly at the points (the fine steps, which all build the same map)
    /// with the same cells and unknowns. Thresholds may differ. The coarse steps capture: one
    /// iteration brings the strips nearly together, and carrying that step on overshoots
    /// (measured on small seed 1: the second capture step moved 168 mm with β = 0.5 against
    /// 24 mm without).
    pub fn momentum_continues(&self, previous: &IterationStep, params: &Parameters) -> bool {
        let sampled = |s: &IterationStep| s.grid_m < params.point_latent_below_grid_m;
        params.momentum > 0.0
            && self.momentum
            && sampled(self)
            && sampled(previous)
            && self.same_unknowns_and_cells(previous, params)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Parameters {
    /// Distance between anchors along the trajectory (paper: 0.5 m).
    pub anchor_spacing_m: f64,
    /// The exported trajectory's corrections continue this far beyond the first and last anchor
    /// its strips observe (within the trajectory): the poses recorded before the first scan and
    /// after the last (the run-up and run-out) take what the smoothness and curvature terms
    /// predict from the estimated corrections, which carries their trend on, instead of the end
    /// anchor's correction held. Beyond it the correction is held; 0 holds it from the end
    /// anchors on. Estimation does not see these anchors. 10 m: the simulator's run-ups are
    /// 4–5 m, and the prediction fades over ~25 m (docs/design/estimation.md, "Run-up and
    /// run-out").
    pub end_extension_m: f64,
    /// Edge of a square map tile (paper: 15 m).
    pub tile_size_m: f64,
    /// Points within this distance of a tile border are also emitted to the neighbour (paper: 0.3 m).
    pub tile_overlap_m: f64,
    /// Points farther than this from the scan head are corrected but not used for estimation:
    /// far away the scan is sparse and grazing, yet its lever arm would dominate the attitude.
    pub max_range_m: f64,
    /// While the vehicle (nearly) stands still, a revolution is used only once the scan head has
    /// moved this far since the last used one; repeated revolutions add no geometry and make
    /// scan-image neighbourhoods degenerate.
    pub min_revolution_advance_m: f64,
    /// Where the points' normals and segments come from: `auto` (the scan image of a rotating
    /// head when its pattern is recognised, else neighbours in 3-D), `scan_image` or
    /// `neighbours` (docs/design/preprocessing.md).
    pub normals: NormalSource,
    /// Where the strips carry a multi-beam head's ring (laser) number: `user_data`,
    /// `scanner_channel` or `{"extra_bytes": NAME}`. With it, `auto` takes normals and segments
    /// from the ring image (rows = rings by elevation, columns = firings).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ring: Option<RingSource>,
    /// A strip of which a smaller share of points becomes usable (a normal, a segment, within
    /// `max_range_m`) stops the run with an error naming the strip and the likely reason, as does
    /// a campaign whose last iteration observes no point (no overlap between passes).
    pub min_usable_share: f64,
    /// Turns those errors into warnings: the run goes on with what it can use.
    pub allow_low_usable_share: bool,
    /// Edge of a latent-map cell (voxel) holding local surface models.
    pub cell_size_m: f64,
    /// Points join a cell's surface model when their normals agree within this angle.
    pub normal_group_angle_deg: f64,
    /// Form a cell's surface models per scan-image segment (another segment of the same strip
    /// pass joins only if coplanar; segments of different strips join by normal and plane
    /// distance) instead of by normal alone. On by default: on medium seed 1 the datum-free
    /// spreads are 4–10 % smaller, the latent map 13 % closer to the truth and 2.5 points more
    /// of the surface points are used. A triangle of another pass then also gives a point its
    /// latent height only if its corners lie in one segment of their pass
    /// (docs/design/estimation.md, "The latent map").
    pub segment_surfaces: bool,
    /// How far from a control or check point (`$.control`) the adjusted surfaces are observed:
    /// a point's surfaces are those within this distance whose plane passes through it. Half a
    /// metre holds a few hundred points of every pass at street density, and stays on the
    /// surfaces a surveyor measures (a marking on the road, a façade corner) rather than reaching
    /// a kerb or a window recess.
    pub control_radius_m: f64,
    /// σ of one point's distance from a control target's surface: the scanner's precision. A
    /// pass of `k` points observes a target to `√(σ_target² + σ²/k)`. Not `sigma_distance_m`,
    /// which is inflated because the latent map's millions of observations share surfaces and
    /// must not outweigh the GNSS/IMU prior: a target's few points are the only observation of
    /// the datum, and weighted that way the prior held the map 7–13 mm off the targets.
    pub control_point_sigma_m: f64,
    /// The scanners' mounting calibration to estimate with the trajectories (boresight, lever
    /// arm, range offset per scanner); by default none (docs/design/calibration.md).
    #[serde(skip_serializing_if = "CalibrationOptions::is_empty")]
    pub calibration: CalibrationOptions,
    /// Effective σ of one point-to-surface distance. The scanner is good to ~5 mm, but points
    /// share surfaces, pixels and triangles, so they are far from independent; weighting them
    /// as independent 5 mm observations lets tiny systematic errors outweigh the GNSS/IMU prior
    /// by orders of magnitude. 3 cm was measured better on every metric
    /// (docs/design/estimation.md, "Observations").
    pub sigma_distance_m: f64,
    /// σ of the prior on the total position correction, per anchor. Not the GNSS/IMU accuracy
    /// itself: the prior holds every anchor independently, so over a stretch of `n` anchors it
    /// holds their mean to σ/√n, while the real error is correlated over hundreds of metres
    /// (docs/design/estimation.md, "The per-trajectory solve").
    pub sigma_prior_position_m: f64,
    /// σ of the prior on the total attitude correction, per anchor (as for the position, an
    /// independent prior per anchor holds a stretch's mean far tighter than its σ reads). 0.02°:
    /// 0.05° makes small and medium agree better still, but at a real scanner's 0.3° step one
    /// stretch of street then swings by centimetres (docs/design/estimation.md, "The
    /// per-trajectory solve"). The heading has its own (`sigma_prior_heading_deg`): this is the
    /// tilt's.
    pub sigma_prior_rotation_deg: f64,
    /// σ of that prior about the vertical (the heading, for a vehicle that is nearly level); 0:
    /// `sigma_prior_rotation_deg` on all three axes. 0.05°: the tilt's 0.02° holds every pass to
    /// its own GNSS/IMU heading, so passes through one place keep different headings and the
    /// strips disagree (docs/design/estimation.md, "The per-trajectory solve"). The tilt keeps
    /// 0.02°, which a real scanner's 0.3° step needs.
    pub sigma_prior_heading_deg: f64,
    /// σ of the change in position correction between neighbouring anchors.
    pub sigma_smooth_position_m: f64,
    /// σ of the change in attitude correction between neighbouring anchors. 0.004°: attitude
    /// errors with periods from ~5 s change by up to ~0.0016° per 0.5 m at 8 m/s, and a stiffer
    /// term (0.001°) makes strips disagree where the attitude has to bend.
    pub sigma_smooth_rotation_deg: f64,
    /// σ of the second difference of the position correction over three neighbouring anchors
    /// (curvature). GNSS/IMU errors bend over hundreds of metres; a kink within metres is an
    /// artefact. 0 disables the term.
    pub sigma_curvature_position_m: f64,
    /// σ of the second difference of the attitude correction; 0 disables the term. 0.0003°,
    /// loose enough for the smoothness above.
    pub sigma_curvature_rotation_deg: f64,
    /// The curvature σ's above as every trajectory's process model (`fixed`), or as the floor
    /// from which each trajectory estimates its own, per axis (`estimated`): after every
    /// point-sampled iteration with momentum that estimates the attitude, each σ² moves halfway (in log space)
    /// towards the variance-component estimate `mean[(Δ²x̂)² + Var(Δ²x)]` over the trajectory's
    /// anchors, with `Var` from the solve's posterior covariance, and stays between the σ above
    /// and `√2 ×` the smoothness σ (the curvature of a random walk of that step). Where the data
    /// say little the posterior term keeps the σ where it is; where they are strong it follows
    /// them. Smooth (sinusoidal) GNSS/IMU errors want a stiff curvature term, Gauss–Markov and
    /// random-walk errors a loose one.
    #[serde(skip_serializing_if = "ProcessModel::is_fixed")]
    pub process_model: ProcessModel,
    /// An anchor's own observations are trusted only in directions carrying at least this share
    /// of its strongest direction's information (rotations compared as displacements at 10 m).
    pub weak_information_ratio: f64,
    /// Steps with pixels finer than this sample the other passes' surfaces for each point (its
    /// own pass contributes the point's own height) instead of rasterising every triangle into
    /// pixels of the step's grid, which would cost ~200 pixel writes per point at 2 cm: at pixel
    /// centres that follow the point spacing ([`Self::latent_pixel_share`]) or exactly at the
    /// points. Coarser steps keep the raster, whose pixels smooth the latent surface while
    /// strips are still far apart. 0 rasterises every step.
    pub point_latent_below_grid_m: f64,
    /// In those steps, sample the other passes' triangles at pixel centres: a raster per surface
    /// model whose pixel is this share of the model's mean point spacing (at least the step's
    /// grid), so that each triangle covers about one centre and the cost is O(points) instead of
    /// O(points × passes over a place). A point reads its own pixel: the other passes' heights
    /// at the centre, carried to the point along their mean slope, and its own pass by its own
    /// height. 0 evaluates every covering triangle exactly at the points (the exact route). At
    /// 0.7 every datum-free figure on small seeds 1–2 and medium seed 1 is within ±0.02 mm of the
    /// exact route's, the latent map is closer to the truth, and the 2 cm iteration is 1.4×
    /// (small) to 1.7× (medium) faster (docs/design/estimation.md, "The latent map"). With a
    /// consensus gate ([`Self::cover_agreement_thresholds`]) the exact route runs.
    pub latent_pixel_share: f64,
    /// Every step's outlier threshold is at least this many robust σ (1.4826 × median |e|) of the
    /// previous iteration's point-to-map distances; 0 keeps the schedule's thresholds as they are.
    /// The paper's final 7 mm suit a scanner with ~2.5 mm noise; with noisier ranges a fixed 7 mm
    /// rejects good points by the hundred thousand and truncates their distribution.
    pub threshold_floor_sigmas: f64,
    /// In point-sampled steps, a triangle of another pass adds its height to a point's latent
    /// height only where it lies within this many outlier thresholds of the consensus there
    /// (the mean of the point's own height and every covering triangle's); 0 takes every
    /// covering triangle. With one covering pass it changes nothing the outlier test does not
    /// already reject; where several passes cover a point, one pass's bridge over a step or a car
    /// it alone saw no longer spoils the mean of those that agree. Judged against the consensus,
    /// not the point alone: passes that are off together stay outliers of the rest instead of
    /// agreeing among themselves. Off by default: at 2 the datum-free spreads improve 0.1–2.5 % and
    /// points used rise ~0.5 points, but every covering pair is held until the consensus is
    /// known, and the largest anchor change of the last iteration grows on medium seed 2
    /// (docs/design/estimation.md, "The latent map").
    pub cover_agreement_thresholds: f64,
    /// Heavy-ball momentum β of the alternating least squares: each trajectory step adds
    /// β × its previous step, between the fine, point-sampled iterations whose steps allow it
    /// ([`IterationStep::momentum_continues`]). A shift shared by all passes at a place moves the map with
    /// it, so plain alternation relaxes it by only a few per cent per iteration; momentum turns a
    /// contraction ρ into about (ρ + β)/2 + √(((ρ + β)/2)² − β) without moving the fixed point.
    /// 0 disables it.
    pub momentum: f64,
    /// Node spacing of the common-mode field, the coarse level of the estimation: before the
    /// per-trajectory solves of every point-sampled step, one translation field over the whole
    /// campaign (bilinear between nodes this far apart) is solved with the latent map moving
    /// along, and added to every trajectory at its anchors. It moves the shift every pass at a
    /// place shares, which alternation relaxes by only a few per cent per iteration. 0 disables it.
    /// 7.5 m: medium seed 1's latent map lies 4.27 mm from the truth without the campaign's
    /// shift at 7.5 m against 5.52 mm at 15 m and 4.48 mm at 5 m. The field's sparse solve takes
    /// a street network of ~50 km² at 7.5 m with the heading (~215 km² at 15 m; without the
    /// heading ~85 and ~350 km²: `MAX_FIELD_FACTOR_ENTRIES` in `precimap-estimate`;
    /// docs/design/estimation.md, "The common-mode field").
    pub common_mode_field_m: f64,
    /// Whether momentum, in steps that solve the field, carries only the part of the last step
    /// that no field on the same nodes represents (the field re-solves the rest itself, so
    /// carrying it too makes the two levels fight). Off by default: it halves the last
    /// iterations' changes and makes small campaigns agree better without the campaign's shift
    /// (seed 1: 1.199 → 1.131 mm, seed 2: 0.621 → 0.572 mm), but medium agrees worse (2.90 →
    /// 2.99 mm; docs/design/estimation.md, "The common-mode field").
    pub field_free_momentum: bool,
    /// In steps that solve the common-mode field, solve with it one rotation of the whole
    /// campaign about its centre (the field's constant part is the translation): the rigid
    /// motion the strips' agreement cannot see, as the latent map moves with the strips.
    /// Alternation relaxes it only through the prior, by a share per iteration that shrinks as
    /// the data grow, so the campaign would keep the tilt its first iterations gave it. Solved
    /// with the field, the prior and smoothness decide it at once. On by default: at a real
    /// scanner's 0.3° step the campaign's tilt falls 4.6–6× and the latent map comes 18–27 %
    /// closer to the truth without the campaign's shift; at 1.5° the figures move by 2 % or less
    /// (docs/design/estimation.md, "The campaign's rotation").
    pub campaign_motion: bool,
    /// Give the common-mode field a heading too: a rotation about the vertical, bilinear between
    /// the same nodes, added to every anchor's attitude correction. Every pass through a place
    /// turning with the map about a point near them (the translation field's gradient carrying
    /// the positions round) changes no residual, only the prior and smoothness see it, so
    /// alternation relaxes it slowly, and more slowly the looser the heading's prior
    /// (`sigma_prior_heading_deg`). Solved with the field, they decide it at once. On by default:
    /// iteration 18 comes within 0.12 mm RMS of the fixed point on small s1 (0.95 mm without),
    /// and the latent map 1.5–12 % closer to the truth (docs/design/estimation.md, "The
    /// common-mode field").
    pub common_mode_heading: bool,
    /// Give the common-mode field a tilt too (needs `common_mode_heading`): rotations about the
    /// two horizontal axes, bilinear between the same nodes, added to every anchor's attitude
    /// correction, so that the field turns the passes at a place about any axis. Every pass
    /// through a place tilting with the map (the translation field's vertical gradient carrying
    /// the heights along) is as invisible to the strips as the shared heading, and the denser
    /// the scanner, the smaller the prior's share of the information and the slower alternation
    /// relaxes it. Off by default: at a real scanner's 0.3° step iteration 18 has 28 % less
    /// vertical error, but the iteration settles at a less accurate point than the default
    /// reaches by running on, and the 1.5° campaigns lose 0.3–4.5 % (docs/design/estimation.md,
    /// "The common-mode field").
    pub common_mode_tilt: bool,
    /// In point-sampled steps, give each pass the gradient of the cost the common-mode field
    /// minimises: a point's own pass is weighted by its share `c/(c+1)` in the latent height
    /// (`c` other passes' triangles there), and every other pass whose triangle covers the point
    /// is pulled by the point's residual with weight `1/(c+1)` (the transpose of the latent
    /// height's dependence on that triangle). Without it the per-trajectory solves hold the map
    /// fixed, and their fixed point differs from the field's wherever passes sample a place
    /// with different densities (docs/design/estimation.md, "The consistent gradient"). On by
    /// default: the median anchor's last change falls ~3× (to 0.4 mm) and the datum-free spreads
    /// improve on small, at ~1.2× the map task's CPU.
    pub consistent_gradient: bool,
    /// Anderson acceleration over the settling iterations: each of them (point-sampled, no
    /// momentum carried into it) records where it started and where it ended, and the next one
    /// starts from the combination of the last `anderson_depth` + 1 results that best cancels
    /// their steps (`precimap_estimate::anderson`). The fixed point does not move. With depth 5
    /// a 48-step schedule (under a stiffer attitude prior) converged in 19 / 20 / 25 iterations
    /// instead of 26 / 29 / 44 on small seeds 1, 2 and medium seed 1, to the same figures
    /// (≤ 0.01 mm). Within the default schedule it changes small seeds 1 and 2's figures by 1.3 %
    /// or less either way, and iteration 18's largest change falls 2.8–3.8×
    /// (docs/design/estimation.md, "Anderson acceleration"). 0 turns it off.
    pub anderson_depth: usize,
    /// Iterations in order; estimation stops early once converged on the last step's settings.
    pub schedule: Vec<IterationStep>,
    /// Converged when no anchor moves a point at 10 m range by more than this between iterations.
    pub convergence_tolerance_m: f64,
    /// Voxel edge of the exported latent map (`OUT/latent/`): one point per voxel and surface
    /// side, the mean of the last iteration's observations moved onto the latent surface. 0
    /// writes no latent map.
    pub latent_map_grid_m: f64,
}

impl Default for Parameters {
    fn default() -> Self {
        Self {
            anchor_spacing_m: 0.5,
            end_extension_m: 10.0,
            tile_size_m: 15.0,
            tile_overlap_m: 0.3,
            max_range_m: 100.0,
            min_revolution_advance_m: 0.03,
            normals: NormalSource::Auto,
            ring: None,
            min_usable_share: 0.5,
            allow_low_usable_share: false,
            cell_size_m: 1.0,
            normal_group_angle_deg: 30.0,
            segment_surfaces: true,
            control_radius_m: 0.5,
            control_point_sigma_m: 0.005,
            calibration: CalibrationOptions::default(),
            sigma_distance_m: 0.03,
            sigma_prior_position_m: 1.0,
            sigma_prior_rotation_deg: 0.02,
            sigma_prior_heading_deg: 0.05,
            sigma_smooth_position_m: 0.005,
            sigma_smooth_rotation_deg: 0.004,
            sigma_curvature_position_m: 0.0001,
            sigma_curvature_rotation_deg: 0.0003,
            process_model: ProcessModel::Fixed,
            weak_information_ratio: 0.01,
            point_latent_below_grid_m: 0.03,
            latent_pixel_share: 0.7,
            threshold_floor_sigmas: 4.0,
            cover_agreement_thresholds: 0.0,
            momentum: 0.85,
            common_mode_field_m: 7.5,
            field_free_momentum: false,
            campaign_motion: true,
            common_mode_heading: true,
            common_mode_tilt: false,
            consistent_gradient: true,
            anderson_depth: 5,
            schedule: default_schedule(),
            convergence_tolerance_m: 1e-4,
            latent_map_grid_m: 0.1,
        }
    }
}

/// How each trajectory's curvature σ is chosen ([`Parameters::process_model`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProcessModel {
    /// The campaign's σ for every trajectory.
    #[default]
    Fixed,
    /// Each trajectory's own, estimated per axis from the campaign's σ upwards.
    Estimated,
}

impl ProcessModel {
    pub fn is_fixed(&self) -> bool {
        *self == Self::Fixed
    }
}

/// The source of the points' normals and segments ([`Parameters::normals`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NormalSource {
    /// The scan image when the strip's pattern is recognised as a rotating head's, else 3-D
    /// neighbours.
    #[default]
    Auto,
    /// Always the scan image.
    ScanImage,
    /// Always 3-D neighbours (any pattern).
    Neighbours,
    /// Always the ring image of a multi-beam head (needs [`Parameters::ring`]).
    RingImage,
}

/// Where a multi-beam head's ring number is in a strip's point records ([`Parameters::ring`]).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RingSource {
    /// The LAS user-data byte.
    UserData,
    /// The LAS 1.4 scanner channel (two bits: at most four rings).
    ScannerChannel,
    /// An extra-bytes field of this name (an unsigned or signed integer of 1 or 2 bytes).
    ExtraBytes(String),
}

/// The paper's schedule (§7.1) — grid 10 cm → 2 cm (most) → 1 cm, threshold 0.3 m → 7 mm,
/// translation only while the strips are far apart — preceded by two capture steps (3 m cells,
/// 25 cm pixels, 1 m threshold): GNSS/IMU errors of σ 0.3 m per axis put two passes up to ~1 m
/// apart, beyond the paper's first threshold. 18 iterations in all.
pub fn default_schedule() -> Vec<IterationStep> {
    let mut s = Vec::with_capacity(18);
    let mut push = |n: usize, grid_m: f64, threshold_m: f64, rotation: bool, cell_m: Option<f64>| {
        for _ in 0..n {
            s.push(IterationStep {
                cell_m,
                column_cells: cell_m.is_some(),
                rotation,
                // The steps with thresholds under 2 cm settle without momentum
                // (IterationStep::momentum).
                momentum: threshold_m >= 0.02,
                ..IterationStep::new(grid_m, threshold_m)
            });
        }
    };
    push(2, 0.25, 1.0, false, Some(3.0));
    push(1, 0.10, 0.30, false, None);
    push(1, 0.10, 0.15, true, None);
    push(1, 0.05, 0.08, true, None);
    push(1, 0.05, 0.05, true, None);
    push(2, 0.02, 0.03, true, None);
    push(4, 0.02, 0.02, true, None);
    push(1, 0.02, 0.015, true, None);
    push(1, 0.02, 0.012, true, None);
    push(2, 0.01, 0.01, true, None);
    push(2, 0.01, 0.007, true, None);
    s
}

/// A parameter that is out of its valid range: the field path and what is wrong.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("parameters.{field}: {problem}")]
pub struct ParameterProblem {
    pub field: String,
    pub problem: String,
}

impl Parameters {
    /// σ of the attitude prior about the world's x, y and z axes (degrees).
    pub fn sigma_prior_rotation_axes_deg(&self) -> [f64; 3] {
        let tilt = self.sigma_prior_rotation_deg;
        let heading = self.sigma_prior_heading_deg;
        [tilt, tilt, if heading > 0.0 { heading } else { tilt }]
    }

    /// The anchors a trajectory's exported corrections span: `estimated` (the first and last
    /// anchor its strips' points use) extended by [`Self::end_extension_m`] on either side, but
    /// not past the trajectory's own anchors `0..=trajectory_last`.
    pub fn exported_anchor_range(&self, estimated: (u32, u32), trajectory_last: u32) -> (u32, u32) {
        let extension = (self.end_extension_m / self.anchor_spacing_m).ceil();
        // Saturating: a huge extension just reaches the trajectory's ends.
        let extension =
            if extension.is_finite() && extension > 0.0 { extension.min(u32::MAX as f64) as u32 } else { 0 };
        let first = estimated.0.saturating_sub(extension);
        let last = estimated.1.saturating_add(extension).min(trajectory_last.max(estimated.1));
        (first, last)
    }

    /// Every out-of-range value, each with its field name.
    pub fn problems(&self) -> Vec<ParameterProblem> {
        let mut out = Vec::new();
        self.input_problems(&mut out);
        self.geometry_and_weight_problems(&mut out);
        self.schedule_problems(&mut out);
        self.field_and_map_problems(&mut out);
        out
    }

    /// The anchors and where strips carry a multi-beam ring.
    fn input_problems(&self, out: &mut Vec<ParameterProblem>) {
        check_positive(out, "anchor_spacing_m", self.anchor_spacing_m);
        if self.normals == NormalSource::RingImage && self.ring.is_none() {
            out.push(ParameterProblem {
                field: "normals".into(),
                problem: "ring_image needs parameters.ring, where the strips carry the ring number (user_data, \
                          scanner_channel or {\"extra_bytes\": NAME})"
                    .into(),
            });
        }
        if let Some(RingSource::ExtraBytes(name)) = &self.ring {
            if name.is_empty() || name.len() > 32 {
                out.push(ParameterProblem {
                    field: "ring.extra_bytes".into(),
                    problem: format!("must name an extra-bytes field (1–32 characters), got {name:?}"),
                });
            }
        }
    }

    /// Tiles, cells, ranges and the σ of every term.
    fn geometry_and_weight_problems(&self, out: &mut Vec<ParameterProblem>) {
        check_positive(out, "tile_size_m", self.tile_size_m);
        check_positive(out, "cell_size_m", self.cell_size_m);
        check_positive(out, "max_range_m", self.max_range_m);
        check_positive(out, "normal_group_angle_deg", self.normal_group_angle_deg);
        check_positive(out, "sigma_distance_m", self.sigma_distance_m);
        check_positive(out, "control_radius_m", self.control_radius_m);
        check_positive(out, "control_point_sigma_m", self.control_point_sigma_m);
        let c = &self.calibration;
        for (field, value) in [
            ("calibration.prior_boresight_deg", c.prior_boresight_deg),
            ("calibration.prior_lever_arm_m", c.prior_lever_arm_m),
            ("calibration.prior_range_offset_m", c.prior_range_offset_m),
            ("calibration.tolerance_boresight_deg", c.tolerance_boresight_deg),
            ("calibration.tolerance_lever_arm_m", c.tolerance_lever_arm_m),
            ("calibration.tolerance_range_offset_m", c.tolerance_range_offset_m),
        ] {
            check_positive(out, field, value);
        }
        if !(0.0..1.0).contains(&c.min_separation) {
            out.push(ParameterProblem {
                field: "calibration.min_separation".into(),
                problem: format!("must be in [0, 1), got {}", c.min_separation),
            });
        }
        check_positive(out, "sigma_prior_position_m", self.sigma_prior_position_m);
        check_positive(out, "sigma_prior_rotation_deg", self.sigma_prior_rotation_deg);
        if self.sigma_prior_heading_deg != 0.0 {
            check_positive(out, "sigma_prior_heading_deg", self.sigma_prior_heading_deg);
        }
        check_positive(out, "sigma_smooth_position_m", self.sigma_smooth_position_m);
        check_positive(out, "sigma_smooth_rotation_deg", self.sigma_smooth_rotation_deg);
        check_positive(out, "convergence_tolerance_m", self.convergence_tolerance_m);
        for (field, v) in [
            ("sigma_curvature_position_m", self.sigma_curvature_position_m),
            ("sigma_curvature_rotation_deg", self.sigma_curvature_rotation_deg),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                out.push(ParameterProblem { field: field.into(), problem: "must be zero (off) or positive".into() });
            }
        }
        if (self.sigma_curvature_position_m > 0.0) != (self.sigma_curvature_rotation_deg > 0.0) {
            out.push(ParameterProblem {
                field: "sigma_curvature_rotation_deg".into(),
                problem: "the curvature terms are on or off together: set both positive or both 0".into(),
            });
        }
        if self.process_model == ProcessModel::Estimated && self.sigma_curvature_position_m <= 0.0 {
            out.push(ParameterProblem {
                field: "process_model".into(),
                problem: "an estimated process model starts from the curvature σ's: set both positive".into(),
            });
        }
        if !(self.end_extension_m.is_finite() && self.end_extension_m >= 0.0) {
            out.push(ParameterProblem {
                field: "end_extension_m".into(),
                problem: "must be zero (off) or positive".into(),
            });
        }
        if !(0.0..1.0).contains(&self.weak_information_ratio) {
            out.push(ParameterProblem { field: "weak_information_ratio".into(), problem: "must be in [0, 1)".into() });
        }
    }

    /// The iteration schedule, the outlier floor and the accelerations.
    fn schedule_problems(&self, out: &mut Vec<ParameterProblem>) {
        for (i, step) in self.schedule.iter().enumerate() {
            check_positive(out, &format!("schedule[{i}].grid_m"), step.grid_m);
            check_positive(out, &format!("schedule[{i}].threshold_m"), step.threshold_m);
            if let Some(c) = step.cell_m {
                check_positive(out, &format!("schedule[{i}].cell_m"), c);
                if !divides(self.tile_size_m, c) {
                    out.push(ParameterProblem {
                        field: format!("schedule[{i}].cell_m"),
                        problem: format!("must divide tile_size_m ({}) into whole cells", self.tile_size_m),
                    });
                }
            }
        }
        if !(self.threshold_floor_sigmas.is_finite() && self.threshold_floor_sigmas >= 0.0) {
            out.push(ParameterProblem {
                field: "threshold_floor_sigmas".into(),
                problem: "must be zero (off) or positive".into(),
            });
        }
        if !(self.cover_agreement_thresholds.is_finite() && self.cover_agreement_thresholds >= 0.0) {
            out.push(ParameterProblem {
                field: "cover_agreement_thresholds".into(),
                problem: "must be zero (off) or positive".into(),
            });
        }
        if self.anderson_depth > MAX_ANDERSON_DEPTH {
            out.push(ParameterProblem {
                field: "anderson_depth".into(),
                problem: format!("must be 0 (off) to {MAX_ANDERSON_DEPTH}, got {}", self.anderson_depth),
            });
        }
        if !(0.0..1.0).contains(&self.momentum) {
            out.push(ParameterProblem { field: "momentum".into(), problem: "must be in [0, 1)".into() });
        }
    }

    /// The common-mode field, the latent map and the strips' usable share.
    fn field_and_map_problems(&self, out: &mut Vec<ParameterProblem>) {
        // Nodes closer than a few metres would see no more than the per-trajectory solves do, and
        // their count grows with the square of 1/spacing (the field's solve is dense).
        if !(self.common_mode_field_m.is_finite()
            && (self.common_mode_field_m == 0.0 || self.common_mode_field_m >= MIN_FIELD_SPACING_M))
        {
            out.push(ParameterProblem {
                field: "common_mode_field_m".into(),
                problem: format!(
                    "must be 0 (off) or a node spacing of at least {MIN_FIELD_SPACING_M} m, got {}",
                    self.common_mode_field_m
                ),
            });
        }
        if self.common_mode_tilt && !self.common_mode_heading {
            out.push(ParameterProblem {
                field: "common_mode_tilt".into(),
                problem: "needs common_mode_heading: the field's tilt is solved with its heading, as one rotation"
                    .into(),
            });
        }
        if !(self.latent_map_grid_m.is_finite() && (self.latent_map_grid_m == 0.0 || self.latent_map_grid_m >= 0.005)) {
            out.push(ParameterProblem {
                field: "latent_map_grid_m".into(),
                problem: format!(
                    "must be 0 (no latent map) or a voxel edge of at least 0.005 m, got {}",
                    self.latent_map_grid_m
                ),
            });
        }
        if !(self.point_latent_below_grid_m.is_finite() && self.point_latent_below_grid_m >= 0.0) {
            out.push(ParameterProblem {
                field: "point_latent_below_grid_m".into(),
                problem: "must be zero (always rasterise) or positive".into(),
            });
        }
        if !(self.latent_pixel_share.is_finite() && self.latent_pixel_share >= 0.0) {
            out.push(ParameterProblem {
                field: "latent_pixel_share".into(),
                problem: "must be zero (sample at every point) or a positive share of the point spacing".into(),
            });
        }
        if !(self.min_revolution_advance_m.is_finite() && self.min_revolution_advance_m >= 0.0) {
            out.push(ParameterProblem {
                field: "min_revolution_advance_m".into(),
                problem: "must be zero or positive".into(),
            });
        }
        if !(0.0..=1.0).contains(&self.min_usable_share) {
            out.push(ParameterProblem {
                field: "min_usable_share".into(),
                problem: format!("must be a share in [0, 1], got {}", self.min_usable_share),
            });
        }
        if !(self.tile_overlap_m.is_finite() && self.tile_overlap_m >= 0.0) {
            out.push(ParameterProblem { field: "tile_overlap_m".into(), problem: "must be zero or positive".into() });
        } else if self.tile_overlap_m * 2.0 >= self.tile_size_m {
            out.push(ParameterProblem {
                field: "tile_overlap_m".into(),
                problem: "must be less than half of tile_size_m".into(),
            });
        }
        if self.schedule.is_empty() {
            out.push(ParameterProblem { field: "schedule".into(), problem: "needs at least one iteration".into() });
        }
        // `divides` accepts non-positive sizes: those are reported above already.
        if !divides(self.tile_size_m, self.cell_size_m) {
            out.push(ParameterProblem {
                field: "cell_size_m".into(),
                problem: format!("must divide tile_size_m ({}) into whole cells", self.tile_size_m),
            });
        }
        if self.normal_group_angle_deg >= 90.0 {
            out.push(ParameterProblem { field: "normal_group_angle_deg".into(), problem: "must be below 90".into() });
        }
    }
}

/// Smallest node spacing of the common-mode field.
pub const MIN_FIELD_SPACING_M: f64 = 5.0;

/// Largest Anderson history: each entry keeps two correction sets per trajectory, and the
/// settling steps offer six iterations by default.
pub const MAX_ANDERSON_DEPTH: usize = 10;

fn divides(tile: f64, cell: f64) -> bool {
    if !(tile > 0.0 && cell > 0.0) {
        return true;
    }
    let cells = tile / cell;
    (cells - cells.round()).abs() < 1e-9
}

/// Records `field` as a problem unless `v` is a positive finite number.
fn check_positive(out: &mut Vec<ParameterProblem>, field: &str, v: f64) {
    if !(v.is_finite() && v > 0.0) {
        out.push(ParameterProblem { field: field.into(), problem: format!("must be a positive number, got {v}") });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exported_anchor_range_extends_within_the_trajectory() {
        let p = Parameters::default();
        // 10 m at 0.5 m: 20 anchors either side.
        assert_eq!(p.exported_anchor_range((50, 100), 1000), (30, 120));
        // Not past the trajectory's first or last anchor.
        assert_eq!(p.exported_anchor_range((9, 921), 930), (0, 930));
        // No extension: the estimated range.
        let off = Parameters { end_extension_m: 0.0, ..Parameters::default() };
        assert_eq!(off.exported_anchor_range((50, 100), 1000), (50, 100));
        // A partial anchor counts whole; a huge extension reaches the ends without overflow.
        let odd = Parameters { end_extension_m: 0.7, ..Parameters::default() };
        assert_eq!(odd.exported_anchor_range((50, 100), 1000), (48, 102));
        let huge = Parameters { end_extension_m: 1e300, ..Parameters::default() };
        assert_eq!(huge.exported_anchor_range((50, 100), u32::MAX), (0, u32::MAX));
        let bad = Parameters { end_extension_m: f64::NAN, ..Parameters::default() };
        assert!(bad.problems().iter().any(|p| p.field == "end_extension_m"));
    }

    #[test]
    fn defaults_follow_the_paper() {
        let p = Parameters::default();
        assert_eq!(p.schedule.len(), 18);
        assert_eq!(
            p.schedule[2],
            IterationStep {
                grid_m: 0.10,
                threshold_m: 0.30,
                rotation: false,
                cell_m: None,
                column_cells: false,
                momentum: true
            }
        );
        assert!(p.schedule.iter().skip(3).all(|s| s.rotation));
        assert_eq!(*p.schedule.last().unwrap(), IterationStep { momentum: false, ..IterationStep::new(0.01, 0.007) });
        // The last six steps (thresholds 15 mm → 7 mm) settle; every earlier step may carry
        // momentum.
        assert!(p.schedule.iter().all(|s| s.momentum == (s.threshold_m >= 0.02)));
        assert!(p.schedule.iter().skip(12).all(|s| !s.momentum));
        assert!(p.problems().is_empty());
    }

    #[test]
    fn an_estimated_process_model_needs_the_curvature_terms_and_updates_in_fine_steps() {
        let p: Parameters = serde_json::from_str(r#"{"process_model": "estimated"}"#).unwrap();
        assert_eq!(p.process_model, ProcessModel::Estimated);
        assert!(p.problems().is_empty());
        // The capture and coarse raster steps keep the σ's, the point-sampled steps with momentum
        // update them, the settling steps keep them.
        let updating: Vec<usize> = (0..p.schedule.len()).filter(|&i| p.schedule[i].updates_process_model(&p)).collect();
        assert_eq!(updating, (6..12).collect::<Vec<_>>());
        assert!(!Parameters::default().schedule[10].updates_process_model(&Parameters::default()));
        let off = Parameters { sigma_curvature_position_m: 0.0, sigma_curvature_rotation_deg: 0.0, ..p };
        assert_eq!(off.problems()[0].field, "process_model");
        // The default is not written, so that default parameters serialise as they always did.
        assert!(!serde_json::to_string(&Parameters::default()).unwrap().contains("process_model"));
        assert!(serde_json::from_str::<Parameters>(r#"{"process_model": "adaptive"}"#).is_err());
    }

    #[test]
    fn momentum_carries_on_between_point_sampled_steps_only() {
        let p = Parameters::default();
        let s = &p.schedule;
        // Capture and coarse raster steps never carry momentum, the fine steps with thresholds
        // of 2 cm and more do (also across a threshold change), the first fine step has nothing
        // to carry yet, and the last six steps settle.
        assert!(!s[1].momentum_continues(&s[0], &p));
        assert!(!s[5].momentum_continues(&s[4], &p));
        assert!(!s[6].momentum_continues(&s[5], &p));
        assert!(s[7].momentum_continues(&s[6], &p));
        assert!(s[11].momentum_continues(&s[10], &p));
        assert!((12..18).all(|i| !s[i].momentum_continues(&s[i - 1], &p)));
        // A 1 cm step that allows it carries momentum on (also across the grid change).
        let carry = IterationStep { momentum: true, ..s[14] };
        assert!(carry.momentum_continues(&s[13], &p));
        let carry = IterationStep { momentum: true, ..s[16] };
        assert!(carry.momentum_continues(&s[15], &p));
        let off = Parameters { momentum: 0.0, ..Default::default() };
        assert!(!s[7].momentum_continues(&s[6], &off));
        let frozen = IterationStep { rotation: false, ..s[7] };
        assert!(!frozen.momentum_continues(&s[6], &p));
        let bad = Parameters { momentum: 1.0, ..Default::default() };
        assert_eq!(bad.problems()[0].field, "momentum");
        for spacing in [1.0, -30.0, f64::NAN] {
            let bad = Parameters { common_mode_field_m: spacing, ..Default::default() };
            assert_eq!(bad.problems()[0].field, "common_mode_field_m");
        }
        assert!(Parameters { common_mode_field_m: 0.0, ..Default::default() }.problems().is_empty());
        // The field's tilt is solved with its heading, not alone.
        let tilt_alone = Parameters { common_mode_tilt: true, common_mode_heading: false, ..Default::default() };
        assert_eq!(tilt_alone.problems()[0].field, "common_mode_tilt");
        assert!(Parameters { common_mode_tilt: true, ..Default::default() }.problems().is_empty());
        // The heading's prior: its own σ, or 0 for the tilt's.
        for heading in [-0.05, f64::NAN, f64::INFINITY] {
            let bad = Parameters { sigma_prior_heading_deg: heading, ..Default::default() };
            assert_eq!(bad.problems()[0].field, "sigma_prior_heading_deg");
        }
        let same = Parameters { sigma_prior_rotation_deg: 0.03, sigma_prior_heading_deg: 0.0, ..Default::default() };
        assert!(same.problems().is_empty());
        assert_eq!(same.sigma_prior_rotation_axes_deg(), [0.03; 3]);
        let own = Parameters { sigma_prior_heading_deg: 0.07, ..same };
        assert_eq!(own.sigma_prior_rotation_axes_deg(), [0.03, 0.03, 0.07]);
    }

    #[test]
    fn partial_override_and_unknown_fields() {
        let p: Parameters = serde_json::from_str(r#"{"anchor_spacing_m": 1.0}"#).unwrap();
        assert_eq!(p.anchor_spacing_m, 1.0);
        assert_eq!(p.tile_size_m, 15.0);
        assert!(serde_json::from_str::<Parameters>(r#"{"anchor_spacing": 1.0}"#).is_err());
        let p: Parameters = serde_json::from_str(
            r#"{"schedule": [{"grid_m": 0.2, "threshold_m": 0.5, "cell_m": 3.0, "column_cells": true, "rotation": false},
                             {"grid_m": 0.01, "threshold_m": 0.007}]}"#,
        )
        .unwrap();
        assert_eq!(p.schedule[1], IterationStep::new(0.01, 0.007));
        assert!(p.schedule[0].column_cells && !p.schedule[0].rotation && p.schedule[0].momentum);
        let settle: IterationStep =
            serde_json::from_str(r#"{"grid_m": 0.01, "threshold_m": 0.007, "momentum": false}"#).unwrap();
        assert!(!settle.momentum);
        assert_eq!(p.schedule[0].cell_size(&p), 3.0);
        let bad = Parameters {
            schedule: vec![IterationStep { cell_m: Some(4.0), ..IterationStep::new(0.1, 0.1) }],
            ..Default::default()
        };
        assert_eq!(bad.problems()[0].field, "schedule[0].cell_m");
        let bad = Parameters { cell_size_m: 0.7, tile_overlap_m: -1.0, ..Default::default() };
        let fields: Vec<_> = bad.problems().into_iter().map(|p| p.field).collect();
        assert_eq!(fields, vec!["tile_overlap_m", "cell_size_m"]);
    }
}
