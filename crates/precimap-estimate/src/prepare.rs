//! Per-strip preparation (the `segment_strip` map task): point geometry against the
//! trajectory, the scan image (rows = measurement within a scanner revolution, columns =
//! revolutions, per channel; [`precimap_segment::ScanImage`]), RANSAC normals and the
//! Felzenszwalb–Huttenlocher segmentation ([`precimap_segment::segment_strip`]), and the
//! segmented points keyed into tiles with a border overlap.

use crate::chunk::{TileChunk, NO_NEIGHBOUR};
use precimap_core::geom::rotate_small;
use precimap_core::{Parameters, TileKey, Trajectory, Vec3};
pub use precimap_segment::{PixelNormal, ScanImage, SegmentParams, SegmentStats, DROPPED_SEGMENT, NO_SEGMENT};
use precimap_segment::{StripGeometry, NO_POINT};
use std::collections::HashMap;

/// A strip's points in acquisition order (struct of arrays, as read from LAS).
#[derive(Clone, Copy, Debug)]
pub struct StripSamples<'a> {
    pub x: &'a [f64],
    pub y: &'a [f64],
    pub z: &'a [f64],
    pub gps_time: &'a [f64],
    pub scan_angle_deg: &'a [f32],
    /// Scanner channel (revolutions are found per channel).
    pub channel: &'a [u8],
}

impl StripSamples<'_> {
    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PrepareError {
    #[error("point {index}: GPS time {time:.6} s lies outside the trajectory's span {start:.6}–{end:.6} s; supply a trajectory that covers the whole strip")]
    NotCovered { index: usize, time: f64, start: f64, end: f64 },
    #[error("point {index}: {field} is not a finite number")]
    NotFinite { index: usize, field: &'static str },
    #[error("point {index}: GPS time {time:.6} s is earlier than the previous point's {previous:.6} s; strips must be in acquisition order")]
    NotInOrder { index: usize, time: f64, previous: f64 },
    #[error("the strip has no points")]
    Empty,
    #[error("columns differ in length ({0})")]
    Shape(String),
}

/// Geometry of one measurement relative to its trajectory.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeasurementGeometry {
    /// Scan-head position `t0 = c + R·ℓ` (absolute).
    pub t0: [f64; 3],
    /// Measurement vector `r = p − t0`.
    pub r: [f64; 3],
    /// Anchor index `⌊s/Δ⌋` and fraction.
    pub anchor: u32,
    pub lambda: f32,
    /// Vehicle speed at the measurement, m/s.
    pub speed: f64,
}

/// Geometry of the point `p` measured at time `t` by a scanner with lever arm `lever_arm`.
/// `None` when the trajectory does not cover `t`. For many points of one strip, a
/// [`GeometryCursor`] gives the same values faster.
pub fn measurement_geometry(
    trajectory: &Trajectory,
    lever_arm: &Vec3,
    anchor_spacing_m: f64,
    t: f64,
    p: [f64; 3],
) -> Option<MeasurementGeometry> {
    GeometryCursor::new(trajectory, lever_arm, anchor_spacing_m).at(t, p)
}

/// [`measurement_geometry`] for the points of one strip in turn: it keeps the trajectory segment
/// of the previous point, so points in time order find theirs in O(1) (a step forward, a binary
/// search only after a jump), and it rotates the lever arm alone (`R_i·Exp(λ·ω_i)·ℓ`, with the
/// rotation's series exact to double precision for the small angle of one segment) instead of
/// forming the interpolated rotation matrix.
#[derive(Clone, Debug)]
pub struct GeometryCursor<'a> {
    trajectory: &'a Trajectory,
    lever_arm: [f64; 3],
    anchor_spacing_m: f64,
    /// The segment of the last point and what every point in it shares; `usize::MAX` before
    /// the first point.
    index: usize,
    segment: SegmentData,
}

#[derive(Clone, Copy, Debug, Default)]
struct SegmentData {
    t0: f64,
    t1: f64,
    p0: [f64; 3],
    p1: [f64; 3],
    rotation: [[f64; 3]; 3],
    omega: [f64; 3],
    arc0: f64,
    arc1: f64,
    speed: f64,
}

impl<'a> GeometryCursor<'a> {
    pub fn new(trajectory: &'a Trajectory, lever_arm: &Vec3, anchor_spacing_m: f64) -> Self {
        Self {
            trajectory,
            lever_arm: [lever_arm.x, lever_arm.y, lever_arm.z],
            anchor_spacing_m,
            index: usize::MAX,
            segment: SegmentData::default(),
        }
    }

    /// The segment holding `t`: the last sample at or before `t`, at most the last but one
    /// (exactly [`Trajectory::locate`]'s choice). `None` outside the trajectory's span.
    #[inline]
    fn locate(&mut self, t: f64) -> Option<()> {
        let times = self.trajectory.times();
        let last = times.len() - 2;
        let s = &self.segment;
        if self.index != usize::MAX && t >= s.t0 && (t < s.t1 || (self.index == last && t <= s.t1)) {
            return Some(());
        }
        if !self.trajectory.covers(t) {
            return None;
        }
        let mut i = self.index;
        if i != usize::MAX && t >= s.t0 && i + 4 <= last && t < times[i + 4] {
            // A few segments ahead (time order): step.
            while times[i + 1] <= t {
                i += 1;
            }
        } else {
            i = match times.binary_search_by(|x| x.total_cmp(&t)) {
                Ok(i) => i.min(last),
                Err(i) => i - 1,
            };
        }
        self.load(i);
        Some(())
    }

    fn load(&mut self, i: usize) {
        let tr = self.trajectory;
        let (times, positions, arcs) = (tr.times(), tr.positions(), tr.arc_lengths());
        let r = &tr.rotations()[i];
        let w = tr.segment_rotations()[i];
        let p = |v: &Vec3| [v.x, v.y, v.z];
        self.index = i;
        self.segment = SegmentData {
            t0: times[i],
            t1: times[i + 1],
            p0: p(&positions[i]),
            p1: p(&positions[i + 1]),
            rotation: [
                [r[(0, 0)], r[(0, 1)], r[(0, 2)]],
                [r[(1, 0)], r[(1, 1)], r[(1, 2)]],
                [r[(2, 0)], r[(2, 1)], r[(2, 2)]],
            ],
            omega: [w.x, w.y, w.z],
            arc0: arcs[i],
            arc1: arcs[i + 1],
            speed: (arcs[i + 1] - arcs[i]) / (times[i + 1] - times[i]),
        };
    }

    /// The geometry of point `p` measured at `t`; `None` outside the trajectory's span.
    #[inline]
    pub fn at(&mut self, t: f64, p: [f64; 3]) -> Option<MeasurementGeometry> {
        self.locate(t)?;
        let s = &self.segment;
        let lambda = ((t - s.t0) / (s.t1 - s.t0)).clamp(0.0, 1.0);
        let arm = rotate_small(s.omega.map(|w| w * lambda), self.lever_arm);
        let r = &s.rotation;
        let mut t0 = [0.0; 3];
        for k in 0..3 {
            let c = s.p0[k] + (s.p1[k] - s.p0[k]) * lambda;
            t0[k] = c + (r[k][0] * arm[0] + r[k][1] * arm[1] + r[k][2] * arm[2]);
        }
        let arc = s.arc0 + (s.arc1 - s.arc0) * lambda;
        let u = (arc / self.anchor_spacing_m).max(0.0);
        let anchor = precimap_core::geom::floor(u);
        Some(MeasurementGeometry {
            t0,
            r: [p[0] - t0[0], p[1] - t0[1], p[2] - t0[2]],
            anchor: anchor as u32,
            lambda: (u - anchor) as f32,
            speed: s.speed,
        })
    }
}

/// Everything a strip contributes to estimation, and its segmentation.
#[derive(Debug)]
pub struct PreparedStrip {
    pub chunks: Vec<TileChunk>,
    pub stats: PrepareStats,
    /// Per point (file order): segment id, [`NO_SEGMENT`] (no normal, small region) or
    /// [`DROPPED_SEGMENT`] (revolution dropped at standstill).
    pub segment: Vec<u32>,
    /// The scan image (row and column of every point).
    pub image: ScanImage,
    /// Per point (file order): its normal, facing the scanner, if the fit succeeded (what the
    /// chunks carry; kept for evaluation against truth).
    pub normals: Vec<Option<PixelNormal>>,
}

#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PrepareStats {
    pub points: u64,
    /// Points with a usable normal (they go to the tiles).
    pub points_with_normal: u64,
    /// Emitted point copies, including border duplicates.
    pub points_emitted: u64,
    pub revolutions: u64,
    pub rows_per_revolution: u32,
    pub revolution_period_s: f64,
    pub first_anchor: u32,
    pub last_anchor: u32,
    pub time_start: f64,
    pub time_end: f64,
    /// The strip had no scan angles (all equal); rows came from the beam directions instead
    /// ([`reconstructed_scan_angles`]).
    #[serde(default)]
    pub scan_angles_reconstructed: bool,
    pub segmentation: SegmentStats,
}

/// Identity of a strip inside a campaign.
#[derive(Clone, Copy, Debug)]
pub struct StripContext<'a> {
    pub strip: u32,
    pub trajectory: u32,
    pub trajectory_data: &'a Trajectory,
    pub lever_arm: Vec3,
    pub params: &'a Parameters,
    pub segment: &'a SegmentParams,
}

/// The phases of preparing a strip, in order, for callers that measure where the time goes
/// ([`prepare_strip_observed`]). `Decode` (reading the LAS/LAZ file) is reported by the caller
/// that reads the strip, `Encode` by the one that encodes the chunks; the others by
/// [`prepare_strip_observed`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PreparePhase {
    /// Reading and decoding the strip file.
    Decode,
    /// Checks and the geometry against the trajectory (scan-head position, anchor, λ).
    Geometry,
    /// The scan image: rows, columns, standstill thinning, the pixel grid.
    ScanImage,
    /// RANSAC normals.
    Normals,
    /// C0/C1 edge weights, Felzenszwalb–Huttenlocher, small regions.
    Segmentation,
    /// Image links and tile membership (the chunks in memory).
    Tiling,
    /// Chunk encoding to bytes.
    Encode,
}

impl PreparePhase {
    pub const ALL: [PreparePhase; 7] = [
        PreparePhase::Decode,
        PreparePhase::Geometry,
        PreparePhase::ScanImage,
        PreparePhase::Normals,
        PreparePhase::Segmentation,
        PreparePhase::Tiling,
        PreparePhase::Encode,
    ];

    pub fn name(self) -> &'static str {
        match self {
            PreparePhase::Decode => "decode",
            PreparePhase::Geometry => "geometry",
            PreparePhase::ScanImage => "scan_image",
            PreparePhase::Normals => "normals",
            PreparePhase::Segmentation => "segmentation",
            PreparePhase::Tiling => "tiling",
            PreparePhase::Encode => "encode",
        }
    }
}

pub fn prepare_strip(samples: &StripSamples<'_>, ctx: &StripContext<'_>) -> Result<PreparedStrip, PrepareError> {
    prepare_strip_observed(samples, ctx, &mut |_| {})
}

/// [`prepare_strip`] calling `phase_done` at the end of each of its phases (in order: geometry,
/// scan image, normals, segmentation, tiling); the result is the same.
pub fn prepare_strip_observed(
    samples: &StripSamples<'_>,
    ctx: &StripContext<'_>,
    phase_done: &mut dyn FnMut(PreparePhase),
) -> Result<PreparedStrip, PrepareError> {
    let n = samples.len();
    if [samples.y.len(), samples.z.len(), samples.gps_time.len(), samples.scan_angle_deg.len(), samples.channel.len()]
        .iter()
        .any(|&l| l != n)
    {
        return Err(PrepareError::Shape(format!("{n} points")));
    }
    if n == 0 {
        return Err(PrepareError::Empty);
    }
    let geometry = strip_geometry(samples, ctx)?;
    let head = &geometry.head;
    phase_done(PreparePhase::Geometry);
    let reconstructed = if scan_angles_missing(samples.scan_angle_deg) {
        reconstructed_scan_angles(head, samples, ctx.trajectory_data)
    } else {
        None
    };
    let scan_angles_reconstructed = reconstructed.is_some();
    let angles = reconstructed.as_deref().unwrap_or(samples.scan_angle_deg);
    let mut image = ScanImage::build(angles, samples.gps_time, samples.channel);
    drop(reconstructed);
    image.thin_standstill(head, ctx.params.min_revolution_advance_m);
    let grid = image.grid();
    phase_done(PreparePhase::ScanImage);
    let geo = StripGeometry { x: samples.x, y: samples.y, z: samples.z, head };
    let normals = precimap_segment::estimate_normals(&geo, &image, &grid, ctx.segment);
    phase_done(PreparePhase::Normals);
    let segmentation = precimap_segment::segment_with_normals(&geo, &image, &grid, normals, ctx.segment);
    phase_done(PreparePhase::Segmentation);
    let links = Links { image: &image, grid: &grid };
    let chunks = emit_tiles(samples, ctx, &geometry, &links, &segmentation.normals, &segmentation.segment);
    drop(grid);
    phase_done(PreparePhase::Tiling);
    let emitted = chunks.iter().map(|c| c.len() as u64).sum();
    let first_anchor = geometry.anchor.iter().copied().min().unwrap_or(0);
    let last_anchor = geometry.anchor.iter().copied().max().unwrap_or(0) + 1;
    Ok(PreparedStrip {
        chunks,
        stats: PrepareStats {
            points: n as u64,
            points_with_normal: segmentation.stats.points_with_normal,
            points_emitted: emitted,
            revolutions: image.columns as u64,
            rows_per_revolution: image.rows,
            revolution_period_s: image.period_s,
            first_anchor,
            last_anchor,
            time_start: samples.gps_time[0],
            time_end: samples.gps_time[n - 1],
            scan_angles_reconstructed,
            segmentation: segmentation.stats,
        },
        segment: segmentation.segment,
        image,
        normals: segmentation.normals,
    })
}

/// What preparation keeps of each point's [`MeasurementGeometry`], struct of arrays: the
/// scan-head positions are the segmentation's input as they are, and `r = p − t0` is recomputed
/// where needed (the same subtraction) rather than stored (a third of the bytes per point).
struct HeadGeometry {
    head: Vec<[f64; 3]>,
    anchor: Vec<u32>,
    lambda: Vec<f32>,
}

impl HeadGeometry {
    /// The measurement vector `p − t0` of point `k`, as [`GeometryCursor::at`] computes it.
    #[inline]
    fn r(&self, samples: &StripSamples<'_>, k: usize) -> [f64; 3] {
        let t0 = self.head[k];
        [samples.x[k] - t0[0], samples.y[k] - t0[1], samples.z[k] - t0[2]]
    }
}

fn strip_geometry(samples: &StripSamples<'_>, ctx: &StripContext<'_>) -> Result<HeadGeometry, PrepareError> {
    let (start, end) = ctx.trajectory_data.time_span();
    let n = samples.len();
    let mut out =
        HeadGeometry { head: Vec::with_capacity(n), anchor: Vec::with_capacity(n), lambda: Vec::with_capacity(n) };
    let mut previous = f64::NEG_INFINITY;
    let mut cursor = GeometryCursor::new(ctx.trajectory_data, &ctx.lever_arm, ctx.params.anchor_spacing_m);
    for k in 0..samples.len() {
        let t = samples.gps_time[k];
        let p = [samples.x[k], samples.y[k], samples.z[k]];
        for (v, field) in [(t, "GPS time"), (p[0], "x"), (p[1], "y"), (p[2], "z")] {
            if !v.is_finite() {
                return Err(PrepareError::NotFinite { index: k, field });
            }
        }
        if !samples.scan_angle_deg[k].is_finite() {
            return Err(PrepareError::NotFinite { index: k, field: "scan angle" });
        }
        if t < previous {
            return Err(PrepareError::NotInOrder { index: k, time: t, previous });
        }
        previous = t;
        let g = cursor.at(t, p).ok_or(PrepareError::NotCovered { index: k, time: t, start, end })?;
        out.head.push(g.t0);
        out.anchor.push(g.anchor);
        out.lambda.push(g.lambda);
    }
    Ok(out)
}

/// A strip carries no scan angles when every point has the same value (LAS writers that do not
/// know the angle leave the field 0).
fn scan_angles_missing(angles: &[f32]) -> bool {
    angles.first().is_some_and(|&a| angles.iter().all(|&b| b == a))
}

/// Scan angles reconstructed from the geometry, for strips without the field. A rotating
/// scanner's beams lie in one plane fixed to the vehicle: in the body frame, every beam
/// direction of a channel is perpendicular to the rotation axis, which is therefore the
/// direction in which the beam directions spread least (the smallest eigenvector of
/// `Σ u uᵀ`). A beam's angle is its azimuth about that axis, signed so that it grows with time
/// within a revolution as the LAS field does. The zero of the angle differs from the scanner's;
/// the scan image only needs measurement order and revolution boundaries. `None` when a channel's
/// beams do not lie in a plane (not a rotating line scanner: the smallest spread is over 5 % of
/// the largest), so the strip keeps no scan-image neighbourhood.
pub fn reconstructed_scan_angles(
    head: &[[f64; 3]],
    samples: &StripSamples<'_>,
    trajectory: &Trajectory,
) -> Option<Vec<f32>> {
    let n = head.len();
    // Unit beam directions in the body frame.
    let mut body = Vec::with_capacity(n);
    for (k, t0) in head.iter().enumerate() {
        let pose = trajectory.pose_at(samples.gps_time[k])?;
        let r = [samples.x[k] - t0[0], samples.y[k] - t0[1], samples.z[k] - t0[2]];
        let u = pose.rotation.transpose() * Vec3::from(r);
        let norm = u.norm();
        body.push(if norm > 0.0 { u / norm } else { Vec3::zeros() });
    }
    let mut scatter = [nalgebra::Matrix3::<f64>::zeros(); 256];
    for (u, &c) in body.iter().zip(samples.channel) {
        scatter[c as usize] += u * u.transpose();
    }
    // Per channel, the plane's basis (e1, e2); e1 × e2 is the rotation axis.
    let mut basis: [Option<(Vec3, Vec3)>; 256] = [None; 256];
    for (c, m) in scatter.iter().enumerate() {
        if m.trace() == 0.0 {
            continue;
        }
        let eig = nalgebra::SymmetricEigen::new(*m);
        let order = {
            let mut o = [0usize, 1, 2];
            o.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
            o
        };
        if eig.eigenvalues[order[0]] > 0.05 * eig.eigenvalues[order[2]] {
            return None;
        }
        let axis: Vec3 = eig.eigenvectors.column(order[0]).into_owned();
        let e1: Vec3 = eig.eigenvectors.column(order[2]).into_owned();
        basis[c] = Some((e1, axis.cross(&e1)));
    }
    let mut azimuth: Vec<f64> = body
        .iter()
        .zip(samples.channel)
        .map(|(u, &c)| {
            let (e1, e2) = basis[c as usize].expect("every channel with points has a basis");
            u.dot(&e2).atan2(u.dot(&e1)).to_degrees()
        })
        .collect();
    drop(body);
    // Orientation per channel: consecutive beams mostly step forward.
    let mut votes = [0i64; 256];
    let mut last: [Option<f64>; 256] = [None; 256];
    for (&a, &c) in azimuth.iter().zip(samples.channel) {
        if let Some(prev) = last[c as usize] {
            let step = (a - prev + 540.0).rem_euclid(360.0) - 180.0;
            votes[c as usize] += if step > 0.0 {
                1
            } else if step < 0.0 {
                -1
            } else {
                0
            };
        }
        last[c as usize] = Some(a);
    }
    for (a, &c) in azimuth.iter_mut().zip(samples.channel) {
        if votes[c as usize] < 0 {
            *a = -*a;
        }
    }
    // A revolution must not be split where beams are dense: put the wrap-around (±180°) in the
    // middle of the widest gap in azimuth (the sky, for a head that sees the ground).
    const BINS: usize = 720;
    let mut occupied = vec![[false; BINS]; 256];
    for (&a, &c) in azimuth.iter().zip(samples.channel) {
        let bin = ((a + 180.0) / 360.0 * BINS as f64) as usize;
        occupied[c as usize][bin.min(BINS - 1)] = true;
    }
    let mut gap_centre = [180.0f64; 256];
    for (c, bins) in occupied.iter().enumerate() {
        let Some(start) = bins.iter().position(|&b| b) else { continue };
        // Walk once round the circle from an occupied bin, measuring runs of empty bins.
        let (mut best, mut best_mid, mut run) = (0usize, None, 0usize);
        for i in 1..=BINS {
            if bins[(start + i) % BINS] {
                if run > best {
                    best = run;
                    best_mid = Some(start as f64 + i as f64 - run as f64 / 2.0);
                }
                run = 0;
            } else {
                run += 1;
            }
        }
        if let Some(mid) = best_mid {
            gap_centre[c] = mid * 360.0 / BINS as f64 - 180.0;
        }
    }
    Some(
        azimuth
            .iter()
            .zip(samples.channel)
            .map(|(&a, &c)| {
                let a = (a - gap_centre[c as usize]).rem_euclid(360.0) - 180.0;
                // −180 and 180 are the same beam.
                (if a >= 180.0 { a - 360.0 } else { a }) as f32
            })
            .collect(),
    )
}

/// Scan-image neighbour links: next row in the same revolution (wrapping round), same row in the
/// next revolution. Looked up in the pixel grid for the emitted points only, rather than stored
/// for every point.
struct Links<'a> {
    image: &'a ScanImage,
    grid: &'a [u32],
}

// Links are read straight from the grid: its empty pixels must read as "no neighbour".
const _: () = assert!(NO_POINT == NO_NEIGHBOUR);

impl Links<'_> {
    /// `(right, down)` of point `k` (in the image: not dropped), or [`NO_NEIGHBOUR`].
    #[inline]
    fn of(&self, k: usize) -> (u32, u32) {
        let rows = self.image.rows as usize;
        let row = self.image.row[k] as usize;
        let px = self.image.column[k] as usize * rows + row;
        // Rows wrap around: the revolution is a circle.
        let next = if row + 1 < rows { px + 1 } else { px + 1 - rows };
        let right = if rows > 2 { self.grid[next] } else { NO_NEIGHBOUR };
        let down = self.grid.get(px + rows).copied().unwrap_or(NO_NEIGHBOUR);
        (right, down)
    }
}

fn emit_tiles(
    samples: &StripSamples<'_>,
    ctx: &StripContext<'_>,
    geometry: &HeadGeometry,
    links: &Links<'_>,
    normals: &[Option<PixelNormal>],
    segment: &[u32],
) -> Vec<TileChunk> {
    let params = ctx.params;
    // Points per tile, in acquisition order. Consecutive points mostly fall in the tiles of the
    // previous point: a small cache of recent tiles saves the map look-up.
    let mut tiles: Vec<(TileKey, Vec<u32>)> = Vec::new();
    let mut index: HashMap<TileKey, usize> = HashMap::new();
    let mut recent: [(TileKey, usize); 4] = [(TileKey { tx: i32::MIN, ty: i32::MIN }, 0); 4];
    let max_range2 = params.max_range_m * params.max_range_m;
    for k in 0..samples.len() {
        let r = geometry.r(samples, k);
        if segment[k] >= DROPPED_SEGMENT || normals[k].is_none() || r[0] * r[0] + r[1] * r[1] + r[2] * r[2] > max_range2
        {
            continue;
        }
        for key in TileKey::with_overlap(samples.x[k], samples.y[k], params.tile_size_m, params.tile_overlap_m) {
            let slot = match recent.iter().find(|(r, _)| *r == key) {
                Some(&(_, slot)) => slot,
                None => {
                    let slot = *index.entry(key).or_insert_with(|| {
                        tiles.push((key, Vec::new()));
                        tiles.len() - 1
                    });
                    recent.rotate_right(1);
                    recent[0] = (key, slot);
                    slot
                }
            };
            tiles[slot].1.push(k as u32);
        }
    }
    tiles.sort_unstable_by_key(|(key, _)| *key);
    // Global point index → index inside the tile being emitted (reset after each tile).
    let mut local = vec![NO_NEIGHBOUR; samples.len()];
    tiles
        .into_iter()
        .map(|(key, globals)| {
            let (ox, oy) = key.origin(params.tile_size_m);
            let origin = [ox, oy, 0.0];
            let mut chunk = TileChunk::with_capacity(key, ctx.strip, ctx.trajectory, origin, globals.len());
            for (i, &g) in globals.iter().enumerate() {
                local[g as usize] = i as u32;
            }
            let local_of = |g: u32| if g == NO_NEIGHBOUR { NO_NEIGHBOUR } else { local[g as usize] };
            for &g in &globals {
                let k = g as usize;
                let Some(nrm) = normals[k] else { continue };
                let (t0, r) = (geometry.head[k], geometry.r(samples, k));
                let (right, down) = links.of(k);
                chunk.push(
                    [(t0[0] - ox) as f32, (t0[1] - oy) as f32, t0[2] as f32],
                    [r[0] as f32, r[1] as f32, r[2] as f32],
                    nrm.normal,
                    geometry.anchor[k],
                    geometry.lambda[k],
                    local_of(right),
                    local_of(down),
                    nrm.edge_limit,
                    segment[k],
                    g,
                );
            }
            for &g in &globals {
                local[g as usize] = NO_NEIGHBOUR;
            }
            chunk
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A straight drive over flat ground scanned by one rotating head: the scan image must have
    /// the simulated rows and columns, and normals must point up.
    #[test]
    fn scan_image_links_and_normals_on_flat_ground() {
        let speed = 10.0;
        let times: Vec<f64> = (0..=400).map(|i| 1000.0 + i as f64 * 0.005).collect();
        let positions = times.iter().map(|t| Vec3::new((t - 1000.0) * speed, 0.0, 2.0)).collect();
        let traj = Trajectory::new(times, positions, vec![[0.0; 3]; 401]).unwrap();
        let rows = 360u32;
        let rate = 50.0;
        let (mut x, mut y, mut z, mut t, mut a) = (vec![], vec![], vec![], vec![], vec![]);
        for rev in 0..60 {
            for j in 0..rows {
                let phi = -180.0 + j as f64 * 360.0 / rows as f64;
                let time = 1000.1 + rev as f64 / rate + j as f64 / (rate * rows as f64);
                let c = (time - 1000.0) * speed;
                // Beam in the y–z plane; only downward beams hit the ground (z = 0).
                let dir = Vec3::new(0.0, phi.to_radians().sin(), phi.to_radians().cos());
                if dir.z > -0.3 {
                    continue;
                }
                let s = -2.0 / dir.z;
                x.push(c);
                y.push(dir.y * s);
                z.push(0.0);
                t.push(time);
                a.push(phi as f32);
            }
        }
        let channel = vec![0u8; x.len()];
        let samples = StripSamples { x: &x, y: &y, z: &z, gps_time: &t, scan_angle_deg: &a, channel: &channel };
        let params = Parameters::default();
        let segment = SegmentParams::default();
        let ctx = StripContext {
            strip: 3,
            trajectory: 1,
            trajectory_data: &traj,
            lever_arm: Vec3::zeros(),
            params: &params,
            segment: &segment,
        };
        let prepared = prepare_strip(&samples, &ctx).unwrap();
        assert_eq!(prepared.stats.rows_per_revolution, rows);
        assert_eq!(prepared.stats.revolutions, 60);
        assert!((prepared.stats.revolution_period_s - 0.02).abs() < 1e-9);
        // Interior points all get upward normals; only the image border loses some. Flat ground
        // is one segment.
        assert!(prepared.stats.points_with_normal as f64 > 0.9 * prepared.stats.points as f64);
        let sizes: Vec<usize> = (0..prepared.stats.segmentation.segments as u32)
            .map(|s| prepared.segment.iter().filter(|&&x| x == s).count())
            .collect();
        assert_eq!(prepared.stats.segmentation.segments, 1, "{sizes:?} {:?}", prepared.stats.segmentation);
        assert!(prepared.segment.iter().filter(|&&s| s == 0).count() as f64 > 0.9 * prepared.stats.points as f64);
        for chunk in &prepared.chunks {
            for nrm in &chunk.normal {
                assert!(nrm[2] > 0.999, "{nrm:?}");
            }
            assert!(chunk.right.iter().filter(|&&r| r != NO_NEIGHBOUR).count() > chunk.len() / 2);
        }
        // The anchor coordinate follows arc length: first point at 1 m → anchor 2.
        assert_eq!(prepared.stats.first_anchor, 2);
    }

    /// A strip without scan angles (all 0) gets its scan image from the beam directions: with the
    /// scan plane turned 30° in the vehicle and the vehicle heading 20°, the image has the same
    /// size, the same points get normals and the ground is still one segment.
    #[test]
    fn strip_without_scan_angles_gets_its_rows_from_the_beam_directions() {
        let speed = 10.0;
        let heading = 20f64.to_radians();
        let times: Vec<f64> = (0..=400).map(|i| 1000.0 + i as f64 * 0.005).collect();
        let positions =
            times.iter().map(|t| Vec3::new(heading.cos(), heading.sin(), 0.0) * ((t - 1000.0) * speed)).collect();
        let traj = Trajectory::new(times, positions, vec![[0.0, 0.0, 20.0]; 401]).unwrap();
        let rows = 300u32;
        let rate = 40.0;
        let turn = 30f64.to_radians();
        let (mut x, mut y, mut z, mut t, mut a) = (vec![], vec![], vec![], vec![], vec![]);
        for rev in 0..50 {
            for j in 0..rows {
                let phi = -180.0 + j as f64 * 360.0 / rows as f64;
                let time = 1000.1 + rev as f64 / rate + j as f64 / (rate * rows as f64);
                let pose = traj.pose_at(time).unwrap();
                let (sp, cp) = phi.to_radians().sin_cos();
                // The plane of (0, sin φ, cos φ) turned about the body's z axis.
                let body = Vec3::new(-turn.sin() * sp, turn.cos() * sp, cp);
                let dir = pose.rotation * body;
                // Only downward beams hit the ground (z = 0); the head is 2 m up.
                if dir.z > -0.3 {
                    continue;
                }
                let p = pose.position + dir * (-2.0 / dir.z);
                x.push(p.x);
                y.push(p.y);
                z.push(0.0);
                t.push(time);
                a.push(phi as f32);
            }
        }
        let traj_head = Trajectory::new(
            traj.times().to_vec(),
            traj.positions().iter().map(|p| p + Vec3::new(0.0, 0.0, 2.0)).collect(),
            traj.rpy_deg().to_vec(),
        )
        .unwrap();
        let channel = vec![0u8; x.len()];
        let zeros = vec![0f32; x.len()];
        let params = Parameters::default();
        let segment = SegmentParams::default();
        let ctx = StripContext {
            strip: 0,
            trajectory: 0,
            trajectory_data: &traj_head,
            lever_arm: Vec3::zeros(),
            params: &params,
            segment: &segment,
        };
        let with = StripSamples { x: &x, y: &y, z: &z, gps_time: &t, scan_angle_deg: &a, channel: &channel };
        let without = StripSamples { scan_angle_deg: &zeros, ..with };
        let known = prepare_strip(&with, &ctx).unwrap();
        let rebuilt = prepare_strip(&without, &ctx).unwrap();
        assert!(!known.stats.scan_angles_reconstructed && rebuilt.stats.scan_angles_reconstructed);
        assert_eq!(known.stats.rows_per_revolution, rows);
        assert_eq!(rebuilt.stats.rows_per_revolution, rows);
        // The simulated angle wraps at the nadir, inside the ground fan; the reconstruction puts
        // the seam in the sky, so its first and last revolutions are halves: one column more.
        assert_eq!(rebuilt.stats.revolutions, known.stats.revolutions + 1);
        assert!(known.stats.points_with_normal as f64 > 0.9 * known.stats.points as f64);
        assert!(rebuilt.stats.points_with_normal as f64 >= 0.99 * known.stats.points_with_normal as f64);
        assert_eq!(rebuilt.stats.segmentation.segments, 1);
        // Same angular steps between consecutive beams; columns advance only at the seam.
        for k in 0..x.len() - 1 {
            let step = |image: &ScanImage| (image.row[k + 1] + rows - image.row[k]) % rows;
            if known.image.column[k + 1] == known.image.column[k] {
                assert_eq!(step(&rebuilt.image), step(&known.image), "point {k}");
            }
            let advance = rebuilt.image.column[k + 1] - rebuilt.image.column[k];
            assert!(advance <= 1, "point {k}: {advance}");
        }
    }

    /// Beams that do not lie in one plane are not a rotating scanner's: no angles are made up.
    #[test]
    fn scattered_beams_give_no_reconstructed_angles() {
        let times: Vec<f64> = (0..=10).map(|i| i as f64 * 0.1).collect();
        let positions = times.iter().map(|t| Vec3::new(*t, 0.0, 0.0)).collect();
        let traj = Trajectory::new(times, positions, vec![[0.0; 3]; 11]).unwrap();
        let mut cursor = GeometryCursor::new(&traj, &Vec3::zeros(), 0.5);
        let (mut x, mut y, mut z, mut t) = (vec![], vec![], vec![], vec![]);
        let mut head = vec![];
        for k in 0..500 {
            let time = k as f64 * 0.001;
            // Directions spread over a sphere (golden-angle spiral).
            let h = 1.0 - 2.0 * (k as f64 + 0.5) / 500.0;
            let r = (1.0 - h * h).sqrt();
            let phi = k as f64 * 2.399_963;
            let p = [time + 5.0 * r * phi.cos(), 5.0 * r * phi.sin(), 5.0 * h];
            head.push(cursor.at(time, p).unwrap().t0);
            x.push(p[0]);
            y.push(p[1]);
            z.push(p[2]);
            t.push(time);
        }
        let zeros = vec![0f32; x.len()];
        let channel = vec![0u8; x.len()];
        let samples = StripSamples { x: &x, y: &y, z: &z, gps_time: &t, scan_angle_deg: &zeros, channel: &channel };
        assert!(scan_angles_missing(&zeros));
        assert!(reconstructed_scan_angles(&head, &samples, &traj).is_none());
    }

    /// The cursor gives what the full interpolation gives (pose at t, rotation times lever arm,
    /// arc length), in time order, backwards, at sample times and at both ends; outside the span
    /// nothing.
    #[test]
    fn geometry_cursor_matches_the_interpolated_pose() {
        let times: Vec<f64> = (0..50).map(|i| 100.0 + i as f64 * 0.01 + (i % 3) as f64 * 0.002).collect();
        let positions = times.iter().map(|t| Vec3::new((t - 100.0) * 12.0, (t * 3.0).sin(), 0.1 * t)).collect();
        // Mostly 0.3° per sample (the series branch), every fifth sample a 3° jump (closed form).
        let rpy = (0..50)
            .map(|i| {
                [(i as f64 * 0.3).sin() * 0.2, i as f64 * 0.05, i as f64 * 0.3 + if i % 5 == 0 { 3.0 } else { 0.0 }]
            })
            .collect();
        let traj = Trajectory::new(times.clone(), positions, rpy).unwrap();
        let lever = Vec3::new(0.8, -0.4, 1.9);
        let mut ts: Vec<f64> = (0..2000).map(|k| 100.0 + k as f64 * 0.000_26).filter(|t| *t <= times[49]).collect();
        ts.extend(times.iter().copied());
        ts.extend([times[49], times[0], 100.2345, 100.0001, times[49]]);
        let mut cursor = GeometryCursor::new(&traj, &lever, 0.5);
        let p = [3.0, 4.0, 5.0];
        for &t in &ts {
            let g = cursor.at(t, p).unwrap();
            let pose = traj.pose_at(t).unwrap();
            let t0 = pose.position + pose.rotation * lever;
            for k in 0..3 {
                assert!((g.t0[k] - t0[k]).abs() < 1e-12, "t {t}: {:?} vs {t0:?}", g.t0);
                assert!((g.r[k] - (p[k] - t0[k])).abs() < 1e-12);
            }
            let u = traj.arc_length_at(t).unwrap() / 0.5;
            assert_eq!(g.anchor, u.floor() as u32, "t {t}");
            assert!((g.lambda as f64 - u.fract()).abs() < 1e-6, "t {t}");
        }
        assert!(cursor.at(times[0] - 1e-9, p).is_none());
        assert!(cursor.at(times[49] + 1e-9, p).is_none());
        assert!(cursor.at(f64::NAN, p).is_none());
        assert!(cursor.at(100.3, p).is_some());
    }

    #[test]
    fn uncovered_and_unordered_points_are_reported() {
        let traj =
            Trajectory::new(vec![0.0, 1.0], vec![Vec3::zeros(), Vec3::new(1.0, 0.0, 0.0)], vec![[0.0; 3]; 2]).unwrap();
        let params = Parameters::default();
        let segment = SegmentParams::default();
        let ctx = StripContext {
            strip: 0,
            trajectory: 0,
            trajectory_data: &traj,
            lever_arm: Vec3::zeros(),
            params: &params,
            segment: &segment,
        };
        let xs = [0.0, 0.0];
        let ch = [0u8, 0];
        let samples =
            StripSamples { x: &xs, y: &xs, z: &xs, gps_time: &[0.5, 2.0], scan_angle_deg: &[0.0, 1.0], channel: &ch };
        assert_eq!(
            prepare_strip(&samples, &ctx).unwrap_err(),
            PrepareError::NotCovered { index: 1, time: 2.0, start: 0.0, end: 1.0 }
        );
        let samples =
            StripSamples { x: &xs, y: &xs, z: &xs, gps_time: &[0.5, 0.4], scan_angle_deg: &[0.0, 1.0], channel: &ch };
        assert!(matches!(prepare_strip(&samples, &ctx).unwrap_err(), PrepareError::NotInOrder { index: 1, .. }));
        let samples = StripSamples {
            x: &[0.0, f64::NAN],
            y: &xs,
            z: &xs,
            gps_time: &[0.5, 0.6],
            scan_angle_deg: &[0.0, 1.0],
            channel: &ch,
        };
        assert_eq!(prepare_strip(&samples, &ctx).unwrap_err(), PrepareError::NotFinite { index: 1, field: "x" });
    }
}
