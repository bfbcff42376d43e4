//! The last stages: `export` (each strip and each trajectory with its corrections) and
//! `report` (the campaign's report, written by its own task).

use super::iterate::campaign_crs;
use super::*;
use precimap_jobs::{NewTask, StageSpec};
use precimap_pipeline::report::{Report, Timings};

pub(super) fn export_stage(state: &PlanState) -> Next {
    let spacing = state.params.anchor_spacing_m;
    let calibration = state.calibration_input();
    let mut tasks: Vec<NewTask> = state
        .strips
        .iter()
        .map(|s| {
            TaskInput::ExportStrip {
                prefix: state.prefix.clone(),
                strip: s.clone(),
                anchor_spacing_m: spacing,
                corrections: corrections_or_zero(state, s.trajectory),
                mounting: calibration.as_ref().and_then(|c| c.scanners.get(s.scanner as usize).copied()),
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
pub(super) fn report_stage(state: &PlanState, campaign: &CampaignRecord, now_ms: i64) -> Next {
    let report = Report {
        calibration: state.calibration_state().map(|c| c.report(&state.scanners)),
        campaign: state.name.clone(),
        manifest: format!("campaign {}", campaign.id),
        points_total: state.points_total,
        tiles: state.tiles.len(),
        strips: state.strip_reports.clone(),
        iterations: state.iterations.clone(),
        converged: state.converged,
        trajectories: state.trajectory_reports.clone(),
        residual_histogram: state.histogram.clone(),
        control: precimap_pipeline::control_report::ControlReport::new(&state.control, &state.control_sums),
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
