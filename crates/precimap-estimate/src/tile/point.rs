//! The point-sampled latent map of [`super::estimate_tile`]: latent heights evaluated exactly at
//! the points of the tile's core ([`point_latent`]), and what every route hands the observation
//! loop ([`PointLatent`], [`Latent`]).

use super::triangles::{PlaneTriangle, Triangles};
use super::{floor_i64, lifted, MAX_SLOPE, NONE};
use crate::latent::{LatentSample, LatentSink};
use crate::stats::TileStats;

/// The core points of a tile sorted into a bucket grid per surface model (about
/// [`POINTS_PER_BUCKET`] per bucket), in bucket order: the points a triangle may cover lie next
/// to each other in memory.
pub(super) struct CoreIndex {
    pub(super) grids: Vec<Buckets>,
    /// Per bucket, the first item; one more entry closes the last bucket.
    pub(super) start: Vec<u32>,
    /// Point index (into the tile's points) per item.
    pub(super) items: Vec<u32>,
    /// Plane coordinates of each item in its model's frame.
    pub(super) item_uv: Vec<[f64; 2]>,
    /// Strip and anchor of each item (for the own-pass test).
    pub(super) item_owner: Vec<(u32, u32)>,
    /// Height of each item above its model's plane (in item order: read where the items are
    /// walked in order, not by point index).
    pub(super) item_h: Vec<f64>,
}

impl CoreIndex {
    pub(super) fn new(t: &Triangles, in_core: &impl Fn(&[f64; 3]) -> bool) -> Self {
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
    pub(super) fn for_each_cover(
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

/// A triangle of [`CoreIndex::for_each_cover`] in its model's plane: the model, the corner it
/// hangs off and that corner's scan head (zero without vehicle positions), and its height and
/// slope.
pub(super) struct CoveringTriangle {
    pub(super) model: u32,
    pub(super) first: usize,
    pub(super) vehicle: [f64; 2],
    pub(super) plane: PlaneTriangle,
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
pub(super) fn point_latent<S: LatentSink>(
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
pub(super) struct Latent {
    /// Per point, what the observation loop reads of the latent map.
    pub(super) points: Vec<PointLatent>,
    /// Per item, the pulls on its covering triangles (empty without the consistent gradient).
    pub(super) pull: Vec<[f64; 2]>,
}

/// What the observation loop reads of the latent map at one point, in one record: the routes
/// write them in item (pixel) order, scattered over the points, so one 40-byte record is
/// written where three columns took three scattered writes.
#[derive(Clone, Copy, Debug)]
pub(super) struct PointLatent {
    /// The latent height (NaN: not observable).
    pub(super) height: f64,
    /// `[x, y, share]` for the common-mode field (zeros without it).
    pub(super) others: [f64; 3],
    /// The number of other passes' triangles the latent height averages.
    pub(super) covering: u32,
}

impl Default for PointLatent {
    fn default() -> Self {
        Self { height: f64::NAN, others: [0.0; 3], covering: 0 }
    }
}

/// The observation loop's outlier threshold and weight, for the pulls of [`point_latent`]: a
/// point used with residual `e` and `c` covering triangles pulls on each with weight `ω/(c+1)`.
#[derive(Clone, Copy)]
pub(super) struct ItemPull {
    pub(super) threshold: f64,
    pub(super) weight: f64,
}

/// Mean number of core points per bucket of [`point_latent`]'s grids.
pub(super) const POINTS_PER_BUCKET: f64 = 2.0;

/// Points of one strip this many anchors apart or more (32 m along the trajectory) belong to
/// different passes over a place.
pub(super) const SAME_PASS_ANCHORS: u32 = 64;

/// Bucket grid of one surface model's core points: bucket (i, j) covers
/// `u0 + [i, i+1)/inv × v0 + [j, j+1)/inv`.
pub(super) struct Buckets {
    pub(super) u0: f64,
    pub(super) v0: f64,
    pub(super) inv: f64,
    pub(super) nu: u32,
    pub(super) nv: u32,
    pub(super) offset: usize,
}

/// Other passes' surface heights at one point.
#[derive(Clone, Copy, Default)]
pub(super) struct Sample {
    pub(super) sum: f64,
    pub(super) sum2: f64,
    pub(super) slope: [f64; 2],
    /// Sum of the contributing triangles' scan-head positions (common-mode field only).
    pub(super) vehicle: [f64; 2],
    pub(super) count: u32,
}

impl Sample {
    /// Adds one triangle's height, slope and scan head if `take`, else exact zeros: without a
    /// branch (see [`CoreIndex::for_each_cover`]; on small s1 a seventh of the candidates are
    /// taken).
    #[inline]
    pub(super) fn add_masked(&mut self, take: bool, h: f64, hx: f64, hy: f64, vehicle: [f64; 2]) {
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
    pub(super) fn remove(&mut self, h: f64, slope: [f32; 2], vehicle: [f64; 2]) {
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
    pub(super) fn mean_with(&self, own: f64) -> f64 {
        (own + self.sum) / (self.count as f64 + 1.0)
    }
}
