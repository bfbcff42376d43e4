//! Field campaigns at the strip boundary: a strip's declared CRS against the campaign's, its GPS
//! times on its trajectory's scale, and its coordinates in the processing frame and back.

use crate::campaign::{StripEntry, TrajectoryEntry};
use crate::error::PipelineError;
use precimap_core::RingSource;
use precimap_formats::gps_time::{describe_range, TimeConvention};
use precimap_formats::trajectory::strip_clock;
use precimap_formats::{read_strip_with_ring, strip_info, StripInfo, StripPoints};

fn input_error(entry: &StripEntry, message: String) -> PipelineError {
    PipelineError::Input { what: format!("strip {} ({})", entry.id, entry.path.display()), message }
}

/// A strip that declares a CRS must declare the campaign's strip CRS.
pub fn check_strip_crs(entry: &StripEntry, info: &StripInfo) -> Result<(), PipelineError> {
    let (Some(georef), Some(declared)) = (&entry.georef, &info.crs) else { return Ok(()) };
    let want = &georef.strip_crs;
    match declared.epsg {
        Some(code) if code == want.epsg() => Ok(()),
        Some(_) => Err(input_error(
            entry,
            format!(
                "the file declares {declared} but the campaign's strips are in {want} ($.crs.strips, or \
                 $.crs.processing when absent); reproject the strip or set $.crs.strips to its CRS"
            ),
        )),
        None => Err(input_error(
            entry,
            format!(
                "the file declares a CRS ({declared}) that names no EPSG code, so it cannot be checked against the \
                 campaign's {want}; re-export the strip with an EPSG-coded CRS"
            ),
        )),
    }
}

/// Reads a strip for estimation: CRS checked, GPS times on its trajectory's scale and inside its
/// span, coordinates in the processing frame; with `ring`, each point's ring number from there.
pub fn read_strip_in_frame(
    entry: &StripEntry,
    traj: &TrajectoryEntry,
    ring: Option<&RingSource>,
) -> Result<StripPoints, PipelineError> {
    let info = strip_info(&entry.path)?;
    check_strip_crs(entry, &info)?;
    let mut points = read_strip_with_ring(&entry.path, ring)?;
    let Some((first, last)) = points.gps_time_span() else { return Ok(points) };
    let (offset, week) = strip_clock(info.time_convention, points.gps_time[0], &traj.clock);
    let (start, end) = traj.data.time_span();
    if first + offset < start || last + offset > end {
        let traj_convention = traj.clock.time.unwrap_or(info.time_convention);
        return Err(input_error(
            entry,
            format!(
                "its GPS times span {} but trajectory {} ({}) covers only {}; supply a trajectory that covers the \
                 whole strip, cut the strip to the trajectory's span, or check $.gps_week",
                describe_range(first, last, info.time_convention, week),
                traj.id,
                traj.path.display(),
                describe_range(start, end, traj_convention, week)
            ),
        ));
    }
    if offset != 0.0 {
        points.gps_time.iter_mut().for_each(|t| *t += offset);
    }
    if let Some(georef) = &entry.georef {
        for i in 0..points.len() {
            let p = georef.local_from_strip([points.x[i], points.y[i], points.z[i]]).map_err(|e| {
                PipelineError::Format(precimap_formats::FormatError::Point {
                    path: entry.path.clone(),
                    index: i as u64,
                    message: format!("{e}; check the strip's CRS"),
                })
            })?;
            [points.x[i], points.y[i], points.z[i]] = p;
        }
    }
    Ok(points)
}

/// A strip's GPS time convention from its header, its CRS checked.
pub fn strip_time_convention(entry: &StripEntry) -> Result<TimeConvention, PipelineError> {
    let info = strip_info(&entry.path)?;
    check_strip_crs(entry, &info)?;
    Ok(info.time_convention)
}
