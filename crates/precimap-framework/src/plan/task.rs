//! What travels through the queue: each task's input (the `input` column, [`TaskInput`], with the
//! strip, trajectory and corrections references it carries) and the results the planner reads
//! back (the `result` column).

use super::*;
use precimap_core::{ControlTarget, IterationStep, Parameters};
use precimap_estimate::anderson::AndersonMoments;
use precimap_estimate::TileStats;
use precimap_formats::Manifest;
use precimap_jobs::NewTask;
use precimap_pipeline::report::{Report, TrajectoryReport};

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct StripInput {
    pub index: u32,
    pub id: String,
    pub uri: String,
    pub trajectory: u32,
    pub trajectory_id: String,
    pub trajectory_uri: String,
    pub lever_arm: [f64; 3],
    /// The index of the strip's scanner among the campaign's (the calibration's order).
    #[serde(default)]
    pub scanner: u32,
    /// A field campaign's CRS and how the strip's trajectory is read.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<FieldInput>,
}

/// What a map task needs of the scanners' calibration, where the campaign estimates it.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct CalibrationInput {
    pub layout: precimap_core::CalibrationLayout,
    pub scanner_of_strip: Vec<u32>,
    pub scanners: Vec<precimap_core::ScannerCalibration>,
}

impl CalibrationInput {
    pub fn tile(&self) -> precimap_estimate::TileCalibration<'_> {
        precimap_estimate::TileCalibration {
            layout: &self.layout,
            scanner_of_strip: &self.scanner_of_strip,
            scanners: &self.scanners,
        }
    }
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
pub(super) fn field_input(manifest: &Manifest, index: usize) -> Option<FieldInput> {
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

/// The input of an `apply_calibration` task ([`TaskInput::ApplyCalibration`]).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ApplyCalibrationInput {
    pub prefix: String,
    pub iteration: u32,
    pub trajectory: TrajectoryInput,
    /// The corrections the solve wrote (with an unchanged calibration).
    pub corrections: CorrectionsRef,
    /// The trajectory's share object.
    pub share: String,
    /// The corrections the iteration started from (the change is measured from them).
    pub iteration_start: CorrectionsRef,
    pub delta: Vec<f64>,
    /// The solve's report of the trajectory (its observation counts), made again from the
    /// moved corrections.
    pub report: TrajectoryReport,
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
        /// The control and check targets near the tile (processing frame).
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        control: Vec<ControlTarget>,
        /// The scanners' current calibration, where the campaign estimates it.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        calibration: Option<CalibrationInput>,
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
        /// The calibration's unknowns, where the step estimates it: solve with the terms the
        /// blocks carry, and write the trajectory's share of the calibration's solve (`share`).
        #[serde(default, skip_serializing_if = "is_zero")]
        calibration: u32,
    },
    /// One trajectory's corrections moved by the calibration's step the planner solved from
    /// every trajectory's share (`precimap_estimate::solve::apply_calibration_step`).
    ApplyCalibration(Box<ApplyCalibrationInput>),
    /// One trajectory's share of Anderson's coefficient problem from its settling iterations'
    /// history (`precimap_estimate::anderson::trajectory_moments`), oldest first. The shares
    /// are small; the planner sums them in trajectory order and solves for the coefficients.
    AndersonMoments { trajectory: u32, starts: Vec<CorrectionsRef>, results: Vec<CorrectionsRef> },
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
        /// The strip's scanner's estimated calibration, where the campaign estimates it.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        mounting: Option<precimap_core::ScannerCalibration>,
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
            | Self::ApplyCalibration(_)
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
            Self::ApplyCalibration(_) => KIND_APPLY_CALIBRATION,
            Self::ExportStrip { .. } => KIND_EXPORT_STRIP,
            Self::ExportTrajectory { .. } => KIND_EXPORT_TRAJECTORY,
            Self::WriteReport { .. } => KIND_WRITE_REPORT,
        }
    }

    pub(super) fn task(&self, key: String) -> NewTask {
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
    /// The trajectory's share of the calibration's solve without its `y` (which the share
    /// object holds), where the task solved with the calibration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<precimap_estimate::calibration::CalibrationShare>,
}

/// `apply_calibration`'s result: the trajectory's change once the calibration's step is applied.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ApplyResult {
    pub trajectory: u32,
    pub max_change_m: f64,
    pub max_change_anchor: u32,
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

fn is_zero(v: &u32) -> bool {
    *v == 0
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
