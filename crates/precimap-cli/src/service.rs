//! The job-framework commands: `run` on the embedded default, `serve`, `work`, and the client
//! commands `submit`, `status`, `results`, `cancel`, `delete`.

use crate::progress::Display;
use crate::storage_args::{LimitArgs, RetentionArgs};
use anyhow::{bail, Context, Result};
use clap::Args;
use precimap_api::{ApiState, Auth, Client};
use precimap_framework::{
    default_queue, run_embedded, EmbeddedOptions, Executor, ExecutorConfig, Framework, Objects, RunStatus, TaskContext,
    WorkOutcome,
};
use precimap_jobs::JobStore;
use std::collections::HashSet;
use std::path::Path;
use std::time::Duration;

/// Where the job store and the object store are.
#[derive(Args, Debug, Clone)]
pub struct Backends {
    /// Job store: sqlite://PATH or postgres://USER@HOST/DB.
    #[arg(long, env = "PRECIMAP_DB", default_value = "sqlite://precimap-state/jobs.db")]
    pub db: String,
    /// Object store: file:///ABSOLUTE/FOLDER or s3://BUCKET[/PREFIX] (with the AWS_* variables).
    #[arg(long, env = "PRECIMAP_STORE")]
    pub store: Option<String>,
    /// Lease of a claimed task in seconds (heartbeats renew it every third).
    #[arg(long, env = "PRECIMAP_LEASE_S", default_value_t = 60)]
    pub lease_s: u64,
    #[command(flatten)]
    pub retention: RetentionArgs,
}

impl Backends {
    fn store_url(&self) -> Result<String> {
        match &self.store {
            Some(s) => Ok(s.clone()),
            None => {
                let dir = std::env::current_dir()?.join("precimap-state").join("store");
                Ok(format!("file://{}", dir.display()))
            }
        }
    }

    async fn connect(&self) -> Result<Framework> {
        if let Some(path) = self.db.strip_prefix("sqlite://") {
            if let Some(parent) = Path::new(path.split('?').next().unwrap_or(path)).parent() {
                if !parent.as_os_str().is_empty() {
                    std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
                }
            }
        }
        let jobs =
            JobStore::connect(&self.db).await.with_context(|| format!("connecting to the job store {}", self.db))?;
        let objects = Objects::from_url(&self.store_url()?)?;
        Ok(Framework { jobs, objects, queue: default_queue() })
    }

    fn executor(&self, framework: &Framework) -> Executor {
        let scratch = std::env::temp_dir().join(format!("precimap-scratch-{}", std::process::id()));
        let config = ExecutorConfig {
            lease: Duration::from_secs(self.lease_s.max(3)),
            retention: self.retention.retention(),
            ..ExecutorConfig::default()
        };
        Executor::new(framework.jobs.clone(), TaskContext::new(framework.objects.clone(), scratch), config)
    }
}

/// Installs the process's Prometheus recorder (once; `serve` and `work` call it) and returns
/// what renders its series.
fn install_metrics() -> Result<precimap_api::MetricsRenderer> {
    use metrics_exporter_prometheus::{Matcher, PrometheusBuilder};
    use metrics_util::MetricKindMask;
    // Seconds: a claim takes milliseconds, a task up to minutes.
    const BUCKETS: [f64; 16] =
        [0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0];
    let handle = PrometheusBuilder::new()
        .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), &BUCKETS)
        .context("setting the metrics' histogram buckets")?
        // A finished campaign's gauges stop being set; drop them after a while.
        .idle_timeout(MetricKindMask::GAUGE, Some(Duration::from_secs(600)))
        .install_recorder()
        .context("installing the metrics recorder")?;
    precimap_framework::metrics::describe();
    Ok(precimap_api::MetricsRenderer(std::sync::Arc::new(move || handle.render())))
}

/// Serves `GET /metrics` (this process's series) and `GET /healthz` on `address`, for an
/// executor running as its own process.
async fn serve_executor_metrics(address: &str, render: precimap_api::MetricsRenderer) -> Result<()> {
    use axum::routing::get;
    let listener =
        tokio::net::TcpListener::bind(address).await.with_context(|| format!("listening for metrics on {address}"))?;
    let app = axum::Router::new()
        .route(
            "/metrics",
            get(move || {
                let render = render.clone();
                async move {
                    ([(axum::http::header::CONTENT_TYPE, "text/plain; version=0.0.4; charset=utf-8")], (render.0)())
                }
            }),
        )
        .route("/healthz", get(|| async { "ok" }));
    tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            tracing::warn!(error = %e, "the metrics endpoint stopped");
        }
    });
    Ok(())
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the async runtime")
}

fn cores() -> usize {
    rayon::current_num_threads().max(1)
}

/// `precimap run` on the embedded default: SQLite + local store + in-process executors.
pub fn run_framework(manifest: &Path, out: &Path, keep_work: bool) -> Result<precimap_pipeline::Report> {
    let display = Display::new();
    let options = EmbeddedOptions { out_dir: out.to_path_buf(), concurrency: cores(), keep_state: keep_work };
    let mut shown = 0usize;
    let mut last_stage = String::new();
    runtime()?
        .block_on(run_embedded(manifest, &options, |s: &RunStatus| {
            let stage = &s.campaign.stage;
            if *stage != last_stage && (stage == "prepare" || stage == "export") {
                display.permanent(&format!("{stage}: {} tasks", s.stage_counts.total()));
            }
            last_stage.clone_from(stage);
            for it in s.iterations.iter().skip(shown) {
                if let Ok(report) =
                    serde_json::from_value::<precimap_pipeline::report::IterationReport>(it.stats.clone())
                {
                    display.iteration(&report, s.campaign.iterations_planned as usize);
                }
            }
            shown = s.iterations.len();
            display.transient(&format!(
                "{} {}: {} done, {} running, {} queued",
                s.campaign.stage,
                if s.campaign.iteration > 0 { format!("{}", s.campaign.iteration) } else { String::new() },
                s.stage_counts.done,
                s.stage_counts.leased,
                s.stage_counts.queued
            ));
        }))
        .with_context(|| format!("running {}", manifest.display()))?;
    let path = out.join("report.json");
    let report: precimap_pipeline::Report =
        serde_json::from_slice(&std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?)?;
    display.finish(&report);
    Ok(report)
}

#[derive(Args, Debug)]
pub struct ServeArgs {
    #[command(flatten)]
    pub backends: Backends,
    /// Address to listen on.
    #[arg(long, env = "PRECIMAP_LISTEN", default_value = "127.0.0.1:8080")]
    pub listen: String,
    /// In-process executors (0: only separate `precimap work` processes run tasks).
    #[arg(long, env = "PRECIMAP_WORKERS", default_value_t = 0)]
    pub workers: usize,
    /// Bearer token writers must present.
    #[arg(long, env = "PRECIMAP_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Accept writes without a token (only sensible on a loopback address).
    #[arg(long)]
    pub no_auth: bool,
    /// Largest accepted upload in bytes.
    #[arg(long, env = "PRECIMAP_MAX_UPLOAD_BYTES", default_value_t = 64 << 30)]
    pub max_upload_bytes: u64,
    /// On SIGTERM or SIGINT the server stops accepting, finishes its requests, and gives its
    /// in-process executors (--workers) this many seconds to finish their tasks before handing
    /// the unfinished ones back to the queue.
    #[arg(long, env = "PRECIMAP_SHUTDOWN_GRACE_S", default_value_t = 90)]
    pub shutdown_grace_s: u64,
    /// Largest accepted manifest in bytes (read no further than this).
    #[arg(long, env = "PRECIMAP_MAX_MANIFEST_BYTES", default_value_t = 4 << 20)]
    pub max_manifest_bytes: usize,
    #[command(flatten)]
    pub limits: HttpLimits,
    #[command(flatten)]
    pub campaign_limits: LimitArgs,
}

/// What clients may hold open and ask for at once; every wait has a timeout.
#[derive(Args, Debug, Clone)]
pub struct HttpLimits {
    /// Open connections at most; more clients wait in the listen backlog.
    #[arg(long, env = "PRECIMAP_MAX_CONNECTIONS", default_value_t = 1024)]
    pub max_connections: usize,
    /// Seconds from a request's first byte until its header must be complete.
    #[arg(long, env = "PRECIMAP_HEADER_TIMEOUT_S", default_value_t = 20.0)]
    pub header_timeout_s: f64,
    /// Seconds a connection may sit idle (before its first request or between requests).
    #[arg(long, env = "PRECIMAP_IDLE_TIMEOUT_S", default_value_t = 60.0)]
    pub idle_timeout_s: f64,
    /// Longest wait in seconds for the next part of a request body; also the grace period
    /// before --body-min-rate applies.
    #[arg(long, env = "PRECIMAP_BODY_TIMEOUT_S", default_value_t = 30.0)]
    pub body_timeout_s: f64,
    /// Bytes per second a request body must average while the server waits for it (0: off).
    #[arg(long, env = "PRECIMAP_BODY_MIN_RATE", default_value_t = 1024)]
    pub body_min_rate: u64,
    /// Requests handled at once; more are answered 503 with Retry-After.
    #[arg(long, env = "PRECIMAP_MAX_IN_FLIGHT", default_value_t = 256)]
    pub max_in_flight: usize,
    /// Authorised writes (submissions, uploads, cancels, deletes) handled at once; more get 503.
    #[arg(long, env = "PRECIMAP_MAX_IN_FLIGHT_WRITES", default_value_t = 16)]
    pub max_in_flight_writes: usize,
    /// Sustained reads per second per client address; more get 429 (0: unlimited).
    #[arg(long, env = "PRECIMAP_READS_PER_S", default_value_t = 20.0)]
    pub reads_per_s: f64,
    /// Reads a client may make in a burst above --reads-per-s.
    #[arg(long, env = "PRECIMAP_READ_BURST", default_value_t = 100.0)]
    pub read_burst: f64,
}

impl HttpLimits {
    fn seconds(name: &str, value: f64) -> Result<Duration> {
        Duration::try_from_secs_f64(value)
            .ok()
            .filter(|d| !d.is_zero())
            .with_context(|| format!("--{name} must be a positive number of seconds, not {value}"))
    }

    fn connection(&self) -> Result<precimap_api::ConnectionLimits> {
        if self.max_connections == 0 {
            bail!("--max-connections must be at least 1");
        }
        Ok(precimap_api::ConnectionLimits {
            max_connections: self.max_connections,
            header_timeout: Self::seconds("header-timeout-s", self.header_timeout_s)?,
            idle_timeout: Self::seconds("idle-timeout-s", self.idle_timeout_s)?,
            body_timeout: Self::seconds("body-timeout-s", self.body_timeout_s)?,
            body_min_rate: self.body_min_rate,
        })
    }

    fn admission(&self) -> Result<precimap_api::AdmissionLimits> {
        if self.max_in_flight == 0 || self.max_in_flight_writes == 0 {
            bail!("--max-in-flight and --max-in-flight-writes must be at least 1");
        }
        if !(self.reads_per_s.is_finite() && self.reads_per_s >= 0.0) {
            bail!("--reads-per-s must be 0 (unlimited) or a positive number, not {}", self.reads_per_s);
        }
        if !(self.read_burst.is_finite() && self.read_burst >= 1.0) {
            bail!("--read-burst must be at least 1, not {}", self.read_burst);
        }
        Ok(precimap_api::AdmissionLimits {
            max_in_flight: self.max_in_flight,
            max_in_flight_writes: self.max_in_flight_writes,
            reads_per_s: self.reads_per_s,
            read_burst: self.read_burst,
        })
    }
}

pub fn serve(args: ServeArgs) -> Result<()> {
    let auth = match (&args.token, args.no_auth) {
        (Some(t), _) if !t.is_empty() => Auth::Token(t.clone()),
        (_, true) => Auth::Disabled,
        _ => {
            bail!("set PRECIMAP_TOKEN (or --token) so that only authorised clients can write; --no-auth disables this")
        }
    };
    let connection_limits = args.limits.connection()?;
    let admission_limits = args.limits.admission()?;
    runtime()?.block_on(async move {
        let framework = args.backends.connect().await?;
        let mut state = ApiState::new(framework.clone(), auth).with_admission(admission_limits);
        state.max_upload_bytes = args.max_upload_bytes;
        state.metrics = Some(install_metrics()?);
        state.max_manifest_bytes = args.max_manifest_bytes;
        state.limits = args.campaign_limits.limits();
        let listener = tokio::net::TcpListener::bind(&args.listen)
            .await
            .with_context(|| format!("listening on {}", args.listen))?;
        eprintln!(
            "precimap serving on http://{} (job store {}, object store {})",
            listener.local_addr()?,
            args.backends.db,
            framework.objects.url()
        );
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        let executor = args.backends.executor(&framework);
        let in_process = executor.clone();
        let workers = args.workers;
        let mut background = tokio::spawn(async move {
            if workers > 0 {
                executor.work_loop(workers, stop_rx).await
            } else {
                // Still rescue expired leases of remote executors.
                let mut stop = stop_rx;
                while !*stop.borrow() {
                    if let Err(e) = executor.reconcile().await {
                        tracing::warn!(error = %e, "reconcile failed");
                    }
                    tokio::select! { _ = tokio::time::sleep(Duration::from_secs(5)) => {}, _ = stop.changed() => {} }
                }
                Ok(())
            }
        });
        let shutdown = shutdown_signal();
        precimap_api::serve(listener, precimap_api::app(state), connection_limits, shutdown).await?;
        let _ = stop_tx.send(true);
        tokio::select! {
            finished = &mut background => finished??,
            () = tokio::time::sleep(Duration::from_secs(args.shutdown_grace_s)) => {
                background.abort();
                let _ = background.await;
                hand_back(&in_process, workers).await?;
            }
        }
        Ok(())
    })
}

#[derive(Args, Debug)]
pub struct WorkArgs {
    #[command(flatten)]
    pub backends: Backends,
    /// Claim one task, run it and exit: 0 done, 3 no work, 4 the task failed, 5 the lease was lost.
    #[arg(long)]
    pub once: bool,
    /// Executor loops in this process. Their CPU work shares one pool of `--threads` threads
    /// (default: all cores); more loops than threads overlap downloads and uploads with it.
    #[arg(long, default_value_t = 1)]
    pub concurrency: usize,
    /// Exit after this many seconds without any runnable task (default: run until stopped).
    #[arg(long)]
    pub idle_exit_s: Option<u64>,
    /// On SIGTERM or SIGINT: claim nothing more and let running tasks finish for at most this
    /// many seconds, then hand the unfinished ones back to the queue and exit 0. Keep it below
    /// the platform's kill deadline (Kubernetes' terminationGracePeriodSeconds).
    #[arg(long, env = "PRECIMAP_SHUTDOWN_GRACE_S", default_value_t = 90)]
    pub shutdown_grace_s: u64,
    /// Serve this executor's metrics (`GET /metrics`, Prometheus text format) and a liveness
    /// probe (`GET /healthz`) on this address, e.g. 0.0.0.0:9184.
    #[arg(long, env = "PRECIMAP_METRICS_LISTEN")]
    pub metrics_listen: Option<String>,
}

/// Resolves on SIGINT (Ctrl-C) or SIGTERM (what Kubernetes, Docker and systemd send to stop).
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(e) => {
                tracing::warn!(error = %e, "cannot listen for SIGTERM; stopping on Ctrl-C only");
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// Resolves `grace` after `stop` turns true.
async fn grace_after(mut stop: tokio::sync::watch::Receiver<bool>, grace: Duration) {
    if stop.wait_for(|stopped| *stopped).await.is_err() {
        // The sender is gone without a stop: never.
        std::future::pending::<()>().await;
    }
    tokio::time::sleep(grace).await;
}

/// After a shutdown's grace has run out: hands the unfinished tasks back (their futures are
/// dropped by then) and says so.
async fn hand_back(executor: &Executor, concurrency: usize) -> Result<()> {
    let released = executor.release_held(concurrency).await.context("handing unfinished tasks back")?;
    eprintln!("stopping: {released} unfinished task(s) handed back to the queue");
    Ok(())
}

pub fn work(args: WorkArgs) -> Result<i32> {
    runtime()?.block_on(async move {
        let framework = args.backends.connect().await?;
        if let Some(address) = &args.metrics_listen {
            serve_executor_metrics(address, install_metrics()?).await?;
        }
        let executor = args.backends.executor(&framework);
        let grace = Duration::from_secs(args.shutdown_grace_s);
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        if args.once {
            executor.reconcile().await?;
            let signalled = async {
                shutdown_signal().await;
                tokio::time::sleep(grace).await;
            };
            let outcome = tokio::select! {
                outcome = executor.work_once() => outcome?,
                () = signalled => {
                    hand_back(&executor, 1).await?;
                    return Ok(0);
                }
            };
            eprintln!("{outcome:?}");
            return Ok(match outcome {
                WorkOutcome::Done { .. } => 0,
                WorkOutcome::NoWork => 3,
                WorkOutcome::Failed { .. } => 4,
                WorkOutcome::LeaseLost { .. } => 5,
            });
        }
        let idle_exit = args.idle_exit_s.map(Duration::from_secs);
        let jobs = framework.jobs.clone();
        tokio::spawn(async move {
            let mut idle_since = std::time::Instant::now();
            // One listener for the whole loop: a signal must not fall between two of them.
            let signal = shutdown_signal();
            tokio::pin!(signal);
            loop {
                tokio::select! {
                    () = &mut signal => {
                        eprintln!("stopping: no new tasks; running ones have {} s to finish", grace.as_secs());
                        break;
                    }
                    _ = tokio::time::sleep(Duration::from_millis(500)) => {}
                }
                if let Some(limit) = idle_exit {
                    let busy = match jobs.list_campaigns(100).await {
                        Ok(c) => c.iter().any(|c| c.state == precimap_jobs::CampaignState::Running),
                        Err(_) => true,
                    };
                    if busy {
                        idle_since = std::time::Instant::now();
                    } else if idle_since.elapsed() >= limit {
                        break;
                    }
                }
            }
            let _ = stop_tx.send(true);
        });
        tokio::select! {
            finished = executor.work_loop(args.concurrency, stop_rx.clone()) => finished?,
            () = grace_after(stop_rx, grace) => hand_back(&executor, args.concurrency).await?,
        }
        Ok(0)
    })
}

#[derive(Args, Debug)]
pub struct ClientArgs {
    /// The precimap server.
    #[arg(long, env = "PRECIMAP_SERVER", default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// Bearer token for writes.
    #[arg(long, env = "PRECIMAP_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
}

impl ClientArgs {
    fn client(&self) -> Client {
        Client::new(&self.server, self.token.clone())
    }
}

pub fn submit(manifest: &Path, args: &ClientArgs) -> Result<()> {
    let client = args.client();
    let submitted = runtime()?
        .block_on(client.submit_local(manifest, |uri, bytes| eprintln!("uploaded {uri} ({bytes} bytes)")))
        .with_context(|| format!("submitting {}", manifest.display()))?;
    eprintln!("submitted: {}{}", args.server.trim_end_matches('/'), submitted.href);
    outln!("{}", submitted.id);
    Ok(())
}

pub fn status(id: uuid::Uuid, watch: bool, json: bool, args: &ClientArgs) -> Result<i32> {
    let client = args.client();
    runtime()?.block_on(async {
        let mut printed = HashSet::new();
        loop {
            let s = client.status(id).await?;
            if json {
                outln!("{}", serde_json::to_string_pretty(&s)?);
            } else {
                for (i, it) in s.iterations.iter().enumerate() {
                    if printed.insert(i) {
                        outln!("iteration {:>2}: {it}", i + 1);
                    }
                }
                outln!(
                    "{} {}: {} stage {} (iteration {}/{}) — tasks: {} queued, {} running, {} done, {} dead{}",
                    s.campaign.id,
                    s.campaign.name,
                    s.campaign.state,
                    s.campaign.stage,
                    s.campaign.iteration,
                    s.campaign.iterations_planned,
                    s.tasks.queued,
                    s.tasks.leased,
                    s.tasks.done,
                    s.tasks.dead,
                    s.campaign.error.as_ref().map(|e| format!("\nerror: {e}")).unwrap_or_default()
                );
            }
            if !watch || s.campaign.state != "running" {
                return Ok(match s.campaign.state.as_str() {
                    "succeeded" | "running" => 0,
                    _ => 1,
                });
            }
            tokio::time::sleep(Duration::from_secs(2)).await;
        }
    })
}

pub fn results(id: uuid::Uuid, out: &Path, args: &ClientArgs) -> Result<()> {
    let client = args.client();
    let names = runtime()?.block_on(client.results(id, out))?;
    eprintln!("{} files written to {}", names.len(), out.display());
    Ok(())
}

pub fn cancel(id: uuid::Uuid, args: &ClientArgs) -> Result<()> {
    runtime()?.block_on(args.client().cancel(id))?;
    eprintln!("campaign {id} cancelled");
    Ok(())
}

pub fn delete(id: uuid::Uuid, args: &ClientArgs) -> Result<()> {
    runtime()?.block_on(args.client().delete(id))?;
    eprintln!("campaign {id} deleted");
    Ok(())
}
