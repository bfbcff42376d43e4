//! Accuracy against simulated truth: strip offset spread, surface error, trajectory error.
//!
//! `precimap evaluate --truth CAMP/truth --result OUT` compares the campaign's input ("before")
//! and the estimation's output ("after") with what the simulator knows:
//!
//! - `CAMP/manifest.json`: the campaign (its strips and trajectories, URIs relative to `CAMP`);
//! - `CAMP/truth/{strip}.truth`: per point, in file order, the noise-free position, true normal,
//!   surface id and class ([`precimap_sim::truth`]);
//! - `CAMP/truth/trajectories/{trajectory}.csv`: the true trajectories;
//! - `OUT/strips/{strip}.las|.laz`, `OUT/trajectories/{trajectory}.csv`, `OUT/report.json`;
//! - `OUT/segments/{strip}.seg` (optional): the segment id of every point, as `precimap run` wrote
//!   it; with it, the segmentation is measured too ([`SegmentEvaluation`]);
//! - `OUT/latent/*.las` (optional): the exported latent map, measured against the true surfaces
//!   ([`LatentMapEvaluation`]).
//!
//! Strips are processed one at a time per thread (rayon across strips), so memory is bounded by
//! a strip per worker; everything accumulated across strips is constant-size or per tile.

mod agreement;
mod assignments;
mod latent;
mod normals;
mod precision;
mod segments;
mod stats;
mod trajectory;

pub use agreement::{AgreementTally, Orientation, Spread, SpreadMetric, SurfaceAgreement, UsedShares};
pub use assignments::{AssignmentEvaluation, AssignmentTally, ClassAssignments};
pub use latent::{evaluate_latent_map, read_latent_maps, LatentClassFigures, LatentMapEvaluation};
pub use normals::{NormalEvaluation, NormalFigures, NormalTally};
pub use precision::{AxisValues, FrameValues, SigmaSums, StatedPrecision, TableError};
pub use segments::{SegmentEvaluation, SegmentTally};
pub use stats::{
    signed_normal_error, strip_offset_spread, AbsHistogram, ClassSurfaceStripMeans, ErrorStats, GroupStripMeans,
    ShiftFreeMeans, SurfaceStripMeans, TileStripMeans,
};
pub use trajectory::{
    largest_frame_errors, position_error_at, position_error_from, trajectory_errors, unscanned_frame_sums, FrameSums,
    LargestError, TiltSums, TrajectoryErrors, ATTITUDE_COMPONENTS, FRAME_COMPONENTS,
};

use precimap_core::{TileKey, Trajectory};
use precimap_formats::{load_manifest, read_strip, read_trajectory_csv, resolve_uri, FormatError, ManifestError};
use precimap_sim::truth::{SurfaceClass, TruthError, TruthReader};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Tiles of the strip offset spread (the paper's tile size), keyed by the TRUE position so that
/// before and after compare the same points.
pub const SPREAD_TILE_M: f64 = 15.0;
/// A strip takes part in a tile's spread with at least this many surface points there: fewer give
/// a mean dominated by noise and local surface detail.
pub const SPREAD_MIN_POINTS: usize = 200;
/// The same for the spreads of one surface class: a curb or a pole holds far fewer points of a
/// strip in a tile than 200 (50 points of 5 mm noise still give a mean to 0.7 mm).
pub const CLASS_SPREAD_MIN_POINTS: usize = 50;
/// Points whose result GPS time differs from the input's by more than this are out of order.
const GPS_TIME_TOLERANCE_S: f64 = 1e-6;

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
    fn new(before: [f64; 3], after: [f64; 3]) -> Self {
        Self {
            along_track: metric(before[0], after[0]),
            across_track: metric(before[1], after[1]),
            vertical: metric(before[2], after[2]),
        }
    }

    fn components(&self) -> [&Metric; 3] {
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
    fn new(before: [f64; 3], after: [f64; 3]) -> Self {
        Self {
            roll: metric(before[0], after[0]),
            pitch: metric(before[1], after[1]),
            heading: metric(before[2], after[2]),
        }
    }

    fn components(&self) -> [&Metric; 3] {
        [&self.roll, &self.pitch, &self.heading]
    }
}

/// A trajectory's frame sums over its run-up and run-out, and their length in metres
/// ([`unscanned_frame_sums`]).
type UnscannedSums = (FrameSums, f64);

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
}

/// One tile's strips and their offsets from the tile's mean (metres, strip ids).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TileDisagreement {
    pub tile: String,
    pub rms_m: f64,
    pub offsets_m: BTreeMap<String, f64>,
}

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("truth folder {}: {source}; pass the campaign's truth folder (CAMP/truth)", path.display())]
    TruthDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Manifest(#[from] ManifestError),
    #[error("{}: {what} {id:?}: {message}", manifest.display())]
    Uri { manifest: PathBuf, what: &'static str, id: String, message: String },
    #[error("{what} id {id:?} cannot name a file (it contains a path separator or is . or ..)")]
    BadId { what: &'static str, id: String },
    #[error(transparent)]
    Format(#[from] FormatError),
    #[error(transparent)]
    Truth(#[from] TruthError),
    #[error("strip {strip}: the {which} strip {} has {found} points but its truth {} has {expected}; every point of the input must be kept, in order", path.display(), truth.display())]
    PointCount { strip: String, which: &'static str, path: PathBuf, truth: PathBuf, found: u64, expected: u64 },
    #[error("strip {strip}: no result strip: neither {} nor {} exists", las.display(), laz.display())]
    MissingResultStrip { strip: String, las: PathBuf, laz: PathBuf },
    #[error("trajectory {trajectory}: no corrected trajectory {}", path.display())]
    MissingResultTrajectory { trajectory: String, path: PathBuf },
    #[error("strip {strip}: point {index} of {} has GPS time {found} but the input's has {expected}; result points must keep the input order", path.display())]
    PointOrder { strip: String, path: PathBuf, index: usize, found: f64, expected: f64 },
    #[error("strip {strip}: truth point {index} of {} has an invalid normal {normal:?}", path.display())]
    BadNormal { strip: String, path: PathBuf, index: u64, normal: [f32; 3] },
    #[error("{}: {message}", path.display())]
    Report { path: PathBuf, message: String },
    #[error("the latent map (OUT/latent/*.las) has a point in cell {cells:?}, more than 2³¹ cells of 10 cm from its lowest cell {origin:?}: a map point's coordinates are corrupt; re-export the map with `precimap run`")]
    LatentMapExtent { cells: [i64; 3], origin: [i64; 3] },
    #[error(transparent)]
    CorrectionsTable(#[from] TableError),
    #[error("{strips} strips: the latent map's evaluation tells at most {most} strips apart")]
    TooManyStrips { strips: usize, most: usize },
}

/// Evaluates the result folder `result_dir` of `precimap run` against the truth folder
/// `truth_dir` (`CAMP/truth`; the manifest is `CAMP/manifest.json`). The campaign folder `CAMP`
/// itself is taken as well: it is what people pass first.
pub fn evaluate(truth_dir: &Path, result_dir: &Path) -> Result<Evaluation, EvalError> {
    let nested = truth_dir.join("truth");
    let truth_dir = if !truth_dir.join("truth.json").is_file() && nested.join("truth.json").is_file() {
        nested.as_path()
    } else {
        truth_dir
    };
    let truth_dir =
        std::fs::canonicalize(truth_dir).map_err(|source| EvalError::TruthDir { path: truth_dir.into(), source })?;
    // Canonical, so `..` of a symlinked or relative `truth` folder is the campaign folder.
    let campaign_dir = truth_dir.parent().unwrap_or(&truth_dir).to_path_buf();
    let manifest_path = campaign_dir.join("manifest.json");
    let manifest = load_manifest(&manifest_path)?;
    let input_uri = |what, id: &str, uri: &str| {
        resolve_uri(&campaign_dir, uri).map_err(|message| EvalError::Uri {
            manifest: manifest_path.clone(),
            what,
            id: id.to_string(),
            message,
        })
    };

    let mut strip_jobs = Vec::with_capacity(manifest.strips.len());
    for s in &manifest.strips {
        check_id("strip", &s.id)?;
        strip_jobs.push((s.id.clone(), input_uri("strip", &s.id, &s.uri)?));
    }
    let mut trajectory_jobs = Vec::with_capacity(manifest.trajectories.len());
    for t in &manifest.trajectories {
        check_id("trajectory", &t.id)?;
        trajectory_jobs.push((t.id.clone(), input_uri("trajectory", &t.id, &t.uri)?));
    }

    // Trajectories first: they are small, and each strip's points look up their own
    // trajectory's error (for the local datum).
    let loaded: Vec<LoadedTrajectory> = trajectory_jobs
        .par_iter()
        .map(|(id, input)| load_trajectory(id, input, &truth_dir, result_dir))
        .collect::<Result<_, _>>()?;
    let strip_trajectory: Vec<Option<&LoadedTrajectory>> = manifest
        .strips
        .iter()
        .map(|s| trajectory_jobs.iter().position(|(id, _)| *id == s.trajectory).map(|t| &loaded[t]))
        .collect();
    let strips: Vec<StripOutcome> = strip_jobs
        .par_iter()
        .enumerate()
        .map(|(k, (id, input))| evaluate_strip(id, k as u32, input, strip_trajectory[k], &truth_dir, result_dir))
        .collect::<Result<_, _>>()?;
    let trajectories: Vec<(TrajectoryErrors, TrajectoryErrors)> = loaded
        .iter()
        .map(|t| (trajectory_errors(&t.input, &t.truth), trajectory_errors(&t.result, &t.truth)))
        .collect();
    let [datum_before, datum_after] = totals(&trajectories).map(|t| t.mean_position_error_m());
    // Where a trajectory's strips have points: beyond them its corrections are predicted (the
    // estimate continued over the run-up and run-out), not estimated, and the largest errors
    // would mostly sit at its two ends.
    let scanned: Vec<Option<(f64, f64)>> = trajectory_jobs
        .iter()
        .map(|(id, _)| {
            manifest
                .strips
                .iter()
                .zip(&strips)
                .filter(|(s, _)| s.trajectory == *id)
                .filter_map(|(_, o)| o.time_span)
                .fold(None, |span: Option<(f64, f64)>, (first, last)| {
                    Some(span.map_or((first, last), |(a, b)| (a.min(first), b.max(last))))
                })
        })
        .collect();
    // Per trajectory, before and after: the largest errors while scanning, and the sums over the
    // run-up and run-out (one pass over the loaded trajectories).
    let (largest, unscanned_per_trajectory): (Vec<[FrameLargest; 2]>, Vec<[UnscannedSums; 2]>) = loaded
        .par_iter()
        .zip(&scanned)
        .map(|(t, &span)| {
            // A trajectory without strip points has nothing scanned to look in.
            let largest =
                |eval, datum| span.map_or([None; 3], |within| largest_frame_errors(eval, &t.truth, datum, within));
            (
                [largest(&t.input, datum_before).into(), largest(&t.result, datum_after).into()],
                [unscanned_frame_sums(&t.input, &t.truth, span), unscanned_frame_sums(&t.result, &t.truth, span)],
            )
        })
        .unzip();
    let mut unscanned: [UnscannedSums; 2] = [(FrameSums::default(), 0.0); 2];
    for sums in &unscanned_per_trajectory {
        for (total, (sums, length_m)) in unscanned.iter_mut().zip(sums) {
            total.0.merge(sums);
            total.1 += length_m;
        }
    }
    // The trajectories (input, truth and result: 0.4 GB on the large campaign) are done with:
    // freed before the latent map is read, not held through its peak.
    drop(strip_trajectory);
    drop(loaded);
    let report = read_report(&result_dir.join("report.json"))?;
    let mut evaluation = assemble(&strip_jobs, strips, &trajectory_jobs, trajectories, &largest, report);
    let [(before, before_m), (after, after_m)] = &unscanned;
    evaluation.trajectory_error_without_datum_unscanned_rms_m = (*before_m > 0.0 && *after_m > 0.0).then(|| {
        FrameMetric::new(
            before.rms_without(evaluation.datum_error_m.before, *before_m),
            after.rms_without(evaluation.datum_error_m.after, *after_m),
        )
    });
    // The map keeps the result's datum: it is matched to the truth without the campaign's shift.
    let latent_map = match read_latent_maps(result_dir)? {
        Some(map) => {
            let ids: Vec<String> = strip_jobs.iter().map(|(id, _)| id.clone()).collect();
            Some(evaluate_latent_map(&map, &ids, &truth_dir, evaluation.campaign_shift_m.after)?)
        }
        None => None,
    };
    evaluation.latent_map_error_rms_m = latent_map.as_ref().map(|l| l.error_rms_m);
    evaluation.latent_map_error_without_campaign_shift_rms_m =
        latent_map.as_ref().map(|l| l.error_without_campaign_shift_rms_m);
    evaluation.latent_map_error_without_tile_shift_rms_m =
        latent_map.as_ref().map(|l| l.error_without_tile_shift_rms_m);
    evaluation.latent_map = latent_map;
    evaluation.stated_precision =
        read_corrections_tables(result_dir, trajectory_jobs.iter().map(|(id, _)| id.as_str()))?.and_then(|sums| {
            sums.stated(
                evaluation.trajectory_error_without_datum_rms_m.components().map(|m| m.after),
                evaluation.trajectory_attitude_error_without_mean_rms_deg.components().map(|m| m.after),
            )
        });
    Ok(evaluation)
}

/// Every trajectory's corrections table (`OUT/corrections/{id}.csv`), summed; `None` unless each
/// trajectory has one (a partial figure would mislead).
fn read_corrections_tables<'a>(
    result_dir: &Path,
    trajectories: impl Iterator<Item = &'a str>,
) -> Result<Option<SigmaSums>, EvalError> {
    let mut sums = SigmaSums::default();
    for id in trajectories {
        let path = result_dir.join("corrections").join(format!("{id}.csv"));
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(EvalError::Report { path, message: e.to_string() }),
        };
        precision::add_table(&mut sums, &text, &path)?;
    }
    Ok(Some(sums))
}

fn check_id(what: &'static str, id: &str) -> Result<(), EvalError> {
    if id.is_empty() || id == "." || id == ".." || id.contains(['/', '\\']) {
        return Err(EvalError::BadId { what, id: id.to_string() });
    }
    Ok(())
}

/// Everything one strip contributes.
#[derive(Debug)]
struct StripOutcome {
    points: u64,
    before: ErrorStats,
    after: ErrorStats,
    per_class: BTreeMap<u8, (ErrorStats, ErrorStats)>,
    tiles_before: TileStripMeans,
    tiles_after: TileStripMeans,
    segments: Option<SegmentTally>,
    assignments: Option<AssignmentTally>,
    /// All classes together: the per-class sums merged, plus the datum samples.
    shift_free_before: ShiftFreeMeans,
    shift_free_after: ShiftFreeMeans,
    /// Per class, and per (class, tile, surface), before and after. A surface id has one class,
    /// so the latter also gives the whole campaign's same-surface spread.
    classes: [BTreeMap<u8, ShiftFreeMeans>; 2],
    class_surfaces: [ClassSurfaceStripMeans; 2],
    agreement: AgreementTally,
    /// The first and last GPS time of the strip's points; `None` without points.
    time_span: Option<(f64, f64)>,
}

fn result_strip_path(result_dir: &Path, id: &str) -> Result<PathBuf, EvalError> {
    let las = result_dir.join("strips").join(format!("{id}.las"));
    let laz = result_dir.join("strips").join(format!("{id}.laz"));
    if las.is_file() {
        Ok(las)
    } else if laz.is_file() {
        Ok(laz)
    } else {
        Err(EvalError::MissingResultStrip { strip: id.to_string(), las, laz })
    }
}

fn evaluate_strip(
    id: &str,
    index: u32,
    input: &Path,
    trajectory: Option<&LoadedTrajectory>,
    truth_dir: &Path,
    result_dir: &Path,
) -> Result<StripOutcome, EvalError> {
    let truth_path = truth_dir.join(format!("{id}.truth"));
    let mut truth = TruthReader::open(&truth_path)?;
    let expected = truth.len();
    let count_error = |which, path: &Path, found: usize| EvalError::PointCount {
        strip: id.to_string(),
        which,
        path: path.to_path_buf(),
        truth: truth_path.clone(),
        found: found as u64,
        expected,
    };
    // Cheap checks first: a missing result should not cost reading the input.
    let result_path = result_strip_path(result_dir, id)?;
    let before = read_strip(input)?;
    if before.len() as u64 != expected {
        return Err(count_error("input", input, before.len()));
    }
    let after = read_strip(&result_path)?;
    if after.len() as u64 != expected {
        return Err(count_error("result", &result_path, after.len()));
    }
    if let Some(i) = (0..after.len()).find(|&i| (after.gps_time[i] - before.gps_time[i]).abs() > GPS_TIME_TOLERANCE_S) {
        return Err(EvalError::PointOrder {
            strip: id.to_string(),
            path: result_path,
            index: i,
            found: after.gps_time[i],
            expected: before.gps_time[i],
        });
    }

    let mut out = StripOutcome {
        points: expected,
        before: ErrorStats::new(),
        after: ErrorStats::new(),
        per_class: BTreeMap::new(),
        tiles_before: TileStripMeans::new(),
        tiles_after: TileStripMeans::new(),
        segments: None,
        assignments: None,
        shift_free_before: ShiftFreeMeans::new(),
        shift_free_after: ShiftFreeMeans::new(),
        classes: Default::default(),
        class_surfaces: Default::default(),
        agreement: AgreementTally::default(),
        time_span: before.gps_time_span(),
    };
    // Per-point id files next to the result (optional), each checked against the point count.
    let per_point_ids =
        |folder: &str, extension: &str, which: &'static str, read: fn(&Path) -> Result<Vec<u32>, FormatError>| {
            let path = result_dir.join(folder).join(format!("{id}.{extension}"));
            if !path.is_file() {
                return Ok(None);
            }
            let ids = read(&path)?;
            if ids.len() as u64 != expected {
                return Err(count_error(which, &path, ids.len()));
            }
            Ok(Some(ids))
        };
    let segment_ids = per_point_ids("segments", "seg", "segment", precimap_formats::read_segments)?;
    let assignment_ids = per_point_ids("assignments", "asg", "assignment", precimap_formats::read_assignments)?;
    let mut tally = SegmentTally::default();
    let mut assigned = AssignmentTally::default();
    // Per trajectory (truth, input, result), the segment the last point's time fell in.
    let mut segment_hints = [0usize; 3];
    let mut i = 0usize;
    while let Some(t) = truth.next_point()? {
        let k = i;
        i += 1;
        if let Some(ids) = &segment_ids {
            tally.add(ids[k], t.surface_id, t.class, t.normal, t.position);
        }
        if let Some(ids) = &assignment_ids {
            assigned.add(ids[k], t.surface_id, t.class);
        }
        if !t.class.is_surface() {
            continue;
        }
        let pb = [before.x[k], before.y[k], before.z[k]];
        let pa = [after.x[k], after.y[k], after.z[k]];
        let bad_normal = || EvalError::BadNormal {
            strip: id.to_string(),
            path: truth_path.clone(),
            index: k as u64,
            normal: t.normal,
        };
        let eb = signed_normal_error(pb, t.position, t.normal).ok_or_else(bad_normal)?;
        let ea = signed_normal_error(pa, t.position, t.normal).ok_or_else(bad_normal)?;
        out.before.add(eb);
        out.after.add(ea);
        let class = out.per_class.entry(t.class as u8).or_default();
        class.0.add(eb);
        class.1.add(ea);
        let tile = TileKey::of(t.position[0], t.position[1], SPREAD_TILE_M);
        out.tiles_before.add(tile, index, eb);
        out.tiles_after.add(tile, index, ea);
        let len = t.normal.iter().map(|&c| (c as f64).powi(2)).sum::<f64>().sqrt();
        let unit = t.normal.map(|c| c as f64 / len);
        let travel = trajectory.and_then(|tr| tr.truth.pose_at(before.gps_time[k])).map(|p| {
            let x = p.rotation.column(0);
            [x[0], x[1], x[2]]
        });
        let orientation = Orientation::of(unit, travel) as u8;
        for (k, e) in [eb, ea].into_iter().enumerate() {
            out.classes[k].entry(t.class as u8).or_default().add(tile, index, e, unit);
            out.class_surfaces[k].add_oriented((t.class as u8, tile, t.surface_id), index, e, unit);
            out.agreement.means[k].add_oriented((orientation, tile, t.surface_id), index, e, unit);
        }
        out.agreement.points[orientation as usize] += 1;
        if assignment_ids.as_ref().is_some_and(|ids| ids[k] != u32::MAX) {
            out.agreement.used[orientation as usize] += 1;
        }
        if let Some(tr) = trajectory {
            let time = before.gps_time[k];
            if let Some(truth_position) = tr.truth.position_at_from(time, &mut segment_hints[0]) {
                if let Some(g) = position_error_from(&tr.input, truth_position, time, &mut segment_hints[1]) {
                    out.shift_free_before.add_datum_sample(tile, g);
                }
                if let Some(g) = position_error_from(&tr.result, truth_position, time, &mut segment_hints[2]) {
                    out.shift_free_after.add_datum_sample(tile, g);
                }
            }
        }
    }
    for class in out.classes[0].values() {
        out.shift_free_before.merge(class.clone());
    }
    for class in out.classes[1].values() {
        out.shift_free_after.merge(class.clone());
    }
    out.segments = segment_ids.map(|_| tally);
    out.assignments = assignment_ids.map(|_| assigned);
    Ok(out)
}

/// One trajectory's input, truth and result.
struct LoadedTrajectory {
    input: Trajectory,
    truth: Trajectory,
    result: Trajectory,
}

fn load_trajectory(id: &str, input: &Path, truth_dir: &Path, result_dir: &Path) -> Result<LoadedTrajectory, EvalError> {
    let truth = read_trajectory_csv(&truth_dir.join("trajectories").join(format!("{id}.csv")))?;
    let result_path = result_dir.join("trajectories").join(format!("{id}.csv"));
    if !result_path.is_file() {
        return Err(EvalError::MissingResultTrajectory { trajectory: id.to_string(), path: result_path });
    }
    Ok(LoadedTrajectory { input: read_trajectory_csv(input)?, truth, result: read_trajectory_csv(&result_path)? })
}

/// `points_used` of the last iteration in report.json; `None` without a report or that field.
fn read_report(path: &Path) -> Result<Option<u64>, EvalError> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(EvalError::Report { path: path.into(), message: format!("cannot read: {e}") }),
    };
    let value: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| EvalError::Report { path: path.into(), message: format!("not valid JSON: {e}") })?;
    let last = value.get("iterations").and_then(|it| it.as_array()).and_then(|it| it.last());
    Ok(last.and_then(|it| it.get("points_used")).and_then(|v| v.as_u64()))
}

fn metric(before: f64, after: f64) -> Metric {
    Metric { before, after }
}

/// Every trajectory's errors together, of the inputs and of the results.
fn totals(trajectories: &[(TrajectoryErrors, TrajectoryErrors)]) -> [TrajectoryErrors; 2] {
    let mut total = [TrajectoryErrors::default(); 2];
    for (b, a) in trajectories {
        total[0].merge(b);
        total[1].merge(a);
    }
    total
}

fn assemble(
    strip_jobs: &[(String, PathBuf)],
    strips: Vec<StripOutcome>,
    trajectory_jobs: &[(String, PathBuf)],
    trajectories: Vec<(TrajectoryErrors, TrajectoryErrors)>,
    largest: &[[FrameLargest; 2]],
    points_used: Option<u64>,
) -> Evaluation {
    let (mut before, mut after) = (ErrorStats::new(), ErrorStats::new());
    let (mut tiles_before, mut tiles_after) = (TileStripMeans::new(), TileStripMeans::new());
    let (mut shift_free_before, mut shift_free_after) = (ShiftFreeMeans::new(), ShiftFreeMeans::new());
    let mut classes: BTreeMap<u8, (ErrorStats, ErrorStats)> = BTreeMap::new();
    let mut class_means: [BTreeMap<u8, ShiftFreeMeans>; 2] = Default::default();
    let mut class_surface_means: [ClassSurfaceStripMeans; 2] = Default::default();
    let mut agreement = AgreementTally::default();
    let mut per_strip = Vec::with_capacity(strips.len());
    let mut points = 0;
    let mut segment_tallies = Vec::new();
    let mut assignment_tally: Option<AssignmentTally> = None;
    let mut assignment_files = 0;
    for ((id, _), s) in strip_jobs.iter().zip(strips) {
        points += s.points;
        if let Some(t) = s.assignments {
            assignment_files += 1;
            assignment_tally.get_or_insert_with(AssignmentTally::default).merge(t);
        }
        if let Some(t) = s.segments {
            segment_tallies.push(t);
        }
        before.merge(&s.before);
        after.merge(&s.after);
        for (class, (b, a)) in &s.per_class {
            let c = classes.entry(*class).or_default();
            c.0.merge(b);
            c.1.merge(a);
        }
        tiles_before.merge(s.tiles_before);
        tiles_after.merge(s.tiles_after);
        shift_free_before.merge(s.shift_free_before);
        shift_free_after.merge(s.shift_free_after);
        for (total, part) in class_means.iter_mut().zip(s.classes) {
            for (class, means) in part {
                total.entry(class).or_default().merge(means);
            }
        }
        for (total, part) in class_surface_means.iter_mut().zip(s.class_surfaces) {
            total.merge(part);
        }
        agreement.merge(s.agreement);
        per_strip.push(StripEvaluation {
            id: id.clone(),
            points: s.points,
            surface_points: s.before.count(),
            rms_m: metric(s.before.rms(), s.after.rms()),
            mean_m: metric(s.before.mean(), s.after.mean()),
        });
    }
    let (spread_before, pairs) = tiles_before.spread(SPREAD_MIN_POINTS);
    let (spread_after, _) = tiles_after.spread(SPREAD_MIN_POINTS);
    let (surface_spread_before, _) = class_surface_means[0].spread(SPREAD_MIN_POINTS);
    let (surface_spread_after, _) = class_surface_means[1].spread(SPREAD_MIN_POINTS);
    let worst_tiles_after = tiles_after
        .worst_tiles(SPREAD_MIN_POINTS, 8)
        .into_iter()
        .map(|(tile, rms_m, offsets)| TileDisagreement {
            tile: tile.to_string(),
            rms_m,
            offsets_m: offsets
                .into_iter()
                .map(|(k, o)| (per_strip.get(k as usize).map_or_else(|| format!("strip-{k}"), |s| s.id.clone()), o))
                .collect(),
        })
        .collect();

    let campaign_shifts = [shift_free_before.campaign_shift(), shift_free_after.campaign_shift()];
    let per_class = classes
        .into_iter()
        .map(|(class, (b, a))| {
            let name = SurfaceClass::from_u8(class).map_or_else(|| format!("class-{class}"), |c| c.name().to_string());
            let spread_without = |k: usize, d: [f64; 3]| {
                class_means[k].get(&class).map_or((f64::NAN, 0), |m| m.spread_without_shift(d, CLASS_SPREAD_MIN_POINTS))
            };
            let spread = |k: usize| spread_without(k, [0.0; 3]);
            let same_surface = |k: usize, d: [f64; 3]| {
                class_surface_means[k].spread_of_without_shift(CLASS_SPREAD_MIN_POINTS, |g| g.0 == class, d).0
            };
            let eval = ClassEvaluation {
                points: b.count(),
                rms_m: metric(b.rms(), a.rms()),
                mean_m: metric(b.mean(), a.mean()),
                p95_abs_m: metric(b.abs_quantile(0.95), a.abs_quantile(0.95)),
                spread_m: metric(spread(0).0, spread(1).0),
                same_surface_spread_m: metric(same_surface(0, [0.0; 3]), same_surface(1, [0.0; 3])),
                same_surface_spread_without_campaign_shift_m: metric(
                    same_surface(0, campaign_shifts[0]),
                    same_surface(1, campaign_shifts[1]),
                ),
                spread_without_campaign_shift_m: metric(
                    spread_without(0, campaign_shifts[0]).0,
                    spread_without(1, campaign_shifts[1]).0,
                ),
                tile_strip_pairs: spread(1).1,
            };
            (name, eval)
        })
        .collect();

    let [traj_before, traj_after] = totals(&trajectories);
    let (datum_before, datum_after) = (traj_before.mean_position_error_m(), traj_after.mean_position_error_m());
    let (attitude_before, attitude_after) =
        (traj_before.mean_rotation_error_deg(), traj_after.mean_rotation_error_deg());
    let per_trajectory = trajectory_jobs
        .iter()
        .zip(&trajectories)
        .zip(largest)
        .map(|(((id, _), (b, a)), [largest_before, largest_after])| TrajectoryEvaluation {
            id: id.clone(),
            samples_before: b.samples,
            samples_after: a.samples,
            samples_outside_truth: b.outside_truth + a.outside_truth,
            position_rms_m: metric(b.position_rms_m(), a.position_rms_m()),
            rotation_rms_deg: metric(b.rotation_rms_deg(), a.rotation_rms_deg()),
            attitude_error_without_mean_rms_deg: AttitudeMetric::new(
                b.attitude.rms_without(attitude_before, b.length_m),
                a.attitude.rms_without(attitude_after, a.length_m),
            ),
            error_without_datum_rms_m: FrameMetric::new(
                b.frame.rms_without(datum_before, b.length_m),
                a.frame.rms_without(datum_after, a.length_m),
            ),
            largest_error_without_datum_before: *largest_before,
            largest_error_without_datum_after: *largest_after,
        })
        .collect();
    let surface_points = before.count();
    let segmentation = (!segment_tallies.is_empty() && segment_tallies.len() == strip_jobs.len())
        .then(|| SegmentEvaluation::from_tallies(&segment_tallies));
    let coplanar = if segmentation.is_some() { segments::coplanar_surfaces(&segment_tallies) } else { HashMap::new() };
    // Only when every strip has its file: a partial audit would mislead.
    let assignments = assignment_tally.filter(|_| assignment_files == strip_jobs.len()).map(|t| t.evaluate(&coplanar));
    let same_surface_agreement = agreement.evaluate(campaign_shifts, assignments.is_some());
    Evaluation {
        same_surface_agreement,
        segment_purity: segmentation.as_ref().map(|s| s.purity),
        surface_points_removed: segmentation.as_ref().map(|s| s.surface_points_removed),
        foliage_points_removed: segmentation.as_ref().map(|s| s.foliage_points_removed),
        segmentation,
        wrong_assignment_share: assignments.as_ref().map(|a| a.wrong_share),
        assignments,
        strip_offset_spread_m: metric(spread_before, spread_after),
        same_surface_spread_m: metric(surface_spread_before, surface_spread_after),
        same_surface_spread_without_campaign_shift_m: metric(
            class_surface_means[0].spread_of_without_shift(SPREAD_MIN_POINTS, |_| true, campaign_shifts[0]).0,
            class_surface_means[1].spread_of_without_shift(SPREAD_MIN_POINTS, |_| true, campaign_shifts[1]).0,
        ),
        spread_without_campaign_shift_m: metric(
            shift_free_before.spread_without_campaign_shift(SPREAD_MIN_POINTS).0,
            shift_free_after.spread_without_campaign_shift(SPREAD_MIN_POINTS).0,
        ),
        spread_without_tile_shift_m: metric(
            shift_free_before.spread_without_tile_shift(SPREAD_MIN_POINTS).0,
            shift_free_after.spread_without_tile_shift(SPREAD_MIN_POINTS).0,
        ),
        campaign_shift_m: VectorMetric {
            before: shift_free_before.campaign_shift(),
            after: shift_free_after.campaign_shift(),
        },
        datum_error_m: VectorMetric { before: datum_before, after: datum_after },
        spread_from_datum_m: metric(
            shift_free_before.spread_of_shift(datum_before, SPREAD_MIN_POINTS).0,
            shift_free_after.spread_of_shift(datum_after, SPREAD_MIN_POINTS).0,
        ),
        spread_from_local_datum_m: metric(
            shift_free_before.spread_of_local_datum(SPREAD_MIN_POINTS).0,
            shift_free_after.spread_of_local_datum(SPREAD_MIN_POINTS).0,
        ),
        surface_error_rms_m: metric(before.rms(), after.rms()),
        surface_error_mean_m: metric(before.mean(), after.mean()),
        surface_error_p95_abs_m: metric(before.abs_quantile(0.95), after.abs_quantile(0.95)),
        trajectory_error_rms_m: metric(traj_before.position_rms_m(), traj_after.position_rms_m()),
        trajectory_rotation_error_rms_deg: metric(traj_before.rotation_rms_deg(), traj_after.rotation_rms_deg()),
        trajectory_attitude_error_rms_deg: AttitudeMetric::new(
            traj_before.attitude.rms_without([0.0; 3], traj_before.length_m),
            traj_after.attitude.rms_without([0.0; 3], traj_after.length_m),
        ),
        mean_attitude_error_deg: VectorMetric { before: attitude_before, after: attitude_after },
        trajectory_attitude_error_without_mean_rms_deg: AttitudeMetric::new(
            traj_before.attitude.rms_without(attitude_before, traj_before.length_m),
            traj_after.attitude.rms_without(attitude_after, traj_after.length_m),
        ),
        trajectory_error_without_datum_rms_m: FrameMetric::new(
            traj_before.frame.rms_without(datum_before, traj_before.length_m),
            traj_after.frame.rms_without(datum_after, traj_after.length_m),
        ),
        trajectory_error_without_datum_unscanned_rms_m: None,
        trajectory_tilt_deg: metric(
            traj_before.tilt.plane().map_or(f64::NAN, |p| p.0),
            traj_after.tilt.plane().map_or(f64::NAN, |p| p.0),
        ),
        trajectory_vertical_error_without_tilt_rms_m: metric(
            traj_before.tilt.plane().map_or(f64::NAN, |p| p.1),
            traj_after.tilt.plane().map_or(f64::NAN, |p| p.1),
        ),
        surface_points_used_share: points_used.filter(|_| surface_points > 0).map(|u| u as f64 / surface_points as f64),
        points_used_last_iteration: points_used,
        tile_strip_pairs: pairs,
        worst_tiles_after,
        latent_map: None,
        latent_map_error_rms_m: None,
        latent_map_error_without_campaign_shift_rms_m: None,
        latent_map_error_without_tile_shift_rms_m: None,
        stated_precision: None,
        surface_points,
        points,
        strips: strip_jobs.len(),
        trajectory_samples: traj_after.samples,
        per_class,
        per_strip,
        per_trajectory,
    }
}

impl Evaluation {
    /// A plain-text table for terminals (millimetres and millidegrees).
    pub fn summary(&self) -> String {
        let mut s = String::new();
        let mut row = |name: &str, m: &Metric, scale: f64, unit: &str| {
            let ratio = if m.before > 0.0 { format!("{:>7.1} %", 100.0 * m.after / m.before) } else { String::new() };
            let _ = writeln!(s, "{name:<34} {:>12.3} {:>12.3} {unit:<5}{ratio}", m.before * scale, m.after * scale);
        };
        row("strip offset spread", &self.strip_offset_spread_m, 1e3, "mm");
        row("  same-surface spread", &self.same_surface_spread_m, 1e3, "mm");
        row("    without the campaign's shift", &self.same_surface_spread_without_campaign_shift_m, 1e3, "mm");
        let a = &self.same_surface_agreement;
        let of = |m: &SpreadMetric, f: fn(&Spread) -> f64| metric(f(&m.before), f(&m.after));
        row("      95th percentile (≥ 50 points)", &of(&a.all, |s| s.p95_m), 1e3, "mm");
        row("      maximum (≥ 50 points)", &of(&a.all, |s| s.max_m), 1e3, "mm");
        row("      up-facing, RMS", &of(&a.up, |s| s.rms_m), 1e3, "mm");
        row("      facing travel, RMS", &of(&a.facing_travel, |s| s.rms_m), 1e3, "mm");
        row("      facing across, RMS", &of(&a.facing_across, |s| s.rms_m), 1e3, "mm");
        row("  without the campaign's shift", &self.spread_without_campaign_shift_m, 1e3, "mm");
        row("  without each tile's shift", &self.spread_without_tile_shift_m, 1e3, "mm");
        row("  from the datum error alone", &self.spread_from_datum_m, 1e3, "mm");
        row("  from each tile's datum alone", &self.spread_from_local_datum_m, 1e3, "mm");
        row("surface error RMS", &self.surface_error_rms_m, 1e3, "mm");
        row("surface error mean", &self.surface_error_mean_m, 1e3, "mm");
        row("surface |error| 95th percentile", &self.surface_error_p95_abs_m, 1e3, "mm");
        row("trajectory position error RMS", &self.trajectory_error_rms_m, 1e3, "mm");
        row("trajectory attitude error RMS", &self.trajectory_rotation_error_rms_deg, 1e3, "mdeg");
        let attitude = self.trajectory_attitude_error_rms_deg.components();
        let attitude_without = self.trajectory_attitude_error_without_mean_rms_deg.components();
        for ((name, m), without) in ATTITUDE_COMPONENTS.iter().zip(attitude).zip(attitude_without) {
            row(&format!("  {name}"), m, 1e3, "mdeg");
            row("    w/o the campaign's rotation", without, 1e3, "mdeg");
        }
        for (name, m) in FRAME_COMPONENTS.iter().zip(self.trajectory_error_without_datum_rms_m.components()) {
            row(&format!("  {name} w/o the datum"), m, 1e3, "mm");
        }
        if let Some(unscanned) = &self.trajectory_error_without_datum_unscanned_rms_m {
            for (name, m) in FRAME_COMPONENTS.iter().zip(unscanned.components()) {
                let short = name.trim_end_matches("-track");
                row(&format!("    {short} in run-up/run-out"), m, 1e3, "mm");
            }
        }
        row("  the campaign's tilt", &self.trajectory_tilt_deg, 1e3, "mdeg");
        row("  vertical w/o the tilt", &self.trajectory_vertical_error_without_tilt_rms_m, 1e3, "mm");
        for (name, c) in &self.per_class {
            row(&format!("  {name} error RMS ({} points)", c.points), &c.rms_m, 1e3, "mm");
        }
        let mut out = format!("{:<34} {:>12} {:>12}\n", "metric", "before", "after");
        out.push_str(&s);
        let _ = writeln!(
            out,
            "strip offset spread per class, after (mm): {:>8} {:>13} {:>12} {:>12} {:>6}",
            "spread", "same-surface", "w/o shift", "same w/o", "pairs"
        );
        for (name, c) in &self.per_class {
            let _ = writeln!(
                out,
                "  {name:<40} {:>8.3} {:>13.3} {:>12.3} {:>12.3} {:>6}",
                c.spread_m.after * 1e3,
                c.same_surface_spread_m.after * 1e3,
                c.spread_without_campaign_shift_m.after * 1e3,
                c.same_surface_spread_without_campaign_shift_m.after * 1e3,
                c.tile_strip_pairs
            );
        }
        let mm = |v: [f64; 3]| format!("({:+.1}, {:+.1}, {:+.1})", v[0] * 1e3, v[1] * 1e3, v[2] * 1e3);
        let _ = writeln!(
            out,
            "datum error (mean trajectory position error, x y z): {} → {} mm; campaign's shift {} → {} mm",
            mm(self.datum_error_m.before),
            mm(self.datum_error_m.after),
            mm(self.campaign_shift_m.before),
            mm(self.campaign_shift_m.after)
        );
        // Degrees in, millidegrees out: the same format as `mm`.
        let _ = writeln!(
            out,
            "campaign's rotation (mean attitude error about x y z): {} → {} mdeg",
            mm(self.mean_attitude_error_deg.before),
            mm(self.mean_attitude_error_deg.after)
        );
        if let Some(p) = &self.stated_precision {
            let three = |v: [f64; 3]| format!("{:.2} / {:.2} / {:.2}", v[0], v[1], v[2]);
            let _ = writeln!(
                out,
                "stated precision (OUT/corrections, {} anchors): σ along / across / vertical {} mm, roll / pitch / \
                 heading {} mdeg; error after over σ {} and {}",
                p.anchors,
                three(p.position_sigma_rms_m.components().map(|v| v * 1e3)),
                three(p.attitude_sigma_rms_deg.components().map(|v| v * 1e3)),
                three(p.position_error_over_sigma.components()),
                three(p.attitude_error_over_sigma.components())
            );
        }
        let largest: Vec<String> = self
            .per_trajectory
            .iter()
            .filter_map(|t| {
                t.largest_error_without_datum_after
                    .along_track
                    .map(|l| format!("{} {:+.1} at {:.0} m", t.id, l.error_m * 1e3, l.arc_m))
            })
            .collect();
        if !largest.is_empty() {
            let _ = writeln!(out, "largest along-track error w/o the datum, after (mm): {}", largest.join(", "));
        }
        let _ = writeln!(
            out,
            "{} strips, {} points, {} surface points, {} tile-strip pairs, {} trajectory samples",
            self.strips, self.points, self.surface_points, self.tile_strip_pairs, self.trajectory_samples
        );
        if let Some(share) = self.surface_points_used_share {
            let _ = writeln!(out, "points used in the last iteration: {:.1} % of surface points", 100.0 * share);
        }
        if let Some(a) = &self.assignments {
            let classes: Vec<String> = a
                .wrong_share_by_class
                .iter()
                .map(|(name, c)| format!("{name} {:.2} %", 100.0 * c.wrong_share))
                .collect();
            let _ = writeln!(
                out,
                "wrong assignments in the last map pass: {:.2} % of {} observations in {} surface models ({})",
                100.0 * a.wrong_share,
                a.points,
                a.models,
                classes.join(", ")
            );
        }
        if let Some(l) = &self.latent_map {
            let classes: Vec<String> = l
                .per_class
                .iter()
                .map(|(name, c)| {
                    format!(
                        "{name} {:.2} / {:.2} / {:.2}",
                        c.error_rms_m * 1e3,
                        c.error_without_campaign_shift_rms_m * 1e3,
                        c.error_without_tile_shift_rms_m * 1e3
                    )
                })
                .collect();
            let _ = writeln!(
                out,
                "latent map: {} points, {} matched; error RMS {:.3} mm (mean {:+.3}), without the campaign's \
                 shift {:.3} mm (|error| 95th percentile {:.3}), without each tile's shift {:.3} mm; the \
                 strips' spread about it (median) {:.3} mm",
                l.points,
                l.matched,
                l.error_rms_m * 1e3,
                l.error_mean_m * 1e3,
                l.error_without_campaign_shift_rms_m * 1e3,
                l.error_without_campaign_shift_p95_abs_m * 1e3,
                l.error_without_tile_shift_rms_m * 1e3,
                l.std_median_m * 1e3
            );
            let _ = writeln!(
                out,
                "  by class, RMS / without the campaign's shift / without each tile's (mm): {}",
                classes.join(", ")
            );
        }
        if !self.worst_tiles_after.is_empty() {
            let _ = writeln!(out, "tiles whose strips disagree most after adjustment (offset from the tile mean, mm):");
            for t in self.worst_tiles_after.iter().take(5) {
                let offsets: Vec<String> = t.offsets_m.iter().map(|(id, o)| format!("{id} {:+.1}", o * 1e3)).collect();
                let _ = writeln!(out, "  tile {} (RMS {:.1}): {}", t.tile, t.rms_m * 1e3, offsets.join(", "));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests;
