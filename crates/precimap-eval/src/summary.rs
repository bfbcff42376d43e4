//! The evaluation as a plain-text table.

use super::*;

impl Evaluation {
    /// A plain-text table for terminals (millimetres and millidegrees).
    pub fn summary(&self) -> String {
        let mut out = format!("{:<34} {:>12} {:>12}\n", "metric", "before", "after");
        out.push_str(&self.metric_rows());
        self.class_spreads(&mut out);
        self.datum_and_precision(&mut out);
        self.counts_and_audits(&mut out);
        self.worst_tiles(&mut out);
        if let Some(c) = &self.calibration {
            c.summary(&mut out);
        }
        out
    }

    /// One row per figure: before, after, and after as a share of before.
    fn metric_rows(&self) -> String {
        let mut s = String::new();
        let mut row = |name: &str, m: &Metric, scale: f64, unit: &str| {
            let ratio = if m.before > 0.0 { format!("{:>7.1} %", 100.0 * m.after / m.before) } else { String::new() };
            let _ = writeln!(s, "{name:<34} {:>12.3} {:>12.3} {unit:<5}{ratio}", m.before * scale, m.after * scale);
        };
        row("strip offset spread", &self.strip_offset_spread_m, 1e3, "mm");
        row("  same-surface spread", &self.same_surface_spread_m, 1e3, "mm");
        row("    without the campaign's shift", &self.same_surface_spread_without_campaign_shift_m, 1e3, "mm");
        let a = &self.same_surface_agreement;
        let of = |m: &SpreadMetric, f: fn(&Spread) -> f64| metric(f(&m.before), f(&m.after));
        row("      95th percentile (≥ 50 points)", &of(&a.all, |s| s.p95_m), 1e3, "mm");
        row("      maximum (≥ 50 points)", &of(&a.all, |s| s.max_m), 1e3, "mm");
        row("      up-facing, RMS", &of(&a.up, |s| s.rms_m), 1e3, "mm");
        row("      facing travel, RMS", &of(&a.facing_travel, |s| s.rms_m), 1e3, "mm");
        row("      facing across, RMS", &of(&a.facing_across, |s| s.rms_m), 1e3, "mm");
        row("  without the campaign's shift", &self.spread_without_campaign_shift_m, 1e3, "mm");
        row("  without each tile's shift", &self.spread_without_tile_shift_m, 1e3, "mm");
        row("  from the datum error alone", &self.spread_from_datum_m, 1e3, "mm");
        row("  from each tile's datum alone", &self.spread_from_local_datum_m, 1e3, "mm");
        row("surface error RMS", &self.surface_error_rms_m, 1e3, "mm");
        row("surface error mean", &self.surface_error_mean_m, 1e3, "mm");
        row("surface |error| 95th percentile", &self.surface_error_p95_abs_m, 1e3, "mm");
        row("trajectory position error RMS", &self.trajectory_error_rms_m, 1e3, "mm");
        row("trajectory attitude error RMS", &self.trajectory_rotation_error_rms_deg, 1e3, "mdeg");
        let attitude = self.trajectory_attitude_error_rms_deg.components();
        let attitude_without = self.trajectory_attitude_error_without_mean_rms_deg.components();
        for ((name, m), without) in ATTITUDE_COMPONENTS.iter().zip(attitude).zip(attitude_without) {
            row(&format!("  {name}"), m, 1e3, "mdeg");
            row("    w/o the campaign's rotation", without, 1e3, "mdeg");
        }
        for (name, m) in FRAME_COMPONENTS.iter().zip(self.trajectory_error_without_datum_rms_m.components()) {
            row(&format!("  {name} w/o the datum"), m, 1e3, "mm");
        }
        if let Some(unscanned) = &self.trajectory_error_without_datum_unscanned_rms_m {
            for (name, m) in FRAME_COMPONENTS.iter().zip(unscanned.components()) {
                let short = name.trim_end_matches("-track");
                row(&format!("    {short} in run-up/run-out"), m, 1e3, "mm");
            }
        }
        row("  the campaign's tilt", &self.trajectory_tilt_deg, 1e3, "mdeg");
        row("  vertical w/o the tilt", &self.trajectory_vertical_error_without_tilt_rms_m, 1e3, "mm");
        for (name, c) in &self.per_class {
            row(&format!("  {name} error RMS ({} points)", c.points), &c.rms_m, 1e3, "mm");
        }
        s
    }

    /// Each class's spreads after the adjustment.
    fn class_spreads(&self, out: &mut String) {
        let _ = writeln!(
            out,
            "strip offset spread per class, after (mm): {:>8} {:>13} {:>12} {:>12} {:>6}",
            "spread", "same-surface", "w/o shift", "same w/o", "pairs"
        );
        for (name, c) in &self.per_class {
            let _ = writeln!(
                out,
                "  {name:<40} {:>8.3} {:>13.3} {:>12.3} {:>12.3} {:>6}",
                c.spread_m.after * 1e3,
                c.same_surface_spread_m.after * 1e3,
                c.spread_without_campaign_shift_m.after * 1e3,
                c.same_surface_spread_without_campaign_shift_m.after * 1e3,
                c.tile_strip_pairs
            );
        }
    }

    /// The datum, the campaign's rotation and the stated precision.
    fn datum_and_precision(&self, out: &mut String) {
        let mm = |v: [f64; 3]| format!("({:+.1}, {:+.1}, {:+.1})", v[0] * 1e3, v[1] * 1e3, v[2] * 1e3);
        let _ = writeln!(
            out,
            "datum error (mean trajectory position error, x y z): {} → {} mm; campaign's shift {} → {} mm",
            mm(self.datum_error_m.before),
            mm(self.datum_error_m.after),
            mm(self.campaign_shift_m.before),
            mm(self.campaign_shift_m.after)
        );
        // Degrees in, millidegrees out: the same format as `mm`.
        let _ = writeln!(
            out,
            "campaign's rotation (mean attitude error about x y z): {} → {} mdeg",
            mm(self.mean_attitude_error_deg.before),
            mm(self.mean_attitude_error_deg.after)
        );
        if let Some(p) = &self.stated_precision {
            let three = |v: [f64; 3]| format!("{:.2} / {:.2} / {:.2}", v[0], v[1], v[2]);
            let _ = writeln!(
                out,
                "stated precision (OUT/corrections, {} anchors): σ along / across / vertical {} mm, roll / pitch / \
                 heading {} mdeg; error after over σ {} and {}",
                p.anchors,
                three(p.position_sigma_rms_m.components().map(|v| v * 1e3)),
                three(p.attitude_sigma_rms_deg.components().map(|v| v * 1e3)),
                three(p.position_error_over_sigma.components()),
                three(p.attitude_error_over_sigma.components())
            );
        }
    }

    /// The largest errors, the counts, the points used, the assignment audit and the latent map.
    fn counts_and_audits(&self, out: &mut String) {
        let largest: Vec<String> = self
            .per_trajectory
            .iter()
            .filter_map(|t| {
                t.largest_error_without_datum_after
                    .along_track
                    .map(|l| format!("{} {:+.1} at {:.0} m", t.id, l.error_m * 1e3, l.arc_m))
            })
            .collect();
        if !largest.is_empty() {
            let _ = writeln!(out, "largest along-track error w/o the datum, after (mm): {}", largest.join(", "));
        }
        let _ = writeln!(
            out,
            "{} strips, {} points, {} surface points, {} tile-strip pairs, {} trajectory samples",
            self.strips, self.points, self.surface_points, self.tile_strip_pairs, self.trajectory_samples
        );
        if let Some(share) = self.surface_points_used_share {
            let _ = writeln!(out, "points used in the last iteration: {:.1} % of surface points", 100.0 * share);
        }
        if let Some(a) = &self.assignments {
            let classes: Vec<String> = a
                .wrong_share_by_class
                .iter()
                .map(|(name, c)| format!("{name} {:.2} %", 100.0 * c.wrong_share))
                .collect();
            let _ = writeln!(
                out,
                "wrong assignments in the last map pass: {:.2} % of {} observations in {} surface models ({})",
                100.0 * a.wrong_share,
                a.points,
                a.models,
                classes.join(", ")
            );
        }
        if let Some(l) = &self.latent_map {
            let classes: Vec<String> = l
                .per_class
                .iter()
                .map(|(name, c)| {
                    format!(
                        "{name} {:.2} / {:.2} / {:.2}",
                        c.error_rms_m * 1e3,
                        c.error_without_campaign_shift_rms_m * 1e3,
                        c.error_without_tile_shift_rms_m * 1e3
                    )
                })
                .collect();
            let _ = writeln!(
                out,
                "latent map: {} points, {} matched; error RMS {:.3} mm (mean {:+.3}), without the campaign's \
                 shift {:.3} mm (|error| 95th percentile {:.3}), without each tile's shift {:.3} mm; the \
                 strips' spread about it (median) {:.3} mm",
                l.points,
                l.matched,
                l.error_rms_m * 1e3,
                l.error_mean_m * 1e3,
                l.error_without_campaign_shift_rms_m * 1e3,
                l.error_without_campaign_shift_p95_abs_m * 1e3,
                l.error_without_tile_shift_rms_m * 1e3,
                l.std_median_m * 1e3
            );
            let _ = writeln!(
                out,
                "  by class, RMS / without the campaign's shift / without each tile's (mm): {}",
                classes.join(", ")
            );
        }
    }

    /// The tiles whose strips disagree most.
    fn worst_tiles(&self, out: &mut String) {
        if !self.worst_tiles_after.is_empty() {
            let _ = writeln!(out, "tiles whose strips disagree most after adjustment (offset from the tile mean, mm):");
            for t in self.worst_tiles_after.iter().take(5) {
                let offsets: Vec<String> = t.offsets_m.iter().map(|(id, o)| format!("{id} {:+.1}", o * 1e3)).collect();
                let _ = writeln!(out, "  tile {} (RMS {:.1}): {}", t.tile, t.rms_m * 1e3, offsets.join(", "));
            }
        }
    }
}
