//! The campaign's stage graph, as a pure state machine the job store runs inside the transaction
//! that completes a stage's last task (docs/design/framework.md, "The barrier, without a
//! coordinator"):
//!
//! `prepare` (one `segment_strip` per strip) → { `estimate` k (one `estimate_tile` per tile) →
//! [`field` k (one `solve_field`, in steps that solve the common-mode field)] →
//! `solve` k (one `solve_trajectory` per trajectory) } for each schedule step, with the in-process
//! driver's early-stop rule → `export` (`export_strip` per strip, `export_trajectory` per
//! trajectory) → `report` (`write_report`) → succeeded.
//!
//! Everything a task needs travels in its input (store keys of its inputs, parameters, the
//! schedule step), so an executor never reads more than its own task row and its own objects.
//!
//! Where each part lives:
//! - this file: the stage, task-kind and output names, and [`CampaignPlanner`], which routes a
//!   finished stage to the step that plans the next one;
//! - `task`: what travels through the queue, the task inputs ([`TaskInput`] and the strip,
//!   trajectory and corrections references it carries) and the task results the planner reads;
//! - `state`: the planner's memory ([`PlanState`]) and a campaign's creation ([`new_campaign`]);
//! - `iterate`: the prepare barrier and one iteration's stages (`estimate`, `field`, `solve`);
//! - `accelerate`: Anderson acceleration between settling iterations (`accelerate`, `combine`);
//! - `finish`: the `export` and `report` stages.

mod accelerate;
mod finish;
mod iterate;
mod state;
mod task;

pub use state::{new_campaign, PlanState};
pub use task::{
    ApplyCalibrationInput, ApplyResult, CalibrationInput, ChunkRef, CombineResult, CorrectionsRef, EstimateResult,
    ExportResult, FieldInput, FieldResult, MomentsResult, SegmentResult, SolveResult, StripInput, TaskInput,
    TrajectoryInput,
};

use accelerate::{after_accelerate, after_combine};
use finish::{export_stage, report_stage};
use iterate::{after_calibrate, after_estimate, after_field, after_prepare, after_solve, estimate_stage};
use precimap_core::TileKey;
use precimap_jobs::{CampaignRecord, FinishedStage, FinishedTask, Next, StagePlanner, Transition};
use precimap_pipeline::overlap_problem;
use serde::{Deserialize, Serialize};

pub const STAGE_PREPARE: &str = "prepare";
pub const STAGE_ESTIMATE: &str = "estimate";
pub const STAGE_FIELD: &str = "field";
pub const STAGE_SOLVE: &str = "solve";
/// Anderson acceleration between two settling iterations (`Parameters::anderson_depth`): each
/// trajectory's share of the coefficients' problem, then (after the planner solved for the
/// coefficients) each trajectory's combination.
pub const STAGE_ACCELERATE: &str = "accelerate";
pub const STAGE_COMBINE: &str = "combine";
/// The calibration's step applied to every trajectory (campaigns that estimate the scanners'
/// calibration, in steps that estimate the attitude).
pub const STAGE_CALIBRATE: &str = "calibrate";
pub const STAGE_EXPORT: &str = "export";
pub const STAGE_REPORT: &str = "report";

pub const KIND_SEGMENT_STRIP: &str = "segment_strip";
pub const KIND_ESTIMATE_TILE: &str = "estimate_tile";
pub const KIND_SOLVE_FIELD: &str = "solve_field";
pub const KIND_SOLVE_TRAJECTORY: &str = "solve_trajectory";
pub const KIND_ANDERSON_MOMENTS: &str = "anderson_moments";
pub const KIND_ANDERSON_COMBINE: &str = "anderson_combine";
pub const KIND_APPLY_CALIBRATION: &str = "apply_calibration";
pub const KIND_EXPORT_STRIP: &str = "export_strip";
pub const KIND_EXPORT_TRAJECTORY: &str = "export_trajectory";
pub const KIND_WRITE_REPORT: &str = "write_report";

/// Output names: `tile` chunks are named by their tile key, blocks by `blocks/{trajectory index}`.
pub const OUTPUT_CORRECTIONS: &str = "corrections";
pub const BLOCKS_PREFIX: &str = "blocks/";
/// A tile's common-mode field equations.
pub const OUTPUT_FIELD: &str = "field";
/// `solve_field` outputs: each trajectory's corrections with the field added (`start/{t}`), and
/// the corrections momentum measures from, shifted alike (`previous/{t}`).
pub const START_PREFIX: &str = "start/";
/// `solve_trajectory` output with the calibration: the trajectory's share of its solve.
pub const OUTPUT_SHARE: &str = "share";
/// `anderson_combine` output: the trajectory's start for the next iteration.
pub const OUTPUT_ACCELERATED: &str = "accelerated";
pub const PREVIOUS_PREFIX: &str = "previous/";
/// The anchors' horizontal positions of every trajectory, written by the first `solve_field`
/// task (from the trajectory files) and read by the later ones instead of those files.
pub const OUTPUT_POSITIONS: &str = "anchor_positions";
/// The latent-map standard-deviation objects (tile, object key) of a campaign's first and last
/// map stage, in tile order.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LatentStdKeys {
    pub first: Vec<(TileKey, String)>,
    pub last: Vec<(TileKey, String)>,
}

/// `estimate_tile` output: the tile's latent-map standard deviation per cell (QC, JSON).
pub const OUTPUT_LATENT_STD: &str = "latent_std";
/// A strip's per-point segment ids (a result, like the exported strips).
pub const SEGMENTS_PREFIX: &str = "segments/";
/// `estimate_tile` output of the last iteration: the tile's latent map (LAS), a result the
/// report task records under the same name (`latent/{tile}.las`).
pub const LATENT_MAP_PREFIX: &str = "latent/";

/// The planner the job store calls at every stage barrier.
#[derive(Clone, Copy, Debug, Default)]
pub struct CampaignPlanner;

impl StagePlanner for CampaignPlanner {
    fn plan(&self, campaign: &CampaignRecord, finished: &FinishedStage) -> Result<Transition, String> {
        let mut state = PlanState::deserialize(&campaign.plan_state)
            .map_err(|e| format!("the campaign's plan state is unreadable ({e}); it was written by another version"))?;
        let mut tiles = Vec::new();
        let mut iteration = None;
        let next = match finished.stage.as_str() {
            STAGE_PREPARE => {
                let task_s;
                (tiles, task_s) = after_prepare(&mut state, &finished.tasks)?;
                state.prepare_s = wall_seconds(finished, task_s);
                if state.tiles.is_empty() {
                    let ids: Vec<&str> = state.strips.iter().map(|s| s.id.as_str()).collect();
                    if let Some(problem) = overlap_problem(0, None, &ids) {
                        if !state.params.allow_low_usable_share {
                            return Err(problem);
                        }
                        tracing::warn!("campaign {}: {problem}", state.name);
                    }
                    // Nothing overlaps: every correction stays zero.
                    export_stage(&state)
                } else {
                    estimate_stage(&mut state)
                }
            }
            STAGE_ESTIMATE => {
                state.iteration_enqueued_at_ms =
                    state.iteration_enqueued_at_ms.or(finished.span_ms.map(|s| s.enqueued_at_ms));
                after_estimate(&mut state, &finished.tasks)?
            }
            STAGE_FIELD => after_field(&mut state, &finished.tasks)?,
            STAGE_SOLVE => {
                let (record, next) = after_solve(&mut state, &finished.tasks, finished.span_ms)?;
                iteration = record;
                next
            }
            STAGE_CALIBRATE => {
                let (record, next) = after_calibrate(&mut state, &finished.tasks, finished.span_ms)?;
                iteration = Some(record);
                next
            }
            STAGE_ACCELERATE => after_accelerate(&mut state, &finished.tasks, finished)?,
            STAGE_COMBINE => after_combine(&mut state, &finished.tasks)?,
            STAGE_EXPORT => {
                let task_s = seconds_of::<ExportResult>(&finished.tasks, |r| r.seconds)?;
                state.task_s += task_s;
                state.export_s = wall_seconds(finished, task_s);
                // The campaign row was last updated when the export stage was enqueued.
                let now_ms = finished.span_ms.map_or(campaign.updated_at_ms, |s| s.finished_at_ms);
                report_stage(&state, campaign, now_ms)
            }
            STAGE_REPORT => Next::Succeed,
            other => return Err(format!("unknown stage {other:?}")),
        };
        Ok(Transition { plan_state: serde_json::to_value(&state).map_err(|e| e.to_string())?, tiles, iteration, next })
    }
}

/// A stage's wall-clock seconds on the database's clock, or `fallback` where the store gave no
/// span (a stage finished without tasks).
fn wall_seconds(finished: &FinishedStage, fallback: f64) -> f64 {
    finished.span_ms.map_or(fallback, |s| s.seconds())
}

fn parse<T: serde::de::DeserializeOwned>(task: &FinishedTask) -> Result<T, String> {
    T::deserialize(&task.result).map_err(|e| format!("{} {}: unreadable result ({e})", task.kind, task.key))
}

fn seconds_of<T: serde::de::DeserializeOwned>(tasks: &[FinishedTask], f: impl Fn(&T) -> f64) -> Result<f64, String> {
    let mut total = 0.0;
    for t in tasks {
        if t.kind == KIND_WRITE_REPORT {
            continue;
        }
        total += f(&parse::<T>(t)?);
    }
    Ok(total)
}
