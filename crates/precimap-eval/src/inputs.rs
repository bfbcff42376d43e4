//! Reading the campaign's trajectories, the result's report and corrections tables.

use super::*;

/// Every trajectory's corrections table (`OUT/corrections/{id}.csv`), summed; `None` unless each
/// trajectory has one (a partial figure would mislead).
pub(crate) fn read_corrections_tables<'a>(
    result_dir: &Path,
    trajectories: impl Iterator<Item = &'a str>,
) -> Result<Option<SigmaSums>, EvalError> {
    let mut sums = SigmaSums::default();
    for id in trajectories {
        let path = result_dir.join("corrections").join(format!("{id}.csv"));
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(EvalError::Report { path, message: e.to_string() }),
        };
        precision::add_table(&mut sums, &text, &path)?;
    }
    Ok(Some(sums))
}

pub(crate) fn check_id(what: &'static str, id: &str) -> Result<(), EvalError> {
    if id.is_empty() || id == "." || id == ".." || id.contains(['/', '\\']) {
        return Err(EvalError::BadId { what, id: id.to_string() });
    }
    Ok(())
}

/// One trajectory's input, truth and result.
pub(crate) struct LoadedTrajectory {
    pub(crate) input: Trajectory,
    pub(crate) truth: Trajectory,
    pub(crate) result: Trajectory,
}

pub(crate) fn load_trajectory(
    id: &str,
    input: &Path,
    truth_dir: &Path,
    result_dir: &Path,
) -> Result<LoadedTrajectory, EvalError> {
    let truth = read_trajectory_csv(&truth_dir.join("trajectories").join(format!("{id}.csv")))?;
    let result_path = result_dir.join("trajectories").join(format!("{id}.csv"));
    if !result_path.is_file() {
        return Err(EvalError::MissingResultTrajectory { trajectory: id.to_string(), path: result_path });
    }
    Ok(LoadedTrajectory { input: read_trajectory_csv(input)?, truth, result: read_trajectory_csv(&result_path)? })
}

/// What the evaluation takes from report.json.
#[derive(Debug, Default)]
pub(crate) struct ReportFigures {
    /// `points_used` of the last iteration.
    pub(crate) points_used: Option<u64>,
    /// `calibration.unknowns`, where the run estimated the mounting calibration.
    pub(crate) calibration: Option<Vec<ReportedUnknown>>,
}

/// `points_used` of the last iteration and the calibration estimates in report.json; neither
/// without a report or those fields.
pub(crate) fn read_report(path: &Path) -> Result<ReportFigures, EvalError> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(ReportFigures::default()),
        Err(e) => return Err(EvalError::Report { path: path.into(), message: format!("cannot read: {e}") }),
    };
    let value: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| EvalError::Report { path: path.into(), message: format!("not valid JSON: {e}") })?;
    let last = value.get("iterations").and_then(|it| it.as_array()).and_then(|it| it.last());
    let calibration = match value.pointer("/calibration/unknowns") {
        None | Some(serde_json::Value::Null) => None,
        Some(unknowns) => Some(
            serde_json::from_value(unknowns.clone())
                .map_err(|e| EvalError::Report { path: path.into(), message: format!("calibration.unknowns: {e}") })?,
        ),
    };
    Ok(ReportFigures { points_used: last.and_then(|it| it.get("points_used")).and_then(|v| v.as_u64()), calibration })
}
