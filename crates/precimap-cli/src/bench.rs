//! `precimap bench …`: rerunnable benchmarks that print per-core throughput. The drivers are in
//! `precimap-bench`; this module parses the subcommands and prints the figures.

use anyhow::Result;
use clap::Subcommand;
use precimap_bench::estimate::EstimateRequest;
use precimap_bench::preprocess::PreprocessRequest;
use precimap_bench::queue::{QueueBenchOptions, QueueRequest};
use precimap_core::IterationStep;
use std::path::PathBuf;

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
        /// Also estimate every scanner's boresight, lever arm and range offset (unless
        /// `--parameters` sets `calibration`), and compare alternating single-thread passes with
        /// and without the calibration: what it costs the map task.
        #[arg(long)]
        calibration: bool,
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
        /// Run only the scenarios whose name (e.g. `grid/gauss_markov/4p`) contains this, or one of
        /// several comma-separated parts.
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
    /// The common-mode field's sparse solve (faer's sparse Cholesky, AMD order) on a synthetic street
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
    let note = |line: &str| eprintln!("{line}");
    match cmd {
        BenchCommand::Accuracy { filter, fast, seed, work, keep, markdown, json, parameters } => {
            let request = crate::accuracy::MatrixRequest { filter, fast, seed, work, markdown, json, keep, parameters };
            crate::accuracy::run_matrix(&request).map(|_| ())
        }
        BenchCommand::Estimate {
            scale,
            seed,
            cache,
            parameters,
            one_pass,
            calibration,
            grid,
            threshold,
            capture,
            json,
        } => {
            let step = match capture {
                true => precimap_core::params::default_schedule()[0],
                false => IterationStep::new(grid, threshold),
            };
            // The manifest's checks of a schedule step.
            let with_step = precimap_core::Parameters { schedule: vec![step], ..Default::default() };
            if let Some(problem) = with_step.problems().first() {
                anyhow::bail!("--grid / --threshold: {problem}");
            }
            let request = EstimateRequest {
                scale,
                seed,
                cache: &cache,
                parameters: parameters.as_deref(),
                step,
                one_pass,
                calibration,
            };
            let result = precimap_bench::estimate::bench_estimate(&request, &note)?;
            match json {
                true => outln!("{}", serde_json::to_string_pretty(&result)?),
                false => outln!("{}", result.text()),
            }
            Ok(())
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
            let options =
                QueueBenchOptions { durable_commits: true, durable_claims: !async_claims, combined: !separate_claims };
            let overhead = (!no_overhead).then_some((overhead_scale, overhead_runs.max(1)));
            let request = QueueRequest { postgres: &postgres, tasks, options, overhead, cache: &cache };
            // With --json only the figures are printed.
            let progress = |line: &str| {
                if !json {
                    eprintln!("{line}");
                }
            };
            let result = precimap_bench::queue::bench_queue(&request, &progress)?;
            if json {
                outln!("{}", serde_json::to_string_pretty(&result)?);
            }
            Ok(())
        }
        BenchCommand::Preprocess { scale, seed, cache, repeat, no_scaling, json } => {
            let request = PreprocessRequest { scale, seed, cache: &cache, repeat, scaling: !no_scaling };
            let result = precimap_bench::preprocess::bench_preprocess(&request, &note)?;
            match json {
                true => outln!("{}", serde_json::to_string_pretty(&result)?),
                false => outln!("{}", result.text()),
            }
            Ok(())
        }
        BenchCommand::Solve { anchors, json } => {
            let rate = precimap_bench::solve::bench_solve(anchors, 5);
            if json {
                outln!("{}", serde_json::json!({ "solve_anchors_per_s_per_core": rate, "anchors": anchors }));
            } else {
                outln!("block-tridiagonal solve: {:.2} M anchors/s per core ({anchors} anchors)", rate / 1e6);
            }
            Ok(())
        }
        BenchCommand::FieldSolve { blocks, per_node, json } => {
            let b = precimap_bench::solve::bench_street_network(blocks, per_node as usize)?;
            match json {
                true => outln!("{}", serde_json::to_string(&b)?),
                false => outln!("{}", b.text(per_node as usize)),
            }
            Ok(())
        }
    }
}

/// CPU seconds (user + system) this process has used so far (Linux; 0 elsewhere).
pub(crate) fn cpu_seconds() -> f64 {
    precimap_bench::cpu_seconds()
}
