//! In-process orchestration of a campaign (the task graph on one machine): load and validate the
//! manifest, prepare every strip into tile chunks, iterate map (tiles) and reduce (trajectories)
//! on the paper's schedule, export corrected strips and trajectories and `report.json`.
//! The task functions in [`tasks`] are the units a job framework invokes one at a time.

pub mod calibration;
pub mod campaign;
pub mod control_report;
pub mod error;
pub mod field;
pub mod prior;
pub mod qc;
pub mod report;
pub mod run;
pub mod tasks;

pub use campaign::{control_targets, Campaign, ResolvedManifest, ResolvedStrip};
pub use error::PipelineError;
pub use report::Report;
pub use run::{
    after_iteration, effective_step, iteration_report, overlap_problem, run_campaign, trajectory_report,
    AfterIteration, Place, Progress, RunOptions,
};
