//! `precimap bench …`: rerunnable benchmarks that print per-core throughput.

use anyhow::{Context, Result};
use clap::Subcommand;
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::IterationStep;
use precimap_estimate::PreparePhase;
use precimap_pipeline::{tasks, Campaign};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// One estimation iteration (by default a 2 cm step) on a simulated campaign, single-threaded
    /// and on all cores.
    Estimate {
        #[arg(long, default_value = "medium")]
        scale: precimap_sim::Scale,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where the simulated campaign and its tile chunks are cached between runs.
        #[arg(long, default_value = "target/bench")]
        cache: PathBuf,
        /// Estimation parameters to change, as a manifest's `parameters` object (e.g.
        /// `'{"latent_pixel_share": 0}'` for the exact point-sampled route), to measure a variant.
        #[arg(long, value_name = "JSON")]
        parameters: Option<String>,
        /// Only the single-thread pass, once: for counting its instructions and simulated cache
        /// misses, which do not drift with the machine's load, e.g. `valgrind --tool=callgrind
        /// --cache-sim=yes --toggle-collect='*estimate_tile_into*'` (with `MALLOC_ARENA_MAX` set,
        /// so that precimap does not restart itself outside valgrind).
        #[arg(long)]
        one_pass: bool,
        /// The step's grid (metres): below `point_latent_below_grid_m` (3 cm by default) the
        /// latent map is sampled at pixel centres, from it up rasterised at this pixel size.
        #[arg(long, default_value_t = 0.02, value_name = "METRES")]
        grid: f64,
        /// The step's outlier threshold (metres).
        #[arg(long, default_value_t = 0.3, value_name = "METRES")]
        threshold: f64,
        /// Measure the default schedule's first step instead: a capture step (3 m column cells,
        /// 25 cm pixels, 1 m threshold, translation only).
        #[arg(long, conflicts_with_all = ["grid", "threshold"])]
        capture: bool,
        #[arg(long)]
        json: bool,
    },
    /// Queue throughput (claim + complete cycles with 1, 4, 16 claimers on SQLite and PostgreSQL)
    /// and the job framework's overhead against the in-process driver on a simulated campaign.
    Queue {
        /// PostgreSQL server to benchmark on (a fresh database is created and dropped).
        #[arg(long, env = "PRECIMAP_TEST_POSTGRES", default_value = "postgres://postgres@127.0.0.1:5432/postgres")]
        postgres: String,
        /// Claim + complete cycles per measurement.
        #[arg(long, default_value_t = 3000)]
        tasks: usize,
        /// PostgreSQL: claims commit without waiting for the WAL flush (`StoreOptions::durable_claims`
        /// off; completions stay durable).
        #[arg(long)]
        async_claims: bool,
        /// Claim with a statement of its own after every completion, instead of claiming the next
        /// task in the completion's transaction (`JobStore::complete_and_claim`, what executors do).
        #[arg(long)]
        separate_claims: bool,
        /// Campaign for the overhead measurement (a full run in-process and through the framework).
        #[arg(long, default_value = "small")]
        overhead_scale: precimap_sim::Scale,
        /// Skip the overhead measurement.
        #[arg(long)]
        no_overhead: bool,
        /// Overhead pairs: in-process and framework this many times each, the order swapped every
        /// pair (in-process first in odd pairs), so a machine that speeds up or slows down through
        /// the runs biases neither; the ratio is the geometric mean over pairs.
        #[arg(long, default_value_t = 1)]
        overhead_runs: usize,
        #[arg(long, default_value = "target/bench")]
        cache: PathBuf,
        #[arg(long)]
        json: bool,
    },
    /// Strip pre-processing (LAZ decoding, geometry, scan image, RANSAC normals, segmentation,
    /// tiling and chunk encoding) on a simulated LAZ campaign: per-core throughput on all cores,
    /// cost per point for growing strip counts, peak memory, and the segmentation against truth.
    Preprocess {
        #[arg(long, default_value = "small")]
        scale: precimap_sim::Scale,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where the simulated LAZ campaign is cached between runs.
        #[arg(long, default_value = "target/bench")]
        cache: PathBuf,
        /// Run the full pass this many times and report the fastest (total and per phase): on a
        /// shared machine the minimum is the figure least disturbed by other processes.
        #[arg(long, default_value_t = 1)]
        repeat: usize,
        /// Skip the passes over 2, 4, 8, … strips (cost per point against strip count).
        #[arg(long)]
        no_scaling: bool,
        #[arg(long)]
        json: bool,
    },
    /// The accuracy matrix: scenes × GNSS/IMU error models × passes, each simulated, adjusted with
    /// the estimator's defaults and evaluated against its truth; writes a Markdown and a JSON
    /// table (one row per scenario).
    Accuracy {
        /// Run only the scenarios whose name (e.g. `grid/gauss_markov/4p`) contains this.
        #[arg(long)]
        filter: Option<String>,
        /// The fast subset at a smaller campaign size (what the test suite runs).
        #[arg(long)]
        fast: bool,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where each scenario's campaign and result are written (and removed after it).
        #[arg(long, default_value = "target/bench/accuracy")]
        work: PathBuf,
        /// Keep each scenario's campaign and result.
        #[arg(long)]
        keep: bool,
        /// Estimation parameters to change, as a manifest's `parameters` object, to measure a
        /// variant of the defaults against the matrix.
        #[arg(long, value_name = "JSON")]
        parameters: Option<String>,
        #[arg(long, default_value = "target/bench/accuracy/accuracy-matrix.md")]
        markdown: PathBuf,
        #[arg(long, default_value = "target/bench/accuracy/accuracy-matrix.json")]
        json: PathBuf,
    },
    /// The block-tridiagonal solver alone.
    Solve {
        #[arg(long, default_value_t = 20_000)]
        anchors: usize,
        #[arg(long)]
        json: bool,
    },
    /// The common-mode field's sparse solve (nested dissection + sparse Cholesky) on a synthetic street
    /// network of BLOCKS × BLOCKS city blocks at 15 m nodes, against a dense Cholesky where one
    /// fits (≤ 6,000 unknowns).
    FieldSolve {
        #[arg(long, default_value_t = 8)]
        blocks: usize,
        /// Unknowns per node: 4 for the field with its heading (`common_mode_heading`, the
        /// default), 6 with its tilt too (`common_mode_tilt`), 3 without either.
        #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u8).range(3..=6))]
        per_node: u8,
        #[arg(long)]
        json: bool,
    },
}

pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Accuracy { filter, fast, seed, work, keep, markdown, json, parameters } => {
            let request = crate::accuracy::MatrixRequest { filter, fast, seed, work, markdown, json, keep, parameters };
            crate::accuracy::run_matrix(&request).map(|_| ())
        }
        BenchCommand::Estimate { scale, seed, cache, parameters, one_pass, grid, threshold, capture, json } => {
            let step = match capture {
                true => precimap_core::params::default_schedule()[0],
                false => IterationStep::new(grid, threshold),
            };
            // The manifest's checks of a schedule step.
            let with_step = precimap_core::Parameters { schedule: vec![step], ..Default::default() };
            if let Some(problem) = with_step.problems().first() {
                anyhow::bail!("--grid / --threshold: {problem}");
            }
            bench_estimate(scale, seed, &cache, parameters.as_deref(), &step, one_pass, json)
        }
        BenchCommand::Queue {
            postgres,
            tasks,
            async_claims,
            separate_claims,
            overhead_scale,
            no_overhead,
            overhead_runs,
            cache,
            json,
        } => {
            let options = precimap_jobs::bench::QueueBenchOptions {
                durable_commits: true,
                durable_claims: !async_claims,
                combined: !separate_claims,
            };
            let overhead = (!no_overhead).then_some((overhead_scale, overhead_runs.max(1)));
            bench_queue(&postgres, tasks, options, overhead, &cache, json)
        }
        BenchCommand::Preprocess { scale, seed, cache, repeat, no_scaling, json } => {
            bench_preprocess(scale, seed, &cache, repeat.max(1), !no_scaling, json)
        }
        BenchCommand::Solve { anchors, json } => {
            let rate = precimap_solve::bench_solve(anchors, 5);
            if json {
                outln!("{}", serde_json::json!({ "solve_anchors_per_s_per_core": rate, "anchors": anchors }));
            } else {
                outln!("block-tridiagonal solve: {:.2} M anchors/s per core ({anchors} anchors)", rate / 1e6);
            }
            Ok(())
        }
        BenchCommand::FieldSolve { blocks, per_node, json } => {
            let b = precimap_solve::sparse::bench_street_network(blocks, per_node as usize)?;
            if json {
                outln!("{}", serde_json::to_string(&b)?);
            } else {
                let area_km2 = (blocks as f64 * 7.0 * 15.0 / 1000.0).powi(2);
                outln!(
                    "field solve, {blocks} × {blocks} blocks ({area_km2:.2} km², {} nodes, {} unknowns):",
                    b.unknowns / per_node as usize,
                    b.unknowns
                );
                outln!(
                    "  sparse (nested dissection by straight cuts + Cholesky): {:.3} s, {} factor entries ({:.1} MiB; dense: {:.1} MiB)",
                    b.sparse_s,
                    b.factor_entries,
                    b.factor_entries as f64 * 12.0 / 1048576.0,
                    (b.unknowns as f64).powi(2) * 8.0 / 1048576.0
                );
                outln!(
                    "  ordered by level structures instead (no coordinates): {:.3} s, {} factor entries \
                     (cuts: {:.2}× the speed, {:.2}× fewer entries)",
                    b.level_set_s,
                    b.level_set_factor_entries,
                    b.level_set_s / b.sparse_s,
                    b.level_set_factor_entries as f64 / b.factor_entries as f64
                );
                match (b.dense_s, b.dense_relative_difference) {
                    (Some(d), Some(diff)) => outln!(
                        "  dense Cholesky: {d:.3} s → sparse {:.1}× faster; solutions differ by {diff:.1e} (relative)",
                        d / b.sparse_s
                    ),
                    _ => outln!("  dense Cholesky: not run (more than 6,000 unknowns)"),
                }
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
    threshold_m: f64,
    /// The step's cells are capture columns (`--capture`).
    column_cells: bool,
    /// estimate_tile compute on one thread.
    estimate_points_per_s_single_thread: f64,
    /// estimate_tile per CPU-second actually spent on a core (thread CPU time, Linux), the
    /// fastest pass with the defaults: robust when other processes share the machine; NaN
    /// where unavailable.
    estimate_points_per_cpu_s: f64,
    /// Peak resident memory during the measured iterations.
    peak_rss_bytes: u64,
    largest_tile_points: u64,
    /// The single-thread pass's minor page faults (fresh pages the kernel had to map and zero)
    /// per point, inside `estimate_tile` (Linux; NaN elsewhere).
    minor_faults_per_point: f64,
    /// The share of that pass's thread CPU spent in the kernel (mostly those faults; Linux,
    /// in clock ticks; NaN elsewhere).
    system_cpu_share: f64,
    /// The passes after the first (absent with `--one-pass`).
    #[serde(flatten)]
    more: Option<MorePasses>,
}

/// What [`bench_estimate`]'s passes after the single-thread one measure.
#[derive(Serialize)]
struct MorePasses {
    /// estimate_tile compute on all cores, per core.
    estimate_points_per_s_per_core: f64,
    /// Including reading and decoding the tile chunks, all cores, per core.
    iteration_points_per_s_per_core: f64,
    parallel_efficiency: f64,
    /// Thread CPU of the fastest pass with the common-mode field's rows (the default) over a pass
    /// without them (`common_mode_field_m` 0): what the field costs the map task.
    field_cpu_ratio: f64,
    /// Thread CPU of a single-thread pass with `consistent_gradient` on over one with it off:
    /// what recording the covering triangles and their pulls costs the map task.
    consistent_gradient_cpu_ratio: f64,
}

fn bench_estimate(
    scale: precimap_sim::Scale,
    seed: u64,
    cache: &Path,
    parameters: Option<&str>,
    step: &IterationStep,
    one_pass: bool,
    json: bool,
) -> Result<()> {
    let (dir, manifest) = cached_campaign(cache, scale, seed, false)?;
    let mut campaign = Campaign::load(&manifest)?;
    if let Some(changes) = parameters {
        campaign.params = with_changes(&campaign.params, changes)?;
    }
    let work = dir.join("work");
    eprintln!("preparing tile chunks in {}", work.display());
    let prepared = precimap_pipeline::run::prepare_all(&campaign, &work, &|_| {})?;
    let corrections: Vec<TrajectoryCorrections> =
        prepared.anchor_ranges.iter().map(|&(a, b)| TrajectoryCorrections::zeros(a, b)).collect();
    let tiles: Vec<_> = prepared.tiles.iter().collect();
    let threads = rayon::current_num_threads();

    let without_field = precimap_core::Parameters { common_mode_field_m: 0.0, ..campaign.params.clone() };
    let gradient = |on| precimap_core::Parameters { consistent_gradient: on, ..campaign.params.clone() };
    // One pass over all tiles.
    let pass_with = |pool: &rayon::ThreadPool, params: &precimap_core::Parameters| -> Result<EstimatePass> {
        let started = Instant::now();
        let per_tile = pool.install(|| {
            tiles
                .par_iter()
                .map(|(tile, strips)| -> Result<EstimatePass> {
                    let ids: Vec<&str> = strips.iter().map(|&s| campaign.strips[s].id.as_str()).collect();
                    let chunks = tasks::load_tile(&work, **tile, &ids)?;
                    let copies: u64 = chunks.iter().map(|c| c.len() as u64).sum();
                    // The kernel's figures are read outside the timed span: their reads of
                    // /proc would count as the task's CPU.
                    let kernel = ThreadKernelUse::now();
                    let t = Instant::now();
                    let cpu = thread_cpu_s();
                    let est = precimap_estimate::estimate_tile(**tile, &chunks, &corrections, params, step)?;
                    let cpu_s = match (cpu, thread_cpu_s()) {
                        (Some(a), Some(b)) => b - a,
                        _ => f64::NAN,
                    };
                    let compute_s = t.elapsed().as_secs_f64();
                    let kernel = ThreadKernelUse::since(kernel);
                    let points = est.stats.points;
                    Ok(EstimatePass { compute_s, wall_s: 0.0, points, copies, largest: copies, cpu_s, kernel })
                })
                .collect::<Result<Vec<_>>>()
        })?;
        let sum = per_tile.into_iter().fold(EstimatePass::default(), EstimatePass::plus);
        Ok(EstimatePass { wall_s: started.elapsed().as_secs_f64(), ..sum })
    };
    let pass = |pool: &rayon::ThreadPool| pass_with(pool, &campaign.params);
    reset_peak_rss();
    let single = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    // In centimetres to a tenth (0.07 × 100 prints as 7.000000000000001).
    let grid_cm = (step.grid_m * 1000.0).round() / 10.0;
    let kind = if step.column_cells { " capture" } else { "" };
    match one_pass {
        true => eprintln!("one {grid_cm} cm{kind} iteration over {} tiles on 1 thread, once", tiles.len()),
        false => {
            eprintln!("one {grid_cm} cm{kind} iteration over {} tiles on 1 thread, then on {threads}", tiles.len())
        }
    }
    let first = pass(&single)?;
    let (c1, points, cpu1) = (first.compute_s, first.points, first.cpu_s);
    let mut fastest_cpu = cpu1;
    let more = if one_pass {
        None
    } else {
        let all = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
        let (second, third) = (pass(&all)?, pass(&all)?);
        let (wn, wn2, cn2, cpu2, cpu3) = (second.wall_s, third.wall_s, third.compute_s, second.cpu_s, third.cpu_s);
        let cpu_without = pass_with(&single, &without_field)?.cpu_s;
        let cpu_consistent = pass_with(&single, &gradient(true))?.cpu_s;
        let cpu_map_held = pass_with(&single, &gradient(false))?.cpu_s;
        let wall_all = wn.min(wn2);
        fastest_cpu = cpu1.min(cpu2).min(cpu3);
        Some(MorePasses {
            // Compute seconds are summed over tiles, i.e. core-seconds.
            estimate_points_per_s_per_core: points as f64 / cn2,
            iteration_points_per_s_per_core: points as f64 / (wall_all * threads as f64),
            parallel_efficiency: (points as f64 / wall_all) / (points as f64 / c1) / threads as f64,
            // The fastest pass with the field (the first one runs cold) against the one without.
            field_cpu_ratio: fastest_cpu / cpu_without,
            consistent_gradient_cpu_ratio: cpu_consistent / cpu_map_held,
        })
    };
    let result = EstimateBench {
        scale: format!("{scale:?}").to_lowercase(),
        points_in_tiles: points,
        point_copies: first.copies,
        tiles: tiles.len(),
        threads: if one_pass { 1 } else { threads },
        grid_m: step.grid_m,
        threshold_m: step.threshold_m,
        column_cells: step.column_cells,
        estimate_points_per_s_single_thread: points as f64 / c1,
        estimate_points_per_cpu_s: points as f64 / fastest_cpu,
        peak_rss_bytes: peak_rss_bytes(),
        largest_tile_points: first.largest,
        minor_faults_per_point: first.kernel.map_or(f64::NAN, |k| k.minor_faults as f64 / points as f64),
        system_cpu_share: first.kernel.map_or(f64::NAN, |k| k.system_share()),
        more,
    };
    if json {
        outln!("{}", serde_json::to_string_pretty(&result)?);
    } else {
        outln!(
            "estimate_tile, {grid_cm} cm{kind} grid, {} points in {} tiles ({} copies with border overlap)\n  \
             single thread: {:.2} M points/s\n  per CPU-second on a core: {:.2} M points/s\n  \
             peak RSS {:.0} MiB (largest tile {} point copies)\n  \
             single-thread pass: {:.3} minor page faults per point, {:.1} % of its CPU in the kernel",
            result.points_in_tiles,
            result.tiles,
            result.point_copies,
            result.estimate_points_per_s_single_thread / 1e6,
            result.estimate_points_per_cpu_s / 1e6,
            result.peak_rss_bytes as f64 / (1 << 20) as f64,
            result.largest_tile_points,
            result.minor_faults_per_point,
            result.system_cpu_share * 100.0,
        );
        if let Some(more) = &result.more {
            outln!(
                "  {threads} threads: {:.2} M points/s per core (compute), {:.2} M points/s per core including chunk reads, parallel efficiency {:.0} %\n  \
                 common-mode field rows: {:.3}× the CPU of the same pass without them\n  \
                 consistent gradient: {:.3}× the CPU of the same pass with the map held",
                more.estimate_points_per_s_per_core / 1e6,
                more.iteration_points_per_s_per_core / 1e6,
                more.parallel_efficiency * 100.0,
                more.field_cpu_ratio,
                more.consistent_gradient_cpu_ratio
            );
        }
    }
    Ok(())
}

/// `params` with the fields of the JSON object `changes` replaced (unknown fields and
/// out-of-range values are errors, as in a manifest).
fn with_changes(params: &precimap_core::Parameters, changes: &str) -> Result<precimap_core::Parameters> {
    let changes: serde_json::Value = serde_json::from_str(changes).context("--parameters is not JSON")?;
    let serde_json::Value::Object(changes) = changes else {
        anyhow::bail!("--parameters must be a JSON object, like a manifest's \"parameters\"");
    };
    let mut merged = serde_json::to_value(params)?;
    if let serde_json::Value::Object(fields) = &mut merged {
        fields.extend(changes);
    }
    let params: precimap_core::Parameters = serde_json::from_value(merged).context("--parameters")?;
    let problems = params.problems();
    if let Some(first) = problems.first() {
        anyhow::bail!("--parameters: {first}");
    }
    Ok(params)
}

#[derive(Serialize)]
struct PreprocessBench {
    scale: String,
    strips: usize,
    points: u64,
    threads: usize,
    /// Full passes run; the figures below are the fastest of them (`--repeat`).
    repeat: usize,
    /// All strips on all cores (rayon over strips), LAZ decoding included: points per CPU-second
    /// of this process (robust on a shared machine).
    preprocess_points_per_s_per_core: f64,
    /// The same per wall-second × threads (lower when other processes share the cores).
    preprocess_points_per_s_per_core_wall: f64,
    /// Peak resident memory while preprocessing (threads strips in flight at once).
    peak_rss_bytes: u64,
    largest_strip_points: u64,
    /// Emitted point copies (border duplicates included) per point segmented, minus one.
    border_overhead: f64,
    chunk_bytes_per_point_copy: f64,
    chunk_bytes_total: u64,
    /// (strips, CPU nanoseconds per point) for the first n strips.
    cost_per_point_ns: Vec<(usize, f64)>,
    /// Where the time goes: per phase (decode, geometry, scan image, normals, segmentation,
    /// tiling, encode), thread CPU nanoseconds per point of the full pass (Linux schedstat; NaN
    /// elsewhere). Their sum is a little below the process figure above (which also counts the
    /// thread pool and the allocator's returns to the kernel).
    phase_cpu_ns_per_point: Vec<PhaseFigure>,
    /// Angle between the estimated and the true normal over surface points with a normal.
    normal_error_deg_mean: f64,
    normals: precimap_eval::NormalEvaluation,
    segment_purity: f64,
    surface_points_removed: f64,
    foliage_points_removed: f64,
    segmentation: precimap_eval::SegmentEvaluation,
}

#[derive(Serialize)]
struct PhaseFigure {
    phase: &'static str,
    cpu_ns_per_point: f64,
    /// Share of the phases' sum.
    share: f64,
}

/// Thread CPU seconds per [`PreparePhase`] (indexed by the enum's order).
type PhaseSeconds = [f64; PreparePhase::ALL.len()];

/// One preprocessing pass: wall s, CPU s, points, copies, chunk bytes, largest strip, thread CPU
/// seconds per phase.
type PassFigures = (f64, f64, u64, u64, u64, u64, PhaseSeconds);

fn bench_preprocess(
    scale: precimap_sim::Scale,
    seed: u64,
    cache: &Path,
    repeat: usize,
    scaling: bool,
    json: bool,
) -> Result<()> {
    let (dir, manifest) = cached_campaign(cache, scale, seed, true)?;
    let campaign = Campaign::load(&manifest)?;
    let threads = rayon::current_num_threads();
    let params = precimap_estimate::SegmentParams::default();
    // One pass over the first n strips: (wall seconds, points, copies, chunk bytes, largest strip).
    let pass = |n: usize| -> Result<PassFigures> {
        let started = Instant::now();
        let cpu_start = cpu_seconds();
        let per_strip = (0..n)
            .into_par_iter()
            .map(|s| -> Result<(u64, u64, u64, PhaseSeconds)> {
                // Each strip is prepared on one thread, so its thread CPU time splits into phases.
                let mut phases: PhaseSeconds = [0.0; PreparePhase::ALL.len()];
                let mut mark = thread_cpu_s().unwrap_or(f64::NAN);
                let mut phase_done = |p: PreparePhase| {
                    let now = thread_cpu_s().unwrap_or(f64::NAN);
                    phases[p as usize] += now - mark;
                    mark = now;
                };
                let prepared = tasks::prepare_strip_in_memory_observed(&campaign, s, &params, &mut phase_done)?;
                let bytes: u64 = prepared.chunks.iter().map(|c| c.encode().len() as u64).sum();
                phase_done(PreparePhase::Encode);
                Ok((prepared.stats.points, prepared.stats.points_emitted, bytes, phases))
            })
            .collect::<Result<Vec<_>>>()?;
        let wall = started.elapsed().as_secs_f64();
        let cpu = cpu_seconds() - cpu_start;
        let points = per_strip.iter().map(|r| r.0).sum();
        let copies = per_strip.iter().map(|r| r.1).sum();
        let bytes = per_strip.iter().map(|r| r.2).sum();
        let largest = per_strip.iter().map(|r| r.0).max().unwrap_or(0);
        let mut phases: PhaseSeconds = [0.0; PreparePhase::ALL.len()];
        for r in &per_strip {
            for (sum, s) in phases.iter_mut().zip(&r.3) {
                *sum += s;
            }
        }
        Ok((wall, cpu, points, copies, bytes, largest, phases))
    };
    let strips = campaign.strips.len();
    reset_peak_rss();
    eprintln!("preprocessing {strips} strips on {threads} threads");
    let (mut wall, mut cpu, points, copies, bytes, largest, mut phases) = pass(strips)?;
    let peak = peak_rss_bytes();
    for _ in 1..repeat {
        let (w, c, .., ph) = pass(strips)?;
        (wall, cpu) = (wall.min(w), cpu.min(c));
        for (best, p) in phases.iter_mut().zip(ph) {
            *best = best.min(p);
        }
    }
    let phase_sum: f64 = phases.iter().sum();
    let phase_cpu_ns_per_point = PreparePhase::ALL
        .iter()
        .map(|&p| PhaseFigure {
            phase: p.name(),
            cpu_ns_per_point: phases[p as usize] / points.max(1) as f64 * 1e9,
            share: phases[p as usize] / phase_sum,
        })
        .collect();
    let mut cost_per_point_ns = Vec::new();
    let mut n = 2;
    while scaling && n <= strips {
        let (_, c, p, ..) = pass(n)?;
        eprintln!("  {n} strips: {:.1} CPU ns per point", c / p as f64 * 1e9);
        cost_per_point_ns.push((n, c / p as f64 * 1e9));
        n *= 2;
    }
    // The segmentation and the normals against the simulator's truth, in a pass of its own (untimed,
    // so that the figures above cover pre-processing alone, memory included).
    let truth = dir.join("campaign").join("truth");
    let evaluated = (0..strips)
        .into_par_iter()
        .map(|s| -> Result<(precimap_eval::SegmentTally, precimap_eval::NormalTally)> {
            let prepared = tasks::prepare_strip_in_memory(&campaign, s, &params)?;
            let path = truth.join(format!("{}.truth", campaign.strips[s].id));
            let mut reader = precimap_sim::truth::TruthReader::open(&path)?;
            let mut tally = precimap_eval::SegmentTally::default();
            let mut normals = precimap_eval::NormalTally::default();
            let mut k = 0usize;
            while let Some(t) = reader.next_point()? {
                let id = *prepared
                    .segment
                    .get(k)
                    .with_context(|| format!("{} has more points than the strip", path.display()))?;
                tally.add(id, t.surface_id, t.class, t.normal, t.position);
                // Points of revolutions dropped at standstill are never given a normal.
                if id != precimap_estimate::DROPPED_SEGMENT {
                    normals.add(t.class, prepared.normals[k].map(|n| n.normal), t.normal);
                }
                k += 1;
            }
            Ok((tally, normals))
        })
        .collect::<Result<Vec<_>>>()?;
    let mut normal_tally = precimap_eval::NormalTally::default();
    for (_, n) in &evaluated {
        normal_tally.merge(n);
    }
    let tallies: Vec<_> = evaluated.into_iter().map(|(t, _)| t).collect();
    let segmentation = precimap_eval::SegmentEvaluation::from_tallies(&tallies);
    let normals = normal_tally.evaluate();
    let segmented: u64 = segmentation.points_segmented;
    let result = PreprocessBench {
        scale: format!("{scale:?}").to_lowercase(),
        strips,
        points,
        threads,
        repeat,
        preprocess_points_per_s_per_core: points as f64 / cpu,
        preprocess_points_per_s_per_core_wall: points as f64 / (wall * threads as f64),
        peak_rss_bytes: peak,
        largest_strip_points: largest,
        border_overhead: copies as f64 / segmented.max(1) as f64 - 1.0,
        chunk_bytes_per_point_copy: bytes as f64 / copies.max(1) as f64,
        chunk_bytes_total: bytes,
        cost_per_point_ns,
        phase_cpu_ns_per_point,
        normal_error_deg_mean: normals.surfaces.mean_deg,
        normals,
        segment_purity: segmentation.purity,
        surface_points_removed: segmentation.surface_points_removed,
        foliage_points_removed: segmentation.foliage_points_removed,
        segmentation,
    };
    if json {
        outln!("{}", serde_json::to_string_pretty(&result)?);
    } else {
        outln!(
            "preprocess (LAZ → tile chunks), {} points in {} strips\n  {:.2} M points/s per core on {threads} threads, \
             peak RSS {:.0} MiB (largest strip {} points)\n  {:.1} chunk bytes per point copy, border overhead {:.1} %\n  \
             segment purity {:.2} %, surface points removed {:.2} %, foliage points removed {:.1} %",
            result.points,
            strips,
            result.preprocess_points_per_s_per_core / 1e6,
            result.peak_rss_bytes as f64 / (1 << 20) as f64,
            result.largest_strip_points,
            result.chunk_bytes_per_point_copy,
            result.border_overhead * 100.0,
            result.segment_purity * 100.0,
            result.surface_points_removed * 100.0,
            result.foliage_points_removed * 100.0
        );
        println!("  normals vs truth (surface points; with normal, mean / p50 / p95 angle):");
        for (class, f) in std::iter::once(("all", &result.normals.surfaces))
            .chain(result.normals.per_class.iter().map(|(c, f)| (c.as_str(), f)))
        {
            println!(
                "    {class:<9} {:>5.1} %  {:>5.2}° / {:>5.2}° / {:>5.2}°",
                f.with_normal_share * 100.0,
                f.mean_deg,
                f.p50_deg,
                f.p95_deg
            );
        }
        println!("  thread CPU per point by phase (full pass, fastest of {repeat}):");
        for f in &result.phase_cpu_ns_per_point {
            println!("    {:<13} {:>7.1} ns  {:>5.1} %", f.phase, f.cpu_ns_per_point, f.share * 100.0);
        }
        println!(
            "    {:<13} {:>7.1} ns  (process: {:.1} ns)",
            "sum",
            phase_sum / points.max(1) as f64 * 1e9,
            cpu / points.max(1) as f64 * 1e9
        );
    }
    Ok(())
}

/// CPU seconds (user + system) this process has used so far (Linux `/proc/self/stat`, clock
/// ticks of 1/100 s); 0 elsewhere.
pub(crate) fn cpu_seconds() -> f64 {
    // utime and stime, in clock ticks of 10 ms (USER_HZ is 100 on Linux).
    proc_stat_fields("/proc/self/stat", [14, 15]).map_or(0.0, |[user, system]| (user + system) as f64 / 100.0)
}

/// The numeric fields `numbers` (1-based, as in `proc(5)`) of a `/proc/…/stat` file; `None`
/// where it is missing or shorter.
fn proc_stat_fields<const N: usize>(path: &str, numbers: [usize; N]) -> Option<[u64; N]> {
    let stat = std::fs::read_to_string(path).ok()?;
    // The command name (field 2) is in parentheses and may hold spaces: count from after it,
    // where field 3 (the state) comes first.
    let fields: Vec<&str> = stat.get(stat.rfind(')')? + 1..)?.split_whitespace().collect();
    let mut out = [0; N];
    for (value, n) in out.iter_mut().zip(numbers) {
        *value = fields.get(n.checked_sub(3)?)?.parse().ok()?;
    }
    Some(out)
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

/// What one pass of `bench estimate` measured, summed over its tiles.
#[derive(Clone, Copy, Debug)]
struct EstimatePass {
    /// `estimate_tile`'s wall seconds, summed over tiles (core-seconds).
    compute_s: f64,
    /// The whole pass's wall seconds, chunk reads included.
    wall_s: f64,
    points: u64,
    copies: u64,
    /// The most point copies in one tile.
    largest: u64,
    /// `estimate_tile`'s thread CPU seconds, summed over tiles (NaN where unavailable).
    cpu_s: f64,
    /// `None` where the kernel's figures cannot be read.
    kernel: Option<ThreadKernelUse>,
}

impl Default for EstimatePass {
    fn default() -> Self {
        let kernel = Some(ThreadKernelUse::default());
        Self { compute_s: 0.0, wall_s: 0.0, points: 0, copies: 0, largest: 0, cpu_s: 0.0, kernel }
    }
}

impl EstimatePass {
    fn plus(self, tile: Self) -> Self {
        Self {
            compute_s: self.compute_s + tile.compute_s,
            wall_s: self.wall_s + tile.wall_s,
            points: self.points + tile.points,
            copies: self.copies + tile.copies,
            largest: self.largest.max(tile.largest),
            cpu_s: self.cpu_s + tile.cpu_s,
            kernel: self.kernel.zip(tile.kernel).map(|(a, b)| a.plus(b)),
        }
    }
}

/// A thread's minor page faults and its user and kernel CPU in clock ticks
/// (`/proc/thread-self/stat`), read before and after a task.
#[derive(Clone, Copy, Debug, Default)]
struct ThreadKernelUse {
    minor_faults: u64,
    user_ticks: u64,
    system_ticks: u64,
}

impl ThreadKernelUse {
    /// `None` where there is no such file.
    fn now() -> Option<Self> {
        // minflt, utime and stime.
        let [minor_faults, user_ticks, system_ticks] = proc_stat_fields("/proc/thread-self/stat", [10, 14, 15])?;
        Some(Self { minor_faults, user_ticks, system_ticks })
    }

    /// What the thread used since `before` was read.
    fn since(before: Option<Self>) -> Option<Self> {
        let (before, after) = (before?, Self::now()?);
        Some(Self {
            minor_faults: after.minor_faults.saturating_sub(before.minor_faults),
            user_ticks: after.user_ticks.saturating_sub(before.user_ticks),
            system_ticks: after.system_ticks.saturating_sub(before.system_ticks),
        })
    }

    fn plus(self, other: Self) -> Self {
        Self {
            minor_faults: self.minor_faults + other.minor_faults,
            user_ticks: self.user_ticks + other.user_ticks,
            system_ticks: self.system_ticks + other.system_ticks,
        }
    }

    fn system_share(&self) -> f64 {
        match self.user_ticks + self.system_ticks {
            0 => f64::NAN,
            all => self.system_ticks as f64 / all as f64,
        }
    }
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

#[derive(Serialize)]
struct QueueBench {
    sqlite: Vec<precimap_jobs::bench::QueueBenchFigures>,
    postgres: Vec<precimap_jobs::bench::QueueBenchFigures>,
    postgres_16_cycles_per_s: f64,
    postgres_16_claim_p99_ms: f64,
    overhead: Option<FrameworkOverhead>,
}

#[derive(Serialize)]
struct FrameworkOverhead {
    scale: String,
    points: u64,
    /// The fastest run of each path.
    in_process_s: f64,
    framework_s: f64,
    /// Framework / in-process wall time − 1: the geometric mean of the pairs' ratios (orders
    /// alternate, so a drift of the machine through the runs cancels over pairs of pairs).
    overhead_ratio: f64,
    /// Standard error of `overhead_ratio` from the pairs' spread (0 with one pair).
    overhead_ratio_se: f64,
    /// CPU seconds (all threads of this process: the embedded framework runs its executors
    /// in-process) of each run, and their ratio: the work the framework adds, independent of
    /// what else the machine is doing, whereas the wall-time ratio also holds stage tails (idle
    /// cores at barriers) and other load.
    in_process_cpu_s: f64,
    framework_cpu_s: f64,
    /// As `overhead_ratio`, of CPU seconds.
    overhead_cpu_ratio: f64,
    overhead_cpu_ratio_se: f64,
    /// Every pair in order: (in-process wall, framework wall, in-process CPU, framework CPU)
    /// seconds; `framework_first` says which ran first in each.
    runs: Vec<[f64; 4]>,
    framework_first: Vec<bool>,
}

/// The geometric mean of `ratios` − 1 and its standard error (delta method on the log ratios).
fn mean_ratio(ratios: impl Iterator<Item = f64>) -> (f64, f64) {
    let logs: Vec<f64> = ratios.map(f64::ln).collect();
    let n = logs.len() as f64;
    let mean = logs.iter().sum::<f64>() / n;
    let se = if logs.len() > 1 {
        (logs.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / (n - 1.0) / n).sqrt()
    } else {
        0.0
    };
    (mean.exp() - 1.0, se * mean.exp())
}

fn bench_queue(
    postgres: &str,
    tasks: usize,
    options: precimap_jobs::bench::QueueBenchOptions,
    overhead: Option<(precimap_sim::Scale, usize)>,
    cache: &Path,
    json: bool,
) -> Result<()> {
    let rt = tokio::runtime::Runtime::new()?;
    let mut sqlite = Vec::new();
    let mut pg = Vec::new();
    for claimers in [1, 4, 16] {
        let f = rt.block_on(precimap_jobs::bench::queue_bench_with("sqlite://", claimers, tasks, options))?;
        if !json {
            eprintln!("sqlite     {claimers:>2} claimers: {}", queue_figures(&f));
        }
        sqlite.push(f);
        let f = rt
            .block_on(precimap_jobs::bench::queue_bench_with(postgres, claimers, tasks, options))
            .with_context(|| format!("PostgreSQL at {postgres}"))?;
        if !json {
            eprintln!("postgresql {claimers:>2} claimers: {}", queue_figures(&f));
        }
        pg.push(f);
    }
    let overhead = match overhead {
        None => None,
        Some((scale, runs)) => {
            let (dir, manifest) = cached_campaign(cache, scale, 1, false)?;
            let mut points = 0;
            let mut measured = Vec::with_capacity(runs);
            let mut framework_first = Vec::with_capacity(runs);
            for run in 1..=runs {
                let in_process_run = || -> Result<(f64, f64, u64)> {
                    let started = Instant::now();
                    let cpu_started = cpu_seconds();
                    let report = precimap_pipeline::run_campaign(
                        &manifest,
                        &precimap_pipeline::RunOptions {
                            out_dir: dir.join("out-in-process"),
                            keep_work: false,
                            assignments: false,
                        },
                        &|_| {},
                    )?;
                    Ok((started.elapsed().as_secs_f64(), cpu_seconds() - cpu_started, report.points_total))
                };
                let framework_run = || -> Result<(f64, f64)> {
                    let started = Instant::now();
                    let cpu_started = cpu_seconds();
                    let options = precimap_framework::EmbeddedOptions {
                        out_dir: dir.join("out-framework"),
                        concurrency: rayon::current_num_threads(),
                        keep_state: false,
                    };
                    rt.block_on(precimap_framework::run_embedded(&manifest, &options, |_| {}))?;
                    Ok((started.elapsed().as_secs_f64(), cpu_seconds() - cpu_started))
                };
                let first = run % 2 == 0;
                let ((ip_wall, ip_cpu, ip_points), framework) = if first {
                    let f = framework_run()?;
                    (in_process_run()?, f)
                } else {
                    let i = in_process_run()?;
                    (i, framework_run()?)
                };
                points = ip_points;
                let in_process = (ip_wall, ip_cpu);
                framework_first.push(first);
                if !json {
                    eprintln!(
                        "  pair {run}/{runs} ({} first): wall in-process {:.1} s, framework {:.1} s ({:+.1} %); CPU {:.1} s, {:.1} s ({:+.1} %)",
                        if first { "framework" } else { "in-process" },
                        in_process.0,
                        framework.0,
                        100.0 * (framework.0 / in_process.0 - 1.0),
                        in_process.1,
                        framework.1,
                        100.0 * (framework.1 / in_process.1.max(1e-9) - 1.0)
                    );
                }
                measured.push([in_process.0, framework.0, in_process.1, framework.1]);
            }
            let fastest = |k: usize| measured.iter().map(|r| r[k]).fold(f64::INFINITY, f64::min);
            let (in_process_s, framework_s) = (fastest(0), fastest(1));
            let (in_process_cpu_s, framework_cpu_s) = (fastest(2), fastest(3));
            let (overhead_ratio, overhead_ratio_se) = mean_ratio(measured.iter().map(|r| r[1] / r[0]));
            let (overhead_cpu_ratio, overhead_cpu_ratio_se) =
                mean_ratio(measured.iter().map(|r| r[3] / r[2].max(1e-9)));
            let o = FrameworkOverhead {
                scale: format!("{scale:?}").to_lowercase(),
                points,
                in_process_s,
                framework_s,
                overhead_ratio,
                overhead_ratio_se,
                in_process_cpu_s,
                framework_cpu_s,
                overhead_cpu_ratio,
                overhead_cpu_ratio_se,
                runs: measured,
                framework_first,
            };
            if !json {
                eprintln!(
                    "framework overhead on {} over {runs} pairs (orders alternating): wall {:+.1} % (standard error \
                     {:.1} %), CPU {:+.1} % ({:.1} %); fastest wall in-process {:.1} s, framework {:.1} s",
                    o.scale,
                    100.0 * o.overhead_ratio,
                    100.0 * o.overhead_ratio_se,
                    100.0 * o.overhead_cpu_ratio,
                    100.0 * o.overhead_cpu_ratio_se,
                    o.in_process_s,
                    o.framework_s
                );
            }
            Some(o)
        }
    };
    let last = pg.last().cloned();
    let result = QueueBench {
        postgres_16_cycles_per_s: last.as_ref().map_or(0.0, |f| f.cycles_per_s),
        postgres_16_claim_p99_ms: last.as_ref().map_or(0.0, |f| f.claim_p99_ms),
        sqlite,
        postgres: pg,
        overhead,
    };
    if json {
        outln!("{}", serde_json::to_string_pretty(&result)?);
    }
    Ok(())
}

/// One line of queue figures: cycles/s, claim and completion latency, CPU per cycle.
fn queue_figures(f: &precimap_jobs::bench::QueueBenchFigures) -> String {
    format!(
        "{:>7.0} cycles/s, claim p50 {:.2} ms, p99 {:.2} ms, completion p99 {:.2} ms, {}",
        f.cycles_per_s,
        f.claim_p50_ms,
        f.claim_p99_ms,
        f.complete_p99_ms,
        cpu_per_cycle(f)
    )
}

/// "CPU per cycle: client … ms, server … ms" with what the bench could measure.
fn cpu_per_cycle(f: &precimap_jobs::bench::QueueBenchFigures) -> String {
    let ms = |v: Option<f64>| v.map_or("n/a".to_string(), |v| format!("{v:.3} ms"));
    format!("CPU per cycle: client {}, server {}", ms(f.client_cpu_ms_per_cycle), ms(f.server_cpu_ms_per_cycle))
}

/// A simulated benchmark campaign, written once into `cache` and reused by later runs; returns its
/// folder and its manifest.
fn cached_campaign(cache: &Path, scale: precimap_sim::Scale, seed: u64, laz: bool) -> Result<(PathBuf, PathBuf)> {
    let suffix = if laz { "-laz" } else { "" };
    let dir = cache.join(format!("{scale:?}-{seed}{suffix}").to_lowercase());
    let manifest = dir.join("campaign").join("manifest.json");
    if !manifest.exists() {
        eprintln!("simulating the {scale:?} campaign into {} (cached for later runs)", dir.display());
        let config = precimap_sim::SimConfig::for_scale(scale, seed);
        precimap_sim::simulate(&config, &dir.join("campaign"), laz).context("simulating")?;
    }
    Ok((dir, manifest))
}

#[cfg(test)]
mod tests {
    use super::mean_ratio;

    #[test]
    fn alternating_pairs_cancel_a_drifting_machine() {
        // True overhead 2 %; the machine gets 6 % faster with every run, so the pair whose
        // framework runs second looks 6 % better and the other 6 % worse.
        let (ratio, se) = mean_ratio([1.02 / 1.06, 1.02 * 1.06].into_iter());
        assert!((ratio - 0.02).abs() < 1e-12, "{ratio}");
        assert!(se > 0.05 && se < 0.07, "the pairs' spread shows in the error: {se}");
        let (ratio, se) = mean_ratio([1.10].into_iter());
        assert!((ratio - 0.10).abs() < 1e-12 && se == 0.0);
    }
}
