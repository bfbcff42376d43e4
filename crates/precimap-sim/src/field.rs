//! A simulated campaign as it comes from the field: the same passes as an Applanix SBET in
//! geographic coordinates (GPS week seconds, a wander-azimuth frame) and the same strips in a UTM
//! CRS with adjusted standard GPS time, converted from the local-frame campaign [`crate::simulate`]
//! wrote. The local frame is the processing frame of the field manifest (its origin is the
//! simulation's origin), so both campaigns describe the same points and poses. Each SBET comes
//! with an SMRMSG accuracy file whose σ follow the pass's simulated error process: its drawn σ,
//! growing with the drift of a GNSS outage and shrinking as it decays. Control targets are
//! stated in the processing CRS's grid.

use crate::gnss::Outage;
use crate::scan::LAS_SCALE;
use crate::SimError;
use precimap_formats::gps_time::{self, TimeConvention};
use precimap_formats::navigation::{navigation_pose, AttitudeConvention, NavSamples};
use precimap_formats::sbet::NavAccuracy;
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
    let truth_path = local.join("truth/truth.json");
    let truth: serde_json::Value =
        std::fs::read(&truth_path).map_err(|source| SimError::Io { path: truth_path.clone(), source }).and_then(
            |b| serde_json::from_slice(&b).map_err(|source| SimError::Json { path: truth_path.clone(), source }),
        )?;
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
        let accuracy = pass_accuracy(&truth, &t.id, data.times(), to_week)
            .ok_or_else(|| format_error(&truth_path, format!("no error statistics of trajectory {}", t.id)))?;
        let uri = format!("trajectories/{}.smrmsg", t.id);
        precimap_formats::sbet::write_smrmsg(&out.join(&uri), &accuracy)?;
        t.accuracy_uri = Some(uri);
    }
    let ext = if laz { "laz" } else { "las" };
    for s in &mut manifest.strips {
        let uri = format!("strips/{}.{ext}", s.id);
        convert_strip(&local.join(&s.uri), &out.join(&uri), &georef, Direction::ToGrid)?;
        s.uri = uri;
    }
    // Control targets in the processing CRS's grid, as a surveyor delivers them.
    if let Some(control) = &mut manifest.control {
        for t in &mut control.targets {
            t.position_m = georef
                .frame
                .grid_from_local(&precimap_core::Vec3::from(t.position_m))
                .map_err(|e| format_error(&manifest_path, format!("control target {}: {e}", t.id)))?;
        }
        control.crs = Some(FIELD_CRS);
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

/// Smallest σ written (metres, degrees): an error model without a position or attitude error
/// still has a navigation solution of finite accuracy.
const SIGMA_FLOOR: (f64, f64) = (0.005, 0.001);

/// The accuracy of pass `id` (from `truth.json`) at one record per second over `times`
/// (adjusted standard GPS time; written in week seconds, `to_week` added): north, east, down σ
/// the pass's drawn σ with an outage's drift added in quadrature, roll and pitch σ as drawn,
/// heading σ with the outage's heading drift. `None` without the pass's statistics.
fn pass_accuracy(truth: &serde_json::Value, id: &str, times: &[f64], to_week: f64) -> Option<NavAccuracy> {
    let pass = truth["trajectories"].as_array()?.iter().find(|t| t["id"] == id)?;
    let triple = |v: &serde_json::Value| -> Option<[f64; 3]> {
        let a = v.as_array()?;
        Some([a.first()?.as_f64()?, a.get(1)?.as_f64()?, a.get(2)?.as_f64()?])
    };
    let [sx, sy, sz] = triple(&pass["errors"]["sigma_position_m"])?.map(|s| s.max(SIGMA_FLOOR.0));
    let [roll, pitch, heading] = triple(&pass["errors"]["sigma_attitude_deg"])?.map(|s| s.max(SIGMA_FLOOR.1));
    let outage: Option<Outage> = serde_json::from_value(pass["outage"].clone()).ok();
    let (&first, &last) = (times.first()?, times.last()?);
    let mut out = NavAccuracy::default();
    let records = ((last - first).ceil() as usize).max(1);
    for k in 0..=records {
        let t = (first + k as f64).min(last);
        let (horizontal, down, turn) = outage.map_or((0.0, 0.0, 0.0), |o| {
            let w = o.weight(t);
            (o.peak_m[0].hypot(o.peak_m[1]) * w, o.peak_m[2].abs() * w, o.peak_heading_deg.abs() * w)
        });
        out.times.push(t + to_week);
        out.position_sigma_m.push([sy.hypot(horizontal), sx.hypot(horizontal), sz.hypot(down)]);
        out.attitude_sigma_deg.push([roll, pitch, heading.hypot(turn)]);
    }
    Some(out)
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Direction {
    ToGrid,
    ToLocal,
}

/// The result of a field campaign (`precimap run` of the manifest [`write_field_campaign`]
/// wrote) in the local frame, as `precimap evaluate` compares results with the truth: strips
/// and trajectories from the processing CRS's grid back into the frame at `origin_grid_m`,
/// `report.json` and the corrections tables (vehicle frame) as they are. Trajectory times in
/// GPS week seconds (the SBET's) become adjusted standard time again, the week `week`'s
/// ([`write_field_campaign`] returns it).
pub fn result_to_local(result: &Path, out: &Path, origin_grid_m: [f64; 3], week: u32) -> Result<(), SimError> {
    let to_adjusted = gps_time::offset(TimeConvention::WeekSeconds, TimeConvention::AdjustedStandard, week);
    let spec = CrsSpec { processing: FIELD_CRS, origin_grid_m, strips: None };
    let georef = spec.georeference().map_err(|e| format_error(result, e))?;
    for dir in ["strips", "trajectories", "corrections"] {
        let (from, to) = (result.join(dir), out.join(dir));
        std::fs::create_dir_all(&to).map_err(|source| SimError::Io { path: to.clone(), source })?;
        let entries = std::fs::read_dir(&from).map_err(|source| SimError::Io { path: from.clone(), source })?;
        let mut names: Vec<_> = entries.filter_map(|e| e.ok().map(|e| e.file_name())).collect();
        names.sort();
        for name in names {
            let (src, dst) = (from.join(&name), to.join(&name));
            let ext = src.extension().and_then(|e| e.to_str()).unwrap_or_default().to_ascii_lowercase();
            match (dir, ext.as_str()) {
                ("strips", "las" | "laz") => convert_strip(&src, &dst, &georef, Direction::ToLocal)?,
                ("trajectories", "csv") => {
                    let grid = precimap_formats::TrajectoryRef {
                        crs: Some(FIELD_CRS),
                        ..precimap_formats::TrajectoryRef::csv("result", "result.csv")
                    };
                    let t =
                        precimap_formats::trajectory::load_trajectory(&src, &grid, None, Some(&georef.frame), None)?;
                    let data = t.trajectory;
                    let times: Vec<f64> = data
                        .times()
                        .iter()
                        .map(|&t| if t < gps_time::SECONDS_PER_WEEK { t + to_adjusted } else { t })
                        .collect();
                    precimap_formats::write_trajectory_csv(&dst, &times, data.positions(), data.rpy_deg())?;
                }
                ("trajectories", _) => {}
                _ => {
                    std::fs::copy(&src, &dst).map_err(|source| SimError::Io { path: dst.clone(), source })?;
                }
            }
        }
    }
    // The latent map, in the grid with its CRS, back into the frame.
    let latent = result.join("latent");
    if latent.is_dir() {
        let to = out.join("latent");
        std::fs::create_dir_all(&to).map_err(|source| SimError::Io { path: to.clone(), source })?;
        let entries = std::fs::read_dir(&latent).map_err(|source| SimError::Io { path: latent.clone(), source })?;
        for entry in entries {
            let src = entry.map_err(|source| SimError::Io { path: latent.clone(), source })?.path();
            let mut points = precimap_formats::read_latent_map(&src)?;
            for p in &mut points {
                let local = georef.frame.local_from_grid(p.position).map_err(|e| format_error(&src, e))?;
                p.position = local.into();
            }
            let name = src.file_name().map(std::path::PathBuf::from).unwrap_or_default();
            precimap_formats::write_latent_map(&to.join(name), &points, None)?;
        }
    }
    let report = result.join("report.json");
    std::fs::copy(&report, out.join("report.json")).map_err(|source| SimError::Io { path: report, source })?;
    Ok(())
}

/// Rewrites a strip between the local frame and the processing CRS's grid, every attribute kept.
fn convert_strip(
    src: &Path,
    dst: &Path,
    georef: &precimap_formats::crs::Georeference,
    direction: Direction,
) -> Result<(), SimError> {
    let mut reader = las::Reader::from_path(src).map_err(|e| format_error(src, e))?;
    let crs = &georef.strip_crs;
    let origin = georef.frame.origin_grid_m();
    let wkt = (direction == Direction::ToGrid).then(|| crs.wkt());
    let declarations = StripDeclarations { wkt, adjusted_standard_time: true };
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
        let position = match direction {
            Direction::ToGrid => georef.strip_from_local([p.x, p.y, p.z]),
            Direction::ToLocal => georef.local_from_strip([p.x, p.y, p.z]),
        }
        .map_err(|e| format_error(src, format!("point {i}: {e}")))?;
        writer.push(&NewPoint {
            position,
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
