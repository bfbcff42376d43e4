//! Segmentation of one scan strip in its acquisition topology (paper §4): the points are put into
//! a scan image ([`ScanImage`]), every pixel gets a normal from a robust RANSAC plane fit in its
//! image neighbourhood ([`estimate_normals`]), neighbouring pixels are compared by C0 (gap off the
//! surface relative to the noise, jump relative to the beam spacing) and C1 (normal angle)
//! continuity, and the Felzenszwalb–Huttenlocher graph segmentation ([`segment`]) groups them
//! into continuous regions; regions smaller than a threshold (tree foliage, noise) are removed.
//! A strip whose pattern makes no scan image gets the same from its neighbours in 3-D
//! ([`segment_unordered`]).
//!
//! Pure: slices in, vectors out, no I/O. Memory is a few words per point of one strip.

mod fh;
mod image;
mod neighbours;
mod normals;
mod rings;

pub use fh::{felzenszwalb_huttenlocher, felzenszwalb_huttenlocher_from, UnionFind};
pub use image::{ScanImage, DROPPED, NO_POINT};
pub use neighbours::{segment_unordered, UnorderedSegmentation};
pub use normals::{estimate_normals, NormalMethod, PixelNormal};

/// Segment id of a point that belongs to no segment (no normal, or a removed small region).
pub const NO_SEGMENT: u32 = u32::MAX;
/// Segment id of a point whose revolution was dropped at standstill (never segmented).
pub const DROPPED_SEGMENT: u32 = u32::MAX - 1;

/// Parameters of the segmentation; the defaults are what the simulated campaigns were tuned with.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct SegmentParams {
    /// Half-width of the image window of the normal fit: the 3×3 ring plus the pixels along the
    /// row and column out to this distance (2 → 12 neighbours), at most 8.
    pub window: u32,
    pub method: NormalMethod,
    /// RANSAC inlier tolerance: `inlier_base_m + inlier_per_range · range` from the plane.
    pub inlier_base_m: f64,
    pub inlier_per_range: f64,
    /// A normal needs at least this many inliers (centre included).
    pub min_inliers: u32,
    /// Longest continuous image edge: `gap_factor ×` the larger of the along-profile beam spacing
    /// (range × angular step) and the across-profile spacing (scan-head advance per revolution),
    /// plus `gap_base_m`.
    pub gap_factor: f64,
    pub gap_base_m: f64,
    /// Edge weight = C0 + C1 with C0 = max(step off the surface / inlier tolerance − 1, 0) and
    /// C1 = max(normal angle − `c1_noise_deg`, 0) / `c1_scale_deg`: differences within the noise
    /// weigh nothing, so a surface (even a curved one) is one zero-weight component and only real
    /// discontinuities compete with Felzenszwalb–Huttenlocher's `k / |C|`.
    pub c1_noise_deg: f64,
    pub c1_scale_deg: f64,
    /// Hard C0 break: neighbours further apart along their mean normal than this many inlier
    /// tolerances are never joined (a curb, a window recess, an occlusion edge).
    pub c0_break: f64,
    /// Hard C1 break: neighbours whose normals differ by more than this are never joined.
    pub c1_break_deg: f64,
    /// Felzenszwalb–Huttenlocher `k` (in edge-weight units × points).
    pub fh_k: f64,
    /// Regions with fewer points are removed (after joining them to a neighbour over an edge no
    /// heavier than `merge_max`, i.e. within the noise).
    pub min_region_points: u32,
    pub merge_max: f64,
    /// Neighbours per point of the 3-D neighbour fallback ([`segment_unordered`]): its plane fit
    /// and its segmentation graph, at most 32.
    pub neighbours: u32,
    /// The fallback's neighbours are measured at most this far apart in time (seconds): points of
    /// one pass, never the same place seen again later in the strip.
    pub neighbour_max_dt_s: f64,
}

impl Default for SegmentParams {
    fn default() -> Self {
        Self {
            window: 2,
            method: NormalMethod::Ransac,
            inlier_base_m: 0.015,
            inlier_per_range: 0.0005,
            min_inliers: 6,
            gap_factor: 2.5,
            gap_base_m: 0.01,
            c1_noise_deg: 5.0,
            c1_scale_deg: 10.0,
            c0_break: 2.0,
            c1_break_deg: 40.0,
            fh_k: 3.0,
            min_region_points: 15,
            merge_max: 1.0,
            neighbours: 12,
            neighbour_max_dt_s: 2.0,
        }
    }
}

/// A strip's points and scan-head positions (absolute, acquisition order).
#[derive(Clone, Copy, Debug)]
pub struct StripGeometry<'a> {
    pub x: &'a [f64],
    pub y: &'a [f64],
    pub z: &'a [f64],
    pub head: &'a [[f64; 3]],
}

impl StripGeometry<'_> {
    #[inline]
    pub fn point(&self, k: usize) -> [f64; 3] {
        [self.x[k], self.y[k], self.z[k]]
    }

    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
}

/// The result of segmenting one strip.
#[derive(Clone, Debug)]
pub struct Segmentation {
    /// Per point: its normal and edge limit, if the fit succeeded.
    pub normals: Vec<Option<PixelNormal>>,
    /// Per point: segment id (dense, in order of first point), [`NO_SEGMENT`], or
    /// [`DROPPED_SEGMENT`] for points of revolutions dropped at standstill.
    pub segment: Vec<u32>,
    pub stats: SegmentStats,
}

#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SegmentStats {
    /// Points in the image (not dropped at standstill).
    pub points_in_image: u64,
    pub points_with_normal: u64,
    /// Regions found by Felzenszwalb–Huttenlocher (including the small ones).
    pub regions: u64,
    /// Regions kept (the segments).
    pub segments: u64,
    /// Points with a normal in removed small regions.
    pub points_in_small_regions: u64,
    /// Points in kept segments.
    pub points_segmented: u64,
}

/// Segments a strip whose scan image is `image` (after standstill thinning).
pub fn segment_strip(geo: &StripGeometry<'_>, image: &ScanImage, params: &SegmentParams) -> Segmentation {
    let grid = image.grid();
    let normals = estimate_normals(geo, image, &grid, params);
    segment_with_normals(geo, image, &grid, normals, params)
}

/// The second half of [`segment_strip`]: C0/C1 edge weights, Felzenszwalb–Huttenlocher and the
/// small-region removal, given the pixel grid (`image.grid()`) and the normals
/// ([`estimate_normals`]); separate so that callers can time the two halves.
pub fn segment_with_normals(
    geo: &StripGeometry<'_>,
    image: &ScanImage,
    grid: &[u32],
    normals: Vec<Option<PixelNormal>>,
    params: &SegmentParams,
) -> Segmentation {
    let mut segment = segment(geo, image, grid, &normals, params);
    for (id, &c) in segment.ids.iter_mut().zip(&image.column) {
        if c == DROPPED {
            *id = DROPPED_SEGMENT;
        }
    }
    let in_image = image.column.iter().filter(|&&c| c != DROPPED).count() as u64;
    finish_segmentation(normals, segment, in_image)
}

/// A segmentation's statistics from its normals and regions (`points_in_image`: the points that
/// took part).
pub(crate) fn finish_segmentation(
    normals: Vec<Option<PixelNormal>>,
    regions: Regions,
    points_in_image: u64,
) -> Segmentation {
    let mut stats = SegmentStats {
        points_in_image,
        points_with_normal: normals.iter().filter(|n| n.is_some()).count() as u64,
        ..Default::default()
    };
    stats.points_segmented = regions.ids.iter().filter(|&&s| s < DROPPED_SEGMENT).count() as u64;
    stats.points_in_small_regions = stats.points_with_normal - stats.points_segmented;
    stats.regions = regions.regions;
    stats.segments = regions.segments;
    Segmentation { normals, segment: regions.ids, stats }
}

pub(crate) struct Regions {
    ids: Vec<u32>,
    regions: u64,
    segments: u64,
}

/// Homogeneity of two neighbouring pixels: `None` where C0 or C1 continuity is broken outright,
/// else the edge weight (0 = same plane). The tests compare squares and cosines, so an edge within
/// the noise (most of them) costs no square root, division or arc cosine.
#[inline]
pub fn edge_weight(p: [f64; 3], q: [f64; 3], np: &PixelNormal, nq: &PixelNormal, c: &EdgeConstants) -> Option<f32> {
    let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
    let gap2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    let limit = np.edge_limit.max(nq.edge_limit) as f64;
    if gap2 > limit * limit {
        return None;
    }
    let (a, b) = (np.normal.map(f64::from), nq.normal.map(f64::from));
    let cos = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0);
    if cos < c.cos_break {
        return None;
    }
    let m = [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
    let len2 = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).max(1e-24);
    // The step along the mean normal, squared and times |m|².
    let along = m[0] * d[0] + m[1] * d[1] + m[2] * d[2];
    let along2 = along * along;
    let tol = np.tolerance.max(nq.tolerance) as f64;
    if along2 > c.c0_break2 * tol * tol * len2 {
        return None;
    }
    let c0 = if along2 <= tol * tol * len2 { 0.0 } else { along.abs() / len2.sqrt() / tol - 1.0 };
    let c1 =
        if cos >= c.cos_noise { 0.0 } else { (cos.acos().to_degrees() - c.c1_noise_deg).max(0.0) / c.c1_scale_deg };
    Some((c0 + c1) as f32)
}

/// The [`SegmentParams`] of [`edge_weight`] in the form it uses.
#[derive(Clone, Copy, Debug)]
pub struct EdgeConstants {
    cos_noise: f64,
    cos_break: f64,
    c0_break2: f64,
    c1_noise_deg: f64,
    c1_scale_deg: f64,
}

impl EdgeConstants {
    pub fn new(params: &SegmentParams) -> Self {
        Self {
            cos_noise: params.c1_noise_deg.to_radians().cos(),
            cos_break: params.c1_break_deg.to_radians().cos(),
            c0_break2: params.c0_break * params.c0_break,
            c1_noise_deg: params.c1_noise_deg,
            c1_scale_deg: params.c1_scale_deg,
        }
    }
}

fn segment(
    geo: &StripGeometry<'_>,
    image: &ScanImage,
    grid: &[u32],
    normals: &[Option<PixelNormal>],
    params: &SegmentParams,
) -> Regions {
    let n = geo.len();
    let rows = image.rows as usize;
    // Edges within the noise (weight 0) are joined at once; only the weighted ones are sorted.
    let weightless = params.fh_k > 0.0;
    let mut uf = UnionFind::new(n);
    let mut edges: Vec<(f32, u32, u32)> = Vec::with_capacity(n / 2);
    let constants = EdgeConstants::new(params);
    for (pixel, &k) in grid.iter().enumerate() {
        if k == NO_POINT {
            continue;
        }
        let Some(nk) = &normals[k as usize] else { continue };
        let (c, r) = (pixel / rows, pixel % rows);
        let mut link = |j: u32| {
            if j == NO_POINT {
                return;
            }
            if let Some(nj) = &normals[j as usize] {
                if let Some(w) = edge_weight(geo.point(k as usize), geo.point(j as usize), nk, nj, &constants) {
                    if w == 0.0 && weightless {
                        uf.join_weightless(k, j);
                    } else {
                        edges.push((w, k, j));
                    }
                }
            }
        };
        // Rows wrap around (the revolution is a circle); a ring image's do not.
        if !image.wraps {
            if r + 1 < rows {
                link(grid[pixel + 1]);
            }
        } else if rows > 2 {
            link(grid[if r + 1 < rows { pixel + 1 } else { pixel + 1 - rows }]);
        }
        if c + 1 < image.columns as usize {
            link(grid[pixel + rows]);
        }
        // A ring image: the same ring one revolution later, which lies the head's advance per
        // revolution away, so its gap is allowed that much.
        let later = c + image.revolution_columns as usize;
        if image.revolution_columns > 0 && later < image.columns as usize {
            let j = grid[later * rows + r];
            if let Some(nj) = normals.get(j as usize).copied().flatten() {
                let advance = image::dist(geo.head[k as usize], geo.head[j as usize]);
                let limit = (params.gap_factor * advance + params.gap_base_m) as f32;
                let widen = |n: &PixelNormal| PixelNormal { edge_limit: n.edge_limit.max(limit), ..*n };
                let (p, q) = (geo.point(k as usize), geo.point(j as usize));
                // Only within the noise: a long edge across a discontinuity would merge whole
                // surfaces of many revolutions at once.
                if edge_weight(p, q, &widen(nk), &widen(&nj), &constants) == Some(0.0) {
                    if weightless {
                        uf.join_weightless(k, j);
                    } else {
                        edges.push((0.0, k, j));
                    }
                }
            }
        }
    }
    let uf = felzenszwalb_huttenlocher_from(uf, edges, params.fh_k, params.min_region_points, params.merge_max as f32);
    label_regions(uf, normals, params.min_region_points)
}

/// Dense segment ids (in order of first point) of the components of `uf` with at least
/// `min_region_points` points; points without a normal and those of smaller components get
/// [`NO_SEGMENT`].
pub(crate) fn label_regions(mut uf: UnionFind, normals: &[Option<PixelNormal>], min_region_points: u32) -> Regions {
    let n = normals.len();
    let mut ids = vec![NO_SEGMENT; n];
    let mut label: Vec<u32> = vec![NO_SEGMENT; n];
    let (mut regions, mut segments) = (0u64, 0u64);
    for k in 0..n {
        if normals[k].is_none() {
            continue;
        }
        let root = uf.find(k as u32) as usize;
        if label[root] == NO_SEGMENT {
            regions += 1;
            if uf.size(root as u32) >= min_region_points {
                label[root] = segments as u32;
                segments += 1;
            } else {
                label[root] = NO_SEGMENT - 1;
            }
        }
        if label[root] != NO_SEGMENT - 1 {
            ids[k] = label[root];
        }
    }
    Regions { ids, regions, segments }
}

#[cfg(test)]
mod tests;
