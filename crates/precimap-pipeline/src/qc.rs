//! Quality-control plots (SVG): each trajectory's corrections along its arc length, the last
//! iteration's residual histogram, the convergence of the iterations, and the offsets at ground
//! control targets. Pure functions of data
//! both drivers hold (the corrections, `report.json`), so the in-process driver and the job
//! framework write the same bytes; a browser shows them.

use crate::control_report::{AccuracyFigures, ControlReport};
use crate::report::{IterationReport, Report};
use crate::tasks::VehicleCorrection;
use base64::Engine as _;
use precimap_core::{ControlRole, TileKey};
use precimap_estimate::{LatentStdMap, ResidualHistogram};
use precimap_formats::crs::Georeference;
use std::fmt::Write;

/// Folder of the QC plots inside a result folder.
pub const QC_DIR: &str = "qc";

/// A trajectory's correction plot as (path inside a result folder, SVG), from its corrections in
/// the vehicle's frames (`tasks::corrections_in_vehicle_frame`): what both drivers write beside
/// the corrected trajectory.
pub fn trajectory_plot(trajectory: &str, anchor_spacing_m: f64, rows: &[VehicleCorrection]) -> (String, String) {
    (format!("{QC_DIR}/corrections-{trajectory}.svg"), corrections_svg(trajectory, anchor_spacing_m, rows))
}

/// The report's QC files as (path inside a result folder, text): the residual and convergence
/// plots and, with control or check targets, their table; what both drivers write beside
/// `report.json`.
pub fn report_qc(report: &Report) -> Vec<(String, String)> {
    let mut files = vec![
        (format!("{QC_DIR}/residuals.svg"), residuals_svg(&report.residual_histogram)),
        (format!("{QC_DIR}/convergence.svg"), convergence_svg(&report.iterations)),
    ];
    if !report.control.targets.is_empty() {
        files.push((format!("{QC_DIR}/control.csv"), crate::control_report::control_csv(&report.control)));
        files.push((format!("{QC_DIR}/control.svg"), control_svg(&report.control)));
    }
    if let Some(c) = &report.calibration {
        files.push((format!("{QC_DIR}/calibration.csv"), calibration::calibration_csv(c)));
        files.push((format!("{QC_DIR}/calibration.svg"), calibration::calibration_svg(c)));
    }
    files
}

/// The latent map's standard-deviation maps of the first iteration (before any correction) and
/// the last, as (path inside a result folder, SVG); a field campaign's state its processing
/// frame ([`frame_note`]).
pub fn latent_std_plots(
    tile_size_m: f64,
    first: &[(TileKey, LatentStdMap)],
    last: &[(TileKey, LatentStdMap)],
    georef: Option<&Georeference>,
) -> [(String, String); 2] {
    let title = |which: &str| format!("Standard deviation of the latent map, {which} iteration");
    let note = georef.map(frame_note);
    let plot = |which: &str, tiles| latent_std_svg(&title(which), tile_size_m, tiles, note.as_deref());
    [
        (format!("{QC_DIR}/latent-std-first.svg"), plot("first (before any correction)", first)),
        (format!("{QC_DIR}/latent-std-last.svg"), plot("last", last)),
    ]
}

/// Where a field campaign's tiles lie: the processing CRS and the origin of its local frame.
pub fn frame_note(georef: &Georeference) -> String {
    let [e, n, h] = georef.frame.origin_grid_m();
    format!(
        "Tiles in the processing frame of {}: local Cartesian, grid axes and grid coordinates at its origin \
         E {e} N {n} h {h} m",
        georef.frame.crs()
    )
}

mod calibration;

const WIDTH: f64 = 960.0;
const LEFT: f64 = 78.0;
const RIGHT: f64 = 24.0;
const PANEL: f64 = 120.0;
const GAP: f64 = 46.0;
const TOP: f64 = 56.0;
/// Longest polyline, in vertices: a longer series is drawn as its minimum and maximum per
/// horizontal pixel (every extreme stays visible, and a 100 km trajectory stays a small file).
const MAX_VERTICES: usize = 2 * (WIDTH as usize);

/// The six components of a trajectory's corrections (translation in mm, rotation in mdeg, world
/// axes) against arc length, one panel each, with their RMS and largest magnitude.
pub fn corrections_svg(trajectory: &str, anchor_spacing_m: f64, rows: &[VehicleCorrection]) -> String {
    // The vehicle's frames, as in the corrections table: a world axis is the vehicle's only
    // where it drives east.
    const PANELS: [(&str, &str); 6] = [
        ("along-track translation", "mm"),
        ("across-track translation (to the left)", "mm"),
        ("vertical translation", "mm"),
        ("roll", "mdeg"),
        ("pitch", "mdeg"),
        ("heading", "mdeg"),
    ];
    let n = rows.len();
    let s0 = rows.first().map_or(0.0, |r| r.arc_m);
    let s1 = s0 + (n.max(2) - 1) as f64 * anchor_spacing_m;
    let mut svg = Svg::new(TOP + 6.0 * (PANEL + GAP));
    svg.title(&format!(
        "Corrections of trajectory {trajectory} in the vehicle's frame ({n} anchors every {} m, arc length {} … {} m)",
        number(anchor_spacing_m),
        number(s0),
        number(s1)
    ));
    for (k, (name, unit)) in PANELS.iter().enumerate() {
        let scale = if k < 3 { 1e3 } else { 1e3 * 180.0 / std::f64::consts::PI };
        let values: Vec<f64> = rows.iter().map(|r| r.values[k] * scale).collect();
        let rms = (values.iter().map(|v| v * v).sum::<f64>() / n.max(1) as f64).sqrt();
        let max = values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        // The posterior σ's RMS over the anchors that have one (the estimated ones).
        let sigmas: Vec<f64> = rows.iter().filter_map(|r| r.sigma.map(|s| s[k] * scale)).collect();
        let sigma = if sigmas.is_empty() {
            String::new()
        } else {
            format!(", σ RMS {}", number((sigmas.iter().map(|v| v * v).sum::<f64>() / sigmas.len() as f64).sqrt()))
        };
        let top = TOP + k as f64 * (PANEL + GAP);
        let (lo, hi) = padded_range(values.iter().copied().chain([0.0]));
        let plot = Plot { top, x: (s0, s1), y: (lo, hi), log_y: false };
        svg.panel(
            &plot,
            &format!("{name} ({unit}): RMS {}, largest |value| {}{sigma}", number(rms), number(max)),
            "arc length (m)",
        );
        svg.zero_line(&plot);
        let points = envelope(&values, (WIDTH - LEFT - RIGHT) as usize)
            .into_iter()
            .map(|(i, v)| (s0 + i as f64 * anchor_spacing_m, v));
        svg.polyline(&plot, points, "#1f5fbf", false);
    }
    svg.finish()
}

/// The last iteration's signed point-to-latent-map distances (mm), with their robust σ and what
/// fell outside the histogram's range.
pub fn residuals_svg(histogram: &ResidualHistogram) -> String {
    let mut svg = Svg::new(TOP + PANEL + GAP);
    let total = histogram.total();
    let sigma = histogram.robust_sigma_m().map_or("–".to_string(), |s| format!("{} mm", number(s * 1e3)));
    svg.title(&format!(
        "Residuals of the last iteration: {total} modelled points, robust σ {sigma}; below {} mm: {}, above {} mm: {}",
        number(histogram.min_m * 1e3),
        histogram.below,
        number((histogram.min_m + histogram.bin_m * histogram.counts.len() as f64) * 1e3),
        histogram.above
    ));
    let bin = histogram.bin_m * 1e3;
    let x0 = histogram.min_m * 1e3;
    let x1 = x0 + bin * histogram.counts.len() as f64;
    let most = histogram.counts.iter().copied().max().unwrap_or(0).max(1) as f64;
    let plot = Plot { top: TOP, x: (x0, x1), y: (0.0, most * 1.05), log_y: false };
    svg.panel(&plot, "points per bin", "signed distance to the latent map (mm)");
    // One path of bars: a step outline closed along the axis.
    let mut outline = Vec::with_capacity(2 * histogram.counts.len() + 2);
    outline.push((x0, 0.0));
    for (i, &c) in histogram.counts.iter().enumerate() {
        let left = x0 + i as f64 * bin;
        outline.push((left, c as f64));
        outline.push((left + bin, c as f64));
    }
    outline.push((x1, 0.0));
    svg.polyline(&plot, outline.into_iter(), "#1f5fbf", true);
    svg.finish()
}

/// Per iteration, the residual σ against the outlier threshold, and the anchors' largest and
/// median change (both on logarithmic axes): how the schedule converged.
pub fn convergence_svg(iterations: &[IterationReport]) -> String {
    let mut svg = Svg::new(TOP + 2.0 * (PANEL + GAP));
    let n = iterations.len();
    let last = iterations.last();
    svg.title(&format!(
        "Convergence over {n} iterations: residual σ {} mm, largest anchor change {} mm in the last{}",
        last.map_or("–".into(), |i| number(i.residual_std_m * 1e3)),
        last.map_or("–".into(), |i| number(i.max_correction_change_m * 1e3)),
        last.and_then(|i| i.max_correction_change_at.as_ref()).map_or(String::new(), |at| format!(" ({at})")),
    ));
    let x = (0.5, n.max(1) as f64 + 0.5);
    let series = |f: fn(&IterationReport) -> f64| -> Vec<(f64, f64)> {
        iterations.iter().map(|i| (i.iteration as f64, f(i) * 1e3)).collect()
    };
    // Per panel its label and (colour, values) per line.
    let panels: [(&str, [Series; 2]); 2] = [
        (
            "residual σ (mm, blue) and outlier threshold (mm, grey)",
            [("#1f5fbf", series(|i| i.residual_std_m)), ("#888888", series(|i| i.threshold_m))],
        ),
        (
            "largest (blue) and median (orange) anchor change (mm at 10 m)",
            [("#1f5fbf", series(|i| i.max_correction_change_m)), ("#d9822b", series(|i| i.median_correction_change_m))],
        ),
    ];
    for (k, (label, lines)) in panels.iter().enumerate() {
        let positive = lines.iter().flat_map(|l| l.1.iter().map(|p| p.1)).filter(|v| *v > 0.0 && v.is_finite());
        let (lo, hi) = positive.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
        let (lo, hi) = if lo.is_finite() { (lo, hi) } else { (1e-3, 1.0) };
        let y = (10f64.powf(lo.log10().floor()), 10f64.powf(hi.log10().ceil().max(lo.log10().floor() + 1.0)));
        let plot = Plot { top: TOP + k as f64 * (PANEL + GAP), x, y, log_y: true };
        svg.panel(&plot, label, "iteration");
        for (colour, points) in lines {
            // Zeros (no change) sit on the axis floor rather than at minus infinity.
            svg.polyline(&plot, points.iter().map(|&(i, v)| (i, v.max(y.0))), colour, false);
        }
    }
    svg.finish()
}

/// The map's offset from every control and check target (mm, map minus target): east and
/// north in one panel, up in the other, one column per target in the report's order; control
/// targets as dots, check targets as rings, with the RMSE figures in the title.
pub fn control_svg(control: &ControlReport) -> String {
    let mut svg = Svg::new(TOP + 2.0 * (PANEL + GAP));
    let mm = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{} mm", number(v * 1e3)));
    let figures = |f: &Option<AccuracyFigures>| {
        f.as_ref().map_or("none".to_string(), |f| {
            format!("horizontal {}, vertical {}", mm(f.rmse_horizontal_m), mm(f.rmse_z_m))
        })
    };
    svg.title(&format!(
        "Ground control: RMSE at control targets {}; at check targets {}",
        figures(&control.control),
        figures(&control.check)
    ));
    let n = control.targets.len();
    let x = (0.5, n.max(1) as f64 + 0.5);
    let at = |axis: usize| -> Vec<(f64, f64, bool)> {
        control
            .targets
            .iter()
            .enumerate()
            .filter_map(|(i, t)| {
                let o = [t.offset_m.x, t.offset_m.y, t.offset_m.z][axis]?;
                Some(((i + 1) as f64, o * 1e3, t.role == ControlRole::Check))
            })
            .collect()
    };
    let panels = [
        (
            "east (blue) and north (orange) offset (mm); dots control, rings check",
            vec![("#1f5fbf", at(0)), ("#d9822b", at(1))],
        ),
        ("vertical offset (mm); dots control, rings check", vec![("#1f5fbf", at(2))]),
    ];
    for (k, (label, series)) in panels.iter().enumerate() {
        let (lo, hi) = padded_range(series.iter().flat_map(|s| s.1.iter().map(|p| p.1)).chain([-1.0, 1.0]));
        let plot = Plot { top: TOP + k as f64 * (PANEL + GAP), x, y: (lo, hi), log_y: false };
        svg.panel(&plot, label, "target (in the manifest's order; qc/control.csv names them)");
        svg.zero_line(&plot);
        for (colour, points) in series {
            svg.dots(&plot, points, colour);
        }
    }
    svg.finish()
}

/// The latent map's standard deviation seen from above, one pixel per [`LatentStdMap`] cell, on
/// the paper's temperature scale (Figures 11–12: blue 0 mm … red [`STD_MAP_RED_MM`] mm or more;
/// grey where no point was observed), as a PNG inside an SVG that carries the title, the colour
/// scale and a scale bar. `tiles` in any order; `tile_size_m` places them.
pub fn latent_std_svg(title: &str, tile_size_m: f64, tiles: &[(TileKey, LatentStdMap)], note: Option<&str>) -> String {
    let side = tiles.iter().map(|(_, m)| m.side).max().unwrap_or(1).max(1);
    let cell_m = tiles.first().map_or(LatentStdMap::CELL_M, |(_, m)| m.cell_m);
    let (tx0, tx1) = tiles.iter().fold((i32::MAX, i32::MIN), |(a, b), (k, _)| (a.min(k.tx), b.max(k.tx)));
    let (ty0, ty1) = tiles.iter().fold((i32::MAX, i32::MIN), |(a, b), (k, _)| (a.min(k.ty), b.max(k.ty)));
    let (columns, rows) =
        if tiles.is_empty() { (1, 1) } else { ((tx1 - tx0 + 1) as u32 * side, (ty1 - ty0 + 1) as u32 * side) };
    let mut rgba = vec![0u8; (columns * rows * 4) as usize];
    let mut means = Vec::new();
    for (key, map) in tiles {
        for j in 0..map.side {
            for i in 0..map.side {
                let Some(mean) = map.mean_m(i, j) else { continue };
                means.push(mean);
                let x = (key.tx - tx0) as u32 * side + i;
                // North up: the image's first row is the northernmost cell.
                let y = rows - 1 - ((key.ty - ty0) as u32 * side + j);
                let at = ((y * columns + x) * 4) as usize;
                let [r, g, b] = temperature(mean * 1e3 / STD_MAP_RED_MM);
                rgba[at..at + 4].copy_from_slice(&[r, g, b, 255]);
            }
        }
    }
    means.sort_by(f64::total_cmp);
    let median = means.get(means.len() / 2).map_or("–".into(), |m| number(m * 1e3));
    let red = means.iter().filter(|m| **m * 1e3 >= STD_MAP_RED_MM).count();
    let red_share = if means.is_empty() { 0.0 } else { 100.0 * red as f64 / means.len() as f64 };
    // Shown at a whole number of screen pixels per cell, up to the page width.
    let zoom = ((WIDTH - LEFT - RIGHT) / columns as f64).floor().clamp(1.0, 8.0);
    let (w, h) = (columns as f64 * zoom, rows as f64 * zoom);
    let legend_top = TOP + h + 24.0;
    let mut svg = Svg::new(legend_top + if note.is_some() { 90.0 } else { 70.0 });
    svg.title(title);
    if let Some(note) = note {
        let _ = write!(svg.out, r##"<text x="{LEFT}" y="{:.1}">{}</text>"##, legend_top + 62.0, escape(note));
    }
    let _ = write!(
        svg.out,
        r##"<text x="{LEFT}" y="44">{} cells of {} m observed: median {median} mm, {} % at {} mm or more; north up, tiles {}…{} × {}…{} of {} m</text>"##,
        means.len(),
        number(cell_m),
        number(red_share),
        number(STD_MAP_RED_MM),
        tx0.min(tx1),
        tx1.max(tx0),
        ty0.min(ty1),
        ty1.max(ty0),
        number(tile_size_m)
    );
    let _ = write!(
        svg.out,
        r##"<rect x="{LEFT}" y="{TOP}" width="{w}" height="{h}" fill="#d8d8d8"/><image x="{LEFT}" y="{TOP}" width="{w}" height="{h}" image-rendering="pixelated" preserveAspectRatio="none" href="data:image/png;base64,{}"/>"##,
        base64(&encode_png(columns, rows, &rgba))
    );
    // Colour scale in 1 mm steps, and a scale bar of a round length.
    for k in 0..=STD_MAP_RED_MM as usize {
        let [r, g, b] = temperature(k as f64 / STD_MAP_RED_MM);
        let x = LEFT + k as f64 * 36.0;
        let label = if k == STD_MAP_RED_MM as usize { format!("≥ {k} mm") } else { format!("{k}") };
        let _ = write!(
            svg.out,
            r##"<rect x="{x}" y="{legend_top}" width="36" height="14" fill="rgb({r},{g},{b})"/><text x="{x}" y="{:.1}">{label}</text>"##,
            legend_top + 28.0
        );
    }
    let bar_m = round_below(columns as f64 * cell_m / 4.0).max(cell_m);
    let bar = bar_m / cell_m * zoom;
    let x = LEFT + 8.0 * 36.0 + 40.0;
    let _ = write!(
        svg.out,
        r##"<rect x="{x}" y="{legend_top}" width="{bar:.1}" height="6" fill="#222222"/><text x="{x}" y="{:.1}">{} m</text>"##,
        legend_top + 28.0,
        number(bar_m)
    );
    svg.finish()
}

/// Standard deviation at which the map turns fully red (mm), the paper's scale.
pub const STD_MAP_RED_MM: f64 = 7.0;

/// The temperature scale: 0 blue, ¼ cyan, ½ green, ¾ yellow, 1 (and above) red.
fn temperature(t: f64) -> [u8; 3] {
    const STOPS: [[f64; 3]; 5] =
        [[0.0, 0.0, 255.0], [0.0, 255.0, 255.0], [0.0, 200.0, 0.0], [255.0, 230.0, 0.0], [230.0, 0.0, 0.0]];
    let t = if t.is_finite() { t.clamp(0.0, 1.0) } else { 1.0 } * 4.0;
    let k = (t.floor() as usize).min(3);
    let f = t - k as f64;
    let (a, b) = (STOPS[k], STOPS[k + 1]);
    [0, 1, 2].map(|c| (a[c] + (b[c] - a[c]) * f).round() as u8)
}

fn encode_png(width: u32, height: u32, rgba: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    // Writing to memory: the only failure is a size the header cannot hold, which a map of
    // whole tiles never reaches; an empty image is then still a valid SVG.
    if let Ok(mut writer) = encoder.write_header() {
        let _ = writer.write_image_data(rgba);
    }
    out
}

/// Standard base64 (RFC 4648 alphabet, with padding), as a `data:` URL needs it.
fn base64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// A line of a plot: its colour and its (x, y) vertices.
type Series = (&'static str, Vec<(f64, f64)>);

/// A panel's placement and data ranges.
struct Plot {
    top: f64,
    x: (f64, f64),
    y: (f64, f64),
    log_y: bool,
}

impl Plot {
    fn px(&self, x: f64) -> f64 {
        let span = (self.x.1 - self.x.0).max(f64::MIN_POSITIVE);
        LEFT + (x - self.x.0) / span * (WIDTH - LEFT - RIGHT)
    }

    fn py(&self, y: f64) -> f64 {
        let (y, lo, hi) =
            if self.log_y { (y.log10(), self.y.0.log10(), self.y.1.log10()) } else { (y, self.y.0, self.y.1) };
        let span = (hi - lo).max(f64::MIN_POSITIVE);
        self.top + PANEL - (y - lo) / span * PANEL
    }
}

struct Svg {
    out: String,
}

impl Svg {
    fn new(height: f64) -> Self {
        let mut out = String::new();
        let _ = write!(
            out,
            r##"<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{height}" viewBox="0 0 {WIDTH} {height}" font-family="sans-serif" font-size="12">"##
        );
        let _ = write!(out, r##"<rect width="100%" height="100%" fill="#ffffff"/>"##);
        Self { out }
    }

    fn title(&mut self, text: &str) {
        let text = escape(text);
        let _ = write!(self.out, r##"<text x="{LEFT}" y="24" font-size="15" font-weight="bold">{text}</text>"##);
    }

    /// Frame, ticks with labels, the panel's label above it and the x axis' label below.
    fn panel(&mut self, plot: &Plot, label: &str, x_label: &str) {
        let (top, bottom, right) = (plot.top, plot.top + PANEL, WIDTH - RIGHT);
        let _ = write!(self.out, r##"<text x="{LEFT}" y="{:.1}">{}</text>"##, top - 8.0, escape(label));
        let _ = write!(
            self.out,
            r##"<rect x="{LEFT}" y="{top:.1}" width="{:.1}" height="{PANEL}" fill="none" stroke="#444444"/>"##,
            right - LEFT
        );
        for t in ticks(plot.x.0, plot.x.1, 8) {
            let x = plot.px(t);
            let _ = write!(
                self.out,
                r##"<line x1="{x:.1}" y1="{top:.1}" x2="{x:.1}" y2="{bottom:.1}" stroke="#e4e4e4"/><text x="{x:.1}" y="{:.1}" text-anchor="middle">{}</text>"##,
                bottom + 14.0,
                number(t)
            );
        }
        let y_ticks = if plot.log_y { decades(plot.y.0, plot.y.1) } else { ticks(plot.y.0, plot.y.1, 4) };
        for t in y_ticks {
            let y = plot.py(t);
            let _ = write!(
                self.out,
                r##"<line x1="{LEFT}" y1="{y:.1}" x2="{right:.1}" y2="{y:.1}" stroke="#e4e4e4"/><text x="{:.1}" y="{:.1}" text-anchor="end">{}</text>"##,
                LEFT - 6.0,
                y + 4.0,
                number(t)
            );
        }
        let _ = write!(
            self.out,
            r##"<text x="{:.1}" y="{:.1}" text-anchor="middle" fill="#444444">{}</text>"##,
            (LEFT + right) / 2.0,
            bottom + 30.0,
            escape(x_label)
        );
    }

    fn zero_line(&mut self, plot: &Plot) {
        if plot.y.0 < 0.0 && plot.y.1 > 0.0 {
            let y = plot.py(0.0);
            let _ = write!(
                self.out,
                r##"<line x1="{LEFT}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#888888"/>"##,
                WIDTH - RIGHT
            );
        }
    }

    fn polyline(&mut self, plot: &Plot, points: impl Iterator<Item = (f64, f64)>, colour: &str, filled: bool) {
        let mut coordinates = String::new();
        for (x, y) in points {
            if x.is_finite() && y.is_finite() {
                let _ = write!(coordinates, "{:.1},{:.1} ", plot.px(x), plot.py(y));
            }
        }
        let fill = if filled { colour } else { "none" };
        let _ = write!(
            self.out,
            r##"<polyline points="{}" fill="{fill}" fill-opacity="0.6" stroke="{colour}" stroke-width="1.2"/>"##,
            coordinates.trim_end()
        );
    }

    /// A dot per point, a ring where its flag is set.
    fn dots(&mut self, plot: &Plot, points: &[(f64, f64, bool)], colour: &str) {
        for &(x, y, ring) in points {
            if x.is_finite() && y.is_finite() {
                let fill = if ring { "none" } else { colour };
                let _ = write!(
                    self.out,
                    r##"<circle cx="{:.1}" cy="{:.1}" r="3.5" fill="{fill}" stroke="{colour}" stroke-width="1.2"/>"##,
                    plot.px(x),
                    plot.py(y)
                );
            }
        }
    }

    fn finish(mut self) -> String {
        self.out.push_str("</svg>\n");
        self.out
    }
}

/// `values` as (index, value) vertices: all of them if they fit [`MAX_VERTICES`], otherwise
/// per one of `columns` equal index ranges its minimum and maximum, in the order they occur.
fn envelope(values: &[f64], columns: usize) -> Vec<(usize, f64)> {
    if values.len() <= MAX_VERTICES || columns == 0 {
        return values.iter().copied().enumerate().collect();
    }
    let mut out = Vec::with_capacity(2 * columns);
    for c in 0..columns {
        let (a, b) = (c * values.len() / columns, (c + 1) * values.len() / columns);
        if a == b {
            continue;
        }
        let (mut lo, mut hi) = (a, a);
        for i in a..b {
            if values[i] < values[lo] {
                lo = i;
            }
            if values[i] > values[hi] {
                hi = i;
            }
        }
        let (first, second) = if lo <= hi { (lo, hi) } else { (hi, lo) };
        out.push((first, values[first]));
        if second != first {
            out.push((second, values[second]));
        }
    }
    out
}

/// The finite values' range widened by 5 % on each side (±1 around a constant).
fn padded_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) =
        values.filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        return (-1.0, 1.0);
    }
    if hi - lo < 1e-12 {
        return (lo - 1.0, hi + 1.0);
    }
    let pad = 0.05 * (hi - lo);
    (lo - pad, hi + pad)
}

/// About `count` round tick values (1, 2 or 5 × a power of ten apart) within `[lo, hi]`.
fn ticks(lo: f64, hi: f64, count: usize) -> Vec<f64> {
    if !(lo.is_finite() && hi.is_finite()) || hi <= lo {
        return Vec::new();
    }
    let raw = (hi - lo) / count.max(1) as f64;
    let power = 10f64.powf(raw.log10().floor());
    // The round step whose tick count comes closest to `count`.
    let misfit = |step: f64| ((hi - lo) / step - count as f64).abs();
    let step = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * power)
        .min_by(|a, b| misfit(*a).total_cmp(&misfit(*b)))
        .unwrap_or(power);
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    // Integer multiples of the step: no drift, and an exact zero.
    (first..=last).map(|k| k as f64 * step).collect()
}

/// The largest 1, 2 or 5 × a power of ten not above `v` (positive).
fn round_below(v: f64) -> f64 {
    let power = 10f64.powf(v.log10().floor());
    [5.0, 2.0, 1.0].into_iter().map(|m| m * power).find(|r| *r <= v).unwrap_or(power)
}

/// The powers of ten within `[lo, hi]` (both positive).
fn decades(lo: f64, hi: f64) -> Vec<f64> {
    let (a, b) = (lo.log10().ceil() as i32, hi.log10().floor() as i32);
    (a..=b).map(|e| 10f64.powi(e)).collect()
}

/// A short label: up to four significant digits, no trailing zeros.
fn number(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return if v.is_nan() {
            "NaN".into()
        } else if v == 0.0 {
            "0".into()
        } else {
            format!("{v}")
        };
    }
    let magnitude = v.abs().log10().floor() as i32;
    if !(-4..6).contains(&magnitude) {
        return format!("{v:.3e}");
    }
    let decimals = (3 - magnitude).max(0) as usize;
    let s = format!("{v:.decimals$}");
    let s = if s.contains('.') { s.trim_end_matches('0').trim_end_matches('.').to_string() } else { s };
    if s == "-0" {
        "0".into()
    } else {
        s
    }
}

/// Text for SVG: the five characters XML reserves, escaped.
fn escape(text: &str) -> String {
    text.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;").replace('\'', "&apos;")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vertices of the svg's polylines, per polyline, in pixels.
    fn polylines(svg: &str) -> Vec<Vec<(f64, f64)>> {
        svg.split("<polyline points=\"")
            .skip(1)
            .map(|rest| {
                rest[..rest.find('"').unwrap()]
                    .split_whitespace()
                    .map(|p| {
                        let (x, y) = p.split_once(',').unwrap();
                        (x.parse().unwrap(), y.parse().unwrap())
                    })
                    .collect()
            })
            .collect()
    }

    /// Tags open and close in order (a well-formedness check without an XML parser: the plots
    /// use only self-closing elements besides `svg` and `text`).
    fn assert_well_formed(svg: &str) {
        assert!(svg.starts_with("<svg xmlns=\"http://www.w3.org/2000/svg\""), "{}", &svg[..80]);
        assert!(svg.ends_with("</svg>\n"));
        assert_eq!(svg.matches("<text").count(), svg.matches("</text>").count());
        assert_eq!(svg.matches('<').count(), svg.matches('>').count());
        // Outside an embedded image's base64 (where any letters may follow each other).
        let text = match svg.find("base64,") {
            Some(start) => {
                let end = start + svg[start..].find('"').unwrap();
                format!("{}{}", &svg[..start], &svg[end..])
            }
            None => svg.to_string(),
        };
        assert!(!text.contains("NaN") && !text.contains("inf"), "non-finite coordinates");
    }

    /// Corrections in the vehicle's frame from `first` on, every 0.5 m, without σ.
    fn rows(first: u32, values: Vec<[f64; 6]>) -> Vec<VehicleCorrection> {
        values
            .into_iter()
            .enumerate()
            .map(|(k, values)| {
                let anchor = first + k as u32;
                VehicleCorrection {
                    anchor,
                    arc_m: anchor as f64 * 0.5,
                    time: 0.0,
                    position: precimap_core::Vec3::zeros(),
                    values,
                    sigma: None,
                    estimated: true,
                }
            })
            .collect()
    }

    #[test]
    fn a_correction_ramp_is_drawn_where_its_values_are() {
        // Translation x rises 0 → 100 mm over 201 anchors (100 m), everything else zero.
        let values: Vec<[f64; 6]> = (0..201).map(|i| [i as f64 * 0.0005, 0.0, 0.0, 0.0, 0.0, 0.0]).collect();
        let mut corrections = rows(40, values);
        // Every anchor but the first has a σ of 2 mm along the track: its RMS is in the label.
        corrections.iter_mut().skip(1).for_each(|r| r.sigma = Some([0.002, 0.0, 0.0, 0.0, 0.0, 0.0]));
        let svg = corrections_svg("v<1>", 0.5, &corrections);
        assert_well_formed(&svg);
        assert!(svg.contains("trajectory v&lt;1&gt;"), "the id is escaped");
        assert!(svg.contains("arc length 20 … 120 m"));
        // RMS of a 0…100 ramp: 100/√3 · √(n(n+1)(2n+1)/6)/… ≈ 57.88 mm for 201 samples.
        let rms = ((0..201).map(|i| (i as f64 * 0.5).powi(2)).sum::<f64>() / 201.0).sqrt();
        assert!(svg.contains(&format!("RMS {}, largest |value| 100, σ RMS 2", number(rms))), "{svg}");
        assert!(svg.contains("in the vehicle&apos;s frame") && svg.contains("along-track translation (mm)"));
        let lines = polylines(&svg);
        assert_eq!(lines.len(), 6);
        let ramp = &lines[0];
        assert_eq!(ramp.len(), 201);
        // Left end at the frame's left edge and bottom (0 mm, padded 5 %), right end at the top.
        let (x_first, y_first) = ramp[0];
        let (x_last, y_last) = ramp[200];
        assert!((x_first - LEFT).abs() < 0.06 && (x_last - (WIDTH - RIGHT)).abs() < 0.06);
        let pad = 5.0;
        let plot = Plot { top: TOP, x: (20.0, 120.0), y: (-pad, 100.0 + pad), log_y: false };
        assert!((y_first - plot.py(0.0)).abs() < 0.06 && (y_last - plot.py(100.0)).abs() < 0.06);
        // A flat component is a line on its zero line.
        assert!(lines[1].iter().all(|p| (p.1 - lines[1][0].1).abs() < 1e-9));
    }

    #[test]
    fn a_long_trajectory_keeps_every_extreme_in_a_bounded_polyline() {
        // 200,000 anchors of small noise with one spike each way.
        let mut values: Vec<[f64; 6]> =
            (0..200_000).map(|i| [((i * 7919) % 13) as f64 * 1e-4, 0.0, 0.0, 0.0, 0.0, 0.0]).collect();
        values[123_457][0] = 0.25;
        values[7][0] = -0.125;
        let svg = corrections_svg("long", 0.5, &rows(0, values));
        assert_well_formed(&svg);
        let ramp = &polylines(&svg)[0];
        assert!(ramp.len() <= MAX_VERTICES, "{} vertices", ramp.len());
        let top = ramp.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
        let bottom = ramp.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
        let plot = Plot { top: TOP, x: (0.0, 1.0), y: (-125.0 - 18.75, 250.0 + 18.75), log_y: false };
        assert!((top - plot.py(250.0)).abs() < 0.06, "the +250 mm spike is drawn: {top}");
        assert!((bottom - plot.py(-125.0)).abs() < 0.06, "the −125 mm spike is drawn: {bottom}");
        assert!(svg.contains("largest |value| 250"));
    }

    #[test]
    fn the_histogram_outline_follows_the_counts() {
        let mut h = ResidualHistogram::default();
        for e in [0.0001, 0.0002, 0.0007, -0.0003, 0.2, -0.3, -0.4] {
            h.add(e);
        }
        let svg = residuals_svg(&h);
        assert_well_formed(&svg);
        assert!(svg.contains("7 modelled points"), "{svg}");
        assert!(svg.contains("below -50 mm: 2, above 50 mm: 1"), "{svg}");
        let outline = &polylines(&svg)[0];
        assert_eq!(outline.len(), 2 * h.counts.len() + 2);
        // Bin 100 ([0, 0.5) mm) holds 2 of the tallest count 2, bin 101 one, bin 99 one.
        let plot = Plot { top: TOP, x: (-50.0, 50.0), y: (0.0, 2.1), log_y: false };
        let height = |bin: usize| outline[1 + 2 * bin].1;
        assert!((height(100) - plot.py(2.0)).abs() < 0.06);
        assert!((height(101) - plot.py(1.0)).abs() < 0.06 && (height(99) - plot.py(1.0)).abs() < 0.06);
        assert!((height(50) - plot.py(0.0)).abs() < 0.06);
        // An empty histogram still renders.
        assert_well_formed(&residuals_svg(&ResidualHistogram::default()));
    }

    #[test]
    fn convergence_is_drawn_on_decades_and_survives_zero_changes() {
        let iterations: Vec<IterationReport> = (1..=4)
            .map(|i| IterationReport {
                iteration: i,
                common_mode_field_max_m: 0.0,
                common_mode_heading_max_deg: 0.0,
                common_mode_tilt_max_deg: 0.0,
                campaign_rotation_deg: [0.0; 3],
                grid_m: 0.1,
                threshold_m: 0.3 / i as f64,
                points_in_tiles: 10,
                points_modelled: 9,
                points_used: 8,
                residual_mean_m: 0.0,
                residual_std_m: 0.01 / i as f64,
                pixel_std_mean_m: 0.0,
                max_correction_change_m: 0.1 / 10f64.powi(i as i32),
                median_correction_change_m: if i == 1 { 0.0 } else { 0.01 / 10f64.powi(i as i32) },
                p99_correction_change_m: 0.0,
                max_correction_change_at: (i == 4).then(|| crate::report::ChangeLocation {
                    trajectory: "v<1>".into(),
                    anchor: 1235,
                    along_m: 617.5,
                }),
                anderson_coefficients: Vec::new(),
                seconds: 1.0,
            })
            .collect();
        let svg = convergence_svg(&iterations);
        assert_well_formed(&svg);
        // The title names where the last iteration's largest change is (the id escaped).
        assert!(svg.contains("in the last (v&lt;1&gt; at 618 m)"), "{}", &svg[..400]);
        let lines = polylines(&svg);
        assert_eq!(lines.len(), 4);
        assert!(lines.iter().all(|l| l.len() == 4));
        // The largest change falls a decade per iteration: equal vertical steps on a log axis.
        let largest = &lines[2];
        let steps: Vec<f64> = largest.windows(2).map(|w| w[1].1 - w[0].1).collect();
        assert!(steps.iter().all(|s| (s - steps[0]).abs() < 0.11 && *s > 0.0), "{steps:?}");
        assert!(svg.contains(">0.001<") && svg.contains(">10<"), "decade labels");
        assert_well_formed(&convergence_svg(&[]));
    }

    /// The PNG inside a map's SVG, decoded: (width, height, RGBA).
    fn embedded_png(svg: &str) -> (u32, u32, Vec<u8>) {
        let start = svg.find("base64,").unwrap() + "base64,".len();
        let text = &svg[start..start + svg[start..].find('"').unwrap()];
        let value = |c: u8| ALPHABET_INDEX.iter().position(|&a| a == c).unwrap() as u32;
        let mut bytes = Vec::new();
        for quad in text.as_bytes().chunks(4) {
            let pad = quad.iter().filter(|&&c| c == b'=').count();
            let n = quad.iter().take(4 - pad).enumerate().fold(0, |n, (k, &c)| n | value(c) << (18 - 6 * k));
            bytes.extend_from_slice(&[(n >> 16) as u8, (n >> 8) as u8, n as u8][..3 - pad]);
        }
        let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().unwrap();
        let mut rgba = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut rgba).unwrap();
        (info.width, info.height, rgba)
    }
    const ALPHABET_INDEX: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

    #[test]
    fn the_latent_map_is_drawn_north_up_on_the_papers_scale() {
        // Two tiles side by side east–west, one row apart north–south: (10, 20) and (11, 21).
        let mut south_west = LatentStdMap::new(15.0);
        south_west.add(0.5, 0.5, 0.001); // its south-west cell: 1 mm
        south_west.add(0.6, 0.4, 0.003); // the same cell again: mean 2 mm
        south_west.add(14.5, 14.5, 0.010); // its north-east cell: 10 mm, beyond red
        let mut north_east = LatentStdMap::new(15.0);
        north_east.add(7.2, 3.9, 0.0);
        north_east.add(-0.1, 3.0, 0.5); // outside the core: not counted
        north_east.add(3.0, 3.0, f64::NAN); // not counted
        let tiles = [(TileKey { tx: 11, ty: 21 }, north_east), (TileKey { tx: 10, ty: 20 }, south_west)];
        let svg = latent_std_svg("A & B", 15.0, &tiles, None);
        assert_well_formed(&svg);
        assert!(svg.contains("A &amp; B"));
        assert!(svg.contains("3 cells of 1 m observed: median 2 mm, 33.33 % at 7 mm or more"), "{svg}");
        let (w, h, rgba) = embedded_png(&svg);
        assert_eq!((w, h), (30, 30));
        let pixel = |x: u32, y: u32| rgba[((y * w + x) * 4) as usize..][..4].to_vec();
        // South-west tile's south-west cell: the image's bottom-left pixel, 2 mm of 7.
        assert_eq!(pixel(0, 29), [temperature(2.0 / 7.0).to_vec(), vec![255]].concat());
        assert_eq!(pixel(14, 15), vec![230, 0, 0, 255], "10 mm is red");
        // North-east tile, cell (7, 3): x 15 + 7, y 29 − (15 + 3); 0 mm is blue.
        assert_eq!(pixel(22, 11), vec![0, 0, 255, 255]);
        // Everything else is transparent (the grey background shows).
        let opaque = rgba.chunks(4).filter(|p| p[3] != 0).count();
        assert_eq!(opaque, 3);
        // No tiles at all still renders.
        assert_well_formed(&latent_std_svg("empty", 15.0, &[], None));
        // A field campaign's plots state its processing frame.
        let georef = precimap_formats::CrsSpec {
            processing: 32632,
            origin_grid_m: [549_800.0, 5_803_400.0, 55.0],
            strips: None,
        }
        .georeference()
        .unwrap();
        for (_, svg) in latent_std_plots(15.0, &tiles, &[], Some(&georef)) {
            assert_well_formed(&svg);
            assert!(
                svg.contains("processing frame of EPSG:32632 (WGS 84 / UTM zone 32N)") && svg.contains("E 549800"),
                "{svg}"
            );
        }
    }

    #[test]
    fn base64_and_the_temperature_scale() {
        assert_eq!(base64(b"Man"), "TWFu");
        assert_eq!(base64(b"Ma"), "TWE=");
        assert_eq!(base64(b"M"), "TQ==");
        assert_eq!(base64(b""), "");
        assert_eq!(temperature(0.0), [0, 0, 255]);
        assert_eq!(temperature(0.5), [0, 200, 0]);
        assert_eq!(temperature(1.0), [230, 0, 0]);
        assert_eq!(temperature(3.0), [230, 0, 0]);
        assert_eq!(temperature(f64::NAN), [230, 0, 0]);
        assert_eq!(round_below(67.5), 50.0);
        assert_eq!(round_below(3.0), 2.0);
    }

    #[test]
    fn tick_values_are_round_and_labels_short() {
        assert_eq!(ticks(0.0, 100.0, 4), vec![0.0, 20.0, 40.0, 60.0, 80.0, 100.0]);
        assert_eq!(ticks(-3.0, 7.0, 4), vec![-2.0, 0.0, 2.0, 4.0, 6.0]);
        assert_eq!(decades(0.002, 30.0), vec![0.01, 0.1, 1.0, 10.0]);
        assert_eq!(number(0.0), "0");
        assert_eq!(number(12.345678), "12.35");
        assert_eq!(number(-0.00012), "-0.00012");
        assert_eq!(number(1234.4), "1234");
        assert_eq!(number(2.5e-6), "2.500e-6");
    }
}
