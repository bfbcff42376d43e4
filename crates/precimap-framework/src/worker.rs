//! Stateless executors: claim one task, run it while heart-beating its lease, commit its outputs
//! through the job store (the commit point), repeat. `work --once` is one round of this loop; the
//! embedded default and `serve` run the loop in-process.

use crate::error::{FrameworkError, TaskError};
use crate::exec::{execute, TaskContext, WriteGate};
use crate::lifecycle::{sweep_campaign, sweep_store_logged, Retention};
use crate::metrics;
use crate::plan::{CampaignPlanner, TaskInput};
use precimap_core::Parameters;
use precimap_jobs::{CampaignState, ClaimedTask, FailOutcome, JobError, JobStore};
use serde::Deserialize;
use std::collections::HashMap;
use std::future::Future;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::{watch, Notify};
use tracing::{debug, info, warn, Instrument as _};
use uuid::Uuid;

/// What one round of an executor did.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum WorkOutcome {
    /// The task ran and its outputs were committed.
    Done { kind: String, key: String },
    /// No task was runnable.
    NoWork,
    /// The task failed; it will be retried or, if permanent or out of attempts, fail its campaign.
    Failed { kind: String, key: String, error: String },
    /// Another executor took the task over (the lease expired) or its campaign was cancelled;
    /// nothing of this attempt was committed.
    LeaseLost { kind: String, key: String },
}

#[derive(Clone, Debug)]
pub struct ExecutorConfig {
    pub worker_id: String,
    /// Lease per claim; heartbeats renew it every third of it.
    pub lease: Duration,
    /// How long an executor keeps retrying a database that is unreachable before giving up.
    pub database_patience: Duration,
    /// What its clean-ups and sweeps keep, and for how long.
    pub retention: Retention,
}

impl Default for ExecutorConfig {
    fn default() -> Self {
        Self {
            worker_id: format!("{}-{}", hostname(), std::process::id()),
            lease: Duration::from_secs(60),
            database_patience: Duration::from_secs(120),
            retention: Retention::default(),
        }
    }
}

fn hostname() -> String {
    std::fs::read_to_string("/etc/hostname").map(|s| s.trim().to_string()).unwrap_or_else(|_| "executor".into())
}

#[derive(Clone, Debug)]
pub struct Executor {
    jobs: JobStore,
    ctx: TaskContext,
    config: ExecutorConfig,
    /// Wakes idle in-process executors when a task completes (a stage may have opened).
    wake: Arc<Notify>,
    /// Campaigns' parameters read so far (they never change).
    params: Arc<Mutex<HashMap<Uuid, Arc<Parameters>>>>,
    /// When this process last swept the store for objects no campaign owns.
    last_store_sweep: Arc<Mutex<Option<Instant>>>,
}

/// Campaigns whose parameters an executor keeps (the cache starts over when full).
const PARAMS_CACHED: usize = 64;

/// Asks the job store whether an attempt may still write ([`crate::exec::WriteGate`]).
#[derive(Debug)]
struct LeaseGate {
    jobs: JobStore,
    task: i64,
    token: Uuid,
    patience: Duration,
}

impl WriteGate for LeaseGate {
    fn may_write(&self) -> futures::future::BoxFuture<'_, Result<bool, String>> {
        Box::pin(async move {
            retry_transient(self.patience, || self.jobs.attempt_may_write(self.task, self.token))
                .await
                .map_err(|e| e.to_string())
        })
    }
}

/// Retries `op` while it fails with a transient database error (a restart, a dropped
/// connection), with back-off, for at most `patience`.
pub async fn retry_transient<T, F, Fut>(patience: Duration, mut op: F) -> Result<T, JobError>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<T, JobError>>,
{
    let started = Instant::now();
    let mut delay = Duration::from_millis(100);
    loop {
        match op().await {
            Err(e) if e.is_transient() && started.elapsed() < patience => {
                warn!(error = %e, "database unavailable; retrying in {delay:?}");
                tokio::time::sleep(delay).await;
                delay = (delay * 2).min(Duration::from_secs(5));
            }
            other => return other,
        }
    }
}

impl Executor {
    pub fn new(jobs: JobStore, ctx: TaskContext, config: ExecutorConfig) -> Self {
        Self {
            jobs,
            ctx,
            config,
            wake: Arc::new(Notify::new()),
            params: Arc::default(),
            last_store_sweep: Arc::default(),
        }
    }

    pub fn jobs(&self) -> &JobStore {
        &self.jobs
    }

    /// Rescues expired leases and advances stages whose last completer stopped before the
    /// barrier (any executor may; it is idempotent).
    pub async fn reconcile(&self) -> Result<(), FrameworkError> {
        let planner = CampaignPlanner;
        let report = retry_transient(self.config.database_patience, || self.jobs.reconcile(&planner)).await?;
        metrics::leases_expired(report.requeued + report.dead);
        metrics::retried("lease_expired", report.requeued);
        if report.requeued + report.dead + report.advanced > 0 {
            info!(
                requeued = report.requeued,
                dead = report.dead,
                advanced = report.advanced,
                "rescued expired leases and stuck stages"
            );
            if report.advanced > 0 {
                // A stage opened (or a campaign finished): idle loops may have work.
                self.wake.notify_waiters();
            }
        }
        for campaign in report.finished {
            self.clean_up(campaign).await;
        }
        self.sweep_finished().await;
        if self.store_sweep_due() {
            sweep_store_logged(&self.jobs, &self.ctx.objects, &self.config.retention).await;
        }
        Ok(())
    }

    /// Whether this process's last store sweep is at least the sweep interval ago (and if so,
    /// records that one starts now).
    fn store_sweep_due(&self) -> bool {
        let mut last = self.last_store_sweep.lock().unwrap_or_else(|p| p.into_inner());
        let due = last.is_none_or(|t| t.elapsed() >= self.config.retention.store_sweep_interval);
        if due {
            *last = Some(Instant::now());
        }
        due
    }

    /// The durable half of the orphan clean-up: sweeps finished campaigns that no sweep has
    /// covered since they finished at least one lease ago (the finishing executor's own clean-up
    /// may have died mid-way; attempts cancelled with the campaign may have written since), and
    /// marks each one after its sweep. A failure only postpones it to a later reconcile.
    async fn sweep_finished(&self) {
        let lease = self.config.lease;
        // Work files go with this sweep once their retention has passed (never, if kept for ever).
        let (grace, keep_work) = match self.config.retention.work {
            Some(work) => (lease.max(work), false),
            None => (lease, true),
        };
        loop {
            let claimed = retry_transient(self.config.database_patience, || self.jobs.claim_sweep(grace, lease)).await;
            let campaign = match claimed {
                Ok(Some(campaign)) => campaign,
                Ok(None) => return,
                Err(e) => {
                    warn!(error = %e, "claiming an orphan sweep failed");
                    return;
                }
            };
            match sweep_campaign(&self.jobs, &self.ctx.objects, campaign, keep_work).await {
                Ok(n) => {
                    if n > 0 {
                        info!(%campaign, removed = n, "swept objects of lost attempts");
                    }
                    if let Err(e) = self.jobs.mark_swept(campaign).await {
                        warn!(%campaign, error = %e, "recording an orphan sweep failed");
                    }
                }
                Err(e) => {
                    // Its sweep lease expires and another reconcile tries again.
                    warn!(%campaign, error = %e, "orphan sweep failed");
                    return;
                }
            }
        }
    }

    /// Runs a task claimed elsewhere (with [`JobStore::claim`]) as [`Executor::work_once`] runs
    /// the one it claims.
    pub async fn run_task(&self, task: ClaimedTask) -> Result<WorkOutcome, FrameworkError> {
        Ok(self.run_claimed(task, false).await?.0)
    }

    /// Claims and runs at most one task.
    pub async fn work_once(&self) -> Result<WorkOutcome, FrameworkError> {
        let claimed = self.claim().await?;
        match claimed {
            None => Ok(WorkOutcome::NoWork),
            Some(task) => Ok(self.run_claimed(task, false).await?.0),
        }
    }

    /// Claims the oldest runnable task, riding out a database restart.
    async fn claim(&self) -> Result<Option<ClaimedTask>, FrameworkError> {
        let started = Instant::now();
        let claim = || self.jobs.claim(&self.config.worker_id, self.config.lease);
        let claimed = retry_transient(self.config.database_patience, claim).await?;
        metrics::claimed(started.elapsed(), claimed.is_some());
        Ok(claimed)
    }

    /// Runs `held` (a task claimed by the previous round) or else a newly claimed task; with
    /// `claim_next`, a successful completion claims the next task in its own transaction
    /// ([`JobStore::complete_and_claim`]) and returns it for the next round.
    async fn work_round(
        &self,
        held: Option<ClaimedTask>,
        claim_next: bool,
    ) -> Result<(WorkOutcome, Option<ClaimedTask>), FrameworkError> {
        let task = match held {
            Some(task) => task,
            None => match self.claim().await? {
                None => return Ok((WorkOutcome::NoWork, None)),
                Some(task) => task,
            },
        };
        self.run_claimed(task, claim_next).await
    }

    /// Runs a claimed task; with `claim_next`, the completion also claims the next task. Its
    /// logs carry the campaign, task and attempt; its time and outcome go to the metrics.
    async fn run_claimed(
        &self,
        task: ClaimedTask,
        claim_next: bool,
    ) -> Result<(WorkOutcome, Option<ClaimedTask>), FrameworkError> {
        let started = Instant::now();
        let kind = task.kind.clone();
        let span = tracing::info_span!(
            "task",
            campaign = %task.campaign,
            task = task.id,
            kind = %task.kind,
            key = %task.key,
            attempt = task.attempt
        );
        let result = self.run_attempt(task, claim_next).instrument(span).await;
        if let Ok((outcome, _)) = &result {
            let outcome = match outcome {
                WorkOutcome::Done { .. } => "done",
                WorkOutcome::Failed { .. } => "failed",
                WorkOutcome::LeaseLost { .. } => "lease_lost",
                WorkOutcome::NoWork => "no_work",
            };
            metrics::task_finished(&kind, outcome, started.elapsed());
        }
        result
    }

    async fn run_attempt(
        &self,
        task: ClaimedTask,
        claim_next: bool,
    ) -> Result<(WorkOutcome, Option<ClaimedTask>), FrameworkError> {
        let patience = self.config.database_patience;
        let (kind, key) = (task.kind.clone(), task.key.clone());
        debug!(%kind, %key, attempt = task.attempt, "running");
        let input = match TaskInput::deserialize(&task.input) {
            Ok(i) => i,
            Err(e) => {
                let error = format!("unreadable task input ({e}); it was queued by another version");
                return Ok((self.fail(&task, TaskError::permanent(error)).await?, None));
            }
        };
        let input = match self.with_campaign_params(&task, input).await {
            Ok(input) => input,
            Err(e) => return Ok((self.fail(&task, e).await?, None)),
        };
        let gate = LeaseGate { jobs: self.jobs.clone(), task: task.id, token: task.lease_token, patience };
        let ctx = self.ctx.with_gate(Arc::new(gate));
        let (lost_tx, mut lost_rx) = watch::channel(false);
        // Aborted on drop, too: an executor shutting down drops this future mid-task, and a
        // heartbeat left running would keep the lease it hands back alive.
        let heartbeat = AbortOnDrop({
            let jobs = self.jobs.clone();
            let task = task.clone();
            let lease = self.config.lease;
            tokio::spawn(async move {
                loop {
                    tokio::time::sleep(lease / 3).await;
                    match jobs.heartbeat(&task, lease).await {
                        Ok(()) => {}
                        Err(JobError::LeaseLost) => {
                            let _ = lost_tx.send(true);
                            return;
                        }
                        // A database restart: keep trying; the lease may still survive it.
                        Err(e) => warn!(error = %e, "heartbeat failed"),
                    }
                }
            })
        });
        let result = tokio::select! {
            r = execute(&ctx, input, task.lease_token) => Some(r),
            _ = lost_rx.wait_for(|lost| *lost) => None,
        };
        drop(heartbeat);
        let Some(result) = result else {
            warn!(%kind, %key, "lease lost while running; abandoning this attempt");
            return Ok((WorkOutcome::LeaseLost { kind, key }, None));
        };
        match result {
            Ok(outcome) => {
                let planner = CampaignPlanner;
                let tries = AtomicU32::new(0);
                let (worker, lease) = (self.config.worker_id.as_str(), self.config.lease);
                let (jobs, task, outcome, planner) = (&self.jobs, &task, &outcome, &planner);
                let complete = || {
                    tries.fetch_add(1, Ordering::Relaxed);
                    async move {
                        if claim_next {
                            jobs.complete_and_claim(task, outcome.clone(), planner, worker, lease).await
                        } else {
                            Ok((jobs.complete(task, outcome.clone(), planner).await?, None))
                        }
                    }
                };
                match retry_transient(patience, complete).await {
                    Ok((completion, mut next)) => {
                        self.wake.notify_waiters();
                        metrics::points_processed(&kind, &outcome.result);
                        if completion.campaign_state != CampaignState::Running {
                            self.clean_up(task.campaign).await;
                            // The clean-up may take a while on a remote store: renew the lease of
                            // the task claimed with the completion before running it.
                            if let Some(n) = &next {
                                match self.jobs.heartbeat(n, lease).await {
                                    Ok(()) => {}
                                    Err(JobError::LeaseLost) => next = None,
                                    Err(e) => warn!(error = %e, "heartbeat of the next task failed"),
                                }
                            }
                        }
                        Ok((WorkOutcome::Done { kind, key }, next))
                    }
                    Err(JobError::LeaseLost) => {
                        let mut next = None;
                        if tries.load(Ordering::Relaxed) > 1 {
                            // A try that failed with a transient error may have committed the task
                            // before its barrier check failed; the retry then finds the task done.
                            // Its stage may be closed but not advanced: advance it now rather than
                            // at the next reconcile.
                            if let Err(e) = self.reconcile().await {
                                warn!(error = %e, "reconcile after a retried completion failed");
                            }
                            // That try may also have claimed a task for this loop, which holds
                            // nothing else now: take it rather than leave it leased until expiry.
                            if claim_next {
                                match self.jobs.leased_by(worker).await {
                                    Ok(mut leased) => next = (!leased.is_empty()).then(|| leased.remove(0)),
                                    Err(e) => {
                                        warn!(error = %e, "looking for a claim lost with a retried completion failed")
                                    }
                                }
                            }
                        }
                        Ok((WorkOutcome::LeaseLost { kind, key }, next))
                    }
                    Err(e) => Err(e.into()),
                }
            }
            Err(e) => Ok((self.fail(&task, e).await?, None)),
        }
    }

    /// `input` with its campaign's parameters filled in where it carries none (read from the job
    /// store once per campaign and process: they never change).
    async fn with_campaign_params(&self, task: &ClaimedTask, input: TaskInput) -> Result<TaskInput, TaskError> {
        if !input.needs_campaign_params() {
            return Ok(input);
        }
        let cached = self.params.lock().unwrap_or_else(|p| p.into_inner()).get(&task.campaign).cloned();
        let params = match cached {
            Some(params) => params,
            None => {
                let patience = self.config.database_patience;
                let stored = retry_transient(patience, || self.jobs.campaign_params(task.campaign))
                    .await
                    .map_err(TaskError::transient)?
                    .ok_or_else(|| {
                        TaskError::permanent("the campaign stores no parameters for its tasks; submit it again")
                    })?;
                let params: Arc<Parameters> = Arc::new(Parameters::deserialize(&stored).map_err(|e| {
                    TaskError::permanent(format!("the campaign's parameters are unreadable ({e}); submit it again"))
                })?);
                let mut held = self.params.lock().unwrap_or_else(|p| p.into_inner());
                if held.len() >= PARAMS_CACHED {
                    held.clear();
                }
                held.insert(task.campaign, Arc::clone(&params));
                params
            }
        };
        Ok(input.with_campaign_params(&params))
    }

    async fn fail(&self, task: &ClaimedTask, error: TaskError) -> Result<WorkOutcome, FrameworkError> {
        let (kind, key) = (task.kind.clone(), task.key.clone());
        warn!(%kind, %key, permanent = error.permanent, error = %error.message, "task failed");
        match retry_transient(self.config.database_patience, || self.jobs.fail(task, &error.message, error.permanent))
            .await
        {
            Ok(outcome) => {
                self.wake.notify_waiters();
                if outcome == FailOutcome::Dead {
                    self.clean_up(task.campaign).await;
                } else {
                    metrics::retried("failed", 1);
                }
                Ok(WorkOutcome::Failed { kind, key, error: error.message })
            }
            Err(JobError::LeaseLost) => Ok(WorkOutcome::LeaseLost { kind, key }),
            Err(e) => Err(e.into()),
        }
    }

    /// Removes a finished campaign's orphaned objects, and its work files unless they are kept
    /// for a while; a failure here only costs storage.
    async fn clean_up(&self, campaign: uuid::Uuid) {
        let keep_work = self.config.retention.keeps_work_at_finish();
        match sweep_campaign(&self.jobs, &self.ctx.objects, campaign, keep_work).await {
            Ok(0) => {}
            Ok(n) => info!(%campaign, removed = n, "removed objects of lost attempts and work files"),
            Err(e) => warn!(%campaign, error = %e, "orphan clean-up failed"),
        }
    }

    /// Hands every task this executor holds back to the queue (see [`JobStore::release`]): what
    /// an executor that stops before its tasks are done does, after dropping their futures, so
    /// that another executor runs them at once. `concurrency` is the loop count `work_loop` ran
    /// with (each loop claims under its own worker id). Returns how many were handed back.
    pub async fn release_held(&self, concurrency: usize) -> Result<usize, FrameworkError> {
        let id = &self.config.worker_id;
        let workers = std::iter::once(id.clone()).chain((0..concurrency.max(1)).map(|i| format!("{id}-{i}")));
        let mut released = 0;
        for worker in workers {
            for task in self.jobs.leased_by(&worker).await? {
                if self.jobs.release(&task).await? {
                    info!(kind = %task.kind, key = %task.key, attempt = task.attempt, "task handed back");
                    metrics::handed_back(&task.kind);
                    released += 1;
                }
            }
        }
        Ok(released)
    }

    /// Runs `concurrency` executor loops until `stop` turns true. Idle loops poll with back-off
    /// (a remote database) and wake at once when a sibling completes a task. A loop that is not
    /// stopping claims its next task in the transaction that completes the current one; a task
    /// claimed that way when `stop` turns true meanwhile is still run before the loop ends.
    pub async fn work_loop(&self, concurrency: usize, stop: watch::Receiver<bool>) -> Result<(), FrameworkError> {
        let mut loops = tokio::task::JoinSet::new();
        for i in 0..concurrency.max(1) {
            let mut me = self.clone();
            me.config.worker_id = format!("{}-{i}", self.config.worker_id);
            let mut stop = stop.clone();
            loops.spawn(async move {
                let _running = LoopGauge::start();
                let mut idle = Duration::from_millis(20);
                let mut last_reconcile = Instant::now() - me.config.lease;
                let mut held: Option<ClaimedTask> = None;
                while held.is_some() || !*stop.borrow() {
                    if last_reconcile.elapsed() >= me.config.lease / 2 {
                        me.reconcile().await?;
                        last_reconcile = Instant::now();
                    }
                    let claim_next = !*stop.borrow();
                    let (outcome, next) = me.work_round(held.take(), claim_next).await?;
                    held = next;
                    match outcome {
                        WorkOutcome::NoWork => {
                            tokio::select! {
                                _ = me.wake.notified() => {}
                                _ = tokio::time::sleep(idle) => {}
                                _ = stop.changed() => {}
                            }
                            idle = (idle * 2).min(Duration::from_secs(1));
                        }
                        _ => idle = Duration::from_millis(20),
                    }
                }
                Ok::<(), FrameworkError>(())
            });
        }
        let mut first_error = None;
        while let Some(joined) = loops.join_next().await {
            match joined {
                Ok(Ok(())) => {}
                Ok(Err(e)) => {
                    first_error.get_or_insert(e);
                }
                Err(e) => {
                    first_error.get_or_insert(FrameworkError::Internal(format!("executor loop stopped: {e}")));
                }
            }
        }
        first_error.map_or(Ok(()), Err)
    }
}

/// Aborts a spawned task when dropped.
#[derive(Debug)]
struct AbortOnDrop<T>(tokio::task::JoinHandle<T>);

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Counts an executor loop in the `precimap_executor_loops` gauge while it lives.
#[derive(Debug)]
struct LoopGauge;

impl LoopGauge {
    fn start() -> Self {
        metrics::executor_loops(1.0);
        LoopGauge
    }
}

impl Drop for LoopGauge {
    fn drop(&mut self) {
        metrics::executor_loops(-1.0);
    }
}
