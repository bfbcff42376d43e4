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
    #[command(flatten)]
    pub limits: LimitArgs,
}

pub fn serve(args: ServeArgs) -> Result<()> {
    let auth = match (&args.token, args.no_auth) {
        (Some(t), _) if !t.is_empty() => Auth::Token(t.clone()),
        (_, true) => Auth::Disabled,
        _ => {
            bail!("set PRECIMAP_TOKEN (or --token) so that only authorised clients can write; --no-auth disables this")
        }
    };
    runtime()?.block_on(async move {
        let framework = args.backends.connect().await?;
        let mut state = ApiState::new(framework.clone(), auth);
        state.max_upload_bytes = args.max_upload_bytes;
        state.limits = args.limits.limits();
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
        let workers = args.workers;
        let background = tokio::spawn(async move {
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
        axum::serve(listener, precimap_api::app(state))
            .with_graceful_shutdown(async {
                let _ = tokio::signal::ctrl_c().await;
            })
            .await?;
        let _ = stop_tx.send(true);
        background.await??;
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
}

pub fn work(args: WorkArgs) -> Result<i32> {
    runtime()?.block_on(async move {
        let framework = args.backends.connect().await?;
        let executor = args.backends.executor(&framework);
        if args.once {
            executor.reconcile().await?;
            let outcome = executor.work_once().await?;
            eprintln!("{outcome:?}");
            return Ok(match outcome {
                WorkOutcome::Done { .. } => 0,
                WorkOutcome::NoWork => 3,
                WorkOutcome::Failed { .. } => 4,
                WorkOutcome::LeaseLost { .. } => 5,
            });
        }
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        let idle_exit = args.idle_exit_s.map(Duration::from_secs);
        let jobs = framework.jobs.clone();
        tokio::spawn(async move {
            let mut idle_since = std::time::Instant::now();
            loop {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => break,
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
        executor.work_loop(args.concurrency, stop_rx).await?;
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
