//! The estimated mounting calibration against the simulator's calibration errors.
//!
//! `report.json`'s `calibration.unknowns` state, per scanner, the correction added to the
//! manifest's mounting; the simulator recorded its points with constant errors on top of that
//! mounting (`truth.json`'s `config.errors.calibration`). A correction that removes an error is
//! its negative, so every unknown is compared with `−error`. For the boresight that holds to
//! first order: the angles compose as a rotation, and at 0.1° the second-order terms stay
//! below 10⁻⁴°.

use super::*;
use precimap_sim::config::CalibrationErrors;
use serde::Deserialize;

/// One unknown as `report.json` states it (`calibration.unknowns[]`).
#[derive(Clone, Debug, PartialEq, Deserialize)]
pub struct ReportedUnknown {
    pub scanner: String,
    /// `boresight_roll`, `lever_arm_x`, `range_offset`, …
    pub name: String,
    /// The correction to add to the manifest's mounting, in the kind's unit (deg or m).
    pub value: f64,
    #[serde(default)]
    pub sigma: f64,
    #[serde(default = "determined_by_default")]
    pub determined: bool,
}

fn determined_by_default() -> bool {
    true
}

/// What a calibration unknown corrects.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Boresight,
    LeverArm,
    RangeOffset,
}

impl Kind {
    /// The kind and axis (0–2) of an unknown's name; `None` for a name the simulator has no
    /// error for.
    fn of(name: &str) -> Option<(Kind, usize)> {
        let axis = |suffix: &str, names: [&str; 3]| names.iter().position(|n| *n == suffix);
        if let Some(angle) = name.strip_prefix("boresight_") {
            axis(angle, ["roll", "pitch", "yaw"]).map(|a| (Kind::Boresight, a))
        } else if let Some(component) = name.strip_prefix("lever_arm_") {
            axis(component, ["x", "y", "z"]).map(|a| (Kind::LeverArm, a))
        } else {
            (name == "range_offset").then_some((Kind::RangeOffset, 0))
        }
    }

    fn unit(self) -> &'static str {
        match self {
            Kind::Boresight => "deg",
            Kind::LeverArm | Kind::RangeOffset => "m",
        }
    }
}

/// One estimated unknown against the correction that removes the simulator's error.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CalibrationComparison {
    pub scanner: String,
    pub name: String,
    /// `deg` (boresight) or `m` (lever arm, range offset): the unit of the three figures below.
    pub unit: String,
    /// The correction the adjustment estimated.
    pub estimated: f64,
    /// The correction that removes the simulator's error (`−error`; 0 for a scanner the
    /// simulator put no error on); `None` for an unknown it has no counterpart for.
    pub expected: Option<f64>,
    /// `estimated − expected`: the calibration error left in the result's mounting.
    pub error: Option<f64>,
    /// The report's formal σ, in `unit`.
    pub sigma: f64,
    /// Whether the adjustment estimated it (otherwise it was held at the manifest's value).
    pub determined: bool,
}

/// The largest |error| per kind of unknown; `None` where no unknown of that kind was compared.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct CalibrationLargestError {
    pub boresight_deg: Option<f64>,
    pub lever_arm_m: Option<f64>,
    pub range_offset_m: Option<f64>,
}

/// The estimated calibration against the simulator's ([`compare_calibration`]).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CalibrationEvaluation {
    /// In the report's order.
    pub unknowns: Vec<CalibrationComparison>,
    /// Held unknowns count too: their error is the simulator's error the result keeps.
    pub largest_error: CalibrationLargestError,
}

/// The simulator's boresight (deg) and lever-arm (m) errors of the head a manifest's scanner
/// names (`left`, `right`, or `roof`, which the simulator gives the left head's errors); `None`
/// for a scanner the simulator has no head of that name for.
fn head_errors(truth: &CalibrationErrors, scanner: &str) -> Option<([f64; 3], [f64; 3])> {
    match scanner {
        "left" | "roof" => Some((truth.boresight_left_deg, truth.lever_arm_left_m)),
        "right" => Some((truth.boresight_right_deg, truth.lever_arm_right_m)),
        _ => None,
    }
}

/// Compares every reported unknown with the correction that removes `truth`'s error. The range
/// scale error (ppm) has no unknown: a range offset estimated on a campaign with one absorbs
/// part of it, which shows as error.
pub fn compare_calibration(reported: &[ReportedUnknown], truth: &CalibrationErrors) -> CalibrationEvaluation {
    let mut largest = CalibrationLargestError::default();
    let unknowns = reported
        .iter()
        .map(|u| {
            let kind = Kind::of(&u.name);
            let expected = kind.map(|(kind, axis)| {
                let error = head_errors(truth, &u.scanner).map_or(0.0, |(boresight, lever_arm)| match kind {
                    Kind::Boresight => boresight[axis],
                    Kind::LeverArm => lever_arm[axis],
                    Kind::RangeOffset => truth.range_offset_m,
                });
                // `0.0 - x`, not `-x`: no error expects +0, not −0.
                0.0 - error
            });
            let error = expected.map(|e| u.value - e);
            if let (Some((kind, _)), Some(error)) = (kind, error) {
                let slot = match kind {
                    Kind::Boresight => &mut largest.boresight_deg,
                    Kind::LeverArm => &mut largest.lever_arm_m,
                    Kind::RangeOffset => &mut largest.range_offset_m,
                };
                *slot = Some(slot.map_or(error.abs(), |m: f64| m.max(error.abs())));
            }
            CalibrationComparison {
                scanner: u.scanner.clone(),
                name: u.name.clone(),
                unit: kind.map_or("", |(k, _)| k.unit()).to_string(),
                estimated: u.value,
                expected,
                error,
                sigma: u.sigma,
                determined: u.determined,
            }
        })
        .collect();
    CalibrationEvaluation { unknowns, largest_error: largest }
}

/// The simulator's calibration errors of the campaign (`truth.json`'s
/// `config.errors.calibration`); none where `truth.json` or that entry is missing.
pub(crate) fn read_truth_calibration(truth_dir: &Path) -> Result<CalibrationErrors, EvalError> {
    let path = truth_dir.join("truth.json");
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(CalibrationErrors::default()),
        Err(e) => return Err(EvalError::Report { path, message: format!("cannot read: {e}") }),
    };
    let value: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| EvalError::Report { path: path.clone(), message: format!("not valid JSON: {e}") })?;
    match value.pointer("/config/errors/calibration") {
        None | Some(serde_json::Value::Null) => Ok(CalibrationErrors::default()),
        Some(c) => serde_json::from_value(c.clone()).map_err(|e| EvalError::Report {
            path,
            message: format!("config.errors.calibration is not the simulator's calibration errors: {e}"),
        }),
    }
}

impl CalibrationEvaluation {
    /// The table of `precimap evaluate`: boresight in degrees, lever arm and range offset in
    /// millimetres.
    pub(crate) fn summary(&self, out: &mut String) {
        let _ = writeln!(out, "calibration against the simulator (expected: the correction that removes its error):");
        let _ = writeln!(
            out,
            "  {:<8} {:<16} {:>11} {:>11} {:>11}",
            "scanner", "unknown", "estimated", "expected", "error"
        );
        let shown = |v: Option<f64>, unit: &str| match (v, unit) {
            (None, _) => format!("{:>11}", "—"),
            (Some(v), "deg") => format!("{v:>+11.4}"),
            (Some(v), _) => format!("{:>+11.2}", v * 1e3),
        };
        for u in &self.unknowns {
            let unit = match u.unit.as_str() {
                "deg" => "deg",
                "m" => "mm",
                _ => "",
            };
            let _ = writeln!(
                out,
                "  {:<8} {:<16} {} {} {} {unit}{}",
                u.scanner,
                u.name,
                shown(Some(u.estimated), &u.unit),
                shown(u.expected, &u.unit),
                shown(u.error, &u.unit),
                if u.determined { "" } else { " (held)" }
            );
        }
        let l = &self.largest_error;
        let largest = [
            l.boresight_deg.map(|v| format!("boresight {v:.4} deg")),
            l.lever_arm_m.map(|v| format!("lever arm {:.2} mm", v * 1e3)),
            l.range_offset_m.map(|v| format!("range offset {:.2} mm", v * 1e3)),
        ];
        let largest: Vec<String> = largest.into_iter().flatten().collect();
        if !largest.is_empty() {
            let _ = writeln!(out, "largest calibration |error|: {}", largest.join(", "));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unknown(scanner: &str, name: &str, value: f64) -> ReportedUnknown {
        ReportedUnknown { scanner: scanner.into(), name: name.into(), value, sigma: 2e-4, determined: true }
    }

    fn truth() -> CalibrationErrors {
        CalibrationErrors {
            boresight_left_deg: [0.05, -0.08, 0.1],
            boresight_right_deg: [-0.1, 0.06, -0.07],
            lever_arm_left_m: [0.03, -0.02, 0.05],
            lever_arm_right_m: [-0.04, 0.05, -0.03],
            range_scale_ppm: 0.0,
            range_offset_m: 0.01,
        }
    }

    #[test]
    fn the_expected_correction_is_minus_the_simulators_error() {
        let reported = [
            unknown("left", "boresight_roll", -0.05),
            unknown("left", "boresight_pitch", 0.08),
            unknown("left", "boresight_yaw", -0.084),
            unknown("right", "lever_arm_y", -0.048),
            unknown("right", "range_offset", -0.0085),
        ];
        let e = compare_calibration(&reported, &truth());
        let expected: Vec<Option<f64>> = e.unknowns.iter().map(|u| u.expected).collect();
        assert_eq!(expected, [Some(-0.05), Some(0.08), Some(-0.1), Some(-0.05), Some(-0.01)]);
        let close = |a: Option<f64>, b: f64| (a.unwrap() - b).abs() < 1e-12;
        assert!(close(e.unknowns[0].error, 0.0) && close(e.unknowns[1].error, 0.0));
        assert!(close(e.unknowns[2].error, 0.016), "{:?}", e.unknowns[2]);
        assert!(close(e.unknowns[3].error, 0.002) && close(e.unknowns[4].error, 0.0015));
        assert_eq!(e.unknowns[2].unit, "deg");
        assert_eq!(e.unknowns[3].unit, "m");
        let l = e.largest_error;
        assert!((l.boresight_deg.unwrap() - 0.016).abs() < 1e-12);
        assert!((l.lever_arm_m.unwrap() - 0.002).abs() < 1e-12);
        assert!((l.range_offset_m.unwrap() - 0.0015).abs() < 1e-12);
        // The error's own sign: an estimate equal to the simulator's error is twice off.
        let wrong = compare_calibration(&[unknown("left", "lever_arm_z", 0.05)], &truth());
        assert!(close(wrong.unknowns[0].error, 0.1));
    }

    #[test]
    fn a_head_without_errors_expects_zero_and_held_unknowns_count() {
        // One head: the roof head carries the left head's errors; a scanner the simulator has no
        // head for expects no correction at all, the range offset included.
        let mut held = unknown("spare", "lever_arm_x", 0.0);
        held.determined = false;
        let reported = [
            unknown("roof", "boresight_pitch", 0.07),
            unknown("spare", "boresight_roll", 0.002),
            unknown("spare", "range_offset", -0.003),
            held,
            unknown("left", "range_scale", 1.0),
        ];
        let e = compare_calibration(&reported, &truth());
        assert_eq!(e.unknowns[0].expected, Some(0.08));
        assert_eq!(e.unknowns[1].expected, Some(0.0));
        assert_eq!(e.unknowns[1].error, Some(0.002));
        assert_eq!(e.unknowns[2].expected, Some(0.0));
        assert_eq!((e.unknowns[3].expected, e.unknowns[3].error), (Some(0.0), Some(0.0)));
        // No counterpart in the simulator: listed, not compared.
        assert_eq!((e.unknowns[4].expected, e.unknowns[4].error, e.unknowns[4].unit.as_str()), (None, None, ""));
        let l = e.largest_error;
        assert!((l.boresight_deg.unwrap() - 0.01).abs() < 1e-12, "{l:?}");
        assert_eq!((l.lever_arm_m, l.range_offset_m), (Some(0.0), Some(0.003)));
        let mut text = String::new();
        e.summary(&mut text);
        assert!(text.contains("(held)") && text.contains("range offset 3.00 mm"), "{text}");

        // A campaign simulated without calibration errors expects no correction anywhere.
        let none = compare_calibration(&reported[..1], &CalibrationErrors::default());
        assert_eq!((none.unknowns[0].expected, none.largest_error.boresight_deg), (Some(0.0), Some(0.07)));
        assert_eq!(none.largest_error.lever_arm_m, None);
    }

    #[test]
    fn the_reports_calibration_is_read_when_present() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("report.json");
        std::fs::write(&path, r#"{"iterations": [{"points_used": 7}]}"#).unwrap();
        let r = read_report(&path).unwrap();
        assert_eq!((r.points_used, r.calibration), (Some(7), None));
        std::fs::write(
            &path,
            r#"{"iterations": [], "calibration": {"unknowns": [{"scanner": "left", "name": "range_offset",
                "unit": "m", "value": -0.004, "sigma": 0.0002, "determined": false, "separation": 0.3,
                "held": "not determined"}], "correlation": [[1.0]]}}"#,
        )
        .unwrap();
        let unknowns = read_report(&path).unwrap().calibration.unwrap();
        assert_eq!(unknowns, [ReportedUnknown { determined: false, ..unknown("left", "range_offset", -0.004) }]);
        std::fs::write(&path, r#"{"calibration": {"unknowns": [{"scanner": "left"}]}}"#).unwrap();
        assert!(read_report(&path).is_err());
    }

    #[test]
    fn the_truths_calibration_is_read_from_truth_json() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(read_truth_calibration(dir.path()).unwrap(), CalibrationErrors::default());
        let path = dir.path().join("truth.json");
        std::fs::write(&path, r#"{"config": {"errors": {"position_sigma_m": [0.1, 0.3]}}}"#).unwrap();
        assert_eq!(read_truth_calibration(dir.path()).unwrap(), CalibrationErrors::default());
        std::fs::write(&path, r#"{"config": {"errors": {"calibration": {"range_offset_m": 0.004}}}}"#).unwrap();
        let c = read_truth_calibration(dir.path()).unwrap();
        assert_eq!((c.range_offset_m, c.boresight_left_deg), (0.004, [0.0; 3]));
        std::fs::write(&path, r#"{"config": {"errors": {"calibration": {"range_offset": 0.004}}}}"#).unwrap();
        assert!(read_truth_calibration(dir.path()).is_err());
    }
}
