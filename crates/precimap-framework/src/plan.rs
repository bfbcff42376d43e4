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

use precimap_core::{IterationStep, Parameters, TileKey};
use precimap_estimate::anderson::{self, AndersonEntry, AndersonHistory, AndersonMoments};
use precimap_estimate::{ResidualHistogram, TileStats};
use precimap_formats::Manifest;
use precimap_jobs::{
    CampaignRecord, FinishedStage, FinishedTask, IterationRecord, NewCampaign, NewTask, Next, QueueConfig,
    StagePlanner, StageSpan, StageSpec, StripRecord, TileRecord, TrajectoryRecord, Transition,
};
use precimap_pipeline::report::{IterationReport, Report, StripReport, Timings, TrajectoryReport};
use precimap_pipeline::{after_iteration, effective_step, iteration_report, overlap_problem, AfterIteration, Place};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

pub const STAGE_PREPARE: &str = "prepare";
pub const STAGE_ESTIMATE: &str = "estimate";
pub const STAGE_FIELD: &str = "field";
pub const STAGE_SOLVE: &str = "solve";
/// Anderson acceleration between two settling iterations (`Parameters::anderson_depth`): each
/// trajectory's share of the coefficients' problem, then (after the planner solved for the
/// coefficients) each trajectory's combination.
pub const STAGE_ACCELERATE: &str = "accelerate";
pub const STAGE_COMBINE: &str = "combine";
pub const STAGE_EXPORT: &str = "export";
pub const STAGE_REPORT: &str = "report";

pub const KIND_SEGMENT_STRIP: &str = "segment_strip";
pub const KIND_ESTIMATE_TILE: &str = "estimate_tile";
pub const KIND_SOLVE_FIELD: &str = "solve_field";
pub const KIND_SOLVE_TRAJECTORY: &str = "solve_trajectory";
pub const KIND_ANDERSON_MOMENTS: &str = "anderson_moments";
pub const KIND_ANDERSON_COMBINE: &str = "anderson_combine";
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

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct StripInput {
    pub index: u32,
    pub id: String,
    pub uri: String,
    pub trajectory: u32,
    pub trajectory_id: String,
    pub trajectory_uri: String,
    pub lever_arm: [f64; 3],
    /// A field campaign's CRS and how the strip's trajectory is read.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<FieldInput>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct TrajectoryInput {
    pub index: u32,
    pub id: String,
    pub uri: String,
    /// Mean lever arm of the trajectory's scanners (see `precimap_pipeline::campaign`).
    pub mean_lever_arm: [f64; 3],
    /// A field campaign's CRS and how the trajectory is read.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<FieldInput>,
}

/// What a task of a field campaign (a manifest with `crs`) needs to read a trajectory and place
/// strips: the manifest's CRS and GPS week and the trajectory's entry (format, CRS, layout).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct FieldInput {
    pub crs: precimap_formats::CrsSpec,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gps_week: Option<u32>,
    pub trajectory: precimap_formats::TrajectoryRef,
}

/// The field input of `manifest`'s trajectory `index`, for a manifest with `crs`.
fn field_input(manifest: &Manifest, index: usize) -> Option<FieldInput> {
    manifest.crs.as_ref().map(|crs| FieldInput {
        crs: crs.clone(),
        gps_week: manifest.gps_week,
        trajectory: manifest.trajectories[index].clone(),
    })
}

/// A trajectory's corrections as a task reads them: the recorded object, or zeros over its
/// anchor range before the first solve.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct CorrectionsRef {
    pub trajectory: u32,
    pub anchors: (u32, u32),
    pub key: Option<String>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ChunkRef {
    pub strip: u32,
    pub key: String,
}

/// One task's input (the `input` column), tagged by kind.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum TaskInput {
    SegmentStrip {
        prefix: String,
        strip: StripInput,
        /// The campaign's parameters; absent in tasks queued now (the executor reads them from
        /// the campaign, where they are stored once), present in tasks queued by older versions.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        params: Option<Box<Parameters>>,
    },
    EstimateTile {
        prefix: String,
        iteration: u32,
        tile: TileKey,
        step: IterationStep,
        /// The campaign's parameters; absent in tasks queued now (the executor reads them from
        /// the campaign, where they are stored once), present in tasks queued by older versions.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        params: Option<Box<Parameters>>,
        trajectories: u32,
        chunks: Vec<ChunkRef>,
        corrections: Vec<CorrectionsRef>,
        /// Also write the tile's latent-map standard deviation (QC: the first and the last
        /// iteration).
        #[serde(default)]
        std_map: bool,
        /// Also write the tile's latent map (the product: the last iteration).
        #[serde(default)]
        latent_map: bool,
        /// The CRS a field campaign's latent map is written in (with `latent_map`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        crs: Option<precimap_formats::CrsSpec>,
    },
    SolveField {
        prefix: String,
        iteration: u32,
        /// The campaign's parameters; absent in tasks queued now (the executor reads them from
        /// the campaign, where they are stored once), present in tasks queued by older versions.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        params: Option<Box<Parameters>>,
        /// Every trajectory (its anchors' positions come from its file, unless `positions` names
        /// them).
        trajectories: Vec<TrajectoryInput>,
        /// The anchor positions object an earlier field task wrote.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        positions: Option<String>,
        current: Vec<CorrectionsRef>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        previous: Option<Vec<CorrectionsRef>>,
        /// Field equation object keys in tile order (the in-process driver's summation order).
        equations: Vec<String>,
    },
    SolveTrajectory {
        prefix: String,
        iteration: u32,
        trajectory: TrajectoryInput,
        step: IterationStep,
        /// The campaign's parameters; absent in tasks queued now (the executor reads them from
        /// the campaign, where they are stored once), present in tasks queued by older versions.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        params: Option<Box<Parameters>>,
        with_sigma: bool,
        current: CorrectionsRef,
        /// The corrections before `current`, when momentum carries the last step on.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        previous: Option<CorrectionsRef>,
        /// The corrections the iteration started from, when they differ from `current` (steps
        /// that solve the common-mode field): the change is measured from them
        /// (`solve_trajectory`'s `change_from`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        iteration_start: Option<CorrectionsRef>,
        /// Blocks object keys in tile order (the in-process driver's summation order).
        blocks: Vec<String>,
    },
    /// One trajectory's share of Anderson's coefficient problem from its settling iterations'
    /// history (`precimap_estimate::anderson::trajectory_moments`), oldest first. The shares
    /// are small; the planner sums them in trajectory order and solves for the coefficients.
    AndersonMoments {
        trajectory: u32,
        starts: Vec<CorrectionsRef>,
        results: Vec<CorrectionsRef>,
    },
    /// One trajectory's start for the next iteration from its results and the campaign's
    /// coefficients (`precimap_estimate::anderson::combine`).
    AndersonCombine {
        prefix: String,
        iteration: u32,
        trajectory: u32,
        results: Vec<CorrectionsRef>,
        coefficients: Vec<f64>,
    },
    ExportStrip {
        prefix: String,
        strip: StripInput,
        anchor_spacing_m: f64,
        corrections: CorrectionsRef,
    },
    ExportTrajectory {
        prefix: String,
        trajectory: TrajectoryInput,
        anchor_spacing_m: f64,
        corrections: CorrectionsRef,
        /// The campaign's parameters, to continue the corrections over the trajectory's run-up
        /// and run-out (`corrections_for_export`). Absent in tasks queued now: the executor
        /// reads them from the campaign, where they are stored once.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        params: Option<Box<Parameters>>,
    },
    WriteReport {
        prefix: String,
        report: Box<Report>,
        /// The tiles' latent-map standard-deviation objects of the first and the last iteration.
        #[serde(default)]
        latent_std: LatentStdKeys,
        #[serde(default)]
        tile_size_m: f64,
        /// The last iteration's latent-map objects as `(result name, object key)`: recorded as
        /// the report's outputs, so the results list them without a copy.
        #[serde(default)]
        latent_map: Vec<(String, String)>,
        /// A field campaign's CRS, which the QC plots state.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        crs: Option<precimap_formats::CrsSpec>,
    },
}

impl TaskInput {
    /// Fills in the campaign's parameters where the input does not carry them (tasks queued
    /// now); an input that carries its own keeps them.
    pub fn with_campaign_params(mut self, campaign: &Parameters) -> Self {
        match &mut self {
            Self::SegmentStrip { params, .. }
            | Self::EstimateTile { params, .. }
            | Self::SolveField { params, .. }
            | Self::SolveTrajectory { params, .. }
            | Self::ExportTrajectory { params, .. } => {
                if params.is_none() {
                    *params = Some(Box::new(campaign.clone()));
                }
            }
            Self::AndersonMoments { .. }
            | Self::AndersonCombine { .. }
            | Self::ExportStrip { .. }
            | Self::WriteReport { .. } => {}
        }
        self
    }

    /// Whether the input lacks parameters it needs (see [`TaskInput::with_campaign_params`]).
    pub fn needs_campaign_params(&self) -> bool {
        match self {
            Self::SegmentStrip { params, .. }
            | Self::EstimateTile { params, .. }
            | Self::SolveField { params, .. }
            | Self::SolveTrajectory { params, .. }
            | Self::ExportTrajectory { params, .. } => params.is_none(),
            _ => false,
        }
    }

    pub fn kind(&self) -> &'static str {
        match self {
            Self::SegmentStrip { .. } => KIND_SEGMENT_STRIP,
            Self::EstimateTile { .. } => KIND_ESTIMATE_TILE,
            Self::SolveField { .. } => KIND_SOLVE_FIELD,
            Self::SolveTrajectory { .. } => KIND_SOLVE_TRAJECTORY,
            Self::AndersonMoments { .. } => KIND_ANDERSON_MOMENTS,
            Self::AndersonCombine { .. } => KIND_ANDERSON_COMBINE,
            Self::ExportStrip { .. } => KIND_EXPORT_STRIP,
            Self::ExportTrajectory { .. } => KIND_EXPORT_TRAJECTORY,
            Self::WriteReport { .. } => KIND_WRITE_REPORT,
        }
    }

    fn task(&self, key: String) -> NewTask {
        NewTask {
            kind: self.kind().to_string(),
            key,
            input: serde_json::to_value(self).expect("task input serialises"),
        }
    }
}

/// Task results (the `result` column) the planner reads back.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SegmentResult {
    pub strip: u32,
    pub stats: precimap_estimate::PrepareStats,
    pub tiles: Vec<TileKey>,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EstimateResult {
    pub stats: TileStats,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FieldResult {
    /// Largest translation the field applied to an anchor.
    pub max_m: f64,
    /// The campaign's rotation solved with the field (degrees; zero without it).
    #[serde(default)]
    pub rotation_deg: [f64; 3],
    /// Largest heading the field gave an anchor (degrees; zero without it).
    #[serde(default)]
    pub heading_max_deg: f64,
    /// Largest tilt the field gave an anchor (degrees; zero without it).
    #[serde(default)]
    pub tilt_max_deg: f64,
    pub nodes: usize,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SolveResult {
    pub trajectory: u32,
    pub max_change_m: f64,
    /// The anchor of the largest change.
    #[serde(default)]
    pub max_change_anchor: u32,
    #[serde(default)]
    pub change_histogram: precimap_core::ChangeHistogram,
    pub report: TrajectoryReport,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MomentsResult {
    pub trajectory: u32,
    pub moments: AndersonMoments,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CombineResult {
    pub trajectory: u32,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ExportResult {
    pub points: u64,
    pub seconds: f64,
}

/// The planner's memory between stages (the campaign's `plan_state` column).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PlanState {
    pub name: String,
    pub prefix: String,
    pub params: Parameters,
    pub strips: Vec<StripInput>,
    pub trajectories: Vec<TrajectoryInput>,
    /// Tile → its chunks in strip order (filled when `prepare` completes).
    pub tiles: Vec<(TileKey, Vec<ChunkRef>)>,
    pub anchor_ranges: Vec<(u32, u32)>,
    pub strip_reports: Vec<StripReport>,
    pub points_total: u64,
    /// Schedule step of the current (or next) iteration and the iteration count so far.
    pub step_index: usize,
    pub iteration: u32,
    /// Robust σ of the last iteration's distances (the outlier threshold's floor).
    pub robust_sigma: Option<f64>,
    /// Latest recorded corrections per trajectory.
    pub corrections: Vec<Option<String>>,
    /// The corrections before the last iteration and that iteration's step (for momentum).
    #[serde(default)]
    pub previous_corrections: Vec<Option<String>>,
    #[serde(default)]
    pub previous_step: Option<IterationStep>,
    /// Blocks keys per trajectory between the map stage and the reduce stage (while the field
    /// stage runs in between).
    #[serde(default)]
    pub pending_blocks: Vec<Vec<String>>,
    /// This iteration's corrections with the field added, which the reduce stage starts from
    /// (empty in iterations without a field).
    #[serde(default)]
    pub started_from: Vec<Option<String>>,
    #[serde(default)]
    pub pending_field_max_m: f64,
    #[serde(default)]
    pub pending_campaign_rotation_deg: [f64; 3],
    #[serde(default)]
    pub pending_field_heading_max_deg: f64,
    #[serde(default)]
    pub pending_field_tilt_max_deg: f64,
    /// The settling iterations' corrections objects Anderson acceleration combines.
    #[serde(default)]
    pub anderson: AndersonHistory<Option<String>>,
    /// The coefficients that made the next iteration's start (reported with that iteration).
    #[serde(default)]
    pub pending_anderson_coefficients: Vec<f64>,
    /// The anchor positions object (see [`OUTPUT_POSITIONS`]), once a field task wrote it.
    #[serde(default)]
    pub anchor_positions: Option<String>,
    /// Statistics of the current iteration's map stage, reported once its reduce stage is done.
    pub pending_stats: Option<TileStats>,
    /// The latent-map standard-deviation objects of the first and the last iteration (QC).
    #[serde(default)]
    pub latent_std: LatentStdKeys,
    /// The last iteration's latent-map objects, `(result name, object key)`.
    #[serde(default)]
    pub latent_map: Vec<(String, String)>,
    pub pending_seconds: f64,
    /// When the current iteration's first stage was enqueued (database clock, ms): its map stage,
    /// or the Anderson stages that made its start, so that their time counts in the iteration
    /// they start and the iterations' seconds add up to the estimation's.
    #[serde(default)]
    pub iteration_enqueued_at_ms: Option<i64>,
    /// Task seconds summed over every finished task (the executors' work, however many shared it).
    #[serde(default)]
    pub task_s: f64,
    pub iterations: Vec<IterationReport>,
    pub converged: bool,
    pub trajectory_reports: Vec<TrajectoryReport>,
    pub histogram: ResidualHistogram,
    pub prepare_s: f64,
    pub estimate_s: f64,
    pub export_s: f64,
}

/// Builds a new campaign's rows and first stage from a validated manifest whose URIs are store keys.
pub fn new_campaign(manifest: &Manifest, prefix: &str, queue: QueueConfig) -> (NewCampaign, StageSpec) {
    let traj_index: BTreeMap<&str, u32> =
        manifest.trajectories.iter().enumerate().map(|(i, t)| (t.id.as_str(), i as u32)).collect();
    let mut lever_sums = vec![([0.0f64; 3], 0usize); manifest.trajectories.len()];
    let strips: Vec<StripInput> = manifest
        .strips
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let t = traj_index.get(s.trajectory.as_str()).copied().unwrap_or(0);
            let lever_arm = manifest.scanners.get(&s.scanner).map(|sc| sc.lever_arm_m).unwrap_or([0.0; 3]);
            let sum = &mut lever_sums[t as usize];
            for k in 0..3 {
                sum.0[k] += lever_arm[k];
            }
            sum.1 += 1;
            StripInput {
                index: i as u32,
                id: s.id.clone(),
                uri: s.uri.clone(),
                trajectory: t,
                trajectory_id: s.trajectory.clone(),
                trajectory_uri: manifest.trajectories[t as usize].uri.clone(),
                lever_arm,
                field: field_input(manifest, t as usize),
            }
        })
        .collect();
    let trajectories: Vec<TrajectoryInput> = manifest
        .trajectories
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let (sum, n) = lever_sums[i];
            let mean = if n > 0 { sum.map(|v| v / n as f64) } else { [0.0; 3] };
            TrajectoryInput {
                index: i as u32,
                id: t.id.clone(),
                uri: t.uri.clone(),
                mean_lever_arm: mean,
                field: field_input(manifest, i),
            }
        })
        .collect();
    let state = PlanState {
        name: manifest.name.clone(),
        prefix: prefix.to_string(),
        params: manifest.parameters.clone(),
        strips: strips.clone(),
        trajectories: trajectories.clone(),
        tiles: Vec::new(),
        anchor_ranges: Vec::new(),
        strip_reports: Vec::new(),
        points_total: 0,
        step_index: 0,
        iteration: 0,
        robust_sigma: None,
        corrections: vec![None; trajectories.len()],
        previous_corrections: vec![None; trajectories.len()],
        previous_step: None,
        pending_blocks: Vec::new(),
        started_from: Vec::new(),
        pending_field_max_m: 0.0,
        pending_campaign_rotation_deg: [0.0; 3],
        pending_field_heading_max_deg: 0.0,
        pending_field_tilt_max_deg: 0.0,
        anderson: AndersonHistory::default(),
        pending_anderson_coefficients: Vec::new(),
        anchor_positions: None,
        pending_stats: None,
        latent_std: LatentStdKeys::default(),
        latent_map: Vec::new(),
        pending_seconds: 0.0,
        iteration_enqueued_at_ms: None,
        task_s: 0.0,
        iterations: Vec::new(),
        converged: false,
        trajectory_reports: Vec::new(),
        histogram: ResidualHistogram::default(),
        prepare_s: 0.0,
        estimate_s: 0.0,
        export_s: 0.0,
    };
    let first = StageSpec {
        stage: STAGE_PREPARE.to_string(),
        iteration: 0,
        tasks: strips
            .iter()
            .map(|s| {
                TaskInput::SegmentStrip { prefix: prefix.to_string(), strip: s.clone(), params: None }
                    .task(s.id.clone())
            })
            .collect(),
    };
    // The strips and trajectories are rows of their own (and in the plan state): the stored spec
    // is the manifest without them, so a large campaign holds its input list once per table.
    let spec = Manifest {
        name: manifest.name.clone(),
        crs: manifest.crs.clone(),
        gps_week: manifest.gps_week,
        scanners: manifest.scanners.clone(),
        trajectories: Vec::new(),
        strips: Vec::new(),
        parameters: manifest.parameters.clone(),
        control: manifest.control.clone(),
    };
    let campaign = NewCampaign {
        name: manifest.name.clone(),
        spec: serde_json::to_value(&spec).expect("manifest serialises"),
        params: serde_json::to_value(&manifest.parameters).expect("parameters serialise"),
        plan_state: serde_json::to_value(&state).expect("plan state serialises"),
        object_prefix: prefix.to_string(),
        iterations_planned: manifest.parameters.schedule.len() as i32,
        strips: strips
            .iter()
            .map(|s| StripRecord {
                index: s.index as i32,
                id: s.id.clone(),
                trajectory: s.trajectory_id.clone(),
                uri: s.uri.clone(),
                points: None,
            })
            .collect(),
        trajectories: trajectories
            .iter()
            .map(|t| TrajectoryRecord { index: t.index as i32, id: t.id.clone(), uri: t.uri.clone() })
            .collect(),
        queue,
    };
    (campaign, first)
}

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

/// The tiles to record, and the stage's task seconds.
fn after_prepare(state: &mut PlanState, tasks: &[FinishedTask]) -> Result<(Vec<TileRecord>, f64), String> {
    let mut results: Vec<(SegmentResult, &FinishedTask)> =
        tasks.iter().map(|t| parse::<SegmentResult>(t).map(|r| (r, t))).collect::<Result<_, _>>()?;
    // Strip order, as the in-process driver combines them.
    results.sort_by_key(|(r, _)| r.strip);
    let mut tiles: BTreeMap<TileKey, Vec<ChunkRef>> = BTreeMap::new();
    let mut ranges = vec![(u32::MAX, 0u32); state.trajectories.len()];
    let mut reports = Vec::with_capacity(results.len());
    let mut points_total = 0;
    let mut seconds = 0.0;
    for (r, task) in &results {
        let strip =
            state.strips.get(r.strip as usize).ok_or_else(|| format!("result names unknown strip {}", r.strip))?;
        let range = &mut ranges[strip.trajectory as usize];
        range.0 = range.0.min(r.stats.first_anchor);
        range.1 = range.1.max(r.stats.last_anchor);
        for out in task.outputs.iter().filter(|o| !o.name.starts_with(SEGMENTS_PREFIX)) {
            let tile: TileKey =
                out.name.parse().map_err(|_| format!("{}: output {:?} is not a tile key", task.key, out.name))?;
            tiles.entry(tile).or_default().push(ChunkRef { strip: r.strip, key: out.object_key.clone() });
        }
        points_total += r.stats.points;
        seconds += r.seconds;
        reports.push(StripReport::new(&strip.id, &r.stats, r.tiles.len()));
    }
    for r in &mut ranges {
        if r.0 == u32::MAX {
            *r = (0, 0);
        }
    }
    let records = tiles
        .iter()
        .map(|(tile, chunks)| TileRecord {
            key: tile.to_string(),
            strips: chunks.iter().map(|c| state.strips[c.strip as usize].id.clone()).collect(),
            points: 0,
        })
        .collect();
    state.tiles = tiles.into_iter().collect();
    state.anchor_ranges = ranges;
    state.strip_reports = reports;
    state.points_total = points_total;
    state.task_s += seconds;
    Ok((records, seconds))
}

/// Whether the current iteration runs the schedule's last step (the run always ends on it:
/// early convergence jumps to it).
fn is_last_step(state: &PlanState) -> bool {
    state.step_index + 1 == state.params.schedule.len()
}

/// Where the current iteration stands in the run, as the in-process driver tells it.
fn place(state: &PlanState) -> Place {
    Place { first: state.iterations.is_empty(), last: is_last_step(state) }
}

fn corrections_ref(state: &PlanState, trajectory: u32) -> CorrectionsRef {
    CorrectionsRef {
        trajectory,
        anchors: state.anchor_ranges[trajectory as usize],
        key: state.corrections[trajectory as usize].clone(),
    }
}

/// Every trajectory's corrections as tasks read them, from one key (or none: zeros) per
/// trajectory.
fn corrections_refs(state: &PlanState, keys: &[Option<String>]) -> Vec<CorrectionsRef> {
    state.trajectories.iter().map(|t| correction_ref(state, t.index, keys)).collect()
}

/// Trajectory `t`'s entry of `keys` (see [`corrections_refs`]).
fn correction_ref(state: &PlanState, t: u32, keys: &[Option<String>]) -> CorrectionsRef {
    CorrectionsRef {
        trajectory: t,
        anchors: state.anchor_ranges[t as usize],
        key: keys.get(t as usize).cloned().flatten(),
    }
}

/// A field campaign's CRS (every strip input carries it).
fn campaign_crs(state: &PlanState) -> Option<precimap_formats::CrsSpec> {
    state.strips.first().and_then(|s| s.field.as_ref()).map(|f| f.crs.clone())
}

fn estimate_stage(state: &mut PlanState) -> Next {
    state.iteration += 1;
    let step = effective_step(&state.params, state.step_index, state.robust_sigma);
    let gather = place(state).latent_gather();
    let tasks = state
        .tiles
        .iter()
        .map(|(tile, chunks)| {
            let mut used: Vec<u32> = chunks.iter().map(|c| state.strips[c.strip as usize].trajectory).collect();
            used.sort_unstable();
            used.dedup();
            TaskInput::EstimateTile {
                prefix: state.prefix.clone(),
                iteration: state.iteration,
                tile: *tile,
                step,
                params: None,
                trajectories: state.trajectories.len() as u32,
                chunks: chunks.clone(),
                corrections: used.into_iter().map(|t| corrections_ref(state, t)).collect(),
                std_map: gather.std_map,
                latent_map: gather.map,
                crs: gather.map.then(|| campaign_crs(state)).flatten(),
            }
            .task(tile.to_string())
        })
        .collect();
    Next::Stage(StageSpec { stage: STAGE_ESTIMATE.to_string(), iteration: state.iteration as i32, tasks })
}

fn after_estimate(state: &mut PlanState, tasks: &[FinishedTask]) -> Result<Next, String> {
    let mut per_tile: Vec<(TileKey, &FinishedTask)> = tasks
        .iter()
        .map(|t| {
            t.key.parse::<TileKey>().map(|k| (k, t)).map_err(|_| format!("estimate task key {:?} is not a tile", t.key))
        })
        .collect::<Result<_, _>>()?;
    // Tile order: the in-process driver sums blocks and statistics in this order.
    per_tile.sort_by_key(|(k, _)| *k);
    let mut stats = TileStats::new(TileKey { tx: 0, ty: 0 });
    let mut blocks: Vec<Vec<String>> = vec![Vec::new(); state.trajectories.len()];
    let mut equations = Vec::new();
    let mut seconds = 0.0;
    let mut latent_std = Vec::with_capacity(per_tile.len());
    let mut latent_map = Vec::new();
    for (tile, task) in &per_tile {
        let r: EstimateResult = parse(task)?;
        stats.merge(&r.stats);
        seconds += r.seconds;
        for out in &task.outputs {
            if out.name == OUTPUT_FIELD {
                equations.push(out.object_key.clone());
                continue;
            }
            if out.name == OUTPUT_LATENT_STD {
                latent_std.push((*tile, out.object_key.clone()));
                continue;
            }
            if out.name.starts_with(LATENT_MAP_PREFIX) {
                latent_map.push((out.name.clone(), out.object_key.clone()));
                continue;
            }
            let t: usize = out
                .name
                .strip_prefix(BLOCKS_PREFIX)
                .and_then(|s| s.parse().ok())
                .filter(|&t: &usize| t < blocks.len())
                .ok_or_else(|| format!("{}: unexpected output {:?}", task.key, out.name))?;
            blocks[t].push(out.object_key.clone());
        }
    }
    state.pending_stats = Some(stats);
    state.pending_seconds = seconds;
    let place = place(state);
    if place.first {
        state.latent_std.first = latent_std.clone();
    }
    if place.last {
        state.latent_std.last = latent_std;
        state.latent_map = latent_map;
    }
    let step = effective_step(&state.params, state.step_index, state.robust_sigma);
    let momentum = state.previous_step.is_some_and(|p| step.momentum_continues(&p, &state.params));
    if !step.solves_field(&state.params) {
        let current = state.corrections.clone();
        let previous = momentum.then(|| state.previous_corrections.clone());
        return Ok(solve_stage(state, blocks, current, previous, None));
    }
    state.pending_blocks = blocks;
    let task = TaskInput::SolveField {
        prefix: state.prefix.clone(),
        iteration: state.iteration,
        params: None,
        trajectories: state.trajectories.clone(),
        positions: state.anchor_positions.clone(),
        current: corrections_refs(state, &state.corrections),
        previous: momentum.then(|| corrections_refs(state, &state.previous_corrections)),
        equations,
    }
    .task("field".into());
    Ok(Next::Stage(StageSpec { stage: STAGE_FIELD.to_string(), iteration: state.iteration as i32, tasks: vec![task] }))
}

fn after_field(state: &mut PlanState, tasks: &[FinishedTask]) -> Result<Next, String> {
    let task = tasks.first().ok_or("the field stage finished without its task")?;
    let r: FieldResult = parse(task)?;
    state.pending_seconds += r.seconds;
    state.pending_field_max_m = r.max_m;
    state.pending_campaign_rotation_deg = r.rotation_deg;
    state.pending_field_heading_max_deg = r.heading_max_deg;
    state.pending_field_tilt_max_deg = r.tilt_max_deg;
    let n = state.trajectories.len();
    let mut start = vec![None; n];
    let mut previous = vec![None; n];
    let mut any_previous = false;
    for out in &task.outputs {
        if out.name == OUTPUT_POSITIONS {
            state.anchor_positions = Some(out.object_key.clone());
            continue;
        }
        let (slot, name) = if let Some(t) = out.name.strip_prefix(START_PREFIX) {
            (&mut start, t)
        } else if let Some(t) = out.name.strip_prefix(PREVIOUS_PREFIX) {
            any_previous = true;
            (&mut previous, t)
        } else {
            return Err(format!("{}: unexpected output {:?}", task.key, out.name));
        };
        let t: usize = name
            .parse()
            .ok()
            .filter(|&t: &usize| t < n)
            .ok_or_else(|| format!("{}: output {:?} names no trajectory", task.key, out.name))?;
        slot[t] = Some(out.object_key.clone());
    }
    if start.iter().any(Option::is_none) {
        return Err(format!("{}: not every trajectory's shifted corrections were recorded", task.key));
    }
    let blocks = std::mem::take(&mut state.pending_blocks);
    state.started_from = start.clone();
    let iteration_start = state.corrections.clone();
    Ok(solve_stage(state, blocks, start, any_previous.then_some(previous), Some(iteration_start)))
}

/// The reduce stage: one `solve_trajectory` per trajectory from `current` (with `previous` when
/// momentum carries the last step on), its change measured from `iteration_start` where the
/// field moved `current` away from it.
fn solve_stage(
    state: &mut PlanState,
    mut blocks: Vec<Vec<String>>,
    current: Vec<Option<String>>,
    previous: Option<Vec<Option<String>>>,
    iteration_start: Option<Vec<Option<String>>>,
) -> Next {
    let step = effective_step(&state.params, state.step_index, state.robust_sigma);
    let with_sigma = is_last_step(state);
    let reference = |keys: &[Option<String>], t: u32| CorrectionsRef {
        trajectory: t,
        anchors: state.anchor_ranges[t as usize],
        key: keys.get(t as usize).cloned().flatten(),
    };
    let tasks = state
        .trajectories
        .iter()
        .map(|traj| {
            TaskInput::SolveTrajectory {
                prefix: state.prefix.clone(),
                iteration: state.iteration,
                trajectory: traj.clone(),
                step,
                params: None,
                with_sigma,
                current: reference(&current, traj.index),
                previous: previous.as_ref().map(|p| reference(p, traj.index)),
                iteration_start: iteration_start.as_ref().map(|s| reference(s, traj.index)),
                blocks: std::mem::take(&mut blocks[traj.index as usize]),
            }
            .task(traj.id.clone())
        })
        .collect();
    Next::Stage(StageSpec { stage: STAGE_SOLVE.to_string(), iteration: state.iteration as i32, tasks })
}

fn after_solve(
    state: &mut PlanState,
    tasks: &[FinishedTask],
    span: Option<StageSpan>,
) -> Result<(IterationRecord, Next), String> {
    let mut changes = precimap_core::ChangeHistogram::default();
    let mut reports = vec![None; state.trajectories.len()];
    // Per trajectory, its largest change and where (in trajectory order, as the in-process
    // driver picks the place among equal changes).
    let mut largest = vec![None; state.trajectories.len()];
    let step = effective_step(&state.params, state.step_index, state.robust_sigma);
    let momentum_carried = state.previous_step.is_some_and(|p| step.momentum_continues(&p, &state.params));
    let starts = state.corrections.clone();
    // Momentum measures the next step from where this one started (after the field, if any).
    state.previous_corrections =
        if state.started_from.is_empty() { state.corrections.clone() } else { std::mem::take(&mut state.started_from) };
    state.previous_step = Some(effective_step(&state.params, state.step_index, state.robust_sigma));
    let mut seconds = state.pending_seconds;
    for task in tasks {
        let r: SolveResult = parse(task)?;
        let t = r.trajectory as usize;
        if t >= reports.len() {
            return Err(format!("{}: result names unknown trajectory {t}", task.key));
        }
        largest[t] = Some((r.max_change_m, r.max_change_anchor));
        changes.merge(&r.change_histogram);
        seconds += r.seconds;
        let key = task
            .outputs
            .iter()
            .find(|o| o.name == OUTPUT_CORRECTIONS)
            .ok_or_else(|| format!("{}: no corrections recorded", task.key))?;
        state.corrections[t] = Some(key.object_key.clone());
        reports[t] = Some(r.report);
    }
    state.trajectory_reports = reports.into_iter().flatten().collect();
    let accelerate =
        state.anderson.record(&state.params, &step, momentum_carried, starts, || state.corrections.clone());
    let stats = state.pending_stats.take().unwrap_or_else(|| TileStats::new(TileKey { tx: 0, ty: 0 }));
    state.task_s += seconds;
    // Wall time from the map stage's enqueueing to the last solve, as the in-process driver
    // reports it (task seconds where the store gave no span).
    let wall = match (state.iteration_enqueued_at_ms.take(), span) {
        (Some(enqueued_at_ms), Some(span)) => StageSpan { enqueued_at_ms, ..span }.seconds(),
        _ => seconds,
    };
    let (max_change, max_change_at) = precimap_pipeline::report::ChangeLocation::largest(
        state
            .trajectories
            .iter()
            .zip(&largest)
            .filter_map(|(t, c)| c.map(|(change, anchor)| (t.id.as_str(), change, anchor))),
        state.params.anchor_spacing_m,
    );
    let mut report = iteration_report(state.iteration as usize, &step, &stats, max_change, &changes, wall);
    report.max_correction_change_at = max_change_at;
    report.common_mode_field_max_m = std::mem::take(&mut state.pending_field_max_m);
    report.campaign_rotation_deg = std::mem::take(&mut state.pending_campaign_rotation_deg);
    report.common_mode_heading_max_deg = std::mem::take(&mut state.pending_field_heading_max_deg);
    report.common_mode_tilt_max_deg = std::mem::take(&mut state.pending_field_tilt_max_deg);
    report.anderson_coefficients = std::mem::take(&mut state.pending_anderson_coefficients);
    state.histogram = stats.histogram.clone();
    state.robust_sigma = stats.histogram.robust_sigma_m();
    state.estimate_s += wall;
    state.iterations.push(report.clone());
    let record = IterationRecord {
        iteration: state.iteration as i32,
        stats: serde_json::to_value(&report).map_err(|e| e.to_string())?,
    };
    let next = match after_iteration(
        state.step_index,
        state.params.schedule.len(),
        max_change,
        state.params.convergence_tolerance_m,
    ) {
        AfterIteration::Step(s) => {
            state.step_index = s;
            if accelerate {
                accelerate_stage(state)
            } else {
                estimate_stage(state)
            }
        }
        AfterIteration::Done { converged } => {
            let ids: Vec<&str> = state.strips.iter().map(|s| s.id.as_str()).collect();
            let problem = overlap_problem(state.tiles.len(), state.iterations.last(), &ids);
            if let Some(problem) = &problem {
                if !state.params.allow_low_usable_share {
                    return Err(problem.clone());
                }
                tracing::warn!("campaign {}: {problem}", state.name);
            }
            state.converged = converged && problem.is_none();
            export_stage(state)
        }
    };
    Ok((record, next))
}

/// One `anderson_moments` task per trajectory over its recorded history (the in-process
/// driver's `AndersonHistory::accelerate` computes the same shares).
fn accelerate_stage(state: &PlanState) -> Next {
    let tasks = state
        .trajectories
        .iter()
        .map(|traj| {
            TaskInput::AndersonMoments {
                trajectory: traj.index,
                starts: history_refs(state, traj.index, |e| &e.starts),
                results: history_refs(state, traj.index, |e| &e.results),
            }
            .task(traj.id.clone())
        })
        .collect();
    Next::Stage(StageSpec { stage: STAGE_ACCELERATE.to_string(), iteration: state.iteration as i32, tasks })
}

/// Trajectory `t`'s recorded corrections in the Anderson history, oldest first (`pick`: each
/// entry's starts or results).
fn history_refs(
    state: &PlanState,
    t: u32,
    pick: impl Fn(&AndersonEntry<Option<String>>) -> &Vec<Option<String>>,
) -> Vec<CorrectionsRef> {
    state.anderson.entries.iter().map(|e| correction_ref(state, t, pick(e))).collect()
}

/// Sums the trajectories' shares in trajectory order (as `precimap_estimate::anderson::accelerate`
/// does), solves for the coefficients and enqueues one `anderson_combine` task per trajectory.
fn after_accelerate(state: &mut PlanState, tasks: &[FinishedTask], finished: &FinishedStage) -> Result<Next, String> {
    let (shares, seconds) = by_trajectory(state, tasks, |r: &MomentsResult| (r.trajectory, r.seconds))?;
    let mut total = AndersonMoments::zeros(state.anderson.entries.len().saturating_sub(1));
    for (t, share) in shares.iter().enumerate() {
        let (share, _) = share.as_ref().ok_or_else(|| format!("no Anderson share was recorded for trajectory {t}"))?;
        total.add(t, &share.moments).map_err(|e| format!("Anderson acceleration: {e}"))?;
    }
    let coefficients = anderson::coefficients(&total);
    state.task_s += seconds;
    // The next iteration starts here.
    state.iteration_enqueued_at_ms = finished.span_ms.map(|s| s.enqueued_at_ms);
    let tasks = state
        .trajectories
        .iter()
        .map(|traj| {
            TaskInput::AndersonCombine {
                prefix: state.prefix.clone(),
                iteration: state.iteration,
                trajectory: traj.index,
                results: history_refs(state, traj.index, |e| &e.results),
                coefficients: coefficients.clone(),
            }
            .task(traj.id.clone())
        })
        .collect();
    state.pending_anderson_coefficients = coefficients;
    Ok(Next::Stage(StageSpec { stage: STAGE_COMBINE.to_string(), iteration: state.iteration as i32, tasks }))
}

/// The combinations become the next iteration's corrections.
fn after_combine(state: &mut PlanState, tasks: &[FinishedTask]) -> Result<Next, String> {
    let (combined, seconds) = by_trajectory(state, tasks, |r: &CombineResult| (r.trajectory, r.seconds))?;
    let mut accelerated = Vec::with_capacity(combined.len());
    for (t, c) in combined.iter().enumerate() {
        let (_, task) =
            c.as_ref().ok_or_else(|| format!("trajectory {t}'s accelerated corrections were not recorded"))?;
        let out = task
            .outputs
            .iter()
            .find(|o| o.name == OUTPUT_ACCELERATED)
            .ok_or_else(|| format!("{}: no accelerated corrections recorded", task.key))?;
        accelerated.push(Some(out.object_key.clone()));
    }
    state.corrections = accelerated;
    state.task_s += seconds;
    Ok(estimate_stage(state))
}

/// Per trajectory index, its task's result and the task (`None` where no task named it).
type ByTrajectory<'a, T> = Vec<Option<(T, &'a FinishedTask)>>;

/// A per-trajectory stage's results by trajectory index, and the sum of the tasks' seconds
/// (`of`: a result's trajectory index and seconds).
fn by_trajectory<'a, T: serde::de::DeserializeOwned>(
    state: &PlanState,
    tasks: &'a [FinishedTask],
    of: impl Fn(&T) -> (u32, f64),
) -> Result<(ByTrajectory<'a, T>, f64), String> {
    let mut out: ByTrajectory<'a, T> = state.trajectories.iter().map(|_| None).collect();
    let mut seconds = 0.0;
    for task in tasks {
        let r: T = parse(task)?;
        let (t, s) = of(&r);
        let slot =
            out.get_mut(t as usize).ok_or_else(|| format!("{}: result names unknown trajectory {t}", task.key))?;
        seconds += s;
        *slot = Some((r, task));
    }
    Ok((out, seconds))
}

fn export_stage(state: &PlanState) -> Next {
    let spacing = state.params.anchor_spacing_m;
    let mut tasks: Vec<NewTask> = state
        .strips
        .iter()
        .map(|s| {
            TaskInput::ExportStrip {
                prefix: state.prefix.clone(),
                strip: s.clone(),
                anchor_spacing_m: spacing,
                corrections: corrections_or_zero(state, s.trajectory),
            }
            .task(s.id.clone())
        })
        .collect();
    tasks.extend(state.trajectories.iter().map(|t| {
        TaskInput::ExportTrajectory {
            prefix: state.prefix.clone(),
            trajectory: t.clone(),
            anchor_spacing_m: spacing,
            corrections: corrections_or_zero(state, t.index),
            params: None,
        }
        .task(t.id.clone())
    }));
    Next::Stage(StageSpec { stage: STAGE_EXPORT.to_string(), iteration: 0, tasks })
}

fn corrections_or_zero(state: &PlanState, trajectory: u32) -> CorrectionsRef {
    CorrectionsRef {
        trajectory,
        anchors: state.anchor_ranges.get(trajectory as usize).copied().unwrap_or((0, 0)),
        key: state.corrections.get(trajectory as usize).cloned().flatten(),
    }
}

/// The report, written at `now_ms` (database clock) by its own task.
fn report_stage(state: &PlanState, campaign: &CampaignRecord, now_ms: i64) -> Next {
    let report = Report {
        campaign: state.name.clone(),
        manifest: format!("campaign {}", campaign.id),
        points_total: state.points_total,
        tiles: state.tiles.len(),
        strips: state.strip_reports.clone(),
        iterations: state.iterations.clone(),
        converged: state.converged,
        trajectories: state.trajectory_reports.clone(),
        residual_histogram: state.histogram.clone(),
        // Wall-clock seconds on the database's clock, as the in-process driver reports them;
        // `task_s` adds the executors' summed task seconds (the work, however many shared it).
        timings: Timings {
            prepare_s: state.prepare_s,
            estimate_s: state.estimate_s,
            export_s: state.export_s,
            total_s: (now_ms - campaign.created_at_ms).max(0) as f64 / 1000.0,
            task_s: Some(state.task_s),
        },
    };
    let task = TaskInput::WriteReport {
        prefix: state.prefix.clone(),
        report: Box::new(report),
        latent_std: state.latent_std.clone(),
        tile_size_m: state.params.tile_size_m,
        latent_map: state.latent_map.clone(),
        crs: campaign_crs(state),
    }
    .task("report".into());
    Next::Stage(StageSpec { stage: STAGE_REPORT.to_string(), iteration: 0, tasks: vec![task] })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An export task queued before its input carried the parameters still reads (its
    /// trajectory's ends are then held); one queued now carries them through the queue.
    #[test]
    fn export_trajectory_input_reads_with_and_without_parameters() {
        let queued_before = serde_json::json!({
            "kind": "export_trajectory",
            "prefix": "c/1",
            "trajectory": {"index": 0, "id": "v01", "uri": "trajectories/v01.csv", "mean_lever_arm": [0.0, 0.0, 0.0]},
            "anchor_spacing_m": 0.5,
            "corrections": {"trajectory": 0, "anchors": [9, 921], "key": null},
        });
        let TaskInput::ExportTrajectory { params, corrections, .. } = serde_json::from_value(queued_before).unwrap()
        else {
            panic!("not an export_trajectory input");
        };
        assert!(params.is_none());
        assert_eq!(corrections.anchors, (9, 921));
        let input = TaskInput::ExportTrajectory {
            prefix: "c/1".into(),
            trajectory: TrajectoryInput {
                index: 0,
                id: "v01".into(),
                uri: "trajectories/v01.csv".into(),
                mean_lever_arm: [0.0; 3],
                field: None,
            },
            anchor_spacing_m: 0.5,
            corrections,
            params: Some(Box::new(Parameters { end_extension_m: 7.0, ..Parameters::default() })),
        };
        let read: TaskInput = serde_json::from_value(serde_json::to_value(&input).unwrap()).unwrap();
        let TaskInput::ExportTrajectory { params: Some(params), .. } = read else {
            panic!("the parameters did not come through");
        };
        assert_eq!(params.end_extension_m, 7.0);
    }
}
