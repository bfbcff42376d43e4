//! precimap's QC plot writer (`precimap_pipeline::qc`) against `plotters` with its SVG backend,
//! on the largest QC plot: a trajectory's six correction panels. Both draw the same series (the
//! per-pixel-column envelope precimap draws, so plotters is not charged for 20,000 vertices a
//! panel) with titles and axis labels like precimap's; the figures are the SVG's size and the time to
//! write it.

use plotters::prelude::*;
use precimap_pipeline::qc::corrections_svg;
use precimap_pipeline::tasks::VehicleCorrection;
use precimap_sim::rng::Rng;
use std::time::Instant;

const PANELS: [&str; 6] = [
    "along-track translation (mm)",
    "across-track translation (to the left) (mm)",
    "vertical translation (mm)",
    "roll (mdeg)",
    "pitch (mdeg)",
    "heading (mdeg)",
];

/// A trajectory of `n` anchors every metre with random-walk corrections (a few cm, a few mdeg).
fn rows(n: usize) -> Vec<VehicleCorrection> {
    let mut rng = Rng::new(0x5EED, 1);
    let mut walk = [0.0f64; 6];
    (0..n)
        .map(|i| {
            for (k, w) in walk.iter_mut().enumerate() {
                *w += if k < 3 { 1e-3 } else { 2e-6 } * rng.normal();
            }
            VehicleCorrection {
                anchor: i as u32,
                arc_m: i as f64,
                time: i as f64 * 0.1,
                position: Default::default(),
                values: walk,
                sigma: Some([5e-3, 5e-3, 5e-3, 1e-5, 1e-5, 1e-5]),
                estimated: true,
            }
        })
        .collect()
}

/// Minimum and maximum per horizontal pixel column, as precimap's plot draws a long series.
fn envelope(values: &[f64], columns: usize) -> Vec<(f64, f64)> {
    if values.len() <= 2 * columns {
        return values.iter().enumerate().map(|(i, &v)| (i as f64, v)).collect();
    }
    let mut out = Vec::with_capacity(2 * columns);
    for c in 0..columns {
        let (a, b) = (c * values.len() / columns, (c + 1) * values.len() / columns);
        let (lo, hi) = values[a..b].iter().enumerate().fold((a, a), |(lo, hi), (i, &v)| {
            (if v < values[lo] { a + i } else { lo }, if v > values[hi] { a + i } else { hi })
        });
        for i in if lo <= hi { [lo, hi] } else { [hi, lo] } {
            out.push((i as f64, values[i]));
        }
    }
    out
}

fn plotters_svg(rows: &[VehicleCorrection]) -> Result<String, Box<dyn std::error::Error>> {
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (960, 1052)).into_drawing_area();
        root.fill(&WHITE)?;
        let root = root.titled(
            &format!("Corrections of trajectory T in the vehicle's frame ({} anchors every 1 m)", rows.len()),
            ("sans-serif", 15),
        )?;
        for (k, area) in root.split_evenly((6, 1)).iter().enumerate() {
            let scale = if k < 3 { 1e3 } else { 1e3 * 180.0 / std::f64::consts::PI };
            let values: Vec<f64> = rows.iter().map(|r| r.values[k] * scale).collect();
            let rms = (values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64).sqrt();
            let (lo, hi) = values.iter().fold((0.0f64, 0.0f64), |(l, h), &v| (l.min(v), h.max(v)));
            let mut chart = ChartBuilder::on(area)
                .caption(format!("{}: RMS {rms:.3}", PANELS[k]), ("sans-serif", 12))
                .x_label_area_size(28)
                .y_label_area_size(60)
                .build_cartesian_2d(0.0..rows.len() as f64, lo..hi)?;
            chart.configure_mesh().x_desc("arc length (m)").draw()?;
            chart.draw_series(LineSeries::new(envelope(&values, 858), &RGBColor(0x1f, 0x5f, 0xbf)))?;
        }
        root.present()?;
    }
    Ok(out)
}

/// The output of `f` and its least wall time (seconds) over `repeats` calls (milliseconds each:
/// below the resolution of a thread's CPU time).
fn best_of(repeats: usize, mut f: impl FnMut() -> String) -> (String, f64) {
    let mut best = (String::new(), f64::INFINITY);
    for _ in 0..repeats {
        let start = Instant::now();
        let out = f();
        let s = start.elapsed().as_secs_f64();
        if s < best.1 {
            best = (out, s);
        }
    }
    best
}

pub fn run(anchors: usize) {
    let rows = rows(anchors);
    println!("# QC plot: a trajectory's six correction panels, {anchors} anchors");
    let (ours, ours_s) = best_of(50, || corrections_svg("T", 1.0, &rows));
    let (theirs, theirs_s) = best_of(50, || plotters_svg(&rows).expect("plotters draws the plot"));
    for (name, svg, s) in [("precimap qc", &ours, ours_s), ("plotters SVGBackend", &theirs, theirs_s)] {
        println!(
            "{name:<20} {:>8} bytes  {:>6.2} ms (least of 50)  elements: {:>4} <text>, {:>4} <line>, {:>3} <polyline>",
            svg.len(),
            s * 1e3,
            svg.matches("<text").count(),
            svg.matches("<line").count(),
            svg.matches("<polyline").count()
        );
    }
    if let Ok(dir) = std::env::var("PLOTS_OUT") {
        let _ = std::fs::write(format!("{dir}/corrections-precimap.svg"), &ours);
        let _ = std::fs::write(format!("{dir}/corrections-plotters.svg"), &theirs);
    }
}
