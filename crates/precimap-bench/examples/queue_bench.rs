//! `cargo run --release -p precimap-bench --example queue_bench -- URL [TASKS] [CLAIMERS...]`
//! prints one JSON line of figures per claimer count. `PRECIMAP_BENCH_ASYNC_COMMIT=1` turns off
//! PostgreSQL's `synchronous_commit` (see `StoreOptions::durable_commits`);
//! `PRECIMAP_BENCH_ASYNC_CLAIMS=1` only for claims (`StoreOptions::durable_claims`);
//! `PRECIMAP_BENCH_SEPARATE_CLAIMS=1` claims with a statement of its own after each completion
//! instead of `JobStore::complete_and_claim`.

use precimap_bench::queue::{queue_bench_with, QueueBenchOptions};

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let url = args.next().unwrap_or_else(|| "postgres://postgres@127.0.0.1:5432/postgres".into());
    let tasks: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(5000);
    let mut claimers: Vec<usize> = args.map(|s| s.parse()).collect::<Result<_, _>>()?;
    if claimers.is_empty() {
        claimers = vec![1, 4, 16];
    }
    let durable = std::env::var("PRECIMAP_BENCH_ASYNC_COMMIT").map_or(true, |v| v != "1");
    let durable_claims = std::env::var("PRECIMAP_BENCH_ASYNC_CLAIMS").map_or(true, |v| v != "1");
    let combined = std::env::var("PRECIMAP_BENCH_SEPARATE_CLAIMS").map_or(true, |v| v != "1");
    let options = QueueBenchOptions { durable_commits: durable, durable_claims, combined };
    for n in claimers {
        let figures = queue_bench_with(&url, n, tasks, options).await?;
        println!("{}", serde_json::to_string(&figures)?);
    }
    Ok(())
}
