//! Step 1 of [`super::estimate_tile`]: every point corrected and sorted into a patch (the points
//! of one strip segment in one cell whose normals agree), and the patches of a cell joined into
//! local surface models.

use super::{cross, dominant_axis, dot, floor_i64, normalize, NONE};
use crate::calibration::TileCalibration;
use crate::chunk::TileChunk;
use precimap_core::calibration::{attitude_matrix, WorldMounting};
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::geom::SmallRotation;
use precimap_core::hash::FxHashMap;
use precimap_core::{IterationStep, Parameters, TileKey};

/// Surface models one cell can hold (distinct normal directions).
pub(super) const MAX_MODELS_PER_CELL: usize = 8;

#[derive(Clone, Copy, Default)]
pub(super) struct CellModels {
    pub(super) ids: [u32; MAX_MODELS_PER_CELL],
    pub(super) len: u8,
}

/// A local surface model while points are gathered, then its frame and raster.
#[derive(Clone, Debug)]
pub(super) struct SurfaceModel {
    pub(super) sum_normal: [f64; 3],
    pub(super) sum_position: [f64; 3],
    pub(super) count: u32,
    // Frame, valid after `finish_frame`.
    pub(super) w: [f64; 3],
    pub(super) e1: [f64; 3],
    pub(super) e2: [f64; 3],
    pub(super) o: [f64; 3],
}

impl SurfaceModel {
    pub(super) fn new() -> Self {
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

    pub(super) fn finish_frame(&mut self) {
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
    pub(super) fn project(&self, p: &[f64; 3]) -> (f64, f64, f64) {
        let d = [p[0] - self.o[0], p[1] - self.o[1], p[2] - self.o[2]];
        (dot(d, self.e1), dot(d, self.e2), dot(d, self.w))
    }

    /// Height of `p` above the model plane (the third coordinate of [`Self::project`]).
    #[inline]
    pub(super) fn height(&self, p: &[f64; 3]) -> f64 {
        dot([p[0] - self.o[0], p[1] - self.o[1], p[2] - self.o[2]], self.w)
    }
}

/// Key of the cell holding `p`; with `unbounded` the cell is a column unbounded along that axis
/// (index 0 there, which no tile-local position reaches, so columns along different axes never
/// share a key).
#[inline]
pub(super) fn cell_key(p: &[f64; 3], inv_cell: f64, unbounded: Option<usize>) -> u64 {
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

/// Largest distance of a point from the plane of a patch (one strip segment in one normal
/// column) it joins: farther, it is a parallel surface of the same segment along the column.
pub(super) const PATCH_PLANE_M: f64 = 0.05;
/// Smallest distance between planes at which patches of different strips join one model.
pub(super) const JOIN_DISTANCE_MIN_M: f64 = 0.1;
/// Largest distance between planes at which two segments of one strip pass join one model.
pub(super) const SAME_PASS_JOIN_M: f64 = 0.03;
/// Anchors (0.5 m each) along a strip within which two of its segments count as one pass.
pub(super) const PASS_ANCHORS: u32 = 64;

/// Identifies one pass of one strip over a place: passes of the same strip more than
/// 64 anchors (32 m) apart along the trajectory count as different views.
#[inline]
pub(super) fn pass_tag(strip: u32, anchor: u32) -> u32 {
    const _: () = assert!(PASS_ANCHORS == 64);
    (strip << 16) | ((anchor >> 6) & 0xFFFF)
}

/// The points of one strip segment in one cell whose normals agree.
#[derive(Clone, Debug)]
pub(super) struct Patch {
    pub(super) cell: u64,
    pub(super) strip: u32,
    /// Anchor of the first point (tells passes of one strip apart, see [`pass_tag`]).
    pub(super) anchor: u32,
    pub(super) sum_normal: [f64; 3],
    pub(super) sum_position: [f64; 3],
    pub(super) count: u32,
}

impl Patch {
    /// Whether `p` lies within [`PATCH_PLANE_M`] of the patch's plane (`norm2`: the squared length
    /// of its normal sum): `|(p − Σp/n)·Σw| / |Σw|`, multiplied out by `n·|Σw|` and squared.
    #[inline]
    pub(super) fn within_plane(&self, p: &[f64; 3], norm2: f64) -> bool {
        let c = self.count as f64;
        let s = &self.sum_position;
        let d = dot([c * p[0] - s[0], c * p[1] - s[1], c * p[2] - s[2]], self.sum_normal);
        d * d <= PATCH_PLANE_M * PATCH_PLANE_M * c * c * norm2
    }
}

/// `|(p − c) · axis|` for the centroid `c` of `count` points whose positions sum to
/// `sum_position`: with a unit `axis`, the distance of `p` from the plane through the centroid.
#[inline]
pub(super) fn offset_along(axis: [f64; 3], sum_position: &[f64; 3], count: f64, p: &[f64; 3]) -> f64 {
    let c = [sum_position[0] / count, sum_position[1] / count, sum_position[2] / count];
    dot([p[0] - c[0], p[1] - c[1], p[2] - c[2]], axis).abs()
}

/// A model of the cell being joined: (id, normal sum, position sum, count, member passes as
/// (strip, anchor)).
pub(super) type OpenModel = (u32, [f64; 3], [f64; 3], f64, Vec<(u32, u32)>);

/// Model id of every patch (dense ids, [`NONE`] where a cell ran out of model slots). Per cell,
/// larger patches go first (ties by index, so the result does not depend on hash order); a patch
/// joins the agreeing model with the nearest plane, or opens a new one.
pub(super) fn join_patches(patches: &[Patch], cos_group: f64, join_distance: f64) -> Vec<u32> {
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

/// Every point of a tile corrected with its trajectory's corrections, and the patch it joined.
pub(super) struct CorrectedPoints {
    /// Tile-local positions.
    pub(super) position: Vec<[f64; 3]>,
    /// Measurement vectors (scan head to point), rotated by the correction.
    pub(super) measurement: Vec<[f64; 3]>,
    /// Absolute horizontal scan-head positions, where the common-mode field acts (empty in
    /// steps that do not solve the field).
    pub(super) vehicle: Vec<[f64; 2]>,
    /// Patch of every point ([`NONE`] where its cell ran out of slots).
    pub(super) patch_of: Vec<u32>,
    /// Per chunk the body attitude at each anchor of its range, where the campaign estimates the
    /// calibration (else empty).
    pub(super) anchor_attitude: Vec<Vec<[[f64; 3]; 3]>>,
    pub(super) patches: Vec<Patch>,
}

/// Corrects every point and sorts it into a patch: the points of one strip segment in one cell
/// whose normals agree (a segment can wrap round a pole or a corner within a cell).
pub(super) fn correct_points(
    tile: TileKey,
    chunks: &[TileChunk],
    corrections: &[TrajectoryCorrections],
    params: &Parameters,
    step: &IterationStep,
    cos_group: f64,
    calibration: Option<&TileCalibration>,
) -> CorrectedPoints {
    let (ox, oy) = tile.origin(params.tile_size_m);
    let inv_cell = 1.0 / step.cell_size(params);
    let total: usize = chunks.iter().map(TileChunk::len).sum();
    let mut position = Vec::with_capacity(total);
    let mut measurement = Vec::with_capacity(total);
    let solves_field = step.solves_field(params);
    let mut vehicle: Vec<[f64; 2]> = Vec::with_capacity(if solves_field { total } else { 0 });
    let mut patch_of = Vec::with_capacity(total);
    let mut anchor_attitude = Vec::with_capacity(if calibration.is_some() { chunks.len() } else { 0 });
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
        // The scanner's current calibration, where the campaign estimates it (checked by
        // `check_chunks`: every chunk then carries the attitudes at its anchors), in the world
        // frame at every anchor; a point takes the interpolation of its two anchors' values.
        let attitudes: Vec<[[f64; 3]; 3]> = match calibration {
            Some(_) => chunk.attitude.iter().map(|&a| attitude_matrix(a)).collect(),
            None => Vec::new(),
        };
        let mounting = calibration.and_then(|c| c.of_strip(chunk.strip)).map(|(_, s)| *s).filter(|s| !s.is_zero());
        let world: Vec<WorldMounting> = match mounting {
            Some(m) => attitudes.iter().map(|a| m.in_world(a)).collect(),
            None => Vec::new(),
        };
        let first = chunk.anchor_range().map_or(0, |(first, _)| first);
        for k in 0..chunk.len() {
            let c = corr.at(chunk.anchor[k], chunk.lambda[k]);
            let rotation = SmallRotation::new([c[3], c[4], c[5]]);
            let mut t0 = chunk.t0[k].map(f64::from);
            let mut r = chunk.r[k].map(f64::from);
            let mut normal = chunk.normal[k].map(f64::from);
            if !world.is_empty() {
                let o = (chunk.anchor[k] - first) as usize;
                let mounting = world[o].lerp(&world[o + 1], chunk.lambda[k] as f64);
                let (head, beam) = mounting.apply(r);
                t0 = [t0[0] + head[0], t0[1] + head[1], t0[2] + head[2]];
                r = beam;
                normal = mounting.turn(normal);
            }
            let rr = rotation.apply(r);
            let p = [t0[0] + shift[0] + c[0] + rr[0], t0[1] + shift[1] + c[1] + rr[1], t0[2] + shift[2] + c[2] + rr[2]];
            let n = rotation.apply(normal);
            if solves_field {
                vehicle.push([chunk.origin[0] + t0[0], chunk.origin[1] + t0[1]]);
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
            let seed = Patch {
                cell: key.0,
                strip: chunk.strip,
                anchor: chunk.anchor[k],
                sum_normal: [0.0; 3],
                sum_position: [0.0; 3],
                count: 0,
            };
            patch_of.push(sort_point(&mut patches, &mut last.1, seed, n, p, cos_group, plane_patches));
        }
        if calibration.is_some() {
            anchor_attitude.push(attitudes);
        }
    }
    CorrectedPoints { position, measurement, vehicle, patch_of, patches, anchor_attitude }
}

/// Adds the point at `p` with normal `n` to the patch of its cell's `slots` whose normal agrees
/// best (within `cos_group`; with `plane_patches` also only one whose plane it lies within), or
/// to a new patch `seed` while the cell has room; returns that patch ([`NONE`]: no room).
#[inline]
fn sort_point(
    patches: &mut Vec<Patch>,
    slots: &mut CellModels,
    seed: Patch,
    n: [f64; 3],
    p: [f64; 3],
    cos_group: f64,
    plane_patches: bool,
) -> u32 {
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
        patches.push(seed);
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
    best
}

/// Joins the patches of a cell into surface models: a patch joins the model whose normal agrees
/// and whose plane is nearest (within the join distance), unless that model already holds
/// another segment of the same strip pass (road and sidewalk, both sides of a curb). Returns
/// the models, their frames finished, and the model of every point ([`NONE`]: none).
pub(super) fn join_into_models(
    patches: &[Patch],
    patch_of: &[u32],
    params: &Parameters,
    step: &IterationStep,
    cos_group: f64,
) -> (Vec<SurfaceModel>, Vec<u32>) {
    // Not below 10 cm: strips that still disagree by a few centimetres must meet in one model, and
    // membership flipping between iterations as the strips move would make the corrections jump.
    let join_distance = step.threshold_m.max(JOIN_DISTANCE_MIN_M);
    let model_of_patch = if params.segment_surfaces {
        join_patches(patches, cos_group, join_distance)
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
    for m in &mut models {
        m.finish_frame();
    }
    (models, model_of)
}
