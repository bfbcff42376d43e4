//! What the framework measures, through the `metrics` facade: each process records its own
//! (executors: tasks, claims, bytes; whoever reconciles: lease expiries), and [`observe_job_store`]
//! reads what only the database knows (the queue, the campaigns) when a scrape asks. The binary
//! installs the Prometheus recorder that renders them; without one, recording costs nothing.
//! Counters are per process: sum them over processes (`sum by (kind) (rate(…))`).

use crate::error::FrameworkError;
use crate::plan::{
    KIND_ANDERSON_COMBINE, KIND_ANDERSON_MOMENTS, KIND_APPLY_CALIBRATION, KIND_ESTIMATE_TILE, KIND_EXPORT_STRIP,
    KIND_EXPORT_TRAJECTORY, KIND_SEGMENT_STRIP, KIND_SOLVE_FIELD, KIND_SOLVE_TRAJECTORY, KIND_WRITE_REPORT,
};
use metrics::{counter, describe_counter, describe_gauge, describe_histogram, gauge, histogram, Unit};
use precimap_jobs::{CampaignState, JobStore};
use std::time::Duration;

pub const TASK_KINDS: [&str; 10] = [
    KIND_SEGMENT_STRIP,
    KIND_ESTIMATE_TILE,
    KIND_SOLVE_FIELD,
    KIND_SOLVE_TRAJECTORY,
    KIND_ANDERSON_MOMENTS,
    KIND_ANDERSON_COMBINE,
    KIND_APPLY_CALIBRATION,
    KIND_EXPORT_STRIP,
    KIND_EXPORT_TRAJECTORY,
    KIND_WRITE_REPORT,
];

const QUEUE_TASKS: &str = "precimap_queue_tasks";
const EXECUTORS_BUSY: &str = "precimap_executors_busy";
const EXECUTOR_LOOPS: &str = "precimap_executor_loops";
const CLAIM_SECONDS: &str = "precimap_claim_duration_seconds";
const TASK_SECONDS: &str = "precimap_task_duration_seconds";
const TASKS_FINISHED: &str = "precimap_tasks_finished_total";
const LEASE_EXPIRIES: &str = "precimap_lease_expiries_total";
const RETRIES: &str = "precimap_task_retries_total";
const POINTS: &str = "precimap_points_processed_total";
const STORE_READ: &str = "precimap_object_store_read_bytes_total";
const STORE_WRITTEN: &str = "precimap_object_store_written_bytes_total";
const CAMPAIGNS: &str = "precimap_campaigns";
const CAMPAIGN_ITERATION: &str = "precimap_campaign_iteration";
const CAMPAIGN_RESIDUAL: &str = "precimap_campaign_residual_std_metres";
const CAMPAIGN_CHANGE: &str = "precimap_campaign_max_correction_change_metres";
const CAMPAIGN_POINTS_USED: &str = "precimap_campaign_points_used";

/// Names, units and help texts of every series; call once after installing a recorder.
pub fn describe() {
    describe_gauge!(QUEUE_TASKS, "Open tasks of all campaigns by kind and state (queued, leased).");
    describe_gauge!(EXECUTORS_BUSY, "Executor loops holding a lease (all processes, from the job store).");
    describe_gauge!(EXECUTOR_LOOPS, "Executor loops running in this process.");
    describe_histogram!(
        CLAIM_SECONDS,
        Unit::Seconds,
        "Time of one claim on the job store, by whether it found a task."
    );
    describe_histogram!(TASK_SECONDS, Unit::Seconds, "Time from claim to commit of a task, by kind and outcome.");
    describe_counter!(
        TASKS_FINISHED,
        "Tasks this process ended, by kind and outcome (done, failed, lease_lost, handed_back)."
    );
    describe_counter!(LEASE_EXPIRIES, "Expired leases this process rescued (requeued or, on the last attempt, dead).");
    describe_counter!(RETRIES, "Tasks queued again after a failure or an expired lease, by reason.");
    describe_counter!(
        POINTS,
        Unit::Count,
        "Points (estimation: point copies) the tasks of this process went through, by kind."
    );
    describe_counter!(STORE_READ, Unit::Bytes, "Bytes this process read from the object store.");
    describe_counter!(STORE_WRITTEN, Unit::Bytes, "Bytes this process wrote to the object store.");
    describe_gauge!(CAMPAIGNS, "Campaigns in the job store's newest 1,000, by state.");
    describe_gauge!(CAMPAIGN_ITERATION, "The iteration a running campaign is at.");
    describe_gauge!(CAMPAIGN_RESIDUAL, "Residual standard deviation of a running campaign's last iteration (metres).");
    describe_gauge!(
        CAMPAIGN_CHANGE,
        "Largest anchor correction change of a running campaign's last iteration (metres)."
    );
    describe_gauge!(CAMPAIGN_POINTS_USED, Unit::Count, "Observations of a running campaign's last iteration.");
}

pub(crate) fn claimed(elapsed: Duration, found: bool) {
    histogram!(CLAIM_SECONDS, "found" => if found { "yes" } else { "no" }).record(elapsed.as_secs_f64());
}

/// A task this process ended: `outcome` is done, failed, lease_lost or handed_back.
pub(crate) fn task_finished(kind: &str, outcome: &'static str, elapsed: Duration) {
    let kind = known_kind(kind);
    histogram!(TASK_SECONDS, "kind" => kind, "outcome" => outcome).record(elapsed.as_secs_f64());
    counter!(TASKS_FINISHED, "kind" => kind, "outcome" => outcome).increment(1);
}

/// The points a finished task went through, read off its result (`stats.points` of the
/// pre-processing and estimation tasks, `points` of an export).
pub(crate) fn points_processed(kind: &str, result: &serde_json::Value) {
    let points = result.pointer("/stats/points").or_else(|| result.get("points")).and_then(serde_json::Value::as_u64);
    if let Some(points) = points {
        counter!(POINTS, "kind" => known_kind(kind)).increment(points);
    }
}

/// A task this process handed back to the queue when it stopped.
pub(crate) fn handed_back(kind: &str) {
    counter!(TASKS_FINISHED, "kind" => known_kind(kind), "outcome" => "handed_back").increment(1);
}

pub(crate) fn retried(reason: &'static str, n: u64) {
    if n > 0 {
        counter!(RETRIES, "reason" => reason).increment(n);
    }
}

pub(crate) fn leases_expired(n: u64) {
    if n > 0 {
        counter!(LEASE_EXPIRIES).increment(n);
    }
}

pub(crate) fn store_read(bytes: u64) {
    counter!(STORE_READ).increment(bytes);
}

pub(crate) fn store_written(bytes: u64) {
    counter!(STORE_WRITTEN).increment(bytes);
}

pub(crate) fn executor_loops(delta: f64) {
    gauge!(EXECUTOR_LOOPS).increment(delta);
}

/// The label for a task kind: one of [`TASK_KINDS`], so that a row queued by another version
/// cannot grow the label set without bound.
fn known_kind(kind: &str) -> &'static str {
    TASK_KINDS.into_iter().find(|k| *k == kind).unwrap_or("other")
}

/// Reads the queue and the running campaigns from the job store into gauges: what a scrape of
/// `/metrics` shows of the whole system, whichever process serves it.
pub async fn observe_job_store(jobs: &JobStore) -> Result<(), FrameworkError> {
    let depth = jobs.queue_depth().await?;
    for kind in TASK_KINDS.into_iter().chain(["other"]) {
        for state in ["queued", "leased"] {
            let n = depth.open.iter().filter(|(k, s, _)| known_kind(k) == kind && s == state).map(|r| r.2).sum::<i64>();
            gauge!(QUEUE_TASKS, "kind" => kind, "state" => state).set(n as f64);
        }
    }
    gauge!(EXECUTORS_BUSY).set(depth.busy_executors as f64);
    let campaigns = jobs.list_campaigns(1000).await?;
    for state in [CampaignState::Running, CampaignState::Succeeded, CampaignState::Failed, CampaignState::Cancelled] {
        let n = campaigns.iter().filter(|c| c.state == state).count();
        gauge!(CAMPAIGNS, "state" => state.as_str()).set(n as f64);
    }
    for campaign in campaigns.iter().filter(|c| c.state == CampaignState::Running) {
        let id = campaign.id.to_string();
        gauge!(CAMPAIGN_ITERATION, "campaign" => id.clone()).set(f64::from(campaign.iteration));
        if let Some(last) = jobs.iterations(campaign.id).await?.last() {
            let stat = |name: &str| last.stats.get(name).and_then(serde_json::Value::as_f64);
            if let Some(v) = stat("residual_std_m") {
                gauge!(CAMPAIGN_RESIDUAL, "campaign" => id.clone()).set(v);
            }
            if let Some(v) = stat("max_correction_change_m") {
                gauge!(CAMPAIGN_CHANGE, "campaign" => id.clone()).set(v);
            }
            if let Some(v) = stat("points_used") {
                gauge!(CAMPAIGN_POINTS_USED, "campaign" => id).set(v);
            }
        }
    }
    Ok(())
}
