//! The planner's memory between stages ([`PlanState`]) and a campaign's creation from its
//! manifest ([`new_campaign`]).

use super::task::field_input;
use super::*;
use precimap_core::{ControlTarget, IterationStep, Parameters};
use precimap_estimate::anderson::AndersonHistory;
use precimap_estimate::{ResidualHistogram, TileStats};
use precimap_formats::Manifest;
use precimap_jobs::{NewCampaign, QueueConfig, StageSpec, StripRecord, TrajectoryRecord};
use precimap_pipeline::report::{IterationReport, StripReport, TrajectoryReport};
use precimap_pipeline::ResolvedManifest;

/// The planner's memory between stages (the campaign's `plan_state` column).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PlanState {
    pub name: String,
    pub prefix: String,
    pub params: Parameters,
    pub strips: Vec<StripInput>,
    pub trajectories: Vec<TrajectoryInput>,
    /// Surveyed control and check targets in the processing frame.
    #[serde(default)]
    pub control: Vec<ControlTarget>,
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
    /// What the last map stage measured at the control and check targets.
    #[serde(default)]
    pub control_sums: Vec<precimap_core::ControlSums>,
    pub prepare_s: f64,
    pub estimate_s: f64,
    pub export_s: f64,
    /// The scanners the strips use, by name (the calibration's order).
    #[serde(default)]
    pub scanners: Vec<String>,
    /// The scanners' current calibration (empty unless the campaign estimates it).
    #[serde(default)]
    pub calibration: Vec<f64>,
    /// The calibration's last step: its precision and which unknowns the geometry determines.
    #[serde(default)]
    pub calibration_step: Option<precimap_estimate::calibration::CalibrationStep>,
}

impl PlanState {
    /// What a map task takes of the calibration, where the campaign estimates it.
    pub(super) fn calibration_input(&self) -> Option<CalibrationInput> {
        if self.calibration.is_empty() {
            return None;
        }
        let layout = self.params.calibration.layout(self.scanners.len());
        let per = layout.per_scanner().max(1);
        let scanners =
            self.calibration.chunks(per).map(|b| precimap_core::ScannerCalibration::from_block(&layout, b)).collect();
        Some(CalibrationInput { layout, scanner_of_strip: self.strips.iter().map(|s| s.scanner).collect(), scanners })
    }

    /// The calibration as the in-process driver keeps it (for the report and the export).
    pub fn calibration_state(&self) -> Option<precimap_pipeline::calibration::CalibrationState> {
        let input = self.calibration_input()?;
        Some(precimap_pipeline::calibration::CalibrationState {
            layout: input.layout,
            options: self.params.calibration.clone(),
            scanner_of_strip: input.scanner_of_strip,
            values: self.calibration.clone(),
            scanners: input.scanners,
            last: self.calibration_step.clone(),
        })
    }
}

impl PlanState {
    /// The state a campaign starts in: its inputs, nothing prepared, no iteration run.
    fn start(
        name: &str,
        prefix: &str,
        params: &Parameters,
        strips: Vec<StripInput>,
        trajectories: Vec<TrajectoryInput>,
        control: Vec<ControlTarget>,
        scanners: Vec<String>,
    ) -> Self {
        let n = trajectories.len();
        let calibration = vec![0.0; params.calibration.layout(scanners.len()).len()];
        Self {
            name: name.to_string(),
            prefix: prefix.to_string(),
            params: params.clone(),
            strips,
            trajectories,
            control,
            tiles: Vec::new(),
            anchor_ranges: Vec::new(),
            strip_reports: Vec::new(),
            points_total: 0,
            step_index: 0,
            iteration: 0,
            robust_sigma: None,
            corrections: vec![None; n],
            previous_corrections: vec![None; n],
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
            control_sums: Vec::new(),
            prepare_s: 0.0,
            estimate_s: 0.0,
            export_s: 0.0,
            scanners,
            calibration,
            calibration_step: None,
        }
    }
}

/// Builds a new campaign's rows and first stage from a validated manifest whose URIs are store
/// keys, with its references followed once ([`ResolvedManifest::new`]: each strip's trajectory
/// and lever arm, each trajectory's mean lever arm, the control targets in the processing frame).
pub fn new_campaign(
    manifest: &Manifest,
    resolved: ResolvedManifest,
    prefix: &str,
    queue: QueueConfig,
) -> (NewCampaign, StageSpec) {
    let strips: Vec<StripInput> = manifest
        .strips
        .iter()
        .zip(&resolved.strips)
        .enumerate()
        .map(|(i, (s, r))| StripInput {
            index: i as u32,
            id: s.id.clone(),
            uri: s.uri.clone(),
            trajectory: r.trajectory,
            trajectory_id: s.trajectory.clone(),
            trajectory_uri: manifest.trajectories[r.trajectory as usize].uri.clone(),
            lever_arm: r.lever_arm,
            scanner: r.scanner,
            field: field_input(manifest, r.trajectory as usize),
        })
        .collect();
    let trajectories: Vec<TrajectoryInput> = manifest
        .trajectories
        .iter()
        .zip(&resolved.mean_lever_arms)
        .enumerate()
        .map(|(i, (t, mean))| TrajectoryInput {
            index: i as u32,
            id: t.id.clone(),
            uri: t.uri.clone(),
            mean_lever_arm: *mean,
            field: field_input(manifest, i),
        })
        .collect();
    let state = PlanState::start(
        &manifest.name,
        prefix,
        &manifest.parameters,
        strips.clone(),
        trajectories.clone(),
        resolved.control,
        resolved.scanners,
    );
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
