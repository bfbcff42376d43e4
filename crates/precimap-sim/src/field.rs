//! A simulated campaign as it comes from the field: the same passes as an Applanix SBET in
//! geographic coordinates (GPS week seconds, a wander-azimuth frame) and the same strips in a UTM
//! CRS with adjusted standard GPS time, converted from the local-frame campaign [`crate::simulate`]
//! wrote. The local frame is the processing frame of the field manifest (its origin is the
//! simulation's origin), so both campaigns describe the same points and poses.

use crate::scan::LAS_SCALE;
use crate::SimError;
use precimap_formats::gps_time::{self, TimeConvention};
use precimap_formats::navigation::{navigation_pose, AttitudeConvention, NavSamples};
use precimap_formats::{
    load_manifest, read_trajectory_csv, CrsSpec, FormatError, NewPoint, StripDeclarations, StripWriter,
    TrajectoryFormat,
};
use std::path::Path;

/// The processing CRS of simulated field campaigns: WGS 84 / UTM zone 32N (the simulation's
/// origin, 549 800 E 5 803 400 N, lies near Hannover).
pub const FIELD_CRS: u32 = 32632;

/// The wander angle written for sample `i` (radians): a slowly turning wander-azimuth frame, so
/// that readers must subtract it.
fn wander(i: usize) -> f64 {
    0.4 + 0.3 * (i as f64 * 1e-3).sin()
}

fn format_error(path: &Path, e: impl std::fmt::Display) -> SimError {
    SimError::Format(FormatError::File { path: path.to_path_buf(), message: e.to_string() })
}

/// Converts the local-frame campaign in `local` (as [`crate::simulate`] wrote it, times taken as
/// adjusted standard GPS time) into a field campaign in `out`: `manifest.json`,
/// `trajectories/{id}.sbet`, `strips/{id}.las|laz`. Its local frame has its origin at
/// `origin_grid_m` in [`FIELD_CRS`]. Returns the GPS week of the first pass.
pub fn write_field_campaign(local: &Path, out: &Path, origin_grid_m: [f64; 3], laz: bool) -> Result<u32, SimError> {
    let manifest_path = local.join("manifest.json");
    let mut manifest = load_manifest(&manifest_path).map_err(|e| format_error(&manifest_path, e))?;
    let spec = CrsSpec { processing: FIELD_CRS, origin_grid_m, strips: None };
    let georef = spec.georeference().map_err(|e| format_error(&manifest_path, e))?;
    for dir in ["trajectories", "strips"] {
        std::fs::create_dir_all(out.join(dir)).map_err(|source| SimError::Io { path: out.join(dir), source })?;
    }
    let mut first_week = None;
    for t in &mut manifest.trajectories {
        let data = read_trajectory_csv(&local.join(&t.uri))?;
        let week = gps_time::week_of_adjusted(data.times()[0])
            .ok_or_else(|| format_error(&local.join(&t.uri), "times are not GPS times"))?;
        first_week.get_or_insert(week);
        let to_week = gps_time::offset(TimeConvention::AdjustedStandard, TimeConvention::WeekSeconds, week);
        let mut nav = NavSamples::with_capacity(data.len(), AttitudeConvention::Navigation);
        for ((time, p), r) in data.times().iter().zip(data.positions()).zip(data.rotations()) {
            let (g, attitude) = navigation_pose(&georef.frame, p, r);
            nav.times.push(time + to_week);
            nav.coordinates.push(g);
            nav.attitude.push(attitude);
        }
        let wanders: Vec<f64> = (0..nav.len()).map(wander).collect();
        t.uri = format!("trajectories/{}.sbet", t.id);
        t.format = TrajectoryFormat::Sbet;
        precimap_formats::sbet::write_sbet(&out.join(&t.uri), &nav, &wanders)?;
    }
    let ext = if laz { "laz" } else { "las" };
    for s in &mut manifest.strips {
        let uri = format!("strips/{}.{ext}", s.id);
        convert_strip(&local.join(&s.uri), &out.join(&uri), &georef)?;
        s.uri = uri;
    }
    manifest.name = format!("{}-field", manifest.name);
    manifest.crs = Some(spec);
    let path = out.join("manifest.json");
    let mut value = serde_json::to_value(&manifest).map_err(|source| SimError::Json { path: path.clone(), source })?;
    if let Some(obj) = value.as_object_mut() {
        obj.remove("parameters");
    }
    crate::write_json(&path, &value)?;
    Ok(first_week.unwrap_or(0))
}

/// Rewrites a local-frame strip in the processing CRS's grid, every attribute kept.
fn convert_strip(src: &Path, dst: &Path, georef: &precimap_formats::crs::Georeference) -> Result<(), SimError> {
    let mut reader = las::Reader::from_path(src).map_err(|e| format_error(src, e))?;
    let crs = &georef.strip_crs;
    let origin = georef.frame.origin_grid_m();
    let declarations = StripDeclarations { wkt: Some(crs.wkt()), adjusted_standard_time: true };
    let mut writer = StripWriter::create_with(
        dst,
        origin.map(|v| (v / 1000.0).round() * 1000.0),
        LAS_SCALE,
        "precimap-sim VMX-250",
        concat!("precimap-sim ", env!("CARGO_PKG_VERSION")),
        declarations,
    )?;
    let data = reader.read_all().map_err(|e| format_error(src, e))?;
    for (i, point) in data.points().enumerate() {
        let p = point.map_err(|e| format_error(src, format!("point {i}: {e}")))?;
        let grid =
            georef.strip_from_local([p.x, p.y, p.z]).map_err(|e| format_error(src, format!("point {i}: {e}")))?;
        writer.push(&NewPoint {
            position: grid,
            gps_time: p.gps_time.unwrap_or(f64::NAN),
            scan_angle_deg: p.scan_angle,
            channel: p.scanner_channel,
            intensity: p.intensity,
            return_number: p.return_number,
            number_of_returns: p.number_of_returns,
            point_source_id: p.point_source_id,
            classification: u8::from(p.classification),
        })?;
    }
    writer.finish()?;
    Ok(())
}
