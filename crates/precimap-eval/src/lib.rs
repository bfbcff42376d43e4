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
//!   ([`LatentMapEvaluation`]);
//! - `CAMP/truth/truth.json`'s simulator config: with `calibration` in report.json, the estimated
//!   mounting calibration against the simulator's calibration errors ([`CalibrationEvaluation`]).
//!
//! Strips are processed one at a time per thread (rayon across strips), so memory is bounded by
//! a strip per worker; everything accumulated across strips is constant-size or per tile.

mod agreement;
mod assemble;
mod assignments;
mod calibration;
mod error;
mod evaluation;
mod inputs;
mod latent;
mod normals;
mod precision;
mod segments;
mod stats;
mod strip;
mod summary;
mod trajectory;

pub use agreement::{AgreementTally, Orientation, Spread, SpreadMetric, SurfaceAgreement, UsedShares};
pub use assignments::{AssignmentEvaluation, AssignmentTally, ClassAssignments};
pub use calibration::{
    compare_calibration, CalibrationComparison, CalibrationEvaluation, CalibrationLargestError, ReportedUnknown,
};
pub use error::EvalError;
pub use evaluation::{
    AttitudeMetric, ClassEvaluation, Evaluation, FrameLargest, FrameMetric, Metric, StripEvaluation, TileDisagreement,
    TrajectoryEvaluation, VectorMetric,
};
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

use assemble::{assemble, totals};
use calibration::read_truth_calibration;
use evaluation::metric;
use inputs::{check_id, load_trajectory, read_corrections_tables, read_report, LoadedTrajectory};
use strip::{evaluate_strip, StripOutcome};

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

/// A trajectory's frame sums over its run-up and run-out, and their length in metres
/// ([`unscanned_frame_sums`]).
type UnscannedSums = (FrameSums, f64);

/// Evaluates the result folder `result_dir` of `precimap run` against the truth folder
/// `truth_dir` (`CAMP/truth`; the manifest is `CAMP/manifest.json`). The campaign folder `CAMP`
/// itself is taken as well: it is what people pass first.
pub fn evaluate(truth_dir: &Path, result_dir: &Path) -> Result<Evaluation, EvalError> {
    let CampaignInputs { truth_dir, manifest, strip_jobs, trajectory_jobs } = campaign_inputs(truth_dir)?;
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
    let mut evaluation = assemble(&strip_jobs, strips, &trajectory_jobs, trajectories, &largest, report.points_used);
    evaluation.calibration = match &report.calibration {
        Some(unknowns) => Some(compare_calibration(unknowns, &read_truth_calibration(&truth_dir)?)),
        None => None,
    };
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

/// The campaign of a truth folder: the canonical truth folder, the manifest, and each strip's and
/// trajectory's id and input file.
struct CampaignInputs {
    truth_dir: PathBuf,
    manifest: precimap_formats::Manifest,
    strip_jobs: Vec<(String, PathBuf)>,
    trajectory_jobs: Vec<(String, PathBuf)>,
}

/// Finds the campaign of `truth_dir` (the campaign folder itself is taken too) and resolves its
/// inputs.
fn campaign_inputs(truth_dir: &Path) -> Result<CampaignInputs, EvalError> {
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
    Ok(CampaignInputs { truth_dir, manifest, strip_jobs, trajectory_jobs })
}

#[cfg(test)]
mod tests;
