//! `precimap bench estimate`: one estimation iteration over every tile of a simulated campaign,
//! on one thread and on all cores, with what the kernel saw (page faults, its share of the CPU).

use crate::fixtures::{cached_campaign, with_changes};
use crate::system::{peak_rss_bytes, reset_peak_rss, thread_cpu_s, ThreadKernelUse};
use crate::{BenchError, Progress};
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::{CalibrationUnknown, IterationStep, Parameters, ScannerCalibration, TileKey};
use precimap_estimate::{LatentGather, TileCalibration};
use precimap_pipeline::calibration::CalibrationState;
use precimap_pipeline::{tasks, Campaign};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What to measure.
#[derive(Clone, Debug)]
pub struct EstimateRequest<'a> {
    pub scale: precimap_sim::Scale,
    pub seed: u64,
    /// Where the simulated campaign and its tile chunks are cached between runs.
    pub cache: &'a Path,
    /// Estimation parameters to change, as a manifest's `parameters` object.
    pub parameters: Option<&'a str>,
    pub step: IterationStep,
    /// Only the single-thread pass, once.
    pub one_pass: bool,
    /// Also measure what estimating the scanners' mounting calibration costs: the chunks carry
    /// what it needs, and interleaved single-thread passes with and without it are compared.
    pub calibration: bool,
}

#[derive(Debug, Serialize)]
pub struct EstimateBench {
    pub scale: String,
    pub points_in_tiles: u64,
    pub point_copies: u64,
    pub tiles: usize,
    pub threads: usize,
    pub grid_m: f64,
    pub threshold_m: f64,
    /// The step's cells are capture columns (`--capture`).
    pub column_cells: bool,
    /// estimate_tile compute on one thread.
    pub estimate_points_per_s_single_thread: f64,
    /// estimate_tile per CPU-second actually spent on a core (thread CPU time, Linux), the
    /// fastest pass with the defaults: robust when other processes share the machine; NaN
    /// where unavailable.
    pub estimate_points_per_cpu_s: f64,
    /// Peak resident memory during the measured iterations.
    pub peak_rss_bytes: u64,
    pub largest_tile_points: u64,
    /// The single-thread pass's minor page faults (fresh pages the kernel had to map and zero)
    /// per point, inside `estimate_tile` (Linux; NaN elsewhere).
    pub minor_faults_per_point: f64,
    /// The share of that pass's thread CPU spent in the kernel (mostly those faults; Linux,
    /// in clock ticks; NaN elsewhere).
    pub system_cpu_share: f64,
    /// The passes after the first (absent with `--one-pass`).
    #[serde(flatten)]
    pub more: Option<MorePasses>,
    /// With `--calibration`: what estimating the mounting calibration costs the map task.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration: Option<CalibrationCost>,
}

/// Thread CPU of single-thread passes that estimate every scanner's boresight, lever arm and
/// range offset (at a non-zero current calibration, so that the points are corrected by it)
/// against the same passes without the calibration, on the same chunks. The passes alternate,
/// and each side's fastest counts: robust when other processes share the machine.
#[derive(Debug, Serialize)]
pub struct CalibrationCost {
    pub passes: usize,
    pub cpu_s_with: f64,
    pub cpu_s_without: f64,
    /// `cpu_s_with / cpu_s_without`.
    pub cpu_ratio: f64,
}

/// Alternating passes with and without the calibration of [`CalibrationCost`].
const CALIBRATION_PASSES: usize = 3;

/// What [`bench_estimate`]'s passes after the single-thread one measure.
#[derive(Debug, Serialize)]
pub struct MorePasses {
    /// estimate_tile compute on all cores, per core.
    pub estimate_points_per_s_per_core: f64,
    /// Including reading and decoding the tile chunks, all cores, per core.
    pub iteration_points_per_s_per_core: f64,
    pub parallel_efficiency: f64,
    /// Thread CPU of the fastest pass with the common-mode field's rows (the default) over a pass
    /// without them (`common_mode_field_m` 0): what the field costs the map task.
    pub field_cpu_ratio: f64,
    /// Thread CPU of a single-thread pass with `consistent_gradient` on over one with it off:
    /// what recording the covering triangles and their pulls costs the map task.
    pub consistent_gradient_cpu_ratio: f64,
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

/// A campaign prepared for estimation passes: its tile chunks in `work`, zero corrections.
struct PreparedTiles {
    campaign: Campaign,
    work: PathBuf,
    corrections: Vec<TrajectoryCorrections>,
    /// Each tile with the indices of the strips that have chunks in it.
    tiles: Vec<(TileKey, Vec<usize>)>,
    step: IterationStep,
    /// With `--calibration`: the campaign's calibration at a non-zero value.
    calibration: Option<CalibrationState>,
}

impl PreparedTiles {
    fn new(request: &EstimateRequest<'_>, progress: Progress<'_>) -> Result<Self, BenchError> {
        let (dir, manifest) = cached_campaign(request.cache, request.scale, request.seed, false, progress)?;
        let mut campaign = Campaign::load(&manifest)?;
        if let Some(changes) = request.parameters {
            campaign.params = with_changes(&campaign.params, changes)?;
        }
        if request.calibration && campaign.params.calibration.is_empty() {
            campaign.params.calibration.estimate =
                vec![CalibrationUnknown::Boresight, CalibrationUnknown::LeverArm, CalibrationUnknown::RangeOffset];
        }
        let calibration = match request.calibration {
            true => CalibrationState::new(&campaign).map(|mut state| {
                // A mounting error's size (the small preset's), so that every point is corrected.
                let scanner = ScannerCalibration {
                    boresight_rad: [0.05f64.to_radians(), -0.08f64.to_radians(), 0.1f64.to_radians()],
                    lever_arm_m: [0.02, -0.03, 0.05],
                    range_offset_m: 0.01,
                };
                state.scanners.iter_mut().for_each(|s| *s = scanner);
                state
            }),
            false => None,
        };
        let work = dir.join("work");
        progress(&format!("preparing tile chunks in {}", work.display()));
        let prepared = precimap_pipeline::run::prepare_all(&campaign, &work, &|_| {})?;
        let corrections = prepared.anchor_ranges.iter().map(|&(a, b)| TrajectoryCorrections::zeros(a, b)).collect();
        let tiles = prepared.tiles.iter().map(|(tile, strips)| (*tile, strips.clone())).collect();
        Ok(Self { campaign, work, corrections, tiles, step: request.step, calibration })
    }

    /// One pass over all tiles on `pool` with `params`.
    fn pass(&self, pool: &rayon::ThreadPool, params: &Parameters) -> Result<EstimatePass, BenchError> {
        self.pass_with(pool, params, None)
    }

    /// [`Self::pass`] estimating the calibration `calibration` too.
    fn pass_with(
        &self,
        pool: &rayon::ThreadPool,
        params: &Parameters,
        calibration: Option<&TileCalibration>,
    ) -> Result<EstimatePass, BenchError> {
        let started = Instant::now();
        let per_tile = pool.install(|| {
            self.tiles
                .par_iter()
                .map(|(tile, strips)| self.tile(*tile, strips, params, calibration))
                .collect::<Result<Vec<_>, _>>()
        })?;
        let sum = per_tile.into_iter().fold(EstimatePass::default(), EstimatePass::plus);
        Ok(EstimatePass { wall_s: started.elapsed().as_secs_f64(), ..sum })
    }

    /// One tile's estimate, timed.
    fn tile(
        &self,
        tile: TileKey,
        strips: &[usize],
        params: &Parameters,
        calibration: Option<&TileCalibration>,
    ) -> Result<EstimatePass, BenchError> {
        let ids: Vec<&str> = strips.iter().map(|&s| self.campaign.strips[s].id.as_str()).collect();
        let chunks = tasks::load_tile(&self.work, tile, &ids)?;
        let copies: u64 = chunks.iter().map(|c| c.len() as u64).sum();
        // The kernel's figures are read outside the timed span: their reads of /proc would count
        // as the task's CPU.
        let kernel = ThreadKernelUse::now();
        let t = Instant::now();
        let cpu = thread_cpu_s();
        let est = precimap_estimate::estimate_tile_recording(
            tile,
            &chunks,
            &self.corrections,
            params,
            &self.step,
            &[],
            calibration,
            None,
            LatentGather::default(),
        )?;
        let cpu_s = match (cpu, thread_cpu_s()) {
            (Some(a), Some(b)) => b - a,
            _ => f64::NAN,
        };
        let compute_s = t.elapsed().as_secs_f64();
        let kernel = ThreadKernelUse::since(kernel);
        let points = est.stats.points;
        Ok(EstimatePass { compute_s, wall_s: 0.0, points, copies, largest: copies, cpu_s, kernel })
    }

    /// The passes on all cores and the single-thread variants after the first pass, and the
    /// fastest CPU figure of the passes with the campaign's parameters.
    fn more_passes(&self, single: &rayon::ThreadPool, first: &EstimatePass) -> Result<(MorePasses, f64), BenchError> {
        let params = &self.campaign.params;
        let threads = rayon::current_num_threads();
        let all = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
        let (second, third) = (self.pass(&all, params)?, self.pass(&all, params)?);
        let without_field = Parameters { common_mode_field_m: 0.0, ..params.clone() };
        let gradient = |on| Parameters { consistent_gradient: on, ..params.clone() };
        let cpu_without = self.pass(single, &without_field)?.cpu_s;
        let cpu_consistent = self.pass(single, &gradient(true))?.cpu_s;
        let cpu_map_held = self.pass(single, &gradient(false))?.cpu_s;
        let wall_all = second.wall_s.min(third.wall_s);
        let fastest_cpu = first.cpu_s.min(second.cpu_s).min(third.cpu_s);
        let points = first.points as f64;
        let more = MorePasses {
            // Compute seconds are summed over tiles, i.e. core-seconds.
            estimate_points_per_s_per_core: points / third.compute_s,
            iteration_points_per_s_per_core: points / (wall_all * threads as f64),
            parallel_efficiency: (points / wall_all) / (points / first.compute_s) / threads as f64,
            // The fastest pass with the field (the first one runs cold) against the one without.
            field_cpu_ratio: fastest_cpu / cpu_without,
            consistent_gradient_cpu_ratio: cpu_consistent / cpu_map_held,
        };
        Ok((more, fastest_cpu))
    }
}

impl PreparedTiles {
    /// [`CalibrationCost`]'s alternating passes, `None` without `--calibration`.
    fn calibration_cost(&self, single: &rayon::ThreadPool) -> Result<Option<CalibrationCost>, BenchError> {
        let Some(state) = &self.calibration else { return Ok(None) };
        let tile = state.tile();
        let params = &self.campaign.params;
        let (mut with, mut without) = (f64::INFINITY, f64::INFINITY);
        for _ in 0..CALIBRATION_PASSES {
            with = with.min(self.pass_with(single, params, Some(&tile))?.cpu_s);
            without = without.min(self.pass(single, params)?.cpu_s);
        }
        Ok(Some(CalibrationCost {
            passes: CALIBRATION_PASSES,
            cpu_s_with: with,
            cpu_s_without: without,
            cpu_ratio: with / without,
        }))
    }
}

/// Runs the passes of `request`.
pub fn bench_estimate(request: &EstimateRequest<'_>, progress: Progress<'_>) -> Result<EstimateBench, BenchError> {
    let prepared = PreparedTiles::new(request, progress)?;
    let step = &request.step;
    let threads = rayon::current_num_threads();
    reset_peak_rss();
    let single = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let (grid_cm, kind) = step_label(step.grid_m, step.column_cells);
    let tiles = prepared.tiles.len();
    match request.one_pass {
        true => progress(&format!("one {grid_cm} cm{kind} iteration over {tiles} tiles on 1 thread, once")),
        false => {
            progress(&format!("one {grid_cm} cm{kind} iteration over {tiles} tiles on 1 thread, then on {threads}"))
        }
    }
    let first = prepared.pass(&single, &prepared.campaign.params)?;
    let points = first.points;
    let (more, fastest_cpu) = match request.one_pass {
        true => (None, first.cpu_s),
        false => {
            let (more, fastest) = prepared.more_passes(&single, &first)?;
            (Some(more), fastest)
        }
    };
    if prepared.calibration.is_some() {
        progress(&format!("{CALIBRATION_PASSES} single-thread passes each with and without the calibration"));
    }
    let calibration = prepared.calibration_cost(&single)?;
    Ok(EstimateBench {
        scale: format!("{:?}", request.scale).to_lowercase(),
        points_in_tiles: points,
        point_copies: first.copies,
        tiles,
        threads: if request.one_pass { 1 } else { threads },
        grid_m: step.grid_m,
        threshold_m: step.threshold_m,
        column_cells: step.column_cells,
        estimate_points_per_s_single_thread: points as f64 / first.compute_s,
        estimate_points_per_cpu_s: points as f64 / fastest_cpu,
        peak_rss_bytes: peak_rss_bytes(),
        largest_tile_points: first.largest,
        minor_faults_per_point: first.kernel.map_or(f64::NAN, |k| k.minor_faults as f64 / points as f64),
        system_cpu_share: first.kernel.map_or(f64::NAN, |k| k.system_share()),
        more,
        calibration,
    })
}

/// A step's grid in centimetres, and " capture" for a capture step's column cells.
fn step_label(grid_m: f64, column_cells: bool) -> (f64, &'static str) {
    // In centimetres to a tenth (0.07 × 100 prints as 7.000000000000001).
    let grid_cm = (grid_m * 1000.0).round() / 10.0;
    (grid_cm, if column_cells { " capture" } else { "" })
}

impl EstimateBench {
    /// The figures for a terminal.
    pub fn text(&self) -> String {
        let (grid_cm, kind) = step_label(self.grid_m, self.column_cells);
        let mut out = format!(
            "estimate_tile, {grid_cm} cm{kind} grid, {} points in {} tiles ({} copies with border overlap)\n  \
             single thread: {:.2} M points/s\n  per CPU-second on a core: {:.2} M points/s\n  \
             peak RSS {:.0} MiB (largest tile {} point copies)\n  \
             single-thread pass: {:.3} minor page faults per point, {:.1} % of its CPU in the kernel",
            self.points_in_tiles,
            self.tiles,
            self.point_copies,
            self.estimate_points_per_s_single_thread / 1e6,
            self.estimate_points_per_cpu_s / 1e6,
            self.peak_rss_bytes as f64 / (1 << 20) as f64,
            self.largest_tile_points,
            self.minor_faults_per_point,
            self.system_cpu_share * 100.0,
        );
        if let Some(more) = &self.more {
            out.push_str(&format!(
                "\n  {} threads: {:.2} M points/s per core (compute), {:.2} M points/s per core including chunk reads, parallel efficiency {:.0} %\n  \
                 common-mode field rows: {:.3}× the CPU of the same pass without them\n  \
                 consistent gradient: {:.3}× the CPU of the same pass with the map held",
                self.threads,
                more.estimate_points_per_s_per_core / 1e6,
                more.iteration_points_per_s_per_core / 1e6,
                more.parallel_efficiency * 100.0,
                more.field_cpu_ratio,
                more.consistent_gradient_cpu_ratio
            ));
        }
        if let Some(c) = &self.calibration {
            out.push_str(&format!(
                "\n  calibration (boresight, lever arm, range offset): {:.3}× the CPU of the same pass without it ({:.3} s against {:.3} s, fastest of {})",
                c.cpu_ratio, c.cpu_s_with, c.cpu_s_without, c.passes
            ));
        }
        out
    }
}
