//! Progress on the terminal: one updating line when stderr is a terminal, plain lines otherwise.

use precimap_pipeline::report::IterationReport;
use precimap_pipeline::{Progress, Report};
use std::io::{IsTerminal, Write};
use std::sync::Mutex;

pub struct Display {
    tty: bool,
    lock: Mutex<()>,
}

impl Display {
    pub fn new() -> Self {
        Self { tty: std::io::stderr().is_terminal(), lock: Mutex::new(()) }
    }

    pub fn transient(&self, line: &str) {
        let _guard = self.lock.lock();
        let mut err = std::io::stderr().lock();
        if self.tty {
            let _ = write!(err, "\r\x1b[2K{line}");
        }
        let _ = err.flush();
    }

    pub fn permanent(&self, line: &str) {
        let _guard = self.lock.lock();
        let mut err = std::io::stderr().lock();
        if self.tty {
            let _ = write!(err, "\r\x1b[2K");
        }
        let _ = writeln!(err, "{line}");
    }

    pub fn show(&self, p: Progress) {
        match p {
            Progress::Loaded { strips, trajectories } => {
                self.permanent(&format!("campaign: {strips} strips, {trajectories} trajectories"))
            }
            Progress::Prepared { done, total } => {
                self.transient(&format!("preparing strips {done}/{total}"));
                if done == total {
                    self.permanent(&format!("prepared {total} strips"));
                }
            }
            Progress::Iteration(it, total) => self.iteration(&it, total),
            Progress::Exported { done, total } => {
                self.transient(&format!("exporting strips {done}/{total}"));
                if done == total {
                    self.permanent(&format!("exported {total} strips"));
                }
            }
        }
    }

    pub fn iteration(&self, it: &IterationReport, total: usize) {
        self.permanent(&format!(
            "iteration {:>2}/{total}  grid {:>4.1} cm  threshold {:>5.1} mm  used {:>10}  residual σ {:>6.2} mm  change median {:>6.2} max {:>7.2} mm{}{}  ({:.1} s)",
            it.iteration,
            it.grid_m * 100.0,
            it.threshold_m * 1000.0,
            it.points_used,
            it.residual_std_m * 1000.0,
            it.median_correction_change_m * 1000.0,
            it.max_correction_change_m * 1000.0,
            it.max_correction_change_at
                .as_ref()
                .map_or(String::new(), |at| format!(" ({at})")),
            // Started from Anderson's combination of the last k + 1 settling iterations.
            match it.anderson_coefficients.len() {
                0 => String::new(),
                k => format!("  accelerated over {} iterations", k + 1),
            },
            it.seconds
        ))
    }

    pub fn finish(&self, report: &Report) {
        self.permanent(&format!(
            "done: {} points, {} tiles, {} iterations{}, {:.1} s (prepare {:.1} s, estimate {:.1} s, export {:.1} s{})",
            report.points_total,
            report.tiles,
            report.iterations.len(),
            if report.converged { " (converged)" } else { "" },
            report.timings.total_s,
            report.timings.prepare_s,
            report.timings.estimate_s,
            report.timings.export_s,
            report.timings.task_s.map(|s| format!("; {s:.1} task-seconds")).unwrap_or_default()
        ));
        self.permanent(&format!("datum: {}", report.control.datum));
        let mm = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{:.1}", v * 1e3));
        for (role, figures) in [("control", &report.control.control), ("check", &report.control.check)] {
            if let Some(f) = figures {
                self.permanent(&format!(
                    "{role} targets: {} of {} observed; RMSE x {} y {} horizontal {} z {} mm (qc/control.csv)",
                    f.targets_observed,
                    f.targets_listed,
                    mm(f.rmse_x_m),
                    mm(f.rmse_y_m),
                    mm(f.rmse_horizontal_m),
                    mm(f.rmse_z_m)
                ));
            }
        }
        if let Some(calibration) = &report.calibration {
            self.calibration(calibration);
        }
    }

    /// One line per scanner: its estimated corrections, and the unknowns held.
    fn calibration(&self, calibration: &precimap_pipeline::calibration::CalibrationReport) {
        let mut scanners: Vec<&str> = Vec::new();
        for u in &calibration.unknowns {
            if !scanners.contains(&u.scanner.as_str()) {
                scanners.push(&u.scanner);
            }
        }
        for scanner in scanners {
            let (estimated, held): (Vec<_>, Vec<_>) =
                calibration.unknowns.iter().filter(|u| u.scanner == scanner).partition(|u| u.determined);
            let value = |u: &&precimap_pipeline::calibration::CalibrationEstimate| match u.unit.as_str() {
                "deg" => format!("{} {:+.4}°", u.name, u.value),
                _ => format!("{} {:+.1} mm", u.name, u.value * 1e3),
            };
            let mut line =
                format!("calibration of {scanner}: {}", estimated.iter().map(value).collect::<Vec<_>>().join(", "));
            if !held.is_empty() {
                line += &format!(
                    "; held (not separated from the trajectories): {}",
                    held.iter().map(|u| u.name.as_str()).collect::<Vec<_>>().join(", ")
                );
            }
            self.permanent(&format!("{line} (qc/calibration.csv)"));
        }
    }
}
