//! The job framework's overhead: the same simulated campaign run in-process and through the
//! embedded framework, in pairs whose order alternates.

use crate::fixtures::cached_campaign;
use crate::system::cpu_seconds;
use crate::{BenchError, Progress};
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

#[derive(Debug, Serialize)]
pub struct FrameworkOverhead {
    pub scale: String,
    pub points: u64,
    /// The fastest run of each path.
    pub in_process_s: f64,
    pub framework_s: f64,
    /// Framework / in-process wall time − 1: the geometric mean of the pairs' ratios (orders
    /// alternate, so a drift of the machine through the runs cancels over pairs of pairs).
    pub overhead_ratio: f64,
    /// Standard error of `overhead_ratio` from the pairs' spread (0 with one pair).
    pub overhead_ratio_se: f64,
    /// CPU seconds (all threads of this process: the embedded framework runs its executors
    /// in-process) of each run, and their ratio: the work the framework adds, independent of
    /// what else the machine is doing, whereas the wall-time ratio also holds stage tails (idle
    /// cores at barriers) and other load.
    pub in_process_cpu_s: f64,
    pub framework_cpu_s: f64,
    /// As `overhead_ratio`, of CPU seconds.
    pub overhead_cpu_ratio: f64,
    pub overhead_cpu_ratio_se: f64,
    /// Every pair in order: (in-process wall, framework wall, in-process CPU, framework CPU)
    /// seconds; `framework_first` says which ran first in each.
    pub runs: Vec<[f64; 4]>,
    pub framework_first: Vec<bool>,
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

/// The campaign in-process: (wall seconds, CPU seconds, points).
fn in_process_run(manifest: &Path, dir: &Path) -> Result<(f64, f64, u64), BenchError> {
    let started = Instant::now();
    let cpu_started = cpu_seconds();
    let options =
        precimap_pipeline::RunOptions { out_dir: dir.join("out-in-process"), keep_work: false, assignments: false };
    let report = precimap_pipeline::run_campaign(manifest, &options, &|_| {})?;
    Ok((started.elapsed().as_secs_f64(), cpu_seconds() - cpu_started, report.points_total))
}

/// The campaign through the embedded framework: (wall seconds, CPU seconds).
fn framework_run(rt: &tokio::runtime::Runtime, manifest: &Path, dir: &Path) -> Result<(f64, f64), BenchError> {
    let started = Instant::now();
    let cpu_started = cpu_seconds();
    let options = precimap_framework::EmbeddedOptions {
        out_dir: dir.join("out-framework"),
        concurrency: rayon::current_num_threads(),
        keep_state: false,
    };
    rt.block_on(precimap_framework::run_embedded(manifest, &options, |_| {}))?;
    Ok((started.elapsed().as_secs_f64(), cpu_seconds() - cpu_started))
}

/// `runs` pairs of runs of the simulated campaign of `scale` (seed 1), in-process first in odd
/// pairs; each pair's line goes to `progress`.
pub fn measure_overhead(
    rt: &tokio::runtime::Runtime,
    cache: &Path,
    scale: precimap_sim::Scale,
    runs: usize,
    progress: Progress<'_>,
) -> Result<FrameworkOverhead, BenchError> {
    let (dir, manifest) = cached_campaign(cache, scale, 1, false, progress)?;
    let mut points = 0;
    let mut measured = Vec::with_capacity(runs);
    let mut framework_first = Vec::with_capacity(runs);
    for run in 1..=runs {
        let first = run % 2 == 0;
        let ((ip_wall, ip_cpu, ip_points), framework) = if first {
            let f = framework_run(rt, &manifest, &dir)?;
            (in_process_run(&manifest, &dir)?, f)
        } else {
            let i = in_process_run(&manifest, &dir)?;
            (i, framework_run(rt, &manifest, &dir)?)
        };
        points = ip_points;
        let in_process = (ip_wall, ip_cpu);
        framework_first.push(first);
        progress(&format!(
            "  pair {run}/{runs} ({} first): wall in-process {:.1} s, framework {:.1} s ({:+.1} %); CPU {:.1} s, {:.1} s ({:+.1} %)",
            if first { "framework" } else { "in-process" },
            in_process.0,
            framework.0,
            100.0 * (framework.0 / in_process.0 - 1.0),
            in_process.1,
            framework.1,
            100.0 * (framework.1 / in_process.1.max(1e-9) - 1.0)
        ));
        measured.push([in_process.0, framework.0, in_process.1, framework.1]);
    }
    let fastest = |k: usize| measured.iter().map(|r| r[k]).fold(f64::INFINITY, f64::min);
    let (overhead_ratio, overhead_ratio_se) = mean_ratio(measured.iter().map(|r| r[1] / r[0]));
    let (overhead_cpu_ratio, overhead_cpu_ratio_se) = mean_ratio(measured.iter().map(|r| r[3] / r[2].max(1e-9)));
    let o = FrameworkOverhead {
        scale: format!("{scale:?}").to_lowercase(),
        points,
        in_process_s: fastest(0),
        framework_s: fastest(1),
        overhead_ratio,
        overhead_ratio_se,
        in_process_cpu_s: fastest(2),
        framework_cpu_s: fastest(3),
        overhead_cpu_ratio,
        overhead_cpu_ratio_se,
        runs: measured,
        framework_first,
    };
    progress(&format!(
        "framework overhead on {} over {runs} pairs (orders alternating): wall {:+.1} % (standard error \
         {:.1} %), CPU {:+.1} % ({:.1} %); fastest wall in-process {:.1} s, framework {:.1} s",
        o.scale,
        100.0 * o.overhead_ratio,
        100.0 * o.overhead_ratio_se,
        100.0 * o.overhead_cpu_ratio,
        100.0 * o.overhead_cpu_ratio_se,
        o.in_process_s,
        o.framework_s
    ));
    Ok(o)
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
