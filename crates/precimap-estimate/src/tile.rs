//! `estimate_tile`: the map task of one estimation iteration (paper §6.3,
//! docs/design/estimation.md).
//!
//! 1. Every point of the tile is corrected with the current trajectory corrections.
//! 2. The latent map is built: points fall into voxel-hashed cells (columns along the point's
//!    normal axis in the capture steps and, with segments, in every other step, so that no cell
//!    face cuts across a surface); inside a cell, points whose normals agree form a local
//!    surface model (LSM: plane with normal `w`, origin `o`, and a height raster of pixel size
//!    `grid_m`). Each strip's surface (the triangles of its scan image) is rasterised into the
//!    LSM pixels, so a pixel knows every strip's surface height there even when the points are
//!    sparser than the pixels.
//!    Steps with pixels finer than `point_latent_below_grid_m` skip the raster and sample the
//!    other passes' triangles for each point instead, at a cost that does not grow with the
//!    pixel count: at pixel centres that follow the point spacing ([`pixels`], the default,
//!    O(points)) or exactly at the points ([`point_latent`], O(points × passes)).
//! 3. Each point in the tile's core becomes an observation: its height above the LSM plane minus
//!    the latent height at its position. Only pixels seen by at least two distinct
//!    strip passes carry inter-strip information; the others are skipped. A point's own strip is
//!    part of the pixel mean, so strips step to the common mean instead of swapping places.
//! 4. Observations within the outlier threshold are linearised and summed into per-anchor 6×6
//!    normal-equation blocks, keyed by trajectory. In point-sampled steps with
//!    `consistent_gradient` (the default) a point also pulls on the passes whose triangles make
//!    its latent height ([`CornerPulls`]), so the blocks carry the gradient of the cost the
//!    common-mode field minimises and both levels share one fixed point.

use crate::blocks::TrajectoryBlocks;
use crate::calibration::TileCalibration;
use crate::chunk::TileChunk;
use crate::field::{FieldAccumulator, FieldEquations};
use crate::latent::{LatentMapGrid, LatentRecord, LatentSink};
use crate::stats::{LatentStdMap, TileStats};
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::{ControlTarget, IterationStep, LatentMapPoint, Parameters, TileKey};

mod control;
mod models;
mod observe;
mod pixels;
mod point;
mod pulls;
mod raster;
mod triangles;

use control::observe_control;
use models::{correct_points, join_into_models, CorrectedPoints};
use observe::{observe_points, Observations};
use point::{point_latent, CoreIndex, ItemPull, Latent, PointLatent, SAME_PASS_ANCHORS};
use pulls::{corner_pulls, CornerPulls};
use raster::{raster_latent, PixelGrid};
use triangles::Triangles;

const NONE: u32 = u32::MAX;
/// Steepest latent surface (tan 20°) against its model plane at which a point is observed.
const MAX_SLOPE: f64 = 0.364;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum EstimateError {
    #[error("chunk of strip {strip} belongs to tile {found}, not to tile {expected}")]
    WrongTile { strip: u32, expected: TileKey, found: TileKey },
    #[error("chunk of strip {strip} names trajectory {trajectory}, but only {known} trajectories have corrections")]
    UnknownTrajectory { strip: u32, trajectory: u32, known: usize },
    #[error("chunk of strip {strip} has no scanner in the calibration ({known} strips known)")]
    UnknownScanner { strip: u32, known: usize },
    #[error("chunk of strip {strip} carries no body attitudes at its anchors, which estimating the calibration needs: prepare the strips again with the calibration switched on")]
    NoAttitude { strip: u32 },
}

/// What one tile emits: normal-equation blocks per trajectory and statistics.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TileEstimate {
    pub tile: TileKey,
    pub blocks: Vec<TrajectoryBlocks>,
    pub stats: TileStats,
    /// The common-mode field's data equations, in steps that solve the field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<FieldEquations>,
    /// The latent map's standard deviation under the core points, per cell (QC; only from
    /// [`estimate_tile_recording`] asked for it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latent_std: Option<LatentStdMap>,
    /// The latent map thinned to voxels (a product; only from [`estimate_tile_recording`] asked
    /// for it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latent_map: Option<Vec<LatentMapPoint>>,
}

#[inline]
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

#[inline]
pub(crate) fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    if n > 0.0 {
        [a[0] / n, a[1] / n, a[2] / n]
    } else {
        [0.0, 0.0, 1.0]
    }
}

/// `x.floor() as i64` without the libm call (`floor` is not inlined on baseline x86-64; it was
/// 4 % of `estimate_tile`). Saturates like `as` for values beyond the i64 range.
#[inline]
fn floor_i64(x: f64) -> i64 {
    let i = x as i64;
    i - ((i as f64) > x) as i64
}

/// The axis along which `n` points most.
#[inline]
pub(crate) fn dominant_axis(n: &[f64; 3]) -> usize {
    let a = n.map(f64::abs);
    if a[0] >= a[1] && a[0] >= a[2] {
        0
    } else if a[1] >= a[2] {
        1
    } else {
        2
    }
}

/// `p` moved by `by` along the unit normal `w`.
#[inline]
fn lifted(p: &[f64; 3], w: [f64; 3], by: f64) -> [f64; 3] {
    [p[0] + by * w[0], p[1] + by * w[1], p[2] + by * w[2]]
}

/// The map task of one iteration on one tile. `corrections[t]` are the current corrections of
/// trajectory `t` (the index chunks carry).
pub fn estimate_tile(
    tile: TileKey,
    chunks: &[TileChunk],
    corrections: &[TrajectoryCorrections],
    params: &Parameters,
    step: &IterationStep,
    control: &[ControlTarget],
) -> Result<TileEstimate, EstimateError> {
    estimate_tile_recording(tile, chunks, corrections, params, step, control, None, None, LatentGather::default())
}

/// A point of a tile's core that became an observation: its strip, its index in the strip file
/// and the tile's surface model it was compared with (ids are per tile and per call).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UsedPoint {
    pub strip: u32,
    pub source: u32,
    pub model: u32,
}

/// What [`estimate_tile_recording`] gathers of the latent map besides the estimate.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LatentGather {
    /// Its standard deviation per cell ([`TileEstimate::latent_std`], QC).
    pub std_map: bool,
    /// The map itself, thinned to voxels of `Parameters::latent_map_grid_m`
    /// ([`TileEstimate::latent_map`], a product).
    pub map: bool,
}

/// [`estimate_tile`], also appending to `used` every point that became an observation (what the
/// assignment audit compares with the simulator's true surfaces) and gathering what `gather`
/// asks of the latent map. `control` holds the control and check targets that can reach the
/// tile ([`crate::control::reaches_tile`]); `calibration`, where the campaign estimates the
/// scanners' mounting, its current values (applied to the points) and layout (the blocks then
/// carry the calibration's terms).
#[allow(clippy::too_many_arguments)]
pub fn estimate_tile_recording(
    tile: TileKey,
    chunks: &[TileChunk],
    corrections: &[TrajectoryCorrections],
    params: &Parameters,
    step: &IterationStep,
    control: &[ControlTarget],
    calibration: Option<&TileCalibration>,
    used: Option<&mut Vec<UsedPoint>>,
    gather: LatentGather,
) -> Result<TileEstimate, EstimateError> {
    let map = gather.map && params.latent_map_grid_m > 0.0;
    let inputs = TileInputs { tile, chunks, corrections, params, step, control, calibration };
    if !(gather.std_map || map) {
        return estimate_tile_into(&inputs, used, &mut ());
    }
    let mut record = LatentRecord {
        std: gather.std_map.then(|| LatentStdMap::new(params.tile_size_m)),
        map: map.then(|| LatentMapGrid::new(params.latent_map_grid_m, step.threshold_m)),
    };
    let estimate = estimate_tile_into(&inputs, used, &mut record)?;
    let (ox, oy) = tile.origin(params.tile_size_m);
    Ok(TileEstimate { latent_std: record.std, latent_map: record.map.map(|g| g.finish([ox, oy])), ..estimate })
}

/// What one tile's map task reads.
struct TileInputs<'a> {
    tile: TileKey,
    chunks: &'a [TileChunk],
    corrections: &'a [TrajectoryCorrections],
    params: &'a Parameters,
    step: &'a IterationStep,
    control: &'a [ControlTarget],
    calibration: Option<&'a TileCalibration<'a>>,
}

fn estimate_tile_into<S: LatentSink>(
    inputs: &TileInputs,
    used: Option<&mut Vec<UsedPoint>>,
    sink: &mut S,
) -> Result<TileEstimate, EstimateError> {
    let TileInputs { tile, chunks, corrections, params, step, control, calibration } = *inputs;
    check_chunks(tile, chunks, corrections, calibration)?;
    let cos_group = params.normal_group_angle_deg.to_radians().cos();
    // 1. Every point corrected and sorted into a patch, the patches joined into surface models.
    let CorrectedPoints { position, measurement, vehicle, patch_of, patches, anchor_attitude } =
        correct_points(tile, chunks, corrections, params, step, cos_group, calibration);
    let (models, model_of) = join_into_models(&patches, &patch_of, params, step, cos_group);
    drop((patch_of, patches));
    let triangles = Triangles {
        chunks,
        models: &models,
        position: &position,
        model_of: &model_of,
        cos_group,
        within_segment: params.segment_surfaces,
    };
    let mut stats = TileStats::new(tile);
    stats.surface_models = models.len() as u64;
    let tile_size = params.tile_size_m;
    let in_core = |p: &[f64; 3]| p[0] >= 0.0 && p[0] < tile_size && p[1] >= 0.0 && p[1] < tile_size;
    // 2. The latent height under every point of the tile's core, and the corner pulls.
    let solves_field = step.solves_field(params);
    let field_vehicle = solves_field.then_some(vehicle.as_slice());
    let (latent, mut pulls) = latent_heights(&triangles, &in_core, params, step, field_vehicle, &mut stats, sink);
    let mut field = solves_field.then(|| field_accumulator(params));
    // 2c. The control targets the core points observe, and what they measure at every target.
    let (ox, oy) = tile.origin(tile_size);
    let (control, control_sums) = observe_control(control, &triangles, &in_core, [ox, oy], params, step.threshold_m);
    stats.control = control_sums;
    // 3–4. Observations of the points in the tile's core, summed into normal-equation blocks and
    //      the field's rows.
    let observations = Observations {
        t: &triangles,
        measurement: &measurement,
        anchor_attitude: &anchor_attitude,
        vehicle: &vehicle,
        latent: &latent,
        weight: 1.0 / (params.sigma_distance_m * params.sigma_distance_m),
        threshold: step.threshold_m,
        control: &control,
        // The calibration is estimated with the attitude, in the steps that estimate it.
        calibration: calibration.filter(|_| step.rotation),
    };
    let blocks = observe_points(&observations, &in_core, pulls.as_mut(), field.as_mut(), &mut stats, used);
    Ok(TileEstimate {
        tile,
        blocks,
        stats,
        field: field.map(FieldAccumulator::finish),
        latent_std: None,
        latent_map: None,
    })
}

/// Every chunk in `tile`, every chunk's trajectory among `corrections`, and with a calibration
/// every chunk's strip with a scanner and the attitudes at its anchors.
fn check_chunks(
    tile: TileKey,
    chunks: &[TileChunk],
    corrections: &[TrajectoryCorrections],
    calibration: Option<&TileCalibration>,
) -> Result<(), EstimateError> {
    for c in chunks {
        if c.tile != tile {
            return Err(EstimateError::WrongTile { strip: c.strip, expected: tile, found: c.tile });
        }
        if c.trajectory as usize >= corrections.len() {
            return Err(EstimateError::UnknownTrajectory {
                strip: c.strip,
                trajectory: c.trajectory,
                known: corrections.len(),
            });
        }
        if let Some(calibration) = calibration {
            if calibration.of_strip(c.strip).is_none() {
                return Err(EstimateError::UnknownScanner {
                    strip: c.strip,
                    known: calibration.scanner_of_strip.len(),
                });
            }
            let anchors = c.anchor_range().map_or(0, |(first, last)| (last - first + 1) as usize);
            if c.attitude.len() != anchors {
                return Err(EstimateError::NoAttitude { strip: c.strip });
            }
        }
    }
    Ok(())
}

/// Step 2: the latent height under every point of the tile's core (NaN: not observable) by the
/// step's route (raster, pixel-sampled or point-sampled), and with a consistent gradient what
/// every used point's residual pulls on the corners of the other passes' triangles that cover
/// it. `vehicle`: the absolute horizontal scan-head positions, in steps that solve the field.
fn latent_heights<S: LatentSink>(
    triangles: &Triangles,
    in_core: &impl Fn(&[f64; 3]) -> bool,
    params: &Parameters,
    step: &IterationStep,
    vehicle: Option<&[[f64; 2]]>,
    stats: &mut TileStats,
    sink: &mut S,
) -> (Vec<PointLatent>, Option<CornerPulls>) {
    let grid = step.grid_m;
    let threshold = step.threshold_m;
    let weight = 1.0 / (params.sigma_distance_m * params.sigma_distance_m);
    let sampled = grid < params.point_latent_below_grid_m;
    let by_pixel = sampled && params.latent_pixel_share > 0.0 && params.cover_agreement_thresholds <= 0.0;
    let index = (sampled && !by_pixel).then(|| CoreIndex::new(triangles, in_core));
    let mut covers = Vec::new();
    let mut pixel_pulls = None;
    let Latent { points: latent, pull } = match &index {
        None if by_pixel => {
            let pulls = params.consistent_gradient.then_some(ItemPull { threshold, weight });
            let (latent, pulls) =
                pixels::pixel_latent(triangles, in_core, grid, params.latent_pixel_share, vehicle, pulls, stats, sink);
            pixel_pulls = pulls;
            latent
        }
        Some(index) => {
            let pulls = params.consistent_gradient.then_some((&mut covers, ItemPull { threshold, weight }));
            let agreement = match params.cover_agreement_thresholds {
                f if f > 0.0 => f * threshold,
                _ => f64::INFINITY,
            };
            point_latent(triangles, index, vehicle, pulls, agreement, stats, sink)
        }
        None => {
            let points = raster_latent(triangles, grid, in_core, vehicle, stats, sink);
            Latent { points, pull: Vec::new() }
        }
    };
    // With a consistent gradient, what every used point's residual pulls on the corners of the
    // other passes' triangles that cover it.
    let pulls = match pixel_pulls {
        Some(pulls) => Some(pulls),
        None => (index.is_some() && params.consistent_gradient).then(|| corner_pulls(triangles, &covers, &pull)),
    };
    (latent, pulls)
}

/// The common-mode field's accumulator with the rotations the parameters ask for.
fn field_accumulator(params: &Parameters) -> FieldAccumulator {
    match (params.common_mode_heading, params.common_mode_tilt) {
        (true, true) => FieldAccumulator::with_tilt(params.common_mode_field_m),
        (true, false) => FieldAccumulator::with_heading(params.common_mode_field_m),
        (false, _) => FieldAccumulator::new(params.common_mode_field_m),
    }
}

#[cfg(test)]
mod tests;
