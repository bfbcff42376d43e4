//! The scanners' mounting calibration across a run: its current value, each iteration's exact
//! step from the trajectories' shares ([`precimap_estimate::calibration::solve_calibration`]),
//! and what the report says of it (docs/design/calibration.md).

use crate::campaign::Campaign;
use crate::error::PipelineError;
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::{CalibrationLayout, CalibrationOptions, ScannerCalibration};
use precimap_estimate::calibration::{solve_calibration, CalibrationStep};
use precimap_estimate::{TileCalibration, TrajectorySolution};

/// The calibration of a campaign that estimates it.
#[derive(Clone, Debug)]
pub struct CalibrationState {
    pub layout: CalibrationLayout,
    pub options: CalibrationOptions,
    pub scanner_of_strip: Vec<u32>,
    /// The current calibration vector (the layout's unknowns), added to the manifest's mounting.
    pub values: Vec<f64>,
    /// Per scanner, the same values.
    pub scanners: Vec<ScannerCalibration>,
    /// The last step: its posterior covariance and which unknowns the geometry determines.
    pub last: Option<CalibrationStep>,
}

impl CalibrationState {
    /// `None` where the campaign estimates no calibration.
    pub fn new(campaign: &Campaign) -> Option<Self> {
        let layout = campaign.calibration_layout();
        (!layout.is_empty()).then(|| Self {
            values: vec![0.0; layout.len()],
            scanners: vec![ScannerCalibration::default(); layout.scanners],
            options: campaign.params.calibration.clone(),
            scanner_of_strip: campaign.scanner_of_strip(),
            layout,
            last: None,
        })
    }

    /// What a tile task takes.
    pub fn tile(&self) -> TileCalibration<'_> {
        TileCalibration { layout: &self.layout, scanner_of_strip: &self.scanner_of_strip, scanners: &self.scanners }
    }

    /// One iteration's step: solved from the solutions' shares, applied to every solution (its
    /// change measured again from `starts`, the corrections the iteration started from) and to
    /// the calibration. Solutions without shares (a step that holds the attitude) leave it as it
    /// is.
    pub fn step(
        &mut self,
        solutions: &mut [TrajectorySolution],
        starts: &[TrajectoryCorrections],
    ) -> Result<(), PipelineError> {
        if solutions.iter().all(|s| s.calibration.is_none()) {
            return Ok(());
        }
        let step = solve_calibration(
            solutions.iter().filter_map(|s| s.calibration.as_ref()),
            &self.values,
            &self.layout,
            &self.options,
        )
        .map_err(|e| PipelineError::Input { what: "the scanners' calibration".into(), message: e.to_string() })?;
        for (solution, start) in solutions.iter_mut().zip(starts) {
            precimap_estimate::solve::apply_calibration_step(solution, &step.delta, start);
        }
        self.set(self.values.iter().zip(&step.delta).map(|(v, d)| v + d).collect());
        self.last = Some(step);
        Ok(())
    }

    fn set(&mut self, values: Vec<f64>) {
        let per = self.layout.per_scanner();
        self.scanners = values.chunks(per.max(1)).map(|b| ScannerCalibration::from_block(&self.layout, b)).collect();
        self.values = values;
    }
}

/// What `report.json` says of the calibration (`calibration`).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CalibrationReport {
    /// Every unknown: its scanner, name, estimate and σ.
    pub unknowns: Vec<CalibrationEstimate>,
    /// Correlations between the unknowns, in the order of `unknowns` (zero for one held).
    pub correlation: Vec<Vec<f64>>,
}

/// One calibration unknown's estimate: the correction to add to the manifest's mounting.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CalibrationEstimate {
    pub scanner: String,
    /// `boresight_roll`, `lever_arm_x`, `range_offset`, …
    pub name: String,
    /// `deg` (boresight) or `m`.
    pub unit: String,
    pub value: f64,
    /// The formal posterior σ (the observations taken as independent), in `unit`.
    pub sigma: f64,
    /// Whether the campaign's geometry determines it within its tolerance; one that it does not
    /// is held at the manifest's value (`value` 0).
    pub determined: bool,
    /// The share of the observations' information on it that the trajectories' corrections
    /// cannot take up (0–1; near 0 they mimic it).
    pub separation: f64,
    /// Why it was held, where it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held: Option<String>,
}

impl CalibrationState {
    /// The report's section: the current estimates with the last step's precision.
    pub fn report(&self, scanner_names: &[String]) -> CalibrationReport {
        let k = self.layout.len();
        let per = self.layout.per_scanner().max(1);
        let covariance = self.last.as_ref().map(|s| s.covariance.clone()).unwrap_or_else(|| vec![0.0; k * k]);
        let determined = self.last.as_ref().map(|s| s.determined.clone()).unwrap_or_else(|| vec![false; k]);
        let unknowns = (0..k)
            .map(|i| {
                let (kind, component) = self.layout.kind_of(i % per);
                let (prior, tolerance) = self.options.prior_and_tolerance(kind);
                let scale = if kind == precimap_core::CalibrationUnknown::Boresight { 1f64.to_degrees() } else { 1.0 };
                let unit = if scale == 1.0 { "m" } else { "deg" };
                let sigma = covariance[i * k + i].max(0.0).sqrt();
                let held = (!determined[i]).then(|| match &self.last {
                    None => "no step estimated the calibration (no iteration estimated the attitude)".to_string(),
                    Some(step) => format!(
                        "the campaign's geometry does not separate it from the trajectories' own errors (separation {:.3}, \
                         at least {} needed; σ {:.3} against a tolerance of {} {unit}, prior σ {} {unit}); it is held at the \
                         manifest's value. Drives that turn and that see the same surfaces from both sides separate it; or \
                         leave it out of parameters.calibration.estimate",
                        step.separation[i],
                        self.options.min_separation,
                        sigma * scale,
                        tolerance * scale,
                        prior * scale
                    ),
                });
                CalibrationEstimate {
                    scanner: scanner_names.get(i / per).cloned().unwrap_or_default(),
                    name: kind.names()[component].to_string(),
                    unit: unit.into(),
                    value: self.values[i] * scale,
                    sigma: sigma * scale,
                    determined: determined[i],
                    separation: self.last.as_ref().map_or(0.0, |s| s.separation[i]),
                    held,
                }
            })
            .collect();
        let correlation = (0..k)
            .map(|i| {
                (0..k)
                    .map(|j| {
                        let d = (covariance[i * k + i] * covariance[j * k + j]).sqrt();
                        if d > 0.0 {
                            covariance[i * k + j] / d
                        } else {
                            0.0
                        }
                    })
                    .collect()
            })
            .collect();
        CalibrationReport { unknowns, correlation }
    }
}
