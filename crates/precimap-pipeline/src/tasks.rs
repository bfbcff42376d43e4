//! The tasks of the task graph (ARCHITECTURE.md) as functions over files: each reads its inputs, calls the pure
//! numeric function of `precimap-estimate`, and writes its outputs. The in-process driver calls
//! them directly; a job framework can call the same functions one task per invocation.

use crate::campaign::{Campaign, StripEntry, TrajectoryEntry};
use crate::error::PipelineError;
use precimap_core::corrections::{apply, AnchorCovariance, TrajectoryCorrections};
use precimap_core::geom::{rpy_from_rot, so3_exp, Mat3};
use precimap_core::{IterationStep, LatentMapPoint, Parameters, ScannerCalibration, TileKey, Vec3};
use precimap_estimate::usable_share_problem;
use precimap_estimate::{
    estimate_tile_recording, prepare_strip_observed, AnchorBlock, CalibrationNormals, CurvatureModel, GeometryCursor,
    LatentGather, PreparePhase, PrepareStats, PreparedStrip, SegmentParams, StripContext, StripSamples,
    TileCalibration, TileChunk, TileEstimate, TrajectorySolution, UsedPoint,
};
use precimap_formats::crs::Georeference;
use std::fs;
use std::path::{Path, PathBuf};

/// Where a tile chunk of one strip lives in the work folder.
pub fn chunk_path(work: &Path, tile: TileKey, strip_id: &str) -> PathBuf {
    work.join("tiles").join(tile.to_string()).join(format!("{strip_id}.chunk"))
}

/// Where the per-point segment ids of one strip live in the work folder (`run` moves the folder
/// to `OUT/segments`).
pub fn segments_path(work: &Path, strip_id: &str) -> PathBuf {
    work.join("segments").join(format!("{strip_id}.seg"))
}

/// Writes a file atomically (temporary name, then rename), so a reader never sees half a file.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), PipelineError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    fs::create_dir_all(dir).map_err(|e| PipelineError::io(dir, e))?;
    let tmp = path.with_extension("partial");
    fs::write(&tmp, bytes).map_err(|e| PipelineError::io(&tmp, e))?;
    fs::rename(&tmp, path).map_err(|e| PipelineError::io(path, e))
}

#[derive(Debug)]
pub struct PrepareOutcome {
    pub stats: PrepareStats,
    pub tiles: Vec<TileKey>,
}

/// `segment_strip`: reads one strip, checks it against its trajectory, segments it, and writes its
/// tile chunks and its per-point segment ids (`segments/{strip}.seg`).
pub fn prepare_strip_task(campaign: &Campaign, strip: usize, work: &Path) -> Result<PrepareOutcome, PipelineError> {
    let entry = &campaign.strips[strip];
    let prepared = prepare_strip_in_memory(campaign, strip, &SegmentParams::default())?;
    write_atomic(&segments_path(work, &entry.id), &precimap_formats::encode_segments(&prepared.segment))?;
    let mut tiles = Vec::with_capacity(prepared.chunks.len());
    for chunk in &prepared.chunks {
        write_atomic(&chunk_path(work, chunk.tile, &entry.id), &chunk.encode())?;
        tiles.push(chunk.tile);
    }
    Ok(PrepareOutcome { stats: prepared.stats, tiles })
}

/// Reads strip `strip` of the campaign and prepares it (geometry, scan image, segmentation,
/// tile chunks) without writing anything. A corrupt or truncated strip is an error naming the
/// file and the point index.
pub fn prepare_strip_in_memory(
    campaign: &Campaign,
    strip: usize,
    segment_params: &SegmentParams,
) -> Result<PreparedStrip, PipelineError> {
    prepare_strip_in_memory_observed(campaign, strip, segment_params, &mut |_| {})
}

/// [`prepare_strip_in_memory`] calling `phase_done` at the end of each phase (decoding the file,
/// then the phases of [`precimap_estimate::prepare_strip_observed`]), for benchmarks.
pub fn prepare_strip_in_memory_observed(
    campaign: &Campaign,
    strip: usize,
    segment_params: &SegmentParams,
    phase_done: &mut dyn FnMut(PreparePhase),
) -> Result<PreparedStrip, PipelineError> {
    let entry = &campaign.strips[strip];
    let traj = &campaign.trajectories[entry.trajectory as usize];
    prepare_strip_chunks_observed(entry, strip as u32, traj, &campaign.params, segment_params, phase_done)
}

/// The storage-free part of `segment_strip` over explicit entries (what a job-framework executor
/// has): reads the strip file, checks it against its trajectory and returns its segment ids and
/// tile chunks in memory. `strip_index` and `entry.trajectory` are the campaign-wide indices the
/// chunks carry.
pub fn prepare_strip_chunks(
    entry: &StripEntry,
    strip_index: u32,
    traj: &TrajectoryEntry,
    params: &Parameters,
    segment_params: &SegmentParams,
) -> Result<PreparedStrip, PipelineError> {
    prepare_strip_chunks_observed(entry, strip_index, traj, params, segment_params, &mut |_| {})
}

fn prepare_strip_chunks_observed(
    entry: &StripEntry,
    strip_index: u32,
    traj: &TrajectoryEntry,
    params: &Parameters,
    segment_params: &SegmentParams,
    phase_done: &mut dyn FnMut(PreparePhase),
) -> Result<PreparedStrip, PipelineError> {
    let points = crate::field::read_strip_in_frame(entry, traj, params.ring.as_ref())?;
    phase_done(PreparePhase::Decode);
    let samples = StripSamples {
        x: &points.x,
        y: &points.y,
        z: &points.z,
        gps_time: &points.gps_time,
        scan_angle_deg: &points.scan_angle_deg,
        channel: &points.channel,
        ring: &points.ring,
    };
    let ctx = StripContext {
        strip: strip_index,
        trajectory: entry.trajectory,
        trajectory_data: &traj.data,
        lever_arm: entry.lever_arm,
        params,
        segment: segment_params,
    };
    let prepared = prepare_strip_observed(&samples, &ctx, phase_done).map_err(|source| PipelineError::Prepare {
        strip: entry.id.clone(),
        path: entry.path.clone(),
        source,
    })?;
    if let Some(problem) = usable_share_problem(&prepared.stats, params.min_usable_share) {
        let what = format!("strip {} ({})", entry.id, entry.path.display());
        if !params.allow_low_usable_share {
            return Err(PipelineError::Input { what, message: problem });
        }
        tracing::warn!("{what}: {problem}");
    }
    Ok(prepared)
}

/// Reads the chunks of one tile (strips in the given order).
pub fn load_tile(work: &Path, tile: TileKey, strip_ids: &[&str]) -> Result<Vec<TileChunk>, PipelineError> {
    strip_ids
        .iter()
        .map(|id| {
            let path = chunk_path(work, tile, id);
            let bytes = fs::read(&path).map_err(|e| PipelineError::io(&path, e))?;
            TileChunk::decode(&bytes).map_err(|source| PipelineError::Chunk { path, source })
        })
        .collect()
}

/// What an estimate task gathers besides its blocks and statistics
/// ([`precimap_estimate::estimate_tile_recording`]).
#[derive(Debug, Default)]
pub struct Gather<'a> {
    /// Every observation's surface model (the assignment audit).
    pub used: Option<&'a mut Vec<UsedPoint>>,
    /// What it keeps of the latent map: its standard deviation per cell (QC), the map itself.
    pub latent: LatentGather,
}

/// `estimate_tile` over chunk files, gathering what `gather` asks for.
#[allow(clippy::too_many_arguments)]
pub fn estimate_tile_task(
    work: &Path,
    tile: TileKey,
    strip_ids: &[&str],
    corrections: &[TrajectoryCorrections],
    campaign: &Campaign,
    step: &IterationStep,
    calibration: Option<&TileCalibration>,
    gather: Gather,
) -> Result<TileEstimate, PipelineError> {
    let chunks = load_tile(work, tile, strip_ids)?;
    let control: Vec<_> = campaign
        .control
        .iter()
        .filter(|t| precimap_estimate::control::reaches_tile(t, tile, &campaign.params))
        .cloned()
        .collect();
    let params = &campaign.params;
    estimate_tile_recording(tile, &chunks, corrections, params, step, &control, calibration, gather.used, gather.latent)
        .map_err(|source| PipelineError::Estimate { tile: tile.to_string(), source })
}

/// The positions of a trajectory's anchors `first..=last` (the common-mode field acts at their
/// horizontal positions, the campaign's rotation about their centre).
pub fn anchor_positions(
    trajectory: &TrajectoryEntry,
    anchor_spacing_m: f64,
    (first, last): (u32, u32),
) -> Vec<[f64; 3]> {
    let count = (last.saturating_sub(first) + 1) as usize;
    trajectory.data.positions_along(anchor_spacing_m, first, count)
}

/// `solve_trajectory` over the blocks every tile emitted for one trajectory; the change is
/// measured from `iteration_start`. `process`: the trajectory's own curvature σ's, where the
/// campaign estimates them.
#[allow(clippy::too_many_arguments)]
pub fn solve_trajectory_task<'a>(
    campaign: &Campaign,
    trajectory: usize,
    blocks: impl IntoIterator<Item = &'a AnchorBlock>,
    current: &TrajectoryCorrections,
    previous: Option<&TrajectoryCorrections>,
    iteration_start: &TrajectoryCorrections,
    prior: Option<&[[f64; 6]]>,
    step: &IterationStep,
    with_sigma: bool,
    calibration: Option<&CalibrationNormals>,
    process: Option<&CurvatureModel>,
) -> Result<TrajectorySolution, PipelineError> {
    precimap_estimate::solve_trajectory(
        blocks,
        current,
        previous,
        Some(iteration_start),
        &campaign.params,
        prior,
        step.rotation,
        with_sigma,
        calibration,
        process,
    )
    .map_err(|source| PipelineError::Solve { trajectory: campaign.trajectories[trajectory].id.clone(), source })
}

/// `export_strip`: every input point, same order, all attributes, coordinates corrected.
pub fn export_strip_task(
    campaign: &Campaign,
    strip: usize,
    corrections: &TrajectoryCorrections,
    mounting: Option<&ScannerCalibration>,
    out_dir: &Path,
) -> Result<(PathBuf, u64), PipelineError> {
    let entry = &campaign.strips[strip];
    let traj = &campaign.trajectories[entry.trajectory as usize];
    let dst = out_dir.join("strips").join(export_strip_name(entry));
    fs::create_dir_all(dst.parent().unwrap_or(out_dir)).map_err(|e| PipelineError::io(out_dir, e))?;
    let written = export_strip_file(entry, traj, campaign.params.anchor_spacing_m, corrections, mounting, &dst)?;
    Ok((dst, written))
}

/// `{strip id}.{las|laz}`: an exported strip keeps its input's compression.
pub fn export_strip_name(entry: &StripEntry) -> String {
    let extension = entry.path.extension().and_then(|e| e.to_str()).unwrap_or("las").to_ascii_lowercase();
    format!("{}.{extension}", entry.id)
}

/// Writes the corrected copy of `entry`'s strip file to `dst`; returns the number of points.
/// `mounting`: the scanner's estimated calibration, applied before the corrections.
pub fn export_strip_file(
    entry: &StripEntry,
    traj: &TrajectoryEntry,
    anchor_spacing_m: f64,
    corrections: &TrajectoryCorrections,
    mounting: Option<&ScannerCalibration>,
    dst: &Path,
) -> Result<u64, PipelineError> {
    let mounting = mounting.filter(|m| !m.is_zero());
    let mut uncovered = None;
    let mut unmapped = None;
    let mut cursor = GeometryCursor::new(&traj.data, &entry.lever_arm, anchor_spacing_m);
    let convention = crate::field::strip_time_convention(entry)?;
    let mut offset = None;
    let georef = entry.georef.as_deref();
    let correct = |i: usize, xyz: [f64; 3], gps_time: f64| {
        let offset = *offset
            .get_or_insert_with(|| precimap_formats::trajectory::strip_clock(convention, gps_time, &traj.clock).0);
        let local = match georef.map(|g| g.local_from_strip(xyz)) {
            None => xyz,
            Some(Ok(p)) => p,
            Some(Err(e)) => {
                unmapped.get_or_insert((i, e));
                return xyz;
            }
        };
        let t = gps_time + offset;
        let moved = match cursor.at(t, local) {
            Some(g) => {
                let (mut t0, mut r) = (g.t0, g.r);
                if let Some(m) = mounting {
                    let attitude = cursor.attitude(t).map(|v| v as f32);
                    let (head, beam) = m.apply(&precimap_core::calibration::attitude_matrix(attitude), r);
                    t0 = std::array::from_fn(|a| t0[a] + head[a]);
                    r = beam;
                }
                apply(t0, r, &corrections.at(g.anchor, g.lambda))
            }
            None => {
                uncovered.get_or_insert(i);
                return xyz;
            }
        };
        match georef.map(|g| g.strip_from_local(moved)) {
            None => moved,
            Some(Ok(p)) => p,
            Some(Err(e)) => {
                unmapped.get_or_insert((i, e));
                xyz
            }
        }
    };
    let written = match georef {
        Some(g) => {
            let crs = precimap_formats::DeclaredCrs { epsg: g.strip_crs.epsg(), wkt: g.strip_crs.wkt() };
            precimap_formats::rewrite_strip_declaring(&entry.path, dst, crs, correct)?
        }
        None => precimap_formats::rewrite_strip_timed(&entry.path, dst, correct)?,
    };
    let what = || format!("strip {} ({})", entry.id, entry.path.display());
    if let Some(i) = uncovered {
        return Err(PipelineError::Input {
            what: what(),
            message: format!("point {i} lies outside trajectory {}'s time span", traj.id),
        });
    }
    if let Some((i, e)) = unmapped {
        return Err(PipelineError::Input { what: what(), message: format!("point {i}: {e}") });
    }
    Ok(written)
}

/// Corrected trajectory: same time stamps, body poses moved so that the scan heads (at the mean
/// lever arm) move by the corrections: `R' = Exp(δθ)·R`, `c' = c + δt + (I − Exp(δθ))·R·ℓ`.
pub fn export_trajectory_task(
    campaign: &Campaign,
    trajectory: usize,
    corrections: &TrajectoryCorrections,
    covariance: Option<&[AnchorCovariance]>,
    out_dir: &Path,
) -> Result<PathBuf, PipelineError> {
    let entry = &campaign.trajectories[trajectory];
    let dst = out_dir.join("trajectories").join(format!("{}.csv", entry.id));
    fs::create_dir_all(dst.parent().unwrap_or(out_dir)).map_err(|e| PipelineError::io(out_dir, e))?;
    let estimated = (corrections.first_anchor, corrections.last_anchor());
    let spacing = campaign.params.anchor_spacing_m;
    let corrections = corrections_for_export(entry, corrections, &campaign.params);
    export_trajectory_file(entry, spacing, &corrections, &dst)?;
    for (name, bytes) in corrections_outputs(entry, spacing, &corrections, estimated, covariance) {
        write_atomic(&out_dir.join(name), &bytes)?;
    }
    Ok(dst)
}

/// A trajectory's corrections table and correction plot (and in a field campaign the WKT of its
/// CRS), as (path inside a result folder, bytes): what both drivers write beside the corrected
/// trajectory. `exported` are the
/// corrections as exported, `estimated` and `covariance` as for
/// [`corrections_in_vehicle_frame`].
pub fn corrections_outputs(
    entry: &TrajectoryEntry,
    anchor_spacing_m: f64,
    exported: &TrajectoryCorrections,
    estimated: (u32, u32),
    covariance: Option<&[AnchorCovariance]>,
) -> Vec<(String, Vec<u8>)> {
    let rows = corrections_in_vehicle_frame(&entry.data, anchor_spacing_m, exported, estimated, covariance);
    let (plot_name, plot) = crate::qc::trajectory_plot(&entry.id, anchor_spacing_m, &rows);
    let mut out = vec![
        (corrections_table_name(&entry.id), corrections_table(&rows).into_bytes()),
        (plot_name, plot.into_bytes()),
    ];
    if let Some(g) = &entry.georef {
        // The exported trajectory's CRS, beside it where GIS tools look for it.
        out.push((format!("trajectories/{}.prj", entry.id), g.frame.crs().wkt().as_bytes().to_vec()));
    }
    out
}

/// The folder of the per-anchor corrections tables inside a result folder.
pub const CORRECTIONS_DIR: &str = "corrections";

/// Where a trajectory's corrections table lies inside a result folder.
pub fn corrections_table_name(trajectory_id: &str) -> String {
    format!("{CORRECTIONS_DIR}/{trajectory_id}.csv")
}

/// The columns of a corrections table ([`corrections_table`]).
pub const CORRECTIONS_TABLE_HEADER: &str = "anchor,arc_m,time,x,y,z,along_m,across_m,vertical_m,roll_deg,pitch_deg,\
heading_deg,sigma_along_m,sigma_across_m,sigma_vertical_m,sigma_roll_deg,sigma_pitch_deg,sigma_heading_deg,estimated";

/// Where an anchor sits on its trajectory and the frames its correction is given in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AnchorFrame {
    pub time: f64,
    pub position: Vec3,
    /// Along the direction of travel (horizontal), across it (horizontal, to the left) and up:
    /// the frame `precimap evaluate` splits position errors in.
    pub track: [[f64; 3]; 3],
    /// The vehicle's body axes (forward, left, up) in the world frame: roll, pitch and heading
    /// are rotations about them.
    pub body: [[f64; 3]; 3],
}

/// The pose at arc length `s` (clamped to the trajectory's ends) and its frames.
pub fn anchor_frame(trajectory: &precimap_core::Trajectory, s: f64) -> AnchorFrame {
    let arc = trajectory.arc_lengths();
    let last = arc.len() - 1;
    // The last sample at or before `s`: past a standstill, whose samples share one arc length.
    let i = arc.partition_point(|&a| a <= s).saturating_sub(1).min(last - 1);
    let span = arc[i + 1] - arc[i];
    let lambda = if span > 0.0 { ((s - arc[i]) / span).clamp(0.0, 1.0) } else { 0.0 };
    let times = trajectory.times();
    let time = times[i] + (times[i + 1] - times[i]) * lambda;
    let pose = trajectory.pose_in_segment(i, lambda);
    let r = pose.rotation;
    let body = [0, 1, 2].map(|k| [r[(0, k)], r[(1, k)], r[(2, k)]]);
    let positions = trajectory.positions();
    let step = positions[i + 1] - positions[i];
    // Standing still, the vehicle's forward axis gives the direction of travel.
    let (dx, dy) = if step.x.hypot(step.y) > 1e-9 { (step.x, step.y) } else { (body[0][0], body[0][1]) };
    let length = dx.hypot(dy);
    let (ax, ay) = if length > 0.0 { (dx / length, dy / length) } else { (1.0, 0.0) };
    let track = [[ax, ay, 0.0], [-ay, ax, 0.0], [0.0, 0.0, 1.0]];
    AnchorFrame { time, position: pose.position, track, body }
}

/// One anchor's exported correction in the vehicle's frames ([`corrections_in_vehicle_frame`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VehicleCorrection {
    pub anchor: u32,
    pub arc_m: f64,
    pub time: f64,
    /// On the input trajectory.
    pub position: Vec3,
    /// Translation along the track, across it (to the left) and up (m), then the rotation about
    /// the vehicle's roll, pitch and heading axes (rad).
    pub values: [f64; 6],
    /// Their posterior standard deviations, where the last solve gave a covariance.
    pub sigma: Option<[f64; 6]>,
    /// Solved for, not continued over the run-up or run-out.
    pub estimated: bool,
}

/// A trajectory's corrections, one per anchor of `exported` (the corrections as exported, run-up
/// and run-out included), in the vehicle's frames ([`AnchorFrame`]), with the posterior standard
/// deviations from `covariance` (one per anchor of the estimated range `estimated`, first to
/// last, in that order).
///
/// The standard deviations are the last iteration's, with the latent map held fixed: how well
/// each pass fits the map, not how far the map is from the truth (`precimap evaluate` compares
/// them with the simulator's errors).
pub fn corrections_in_vehicle_frame(
    trajectory: &precimap_core::Trajectory,
    anchor_spacing_m: f64,
    exported: &TrajectoryCorrections,
    estimated: (u32, u32),
    covariance: Option<&[AnchorCovariance]>,
) -> Vec<VehicleCorrection> {
    let dot = |a: &[f64; 3], b: &[f64]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    exported
        .values
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let anchor = exported.first_anchor + k as u32;
            let arc_m = anchor as f64 * anchor_spacing_m;
            let frame = anchor_frame(trajectory, arc_m);
            let [along, across, up] = frame.track.map(|e| dot(&e, &c[..3]));
            let [roll, pitch, heading] = frame.body.map(|e| dot(&e, &c[3..]));
            let inside = (estimated.0..=estimated.1).contains(&anchor);
            let sigma = covariance.filter(|_| inside).and_then(|v| v.get((anchor - estimated.0) as usize)).map(|cov| {
                let [a, b, c] = cov.sigma_along(0, &frame.track);
                let [d, e, f] = cov.sigma_along(3, &frame.body);
                [a, b, c, d, e, f]
            });
            VehicleCorrection {
                anchor,
                arc_m,
                time: frame.time,
                position: frame.position,
                values: [along, across, up, roll, pitch, heading],
                sigma,
                estimated: inside,
            }
        })
        .collect()
}

/// The corrections table (`OUT/corrections/{trajectory}.csv`, [`CORRECTIONS_TABLE_HEADER`]): one
/// row per anchor, translations in metres, rotations in degrees; empty σ cells where there is
/// none; `estimated` 1 on the anchors the adjustment solved for, 0 on those continued past them.
pub fn corrections_table(rows: &[VehicleCorrection]) -> String {
    use std::fmt::Write;
    let mut out = String::with_capacity(200 * (rows.len() + 1));
    out.push_str(CORRECTIONS_TABLE_HEADER);
    out.push('\n');
    for r in rows {
        let [along, across, up, roll, pitch, heading] = r.values;
        let (p, s) = (r.position, r.arc_m);
        let _ = write!(
            out,
            "{},{s:.3},{:.6},{:.4},{:.4},{:.4},{along:.6},{across:.6},{up:.6},{:.7},{:.7},{:.7}",
            r.anchor,
            r.time,
            p.x,
            p.y,
            p.z,
            roll.to_degrees(),
            pitch.to_degrees(),
            heading.to_degrees()
        );
        match r.sigma {
            Some([a, b, c, d, e, f]) => {
                let _ = write!(
                    out,
                    ",{a:.6},{b:.6},{c:.6},{:.7},{:.7},{:.7}",
                    d.to_degrees(),
                    e.to_degrees(),
                    f.to_degrees()
                );
            }
            None => out.push_str(",,,,,,"),
        }
        let _ = writeln!(out, ",{}", u8::from(r.estimated));
    }
    out
}

/// Writes QC plots, given as (path inside a result folder, SVG) like the [`crate::qc`]
/// functions return them, into `out_dir`.
pub fn write_plots(out_dir: &Path, plots: impl IntoIterator<Item = (String, String)>) -> Result<(), PipelineError> {
    for (name, svg) in plots {
        write_atomic(&out_dir.join(name), svg.as_bytes())?;
    }
    Ok(())
}

/// The folder of the latent map's tiles inside a result folder.
pub const LATENT_DIR: &str = "latent";

/// Where a tile's latent map lies inside a result folder (the framework names its output so).
pub fn latent_map_name(tile: TileKey) -> String {
    format!("{LATENT_DIR}/{tile}.las")
}

/// Writes one tile's latent map into `out_dir` ([`latent_map_name`]), in a field campaign in
/// its processing CRS ([`latent_map_in_crs`]).
pub fn write_latent_map_tile(
    out_dir: &Path,
    tile: TileKey,
    points: &[LatentMapPoint],
    georef: Option<&Georeference>,
) -> Result<(), PipelineError> {
    let path = out_dir.join(latent_map_name(tile));
    let dir = path.parent().unwrap_or(Path::new("."));
    fs::create_dir_all(dir).map_err(|e| PipelineError::io(dir, e))?;
    let (points, wkt) = latent_map_in_crs(tile, points, georef)?;
    Ok(precimap_formats::write_latent_map(&path, &points, wkt)?)
}

/// A tile's latent map as both drivers export it: in a field campaign its points in grid
/// coordinates of the processing CRS, with that CRS's WKT; otherwise as estimated.
pub fn latent_map_in_crs<'a>(
    tile: TileKey,
    points: &[LatentMapPoint],
    georef: Option<&'a Georeference>,
) -> Result<(Vec<LatentMapPoint>, Option<&'a str>), PipelineError> {
    let Some(g) = georef else { return Ok((points.to_vec(), None)) };
    let grid = points
        .iter()
        .map(|p| {
            let position = g.frame.grid_from_local(&Vec3::from(p.position)).map_err(|e| PipelineError::Input {
                what: format!("latent map tile {tile}"),
                message: format!("{e}; check $.crs"),
            })?;
            Ok(LatentMapPoint { position, ..*p })
        })
        .collect::<Result<Vec<_>, PipelineError>>()?;
    Ok((grid, Some(g.frame.crs().wkt())))
}

/// The estimated corrections continued over the trajectory's run-up and run-out (the poses
/// before its strips' first and after their last point), up to `params.end_extension_m`
/// ([`precimap_estimate::extend_corrections`]).
pub fn corrections_for_export(
    entry: &TrajectoryEntry,
    corrections: &TrajectoryCorrections,
    params: &Parameters,
) -> TrajectoryCorrections {
    let estimated = (corrections.first_anchor, corrections.last_anchor());
    let last = trajectory_last_anchor(&entry.data, params.anchor_spacing_m);
    precimap_estimate::extend_corrections(corrections, params.exported_anchor_range(estimated, last), params)
}

/// The anchor after a trajectory's last pose: the last one its poses interpolate from.
fn trajectory_last_anchor(trajectory: &precimap_core::Trajectory, anchor_spacing_m: f64) -> u32 {
    // `as` saturates: a trajectory beyond u32::MAX anchors just ends there.
    ((trajectory.length_m() / anchor_spacing_m).floor() as u32).saturating_add(1)
}

/// Writes `entry`'s corrected trajectory CSV to `dst`; in a field campaign in grid coordinates of
/// the processing CRS (angles about the grid axes; its WKT is written beside it, see
/// [`corrections_outputs`]).
pub fn export_trajectory_file(
    entry: &TrajectoryEntry,
    anchor_spacing_m: f64,
    corrections: &TrajectoryCorrections,
    dst: &Path,
) -> Result<(), PipelineError> {
    let t = &entry.data;
    let mut positions = Vec::with_capacity(t.len());
    let mut rpy = Vec::with_capacity(t.len());
    for ((c, r), s) in t.positions().iter().zip(t.rotations()).zip(t.arc_lengths()) {
        let u = s / anchor_spacing_m;
        let anchor = u.floor();
        let x = corrections.at(anchor as u32, (u - anchor) as f32);
        let delta = so3_exp(&Vec3::new(x[3], x[4], x[5]));
        let rotated: Mat3 = delta * r;
        let lever = r * entry.mean_lever_arm;
        let position = c + Vec3::new(x[0], x[1], x[2]) + (lever - delta * lever);
        match &entry.georef {
            // Field campaigns: grid coordinates and angles about the grid axes of the processing CRS.
            Some(g) => {
                let (grid, angles) =
                    precimap_formats::navigation::grid_pose(&g.frame, &position, &rotated).map_err(|e| {
                        PipelineError::Input { what: format!("trajectory {}", entry.id), message: e.to_string() }
                    })?;
                positions.push(Vec3::from(grid));
                rpy.push(angles);
            }
            None => {
                let (roll, pitch, yaw) = rpy_from_rot(&rotated);
                positions.push(position);
                rpy.push([roll.to_degrees(), pitch.to_degrees(), yaw.to_degrees()]);
            }
        }
    }
    precimap_formats::write_trajectory_csv(dst, t.times(), &positions, &rpy)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    /// The corrections table gives each anchor's correction and standard deviations in the
    /// vehicle's frames: driving north (+y), along-track is world y, across (to the left) is −x;
    /// roll turns about y, pitch about −x, heading about z.
    #[test]
    fn the_corrections_table_is_in_the_vehicles_frame() {
        let times: Vec<f64> = (0..=200).map(|k| k as f64 * 0.5).collect();
        let positions = times.iter().map(|&t| Vec3::new(1000.0, 2000.0 + t, 50.0)).collect();
        let data =
            precimap_core::Trajectory::new(times.clone(), positions, vec![[0.0, 0.0, 90.0]; times.len()]).unwrap();
        let estimated = (10, 20);
        let correction = [0.001, 0.002, 0.003, 1e-4, 2e-4, 3e-4];
        let exported = TrajectoryCorrections { first_anchor: 5, values: vec![correction; 21] };
        let sigma = [1e-3, 3e-3, 2e-3, 1e-5, 2e-5, 3e-5];
        // x and y correlated: the table must rotate the covariance, not only the σ.
        let covariance: Vec<AnchorCovariance> = (0..11)
            .map(|_| {
                AnchorCovariance::from_fn(|a, b| match (a, b) {
                    (a, b) if a == b => sigma[a] * sigma[a],
                    (0, 1) => 0.5 * sigma[0] * sigma[1],
                    _ => 0.0,
                })
            })
            .collect();
        let table =
            corrections_table(&corrections_in_vehicle_frame(&data, 0.5, &exported, estimated, Some(&covariance)));
        let rows: Vec<Vec<&str>> = table.lines().map(|l| l.split(',').collect()).collect();
        assert_eq!(rows[0].join(","), CORRECTIONS_TABLE_HEADER);
        assert_eq!(rows.len(), 22);
        let column = |name: &str| rows[0].iter().position(|h| *h == name).unwrap();
        let value = |row: &[&str], name: &str| row[column(name)].parse::<f64>().unwrap();
        // Anchor 5 was continued, not estimated: no standard deviation.
        assert_eq!(rows[1][column("anchor")], "5");
        assert_eq!(rows[1][column("estimated")], "0");
        assert_eq!(rows[1][column("sigma_along_m")], "");
        // Anchor 12: 6 m along, 6 s in.
        let row = &rows[8];
        assert_eq!(row[column("anchor")], "12");
        assert_eq!(row[column("estimated")], "1");
        assert_eq!((value(row, "arc_m"), value(row, "time")), (6.0, 6.0));
        assert_eq!((value(row, "x"), value(row, "y"), value(row, "z")), (1000.0, 2006.0, 50.0));
        // To the printed digits: 1 µm, 0.1 µdeg.
        let close = |name: &str, expected: f64| {
            let v = value(row, name);
            let digit = if name.ends_with("_deg") { 1e-7 } else { 1e-6 };
            assert!((v - expected).abs() <= 0.5 * digit + 1e-12, "{name}: {v}, expected {expected}");
        };
        close("along_m", 0.002);
        close("across_m", -0.001);
        close("vertical_m", 0.003);
        close("roll_deg", 2e-4f64.to_degrees());
        close("pitch_deg", -1e-4f64.to_degrees());
        close("heading_deg", 3e-4f64.to_degrees());
        close("sigma_along_m", 3e-3);
        close("sigma_across_m", 1e-3);
        close("sigma_vertical_m", 2e-3);
        close("sigma_roll_deg", 2e-5f64.to_degrees());
        close("sigma_pitch_deg", 1e-5f64.to_degrees());
        close("sigma_heading_deg", 3e-5f64.to_degrees());
        // Driving north-east, the correlation shows: along (x + y)/√2 holds σx² + σy² + 2ρσxσy.
        let turned: Vec<Vec3> = times.iter().map(|&t| Vec3::new(1000.0 + t, 2000.0 + t, 50.0)).collect();
        let data = precimap_core::Trajectory::new(times.clone(), turned, vec![[0.0, 0.0, 45.0]; times.len()]).unwrap();
        let table =
            corrections_table(&corrections_in_vehicle_frame(&data, 0.5, &exported, estimated, Some(&covariance)));
        let row: Vec<&str> = table.lines().nth(8).unwrap().split(',').collect();
        let along = ((1e-6 + 9e-6 + 3e-6) / 2.0f64).sqrt();
        assert!((value(&row, "sigma_along_m") - along).abs() < 1e-6, "{row:?}");
        // Without covariances (an earlier iteration's corrections), the σ cells stay empty.
        let table = corrections_table(&corrections_in_vehicle_frame(&data, 0.5, &exported, estimated, None));
        assert!(table.lines().skip(1).all(|l| l.contains(",,,,,,")));
    }

    /// A trajectory's run-up and run-out take the estimated corrections' trend on, as far as
    /// `end_extension_m` reaches and not past its own ends.
    #[test]
    fn exported_corrections_continue_over_the_run_up_and_run_out() {
        // 100 m straight at 1 m/s: anchors 0..=201.
        let times: Vec<f64> = (0..=200).map(|k| k as f64 * 0.5).collect();
        let positions = times.iter().map(|&t| Vec3::new(t, 0.0, 0.0)).collect();
        let data = precimap_core::Trajectory::new(times.clone(), positions, vec![[0.0; 3]; times.len()]).unwrap();
        let entry = TrajectoryEntry {
            id: "t".into(),
            path: PathBuf::from("t.csv"),
            data: Arc::new(data),
            mean_lever_arm: Vec3::zeros(),
            clock: Default::default(),
            georef: None,
            accuracy: None,
            accuracy_uri: String::new(),
        };
        // Estimated on anchors 40..=160 with a trend of 1 mm per anchor in x.
        let corrections = TrajectoryCorrections {
            first_anchor: 40,
            values: (40..=160).map(|i| [0.001 * i as f64, 0.0, 0.0, 0.0, 0.0, 0.0]).collect(),
        };
        let params = Parameters::default();
        let exported = corrections_for_export(&entry, &corrections, &params);
        // 10 m at 0.5 m: 20 anchors either side.
        assert_eq!((exported.first_anchor, exported.last_anchor()), (20, 180));
        assert_eq!(&exported.values[20..141], &corrections.values[..]);
        // The trend carries on (held, they would stay at 0.040 and 0.160).
        let (run_up, run_out) = (exported.values[0][0], exported.values[160][0]);
        assert!(run_up < 0.040 - 0.8 * 0.020 && run_up > 0.040 - 1.01 * 0.020, "run-up {run_up}");
        assert!(run_out > 0.160 + 0.8 * 0.020 && run_out < 0.160 + 1.01 * 0.020, "run-out {run_out}");
        // Not past the trajectory's own ends; off at 0.
        let far = Parameters { end_extension_m: 1000.0, ..Parameters::default() };
        let exported = corrections_for_export(&entry, &corrections, &far);
        assert_eq!((exported.first_anchor, exported.last_anchor()), (0, 201));
        let off = Parameters { end_extension_m: 0.0, ..Parameters::default() };
        assert_eq!(corrections_for_export(&entry, &corrections, &off), corrections);
    }
}
