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

use crate::blocks::{AnchorBlock, IntervalMoments, TrajectoryBlocks};
use crate::chunk::{TileChunk, NO_NEIGHBOUR};
use crate::control::{observe_targets, TargetObservation, TilePoints};
use crate::field::{FieldAccumulator, FieldEquations, FieldRow};
use crate::latent::{LatentMapGrid, LatentRecord, LatentSample, LatentSink};
use crate::stats::{LatentStdMap, ResidualHistogram, TileStats};
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::geom::{floor, SmallRotation};
use precimap_core::hash::FxHashMap;
use precimap_core::{ControlSums, ControlTarget, IterationStep, LatentMapPoint, Parameters, TileKey};
use std::collections::BTreeMap;

mod pixels;

const NONE: u32 = u32::MAX;
/// Pixel tag once two different strip passes contributed.
const MULTI: u32 = u32::MAX;
/// Surface models one cell can hold (distinct normal directions).
const MAX_MODELS_PER_CELL: usize = 8;
/// Steepest latent surface (tan 20°) against its model plane at which a point is observed.
const MAX_SLOPE: f64 = 0.364;
/// A scan-image triangle is rasterised only if its facet is within 15° of the model's normal:
/// steeper facets bridge a step (curb, window recess, occlusion) and would bias the heights.
const FACET_COS: f64 = 0.965_925_826_289_068_3;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum EstimateError {
    #[error("chunk of strip {strip} belongs to tile {found}, not to tile {expected}")]
    WrongTile { strip: u32, expected: TileKey, found: TileKey },
    #[error("chunk of strip {strip} names trajectory {trajectory}, but only {known} trajectories have corrections")]
    UnknownTrajectory { strip: u32, trajectory: u32, known: usize },
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

#[derive(Clone, Copy, Default)]
struct CellModels {
    ids: [u32; MAX_MODELS_PER_CELL],
    len: u8,
}

/// A local surface model while points are gathered, then its frame and raster.
#[derive(Clone, Debug)]
struct SurfaceModel {
    sum_normal: [f64; 3],
    sum_position: [f64; 3],
    count: u32,
    // Frame, valid after `finish_frame`.
    w: [f64; 3],
    e1: [f64; 3],
    e2: [f64; 3],
    o: [f64; 3],
}

impl SurfaceModel {
    fn new() -> Self {
        Self {
            sum_normal: [0.0; 3],
            sum_position: [0.0; 3],
            count: 0,
            w: [0.0; 3],
            e1: [0.0; 3],
            e2: [0.0; 3],
            o: [0.0; 3],
        }
    }

    fn finish_frame(&mut self) {
        let w = normalize(self.sum_normal);
        let helper = if w[2].abs() < 0.9 { [0.0, 0.0, 1.0] } else { [1.0, 0.0, 0.0] };
        let e1 = normalize(cross(helper, w));
        let e2 = cross(w, e1);
        let c = self.count as f64;
        self.o = [self.sum_position[0] / c, self.sum_position[1] / c, self.sum_position[2] / c];
        self.w = w;
        self.e1 = e1;
        self.e2 = e2;
    }

    #[inline]
    fn project(&self, p: &[f64; 3]) -> (f64, f64, f64) {
        let d = [p[0] - self.o[0], p[1] - self.o[1], p[2] - self.o[2]];
        (dot(d, self.e1), dot(d, self.e2), dot(d, self.w))
    }

    /// Height of `p` above the model plane (the third coordinate of [`Self::project`]).
    #[inline]
    fn height(&self, p: &[f64; 3]) -> f64 {
        dot([p[0] - self.o[0], p[1] - self.o[1], p[2] - self.o[2]], self.w)
    }
}

/// A raster pixel: the heights of the triangles sampled at its centre (sum, sum of squares,
/// count), which passes they came from, and the sum of their scan heads (zeros without the
/// common-mode field). The scan heads are in the pixel, not in a column of their own: at 5 cm
/// a triangle writes ~6 pixels (small s1: 59.4 M writes from 10.2 M triangles into 6.5 MB of
/// rasters per tile), and one scattered write to 32 bytes instead of two to 16 made that pass
/// 1.09× faster.
#[derive(Clone, Copy, Default)]
struct Pixel {
    sum: f32,
    sum2: f32,
    count: u32,
    tag: u32,
    vehicle: [f64; 2],
}

impl Pixel {
    #[inline]
    fn add(&mut self, h: f32, tag: u32, vehicle: [f64; 2]) {
        if self.count == 0 {
            self.tag = tag;
        } else if self.tag != tag {
            self.tag = MULTI;
        }
        self.sum += h;
        self.sum2 += h * h;
        self.count += 1;
        self.vehicle[0] += vehicle[0];
        self.vehicle[1] += vehicle[1];
    }

    #[inline]
    fn shared(&self) -> bool {
        self.count > 0 && self.tag == MULTI
    }

    #[inline]
    fn mean(&self) -> f64 {
        self.sum as f64 / self.count as f64
    }
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

/// Key of the cell holding `p`; with `unbounded` the cell is a column unbounded along that axis
/// (index 0 there, which no tile-local position reaches, so columns along different axes never
/// share a key).
#[inline]
fn cell_key(p: &[f64; 3], inv_cell: f64, unbounded: Option<usize>) -> u64 {
    const OFFSET: i64 = 1 << 20;
    let index = |axis: usize| {
        if unbounded == Some(axis) {
            0
        } else {
            (floor_i64(p[axis] * inv_cell) + OFFSET) as u64 & 0x1F_FFFF
        }
    };
    (index(0) << 42) | (index(1) << 21) | index(2)
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

/// Largest distance of a point from the plane of a patch (one strip segment in one normal
/// column) it joins: farther, it is a parallel surface of the same segment along the column.
const PATCH_PLANE_M: f64 = 0.05;
/// Smallest distance between planes at which patches of different strips join one model.
const JOIN_DISTANCE_MIN_M: f64 = 0.1;
/// Largest distance between planes at which two segments of one strip pass join one model.
const SAME_PASS_JOIN_M: f64 = 0.03;
/// Anchors (0.5 m each) along a strip within which two of its segments count as one pass.
const PASS_ANCHORS: u32 = 64;

/// Identifies one pass of one strip over a place: passes of the same strip more than
/// 64 anchors (32 m) apart along the trajectory count as different views.
#[inline]
fn pass_tag(strip: u32, anchor: u32) -> u32 {
    const _: () = assert!(PASS_ANCHORS == 64);
    (strip << 16) | ((anchor >> 6) & 0xFFFF)
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
    estimate_tile_recording(tile, chunks, corrections, params, step, control, None, LatentGather::default())
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
/// tile ([`crate::control::reaches_tile`]).
#[allow(clippy::too_many_arguments)]
pub fn estimate_tile_recording(
    tile: TileKey,
    chunks: &[TileChunk],
    corrections: &[TrajectoryCorrections],
    params: &Parameters,
    step: &IterationStep,
    control: &[ControlTarget],
    used: Option<&mut Vec<UsedPoint>>,
    gather: LatentGather,
) -> Result<TileEstimate, EstimateError> {
    let map = gather.map && params.latent_map_grid_m > 0.0;
    if !(gather.std_map || map) {
        return estimate_tile_into(tile, chunks, corrections, params, step, control, used, &mut ());
    }
    let mut record = LatentRecord {
        std: gather.std_map.then(|| LatentStdMap::new(params.tile_size_m)),
        map: map.then(|| LatentMapGrid::new(params.latent_map_grid_m, step.threshold_m)),
    };
    let estimate = estimate_tile_into(tile, chunks, corrections, params, step, control, used, &mut record)?;
    let (ox, oy) = tile.origin(params.tile_size_m);
    Ok(TileEstimate { latent_std: record.std, latent_map: record.map.map(|g| g.finish([ox, oy])), ..estimate })
}

#[allow(clippy::too_many_arguments)]
fn estimate_tile_into<S: LatentSink>(
    tile: TileKey,
    chunks: &[TileChunk],
    corrections: &[TrajectoryCorrections],
    params: &Parameters,
    step: &IterationStep,
    control: &[ControlTarget],
    mut used: Option<&mut Vec<UsedPoint>>,
    sink: &mut S,
) -> Result<TileEstimate, EstimateError> {
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
    }
    let tile_size = params.tile_size_m;
    let (ox, oy) = tile.origin(tile_size);
    let inv_cell = 1.0 / step.cell_size(params);
    let cos_group = params.normal_group_angle_deg.to_radians().cos();
    let grid = step.grid_m;
    let total: usize = chunks.iter().map(TileChunk::len).sum();

    // 1. Correct every point and sort it into a patch: the points of one strip segment in one
    //    cell whose normals agree (a segment can wrap round a pole or a corner within a cell).
    let mut position = Vec::with_capacity(total);
    let mut measurement = Vec::with_capacity(total);
    let solves_field = step.solves_field(params);
    // Absolute horizontal scan-head positions, where the common-mode field acts.
    let mut vehicle: Vec<[f64; 2]> = Vec::with_capacity(if solves_field { total } else { 0 });
    let mut patch_of = Vec::with_capacity(total);
    let mut patches: Vec<Patch> = Vec::new();
    // A cell is a column along its points' normal axis in the capture steps (column cells) and,
    // with segments, in every other step: a cell face across a surface would split the passes
    // that disagree about where the surface is (by more than its distance to the face) into two
    // cells that never meet, and that disagreement then persists. Along the normal, outside the
    // capture steps, plane distance tells a segment's parallel surfaces apart (`within_plane`);
    // the capture steps, with the passes still decimetres apart, group by normal alone.
    let normal_columns = step.column_cells || params.segment_surfaces;
    let plane_patches = params.segment_surfaces && !step.column_cells;
    let mut patch_slots: FxHashMap<(u64, u32, u32), CellModels> = FxHashMap::default();
    for (chunk_index, chunk) in chunks.iter().enumerate() {
        let corr = &corrections[chunk.trajectory as usize];
        let shift = [chunk.origin[0] - ox, chunk.origin[1] - oy, chunk.origin[2]];
        let mut last = ((u64::MAX, 0u32, 0u32), CellModels::default());
        for k in 0..chunk.len() {
            let c = corr.at(chunk.anchor[k], chunk.lambda[k]);
            let rotation = SmallRotation::new([c[3], c[4], c[5]]);
            let rr = rotation.apply(chunk.r[k].map(f64::from));
            let t0 = chunk.t0[k];
            let p = [
                t0[0] as f64 + shift[0] + c[0] + rr[0],
                t0[1] as f64 + shift[1] + c[1] + rr[1],
                t0[2] as f64 + shift[2] + c[2] + rr[2],
            ];
            let n = rotation.apply(chunk.normal[k].map(f64::from));
            if solves_field {
                vehicle.push([chunk.origin[0] + t0[0] as f64, chunk.origin[1] + t0[1] as f64]);
            }
            position.push(p);
            measurement.push(rr);
            let unbounded = normal_columns.then(|| dominant_axis(&n));
            let cell = cell_key(&p, inv_cell, unbounded);
            let key = if params.segment_surfaces {
                (cell, chunk_index as u32, chunk.segment[k])
            } else {
                (cell, u32::MAX, 0)
            };
            if key != last.0 {
                if last.0 .0 != u64::MAX {
                    patch_slots.insert(last.0, last.1);
                }
                last = (key, patch_slots.get(&key).copied().unwrap_or_default());
            }
            let slots = &mut last.1;
            let mut best = NONE;
            // The best cosine so far as `along² / norm²` (`cos_group` to begin with): the tests
            // `cos > best` and of the plane distance, squared and multiplied out, need no root
            // and no division (they run per point).
            let (mut best_along2, mut best_norm2) = (cos_group * cos_group, 1.0);
            for &id in &slots.ids[..slots.len as usize] {
                let m = &patches[id as usize];
                let norm2 = dot(m.sum_normal, m.sum_normal);
                let along = dot(n, m.sum_normal);
                if along > 0.0
                    && along * along * best_norm2 > best_along2 * norm2
                    && (!plane_patches || m.within_plane(&p, norm2))
                {
                    (best_along2, best_norm2) = (along * along, norm2);
                    best = id;
                }
            }
            if best == NONE && (slots.len as usize) < MAX_MODELS_PER_CELL {
                best = patches.len() as u32;
                patches.push(Patch {
                    cell: key.0,
                    strip: chunk.strip,
                    anchor: chunk.anchor[k],
                    sum_normal: [0.0; 3],
                    sum_position: [0.0; 3],
                    count: 0,
                });
                slots.ids[slots.len as usize] = best;
                slots.len += 1;
            }
            if best != NONE {
                let m = &mut patches[best as usize];
                for a in 0..3 {
                    m.sum_normal[a] += n[a];
                    m.sum_position[a] += p[a];
                }
                m.count += 1;
            }
            patch_of.push(best);
        }
    }
    drop(patch_slots);
    // 1b. Join the patches of a cell into surface models: a patch joins the model whose normal
    //     agrees and whose plane is nearest (within the join distance), unless that model already
    //     holds another segment of the same strip pass (road and sidewalk, both sides of a curb).
    // Not below 10 cm: strips that still disagree by a few centimetres must meet in one model, and
    // membership flipping between iterations as the strips move would make the corrections jump.
    let join_distance = step.threshold_m.max(JOIN_DISTANCE_MIN_M);
    let model_of_patch = if params.segment_surfaces {
        join_patches(&patches, cos_group, join_distance)
    } else {
        (0..patches.len() as u32).collect()
    };
    let mut models: Vec<SurfaceModel> = Vec::new();
    for (patch, &id) in patches.iter().zip(&model_of_patch) {
        if id == NONE {
            continue;
        }
        if id as usize >= models.len() {
            models.resize(id as usize + 1, SurfaceModel::new());
        }
        let m = &mut models[id as usize];
        for a in 0..3 {
            m.sum_normal[a] += patch.sum_normal[a];
            m.sum_position[a] += patch.sum_position[a];
        }
        m.count += patch.count;
    }
    let model_of: Vec<u32> =
        patch_of.iter().map(|&p| if p == NONE { NONE } else { model_of_patch[p as usize] }).collect();
    drop(patch_of);
    for m in &mut models {
        m.finish_frame();
    }
    let triangles = Triangles {
        chunks,
        models: &models,
        position: &position,
        model_of: &model_of,
        cos_group,
        within_segment: params.segment_surfaces,
    };
    let weight = 1.0 / (params.sigma_distance_m * params.sigma_distance_m);
    let threshold = step.threshold_m;
    let mut stats = TileStats::new(tile);
    stats.surface_models = models.len() as u64;
    let in_core = |p: &[f64; 3]| p[0] >= 0.0 && p[0] < tile_size && p[1] >= 0.0 && p[1] < tile_size;
    // 2. The latent height under every point of the tile's core (NaN: not observable).
    let sampled = grid < params.point_latent_below_grid_m;
    let by_pixel = sampled && params.latent_pixel_share > 0.0 && params.cover_agreement_thresholds <= 0.0;
    let index = (sampled && !by_pixel).then(|| CoreIndex::new(&triangles, &in_core));
    let mut covers = Vec::new();
    let mut pixel_pulls = None;
    let Latent { points: latent, pull } = match &index {
        None if by_pixel => {
            let vehicle = solves_field.then_some(vehicle.as_slice());
            let pulls = params.consistent_gradient.then_some(ItemPull { threshold, weight });
            let (latent, pulls) = pixels::pixel_latent(
                &triangles,
                &in_core,
                grid,
                params.latent_pixel_share,
                vehicle,
                pulls,
                &mut stats,
                sink,
            );
            pixel_pulls = pulls;
            latent
        }
        Some(index) => {
            let pulls = params.consistent_gradient.then_some((&mut covers, ItemPull { threshold, weight }));
            let agreement = match params.cover_agreement_thresholds {
                f if f > 0.0 => f * threshold,
                _ => f64::INFINITY,
            };
            let vehicle = solves_field.then_some(vehicle.as_slice());
            point_latent(&triangles, index, vehicle, pulls, agreement, &mut stats, sink)
        }
        None => {
            let vehicle = solves_field.then_some(vehicle.as_slice());
            let points = raster_latent(&triangles, grid, &in_core, vehicle, &mut stats, sink);
            Latent { points, pull: Vec::new() }
        }
    };
    // 2b. With a consistent gradient, what every used point's residual pulls on the corners of
    //     the other passes' triangles that cover it.
    let mut pulls = match pixel_pulls {
        Some(pulls) => Some(pulls),
        None => (index.is_some() && params.consistent_gradient).then(|| corner_pulls(&triangles, &covers, &pull)),
    };
    drop((index, covers, pull));
    let mut field = solves_field.then(|| match (params.common_mode_heading, params.common_mode_tilt) {
        (true, true) => FieldAccumulator::with_tilt(params.common_mode_field_m),
        (true, false) => FieldAccumulator::with_heading(params.common_mode_field_m),
        (false, _) => FieldAccumulator::new(params.common_mode_field_m),
    });

    // 2c. Control targets: the core points that observe them.
    let (control_observations, control_sums) =
        observe_control(control, chunks, &position, &models, &model_of, [ox, oy], &in_core, params, threshold);
    stats.control = control_sums;
    let mut control_observations = control_observations.into_iter().peekable();

    // 3–4. Observations of the points in the tile's core, summed into normal-equation blocks.
    let mut histogram = ResidualHistogram::default();
    let mut per_trajectory: BTreeMap<u32, BTreeMap<u32, AnchorBlock>> = BTreeMap::new();
    let mut base = 0usize;
    for chunk in chunks {
        let Some((first, last)) = chunk.anchor_range() else { continue };
        let mut intervals = vec![IntervalMoments::default(); (last - first) as usize];
        for k in 0..chunk.len() {
            let a = base + k;
            let lambda = chunk.lambda[k] as f64;
            let moments = &mut intervals[(chunk.anchor[k] - first) as usize];
            // With a consistent gradient, what the other points' residuals pull on this one
            // through the triangles it is a corner of; on its own model the pull shares the
            // point's own Jacobian row, so it joins the point's observation below.
            let mut own_pull = match &mut pulls {
                Some(pulls) => pulls.take(a, &models, &measurement, moments, lambda),
                None => None,
            };
            let p = &position[a];
            let core = in_core(p);
            stats.points += core as u64;
            let id = model_of[a];
            let at = &latent[a];
            let latent = if core && id != NONE { at.height } else { f64::NAN };
            if !latent.is_nan() {
                let m = &models[id as usize];
                let h = m.height(p);
                stats.points_modelled += 1;
                let e = h - latent;
                histogram.add(e);
                if e.abs() <= threshold {
                    stats.points_used += 1;
                    if let Some(used) = used.as_deref_mut() {
                        used.push(UsedPoint { strip: chunk.strip, source: chunk.source[k], model: id });
                    }
                    stats.residual_sum_m += e;
                    stats.residual_sum2_m2 += e * e;
                    let w = m.w;
                    let g = jacobian(w, measurement[a]);
                    // With a consistent gradient the point pulls on its own pass by its share in
                    // the latent height; the covering passes get the rest (`corner_pulls`).
                    let own_weight = match &pulls {
                        Some(_) => weight * at.covering as f64 / (at.covering as f64 + 1.0),
                        None => weight,
                    };
                    // Both observations in one: weights add, and so do weight × residual.
                    let (total, weighted, observations) = match own_pull.take() {
                        Some([w_sum, we_sum]) => (own_weight + w_sum, own_weight * e - we_sum, 2),
                        None => (own_weight, own_weight * e, 1),
                    };
                    moments.add_weighted(&g, weighted, total, lambda, observations);
                    if let Some(field) = field.as_mut() {
                        let [x, y, share] = at.others;
                        field.add(FieldRow {
                            vehicle: vehicle[a],
                            others: [x, y],
                            k: share,
                            w,
                            e,
                            weight,
                            lever: [g[3], g[4], g[5]],
                            anchored: false,
                        });
                    }
                }
            }
            if let Some([w_sum, we_sum]) = own_pull {
                moments.add(&jacobian(models[id as usize].w, measurement[a]), -we_sum / w_sum, w_sum, lambda);
            }
            while let Some(o) = control_observations.next_if(|o| o.point == a) {
                let g = jacobian(o.w, measurement[a]);
                moments.add_weighted(&g, o.weight * o.e, o.weight, lambda, 1);
                if let Some(field) = field.as_mut() {
                    field.add(FieldRow {
                        vehicle: vehicle[a],
                        others: vehicle[a],
                        k: 1.0,
                        w: o.w,
                        e: o.e,
                        weight: o.weight,
                        lever: [g[3], g[4], g[5]],
                        anchored: true,
                    });
                }
            }
        }
        let blocks = per_trajectory.entry(chunk.trajectory).or_default();
        for (offset, moments) in intervals.iter().enumerate() {
            if moments.is_empty() {
                continue;
            }
            let i = first + offset as u32;
            let mut at = blocks.remove(&i).unwrap_or_else(|| AnchorBlock::new(i));
            let after = blocks.entry(i + 1).or_insert_with(|| AnchorBlock::new(i + 1));
            moments.scatter(&mut at, after);
            blocks.insert(i, at);
        }
        base += chunk.len();
    }
    stats.histogram = histogram;
    let blocks = per_trajectory
        .into_iter()
        .map(|(trajectory, map)| TrajectoryBlocks { trajectory, blocks: map.into_values().collect() })
        .collect();
    Ok(TileEstimate {
        tile,
        blocks,
        stats,
        field: field.map(FieldAccumulator::finish),
        latent_std: None,
        latent_map: None,
    })
}

/// The control targets' observations among the tile's core points and what the points measured
/// at every target ([`crate::control::observe_targets`]).
#[allow(clippy::too_many_arguments)]
fn observe_control(
    control: &[ControlTarget],
    chunks: &[TileChunk],
    position: &[[f64; 3]],
    models: &[SurfaceModel],
    model_of: &[u32],
    origin: [f64; 2],
    in_core: &impl Fn(&[f64; 3]) -> bool,
    params: &Parameters,
    threshold: f64,
) -> (Vec<TargetObservation>, Vec<ControlSums>) {
    if control.is_empty() {
        return (Vec::new(), Vec::new());
    }
    // Each point's strip pass: chunks are consecutive runs of the points.
    let mut starts = Vec::with_capacity(chunks.len());
    let mut base = 0;
    for c in chunks {
        starts.push(base);
        base += c.len();
    }
    let pass = |i: usize| {
        let c = starts.partition_point(|&s| s <= i) - 1;
        pass_tag(chunks[c].strip, chunks[c].anchor[i - starts[c]])
    };
    let model = |i: usize| {
        let id = model_of[i];
        (id != NONE && in_core(&position[i])).then(|| (models[id as usize].w, models[id as usize].o))
    };
    let points = TilePoints { origin, position, model, pass };
    observe_targets(control, &points, params, threshold)
}

/// The points of one strip segment in one cell whose normals agree.
#[derive(Clone, Debug)]
struct Patch {
    cell: u64,
    strip: u32,
    /// Anchor of the first point (tells passes of one strip apart, see [`pass_tag`]).
    anchor: u32,
    sum_normal: [f64; 3],
    sum_position: [f64; 3],
    count: u32,
}

impl Patch {
    /// Whether `p` lies within [`PATCH_PLANE_M`] of the patch's plane (`norm2`: the squared length
    /// of its normal sum): `|(p − Σp/n)·Σw| / |Σw|`, multiplied out by `n·|Σw|` and squared.
    #[inline]
    fn within_plane(&self, p: &[f64; 3], norm2: f64) -> bool {
        let c = self.count as f64;
        let s = &self.sum_position;
        let d = dot([c * p[0] - s[0], c * p[1] - s[1], c * p[2] - s[2]], self.sum_normal);
        d * d <= PATCH_PLANE_M * PATCH_PLANE_M * c * c * norm2
    }
}

/// `|(p − c) · axis|` for the centroid `c` of `count` points whose positions sum to
/// `sum_position`: with a unit `axis`, the distance of `p` from the plane through the centroid.
#[inline]
fn offset_along(axis: [f64; 3], sum_position: &[f64; 3], count: f64, p: &[f64; 3]) -> f64 {
    let c = [sum_position[0] / count, sum_position[1] / count, sum_position[2] / count];
    dot([p[0] - c[0], p[1] - c[1], p[2] - c[2]], axis).abs()
}

/// A model of the cell being joined: (id, normal sum, position sum, count, member passes as
/// (strip, anchor)).
type OpenModel = (u32, [f64; 3], [f64; 3], f64, Vec<(u32, u32)>);

/// Model id of every patch (dense ids, [`NONE`] where a cell ran out of model slots). Per cell,
/// larger patches go first (ties by index, so the result does not depend on hash order); a patch
/// joins the agreeing model with the nearest plane, or opens a new one.
fn join_patches(patches: &[Patch], cos_group: f64, join_distance: f64) -> Vec<u32> {
    let mut order: Vec<u32> = (0..patches.len() as u32).collect();
    order.sort_unstable_by_key(|&i| (patches[i as usize].cell, std::cmp::Reverse(patches[i as usize].count), i));
    let mut out = vec![NONE; patches.len()];
    let mut next_model = 0u32;
    let mut open: Vec<OpenModel> = Vec::new();
    let mut cell = u64::MAX;
    for &i in &order {
        let p = &patches[i as usize];
        if p.cell != cell {
            open.clear();
            cell = p.cell;
        }
        let n = normalize(p.sum_normal);
        let c = p.count as f64;
        let centre = [p.sum_position[0] / c, p.sum_position[1] / c, p.sum_position[2] / c];
        let mut best: Option<(usize, f64)> = None;
        for (slot, (_, sn, sp, count, passes)) in open.iter().enumerate() {
            let w = normalize(*sn);
            if dot(n, w) <= cos_group {
                continue;
            }
            let d = offset_along(w, sp, *count, &centre);
            // Within one strip pass the geometry is exact up to the noise: another segment of the
            // same pass joins only if coplanar (a surface split by an occlusion), never a parallel
            // surface nearby (road and sidewalk either side of a curb).
            let same_pass = passes.iter().any(|&(s, a)| s == p.strip && a.abs_diff(p.anchor) < PASS_ANCHORS);
            let limit = if same_pass { SAME_PASS_JOIN_M } else { join_distance };
            if d <= limit && best.is_none_or(|(_, bd)| d < bd) {
                best = Some((slot, d));
            }
        }
        let slot = match best {
            Some((slot, _)) => slot,
            None if open.len() < 2 * MAX_MODELS_PER_CELL => {
                open.push((next_model, [0.0; 3], [0.0; 3], 0.0, Vec::new()));
                next_model += 1;
                open.len() - 1
            }
            None => continue,
        };
        let m = &mut open[slot];
        for a in 0..3 {
            m.1[a] += p.sum_normal[a];
            m.2[a] += p.sum_position[a];
        }
        m.3 += c;
        m.4.push((p.strip, p.anchor));
        out[i as usize] = m.0;
    }
    out
}

/// One model's raster: pixel (i, j) has its centre at `u0 + (i + ½)·size`, `v0 + (j + ½)·size`,
/// and its index `offset + j·nu + i` in the tile's pixels.
#[derive(Clone, Copy, Debug, Default)]
struct PixelGrid {
    u0: f64,
    v0: f64,
    size: f64,
    inv: f64,
    nu: u32,
    nv: u32,
    offset: usize,
}

impl PixelGrid {
    /// The pixel holding `(u, v)` (clamped to the raster).
    #[inline]
    fn pixel(&self, u: f64, v: f64) -> usize {
        let inv = self.inv;
        let i = floor_i64((u - self.u0) * inv).clamp(0, self.nu as i64 - 1) as usize;
        let j = floor_i64((v - self.v0) * inv).clamp(0, self.nv as i64 - 1) as usize;
        self.offset + j * self.nu as usize + i
    }

    /// The four pixel centres around `(u, v)` that bilinear interpolation reads; `None` unless
    /// all four lie in the raster. One look-up for every value read there (height, scan heads).
    #[inline]
    fn cell(&self, u: f64, v: f64) -> Option<Cell> {
        let fu = (u - self.u0) / self.size - 0.5;
        let fv = (v - self.v0) / self.size - 0.5;
        let (i0, j0) = (floor(fu), floor(fv));
        let (tu, tv) = (fu - i0, fv - j0);
        let (i0, j0) = (i0 as i64, j0 as i64);
        if i0 < 0 || j0 < 0 || i0 + 1 >= self.nu as i64 || j0 + 1 >= self.nv as i64 {
            return None;
        }
        Some(Cell { at: self.offset + (j0 * self.nu as i64 + i0) as usize, tu, tv })
    }

    /// The pixel centres under `plane`'s bounding box (the exact box: a triangle spans about
    /// one pixel, and each row or column more would double the candidates); `None` if none.
    #[inline]
    fn centres_under<'a>(&'a self, plane: &'a PlaneTriangle) -> Option<CentreBox<'a>> {
        let (inv, [u0, v0, _], d1, d2) = (self.inv, plane.origin, plane.d1, plane.d2);
        let (xs, ys) = ((u0 - self.u0) * inv - 0.5, (v0 - self.v0) * inv - 0.5);
        let (x1, x2) = (xs + d1[0] * inv, xs + d2[0] * inv);
        let (y1, y2) = (ys + d1[1] * inv, ys + d2[1] * inv);
        let i = [ceil_i64(xs.min(x1).min(x2)).max(0), floor_i64(xs.max(x1).max(x2)).min(self.nu as i64 - 1)];
        let j = [ceil_i64(ys.min(y1).min(y2)).max(0), floor_i64(ys.max(y1).max(y2)).min(self.nv as i64 - 1)];
        (i[0] <= i[1] && j[0] <= j[1]).then_some(CentreBox { grid: self, plane, xs, ys, i, j })
    }
}

/// The pixel centres under a triangle's bounding box ([`PixelGrid::centres_under`]).
struct CentreBox<'a> {
    grid: &'a PixelGrid,
    plane: &'a PlaneTriangle,
    /// The triangle's first corner in pixel coordinates (centre (i, j) at (i, j)).
    xs: f64,
    ys: f64,
    /// First and last column and row.
    i: [i64; 2],
    j: [i64; 2],
}

impl CentreBox<'_> {
    /// How far outside an edge (in barycentric coordinates) a centre still counts as inside:
    /// both walks take the same centres.
    const SLACK: f64 = -1e-9;

    /// How many centres [`Self::for_each`] visits.
    #[inline]
    fn len(&self) -> usize {
        ((self.i[1] - self.i[0] + 1) * (self.j[1] - self.j[0] + 1)) as usize
    }

    /// `visit(pixel, height, inside)` for every centre in the box, row by row: its index in the
    /// tile's pixels, the plane's height there, and whether it lies in the triangle (by its
    /// barycentric coordinates, with 10⁻⁹ of slack). For triangles of about one centre (the
    /// pixel route's), whose box holds about two (4.46 per point): a caller can write every
    /// one without a branch.
    #[inline]
    fn for_each(&self, mut visit: impl FnMut(usize, f64, bool)) {
        let (g, plane) = (self.grid, self.plane);
        for j in self.j[0]..=self.j[1] {
            let dv = (j as f64 - self.ys) * g.size;
            let row = g.offset + j as usize * g.nu as usize;
            for i in self.i[0]..=self.i[1] {
                let (l1, l2) = plane.barycentric((i as f64 - self.xs) * g.size, dv);
                let inside = (l1 >= Self::SLACK) & (l2 >= Self::SLACK) & (1.0 - l1 - l2 >= Self::SLACK);
                visit(row + i as usize, plane.height(l1, l2), inside);
            }
        }
    }

    /// `visit(pixel, height)` for the centres in the triangle only, row by row (scanline
    /// form, for triangles that span several pixels: the raster steps' at 5 cm cover about six
    /// centres each). Along a row each barycentric coordinate is affine in the
    /// column, so the three half-planes bound the row's span directly: three divisions per
    /// triangle, where the scanline this replaced divided three times per row, and no test per
    /// centre of the box. A centre within rounding of an edge may fall either way, as with the
    /// per-centre test.
    #[inline]
    fn for_each_inside(&self, mut visit: impl FnMut(usize, f64)) {
        let (g, plane) = (self.grid, self.plane);
        let (d1, d2) = (plane.d1, plane.d2);
        // Per column: the change of l1, l2 and 1 − l1 − l2.
        let step1 = d2[1] * g.size * plane.inv_area;
        let step2 = -d1[1] * g.size * plane.inv_area;
        let steps = [step1, step2, -(step1 + step2)];
        let inverse = steps.map(|b| if b != 0.0 { 1.0 / b } else { 0.0 });
        let last = (self.i[1] - self.i[0]) as f64;
        for j in self.j[0]..=self.j[1] {
            let dv = (j as f64 - self.ys) * g.size;
            // The coordinates at the box's first column; column k adds k steps.
            let (l1, l2) = plane.barycentric((self.i[0] as f64 - self.xs) * g.size, dv);
            let first = [l1, l2, 1.0 - l1 - l2];
            let (mut lo, mut hi) = (0.0f64, last);
            for c in 0..3 {
                // first + k·step ≥ SLACK
                let bound = (Self::SLACK - first[c]) * inverse[c];
                if steps[c] > 0.0 {
                    lo = lo.max(bound);
                } else if steps[c] < 0.0 {
                    hi = hi.min(bound);
                } else if first[c] < Self::SLACK {
                    hi = -1.0;
                }
            }
            let (k0, k1) = (ceil_i64(lo), floor_i64(hi));
            let row = g.offset + j as usize * g.nu as usize + self.i[0] as usize;
            for k in k0..=k1 {
                let kf = k as f64;
                visit(row + k as usize, plane.height(l1 + kf * step1, l2 + kf * step2));
            }
        }
    }
}

/// `x.ceil() as i64` without the libm call (see [`floor_i64`]).
#[inline]
fn ceil_i64(x: f64) -> i64 {
    let i = x as i64;
    i + ((i as f64) < x) as i64
}

/// The four pixel centres around a point that bilinear interpolation reads: the lower-left
/// one's index in the tile's pixels and the point's fractions of the way to the next column and
/// row ([`PixelGrid::cell`]).
#[derive(Clone, Copy, Debug)]
struct Cell {
    at: usize,
    tu: f64,
    tv: f64,
}

/// Latent height in `cell`, bilinear between its four pixel centres, all of which must be
/// shared by two or more strip passes. `None` also where the latent surface is steeper than
/// [`MAX_SLOPE`] against the model plane: there (curbs, recesses, occlusion edges) the distance
/// along the model normal does not measure the distance to the surface, and a lateral offset
/// between strips would be read as a height difference.
#[inline]
fn latent_height(r: &PixelGrid, pixels: &[Pixel], cell: Cell) -> Option<f64> {
    let (Cell { at, tu, tv }, row) = (cell, r.nu as usize);
    let height = |k: usize| -> Option<f64> {
        let p = &pixels[k];
        p.shared().then(|| p.mean())
    };
    let (a, b, c, d) = (height(at)?, height(at + 1)?, height(at + row)?, height(at + row + 1)?);
    let slope_u = ((b - a) * (1.0 - tv) + (d - c) * tv) / r.size;
    let slope_v = ((c - a) * (1.0 - tu) + (d - b) * tu) / r.size;
    if slope_u * slope_u + slope_v * slope_v > MAX_SLOPE * MAX_SLOPE {
        return None;
    }
    let bottom = a * (1.0 - tu) + b * tu;
    let top = c * (1.0 - tu) + d * tu;
    Some(bottom * (1.0 - tv) + top * tv)
}

/// The scan-image triangles of a tile's strips (point, next in revolution, same row next
/// revolution, and the opposite triangle of that quad), each with the surface models it lies on.
struct Triangles<'a> {
    chunks: &'a [TileChunk],
    models: &'a [SurfaceModel],
    position: &'a [[f64; 3]],
    model_of: &'a [u32],
    cos_group: f64,
    /// Only triangles whose three corners lie in one scan-image segment: one whose corners the
    /// segmentation split (a C0 or C1 break: a curb, a window reveal, a bridge over the far curb
    /// at grazing incidence) interpolates across that break, and the points of other passes
    /// under it get a latent height centimetres off, so they are rejected as outliers.
    within_segment: bool,
}

impl Triangles<'_> {
    /// Calls `visit(model, corners, indices, strip, anchor, first)` (the corners' positions and
    /// point indices; `first`: index of the corner the triangle hangs off) for every triangle and
    /// every surface model one of its corners belongs to, provided the triangle is continuous
    /// surface (short edges) lying on that model (facet and model normals agree, and the
    /// corners' models are not at odds) and, with `within_segment`, within one segment.
    fn for_each(&self, mut visit: impl FnMut(u32, [[f64; 3]; 3], [usize; 3], u32, u32, usize)) {
        let mut base = 0usize;
        for chunk in self.chunks {
            for k in 0..chunk.len() {
                let (right, down) = (chunk.right[k], chunk.down[k]);
                if right == NO_NEIGHBOUR || down == NO_NEIGHBOUR {
                    continue;
                }
                let (a, b, c) = (base + k, base + right as usize, base + down as usize);
                let limit =
                    chunk.edge_limit[k].max(chunk.edge_limit[right as usize]).max(chunk.edge_limit[down as usize]);
                let anchor = chunk.anchor[k];
                let segment = &chunk.segment;
                let joined = |i: u32, j: u32| !self.within_segment || segment[i as usize] == segment[j as usize];
                if joined(k as u32, right) && joined(k as u32, down) {
                    self.triangle([a, b, c], limit as f64, |m, p, v| visit(m, p, v, chunk.strip, anchor, a));
                }
                let diagonal = chunk.down[right as usize];
                if diagonal != NO_NEIGHBOUR && joined(diagonal, right) && joined(diagonal, down) {
                    let d = base + diagonal as usize;
                    let limit = limit.max(chunk.edge_limit[diagonal as usize]);
                    self.triangle([b, d, c], limit as f64, |m, p, v| visit(m, p, v, chunk.strip, anchor, a));
                }
            }
            base += chunk.len();
        }
    }

    #[inline]
    fn triangle(&self, v: [usize; 3], limit: f64, mut visit: impl FnMut(u32, [[f64; 3]; 3], [usize; 3])) {
        let ids = [self.model_of[v[0]], self.model_of[v[1]], self.model_of[v[2]]];
        if ids.contains(&NONE) {
            return;
        }
        let [pa, pb, pc] = [self.position[v[0]], self.position[v[1]], self.position[v[2]]];
        let ab = [pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2]];
        let ac = [pc[0] - pa[0], pc[1] - pa[1], pc[2] - pa[2]];
        let bc = [pc[0] - pb[0], pc[1] - pb[1], pc[2] - pb[2]];
        let limit2 = limit * limit;
        if dot(ab, ab) > limit2 || dot(ac, ac) > limit2 || dot(bc, bc) > limit2 {
            return;
        }
        let face = cross(ab, ac);
        let area2_sq = dot(face, face);
        if area2_sq < 1e-24 {
            return;
        }
        // |cos| of the facet against a unit model normal, compared squared: no root, no division.
        let facet_limit = FACET_COS * FACET_COS * area2_sq;
        for (slot, &id) in ids.iter().enumerate() {
            if ids[..slot].contains(&id) {
                continue;
            }
            let m = &self.models[id as usize];
            let along = dot(face, m.w);
            if along * along < facet_limit
                || ids.iter().any(|&other| other != id && dot(self.models[other as usize].w, m.w) < self.cos_group)
            {
                continue;
            }
            visit(id, [pa, pb, pc], v);
        }
    }

    /// A visited triangle in model `id`'s plane: corners on that model from `uvh` (their
    /// projections, computed once per point), a corner on another (agreeing) model projected
    /// here. `None` for a triangle without area in the plane. Always inlined: out of line it
    /// cost the 2 cm pass 1.8 % more instructions (callgrind).
    #[inline(always)]
    fn plane_triangle(
        &self,
        id: u32,
        p: &[[f64; 3]; 3],
        corners: [usize; 3],
        uvh: &[[f64; 3]],
    ) -> Option<PlaneTriangle> {
        let mut plane = [[0.0; 3]; 3];
        for (k, (&a, at)) in corners.iter().zip(&mut plane).enumerate() {
            *at = if self.model_of[a] == id {
                uvh[a]
            } else {
                let (u, v, h) = self.models[id as usize].project(&p[k]);
                [u, v, h]
            };
        }
        PlaneTriangle::new(plane)
    }
}

/// Latent heights from height rasters of pixel size `grid`: every triangle is rasterised into
/// the pixels of its models (heights interpolated at the pixel centres), and a point's latent
/// height is the bilinear interpolation of the four pixels around it ([`latent_height`]).
///
/// With `vehicle` it also gives, per point, the mean scan-head position of everything its
/// latent height averages (its own pass included, which makes the field's row
/// `φ(v) − φ(v̄)` carry the other passes' share by itself) and a share of 1, `[x, y, 1]`.
fn raster_latent<S: LatentSink>(
    t: &Triangles,
    grid: f64,
    in_core: &impl Fn(&[f64; 3]) -> bool,
    vehicle: Option<&[[f64; 2]]>,
    stats: &mut TileStats,
    sink: &mut S,
) -> Vec<PointLatent> {
    let models = t.models;
    // Raster extents from the member points; one pixel of margin on each side keeps bilinear
    // interpolation inside the raster.
    let mut bounds = vec![[f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY]; models.len()];
    // Every member point in its model's plane, once: the triangles' corners and the core points
    // read it.
    let mut uvh = vec![[0.0f64; 3]; t.position.len()];
    for ((p, &id), at) in t.position.iter().zip(t.model_of).zip(&mut uvh) {
        if id == NONE {
            continue;
        }
        let (u, v, h) = models[id as usize].project(p);
        *at = [u, v, h];
        let b = &mut bounds[id as usize];
        b[0] = b[0].min(u);
        b[1] = b[1].max(u);
        b[2] = b[2].min(v);
        b[3] = b[3].max(v);
    }
    let mut pixel_count = 0usize;
    let inv = 1.0 / grid;
    let rasters: Vec<PixelGrid> = bounds
        .iter()
        .map(|b| {
            let r = PixelGrid {
                u0: b[0] - grid,
                v0: b[2] - grid,
                size: grid,
                inv,
                nu: ((b[1] - b[0]) / grid).ceil() as u32 + 2,
                nv: ((b[3] - b[2]) / grid).ceil() as u32 + 2,
                offset: pixel_count,
            };
            pixel_count += (r.nu * r.nv) as usize;
            r
        })
        .collect();
    let mut pixels = vec![Pixel::default(); pixel_count];
    t.for_each(|id, p, corners, strip, anchor, first| {
        let from = vehicle.map_or([0.0; 2], |v| v[first]);
        let r = &rasters[id as usize];
        let tag = pass_tag(strip, anchor);
        let Some(plane) = t.plane_triangle(id, &p, corners, &uvh) else { return };
        let Some(centres) = r.centres_under(&plane) else { return };
        centres.for_each_inside(|at, height| pixels[at].add(height as f32, tag, from));
    });
    stats.pixels = pixel_count as u64;
    for p in &pixels {
        if p.shared() {
            stats.pixels_shared += 1;
            let mean = p.sum as f64 / p.count as f64;
            let var = (p.sum2 as f64 / p.count as f64 - mean * mean).max(0.0);
            stats.pixel_std_sum_m += var.sqrt();
        }
    }
    t.position
        .iter()
        .zip(t.model_of)
        .zip(&uvh)
        .map(|((p, &id), &[u, v, own])| {
            if id == NONE || !in_core(p) {
                return PointLatent::default();
            }
            let m = &models[id as usize];
            let r = &rasters[id as usize];
            let cell = r.cell(u, v);
            let h = cell.and_then(|cell| latent_height(r, &pixels, cell)).unwrap_or(f64::NAN);
            if let (true, Some(cell)) = (S::RECORDS && !h.is_nan(), cell) {
                let (std_m, contributions) = raster_std(r, &pixels, cell);
                sink.add(&LatentSample {
                    position: lifted(p, m.w, h - own),
                    normal: m.w,
                    residual_m: own - h,
                    std_m,
                    passes: contributions,
                    used: true,
                });
            }
            let others = match (vehicle, cell) {
                (Some(_), Some(cell)) if !h.is_nan() => raster_vehicle_mean(r, &pixels, cell),
                _ => [0.0; 3],
            };
            PointLatent { height: h, others, covering: 0 }
        })
        .collect()
}

/// Standard deviation of the strips' heights in the pixel holding the point of `cell` (the one
/// of its four centres nearest to the point, which [`latent_height`] interpolated from, so it has
/// contributions), and that pixel's count of surface contributions.
fn raster_std(r: &PixelGrid, pixels: &[Pixel], cell: Cell) -> (f64, u32) {
    let Cell { at, tu, tv } = cell;
    let p = &pixels[at + (tu >= 0.5) as usize + (tv >= 0.5) as usize * r.nu as usize];
    let n = p.count as f64;
    let mean = p.sum as f64 / n;
    ((p.sum2 as f64 / n - mean * mean).max(0.0).sqrt(), p.count)
}

/// `p` moved by `by` along the unit normal `w`.
#[inline]
fn lifted(p: &[f64; 3], w: [f64; 3], by: f64) -> [f64; 3] {
    [p[0] + by * w[0], p[1] + by * w[1], p[2] + by * w[2]]
}

/// Mean scan-head position of the contributions to the four pixels a point's latent height
/// interpolates, weighted like the heights (bilinear), as `[x, y, 1]`.
fn raster_vehicle_mean(r: &PixelGrid, pixels: &[Pixel], cell: Cell) -> [f64; 3] {
    let (Cell { at, tu, tv }, row) = (cell, r.nu as usize);
    let mut out = [0.0, 0.0, 1.0];
    for (di, dj, wgt) in
        [(0, 0, (1.0 - tu) * (1.0 - tv)), (1, 0, tu * (1.0 - tv)), (0, 1, (1.0 - tu) * tv), (1, 1, tu * tv)]
    {
        let p = &pixels[at + dj * row + di];
        let c = p.count as f64;
        out[0] += wgt * p.vehicle[0] / c;
        out[1] += wgt * p.vehicle[1] / c;
    }
    out
}

/// The core points of a tile sorted into a bucket grid per surface model (about
/// [`POINTS_PER_BUCKET`] per bucket), in bucket order: the points a triangle may cover lie next
/// to each other in memory.
struct CoreIndex {
    grids: Vec<Buckets>,
    /// Per bucket, the first item; one more entry closes the last bucket.
    start: Vec<u32>,
    /// Point index (into the tile's points) per item.
    items: Vec<u32>,
    /// Plane coordinates of each item in its model's frame.
    item_uv: Vec<[f64; 2]>,
    /// Strip and anchor of each item (for the own-pass test).
    item_owner: Vec<(u32, u32)>,
    /// Height of each item above its model's plane (in item order: read where the items are
    /// walked in order, not by point index).
    item_h: Vec<f64>,
}

impl CoreIndex {
    fn new(t: &Triangles, in_core: &impl Fn(&[f64; 3]) -> bool) -> Self {
        let models = t.models;
        let n = t.position.len();
        let mut uvh = vec![[f64::NAN; 3]; n];
        let mut owner = vec![(0u32, 0u32); n];
        let mut bounds = vec![[f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY, 0.0]; models.len()];
        let mut base = 0usize;
        for chunk in t.chunks {
            for k in 0..chunk.len() {
                let a = base + k;
                let id = t.model_of[a];
                if id == NONE || !in_core(&t.position[a]) {
                    continue;
                }
                let (u, v, h) = models[id as usize].project(&t.position[a]);
                uvh[a] = [u, v, h];
                owner[a] = (chunk.strip, chunk.anchor[k]);
                let b = &mut bounds[id as usize];
                b[0] = b[0].min(u);
                b[1] = b[1].max(u);
                b[2] = b[2].min(v);
                b[3] = b[3].max(v);
                b[4] += 1.0;
            }
            base += chunk.len();
        }
        // Bucket grids (counting sort of the core points by model and bucket).
        let mut grids: Vec<Buckets> = Vec::with_capacity(models.len());
        let mut total = 0usize;
        for b in &bounds {
            let count = b[4];
            if count == 0.0 {
                grids.push(Buckets { u0: 0.0, v0: 0.0, inv: 0.0, nu: 0, nv: 0, offset: total });
                continue;
            }
            let (du, dv) = (b[1] - b[0], b[3] - b[2]);
            let size = (POINTS_PER_BUCKET * du.max(1e-3) * dv.max(1e-3) / count).sqrt().max(1e-3);
            let nu = (du / size) as u32 + 1;
            let nv = (dv / size) as u32 + 1;
            grids.push(Buckets { u0: b[0], v0: b[2], inv: 1.0 / size, nu, nv, offset: total });
            total += (nu * nv) as usize;
        }
        let mut start = vec![0u32; total + 1];
        let bucket_of = |a: usize| -> Option<usize> {
            let id = t.model_of[a];
            if id == NONE || uvh[a][0].is_nan() {
                return None;
            }
            let g = &grids[id as usize];
            let i = (((uvh[a][0] - g.u0) * g.inv) as u32).min(g.nu - 1);
            let j = (((uvh[a][1] - g.v0) * g.inv) as u32).min(g.nv - 1);
            Some(g.offset + (j * g.nu + i) as usize)
        };
        for a in 0..n {
            if let Some(b) = bucket_of(a) {
                start[b + 1] += 1;
            }
        }
        for b in 0..total {
            start[b + 1] += start[b];
        }
        let count = start[total] as usize;
        let mut fill = start.clone();
        let mut items = vec![0u32; count];
        for a in 0..n {
            if let Some(b) = bucket_of(a) {
                items[fill[b] as usize] = a as u32;
                fill[b] += 1;
            }
        }
        drop(fill);
        // One gather from the point-indexed projections for both item-ordered columns.
        let (item_uv, item_h): (Vec<[f64; 2]>, Vec<f64>) = items
            .iter()
            .map(|&a| {
                let [u, v, h] = uvh[a as usize];
                ([u, v], h)
            })
            .unzip();
        let item_owner: Vec<(u32, u32)> = items.iter().map(|&a| owner[a as usize]).collect();
        Self { grids, start, items, item_uv, item_owner, item_h }
    }

    /// Calls `visit(triangle, item, take, l1, l2)` for every candidate item of every triangle
    /// (barycentric coordinates `l1`, `l2`); `take` is whether the item lies inside the triangle
    /// and belongs to another pass than the triangle. Candidates that are not taken are visited
    /// too: callers add `take × value` without a branch (whether a candidate is taken is close to
    /// a coin toss, and mispredictions cost more than the sums; visiting only the taken ones,
    /// gathered without a branch, measured 4–5 % slower).
    ///
    /// The candidates are the items in the buckets under the triangle's bounding box: on small
    /// s1, 14.2 per triangle against 10.1 for the triangle's exact extent in each bucket row,
    /// yet 1.17× faster in all, as finding those extents took unpredictable branches (and
    /// 1.13× faster than finding them without a branch). `inside` alone decides.
    #[inline]
    fn for_each_cover(
        &self,
        t: &Triangles,
        vehicle: Option<&[[f64; 2]]>,
        mut visit: impl FnMut(&CoveringTriangle, usize, bool, f64, f64),
    ) {
        let models = t.models;
        t.for_each(|id, p, _, strip, anchor, first| {
            let (m, g) = (&models[id as usize], &self.grids[id as usize]);
            if g.nu == 0 {
                return;
            }
            let corners = p.map(|q| {
                let (u, v, h) = m.project(&q);
                [u, v, h]
            });
            let Some(plane) = PlaneTriangle::new(corners) else { return };
            let tri = CoveringTriangle { model: id, first, vehicle: vehicle.map_or([0.0; 2], |v| v[first]), plane };
            // Corners in bucket units.
            let [[x0, y0, _], [x1, y1, _], [x2, y2, _]] = corners;
            let bx = [(x0 - g.u0) * g.inv, (x1 - g.u0) * g.inv, (x2 - g.u0) * g.inv];
            let by = [(y0 - g.v0) * g.inv, (y1 - g.v0) * g.inv, (y2 - g.v0) * g.inv];
            let j0 = floor_i64(by[0].min(by[1]).min(by[2])).max(0);
            let j1 = floor_i64(by[0].max(by[1]).max(by[2])).min(g.nv as i64 - 1);
            const SLACK: f64 = -1e-9;
            let i0 = floor_i64(bx[0].min(bx[1]).min(bx[2])).max(0);
            let i1 = floor_i64(bx[0].max(bx[1]).max(bx[2])).min(g.nu as i64 - 1);
            if i0 > i1 {
                return;
            }
            for j in j0..=j1 {
                let row = g.offset + (j as usize) * g.nu as usize;
                let (s, e) = (self.start[row + i0 as usize] as usize, self.start[row + i1 as usize + 1] as usize);
                for q in s..e {
                    let (l1, l2) = plane.barycentric(self.item_uv[q][0] - x0, self.item_uv[q][1] - y0);
                    let inside = (l1 >= SLACK) & (l2 >= SLACK) & (1.0 - l1 - l2 >= SLACK);
                    let (s_q, a_q) = self.item_owner[q];
                    let own_pass = (s_q == strip) & (a_q.abs_diff(anchor) < SAME_PASS_ANCHORS);
                    visit(&tri, q, inside & !own_pass, l1, l2);
                }
            }
        });
    }
}

/// A triangle in a surface model's plane: its first corner `(u, v, h)`, the other two relative
/// to it, and its slope `(∂h/∂u, ∂h/∂v)`; what both sampled routes evaluate at points or pixel
/// centres.
#[derive(Clone, Copy, Debug)]
struct PlaneTriangle {
    origin: [f64; 3],
    d1: [f64; 3],
    d2: [f64; 3],
    inv_area: f64,
    hx: f64,
    hy: f64,
}

impl PlaneTriangle {
    /// `None` for a triangle without area in the plane (seen edge-on).
    #[inline]
    fn new([c0, c1, c2]: [[f64; 3]; 3]) -> Option<Self> {
        let d1 = [c1[0] - c0[0], c1[1] - c0[1], c1[2] - c0[2]];
        let d2 = [c2[0] - c0[0], c2[1] - c0[1], c2[2] - c0[2]];
        let area = d1[0] * d2[1] - d2[0] * d1[1];
        if area.abs() < 1e-12 {
            return None;
        }
        let inv_area = 1.0 / area;
        let hx = (d1[2] * d2[1] - d2[2] * d1[1]) * inv_area;
        let hy = (d2[2] * d1[0] - d1[2] * d2[0]) * inv_area;
        Some(Self { origin: c0, d1, d2, inv_area, hx, hy })
    }

    /// Barycentric coordinates `(l1, l2)` of the corners 1 and 2 at `(du, dv)` from corner 0.
    #[inline]
    fn barycentric(&self, du: f64, dv: f64) -> (f64, f64) {
        let (d1, d2) = (&self.d1, &self.d2);
        ((du * d2[1] - d2[0] * dv) * self.inv_area, (d1[0] * dv - du * d1[1]) * self.inv_area)
    }

    /// Height at the barycentric coordinates `(l1, l2)`.
    #[inline]
    fn height(&self, l1: f64, l2: f64) -> f64 {
        self.origin[2] + l1 * self.d1[2] + l2 * self.d2[2]
    }
}

/// A triangle of [`CoreIndex::for_each_cover`] in its model's plane: the model, the corner it
/// hangs off and that corner's scan head (zero without vehicle positions), and its height and
/// slope.
struct CoveringTriangle {
    model: u32,
    first: usize,
    vehicle: [f64; 2],
    plane: PlaneTriangle,
}

/// Latent heights evaluated exactly at the points of the tile's core — the limit of an
/// infinitely fine raster, at a cost that does not grow with the pixel count. Every triangle of
/// another pass of any strip that covers a point (in its model's plane) contributes its height
/// there; the point's own pass contributes the point's own height. The latent height is the mean
/// of these, provided at least one other pass covers the point and the other passes' facets
/// there are not steeper than [`MAX_SLOPE`] against the model plane. With a finite `agreement`
/// ([`Parameters::cover_agreement_thresholds`]) a triangle farther than that from the mean of
/// the point and all its covering triangles is left out.
///
/// Also returns, per point, the number `c` of other passes' triangles its latent height averages
/// (0 where it has none), and with `vehicle` (absolute horizontal scan-head positions) the mean
/// scan-head position of those triangles and their share, `[x, y, c/(c+1)]` (what the
/// common-mode field's observation row needs); otherwise that vector is empty.
///
/// With `pulls`, every (point, triangle) pair taken is recorded in its vector as
/// `[item, corner the triangle hangs off, model]`, and the last vector returned holds, per item,
/// what the point's residual pulls on each of its covering triangles ([`ItemPull`]); the two are
/// what [`corner_pulls`] gathers. Without `pulls` that vector is empty.
fn point_latent<S: LatentSink>(
    t: &Triangles,
    index: &CoreIndex,
    vehicle: Option<&[[f64; 2]]>,
    pulls: Option<(&mut Vec<[u32; 3]>, ItemPull)>,
    agreement: f64,
    stats: &mut TileStats,
    sink: &mut S,
) -> Latent {
    let n = t.position.len();
    // Every triangle adds its height (and slope) to the core points of other passes it covers.
    let mut acc = vec![Sample::default(); index.items.len()];
    let gated = agreement.is_finite();
    let (covers, pull_terms) = match pulls {
        Some((covers, terms)) => (Some(covers), Some(terms)),
        None => (None, None),
    };
    if !gated && covers.is_none() {
        index.for_each_cover(t, vehicle, |tri, q, take, l1, l2| {
            acc[q].add_masked(take, tri.plane.height(l1, l2), tri.plane.hx, tri.plane.hy, tri.vehicle);
        });
    } else {
        // Every (point, triangle) pair taken, with its height and slope; appended without a
        // branch: every candidate is written, only a taken one is kept.
        let mut own_covers = Vec::new();
        let covers = covers.unwrap_or(&mut own_covers);
        covers.clear();
        let mut heights: Vec<f64> = Vec::new();
        let mut slopes: Vec<[f32; 2]> = Vec::new();
        let mut len = 0;
        index.for_each_cover(t, vehicle, |tri, q, take, l1, l2| {
            let h = tri.plane.height(l1, l2);
            acc[q].add_masked(take, h, tri.plane.hx, tri.plane.hy, tri.vehicle);
            if len == covers.len() {
                let grown = len + len / 2 + 1024;
                covers.resize(grown, [0; 3]);
                if gated {
                    heights.resize(grown, 0.0);
                    slopes.resize(grown, [0.0; 2]);
                }
            }
            covers[len] = [q as u32, tri.first as u32, tri.model];
            if gated {
                heights[len] = h;
                slopes[len] = [tri.plane.hx as f32, tri.plane.hy as f32];
            }
            len += take as usize;
        });
        covers.truncate(len);
        if gated {
            // The consensus: the mean of the point and every covering triangle. A triangle far
            // from it (a bridge over a step, a car one pass saw) is taken out again; judged
            // against the consensus rather than the point alone, passes that are off together
            // stay outliers of the rest instead of agreeing among themselves. Points where no
            // triangle is taken out keep their sums bit for bit.
            let consensus: Vec<f64> = index.item_h.iter().zip(&acc).map(|(&h, s)| s.mean_with(h)).collect();
            let mut kept = 0;
            for i in 0..len {
                let [q, first, _] = covers[i];
                let h = heights[i];
                if (h - consensus[q as usize]).abs() <= agreement {
                    covers[kept] = covers[i];
                    kept += 1;
                    continue;
                }
                acc[q as usize].remove(h, slopes[i], vehicle.map_or([0.0; 2], |v| v[first as usize]));
            }
            covers.truncate(kept);
        }
    }
    let mut points = vec![PointLatent::default(); n];
    let mut pull = vec![[0.0; 2]; if pull_terms.is_some() { index.items.len() } else { 0 }];
    for (q, &a) in index.items.iter().enumerate() {
        let s = &acc[q];
        if s.count == 0 {
            continue;
        }
        let h = index.item_h[q];
        let c = s.count as f64;
        let (gx, gy) = (s.slope[0] / c, s.slope[1] / c);
        let mean = s.mean_with(h);
        stats.pixels_shared += 1;
        let var = ((h * h + s.sum2) / (c + 1.0) - mean * mean).max(0.0);
        stats.pixel_std_sum_m += var.sqrt();
        let usable = gx * gx + gy * gy <= MAX_SLOPE * MAX_SLOPE;
        if S::RECORDS {
            let w = t.models[t.model_of[a as usize] as usize].w;
            sink.add(&LatentSample {
                position: lifted(&t.position[a as usize], w, mean - h),
                normal: w,
                residual_m: h - mean,
                std_m: var.sqrt(),
                passes: s.count + 1,
                used: usable,
            });
        }
        if usable {
            // [x, y, share of the other passes in the latent mean].
            let others = match vehicle {
                Some(_) => [s.vehicle[0] / c, s.vehicle[1] / c, c / (c + 1.0)],
                None => [0.0; 3],
            };
            points[a as usize] = PointLatent { height: mean, others, covering: s.count };
            // The observation loop's residual `h − latent` and its test against the threshold.
            if let Some(ItemPull { threshold, weight }) = pull_terms {
                let e = h - mean;
                if e.abs() <= threshold {
                    let alpha = weight / (s.count as f64 + 1.0);
                    pull[q] = [alpha, alpha * e];
                }
            }
        }
    }
    stats.pixels = index.items.len() as u64;
    Latent { points, pull }
}

/// What [`point_latent`] finds (the raster route finds no pulls and no covering counts).
struct Latent {
    /// Per point, what the observation loop reads of the latent map.
    points: Vec<PointLatent>,
    /// Per item, the pulls on its covering triangles (empty without the consistent gradient).
    pull: Vec<[f64; 2]>,
}

/// What the observation loop reads of the latent map at one point, in one record: the routes
/// write them in item (pixel) order, scattered over the points, so one 40-byte record is
/// written where three columns took three scattered writes.
#[derive(Clone, Copy, Debug)]
struct PointLatent {
    /// The latent height (NaN: not observable).
    height: f64,
    /// `[x, y, share]` for the common-mode field (zeros without it).
    others: [f64; 3],
    /// The number of other passes' triangles the latent height averages.
    covering: u32,
}

impl Default for PointLatent {
    fn default() -> Self {
        Self { height: f64::NAN, others: [0.0; 3], covering: 0 }
    }
}

/// The observation loop's outlier threshold and weight, for the pulls of [`point_latent`]: a
/// point used with residual `e` and `c` covering triangles pulls on each with weight `ω/(c+1)`.
#[derive(Clone, Copy)]
struct ItemPull {
    threshold: f64,
    weight: f64,
}

/// What the used points' residuals pull on the triangles that cover them, gathered per corner
/// point the triangles hang off ([`Parameters::consistent_gradient`]). A point `j` with `c`
/// covering triangles and residual `e` has latent height `(own + Σ triangles)/(c+1)`, so moving a
/// triangle's pass by `δ` changes `e` by `−g·δ/(c+1)`. Each covering triangle's pass therefore
/// gets the observation "residual −e, weight ω/(c+1)" with the triangle's Jacobian, that of the
/// corner it hangs off (the other two corners are one point or one revolution away).
struct CornerPulls {
    /// Per point: Σ weight and Σ weight × residual, for the point's own model.
    sums: Vec<[f64; 2]>,
    /// The same where a triangle lies on another model than its corner's: (corner, model, sums),
    /// sorted.
    other_models: Vec<(usize, u32, [f64; 2])>,
    /// First entry of `other_models` not yet passed: points are added in increasing order.
    next_other: usize,
}

impl CornerPulls {
    /// The pull on point `a` (a triangle corner) through triangles on its own model, as
    /// (Σ weight, Σ weight × residual), if any; and the pulls through triangles on other models
    /// added to its interval's moments. `a` must increase from call to call.
    #[inline]
    fn take(
        &mut self,
        a: usize,
        models: &[SurfaceModel],
        measurement: &[[f64; 3]],
        moments: &mut IntervalMoments,
        lambda: f64,
    ) -> Option<[f64; 2]> {
        // A cursor, not a binary search per point: the calls come in point order.
        let others = &self.other_models;
        while self.next_other < others.len() && others[self.next_other].0 < a {
            self.next_other += 1;
        }
        while self.next_other < others.len() && others[self.next_other].0 == a {
            let (_, model, [w_sum, we_sum]) = others[self.next_other];
            if w_sum > 0.0 {
                moments.add(&jacobian(models[model as usize].w, measurement[a]), -we_sum / w_sum, w_sum, lambda);
            }
            self.next_other += 1;
        }
        let sums = self.sums[a];
        (sums[0] > 0.0).then_some(sums)
    }
}

/// The Jacobian row of a point's distance along the normal `w` with respect to its pass's
/// correction (translation, then rotation about the scan head at measurement vector `r`).
#[inline]
fn jacobian(w: [f64; 3], r: [f64; 3]) -> [f64; 6] {
    let rw = cross(r, w);
    [w[0], w[1], w[2], rw[0], rw[1], rw[2]]
}

/// Gathers the pulls of [`point_latent`] (`pull`, per item: `ω/(c+1)` and `ω/(c+1)·e` of the
/// points the observation loop will use, else zeros) on the corners their covering triangles
/// hang off.
fn corner_pulls(t: &Triangles, covers: &[[u32; 3]], pull: &[[f64; 2]]) -> CornerPulls {
    let mut sums = vec![[0.0; 2]; t.position.len()];
    let mut other: FxHashMap<(usize, u32), [f64; 2]> = FxHashMap::default();
    for &[q, corner, model] in covers {
        let (pull, corner) = (pull[q as usize], corner as usize);
        let s = if model == t.model_of[corner] { &mut sums[corner] } else { other.entry((corner, model)).or_default() };
        s[0] += pull[0];
        s[1] += pull[1];
    }
    let mut other_models: Vec<(usize, u32, [f64; 2])> = other.into_iter().map(|((a, m), s)| (a, m, s)).collect();
    other_models.sort_by_key(|o| (o.0, o.1));
    CornerPulls { sums, other_models, next_other: 0 }
}

/// Mean number of core points per bucket of [`point_latent`]'s grids.
const POINTS_PER_BUCKET: f64 = 2.0;

/// Points of one strip this many anchors apart or more (32 m along the trajectory) belong to
/// different passes over a place.
const SAME_PASS_ANCHORS: u32 = 64;

/// Bucket grid of one surface model's core points: bucket (i, j) covers
/// `u0 + [i, i+1)/inv × v0 + [j, j+1)/inv`.
struct Buckets {
    u0: f64,
    v0: f64,
    inv: f64,
    nu: u32,
    nv: u32,
    offset: usize,
}

/// Other passes' surface heights at one point.
#[derive(Clone, Copy, Default)]
struct Sample {
    sum: f64,
    sum2: f64,
    slope: [f64; 2],
    /// Sum of the contributing triangles' scan-head positions (common-mode field only).
    vehicle: [f64; 2],
    count: u32,
}

impl Sample {
    /// Adds one triangle's height, slope and scan head if `take`, else exact zeros: without a
    /// branch (see [`CoreIndex::for_each_cover`]; on small s1 a seventh of the candidates are
    /// taken).
    #[inline]
    fn add_masked(&mut self, take: bool, h: f64, hx: f64, hy: f64, vehicle: [f64; 2]) {
        let m = take as u32 as f64;
        let h = m * h;
        self.sum += h;
        self.vehicle[0] += m * vehicle[0];
        self.vehicle[1] += m * vehicle[1];
        self.sum2 += h * h;
        self.slope[0] += m * hx;
        self.slope[1] += m * hy;
        self.count += take as u32;
    }

    /// Takes out one triangle [`Self::add_masked`] added (its slope as stored, in f32).
    #[inline]
    fn remove(&mut self, h: f64, slope: [f32; 2], vehicle: [f64; 2]) {
        self.sum -= h;
        self.sum2 -= h * h;
        self.slope[0] -= slope[0] as f64;
        self.slope[1] -= slope[1] as f64;
        self.vehicle[0] -= vehicle[0];
        self.vehicle[1] -= vehicle[1];
        self.count -= 1;
    }

    /// The mean of the point's own height `own` and the other passes' heights.
    #[inline]
    fn mean_with(&self, own: f64) -> f64 {
        (own + self.sum) / (self.count as f64 + 1.0)
    }
}

#[cfg(test)]
mod tests;
