//! The calibration's QC: its estimates as a table (`qc/calibration.csv`) and a plot
//! (`qc/calibration.svg`).

use super::{padded_range, Plot, Svg, GAP, PANEL, TOP};
use crate::calibration::CalibrationReport;

/// One line per unknown: its scanner, name, unit, estimate (the correction added to the
/// manifest's mounting), formal σ, separation, whether it was estimated, and why not.
pub fn calibration_csv(report: &CalibrationReport) -> String {
    let mut out = String::from("scanner,unknown,unit,correction,sigma,separation,estimated,held_because\n");
    for u in &report.unknowns {
        let held = u.held.as_deref().unwrap_or("").replace('"', "'");
        out.push_str(&format!(
            "{},{},{},{},{},{:.3},{},\"{held}\"\n",
            u.scanner, u.name, u.unit, u.value, u.sigma, u.separation, u.determined
        ));
    }
    out
}

/// The estimates with ±2σ, angles (mdeg) in one panel and lengths (mm) in the other, one column
/// per unknown in the report's order; held unknowns as rings.
pub fn calibration_svg(report: &CalibrationReport) -> String {
    let mut svg = Svg::new(TOP + 2.0 * (PANEL + GAP));
    let scanners: Vec<&str> = report.unknowns.iter().map(|u| u.scanner.as_str()).fold(Vec::new(), |mut v, s| {
        if !v.contains(&s) {
            v.push(s);
        }
        v
    });
    svg.title(&format!("Mounting calibration of {}: corrections to the manifest's mounting", scanners.join(", ")));
    let n = report.unknowns.len();
    let x = (0.5, n.max(1) as f64 + 0.5);
    let series = |angles: bool| -> Vec<(f64, f64, bool)> {
        report
            .unknowns
            .iter()
            .enumerate()
            .filter(|(_, u)| (u.unit == "deg") == angles)
            .flat_map(|(i, u)| {
                let v = u.value * 1e3;
                let s = 2.0 * u.sigma * 1e3;
                let held = !u.determined;
                [((i + 1) as f64, v, held), ((i + 1) as f64, v - s, true), ((i + 1) as f64, v + s, true)]
            })
            .collect()
    };
    let panels = [
        ("boresight (mdeg), with ±2σ as rings", series(true)),
        ("lever arm and range offset (mm), with ±2σ as rings", series(false)),
    ];
    for (k, (label, points)) in panels.iter().enumerate() {
        let (lo, hi) = padded_range(points.iter().map(|p| p.1).chain([-1.0, 1.0]));
        let plot = Plot { top: TOP + k as f64 * (PANEL + GAP), x, y: (lo, hi), log_y: false };
        svg.panel(&plot, label, "unknown (in the report's order; qc/calibration.csv names them)");
        svg.zero_line(&plot);
        svg.dots(&plot, points, "#1f5fbf");
    }
    svg.finish()
}
