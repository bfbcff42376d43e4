//! Normals and segments of a strip whose acquisition pattern makes no scan image (airborne
//! scanners, unordered or merged files, heads whose pattern is not recognised): every point's
//! neighbours are found in 3-D, in a voxel hash, among the points measured within
//! [`SegmentParams::neighbour_max_dt_s`] of it (one pass, not the same place seen again later).
//!
//! The voxel edge is chosen from the data so that a typical point's voxel holds about as many
//! points as a neighbourhood has; the candidates of a point are its own voxel's points (when it
//! holds enough) or those of the 27 voxels around it. In a very dense voxel (a standstill, the
//! ground beside the head) they are the points nearest in acquisition order and a thinned sample
//! of the rest, so that no query costs more than O(k). The normal is the scan-image path's robust
//! plane fit ([`SegmentParams::method`]) on the neighbours, with the same planarity test; the
//! Felzenszwalb–Huttenlocher graph is the neighbour graph with the same C0/C1 edge weights; and
//! each point is linked to its nearest neighbour along two tangent directions, which gives the
//! estimator the triangles the scan image's "next in revolution" and "next revolution" give.
//!
//! Memory per point: 12 bytes of voxel index, 4 per neighbour (dropped before the links are
//! returned), a normal, the union–find and the links: about 120 bytes with 12 neighbours,
//! whatever the pattern.

use crate::fh::{felzenszwalb_huttenlocher_from, UnionFind};
use crate::image::{dist, NO_POINT};
use crate::normals::{fit_neighbourhood, Budget, MAX_FIT_NEIGHBOURS};
use crate::{edge_weight, label_regions, EdgeConstants, PixelNormal, SegmentParams, Segmentation, StripGeometry};

/// Most neighbours per point.
const MAX_NEIGHBOURS: usize = 32;
const _: () = assert!(MAX_NEIGHBOURS <= MAX_FIT_NEIGHBOURS);
/// Bits per axis of a voxel key (three fit a u64).
const AXIS_BITS: u32 = 21;
/// Rounds of voxel-size refinement.
const VOXEL_ROUNDS: usize = 4;
/// A voxel with more than this many times k points is searched in part ([`VoxelIndex::nearest`]).
const DENSE_CAP: usize = 16;
/// The part: this many times k points either side in acquisition order, and a sample of the rest.
const WINDOW: usize = 4;

/// The fallback's result: the segmentation, and per point its two tangent neighbours
/// `[right, down]` (point indices, [`NO_POINT`] where none), the scan image's links' stand-in.
#[derive(Clone, Debug)]
pub struct UnorderedSegmentation {
    pub segmentation: Segmentation,
    pub links: Vec<[u32; 2]>,
    /// The voxel edge used, metres.
    pub voxel_m: f64,
}

/// Normals from 3-D neighbours, segments on the neighbour graph, and tangent links, for a strip
/// of any acquisition pattern. `time` is each point's GPS time (seconds).
pub fn segment_unordered(geo: &StripGeometry<'_>, time: &[f64], params: &SegmentParams) -> UnorderedSegmentation {
    let n = geo.len().min(time.len());
    let k = (params.neighbours as usize).clamp(3, MAX_NEIGHBOURS);
    let index = VoxelIndex::build(geo, n, k);
    let neighbours = index.nearest(geo, time, k, params.neighbour_max_dt_s);
    let voxel_m = index.size;
    drop(index);
    let normals = neighbour_normals(geo, &neighbours, k, params);
    let regions = neighbour_regions(geo, &neighbours, k, &normals, params);
    let links = tangent_links(geo, &neighbours, k, &normals);
    drop(neighbours);
    let segmentation = crate::finish_segmentation(normals, regions, n as u64);
    UnorderedSegmentation { segmentation, links, voxel_m }
}

/// Points sorted by voxel, with each one's voxel key.
struct VoxelIndex {
    size: f64,
    origin: [f64; 3],
    keys: Vec<u64>,
    order: Vec<u32>,
}

impl VoxelIndex {
    /// Chooses the voxel edge so that the voxel of the median point (points weighted equally)
    /// holds about `target` points, starting from the bounding box's share per point as if the
    /// points covered its horizontal area (a surface), then refined from the measured occupancy.
    fn build(geo: &StripGeometry<'_>, n: usize, target: usize) -> Self {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for i in 0..n {
            let p = geo.point(i);
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let extent = if n == 0 { 0.0 } else { (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max) };
        // Every axis must fit its key bits (with one voxel of margin either side).
        let smallest = (extent / ((1u64 << AXIS_BITS) - 4) as f64).max(1e-4);
        let area = ((hi[0] - lo[0]).max(1e-3) * (hi[1] - lo[1]).max(1e-3)).max(1e-6);
        let mut size = (area * target as f64 / n.max(1) as f64).sqrt().max(smallest);
        let mut index = Self { size, origin: lo, keys: Vec::new(), order: Vec::new() };
        for round in 0..VOXEL_ROUNDS {
            index.sort(geo, n, size);
            if round + 1 == VOXEL_ROUNDS || n == 0 {
                break;
            }
            let median = index.median_occupancy();
            // A surface's voxels hold points ∝ size²: the square root of the ratio, bounded so
            // that clumps (a volume) or a few isolated points do not swing it too far.
            let factor = (target as f64 / median as f64).sqrt().clamp(0.25, 4.0);
            if (0.8..1.25).contains(&factor) {
                break;
            }
            size = (size * factor).max(smallest);
        }
        index
    }

    fn sort(&mut self, geo: &StripGeometry<'_>, n: usize, size: f64) {
        self.size = size;
        let inv = 1.0 / size;
        let mut pairs: Vec<(u64, u32)> = (0..n).map(|i| (self.key_of(geo.point(i), inv), i as u32)).collect();
        pairs.sort_unstable();
        self.keys = pairs.iter().map(|p| p.0).collect();
        self.order = pairs.iter().map(|p| p.1).collect();
    }

    #[inline]
    fn key_of(&self, p: [f64; 3], inv: f64) -> u64 {
        // One voxel of margin below, so that the neighbours of the first voxel have keys too.
        let cell = |a: usize| (((p[a] - self.origin[a]) * inv) as u64 + 1).min((1 << AXIS_BITS) - 2);
        (cell(0) << (2 * AXIS_BITS)) | (cell(1) << AXIS_BITS) | cell(2)
    }

    /// The occupancy of the voxel the median point lies in.
    fn median_occupancy(&self) -> usize {
        let mut runs: Vec<usize> = Vec::new();
        let mut start = 0;
        while start < self.keys.len() {
            let end = start + self.keys[start..].partition_point(|&k| k == self.keys[start]);
            runs.push(end - start);
            start = end;
        }
        runs.sort_unstable();
        let mut seen = 0;
        for &r in &runs {
            seen += r;
            if 2 * seen >= self.keys.len() {
                return r.max(1);
            }
        }
        1
    }

    /// The range of `order` holding voxel `key`.
    fn range(&self, key: u64) -> std::ops::Range<usize> {
        let start = self.keys.partition_point(|&k| k < key);
        let end = start + self.keys[start..].partition_point(|&k| k == key);
        start..end
    }

    /// The `k` nearest neighbours of every point (`n·k` entries, nearest first, [`NO_POINT`]
    /// padded), among the points within `max_dt` seconds of it.
    fn nearest(&self, geo: &StripGeometry<'_>, time: &[f64], k: usize, max_dt: f64) -> Vec<u32> {
        let n = self.keys.len();
        let mut out = vec![NO_POINT; n * k];
        let mut ranges: Vec<std::ops::Range<usize>> = Vec::with_capacity(27);
        let mut best: Vec<(f64, u32)> = Vec::with_capacity(k + 1);
        let mut start = 0;
        while start < n {
            let key = self.keys[start];
            let end = start + self.keys[start..].partition_point(|&x| x == key);
            ranges.clear();
            if end - start > 2 * k {
                // A dense voxel holds enough neighbours of its own.
                ranges.push(start..end);
            } else {
                for dx in [-1i64, 0, 1] {
                    for dy in [-1i64, 0, 1] {
                        for dz in [-1i64, 0, 1] {
                            let d = (dx << (2 * AXIS_BITS)) + (dy << AXIS_BITS) + dz;
                            let r = self.range(key.wrapping_add_signed(d));
                            if !r.is_empty() {
                                ranges.push(r);
                            }
                        }
                    }
                }
            }
            let dense = end - start > 2 * k;
            for pos in start..end {
                let i = self.order[pos];
                let (p, t) = (geo.point(i as usize), time[i as usize]);
                best.clear();
                let mut consider = |j: u32| {
                    if j == i || (time[j as usize] - t).abs() > max_dt {
                        return;
                    }
                    let q = geo.point(j as usize);
                    let d2 = (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) + (q[2] - p[2]).powi(2);
                    if best.len() == k && d2 >= best[k - 1].0 {
                        return;
                    }
                    // Ties in index order: the result does not depend on the scan order.
                    let at = best.partition_point(|&(e, m)| e < d2 || (e == d2 && m < j));
                    best.insert(at, (d2, j));
                    best.truncate(k);
                };
                if dense && end - start > DENSE_CAP * k {
                    // A very dense voxel (a standstill, the ground next to the head): the points
                    // nearest in acquisition order (the voxel keeps it), and a thinned sample of
                    // the rest, so that a query costs O(k) however full the voxel is.
                    let window = WINDOW * k;
                    let (lo, hi) = (pos.saturating_sub(window).max(start), (pos + window).min(end));
                    self.order[lo..hi].iter().for_each(|&j| consider(j));
                    let stride = (end - start) / (DENSE_CAP * k / 2);
                    (start..end)
                        .step_by(stride.max(1))
                        .filter(|q| !(lo..hi).contains(q))
                        .for_each(|q| consider(self.order[q]));
                } else {
                    for r in &ranges {
                        // A very dense voxel next to a sparse one: a thinned sample of it.
                        let stride = (r.len() / (DENSE_CAP * k / 2)).max(1);
                        self.order[r.clone()].iter().step_by(stride).for_each(|&j| consider(j));
                    }
                }
                let row = &mut out[i as usize * k..(i as usize + 1) * k];
                for (slot, &(_, j)) in row.iter_mut().zip(&best) {
                    *slot = j;
                }
            }
            start = end;
        }
        out
    }
}

/// The neighbours of point `i` (nearest first).
#[inline]
fn row(neighbours: &[u32], k: usize, i: usize) -> impl Iterator<Item = u32> + '_ {
    neighbours[i * k..(i + 1) * k].iter().copied().take_while(|&j| j != NO_POINT)
}

/// Every point's normal (facing its scan head) from a robust plane fit to its neighbours, with
/// the scan-image path's tolerance; its edge limit spans its neighbourhood.
fn neighbour_normals(
    geo: &StripGeometry<'_>,
    neighbours: &[u32],
    k: usize,
    params: &SegmentParams,
) -> Vec<Option<PixelNormal>> {
    let budget = Budget::new();
    let mut rel: Vec<[f32; 3]> = Vec::with_capacity(k);
    (0..neighbours.len() / k)
        .map(|i| {
            let p = geo.point(i);
            rel.clear();
            rel.extend(row(neighbours, k, i).map(|j| {
                let q = geo.point(j as usize);
                [(q[0] - p[0]) as f32, (q[1] - p[1]) as f32, (q[2] - p[2]) as f32]
            }));
            let head = geo.head[i];
            let range = dist(p, head);
            let tol = params.inlier_base_m + params.inlier_per_range * range;
            let mut n = fit_neighbourhood(&rel, tol as f32, i as u64, params, &budget)?;
            let to_point = [p[0] - head[0], p[1] - head[1], p[2] - head[2]];
            if n[0] * to_point[0] + n[1] * to_point[1] + n[2] * to_point[2] > 0.0 {
                n = n.map(|v| -v);
            }
            // Continuous surface reaches the neighbourhood's edge: the gap factor times the local
            // spacing (the fourth neighbour), at least the farthest neighbour with some margin.
            let len = |q: &[f32; 3]| f64::from(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
            let spacing = rel.get(3).or(rel.last()).map_or(0.0, len);
            let farthest = rel.last().map_or(0.0, len);
            let limit = (params.gap_factor * spacing).max(1.25 * farthest) + params.gap_base_m;
            Some(PixelNormal {
                normal: [n[0] as f32, n[1] as f32, n[2] as f32],
                edge_limit: limit as f32,
                tolerance: tol as f32,
            })
        })
        .collect()
}

/// Felzenszwalb–Huttenlocher on the neighbour graph (each pair once) with the C0/C1 weights.
fn neighbour_regions(
    geo: &StripGeometry<'_>,
    neighbours: &[u32],
    k: usize,
    normals: &[Option<PixelNormal>],
    params: &SegmentParams,
) -> crate::Regions {
    let n = normals.len();
    let weightless = params.fh_k > 0.0;
    let constants = EdgeConstants::new(params);
    let mut uf = UnionFind::new(n);
    let mut edges: Vec<(f32, u32, u32)> = Vec::new();
    for i in 0..n {
        let Some(ni) = &normals[i] else { continue };
        for j in row(neighbours, k, i) {
            let ju = j as usize;
            // A pair both list is taken from its lower index only.
            if ju < i && row(neighbours, k, ju).any(|m| m as usize == i) {
                continue;
            }
            let Some(nj) = &normals[ju] else { continue };
            if let Some(w) = edge_weight(geo.point(i), geo.point(ju), ni, nj, &constants) {
                if w == 0.0 && weightless {
                    uf.join_weightless(i as u32, j);
                } else {
                    edges.push((w, i as u32, j));
                }
            }
        }
    }
    let uf = felzenszwalb_huttenlocher_from(uf, edges, params.fh_k, params.min_region_points, params.merge_max as f32);
    label_regions(uf, normals, params.min_region_points)
}

/// Per point with a normal, its nearest neighbour within 45° of each of two tangent directions:
/// `right` along `e1`, `down` along `e2 = n × e1`. `e1` is the horizontal tangent of a surface
/// that is not near-horizontal and the projected x axis of one that is, so that neighbouring
/// points of a surface share their frame and `down` of `right` closes a quad.
fn tangent_links(
    geo: &StripGeometry<'_>,
    neighbours: &[u32],
    k: usize,
    normals: &[Option<PixelNormal>],
) -> Vec<[u32; 2]> {
    (0..normals.len())
        .map(|i| {
            let Some(nrm) = &normals[i] else { return [NO_POINT; 2] };
            let (e1, e2) = tangent_frame(nrm.normal.map(f64::from));
            let p = geo.point(i);
            let mut link = [NO_POINT; 2];
            for j in row(neighbours, k, i) {
                let q = geo.point(j as usize);
                let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
                let (u, v) = (dot(d, e1), dot(d, e2));
                if link[0] == NO_POINT && u > v.abs() {
                    link[0] = j;
                } else if link[1] == NO_POINT && v > u.abs() {
                    link[1] = j;
                }
                if link[0] != NO_POINT && link[1] != NO_POINT {
                    break;
                }
            }
            link
        })
        .collect()
}

/// Two unit tangents of a unit normal `n` ([`tangent_links`]).
fn tangent_frame(n: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let e1 = if n[2].abs() < 0.9 {
        // z × n: horizontal, along the surface.
        [-n[1], n[0], 0.0]
    } else {
        // x − (x·n) n.
        [1.0 - n[0] * n[0], -n[0] * n[1], -n[0] * n[2]]
    };
    let len = dot(e1, e1).sqrt();
    let e1 = e1.map(|v| v / len);
    let e2 = [n[1] * e1[2] - n[2] * e1[1], n[2] * e1[0] - n[0] * e1[2], n[0] * e1[1] - n[1] * e1[0]];
    (e1, e2)
}

#[inline]
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[cfg(test)]
mod tests;
