//! `precimap bench preprocess`: strip pre-processing (LAZ decoding, geometry, scan image, RANSAC
//! normals, segmentation, tiling and chunk encoding) on a simulated LAZ campaign, per phase, and
//! the segmentation and normals against the simulator's truth.

use crate::fixtures::cached_campaign;
use crate::system::{cpu_seconds, peak_rss_bytes, reset_peak_rss, thread_cpu_s};
use crate::{BenchError, Progress};
use precimap_estimate::{PreparePhase, SegmentParams};
use precimap_eval::{NormalTally, SegmentEvaluation, SegmentTally};
use precimap_pipeline::{tasks, Campaign};
use rayon::prelude::*;
use serde::Serialize;
use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

/// What to measure.
#[derive(Clone, Debug)]
pub struct PreprocessRequest<'a> {
    pub scale: precimap_sim::Scale,
    pub seed: u64,
    /// Where the simulated LAZ campaign is cached between runs.
    pub cache: &'a Path,
    /// Full passes to run; the figures are the fastest.
    pub repeat: usize,
    /// Also the passes over 2, 4, 8, … strips (cost per point against strip count).
    pub scaling: bool,
}

#[derive(Debug, Serialize)]
pub struct PreprocessBench {
    pub scale: String,
    pub strips: usize,
    pub points: u64,
    pub threads: usize,
    /// Full passes run; the figures below are the fastest of them (`--repeat`).
    pub repeat: usize,
    /// All strips on all cores (rayon over strips), LAZ decoding included: points per CPU-second
    /// of this process (robust on a shared machine).
    pub preprocess_points_per_s_per_core: f64,
    /// The same per wall-second × threads (lower when other processes share the cores).
    pub preprocess_points_per_s_per_core_wall: f64,
    /// Peak resident memory while preprocessing (threads strips in flight at once).
    pub peak_rss_bytes: u64,
    pub largest_strip_points: u64,
    /// Emitted point copies (border duplicates included) per point segmented, minus one.
    pub border_overhead: f64,
    pub chunk_bytes_per_point_copy: f64,
    pub chunk_bytes_total: u64,
    /// (strips, CPU nanoseconds per point) for the first n strips.
    pub cost_per_point_ns: Vec<(usize, f64)>,
    /// Where the time goes: per phase (decode, geometry, scan image, normals, segmentation,
    /// tiling, encode), thread CPU nanoseconds per point of the full pass (Linux schedstat; NaN
    /// elsewhere). Their sum is a little below the process figure above (which also counts the
    /// thread pool and the allocator's returns to the kernel).
    pub phase_cpu_ns_per_point: Vec<PhaseFigure>,
    /// Angle between the estimated and the true normal over surface points with a normal.
    pub normal_error_deg_mean: f64,
    pub normals: precimap_eval::NormalEvaluation,
    pub segment_purity: f64,
    pub surface_points_removed: f64,
    pub foliage_points_removed: f64,
    pub segmentation: SegmentEvaluation,
    /// The process's CPU seconds of the fastest full pass (for the text's phase sum).
    #[serde(skip)]
    pub cpu_s: f64,
    /// The phases' thread CPU seconds of the fastest full pass, summed.
    #[serde(skip)]
    pub phase_sum_s: f64,
}

#[derive(Debug, Serialize)]
pub struct PhaseFigure {
    pub phase: &'static str,
    pub cpu_ns_per_point: f64,
    /// Share of the phases' sum.
    pub share: f64,
}

/// Thread CPU seconds per [`PreparePhase`] (indexed by the enum's order).
type PhaseSeconds = [f64; PreparePhase::ALL.len()];

/// One preprocessing pass over the first strips.
#[derive(Clone, Copy, Debug)]
struct Pass {
    wall_s: f64,
    cpu_s: f64,
    points: u64,
    copies: u64,
    chunk_bytes: u64,
    largest: u64,
    phases: PhaseSeconds,
}

/// One strip's figures: points, copies, chunk bytes, thread CPU seconds per phase.
type StripFigures = (u64, u64, u64, PhaseSeconds);

/// Prepares strip `s` on the calling thread, its thread CPU time split into phases.
fn prepare_strip(campaign: &Campaign, s: usize, params: &SegmentParams) -> Result<StripFigures, BenchError> {
    let mut phases: PhaseSeconds = [0.0; PreparePhase::ALL.len()];
    let mut mark = thread_cpu_s().unwrap_or(f64::NAN);
    let mut phase_done = |p: PreparePhase| {
        let now = thread_cpu_s().unwrap_or(f64::NAN);
        phases[p as usize] += now - mark;
        mark = now;
    };
    let prepared = tasks::prepare_strip_in_memory_observed(campaign, s, params, &mut phase_done)?;
    let bytes: u64 = prepared.chunks.iter().map(|c| c.encode().len() as u64).sum();
    phase_done(PreparePhase::Encode);
    Ok((prepared.stats.points, prepared.stats.points_emitted, bytes, phases))
}

/// One pass over the first `n` strips, on all cores (rayon over strips).
fn pass(campaign: &Campaign, params: &SegmentParams, n: usize) -> Result<Pass, BenchError> {
    let started = Instant::now();
    let cpu_start = cpu_seconds();
    let per_strip =
        (0..n).into_par_iter().map(|s| prepare_strip(campaign, s, params)).collect::<Result<Vec<_>, _>>()?;
    let wall_s = started.elapsed().as_secs_f64();
    let cpu_s = cpu_seconds() - cpu_start;
    let mut phases: PhaseSeconds = [0.0; PreparePhase::ALL.len()];
    for r in &per_strip {
        for (sum, s) in phases.iter_mut().zip(&r.3) {
            *sum += s;
        }
    }
    Ok(Pass {
        wall_s,
        cpu_s,
        points: per_strip.iter().map(|r| r.0).sum(),
        copies: per_strip.iter().map(|r| r.1).sum(),
        chunk_bytes: per_strip.iter().map(|r| r.2).sum(),
        largest: per_strip.iter().map(|r| r.0).max().unwrap_or(0),
        phases,
    })
}

/// The segmentation and the normals of every strip against the simulator's truth in `truth`.
fn against_truth(
    campaign: &Campaign,
    params: &SegmentParams,
    truth: &Path,
) -> Result<(SegmentEvaluation, precimap_eval::NormalEvaluation), BenchError> {
    let evaluated = (0..campaign.strips.len())
        .into_par_iter()
        .map(|s| -> Result<(SegmentTally, NormalTally), BenchError> {
            let prepared = tasks::prepare_strip_in_memory(campaign, s, params)?;
            let path = truth.join(format!("{}.truth", campaign.strips[s].id));
            let mut reader = precimap_sim::truth::TruthReader::open(&path)?;
            let mut tally = SegmentTally::default();
            let mut normals = NormalTally::default();
            let mut k = 0usize;
            while let Some(t) = reader.next_point()? {
                let id = *prepared.segment.get(k).ok_or_else(|| BenchError::TruthLonger { path: path.clone() })?;
                tally.add(id, t.surface_id, t.class, t.normal, t.position);
                // Points of revolutions dropped at standstill are never given a normal.
                if id != precimap_estimate::DROPPED_SEGMENT {
                    normals.add(t.class, prepared.normals[k].map(|n| n.normal), t.normal);
                }
                k += 1;
            }
            Ok((tally, normals))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut normal_tally = NormalTally::default();
    for (_, n) in &evaluated {
        normal_tally.merge(n);
    }
    let tallies: Vec<_> = evaluated.into_iter().map(|(t, _)| t).collect();
    Ok((SegmentEvaluation::from_tallies(&tallies), normal_tally.evaluate()))
}

/// Runs the passes of `request`.
pub fn bench_preprocess(
    request: &PreprocessRequest<'_>,
    progress: Progress<'_>,
) -> Result<PreprocessBench, BenchError> {
    let (dir, manifest) = cached_campaign(request.cache, request.scale, request.seed, true, progress)?;
    let campaign = Campaign::load(&manifest)?;
    let threads = rayon::current_num_threads();
    let params = SegmentParams::default();
    let strips = campaign.strips.len();
    let repeat = request.repeat.max(1);
    reset_peak_rss();
    progress(&format!("preprocessing {strips} strips on {threads} threads"));
    let mut best = pass(&campaign, &params, strips)?;
    let peak = peak_rss_bytes();
    for _ in 1..repeat {
        let again = pass(&campaign, &params, strips)?;
        (best.wall_s, best.cpu_s) = (best.wall_s.min(again.wall_s), best.cpu_s.min(again.cpu_s));
        for (b, p) in best.phases.iter_mut().zip(again.phases) {
            *b = b.min(p);
        }
    }
    let Pass { wall_s: wall, cpu_s: cpu, points, copies, chunk_bytes: bytes, largest, phases } = best;
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
    while request.scaling && n <= strips {
        let p = pass(&campaign, &params, n)?;
        progress(&format!("  {n} strips: {:.1} CPU ns per point", p.cpu_s / p.points as f64 * 1e9));
        cost_per_point_ns.push((n, p.cpu_s / p.points as f64 * 1e9));
        n *= 2;
    }
    // The segmentation and the normals against the simulator's truth, in a pass of its own
    // (untimed, so that the figures above cover pre-processing alone, memory included).
    let (segmentation, normals) = against_truth(&campaign, &params, &dir.join("campaign").join("truth"))?;
    let segmented: u64 = segmentation.points_segmented;
    Ok(PreprocessBench {
        scale: format!("{:?}", request.scale).to_lowercase(),
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
        cpu_s: cpu,
        phase_sum_s: phase_sum,
    })
}

impl PreprocessBench {
    /// The figures for a terminal.
    pub fn text(&self) -> String {
        let mut out = format!(
            "preprocess (LAZ → tile chunks), {} points in {} strips\n  {:.2} M points/s per core on {} threads, \
             peak RSS {:.0} MiB (largest strip {} points)\n  {:.1} chunk bytes per point copy, border overhead {:.1} %\n  \
             segment purity {:.2} %, surface points removed {:.2} %, foliage points removed {:.1} %",
            self.points,
            self.strips,
            self.preprocess_points_per_s_per_core / 1e6,
            self.threads,
            self.peak_rss_bytes as f64 / (1 << 20) as f64,
            self.largest_strip_points,
            self.chunk_bytes_per_point_copy,
            self.border_overhead * 100.0,
            self.segment_purity * 100.0,
            self.surface_points_removed * 100.0,
            self.foliage_points_removed * 100.0
        );
        let _ = write!(out, "\n  normals vs truth (surface points; with normal, mean / p50 / p95 angle):");
        for (class, f) in std::iter::once(("all", &self.normals.surfaces))
            .chain(self.normals.per_class.iter().map(|(c, f)| (c.as_str(), f)))
        {
            let _ = write!(
                out,
                "\n    {class:<9} {:>5.1} %  {:>5.2}° / {:>5.2}° / {:>5.2}°",
                f.with_normal_share * 100.0,
                f.mean_deg,
                f.p50_deg,
                f.p95_deg
            );
        }
        let _ = write!(out, "\n  thread CPU per point by phase (full pass, fastest of {}):", self.repeat);
        for f in &self.phase_cpu_ns_per_point {
            let _ = write!(out, "\n    {:<13} {:>7.1} ns  {:>5.1} %", f.phase, f.cpu_ns_per_point, f.share * 100.0);
        }
        let _ = write!(
            out,
            "\n    {:<13} {:>7.1} ns  (process: {:.1} ns)",
            "sum",
            self.phase_sum_s / self.points.max(1) as f64 * 1e9,
            self.cpu_s / self.points.max(1) as f64 * 1e9
        );
        out
    }
}
