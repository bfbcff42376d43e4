//! A 33,000-strip manifest (4.8 MB, as a careless client might send one): refused by the default
//! bounds before anything is stored; with the bounds raised, accepted within 300 MB of memory
//! and 1.2 KB of database growth per strip (40 MB), on SQLite and on PostgreSQL
//! (`PRECIMAP_TEST_POSTGRES`, default `postgres://postgres@127.0.0.1:5432/postgres`). Prints its
//! figures:
//! `cargo test -p precimap-framework --test campaign_size -- --nocapture`.
//!
//! One test in its own binary, so the process's peak memory is this submission's.

use precimap_framework::{default_queue, CampaignLimits, Framework, Objects, SubmitError};
use precimap_jobs::JobStore;
use std::path::Path;
use std::time::Instant;
use uuid::Uuid;

const STRIPS: usize = 33_000;
const TRAJECTORIES: usize = 330;
/// Database growth allowed for the accepted submission: 1.2 KB per strip.
const MAX_GROWTH: u64 = 1200 * STRIPS as u64;

/// The manifest's JSON and the input files it names, written into the file store at `store`.
fn large_manifest(store: &Path) -> String {
    let upload = Uuid::new_v4().simple().to_string();
    let base = format!("inputs/{upload}");
    let mut trajectories = Vec::with_capacity(TRAJECTORIES);
    for t in 0..TRAJECTORIES {
        let uri = format!("{base}/trajectories/p{t:05}.csv");
        trajectories.push(serde_json::json!({ "id": format!("p{t:05}"), "uri": uri }));
    }
    let mut strips = Vec::with_capacity(STRIPS);
    for s in 0..STRIPS {
        let t = s % TRAJECTORIES;
        let side = if s % 2 == 0 { "left" } else { "right" };
        let id = format!("p{t:05}-{side}-{s:05}");
        let uri = format!("{base}/strips/{id}.las");
        strips.push(serde_json::json!({ "id": id, "trajectory": format!("p{t:05}"), "scanner": side, "uri": uri }));
    }
    for dir in ["trajectories", "strips"] {
        std::fs::create_dir_all(store.join(&base).join(dir)).unwrap();
    }
    for uri in trajectories.iter().chain(&strips).map(|e| e["uri"].as_str().unwrap()) {
        std::fs::write(store.join(uri), b"x").unwrap();
    }
    serde_json::json!({
        "name": "thirty-three thousand strips",
        "scanners": { "left": { "lever_arm_m": [0.0, 0.5, 0.3] }, "right": { "lever_arm_m": [0.0, -0.5, 0.3] } },
        "trajectories": trajectories,
        "strips": strips,
    })
    .to_string()
}

/// `field` of /proc/self/status in bytes (VmRSS, VmHWM).
fn proc_status_bytes(field: &str) -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let line = status.lines().find(|l| l.starts_with(field)).unwrap_or_else(|| panic!("{field} in /proc/self/status"));
    line.split_whitespace().nth(1).unwrap().parse::<u64>().unwrap() * 1024
}

/// Starts a new peak: VmHWM is set to the current RSS.
fn reset_peak() {
    std::fs::write("/proc/self/clear_refs", "5").expect("reset the peak RSS (Linux /proc/self/clear_refs)");
}

/// The database's size as SQLite counts it (pages × page size, the write-ahead log's committed
/// frames included): the files' sizes depend on whether the log was checkpointed yet when the
/// store closed, which a loaded machine may not have done.
async fn sqlite_bytes(url: &str) -> u64 {
    use sqlx::Connection;
    let mut c = sqlx::SqliteConnection::connect(url).await.unwrap();
    let pages: i64 = sqlx::query_scalar("PRAGMA page_count").fetch_one(&mut c).await.unwrap();
    let size: i64 = sqlx::query_scalar("PRAGMA page_size").fetch_one(&mut c).await.unwrap();
    c.close().await.unwrap();
    (pages * size) as u64
}

fn psql(url: &str, sql: &str) -> String {
    let out = std::process::Command::new("psql").args([url, "-tA", "-c", sql]).output().expect("psql");
    assert!(out.status.success(), "psql {sql}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

/// Submits `text` as the server does (parse, then submit within `limits`) and returns the
/// process's peak RSS growth over the RSS before, in bytes, and the seconds it took.
async fn submit_measured(
    framework: &Framework,
    text: &str,
    limits: &CampaignLimits,
) -> (Result<Uuid, SubmitError>, u64, f64) {
    reset_peak();
    let before = proc_status_bytes("VmRSS:");
    let started = Instant::now();
    let manifest = precimap_formats::parse_manifest(text).expect("the manifest is valid");
    let result = framework.submit_with_limits(&manifest, limits).await;
    drop(manifest);
    let seconds = started.elapsed().as_secs_f64();
    (result, proc_status_bytes("VmHWM:").saturating_sub(before), seconds)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_33k_strip_manifest_is_refused_by_default_and_fits_the_bounds_when_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let text = large_manifest(&store);
    eprintln!("manifest: {STRIPS} strips, {TRAJECTORIES} trajectories, {} bytes", text.len());
    let objects = Objects::from_url(&format!("file://{}", store.display())).unwrap();
    let raised = CampaignLimits { max_strips: 50_000, ..CampaignLimits::default() };

    // SQLite: the database's pages before and after.
    let db_dir = dir.path().join("sqlite");
    std::fs::create_dir_all(&db_dir).unwrap();
    let url = format!("sqlite://{}", db_dir.join("jobs.db").display());
    JobStore::connect(&url).await.unwrap().close().await;
    let empty = sqlite_bytes(&url).await;
    let jobs = JobStore::connect(&url).await.unwrap();
    let framework = Framework { jobs: jobs.clone(), objects: objects.clone(), queue: default_queue() };

    let (refused, peak, seconds) = submit_measured(&framework, &text, &CampaignLimits::default()).await;
    let Err(SubmitError::Invalid { problems }) = refused else { panic!("accepted by the default bounds") };
    assert_eq!(problems.len(), 1);
    assert_eq!(problems[0].path, "$.strips");
    assert!(problems[0].message.contains("at most 10000 strips"), "{}", problems[0].message);
    eprintln!("default bounds: refused in {seconds:.2} s, peak RSS +{:.1} MB", peak as f64 / 1e6);
    assert!(jobs.list_campaigns(1).await.unwrap().is_empty());

    let (accepted, peak, seconds) = submit_measured(&framework, &text, &raised).await;
    let id = accepted.expect("accepted with the bounds raised");
    assert_eq!(jobs.strips(id).await.unwrap().len(), STRIPS);
    jobs.close().await;
    let grown = sqlite_bytes(&url).await - empty;
    eprintln!(
        "SQLite: accepted in {seconds:.2} s, peak RSS +{:.1} MB, database +{:.1} MB ({:.0} bytes per strip)",
        peak as f64 / 1e6,
        grown as f64 / 1e6,
        grown as f64 / STRIPS as f64
    );
    assert!(peak < 300_000_000, "peak RSS grew by {peak} bytes");
    assert!(grown < MAX_GROWTH, "the database grew by {grown} bytes");

    // PostgreSQL: pg_database_size before and after.
    let admin = std::env::var("PRECIMAP_TEST_POSTGRES")
        .unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/postgres".into());
    let name = format!("precimap_size_{}", Uuid::new_v4().simple());
    psql(&admin, &format!("CREATE DATABASE {name}"));
    let url = format!("{}/{name}", admin.rsplit_once('/').unwrap().0);
    let jobs = JobStore::connect(&url).await.unwrap();
    let size = || psql(&admin, &format!("SELECT pg_database_size('{name}')")).parse::<u64>().unwrap();
    psql(&url, "CHECKPOINT");
    let empty = size();
    let framework = Framework { jobs: jobs.clone(), objects, queue: default_queue() };
    let (accepted, peak, seconds) = submit_measured(&framework, &text, &raised).await;
    accepted.expect("accepted with the bounds raised");
    jobs.close().await;
    let grown = size() - empty;
    eprintln!(
        "PostgreSQL: accepted in {seconds:.2} s, peak RSS +{:.1} MB, database +{:.1} MB ({:.0} bytes per strip)",
        peak as f64 / 1e6,
        grown as f64 / 1e6,
        grown as f64 / STRIPS as f64
    );
    psql(&admin, &format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)"));
    assert!(peak < 300_000_000, "peak RSS grew by {peak} bytes");
    assert!(grown < MAX_GROWTH, "the database grew by {grown} bytes");
}
