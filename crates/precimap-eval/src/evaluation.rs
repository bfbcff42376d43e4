//! What an evaluation measures: the figures before and after, per class, strip and trajectory.

use super::*;

/// One figure before (input) and after (result) estimation. NaN (JSON `null`) when there was
/// nothing to measure.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Metric {
    pub before: f64,
    pub after: f64,
}

/// A vector (x, y, z) before and after estimation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct VectorMetric {
    pub before: [f64; 3],
    pub after: [f64; 3],
}

/// Surface error of the points of one class.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ClassEvaluation {
    pub points: u64,
    pub rms_m: Metric,
    pub mean_m: Metric,
    pub p95_abs_m: Metric,
    /// The strip offset spread over this class's points alone (per tile and strip with at least
    /// [`CLASS_SPREAD_MIN_POINTS`] of them): how well strips agree on, say, curbs or poles.
    pub spread_m: Metric,
    /// The same per (tile, true surface id): a shift shared by all strips cancels where they see
    /// the same face (not on a pole, whose sides face every way).
    pub same_surface_spread_m: Metric,
    /// `same_surface_spread_m` after removing the campaign's shift (`campaign_shift_m`) from every
    /// point: on poles and cars, how well the strips agree once the datum is out.
    pub same_surface_spread_without_campaign_shift_m: Metric,
    /// `spread_m` after removing the campaign's shift (`campaign_shift_m`) from every point: the
    /// disagreement on this class that the absolute datum does not explain.
    pub spread_without_campaign_shift_m: Metric,
    /// Tile–strip pairs in `spread_m` (after).
    pub tile_strip_pairs: usize,
}

/// Surface error of one strip's surface points.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StripEvaluation {
    pub id: String,
    pub points: u64,
    pub surface_points: u64,
    pub rms_m: Metric,
    pub mean_m: Metric,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TrajectoryEvaluation {
    pub id: String,
    /// Samples compared (input, result).
    pub samples_before: u64,
    pub samples_after: u64,
    /// Samples outside the true trajectory's time span (input plus result), not compared.
    pub samples_outside_truth: u64,
    pub position_rms_m: Metric,
    pub rotation_rms_deg: Metric,
    /// Attitude error per axis of the true vehicle without the campaign's mean attitude error
    /// (`mean_attitude_error_deg`), RMS weighted by arc length.
    pub attitude_error_without_mean_rms_deg: AttitudeMetric,
    /// Position error in the true trajectory's frame without the datum (`datum_error_m`, the
    /// mean over every trajectory), RMS weighted by arc length.
    pub error_without_datum_rms_m: FrameMetric,
    /// Where each frame component of that error is largest while the trajectory's strips have
    /// points, in the input and in the result.
    pub largest_error_without_datum_before: FrameLargest,
    pub largest_error_without_datum_after: FrameLargest,
}

/// A position error's RMS per component of the true trajectory's frame
/// ([`FRAME_COMPONENTS`]), before and after estimation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct FrameMetric {
    pub along_track: Metric,
    pub across_track: Metric,
    pub vertical: Metric,
}

impl FrameMetric {
    pub(crate) fn new(before: [f64; 3], after: [f64; 3]) -> Self {
        Self {
            along_track: metric(before[0], after[0]),
            across_track: metric(before[1], after[1]),
            vertical: metric(before[2], after[2]),
        }
    }

    pub(crate) fn components(&self) -> [&Metric; 3] {
        [&self.along_track, &self.across_track, &self.vertical]
    }
}

/// An attitude error's RMS per axis of the true vehicle ([`ATTITUDE_COMPONENTS`]), before and
/// after estimation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AttitudeMetric {
    pub roll: Metric,
    pub pitch: Metric,
    pub heading: Metric,
}

impl AttitudeMetric {
    pub(crate) fn new(before: [f64; 3], after: [f64; 3]) -> Self {
        Self {
            roll: metric(before[0], after[0]),
            pitch: metric(before[1], after[1]),
            heading: metric(before[2], after[2]),
        }
    }

    pub(crate) fn components(&self) -> [&Metric; 3] {
        [&self.roll, &self.pitch, &self.heading]
    }
}

/// The largest error per frame component ([`largest_frame_errors`]); `None` where the
/// trajectory never moves while its strips have points inside the truth's time span.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct FrameLargest {
    pub along_track: Option<LargestError>,
    pub across_track: Option<LargestError>,
    pub vertical: Option<LargestError>,
}

impl From<[Option<LargestError>; 3]> for FrameLargest {
    fn from([along_track, across_track, vertical]: [Option<LargestError>; 3]) -> Self {
        Self { along_track, across_track, vertical }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Evaluation {
    /// RMS over tile–strip pairs of a strip's mean signed normal error in a 15 m tile minus the
    /// tile's mean over its strips: how well strips agree, independent of the absolute datum.
    pub strip_offset_spread_m: Metric,
    /// The same, but strips are compared only on the same true surface within a tile (groups of
    /// (tile, surface id)). A shift shared by all strips — an absolute error the strips cannot
    /// reveal — cancels here, whereas `strip_offset_spread_m` picks it up wherever strips see
    /// differently oriented surfaces of a tile (a building corner: one head sees one face, the
    /// other head the other face). The gap between the two is datum error, not disagreement.
    /// Not on a surface that faces several ways itself: strips that see a pole (or a car) from
    /// opposite sides move apart by twice the shared shift along the line of sight.
    pub same_surface_spread_m: Metric,
    /// `same_surface_spread_m` after removing the campaign's shift (`campaign_shift_m`) from every
    /// point, which takes the datum out on poles and cars too. Measured: with real
    /// scanners' angular steps (small seed 3 at 0.3° instead of 1.5°) poles reach the 200 points
    /// per strip and tile, and the 56 mm datum made the same-surface spread 4.6 mm (poles 25 mm)
    /// where it is 0.5 mm without (poles 1.7 mm, every other class 0.4–0.6 mm).
    pub same_surface_spread_without_campaign_shift_m: Metric,
    /// `strip_offset_spread_m` after removing from every point the one translation that best
    /// explains all surface errors of the campaign (its absolute datum error).
    pub spread_without_campaign_shift_m: Metric,
    /// `strip_offset_spread_m` after removing, per tile, the translation shared by all its
    /// points: the disagreement between strips that no common motion at a place explains. The
    /// gap to `strip_offset_spread_m` is error shared by all passes at a place.
    pub spread_without_tile_shift_m: Metric,
    /// The translation removed for `spread_without_campaign_shift_m` (x, y, z metres): the
    /// least-squares shift of all surface points against the truth.
    pub campaign_shift_m: VectorMetric,
    /// Mean position error of all trajectories per arc length (x, y, z metres), the absolute
    /// datum error. `before` is the input's, which no relative adjustment can observe: moving
    /// every pass and the map together changes no residual, so only the GNSS/IMU prior places
    /// the result and its mean stays where the input's was.
    pub datum_error_m: VectorMetric,
    /// `strip_offset_spread_m` of strips that would differ from the truth by nothing but
    /// `datum_error_m`: the part of the spread the datum alone explains. `before` is about the
    /// least spread a relative adjustment of this campaign reaches without absolute control (its
    /// result keeps that datum; other errors add to it, rarely cancel it).
    pub spread_from_datum_m: Metric,
    /// As `spread_from_datum_m` with each tile's own datum: the mean trajectory position error
    /// of its surface points (at their times), the error every pass at that place shares;
    /// attitude errors are left out. `after` tells how much of the result's spread is absolute
    /// error shared by all passes at a place rather than strips disagreeing. `before` is not a
    /// floor: the prior and smoothness pool each pass's GNSS/IMU positions along its length, so
    /// the result's shared error varies far less from place to place than the input's.
    pub spread_from_local_datum_m: Metric,
    /// RMS of the signed normal error `(p − p_true)·n_true` over all surface points.
    pub surface_error_rms_m: Metric,
    /// Mean signed normal error over all surface points: a common (datum) shift.
    pub surface_error_mean_m: Metric,
    /// 95th percentile of |signed normal error| over all surface points (±0.25 %).
    pub surface_error_p95_abs_m: Metric,
    /// RMS of the 3D position error of all trajectories at their time stamps.
    pub trajectory_error_rms_m: Metric,
    /// RMS of the attitude error angle of all trajectories at their time stamps.
    pub trajectory_rotation_error_rms_deg: Metric,
    /// The attitude error per axis of each true vehicle (roll about the direction of travel,
    /// pitch, heading), RMS weighted by arc length (so the three need not add up to the angle's
    /// per-sample RMS above in quadrature): what to hold against a GNSS/IMU's specification.
    pub trajectory_attitude_error_rms_deg: AttitudeMetric,
    /// Mean attitude error of all trajectories per arc length, as a rotation vector in the world
    /// frame (x, y, z degrees): the campaign rotated as a whole, every pass and the map together,
    /// which changes no residual: its x and y parts tilt the campaign, its z part turns it.
    pub mean_attitude_error_deg: VectorMetric,
    /// The same per axis without that mean: the attitude accuracy the strips' agreement decides,
    /// as `trajectory_error_without_datum_rms_m` is for the position.
    pub trajectory_attitude_error_without_mean_rms_deg: AttitudeMetric,
    /// RMS of all trajectories' position error without the datum (`datum_error_m`: the input's
    /// before, the result's after), per component of each true trajectory's own frame, weighted
    /// by arc length: the trajectory accuracy a relative adjustment can reach, and where it falls
    /// short (along-track is observed only through surfaces that change along the street).
    pub trajectory_error_without_datum_rms_m: FrameMetric,
    /// The same over the poses outside the time span of their trajectory's strips alone: the
    /// run-up before the first scan and the run-out after the last, whose corrections are
    /// predicted from the estimated ones (`end_extension_m`), not estimated. `None` where every
    /// pose is scanned.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub trajectory_error_without_datum_unscanned_rms_m: Option<FrameMetric>,
    /// Tilt of the least-squares plane through all trajectories' vertical position error over
    /// the true horizontal position (degrees; NaN where the trajectories lie on one line). A
    /// campaign tilted as a whole, every pass and the map together, changes no residual, so the
    /// strips' agreement cannot fix it; the GNSS/IMU prior should (measured: it follows the
    /// attitude prior, and is 5–6× larger at a 0.3° scanner step than at 1.5° without the
    /// campaign's rotation solved with the field).
    pub trajectory_tilt_deg: Metric,
    /// RMS of the vertical position error about that plane (weighted by arc length): the
    /// vertical accuracy the strips' agreement decides.
    pub trajectory_vertical_error_without_tilt_rms_m: Metric,
    /// The same-surface agreement with percentiles, split by the surfaces' orientation to the
    /// direction of travel, and the share of points used per orientation ([`SurfaceAgreement`]).
    pub same_surface_agreement: SurfaceAgreement,
    /// The last iteration's `points_used` (report.json) over the number of surface points.
    pub surface_points_used_share: Option<f64>,
    /// The last iteration's `points_used` from report.json, if present.
    pub points_used_last_iteration: Option<u64>,
    pub tile_strip_pairs: usize,
    pub surface_points: u64,
    pub points: u64,
    pub strips: usize,
    pub trajectory_samples: u64,
    /// By surface class name (road, sidewalk, curb, facade, pole, car, roof); foliage has no
    /// surface and is left out.
    pub per_class: BTreeMap<String, ClassEvaluation>,
    pub per_strip: Vec<StripEvaluation>,
    pub per_trajectory: Vec<TrajectoryEvaluation>,
    /// Quality of the scan-image segmentation (when `OUT/segments` exists).
    pub segmentation: Option<SegmentEvaluation>,
    /// Share of a segment's points on its dominant true surface, weighted by points (0–1).
    pub segment_purity: Option<f64>,
    /// Share of true-surface points (in the scan image) that are in no segment (0–1).
    pub surface_points_removed: Option<f64>,
    /// Share of foliage points (in the scan image) that are in no segment (0–1).
    pub foliage_points_removed: Option<f64>,
    /// The assignment audit (when `OUT/assignments` exists): observations of the last map pass
    /// compared with a surface model built mostly from another true surface.
    pub assignments: Option<AssignmentEvaluation>,
    /// `assignments.wrong_share`: share of the observations assigned to a wrong surface (0–1).
    pub wrong_assignment_share: Option<f64>,
    /// After the adjustment, the tiles whose strips disagree most (see
    /// [`TileStripMeans::worst_tiles`]): where the remaining spread comes from.
    pub worst_tiles_after: Vec<TileDisagreement>,
    /// The exported latent map against the true surfaces (when `OUT/latent` exists). It has no
    /// `before`: the input has no map.
    pub latent_map: Option<LatentMapEvaluation>,
    /// `latent_map.error_rms_m`: the map's absolute error, the datum included.
    pub latent_map_error_rms_m: Option<f64>,
    /// `latent_map.error_without_campaign_shift_rms_m`: the map's error without the datum.
    pub latent_map_error_without_campaign_shift_rms_m: Option<f64>,
    /// `latent_map.error_without_tile_shift_rms_m`: the map's error where one datum holds.
    pub latent_map_error_without_tile_shift_rms_m: Option<f64>,
    /// The precision the result states (`OUT/corrections/*.csv`, every trajectory's) against the
    /// errors after: absent when a trajectory has no corrections table.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stated_precision: Option<StatedPrecision>,
    /// The estimated mounting calibration against the simulator's errors (when report.json has
    /// `calibration`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration: Option<CalibrationEvaluation>,
}

/// One tile's strips and their offsets from the tile's mean (metres, strip ids).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TileDisagreement {
    pub tile: String,
    pub rms_m: f64,
    pub offsets_m: BTreeMap<String, f64>,
}

pub(crate) fn metric(before: f64, after: f64) -> Metric {
    Metric { before, after }
}
