//! The job framework end to end: the embedded default, the REST API over a real port with
//! in-process executors, separate `precimap work` processes on PostgreSQL + an S3 server
//! with executors killed at random and the database restarted — each must give exactly the
//! in-process driver's result — and a corrupt strip failing only its own campaign.

use precimap_api::{app, ApiState, Auth, Client};
use precimap_framework::{
    default_queue, run_embedded, upload_local_inputs, EmbeddedOptions, Executor, ExecutorConfig, Framework, Objects,
    TaskContext,
};
use precimap_jobs::{CampaignState, JobStore};
use precimap_pipeline::{run_campaign, RunOptions};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

fn simulate_tiny(dir: &Path, seed: u64) -> PathBuf {
    let campaign = dir.join(format!("campaign-{seed}"));
    let config = precimap_sim::SimConfig::for_scale(precimap_sim::Scale::Tiny, seed);
    precimap_sim::simulate(&config, &campaign, false).expect("simulate tiny");
    campaign
}

fn in_process(manifest: &Path, out: &Path) {
    run_campaign(manifest, &RunOptions { out_dir: out.to_path_buf(), keep_work: false, assignments: false }, &|_| {})
        .unwrap();
}

/// Runs `manifest` through the embedded framework (SQLite, a local store, two executors), as
/// `precimap run` does, into `out`, and checks that the campaign succeeded.
pub(crate) fn run_embedded_into(manifest: &Path, out: &Path) {
    let options = EmbeddedOptions { out_dir: out.to_path_buf(), concurrency: 2, keep_state: false };
    let rt = tokio::runtime::Runtime::new().unwrap();
    let record = rt.block_on(run_embedded(manifest, &options, |_| {})).unwrap();
    assert_eq!(record.state, CampaignState::Succeeded);
}

/// Every corrected strip and trajectory byte-identical (LAS stores coordinates as integers of
/// 0.1 mm or finer and the CSV writes round-trip floats, so this is equality of the corrections
/// far below 1e-9 m), and the same iteration statistics.
pub(crate) fn assert_same_results(a: &Path, b: &Path) {
    for folder in ["strips", "trajectories", "corrections", "segments", "qc", "latent"] {
        let mut names: Vec<_> = std::fs::read_dir(a.join(folder)).unwrap().map(|e| e.unwrap().file_name()).collect();
        names.sort();
        assert!(!names.is_empty());
        for name in names {
            let x = std::fs::read(a.join(folder).join(&name)).unwrap();
            let y = std::fs::read(b.join(folder).join(&name))
                .unwrap_or_else(|e| panic!("{}: {e}", b.join(folder).join(&name).display()));
            assert!(x == y, "{folder}/{} differs", name.to_string_lossy());
        }
    }
    let ra: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("report.json")).unwrap()).unwrap();
    let rb: serde_json::Value = serde_json::from_slice(&std::fs::read(b.join("report.json")).unwrap()).unwrap();
    assert_eq!(ra["iterations"].as_array().unwrap().len(), rb["iterations"].as_array().unwrap().len());
    for (x, y) in ra["iterations"].as_array().unwrap().iter().zip(rb["iterations"].as_array().unwrap()) {
        for field in [
            "points_used",
            "points_modelled",
            "residual_std_m",
            "max_correction_change_m",
            "max_correction_change_at",
            "common_mode_field_max_m",
            "common_mode_heading_max_deg",
            "common_mode_tilt_max_deg",
            "campaign_rotation_deg",
            "anderson_coefficients",
        ] {
            assert_eq!(x[field], y[field], "{field}");
        }
        // Both drivers say where the largest change is.
        assert!(x["max_correction_change_at"]["trajectory"].is_string(), "{x}");
    }
    // The fine steps solved the common-mode field (its own stage in the framework).
    assert!(ra["iterations"].as_array().unwrap().iter().any(|i| i["common_mode_field_max_m"].as_f64().unwrap() > 0.0));
    // With its heading (the default).
    assert!(ra["iterations"]
        .as_array()
        .unwrap()
        .iter()
        .any(|i| i["common_mode_heading_max_deg"].as_f64().unwrap() > 0.0));
    assert_eq!(ra["converged"], rb["converged"]);
    assert_eq!(ra["points_total"], rb["points_total"]);
    assert_eq!(ra["trajectories"], rb["trajectories"]);
}

/// The report's phases and iterations are wall-clock seconds on both paths (disjoint spans within
/// the run), and the framework adds its summed task seconds.
fn assert_wall_clock_timings(out: &Path, framework: bool) {
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let t = &report["timings"];
    let [prepare, estimate, export, total] =
        ["prepare_s", "estimate_s", "export_s", "total_s"].map(|k| t[k].as_f64().unwrap_or_else(|| panic!("{k}: {t}")));
    assert!(prepare > 0.0 && estimate > 0.0 && export > 0.0, "{t}");
    // Millisecond clocks: allow a few milliseconds per phase boundary.
    assert!(prepare + estimate + export <= total + 0.05, "phases longer than the run: {t}");
    let iterations: f64 = report["iterations"].as_array().unwrap().iter().map(|i| i["seconds"].as_f64().unwrap()).sum();
    assert!((iterations - estimate).abs() < 0.05 + 1e-6 * estimate, "iterations {iterations} s, estimate {t}");
    match t.get("task_s").and_then(serde_json::Value::as_f64) {
        Some(task_s) => assert!(framework && task_s > 0.0, "{t}"),
        None => assert!(!framework, "the framework reports its task seconds: {t}"),
    }
}

async fn wait_finished(jobs: &JobStore, id: uuid::Uuid, limit: Duration) -> precimap_jobs::CampaignRecord {
    let started = Instant::now();
    loop {
        let c = jobs.campaign(id).await.unwrap().unwrap();
        if c.state != CampaignState::Running {
            return c;
        }
        assert!(
            started.elapsed() < limit,
            "campaign {id} still {} after {limit:?} (stage {})",
            c.state.as_str(),
            c.stage
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Two tiny campaigns in `dir`: seed 5 as simulated, and seed 6 with strip v02-right cut to a
/// third of its bytes (its prepare task fails with a message naming the strip).
fn good_and_corrupt_campaigns(dir: &Path) -> (PathBuf, PathBuf) {
    let good = simulate_tiny(dir, 5);
    let bad = simulate_tiny(dir, 6);
    let las = bad.join("strips/v02-right.las");
    let bytes = std::fs::read(&las).unwrap();
    std::fs::write(&las, &bytes[..bytes.len() / 3]).unwrap();
    (good, bad)
}

/// The embedded backends in `dir`: SQLite `jobs.db` and a file store `store/`.
async fn local_framework(dir: &Path) -> (JobStore, Objects, Framework) {
    let jobs = JobStore::connect(&format!("sqlite://{}", dir.join("jobs.db").display())).await.unwrap();
    let objects = Objects::from_url(&format!("file://{}", dir.join("store").display())).unwrap();
    let framework = Framework { jobs: jobs.clone(), objects: objects.clone(), queue: default_queue() };
    (jobs, objects, framework)
}

/// The API over `framework` on a free loopback port (writers need the token `t0ken`).
async fn serve_api(framework: &Framework) -> std::net::SocketAddr {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap();
    let state = ApiState::new(framework.clone(), Auth::Token("t0ken".into()));
    tokio::spawn(async move { axum::serve(listener, app(state)).await.unwrap() });
    address
}

/// Submits the corrupt campaign's manifest `bad`, then `good`, works the queue until both have
/// finished, and checks that the first failed and the second succeeded; returns their ids.
async fn submit_failing_and_succeeding(
    framework: &Framework,
    scratch: &Path,
    bad: &precimap_formats::Manifest,
    good: &precimap_formats::Manifest,
) -> ((uuid::Uuid, precimap_jobs::CampaignRecord), (uuid::Uuid, precimap_jobs::CampaignRecord)) {
    let bad_id = framework.submit(bad).await.unwrap();
    let good_id = framework.submit(good).await.unwrap();
    let workers = LocalExecutors::start(&framework.jobs, &framework.objects, scratch);
    let failed = wait_finished(&framework.jobs, bad_id, Duration::from_secs(600)).await;
    let succeeded = wait_finished(&framework.jobs, good_id, Duration::from_secs(600)).await;
    workers.stop().await;
    assert_eq!(failed.state, CampaignState::Failed);
    assert_eq!(succeeded.state, CampaignState::Succeeded, "{:?}", succeeded.error);
    ((bad_id, failed), (good_id, succeeded))
}

/// Executors in this process (two tasks at a time) working the store's queue until stopped.
struct LocalExecutors {
    stop: tokio::sync::watch::Sender<bool>,
    handle: tokio::task::JoinHandle<Result<(), precimap_framework::FrameworkError>>,
}

impl LocalExecutors {
    fn start(jobs: &JobStore, objects: &Objects, scratch: &Path) -> Self {
        let executor = Executor::new(
            jobs.clone(),
            TaskContext::new(objects.clone(), scratch.to_path_buf()),
            ExecutorConfig::default(),
        );
        let (stop, stop_rx) = tokio::sync::watch::channel(false);
        let handle = tokio::spawn(async move { executor.work_loop(2, stop_rx).await });
        Self { stop, handle }
    }

    async fn stop(self) {
        let _ = self.stop.send(true);
        self.handle.await.unwrap().unwrap();
    }
}

#[test]
fn embedded_run_and_the_http_api_give_the_in_process_result() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = simulate_tiny(dir.path(), 3);
    let manifest = campaign.join("manifest.json");
    let reference = dir.path().join("in-process");
    in_process(&manifest, &reference);

    let rt = tokio::runtime::Runtime::new().unwrap();
    // 1. The embedded default (what `precimap run` does).
    let embedded = dir.path().join("embedded");
    let options = EmbeddedOptions { out_dir: embedded.clone(), concurrency: 3, keep_state: false };
    let record = rt.block_on(run_embedded(&manifest, &options, |_| {})).unwrap();
    assert_eq!(record.state, CampaignState::Succeeded);
    assert!(!embedded.join(".precimap").exists(), "the state folder is removed after the run");
    assert_same_results(&reference, &embedded);
    assert_wall_clock_timings(&embedded, true);
    assert_wall_clock_timings(&reference, false);

    // 2. Over a real port: `submit`, `status`, `results` through the HTTP client.
    let via_http = dir.path().join("via-http");
    rt.block_on(async {
        let (jobs, objects, framework) = local_framework(dir.path()).await;
        let address = serve_api(&framework).await;
        let workers = LocalExecutors::start(&jobs, &objects, &dir.path().join("scratch"));

        let server = format!("http://{address}");
        let unauthorised = Client::new(&server, None);
        let err = unauthorised.submit_local(&manifest, |_, _| {}).await.unwrap_err().to_string();
        assert!(err.contains("401"), "{err}");
        let client = Client::new(&server, Some("t0ken".into()));
        let submitted = client.submit_local(&manifest, |_, _| {}).await.unwrap();
        let finished = wait_finished(&jobs, submitted.id, Duration::from_secs(600)).await;
        assert_eq!(finished.state, CampaignState::Succeeded, "{:?}", finished.error);
        let status = client.status(submitted.id).await.unwrap();
        assert_eq!(status.campaign.state, "succeeded");
        assert!(!status.iterations.is_empty());
        assert_eq!(status.tasks.dead, 0);
        client.results(submitted.id, &via_http).await.unwrap();
        // The QC plots are served as SVG that a browser shows in place and that runs nothing.
        let path = format!("/v1/campaigns/{}/results/qc/convergence.svg", submitted.id);
        let answer = tokio::task::spawn_blocking(move || http_get(address.port(), &path)).await.unwrap();
        let answer = answer.expect("the server answers");
        let head = answer.split("\r\n\r\n").next().unwrap_or_default();
        assert!(head.starts_with("HTTP/1.0 200") || head.starts_with("HTTP/1.1 200"), "{head}");
        let head = head.to_ascii_lowercase();
        assert!(head.contains("content-type: image/svg+xml"), "{head}");
        assert!(head.contains("content-security-policy: default-src 'none'; img-src data:; sandbox"), "{head}");
        assert!(head.contains("x-content-type-options: nosniff"), "{head}");

        // The anchors' positions were read from the trajectory files once, by the first field
        // task; every later field task read the object it wrote.
        let recorded = jobs.recorded_keys(submitted.id).await.unwrap();
        let positions = recorded.iter().filter(|k| k.contains("/anchors/positions.")).count();
        let field_tasks =
            status.iterations.iter().filter(|i| i["common_mode_field_max_m"].as_f64() > Some(0.0)).count();
        assert!(field_tasks > 1, "{field_tasks} iterations solved the field");
        assert_eq!(positions, 1, "one anchor positions object");
        // Only the results stay in the store once the campaign has succeeded: the executor that
        // finished it removes the work files right after its commit.
        let mut kept: Vec<String> =
            framework.results(submitted.id).await.unwrap().into_iter().map(|(_, k)| k).collect();
        kept.sort();
        kept.dedup();
        let waited = Instant::now();
        loop {
            let mut stored = objects.list(&finished.object_prefix).await.unwrap();
            stored.sort();
            if stored == kept {
                break;
            }
            assert!(
                waited.elapsed() < Duration::from_secs(60),
                "{} objects stored, {} results",
                stored.len(),
                kept.len()
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }

        // Deleting the campaign removes its objects.
        let prefix = finished.object_prefix.clone();
        assert!(!objects.list(&prefix).await.unwrap().is_empty());
        client.delete(submitted.id).await.unwrap();
        assert!(objects.list(&prefix).await.unwrap().is_empty());
        assert!(client.status(submitted.id).await.is_err());
        workers.stop().await;
    });
    assert_same_results(&reference, &via_http);
}

/// Runs the tiny campaign with `parameters` in-process and through the embedded framework:
/// both give the same results, and they differ from the default run's (the option does
/// something). Returns the in-process output folder.
fn option_gives_the_in_process_result_through_the_framework(dir: &Path, parameters: serde_json::Value) -> PathBuf {
    let campaign = simulate_tiny(dir, 3);
    let mut manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(campaign.join("manifest.json")).unwrap()).unwrap();
    manifest["parameters"] = parameters;
    let option = campaign.join("manifest-option.json");
    std::fs::write(&option, serde_json::to_vec_pretty(&manifest).unwrap()).unwrap();

    let reference = dir.join("in-process");
    in_process(&option, &reference);
    let embedded = dir.join("embedded");
    run_embedded_into(&option, &embedded);
    assert_same_results(&reference, &embedded);

    let default = dir.join("default");
    in_process(&campaign.join("manifest.json"), &default);
    let name = std::fs::read_dir(default.join("trajectories")).unwrap().next().unwrap().unwrap().file_name();
    let with_option = std::fs::read(reference.join("trajectories").join(&name)).unwrap();
    let without = std::fs::read(default.join("trajectories").join(&name)).unwrap();
    assert_ne!(with_option, without, "the option changed nothing");
    reference
}

/// `field_free_momentum` (an option, off by default) takes the same path in the framework's
/// field task as in the in-process driver, and it does change the result.
#[test]
fn field_free_momentum_gives_the_in_process_result_through_the_framework() {
    let dir = tempfile::tempdir().unwrap();
    option_gives_the_in_process_result_through_the_framework(
        dir.path(),
        serde_json::json!({ "field_free_momentum": true }),
    );
}

/// The field's tilt (`common_mode_tilt`, off by default; field objects version 3) gives the
/// in-process result through the framework, with the momentum's field share removed by the same
/// six-unknown fit in both drivers, and both report the tilt the field solved.
#[test]
fn common_mode_tilt_gives_the_in_process_result_through_the_framework() {
    let dir = tempfile::tempdir().unwrap();
    let reference = option_gives_the_in_process_result_through_the_framework(
        dir.path(),
        serde_json::json!({ "common_mode_tilt": true, "field_free_momentum": true }),
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(reference.join("report.json")).unwrap()).unwrap();
    let iterations = report["iterations"].as_array().unwrap();
    assert!(iterations.iter().any(|i| i["common_mode_tilt_max_deg"].as_f64().unwrap() > 0.0), "{report}");
}

/// A history depth other than the default's 5 gives the framework's `accelerate` stage the
/// in-process result, and it does change the result (every other framework test runs the
/// default's depth).
#[test]
fn anderson_acceleration_gives_the_in_process_result_through_the_framework() {
    let dir = tempfile::tempdir().unwrap();
    let reference = option_gives_the_in_process_result_through_the_framework(
        dir.path(),
        serde_json::json!({ "anderson_depth": 3 }),
    );
    // The report names the combinations: only settling iterations after the first one start
    // from one, each with at most anderson_depth coefficients.
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(reference.join("report.json")).unwrap()).unwrap();
    let accelerated: Vec<usize> = report["iterations"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|i| Some((i["iteration"].as_u64()? as usize, i["anderson_coefficients"].as_array()?.len())))
        .inspect(|&(_, k)| assert!((1..=3).contains(&k), "{k} coefficients"))
        .map(|(i, _)| i)
        .collect();
    assert!(!accelerated.is_empty(), "no iteration started from a combination");
    // The default schedule settles from iteration 13: the first combination starts 15.
    assert!(accelerated.iter().all(|&i| i >= 15), "only after two settling iterations: {accelerated:?}");
}

#[test]
fn a_corrupt_strip_fails_its_campaign_and_not_the_one_beside_it() {
    let dir = tempfile::tempdir().unwrap();
    let (good, bad) = good_and_corrupt_campaigns(dir.path());

    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let (jobs, objects, framework) = local_framework(dir.path()).await;
        let good_manifest = upload_local_inputs(&objects, &good.join("manifest.json")).await.unwrap();
        let bad_manifest = upload_local_inputs(&objects, &bad.join("manifest.json")).await.unwrap();
        let ((bad_id, failed), (good_id, _)) =
            submit_failing_and_succeeding(&framework, &dir.path().join("scratch"), &bad_manifest, &good_manifest).await;
        let error = failed.error.unwrap();
        assert!(error.contains("v02-right"), "the error names the strip: {error}");
        // The failed campaign stops: nothing of it stays queued or leased.
        let counts = jobs.task_counts(bad_id).await.unwrap();
        assert_eq!(counts.queued + counts.leased, 0, "{counts:?}");

        // Objects of lost attempts that land after the finishing executor's clean-up (an attempt
        // cancelled with the failed campaign still writing; a clean-up cut short) are swept by the
        // next reconcile once a lease has passed, and each campaign is marked swept.
        let mut planted = Vec::new();
        for id in [bad_id, good_id] {
            let prefix = jobs.campaign(id).await.unwrap().unwrap().object_prefix;
            let key = format!("{}/it/1/blocks/late.0123456789ab.blk", prefix.trim_end_matches('/'));
            objects.put(&key, b"lost attempt".to_vec().into()).await.unwrap();
            planted.push(key);
        }
        let sweeper = Executor::new(
            jobs.clone(),
            TaskContext::new(objects.clone(), dir.path().join("scratch")),
            ExecutorConfig { lease: Duration::from_millis(20), ..ExecutorConfig::default() },
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
        sweeper.reconcile().await.unwrap();
        for (id, key) in [bad_id, good_id].into_iter().zip(&planted) {
            assert!(!objects.exists(key).await.unwrap(), "{key} swept");
            let (stored, _) = stored_and_recorded(&jobs, &objects, id).await;
            // A failed campaign keeps nothing, a succeeded one its results (work files go).
            let mut kept: Vec<String> = if id == bad_id {
                Vec::new()
            } else {
                framework.results(id).await.unwrap().into_iter().map(|(_, k)| k).collect()
            };
            kept.sort();
            kept.dedup();
            assert_eq!(stored, kept, "only the results remain");
        }
        assert_eq!(jobs.claim_sweep(Duration::ZERO, Duration::ZERO).await.unwrap(), None, "both marked swept");
    });
}

/// The objects under a campaign's prefix and the object keys its tasks recorded, both sorted.
async fn stored_and_recorded(jobs: &JobStore, objects: &Objects, id: uuid::Uuid) -> (Vec<String>, Vec<String>) {
    let campaign = jobs.campaign(id).await.unwrap().unwrap();
    let mut stored = objects.list(&campaign.object_prefix).await.unwrap();
    stored.sort();
    (stored, jobs.recorded_keys(id).await.unwrap())
}

/// PostgreSQL and the S3 server, as `scripts/services.sh` provides them. The test command always
/// sets `PRECIMAP_REQUIRE_SERVICES=1`, so a missing service fails the run instead of skipping.
fn services() -> Option<(String, String)> {
    match (std::env::var("PRECIMAP_TEST_POSTGRES"), std::env::var("PRECIMAP_TEST_S3")) {
        (Ok(pg), Ok(s3)) => Some((pg, s3)),
        _ => {
            assert!(
                std::env::var("PRECIMAP_REQUIRE_SERVICES").as_deref() != Ok("1"),
                "PRECIMAP_TEST_POSTGRES and PRECIMAP_TEST_S3 are required (run ./scripts/test.sh)"
            );
            eprintln!("SKIPPED: PostgreSQL/S3 not configured; ./scripts/test.sh starts them");
            None
        }
    }
}

fn psql(url: &str, sql: &str) -> String {
    let out = std::process::Command::new("psql").args([url, "-tA", "-c", sql]).output().expect("psql");
    assert!(out.status.success(), "psql {sql}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

fn restart_postgres() {
    let version = std::fs::read_dir("/etc/postgresql").unwrap().next().unwrap().unwrap().file_name();
    let status = std::process::Command::new("pg_ctlcluster")
        .args(["--skip-systemctl-redirect", &version.to_string_lossy(), "main", "restart"])
        .status()
        .expect("pg_ctlcluster");
    assert!(status.success());
}

/// A child process killed when the test ends, even by a panic (a leftover server would hold the
/// test's output pipe open).
struct Worker {
    child: std::process::Child,
}

impl Worker {
    /// Waits until the child answers `GET /healthz` on `port` (at most 30 s); panics with
    /// `log()` if it exits or does not answer.
    fn wait_until_serving(&mut self, port: u16, log: impl Fn() -> String) {
        let started = Instant::now();
        while !serves_health(port) {
            if let Some(status) = self.child.try_wait().unwrap() {
                panic!("precimap serve exited ({status}): {}", log());
            }
            assert!(started.elapsed() < Duration::from_secs(30), "precimap serve does not answer: {}", log());
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// A port no one listens on now.
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

impl Drop for Worker {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A `precimap work` process in a working directory of its own under `dir`: executors share
/// nothing but the job store and the object store.
fn spawn_worker(dir: &Path, db: &str, store: &str) -> Worker {
    let workdir = dir.join(format!("executor-{}", uuid::Uuid::new_v4().simple()));
    std::fs::create_dir_all(&workdir).unwrap();
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_precimap"))
        .args(["work", "--db", db, "--store", store, "--lease-s", "3", "--concurrency", "1"])
        .current_dir(&workdir)
        .env("PRECIMAP_LOG", "warn")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("spawn precimap work");
    Worker { child }
}

#[test]
fn separate_workers_on_postgres_and_s3_survive_kills_and_a_database_restart() {
    let Some((pg, s3)) = services() else { return };
    let dir = tempfile::tempdir().unwrap();
    let campaign = simulate_tiny(dir.path(), 4);
    let manifest = campaign.join("manifest.json");
    let reference = dir.path().join("in-process");
    in_process(&manifest, &reference);

    let database = format!("precimap_chaos_{}", uuid::Uuid::new_v4().simple());
    psql(&pg, &format!("CREATE DATABASE {database}"));
    let db = format!("{}/{database}", pg.rsplit_once('/').unwrap().0);
    let store = format!("{s3}/{}", uuid::Uuid::new_v4().simple());

    // `precimap serve` on a free port, without in-process executors.
    let port = free_port();
    let server_url = format!("http://127.0.0.1:{port}");
    let server = std::process::Command::new(env!("CARGO_BIN_EXE_precimap"))
        .args(["serve", "--db", &db, "--store", &store, "--listen", &format!("127.0.0.1:{port}"), "--lease-s", "3"])
        .env("PRECIMAP_TOKEN", "chaos-token")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("spawn precimap serve");
    let mut server = Worker { child: server };
    server.wait_until_serving(port, String::new);
    let rt = tokio::runtime::Runtime::new().unwrap();
    let client = Client::new(&server_url, Some("chaos-token".into()));
    let id = rt.block_on(async { client.submit_local(&manifest, |_, _| {}).await.unwrap().id });

    let mut workers: Vec<Worker> = (0..4).map(|_| spawn_worker(dir.path(), &db, &store)).collect();
    let started = Instant::now();
    let mut kills = 0;
    let mut restarted = false;
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let status = loop {
        std::thread::sleep(Duration::from_millis(700));
        let s = rt.block_on(client.status(id));
        let s = match s {
            Ok(s) => s,
            Err(_) => continue, // the database is restarting
        };
        if s.campaign.state != "running" {
            break s;
        }
        assert!(started.elapsed() < Duration::from_secs(900), "campaign stuck: {s:?}");
        // SIGKILL a random executor every few polls while tasks run, and restart it.
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        if s.tasks.leased > 0 && rng.is_multiple_of(3) && kills < 12 {
            let victim = (rng >> 8) as usize % workers.len();
            workers[victim].child.kill().unwrap();
            workers[victim].child.wait().unwrap();
            workers[victim] = spawn_worker(dir.path(), &db, &store);
            kills += 1;
        }
        if !restarted && s.campaign.iteration >= 2 {
            restart_postgres();
            restarted = true;
        }
    };
    // The executor that finished the campaign removes the killed attempts' objects and the work
    // files right after its commit, and any executor's reconcile sweeps again a lease later (the
    // first clean-up may be cut short). The campaign is reported finished before either is done,
    // so the executors run until the store holds the results alone (or a minute passes).
    let leftovers = || {
        rt.block_on(async {
            let jobs = JobStore::connect(&db).await.unwrap();
            let (stored, _) = stored_and_recorded(&jobs, &Objects::from_url(&store).unwrap(), id).await;
            let results = precimap_framework::lifecycle::result_keys(&jobs, id).await.unwrap();
            jobs.close().await;
            let results: HashSet<String> = results.into_iter().map(|(_, key)| key).collect();
            stored.iter().filter(|k| !results.contains(*k)).count()
        })
    };
    let waited = Instant::now();
    while leftovers() > 0 && waited.elapsed() < Duration::from_secs(60) {
        std::thread::sleep(Duration::from_millis(200));
    }
    drop(workers);
    eprintln!(
        "chaos: {kills} executors killed, database restarted: {restarted}, {:.0} s",
        started.elapsed().as_secs_f64()
    );
    assert_eq!(status.campaign.state, "succeeded", "{:?}", status.campaign.error);
    assert!(restarted && kills >= 2, "{kills} executors killed");
    let out = dir.path().join("results");
    rt.block_on(client.results(id, &out)).unwrap();
    assert_same_results(&reference, &out);
    // No task committed outputs twice, nothing stays leased.
    assert_eq!(psql(&db, "SELECT count(*) FROM tasks WHERE state = 'leased'"), "0");
    assert_eq!(
        psql(&db, "SELECT count(*) FROM (SELECT task_id, name FROM task_outputs GROUP BY 1, 2 HAVING count(*) > 1) d"),
        "0"
    );
    // The objects of killed attempts were cleaned up when the campaign finished: every object
    // left under the campaign's prefix is a recorded output, and a result (work files go).
    rt.block_on(async {
        let jobs = JobStore::connect(&db).await.unwrap();
        let (stored, recorded) = stored_and_recorded(&jobs, &Objects::from_url(&store).unwrap(), id).await;
        let orphans: Vec<_> = stored.iter().filter(|k| recorded.binary_search(k).is_err()).collect();
        assert!(orphans.is_empty(), "{} orphaned objects, e.g. {:?}", orphans.len(), orphans.first());
        let mut results: Vec<String> =
            precimap_framework::lifecycle::result_keys(&jobs, id).await.unwrap().into_iter().map(|(_, k)| k).collect();
        results.sort();
        results.dedup();
        assert_eq!(stored, results);
        jobs.close().await;
    });
    let _ = psql(&pg, &format!("DROP DATABASE IF EXISTS {database} WITH (FORCE)"));
}

/// Whether `precimap serve` answers `GET /healthz` on `port` with 200. A bare connect is not
/// enough: on loopback, a connect to a free ephemeral port can pick that port as its own source
/// and connect to itself.
fn serves_health(port: u16) -> bool {
    http_get(port, "/healthz").is_some_and(|answer| answer.starts_with("HTTP/1.") && answer.contains(" 200 "))
}

/// The whole answer (status line, headers, body) to `GET path` on 127.0.0.1:`port`, over
/// HTTP/1.0 so that the server closes the connection after the body; `None` if it cannot be read
/// within 5 s.
fn http_get(port: u16, path: &str) -> Option<String> {
    use std::io::{Read as _, Write as _};
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    stream.write_all(format!("GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n").as_bytes()).ok()?;
    let mut answer = String::new();
    stream.read_to_string(&mut answer).ok()?;
    Some(answer)
}

/// glibc keeps freed memory in every malloc arena it opens (up to eight per core) and trims the
/// heap between tasks: the binary executes itself again with one arena per core and fixed mmap
/// and trim thresholds (`evaluate`: a low mmap threshold alone), keeping a threshold the user set.
/// An arena limit the user set means no restart: every setting is theirs. Read off a running
/// `precimap serve`'s environment once it answers.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[test]
fn the_binary_tunes_glibc_malloc_unless_told_otherwise() {
    const VARIABLES: [&str; 3] = ["MALLOC_ARENA_MAX", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"];
    let dir = tempfile::tempdir().unwrap();
    let cores = std::thread::available_parallelism().unwrap().get().to_string();
    let never_trim = (usize::MAX / 2).to_string();
    // Per variable, its value in the server's environment (`None`: absent).
    let defaults = [Some(cores.as_str()), Some("33554432"), Some(never_trim.as_str())];
    let user_arenas = [Some("3"), None, None];
    let user_trim = [Some(cores.as_str()), Some("33554432"), Some("1048576")];
    for (preset, expected) in [
        (None, defaults),
        (Some(("MALLOC_ARENA_MAX", "3")), user_arenas),
        (Some(("MALLOC_TRIM_THRESHOLD_", "1048576")), user_trim),
    ] {
        let port = free_port();
        let log_path = dir.path().join(format!("serve-{port}.log"));
        let log = || std::fs::read_to_string(&log_path).unwrap_or_default();
        let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_precimap"));
        command
            .args(["serve", "--no-auth", "--listen", &format!("127.0.0.1:{port}"), "--db"])
            .arg(format!("sqlite://{}/jobs-{port}.db", dir.path().display()))
            .arg("--store")
            .arg(format!("file://{}", dir.path().join("store").display()))
            .stdout(std::process::Stdio::null())
            .stderr(std::fs::File::create(&log_path).unwrap());
        for variable in VARIABLES {
            command.env_remove(variable);
        }
        if let Some((variable, value)) = preset {
            command.env(variable, value);
        }
        let mut server = Worker { child: command.spawn().unwrap() };
        server.wait_until_serving(port, log);
        let environ = std::fs::read(format!("/proc/{}/environ", server.child.id())).unwrap();
        drop(server);
        let entries: Vec<&str> = environ.split(|&b| b == 0).filter_map(|v| std::str::from_utf8(v).ok()).collect();
        for (variable, expected) in VARIABLES.into_iter().zip(expected) {
            let values: Vec<&str> =
                entries.iter().filter_map(|e| e.strip_prefix(variable)?.strip_prefix('=')).collect();
            let expected: Vec<&str> = expected.into_iter().collect();
            assert_eq!(values, expected, "{variable}, preset {preset:?}; precimap serve said: {}", log());
        }
    }
}

/// A program the browser tests need: `$env`, else the first of `candidates` that exists; `None`
/// (the test is skipped) outside `./scripts/test.sh`, which installs Debian's `package`.
fn browser_test_program(env: &str, candidates: &[&str], package: &str) -> Option<PathBuf> {
    let path =
        std::env::var_os(env).map(PathBuf::from).or_else(|| candidates.iter().map(PathBuf::from).find(|p| p.exists()));
    if path.is_none() {
        assert!(
            std::env::var("PRECIMAP_REQUIRE_SERVICES").as_deref() != Ok("1"),
            "{package} is required for the dashboard tests (run ./scripts/test.sh, which installs it)"
        );
        eprintln!("SKIPPED: no {package}; ./scripts/test.sh installs Debian's {package}");
    }
    path
}

/// Headless Chromium (`PRECIMAP_TEST_CHROMIUM`), required when the test command sets
/// `PRECIMAP_REQUIRE_SERVICES=1`, like the other services.
fn chromium() -> Option<PathBuf> {
    browser_test_program("PRECIMAP_TEST_CHROMIUM", &["/usr/bin/chromium", "/usr/bin/chromium-browser"], "chromium")
}

/// chromedriver, for the tests that click.
fn chromedriver() -> Option<PathBuf> {
    browser_test_program("PRECIMAP_TEST_CHROMEDRIVER", &["/usr/bin/chromedriver"], "chromium-driver")
}

/// The DOM of `url` after its scripts ran for `budget_ms` of virtual time (which waits for
/// pending fetches), as headless Chromium serialises it.
fn rendered_dom(chromium: &Path, url: &str, profile: &Path, budget_ms: u32) -> String {
    let mut child = std::process::Command::new(chromium)
        .args([
            "--headless",
            "--no-sandbox", // the test runs as root in CI
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--no-first-run",
            "--window-size=1280,2400",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("--virtual-time-budget={budget_ms}"))
        .args(["--dump-dom", url])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("start chromium");
    // Read stdout on a thread so that a large DOM cannot fill the pipe while we wait.
    let mut stdout = child.stdout.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut dom = String::new();
        std::io::Read::read_to_string(&mut stdout, &mut dom).map(|_| dom)
    });
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            panic!("chromium did not finish rendering {url} within 120 s");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let dom = reader.join().unwrap().unwrap();
    let mut errors = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut errors).unwrap();
    assert!(dom.contains("</html>"), "chromium rendered nothing for {url}: {errors}");
    dom
}

/// The part of `dom` from the element with `id` to the end of its first `closing` tag.
fn element<'a>(dom: &'a str, id: &str, closing: &str) -> &'a str {
    let start = dom.find(&format!("id=\"{id}\"")).unwrap_or_else(|| panic!("no #{id} in the page"));
    let end = dom[start..].find(closing).map_or(dom.len(), |e| start + e + closing.len());
    &dom[start..end]
}

/// The status dashboard in a real browser over a real port: the campaign list with a succeeded,
/// a failed and a cancelled campaign, one campaign's iterations, convergence chart, QC plots
/// (which must load as images despite their sandboxing policy) and events, and a campaign name
/// that looks like markup shown as text.
#[test]
fn the_dashboard_shows_campaigns_in_headless_chromium() {
    let Some(chromium) = chromium() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (good, bad) = good_and_corrupt_campaigns(dir.path());
    const MARKUP_NAME: &str = "town <img src=x onerror=alert(1)> & co";

    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let (jobs, objects, framework) = local_framework(dir.path()).await;
        let address = serve_api(&framework).await;

        let mut good_manifest = upload_local_inputs(&objects, &good.join("manifest.json")).await.unwrap();
        good_manifest.name = MARKUP_NAME.into();
        // Anderson acceleration is on by default: the iterations that started from a combination
        // show.
        assert!(good_manifest.parameters.anderson_depth > 0);
        let bad_manifest = upload_local_inputs(&objects, &bad.join("manifest.json")).await.unwrap();
        let cancelled_id = framework.submit(&bad_manifest).await.unwrap();
        assert!(jobs.cancel_campaign(cancelled_id).await.unwrap());
        let ((bad_id, _), (good_id, _)) =
            submit_failing_and_succeeding(&framework, &dir.path().join("scratch"), &bad_manifest, &good_manifest).await;
        let recorded = jobs.iterations(good_id).await.unwrap();
        let iterations = recorded.len();
        let accelerated = recorded
            .iter()
            .filter(|i| i.stats["anderson_coefficients"].as_array().is_some_and(|c| !c.is_empty()))
            .count();
        assert!(accelerated >= 2, "{accelerated} iterations started from Anderson's combination");
        let results = framework.results(good_id).await.unwrap();
        let in_folder = |folder: &str| results.iter().filter(|(n, _)| n.starts_with(&format!("{folder}/"))).count();
        let (qc_plots, latent_tiles) = (in_folder("qc"), in_folder("latent"));
        assert!(iterations > 1 && qc_plots >= 3, "{iterations} iterations, {qc_plots} plots");
        assert!(latent_tiles > 10, "{latent_tiles} latent-map tiles");

        let server = format!("http://{address}");
        let (chromium, profile) = (chromium.clone(), dir.path().join("chromium"));
        let (succeeded_page, failed_page) = tokio::task::spawn_blocking(move || {
            (
                rendered_dom(&chromium, &format!("{server}/#{good_id}"), &profile, 20_000),
                rendered_dom(&chromium, &format!("{server}/#{bad_id}"), &profile, 10_000),
            )
        })
        .await
        .unwrap();

        // The list: all three campaigns with their states; the markup name is text.
        let dom = &succeeded_page;
        assert!(dom.contains("data-list-ready=\"1\""), "the list never rendered:\n{dom}");
        assert!(dom.contains(&format!("data-detail-ready=\"{good_id}\"")), "the campaign never rendered:\n{dom}");
        let list = element(dom, "campaigns", "</table>");
        for (id, state) in [(good_id, "succeeded"), (bad_id, "failed"), (cancelled_id, "cancelled")] {
            let row = element(list, &id.to_string(), "</tr>");
            assert!(row.contains(&format!("<span class=\"state {state}\">{state}</span>")), "{state}: {row}");
        }
        assert!(dom.contains("town &lt;img src=x onerror=alert(1)&gt; &amp; co"), "the name as text:\n{list}");
        assert!(!dom.contains("onerror=\"alert(1)\""), "the name became markup:\n{dom}");
        // The campaign: one table row per iteration, the convergence chart, every QC plot loaded.
        let table = element(dom, "iterations", "</table>");
        assert_eq!(table.matches("<tr>").count(), 1 + iterations, "{table}");
        // Each iteration's largest change says where it is (a tooltip: "v01 at 123 m"), and the
        // field's cell its largest heading where it solved one.
        let heading_tips = table.matches("<td title=\"heading up to ").count();
        let field_iterations =
            recorded.iter().filter(|i| i.stats["common_mode_heading_max_deg"].as_f64() > Some(0.0)).count();
        assert!(heading_tips > 0 && heading_tips == field_iterations, "{heading_tips} of {field_iterations}: {table}");
        assert_eq!(table.matches("<td title=\"").count() - heading_tips, iterations, "{table}");
        assert!(table.contains(" m\">") && table.contains(" mdeg\">"), "{table}");
        // Those that started from Anderson's combination are marked, the coefficients a tooltip.
        assert_eq!(
            table.matches("<abbr class=\"accelerated\" title=\"started from Anderson").count(),
            accelerated,
            "{table}"
        );
        assert!(table.contains("iterations (γ = "), "{table}");
        let chart = element(dom, "sigma-chart", "</div>");
        assert!(chart.contains("<polyline") && chart.contains("class=\"sigma\""), "{chart}");
        let qc = element(dom, "qc", "</section>");
        assert_eq!(qc.matches("<img").count(), qc_plots, "{qc}");
        assert_eq!(qc.matches("data-loaded=\"1\"").count(), qc_plots, "every plot loads as an image: {qc}");
        // Result files folded per folder (the latent map is one file per tile), top-level files
        // as links.
        let files = element(dom, "result-list", "</section>");
        for (folder, count) in [("strips", in_folder("strips")), ("latent", latent_tiles), ("qc", qc_plots)] {
            let summary = format!("<details data-folder=\"{folder}\"><summary>{folder}/ ({count} files)</summary>");
            assert!(files.contains(&summary), "{summary} in {files}");
        }
        assert!(files.contains("download=\"\">report.json</a>"), "{files}");
        let events = element(dom, "events", "</ol>");
        assert!(events.contains("<strong>succeeded</strong>"), "{events}");
        // The failed campaign's page names the broken strip.
        let error = element(&failed_page, "d-error", "</p>");
        assert!(error.contains("v02-right") && !error.contains(" hidden"), "{error}");
    });
}

/// A WebDriver session (W3C protocol, JSON over HTTP) in headless Chromium; the driver process
/// ends with it.
struct Browser {
    http: reqwest::Client,
    session: String,
    driver: std::process::Child,
}

impl Browser {
    async fn start(chromedriver: &Path, chromium: &Path, profile: &Path) -> Browser {
        let port = free_port();
        let driver = std::process::Command::new(chromedriver)
            .arg(format!("--port={port}"))
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("start chromedriver");
        let mut browser = Browser { http: reqwest::Client::new(), session: format!("http://127.0.0.1:{port}"), driver };
        let started = Instant::now();
        while browser.http.get(format!("{}/status", browser.session)).send().await.is_err() {
            assert!(started.elapsed() < Duration::from_secs(30), "chromedriver did not start");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let capabilities = serde_json::json!({ "capabilities": { "alwaysMatch": {
            "browserName": "chrome",
            "unhandledPromptBehavior": "ignore",
            "goog:chromeOptions": {
                "binary": chromium,
                // The test runs as root in CI.
                "args": ["--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                         format!("--user-data-dir={}", profile.display())],
            },
        }}});
        let created = browser.command(reqwest::Method::POST, "session", capabilities).await;
        let id = created["sessionId"].as_str().expect("a session id").to_string();
        browser.session = format!("{}/session/{id}", browser.session);
        browser
    }

    /// One command (`path` under the session); its `value`. A WebDriver error fails the test.
    async fn command(&self, method: reqwest::Method, path: &str, body: serde_json::Value) -> serde_json::Value {
        let url = if path.is_empty() { self.session.clone() } else { format!("{}/{path}", self.session) };
        let request = self.http.request(method, &url);
        let request = if body.is_null() { request } else { request.json(&body) };
        let reply: serde_json::Value = request.send().await.unwrap().json().await.unwrap();
        let value = reply["value"].clone();
        assert!(value.get("error").is_none(), "WebDriver {path}: {value}");
        value
    }

    async fn script(&self, script: &str) -> serde_json::Value {
        self.command(reqwest::Method::POST, "execute/sync", serde_json::json!({ "script": script, "args": [] })).await
    }

    /// Waits until `condition` (a JavaScript expression) is true in the page.
    async fn wait_for(&self, condition: &str) {
        let started = Instant::now();
        while self.script(&format!("return Boolean({condition});")).await != serde_json::json!(true) {
            assert!(started.elapsed() < Duration::from_secs(30), "never true in the page: {condition}");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    async fn element(&self, css: &str) -> String {
        let found = self
            .command(reqwest::Method::POST, "element", serde_json::json!({ "using": "css selector", "value": css }))
            .await;
        found.as_object().and_then(|o| o.values().next()).and_then(|v| v.as_str()).expect("an element").to_string()
    }

    async fn click(&self, css: &str) {
        let id = self.element(css).await;
        self.command(reqwest::Method::POST, &format!("element/{id}/click"), serde_json::json!({})).await;
    }

    async fn type_into(&self, css: &str, text: &str) {
        let id = self.element(css).await;
        self.command(reqwest::Method::POST, &format!("element/{id}/clear"), serde_json::json!({})).await;
        self.command(reqwest::Method::POST, &format!("element/{id}/value"), serde_json::json!({ "text": text })).await;
    }

    /// Waits for the page's `confirm()` and answers it; returns its text.
    async fn answer_confirm(&self, accept: bool) -> String {
        let started = Instant::now();
        loop {
            let reply: serde_json::Value =
                self.http.get(format!("{}/alert/text", self.session)).send().await.unwrap().json().await.unwrap();
            if let Some(text) = reply["value"].as_str() {
                let answer = if accept { "alert/accept" } else { "alert/dismiss" };
                self.command(reqwest::Method::POST, answer, serde_json::json!({})).await;
                return text.to_string();
            }
            assert!(started.elapsed() < Duration::from_secs(10), "no confirmation dialog: {reply}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    async fn text(&self, css: &str) -> String {
        let script = format!("return document.querySelector({css:?}).textContent;");
        self.script(&script).await.as_str().unwrap_or_default().to_string()
    }
}

impl Browser {
    /// Ends the session, which closes Chromium.
    async fn quit(&self) {
        self.command(reqwest::Method::DELETE, "", serde_json::Value::Null).await;
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

/// The dashboard's one writing action, clicked in a real browser: cancelling a running campaign
/// asks for the writer token first, refuses a wrong one (the server answers 401 and the campaign
/// runs on), does nothing when the confirmation is dismissed, and cancels with the right token.
#[test]
fn the_dashboard_cancels_a_campaign_only_with_the_writer_token() {
    let (Some(chromium), Some(chromedriver)) = (chromium(), chromedriver()) else { return };
    let dir = tempfile::tempdir().unwrap();
    let campaign = simulate_tiny(dir.path(), 11);
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let (jobs, objects, framework) = local_framework(dir.path()).await;
        let address = serve_api(&framework).await;
        // No executor works the queue: the campaign stays running until cancelled.
        let manifest = upload_local_inputs(&objects, &campaign.join("manifest.json")).await.unwrap();
        let id = framework.submit(&manifest).await.unwrap();
        let state = |jobs: JobStore| async move { jobs.campaign(id).await.unwrap().unwrap().state };

        let browser = Browser::start(&chromedriver, &chromium, &dir.path().join("chromium")).await;
        let page = format!("http://{address}/#{id}");
        browser.command(reqwest::Method::POST, "url", serde_json::json!({ "url": page })).await;
        browser.wait_for("!document.getElementById('cancel').hidden").await;

        // 1. No token: the page asks for it and sends nothing.
        browser.click("#cancel").await;
        browser.wait_for("document.getElementById('token-box').open").await;
        assert!(browser.text("#action-message").await.contains("writer token"));
        assert_eq!(state(jobs.clone()).await, CampaignState::Running);

        // 2. A wrong token: confirmed, refused by the server, still running.
        browser.type_into("#token", "not-the-token").await;
        browser.click("#cancel").await;
        assert!(browser.answer_confirm(true).await.contains("Cancel this campaign?"));
        browser.wait_for("document.getElementById('action-message').textContent.startsWith('not cancelled')").await;
        assert_eq!(state(jobs.clone()).await, CampaignState::Running);

        // 3. The right token, but the confirmation dismissed: nothing happens.
        browser.type_into("#token", "t0ken").await;
        browser.click("#cancel").await;
        browser.answer_confirm(false).await;
        tokio::time::sleep(Duration::from_millis(500)).await;
        assert_eq!(state(jobs.clone()).await, CampaignState::Running);

        // 4. Confirmed: cancelled, and the page says so.
        browser.click("#cancel").await;
        browser.answer_confirm(true).await;
        browser.wait_for("document.getElementById('action-message').textContent === 'cancelled'").await;
        assert_eq!(state(jobs.clone()).await, CampaignState::Cancelled);
        browser.wait_for("document.getElementById('cancel').hidden").await;
        browser.quit().await;
    });
}

/// Sends `signal` (e.g. "TERM") to a child process.
#[cfg(unix)]
fn send_signal(child: &std::process::Child, signal: &str) {
    let status = std::process::Command::new("kill")
        .args([&format!("-{signal}"), &child.id().to_string()])
        .status()
        .expect("kill");
    assert!(status.success(), "kill -{signal} {}", child.id());
}

/// `precimap serve --no-auth` on 127.0.0.1:`port` over `dir`'s SQLite `jobs.db` and file store
/// `store/`, with `extra` arguments, once it answers; its standard error goes to the returned file.
fn serve_locally(dir: &Path, port: u16, extra: &[&str]) -> (Worker, PathBuf) {
    let log = dir.join("serve.log");
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_precimap"))
        .args(["serve", "--no-auth", "--listen", &format!("127.0.0.1:{port}")])
        .args(["--db", &format!("sqlite://{}", dir.join("jobs.db").display())])
        .args(["--store", &format!("file://{}", dir.join("store").display())])
        .args(extra)
        .current_dir(dir)
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .expect("spawn precimap serve");
    let mut server = Worker { child };
    server.wait_until_serving(port, || std::fs::read_to_string(&log).unwrap_or_default());
    (server, log)
}

/// Waits at most `limit` for a child to exit; panics with `log()` if it does not.
fn exit_within(child: &mut std::process::Child, limit: Duration, log: impl Fn() -> String) -> std::process::ExitStatus {
    let started = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        assert!(started.elapsed() < limit, "still running {limit:?} after the signal: {}", log());
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// `precimap work` stopped by SIGTERM, as Kubernetes or Docker stop it: given time (its grace),
/// it completes the task it runs, claims nothing more and exits 0; with no grace it hands that
/// task back to the queue at once and exits 0. Each executor runs in its own working directory.
/// Either way the campaign then completes under other executors with exactly the in-process
/// result: no task lost, none completed twice.
#[cfg(unix)]
#[test]
fn an_executor_stops_on_sigterm_without_losing_or_repeating_a_task() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = simulate_tiny(dir.path(), 8);
    let reference = dir.path().join("in-process");
    in_process(&campaign.join("manifest.json"), &reference);
    let rt = tokio::runtime::Runtime::new().unwrap();
    let (jobs, objects, framework) = rt.block_on(local_framework(dir.path()));
    let manifest = rt.block_on(upload_local_inputs(&objects, &campaign.join("manifest.json"))).unwrap();
    let id = rt.block_on(framework.submit(&manifest)).unwrap();
    let db = format!("sqlite://{}", dir.path().join("jobs.db").display());
    let store = format!("file://{}", dir.path().join("store").display());
    let events = |kind: &str| -> Vec<precimap_jobs::EventRecord> {
        let all = rt.block_on(jobs.events(id, 0, 100_000)).unwrap();
        all.into_iter().filter(|e| e.kind == kind).collect()
    };

    for (grace_s, hands_back) in [("60", false), ("0", true)] {
        let workdir = dir.path().join(format!("executor-grace-{grace_s}"));
        std::fs::create_dir_all(&workdir).unwrap();
        let log = workdir.join("stderr.log");
        let child = std::process::Command::new(env!("CARGO_BIN_EXE_precimap"))
            .args(["work", "--db", &db, "--store", &store, "--lease-s", "30", "--concurrency", "1"])
            .args(["--shutdown-grace-s", grace_s])
            .current_dir(&workdir)
            .env("PRECIMAP_LOG", "warn")
            .stdout(std::process::Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("spawn precimap work");
        let mut worker = Worker { child };
        let me = format!("-{}-0", worker.child.id());
        let read_log = || std::fs::read_to_string(&log).unwrap_or_default();
        // Wait until this executor has claimed a task, then stop it while the task runs.
        let started = Instant::now();
        let claimed = loop {
            let mine = events("claimed").into_iter().find(|e| e.message.ends_with(&me));
            if let Some(e) = mine {
                break e.task_id.unwrap();
            }
            assert!(started.elapsed() < Duration::from_secs(60), "no task claimed: {}", read_log());
            std::thread::sleep(Duration::from_millis(10));
        };
        send_signal(&worker.child, "TERM");
        let status = exit_within(&mut worker.child, Duration::from_secs(50), read_log);
        assert!(status.success(), "exit status {status}: {}", read_log());
        assert_eq!(rt.block_on(jobs.task_counts(id)).unwrap().leased, 0, "nothing stays leased: {}", read_log());
        // What became of every task this executor claimed (a completion may claim the next).
        let mine: Vec<i64> =
            events("claimed").iter().filter(|e| e.message.ends_with(&me)).filter_map(|e| e.task_id).collect();
        assert!(mine.contains(&claimed));
        let count = |kind: &str| events(kind).iter().filter(|e| e.task_id.is_some_and(|t| mine.contains(&t))).count();
        let (done, released) = (count("done"), count("released"));
        if hands_back {
            assert!(released >= 1, "the running task was handed back: {}", read_log());
        } else {
            assert_eq!(released, 0, "given time, tasks are finished, not handed back: {}", read_log());
        }
        assert_eq!(done + released, mine.len(), "each claimed task was completed or handed back: {}", read_log());
    }

    let workers = {
        let _runtime = rt.enter();
        LocalExecutors::start(&jobs, &objects, &dir.path().join("scratch"))
    };
    let finished = rt.block_on(wait_finished(&jobs, id, Duration::from_secs(600)));
    rt.block_on(workers.stop());
    assert_eq!(finished.state, CampaignState::Succeeded, "{:?}", finished.error);
    let out = dir.path().join("results");
    rt.block_on(framework.download_results(id, &out)).unwrap();
    assert_same_results(&reference, &out);
}

/// `precimap serve` stopped by SIGTERM: it stops accepting connections at once, finishes the
/// request in flight (an upload whose second half arrives after the signal) and exits 0.
#[cfg(unix)]
#[test]
fn the_server_finishes_its_requests_on_sigterm_and_exits() {
    use std::io::{Read as _, Write as _};
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let (mut server, log) = serve_locally(dir.path(), port, &[]);
    let read_log = || std::fs::read_to_string(&log).unwrap_or_default();

    let body = vec![b'x'; 64 * 1024];
    let mut upload = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    upload.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    let head = format!(
        "PUT /v1/objects/inputs/shutdown/half.bin HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: {}\r\n\
         Connection: close\r\n\r\n",
        body.len()
    );
    upload.write_all(head.as_bytes()).unwrap();
    upload.write_all(&body[..body.len() / 2]).unwrap();
    std::thread::sleep(Duration::from_millis(200));

    send_signal(&server.child, "TERM");
    // New connections are refused once the server has stopped accepting.
    let started = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
        assert!(started.elapsed() < Duration::from_secs(10), "still accepting after SIGTERM: {}", read_log());
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(server.child.try_wait().unwrap().is_none(), "exited with a request in flight: {}", read_log());
    upload.write_all(&body[body.len() / 2..]).unwrap();
    let mut answer = String::new();
    upload.read_to_string(&mut answer).unwrap();
    assert!(answer.starts_with("HTTP/1.1 201"), "the upload in flight completes: {answer}");
    let status = exit_within(&mut server.child, Duration::from_secs(20), read_log);
    assert!(status.success(), "exit status {status}: {}", read_log());
    assert_eq!(std::fs::metadata(dir.path().join("store/inputs/shutdown/half.bin")).unwrap().len(), body.len() as u64);
}

/// A scrape of `GET /metrics` on 127.0.0.1:`port`: each sample line's series (name and labels)
/// with its value. Empty when the endpoint does not answer.
fn scrape(port: u16) -> Vec<(String, f64)> {
    let Some(answer) = http_get(port, "/metrics") else { return Vec::new() };
    let Some((_, body)) = answer.split_once("\r\n\r\n") else { return Vec::new() };
    body.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .filter_map(|l| {
            let (series, value) = l.rsplit_once(' ')?;
            Some((series.to_string(), value.parse().ok()?))
        })
        .collect()
}

/// The sum of the samples of metric `name` whose labels include every one of `labels`
/// (`kind="estimate_tile"`).
fn metric(samples: &[(String, f64)], name: &str, labels: &[&str]) -> f64 {
    samples
        .iter()
        .filter(|(series, _)| {
            let metric_name = series.split('{').next().unwrap_or_default();
            metric_name == name && labels.iter().all(|l| series.contains(l))
        })
        .map(|(_, v)| v)
        .sum()
}

/// `GET /metrics` of `precimap serve` and of a separate `precimap work --metrics-listen`, scraped
/// while a campaign runs: the queue, the executors, claims, task durations, points, object-store
/// bytes, the campaign's iteration and residual each change; an executor SIGKILLed while it
/// holds a task shows up as a lease expiry and a retry once its lease has run out. `GET /readyz`
/// is ready with both stores answering, and not with an object store that does not answer.
#[cfg(unix)]
#[test]
fn metrics_follow_a_campaign_and_readiness_checks_both_stores() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = simulate_tiny(dir.path(), 9);
    let (port, executor_port) = (free_port(), free_port());
    let db = format!("sqlite://{}", dir.path().join("jobs.db").display());
    let store = format!("file://{}", dir.path().join("store").display());
    let (server, log) = serve_locally(dir.path(), port, &["--workers", "2", "--lease-s", "2"]);
    let read_log = || std::fs::read_to_string(&log).unwrap_or_default();
    let ready = http_get(port, "/readyz").unwrap();
    assert!(ready.contains(" 200 ") && ready.contains("\"ready\""), "{ready}");
    let idle = scrape(port);
    assert_eq!(metric(&idle, "precimap_executor_loops", &[]), 2.0, "{idle:?}");
    assert_eq!(metric(&idle, "precimap_queue_tasks", &[]), 0.0);

    let executor_dir = dir.path().join("executor");
    std::fs::create_dir_all(&executor_dir).unwrap();
    let executor_log = executor_dir.join("stderr.jsonl");
    let executor = std::process::Command::new(env!("CARGO_BIN_EXE_precimap"))
        .args(["--log-format", "json", "work", "--db", &db, "--store", &store, "--lease-s", "2"])
        .args(["--concurrency", "1", "--metrics-listen", &format!("127.0.0.1:{executor_port}")])
        .env("PRECIMAP_LOG", "precimap_framework=debug")
        .current_dir(&executor_dir)
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&executor_log).unwrap())
        .spawn()
        .expect("spawn precimap work");
    let mut executor = Worker { child: executor };
    let executor_id = format!(
        "{}-{}-0",
        std::fs::read_to_string("/etc/hostname").map(|s| s.trim().to_string()).unwrap_or_else(|_| "executor".into()),
        executor.child.id()
    );

    let rt = tokio::runtime::Runtime::new().unwrap();
    let client = Client::new(&format!("http://127.0.0.1:{port}"), None);
    let id = rt.block_on(async { client.submit_local(&campaign.join("manifest.json"), |_, _| {}).await.unwrap().id });
    let jobs = rt.block_on(JobStore::connect(&db)).unwrap();
    let (mut most_queued, mut most_busy, mut last_iteration, mut residual_seen) = (0.0f64, 0.0f64, 0.0f64, false);
    let mut executor_samples = Vec::new();
    let started = Instant::now();
    loop {
        let samples = scrape(port);
        most_queued = most_queued.max(metric(&samples, "precimap_queue_tasks", &[]));
        most_busy = most_busy.max(metric(&samples, "precimap_executors_busy", &[]));
        let campaign_label = format!("campaign=\"{id}\"");
        last_iteration = last_iteration.max(metric(&samples, "precimap_campaign_iteration", &[&campaign_label]));
        residual_seen |= metric(&samples, "precimap_campaign_residual_std_metres", &[&campaign_label]) > 0.0;
        // Kill the separate executor once it holds a task (its lease then expires).
        if executor_samples.is_empty() && !rt.block_on(jobs.leased_by(&executor_id)).unwrap().is_empty() {
            executor_samples = scrape(executor_port);
            executor.child.kill().unwrap();
            executor.child.wait().unwrap();
        }
        let status = rt.block_on(client.status(id)).unwrap();
        if status.campaign.state != "running" {
            assert_eq!(status.campaign.state, "succeeded", "{:?}", status.campaign.error);
            break;
        }
        assert!(started.elapsed() < Duration::from_secs(600), "campaign stuck: {}", read_log());
        std::thread::sleep(Duration::from_millis(100));
    }
    let done = scrape(port);

    assert!(!executor_samples.is_empty(), "the separate executor never held a task");
    assert_eq!(metric(&executor_samples, "precimap_executor_loops", &[]), 1.0, "{executor_samples:?}");
    assert!(metric(&executor_samples, "precimap_claim_duration_seconds_count", &["found=\"yes\""]) >= 1.0);
    assert!(most_queued > 0.0 && most_busy > 0.0, "queue {most_queued}, busy {most_busy}");
    assert_eq!(metric(&done, "precimap_queue_tasks", &[]), 0.0, "the queue drained");
    assert!(last_iteration >= 1.0 && residual_seen, "iteration {last_iteration}, residual seen {residual_seen}");
    for kind in ["segment_strip", "estimate_tile", "solve_trajectory", "export_strip"] {
        let kind = format!("kind=\"{kind}\"");
        let n = metric(&done, "precimap_task_duration_seconds_count", &[&kind, "outcome=\"done\""]);
        assert!(n >= 1.0, "{kind}: {n} task durations");
        assert_eq!(n, metric(&done, "precimap_tasks_finished_total", &[&kind, "outcome=\"done\""]));
    }
    assert!(metric(&done, "precimap_points_processed_total", &["kind=\"estimate_tile\""]) > 0.0);
    assert!(metric(&done, "precimap_object_store_read_bytes_total", &[]) > 0.0);
    assert!(metric(&done, "precimap_object_store_written_bytes_total", &[]) > 0.0);
    assert!(metric(&done, "precimap_claim_duration_seconds_count", &[]) > 0.0);
    assert!(metric(&done, "precimap_lease_expiries_total", &[]) >= 1.0, "the killed executor's lease: {done:?}");
    assert!(metric(&done, "precimap_task_retries_total", &["reason=\"lease_expired\""]) >= 1.0);
    assert_eq!(metric(&done, "precimap_campaigns", &["state=\"succeeded\""]), 1.0);
    rt.block_on(jobs.close());
    drop(server);

    // The executor's logs are JSON lines; those of a task carry its campaign, id and attempt.
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(&executor_log)
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not a JSON line ({e}): {l}")))
        .collect();
    let in_task = lines.iter().find(|l| l["span"]["name"] == "task").unwrap_or_else(|| panic!("{lines:?}"));
    assert_eq!(in_task["span"]["campaign"], id.to_string(), "{in_task}");
    assert!(in_task["span"]["task"].is_u64() && in_task["span"]["attempt"].is_u64(), "{in_task}");

    // An object store that does not answer: not ready, and the answer names no address.
    let port = free_port();
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_precimap"))
        .args(["serve", "--no-auth", "--listen", &format!("127.0.0.1:{port}"), "--db", &db])
        .args(["--store", "s3://precimap/readyz"])
        .env("AWS_ENDPOINT", format!("http://127.0.0.1:{}", free_port()))
        .env("AWS_ALLOW_HTTP", "true")
        .env("AWS_ACCESS_KEY_ID", "readyz")
        .env("AWS_SECRET_ACCESS_KEY", "readyz")
        .env("AWS_REGION", "readyz")
        .current_dir(dir.path())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("spawn precimap serve");
    let mut unready = Worker { child };
    unready.wait_until_serving(port, String::new);
    let answer = http_get(port, "/readyz").unwrap();
    assert!(answer.contains(" 503 ") && answer.contains("object store"), "{answer}");
    assert!(!answer.contains("127.0.0.1"), "{answer}");
}
