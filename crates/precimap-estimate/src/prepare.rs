//! Per-strip preparation (the `segment_strip` map task): point geometry against the
//! trajectory, the scan image (rows = measurement within a scanner revolution, columns =
//! revolutions, per channel; [`precimap_segment::ScanImage`]), RANSAC normals and the
//! Felzenszwalb–Huttenlocher segmentation ([`precimap_segment::segment_strip`]), or, for a strip
//! whose pattern makes no scan image, normals and segments from 3-D neighbours
//! ([`precimap_segment::segment_unordered`]); then the segmented points keyed into tiles with a
//! border overlap.

use crate::chunk::{TileChunk, NO_NEIGHBOUR};
use precimap_core::geom::rotate_small;
use precimap_core::{NormalSource, Parameters, TileKey, Trajectory, Vec3};
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
    /// A multi-beam head's ring number per point (`parameters.ring`), or empty.
    pub ring: &'a [u8],
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
    #[error("parameters.normals is scan_image, but {reason}, which would take far more memory than the points; set parameters.normals to auto or neighbours")]
    ScanImageTooLarge { reason: String },
    #[error("parameters.normals is ring_image, but the strip was read without ring numbers; set parameters.ring to where the strips carry them")]
    NoRing,
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

impl GeometryCursor<'_> {
    /// The body attitude at `t` (within the segment of the last [`Self::at`]) as a rotation
    /// vector: `R_i·Exp(λ·ω_i)`, the interpolation [`Trajectory`] uses.
    pub fn attitude(&self, t: f64) -> [f64; 3] {
        use precimap_core::geom::{so3_exp, so3_log};
        let s = &self.segment;
        let lambda = ((t - s.t0) / (s.t1 - s.t0)).clamp(0.0, 1.0);
        let r = precimap_core::Mat3::from_fn(|a, b| s.rotation[a][b]);
        let step = so3_exp(&Vec3::from(s.omega.map(|w| w * lambda)));
        let theta = so3_log(&(r * step));
        [theta.x, theta.y, theta.z]
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
    /// The scan image (row and column of every point), when the normals came from it.
    pub image: Option<ScanImage>,
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
    /// Points emitted at least once: a normal, a segment, within `max_range_m` (what
    /// `min_usable_share` is measured on).
    #[serde(default)]
    pub points_usable: u64,
    /// Revolutions in the scan or ring image (0 without one).
    pub revolutions: u64,
    /// The image's rows: measurements per revolution, or a ring image's rings.
    pub rows_per_revolution: u32,
    pub revolution_period_s: f64,
    pub first_anchor: u32,
    pub last_anchor: u32,
    pub time_start: f64,
    pub time_end: f64,
    /// Seconds between consecutive points more than [`TIME_GAP_S`] apart, summed.
    #[serde(default)]
    pub time_in_gaps_s: f64,
    /// The strip had no scan angles (all equal); rows came from the beam directions instead
    /// ([`reconstructed_scan_angles`]).
    #[serde(default)]
    pub scan_angles_reconstructed: bool,
    /// Where the normals came from: the scan image or 3-D neighbours (never `auto`).
    #[serde(default)]
    pub normal_source: NormalSource,
    /// Why the scan image was not used, when `parameters.normals` is `auto` and it was not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scan_image_refused: Option<String>,
    pub segmentation: SegmentStats,
}

/// A pause between consecutive points longer than this (seconds) is a gap in the acquisition.
pub const TIME_GAP_S: f64 = 1.0;
/// With `normals: auto`, a scan image whose normals cover a smaller share of the points is not
/// the strip's pattern: its normals come from 3-D neighbours instead.
const AUTO_MIN_NORMAL_SHARE: f64 = 0.1;
/// With `normals: auto`, a scan image with more pixels per point is not the strip's pattern (a
/// rotating head's image is mostly full; a pattern the image misreads spreads over millions of
/// columns, and its grid would cost far more memory than the points).
const MAX_PIXELS_PER_POINT: u64 = 16;

/// With `normals: auto`, a scan image with more points per pixel is not a single-profile head's
/// (multiple returns put a few on one pixel; a multi-beam head's rings put all of theirs).
const MAX_POINTS_PER_PIXEL: u64 = 4;

/// With `normals: scan_image`, an image with more pixels per point than this is refused with an
/// error rather than built (its grid would take far more memory than the points).
const MAX_FORCED_PIXELS_PER_POINT: u64 = 64;

/// Why `image` (before standstill thinning) is not a rotating head's scan image; `None`: it is.
fn image_refusal(image: &ScanImage) -> Option<String> {
    let points = image.row.len().max(1) as u64;
    let pixels = image.rows as u64 * image.columns as u64;
    if image.rows < 8 || image.columns < 3 {
        Some(format!("its scan angles make no scan image ({} rows × {} revolutions)", image.rows, image.columns))
    } else if points > MAX_POINTS_PER_PIXEL * pixels {
        Some(format!(
            "its scan image ({} rows × {} revolutions) would hold {:.0} points per pixel: many points share a scan \
             angle and a revolution, as a multi-beam head's do (set parameters.ring if the strips carry ring numbers)",
            image.rows,
            image.columns,
            points as f64 / pixels.max(1) as f64
        ))
    } else if pixels > MAX_PIXELS_PER_POINT * points {
        Some(format!(
            "its scan image would have {} rows × {} revolutions, {:.0} pixels per point",
            image.rows,
            image.columns,
            pixels as f64 / points as f64
        ))
    } else {
        None
    }
}

/// Seconds of the strip's span that fall in gaps between points over [`TIME_GAP_S`].
fn time_in_gaps(times: &[f64]) -> f64 {
    times.windows(2).map(|w| w[1] - w[0]).filter(|&d| d > TIME_GAP_S).sum()
}

/// Why a prepared strip is not usable enough: `None` when at least `min_share` of its points
/// are usable, else what is wrong and the likely reason (a gap-ridden acquisition, a pattern
/// that gave no normals, too few normals, or normals that formed no segments).
pub fn usable_share_problem(stats: &PrepareStats, min_share: f64) -> Option<String> {
    let points = stats.points.max(1) as f64;
    let share = stats.points_usable as f64 / points;
    if share >= min_share {
        return None;
    }
    let normals = stats.points_with_normal as f64 / points;
    let span = stats.time_end - stats.time_start;
    let reason = if span > 0.0 && stats.time_in_gaps_s > 0.5 * span {
        format!(
            "time gaps: {:.0} s of its {:.0} s lie in pauses over {TIME_GAP_S} s between points, so it is not one \
             continuous acquisition",
            stats.time_in_gaps_s, span
        )
    } else if let Some(refused) = stats.scan_image_refused.as_deref().filter(|_| normals < min_share) {
        format!(
            "scan pattern not recognised ({refused}); normals from 3-D neighbours cover {:.1} % of the points \
             (too sparse or too noisy for a plane fit?)",
            100.0 * normals
        )
    } else if normals < min_share {
        format!("too few normals: {:.1} % of the points got one", 100.0 * normals)
    } else {
        format!(
            "{:.1} % of the points have a normal, but most lie in regions under the minimum segment size or \
             beyond max_range_m",
            100.0 * normals
        )
    };
    Some(format!(
        "only {:.1} % of its {} points are usable (a normal, a segment, within max_range_m), below \
         parameters.min_usable_share {:.0} %: {reason}. Check the strip and its trajectory, choose \
         parameters.normals, or set parameters.allow_low_usable_share to go on with what is usable",
        100.0 * share,
        stats.points,
        100.0 * min_share
    ))
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
    let geo = StripGeometry { x: samples.x, y: samples.y, z: samples.z, head };
    let mut scan = None;
    let mut refused = None;
    let mut scan_angles_reconstructed = false;
    if !samples.ring.is_empty() && samples.ring.len() != n {
        return Err(PrepareError::Shape(format!("{n} points, {} ring numbers", samples.ring.len())));
    }
    let normals_from = ctx.params.normals;
    if normals_from == NormalSource::RingImage && samples.ring.is_empty() {
        return Err(PrepareError::NoRing);
    }
    if !samples.ring.is_empty() && matches!(normals_from, NormalSource::Auto | NormalSource::RingImage) {
        match ring_image_segmentation(samples, ctx, &geo, phase_done) {
            Ok((image, grid, segmentation)) => scan = Some((image, grid, segmentation, NormalSource::RingImage)),
            Err(reason) => refused = Some(reason),
        }
    } else if normals_from != NormalSource::Neighbours {
        let reconstructed = if scan_angles_missing(samples.scan_angle_deg) {
            reconstructed_scan_angles(head, samples, ctx.trajectory_data)
        } else {
            None
        };
        scan_angles_reconstructed = reconstructed.is_some();
        let angles = reconstructed.as_deref().unwrap_or(samples.scan_angle_deg);
        let mut image = ScanImage::build(angles, samples.gps_time, samples.channel);
        drop(reconstructed);
        // Judged before the standstill thinning, whose column tables are as wide as the image.
        match image_refusal(&image) {
            Some(reason) if ctx.params.normals == NormalSource::Auto => {
                refused = Some(reason);
                phase_done(PreparePhase::ScanImage);
            }
            Some(reason) if image.rows as u64 * image.columns as u64 > MAX_FORCED_PIXELS_PER_POINT * n as u64 => {
                return Err(PrepareError::ScanImageTooLarge { reason });
            }
            _ => {
                image.thin_standstill(head, ctx.params.min_revolution_advance_m);
                let grid = image.grid();
                phase_done(PreparePhase::ScanImage);
                let normals = precimap_segment::estimate_normals(&geo, &image, &grid, ctx.segment);
                phase_done(PreparePhase::Normals);
                let with = normals.iter().filter(|n| n.is_some()).count();
                if ctx.params.normals == NormalSource::Auto && (with as f64) < AUTO_MIN_NORMAL_SHARE * n as f64 {
                    refused = Some(format!(
                        "its scan image ({} rows × {} revolutions) gave only {:.1} % of the points a normal",
                        image.rows,
                        image.columns,
                        100.0 * with as f64 / n as f64
                    ));
                } else {
                    let segmentation =
                        precimap_segment::segment_with_normals(&geo, &image, &grid, normals, ctx.segment);
                    phase_done(PreparePhase::Segmentation);
                    scan = Some((image, grid, segmentation, NormalSource::ScanImage));
                }
            }
        }
    }
    let (image, links, segmentation, normal_source) = match scan {
        Some((image, grid, segmentation, source)) => (Some(image), Links::Image { grid }, segmentation, source),
        None => {
            let out = precimap_segment::segment_unordered(&geo, samples.gps_time, ctx.segment);
            phase_done(PreparePhase::Normals);
            phase_done(PreparePhase::Segmentation);
            (None, Links::Explicit(out.links), out.segmentation, NormalSource::Neighbours)
        }
    };
    let (chunks, points_usable) =
        emit_tiles(samples, ctx, &geometry, &links.of(image.as_ref()), &segmentation.normals, &segmentation.segment);
    drop(links);
    phase_done(PreparePhase::Tiling);
    let emitted = chunks.iter().map(|c| c.len() as u64).sum();
    let first_anchor = geometry.anchor.iter().copied().min().unwrap_or(0);
    let last_anchor = geometry.anchor.iter().copied().max().unwrap_or(0) + 1;
    // A ring image's columns are firings: its revolutions are whole turns of them.
    let image_stats = image.as_ref().map_or((0, 0, 0.0), |i| match i.revolution_columns {
        0 => (i.columns as u64, i.rows, i.period_s),
        per => ((i.columns / per) as u64, i.rows, i.period_s * per as f64),
    });
    Ok(PreparedStrip {
        chunks,
        stats: PrepareStats {
            points: n as u64,
            points_with_normal: segmentation.stats.points_with_normal,
            points_emitted: emitted,
            points_usable,
            revolutions: image_stats.0,
            rows_per_revolution: image_stats.1,
            revolution_period_s: image_stats.2,
            first_anchor,
            last_anchor,
            time_start: samples.gps_time[0],
            time_end: samples.gps_time[n - 1],
            time_in_gaps_s: time_in_gaps(samples.gps_time),
            scan_angles_reconstructed,
            normal_source,
            scan_image_refused: refused,
            segmentation: segmentation.stats,
        },
        segment: segmentation.segment,
        image,
        normals: segmentation.normals,
    })
}

/// The ring image of a multi-beam strip, its pixel grid and its segmentation; under `auto`,
/// `Err` with the reason when it is refused (fewer than 3 rings or firings, or too few normals).
fn ring_image_segmentation(
    samples: &StripSamples<'_>,
    ctx: &StripContext<'_>,
    geo: &StripGeometry<'_>,
    phase_done: &mut dyn FnMut(PreparePhase),
) -> Result<(ScanImage, Vec<u32>, precimap_segment::Segmentation), String> {
    let auto = ctx.params.normals == NormalSource::Auto;
    let image = ScanImage::from_rings(geo, samples.ring, samples.gps_time, ctx.params.min_revolution_advance_m);
    phase_done(PreparePhase::ScanImage);
    if auto && (image.rows < 3 || image.columns < 3) {
        return Err(format!("its ring numbers make no ring image ({} rings × {} firings)", image.rows, image.columns));
    }
    let grid = image.grid();
    let normals = precimap_segment::estimate_normals(geo, &image, &grid, ctx.segment);
    phase_done(PreparePhase::Normals);
    let n = samples.len();
    let with = normals.iter().filter(|n| n.is_some()).count();
    if auto && (with as f64) < AUTO_MIN_NORMAL_SHARE * n as f64 {
        return Err(format!(
            "its ring image ({} rings × {} firings) gave only {:.1} % of the points a normal",
            image.rows,
            image.columns,
            100.0 * with as f64 / n as f64
        ));
    }
    let segmentation = precimap_segment::segment_with_normals(geo, &image, &grid, normals, ctx.segment);
    phase_done(PreparePhase::Segmentation);
    Ok((image, grid, segmentation))
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

/// Where a point's two mesh neighbours come from: the scan image's pixel grid (next row in the
/// same revolution, wrapping round; same row in the next revolution), looked up for the emitted
/// points only, or the 3-D neighbour fallback's tangent links.
enum Links {
    Image { grid: Vec<u32> },
    Explicit(Vec<[u32; 2]>),
}

impl Links {
    fn of<'a>(&'a self, image: Option<&'a ScanImage>) -> LinkView<'a> {
        match (self, image) {
            (Links::Image { grid }, Some(image)) => LinkView::Image { image, grid },
            (Links::Explicit(links), _) => LinkView::Explicit(links),
            (Links::Image { .. }, None) => LinkView::Explicit(&[]),
        }
    }
}

enum LinkView<'a> {
    Image { image: &'a ScanImage, grid: &'a [u32] },
    Explicit(&'a [[u32; 2]]),
}

// Links are read straight from the grid: its empty pixels must read as "no neighbour".
const _: () = assert!(NO_POINT == NO_NEIGHBOUR);

impl LinkView<'_> {
    /// `(right, down)` of point `k` (in the image: not dropped), or [`NO_NEIGHBOUR`].
    #[inline]
    fn of(&self, k: usize) -> (u32, u32) {
        match self {
            LinkView::Image { image, grid } => {
                let rows = image.rows as usize;
                let row = image.row[k] as usize;
                let px = image.column[k] as usize * rows + row;
                // Rows wrap around: the revolution is a circle; a ring image's do not.
                let right = if !image.wraps {
                    if row + 1 < rows {
                        grid[px + 1]
                    } else {
                        NO_NEIGHBOUR
                    }
                } else if rows > 2 {
                    grid[if row + 1 < rows { px + 1 } else { px + 1 - rows }]
                } else {
                    NO_NEIGHBOUR
                };
                let down = grid.get(px + rows).copied().unwrap_or(NO_NEIGHBOUR);
                (right, down)
            }
            LinkView::Explicit(links) => links.get(k).map_or((NO_NEIGHBOUR, NO_NEIGHBOUR), |l| (l[0], l[1])),
        }
    }
}

fn emit_tiles(
    samples: &StripSamples<'_>,
    ctx: &StripContext<'_>,
    geometry: &HeadGeometry,
    links: &LinkView<'_>,
    normals: &[Option<PixelNormal>],
    segment: &[u32],
) -> (Vec<TileChunk>, u64) {
    let params = ctx.params;
    let with_attitude = !params.calibration.is_empty();
    // Points per tile, in acquisition order. Consecutive points mostly fall in the tiles of the
    // previous point: a small cache of recent tiles saves the map look-up.
    let mut tiles: Vec<(TileKey, Vec<u32>)> = Vec::new();
    let mut index: HashMap<TileKey, usize> = HashMap::new();
    let mut recent: [(TileKey, usize); 4] = [(TileKey { tx: i32::MIN, ty: i32::MIN }, 0); 4];
    let max_range2 = params.max_range_m * params.max_range_m;
    let mut usable = 0u64;
    for k in 0..samples.len() {
        let r = geometry.r(samples, k);
        if segment[k] >= DROPPED_SEGMENT || normals[k].is_none() || r[0] * r[0] + r[1] * r[1] + r[2] * r[2] > max_range2
        {
            continue;
        }
        usable += 1;
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
    let chunks = tiles
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
            // The body attitude at every anchor of the chunk's range, where the campaign
            // estimates the scanners' calibration.
            if let Some((first, last)) = chunk.anchor_range().filter(|_| with_attitude) {
                let count = (last - first + 1) as usize;
                chunk.attitude = ctx
                    .trajectory_data
                    .attitudes_along(params.anchor_spacing_m, first, count)
                    .into_iter()
                    .map(|a| a.map(|v| v as f32))
                    .collect();
            }
            chunk
        })
        .collect();
    (chunks, usable)
}

#[cfg(test)]
mod tests;
