//! `precimap bench …`: rerunnable benchmarks that print per-core throughput.

use anyhow::{Context, Result};
use clap::Subcommand;
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::IterationStep;
use precimap_pipeline::{tasks, Campaign};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// One 2 cm estimation iteration on a simulated campaign, single-threaded and on all cores.
    Estimate {
        #[arg(long, default_value = "medium")]
        scale: precimap_sim::Scale,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where the simulated campaign and its tile chunks are cached between runs.
        #[arg(long, default_value = "target/bench")]
        cache: PathBuf,
        #[arg(long)]
        json: bool,
    },
    /// The block-tridiagonal solver alone.
    Solve {
        #[arg(long, default_value_t = 20_000)]
        anchors: usize,
        #[arg(long)]
        json: bool,
    },
}

pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Estimate { scale, seed, cache, json } => bench_estimate(scale, seed, &cache, json),
        BenchCommand::Solve { anchors, json } => {
            let rate = precimap_solve::bench_solve(anchors, 5);
            if json {
                println!("{}", serde_json::json!({ "solve_anchors_per_s_per_core": rate, "anchors": anchors }));
            } else {
                println!("block-tridiagonal solve: {:.2} M anchors/s per core ({anchors} anchors)", rate / 1e6);
            }
            Ok(())
        }
    }
}

#[derive(Serialize)]
struct EstimateBench {
    scale: String,
    points_in_tiles: u64,
    point_copies: u64,
    tiles: usize,
    threads: usize,
    grid_m: f64,
    /// estimate_tile compute on all cores, per core.
    estimate_points_per_s_per_core: f64,
    /// The same on one thread.
    estimate_points_per_s_single_thread: f64,
    /// estimate_tile per CPU-second actually spent on a core (thread CPU time, Linux), all
    /// threads: robust when other processes share the machine; NaN where unavailable.
    estimate_points_per_cpu_s: f64,
    /// Including reading and decoding the tile chunks, all cores, per core.
    iteration_points_per_s_per_core: f64,
    parallel_efficiency: f64,
    /// Peak resident memory during the measured iterations.
    peak_rss_bytes: u64,
    largest_tile_points: u64,
}

fn bench_estimate(scale: precimap_sim::Scale, seed: u64, cache: &Path, json: bool) -> Result<()> {
    let dir = cache.join(format!("{scale:?}-{seed}").to_lowercase());
    let manifest = dir.join("campaign").join("manifest.json");
    if !manifest.exists() {
        eprintln!("simulating the {scale:?} campaign into {} (cached for later runs)", dir.display());
        let config = precimap_sim::SimConfig::for_scale(scale, seed);
        precimap_sim::simulate(&config, &dir.join("campaign"), false).context("simulating")?;
    }
    let campaign = Campaign::load(&manifest)?;
    let work = dir.join("work");
    eprintln!("preparing tile chunks in {}", work.display());
    let prepared = precimap_pipeline::run::prepare_all(&campaign, &work, &|_| {})?;
    let corrections: Vec<TrajectoryCorrections> =
        prepared.anchor_ranges.iter().map(|&(a, b)| TrajectoryCorrections::zeros(a, b)).collect();
    let step = IterationStep::new(0.02, 0.3);
    let tiles: Vec<_> = prepared.tiles.iter().collect();
    let threads = rayon::current_num_threads();

    // One pass over all tiles: returns (compute seconds summed over tiles, wall seconds, points).
    let pass = |pool: &rayon::ThreadPool| -> Result<(f64, f64, u64, u64, u64, f64)> {
        let started = Instant::now();
        let per_tile = pool.install(|| {
            tiles
                .par_iter()
                .map(|(tile, strips)| -> Result<(f64, u64, u64, f64)> {
                    let ids: Vec<&str> = strips.iter().map(|&s| campaign.strips[s].id.as_str()).collect();
                    let chunks = tasks::load_tile(&work, **tile, &ids)?;
                    let copies: u64 = chunks.iter().map(|c| c.len() as u64).sum();
                    let t = Instant::now();
                    let cpu = thread_cpu_s();
                    let est = precimap_estimate::estimate_tile(**tile, &chunks, &corrections, &campaign.params, &step)?;
                    let cpu = match (cpu, thread_cpu_s()) {
                        (Some(a), Some(b)) => b - a,
                        _ => f64::NAN,
                    };
                    Ok((t.elapsed().as_secs_f64(), est.stats.points, copies, cpu))
                })
                .collect::<Result<Vec<_>>>()
        })?;
        let wall = started.elapsed().as_secs_f64();
        let compute: f64 = per_tile.iter().map(|r| r.0).sum();
        let points: u64 = per_tile.iter().map(|r| r.1).sum();
        let copies: u64 = per_tile.iter().map(|r| r.2).sum();
        let largest = per_tile.iter().map(|r| r.2).max().unwrap_or(0);
        let cpu: f64 = per_tile.iter().map(|r| r.3).sum();
        Ok((compute, wall, points, copies, largest, cpu))
    };
    reset_peak_rss();
    let single = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let all = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    eprintln!("one 2 cm iteration over {} tiles on 1 thread, then on {threads}", tiles.len());
    let (c1, _w1, points, copies, largest, cpu1) = pass(&single)?;
    let (_cn, wn, _, _, _, cpu2) = pass(&all)?;
    let (cn2, wn2, _, _, _, cpu3) = pass(&all)?;
    let wall_all = wn.min(wn2);
    let compute_all = cn2;
    let result = EstimateBench {
        scale: format!("{scale:?}").to_lowercase(),
        points_in_tiles: points,
        point_copies: copies,
        tiles: tiles.len(),
        threads,
        grid_m: step.grid_m,
        // Compute seconds are summed over tiles, i.e. core-seconds.
        estimate_points_per_s_per_core: points as f64 / compute_all,
        estimate_points_per_s_single_thread: points as f64 / c1,
        estimate_points_per_cpu_s: points as f64 / cpu1.min(cpu2).min(cpu3),
        iteration_points_per_s_per_core: points as f64 / (wall_all * threads as f64),
        parallel_efficiency: (points as f64 / wall_all) / (points as f64 / c1) / threads as f64,
        peak_rss_bytes: peak_rss_bytes(),
        largest_tile_points: largest,
    };
    if json {
        println!("{}", serde_json::to_string_pretty(&result)?);
    } else {
        println!(
            "estimate_tile, 2 cm grid, {} points in {} tiles ({} copies with border overlap)\n  \
             single thread: {:.2} M points/s\n  per CPU-second on a core: {:.2} M points/s\n  {} threads: {:.2} M points/s per core (compute), {:.2} M points/s per core including chunk reads, parallel efficiency {:.0} %\n  \
             peak RSS {:.0} MiB (largest tile {} point copies)",
            result.points_in_tiles,
            result.tiles,
            result.point_copies,
            result.estimate_points_per_s_single_thread / 1e6,
            result.estimate_points_per_cpu_s / 1e6,
            threads,
            result.estimate_points_per_s_per_core / 1e6,
            result.iteration_points_per_s_per_core / 1e6,
            result.parallel_efficiency * 100.0,
            result.peak_rss_bytes as f64 / (1 << 20) as f64,
            result.largest_tile_points
        );
    }
    Ok(())
}

/// Resets the kernel's peak-RSS mark so it covers only what follows (Linux; a no-op elsewhere).
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// CPU time the calling thread has spent on a core (first field of
/// `/proc/thread-self/schedstat`, nanoseconds), `None` where unavailable.
fn thread_cpu_s() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse::<u64>().ok().map(|ns| ns as f64 * 1e-9)
}

fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<u64>().ok()).map(|kb| kb * 1024))
        })
        .unwrap_or(0)
}
