//! Per-strip preparation (the `segment_strip` map task of DESIGN §3): point geometry against the
//! trajectory, the scan image (rows = measurement within a scanner revolution, columns =
//! revolutions, per channel; [`precimap_segment::ScanImage`]), RANSAC normals and the
//! Felzenszwalb–Huttenlocher segmentation ([`precimap_segment::segment_strip`]), and the
//! segmented points keyed into tiles with a border overlap.

use crate::chunk::{TileChunk, NO_NEIGHBOUR};
use precimap_core::{Parameters, TileKey, Trajectory, Vec3};
pub use precimap_segment::{PixelNormal, ScanImage, SegmentParams, SegmentStats, DROPPED_SEGMENT, NO_SEGMENT};
use precimap_segment::{StripGeometry, DROPPED, NO_POINT};
use std::collections::BTreeMap;

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

/// Geometry of one measurement relative to its trajectory (DESIGN §2).
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
/// `None` when the trajectory does not cover `t`.
pub fn measurement_geometry(
    trajectory: &Trajectory,
    lever_arm: &Vec3,
    anchor_spacing_m: f64,
    t: f64,
    p: [f64; 3],
) -> Option<MeasurementGeometry> {
    let (i, lambda) = trajectory.locate(t)?;
    let pose = trajectory.pose_in_segment(i, lambda);
    let t0 = pose.position + pose.rotation * lever_arm;
    let arcs = trajectory.arc_lengths();
    let s = arcs[i] + (arcs[i + 1] - arcs[i]) * lambda;
    let times = trajectory.times();
    let speed = (arcs[i + 1] - arcs[i]) / (times[i + 1] - times[i]);
    let u = (s / anchor_spacing_m).max(0.0);
    let anchor = u.floor();
    Some(MeasurementGeometry {
        t0: [t0.x, t0.y, t0.z],
        r: [p[0] - t0.x, p[1] - t0.y, p[2] - t0.z],
        anchor: anchor as u32,
        lambda: (u - anchor) as f32,
        speed,
    })
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
    let head: Vec<[f64; 3]> = geometry.iter().map(|g| g.t0).collect();
    phase_done(PreparePhase::Geometry);
    let mut image = ScanImage::build(samples.scan_angle_deg, samples.gps_time, samples.channel);
    image.thin_standstill(&head, ctx.params.min_revolution_advance_m);
    let grid = image.grid();
    phase_done(PreparePhase::ScanImage);
    let geo = StripGeometry { x: samples.x, y: samples.y, z: samples.z, head: &head };
    let normals = precimap_segment::estimate_normals(&geo, &image, &grid, ctx.segment);
    phase_done(PreparePhase::Normals);
    let segmentation = precimap_segment::segment_with_normals(&geo, &image, &grid, normals, ctx.segment);
    phase_done(PreparePhase::Segmentation);
    drop(head);
    let links = Links::build(&image, &grid);
    drop(grid);
    let chunks = emit_tiles(samples, ctx, &geometry, &links, &segmentation.normals, &segmentation.segment);
    phase_done(PreparePhase::Tiling);
    let emitted = chunks.iter().map(|c| c.len() as u64).sum();
    let first_anchor = geometry.iter().map(|g| g.anchor).min().unwrap_or(0);
    let last_anchor = geometry.iter().map(|g| g.anchor).max().unwrap_or(0) + 1;
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
            segmentation: segmentation.stats,
        },
        segment: segmentation.segment,
        image,
        normals: segmentation.normals,
    })
}

fn strip_geometry(
    samples: &StripSamples<'_>,
    ctx: &StripContext<'_>,
) -> Result<Vec<MeasurementGeometry>, PrepareError> {
    let (start, end) = ctx.trajectory_data.time_span();
    let mut out = Vec::with_capacity(samples.len());
    let mut previous = f64::NEG_INFINITY;
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
        let g = measurement_geometry(ctx.trajectory_data, &ctx.lever_arm, ctx.params.anchor_spacing_m, t, p)
            .ok_or(PrepareError::NotCovered { index: k, time: t, start, end })?;
        out.push(g);
    }
    Ok(out)
}

/// Scan-image neighbour links: next row in the same revolution (wrapping round), same row in the
/// next revolution.
#[derive(Debug)]
struct Links {
    right: Vec<u32>,
    down: Vec<u32>,
}

impl Links {
    fn build(image: &ScanImage, grid: &[u32]) -> Self {
        let n = image.row.len();
        let mut right = vec![NO_NEIGHBOUR; n];
        let mut down = vec![NO_NEIGHBOUR; n];
        let rows = image.rows as usize;
        for k in 0..n {
            let c = image.column[k];
            if c == DROPPED {
                continue;
            }
            let px = c as usize * rows + image.row[k] as usize;
            // Rows wrap around: the revolution is a circle.
            let next = if (image.row[k] as usize) + 1 < rows { px + 1 } else { px + 1 - rows };
            if rows > 2 && grid[next] != NO_POINT {
                right[k] = grid[next];
            }
            if px + rows < grid.len() && grid[px + rows] != NO_POINT {
                down[k] = grid[px + rows];
            }
        }
        Self { right, down }
    }
}

fn emit_tiles(
    samples: &StripSamples<'_>,
    ctx: &StripContext<'_>,
    geometry: &[MeasurementGeometry],
    links: &Links,
    normals: &[Option<PixelNormal>],
    segment: &[u32],
) -> Vec<TileChunk> {
    let params = ctx.params;
    // Points per tile, in acquisition order.
    let mut members: BTreeMap<TileKey, Vec<u32>> = BTreeMap::new();
    let max_range2 = params.max_range_m * params.max_range_m;
    for k in 0..samples.len() {
        let r = geometry[k].r;
        if segment[k] >= DROPPED_SEGMENT || normals[k].is_none() || r[0] * r[0] + r[1] * r[1] + r[2] * r[2] > max_range2
        {
            continue;
        }
        for key in TileKey::with_overlap(samples.x[k], samples.y[k], params.tile_size_m, params.tile_overlap_m) {
            members.entry(key).or_default().push(k as u32);
        }
    }
    members
        .into_iter()
        .map(|(key, globals)| {
            let (ox, oy) = key.origin(params.tile_size_m);
            let origin = [ox, oy, 0.0];
            let mut chunk = TileChunk::with_capacity(key, ctx.strip, ctx.trajectory, origin, globals.len());
            let local = |g: u32| -> u32 {
                if g == NO_NEIGHBOUR {
                    return NO_NEIGHBOUR;
                }
                globals.binary_search(&g).map(|i| i as u32).unwrap_or(NO_NEIGHBOUR)
            };
            for &g in &globals {
                let k = g as usize;
                let geo = &geometry[k];
                let Some(nrm) = normals[k] else { continue };
                chunk.push(
                    [(geo.t0[0] - ox) as f32, (geo.t0[1] - oy) as f32, geo.t0[2] as f32],
                    [geo.r[0] as f32, geo.r[1] as f32, geo.r[2] as f32],
                    nrm.normal,
                    geo.anchor,
                    geo.lambda,
                    local(links.right[k]),
                    local(links.down[k]),
                    nrm.edge_limit,
                    segment[k],
                );
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
