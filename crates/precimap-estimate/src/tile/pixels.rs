//! The fine steps' latent heights sampled at pixel centres ([`pixel_latent`]): O(points) where
//! [`super::point_latent`] is O(points × passes).
//!
//! Every scan-image triangle of every pass is sampled at the centres of the pixels it covers,
//! in a raster per surface model whose pixel follows the local point spacing (a share of it, at
//! least the step's grid): each triangle covers about one centre, whatever the number of passes.
//! A core point then reads the entries of its own pixel only: the other passes' heights at the
//! centre, carried to the point along the mean slope of those passes. The point's own pass
//! contributes the point's own height, as on the exact route, so the residual, the pulls of the
//! consistent gradient and the common-mode field's rows keep their meaning.
//!
//! Entries and core points are both sorted by pixel (counting sorts) and, within a pixel, by
//! chunk and anchor, so that a point's own-pass entries form one contiguous run (same strip,
//! fewer than [`SAME_PASS_ANCHORS`] anchors apart) and prefix sums give the other passes' sums
//! in O(1): the work per pixel is linear in its entries and points.

use super::{
    lifted, CornerPulls, ItemPull, Latent, PixelGrid, PointLatent, Triangles, MAX_SLOPE, NONE, SAME_PASS_ANCHORS,
};
use crate::chunk::NO_NEIGHBOUR;
use crate::latent::{LatentSample, LatentSink};
use crate::stats::TileStats;

/// Pixels per surface model at most, per member point (a floor on the pixel size where the
/// points are denser than the step's grid would need).
const PIXELS_PER_POINT: f64 = 4.0;

/// One triangle sampled at one pixel centre: its pass (chunk, and the anchor of the corner it
/// hangs off), its height at the centre and its slope in the model's plane, its index in
/// triangle order (where its pull is written back, in order of the corner it hangs off), and
/// the scan head of that corner (the common-mode field's rows; zeros without the field). The
/// sort writes each entry to a scattered place: one record there, not a second column.
#[derive(Clone, Copy, Debug, Default)]
struct Entry {
    chunk: u32,
    anchor: u32,
    raw: u32,
    h: f32,
    hx: f32,
    hy: f32,
    vehicle: [f64; 2],
}

/// The entries in triangle order, as columns: each column is dropped when it is done with,
/// and an entry's pass (chunk and anchor) is its corner's, read when the entries are sorted.
/// 24 bytes per entry where a row with the [`Entry`] in it took 36 and a copy of the corners
/// and models 8 more.
struct RawEntries {
    pixel: Vec<u32>,
    /// The corner the triangle hangs off and the model it was sampled on (where its pull goes).
    corner_model: Vec<(u32, u32)>,
    /// Height at the centre and slope in the model's plane.
    height: Vec<[f32; 3]>,
    /// Entries kept: the columns are longer while they fill (see [`Self::room`]).
    len: usize,
}

impl RawEntries {
    /// Columns of `n` entries to fill.
    fn new(n: usize) -> Self {
        Self { pixel: vec![0; n], corner_model: vec![(0, 0); n], height: vec![[0.0; 3]; n], len: 0 }
    }

    /// Room for `more` entries after the kept ones. Every candidate is written and only the
    /// kept ones advance `len`: a centre inside the triangle or not is a coin toss for the
    /// branch predictor (1.65 of 4.46 candidates per point are kept).
    #[inline]
    fn room(&mut self, more: usize) {
        let need = self.len + more;
        if need > self.pixel.len() {
            let size = need.max(2 * self.pixel.len());
            self.pixel.resize(size, 0);
            self.corner_model.resize(size, (0, 0));
            self.height.resize(size, [0.0; 3]);
        }
    }

    /// Cuts the columns to the kept entries.
    fn finish(&mut self) {
        self.pixel.truncate(self.len);
        self.corner_model.truncate(self.len);
        self.height.truncate(self.len);
    }
}

/// A core point in pixel order: its index, pass (chunk and anchor) and plane coordinates.
#[derive(Clone, Copy, Debug, Default)]
struct Item {
    point: u32,
    chunk: u32,
    anchor: u32,
    u: f64,
    v: f64,
    h: f64,
}

/// Running sums over a pixel's entries, in entry order (prefix sums: the sums of a contiguous
/// run of entries are one difference).
#[derive(Clone, Copy, Debug, Default)]
struct Sums {
    h: f64,
    h2: f64,
    hx: f64,
    hy: f64,
    vehicle: [f64; 2],
    count: f64,
}

impl Sums {
    #[inline]
    fn plus(&self, e: &Entry) -> Self {
        let (h, vehicle) = (e.h as f64, e.vehicle);
        Self {
            h: self.h + h,
            h2: self.h2 + h * h,
            hx: self.hx + e.hx as f64,
            hy: self.hy + e.hy as f64,
            vehicle: [self.vehicle[0] + vehicle[0], self.vehicle[1] + vehicle[1]],
            count: self.count + 1.0,
        }
    }

    #[inline]
    fn minus(&self, o: &Self) -> Self {
        Self {
            h: self.h - o.h,
            h2: self.h2 - o.h2,
            hx: self.hx - o.hx,
            hy: self.hy - o.hy,
            vehicle: [self.vehicle[0] - o.vehicle[0], self.vehicle[1] - o.vehicle[1]],
            count: self.count - o.count,
        }
    }
}

/// Stable counting sort by key (each `< buckets`): per bucket its first position (one more entry
/// closes the last), and `put(position, index)` for every element in order. The elements are
/// read in sequence and written where they go (scattered writes cost less than gathered reads,
/// which stall on every cache miss).
fn counting_sort(
    keys: impl Iterator<Item = u32> + Clone,
    buckets: usize,
    mut put: impl FnMut(usize, usize),
) -> Vec<u32> {
    let mut start = vec![0u32; buckets + 1];
    for k in keys.clone() {
        start[k as usize + 1] += 1;
    }
    for b in 0..buckets {
        start[b + 1] += start[b];
    }
    // Each bucket's first position serves as its fill cursor, which ends on the next bucket's
    // first position: one shift restores the starts without a second array.
    for (i, k) in keys.enumerate() {
        put(start[k as usize] as usize, i);
        start[k as usize] += 1;
    }
    start.copy_within(0..buckets, 1);
    start[0] = 0;
    start
}

/// Latent heights of the tile's core points from the other passes' triangles sampled at pixel
/// centres (module docs). `pixel_share` is the pixel size as a share of each model's mean
/// point spacing (the geometric mean of a point's two scan-image edges), `grid` its least size.
///
/// Returns what [`super::point_latent`] returns and, with `pulls`, the pulls of the used points
/// gathered per triangle corner ([`CornerPulls`]): an entry's triangle receives the pull of
/// every point it is another pass to, `ω/(c+1)` and `ω/(c+1)·e`, as on the exact route.
#[allow(clippy::too_many_arguments)]
pub(super) fn pixel_latent<S: LatentSink>(
    t: &Triangles,
    in_core: &impl Fn(&[f64; 3]) -> bool,
    grid: f64,
    pixel_share: f64,
    vehicle: Option<&[[f64; 2]]>,
    pulls: Option<ItemPull>,
    stats: &mut TileStats,
    sink: &mut S,
) -> (Latent, Option<CornerPulls>) {
    let n = t.position.len();
    // 1. Every member point in its model's plane; core points are the items that read the raster.
    let members = Members::project(t, in_core);
    // 2. One raster per model with core points.
    let (grids, pixel_count) = rasters(&members, grid, pixel_share);
    let passes = Passes::new(t, members.chunk_start);
    // 3. Every triangle at the pixel centres it covers, sorted by pixel.
    let sampled = sample_entries(t, &grids, pixel_count, &members.uvh, &passes, vehicle, pulls.is_some());
    // 4. The core points sorted by pixel.
    let (items, item_start) = sort_items(t, &grids, pixel_count, members.core, &members.uvh, &passes);
    drop((members.uvh, passes));
    // 5. Per pixel: each point's other passes, its latent height and the pulls it sends.
    let mut out = PixelOutputs {
        points: vec![PointLatent::default(); n],
        raw_pull: vec![[0.0f64; 2]; sampled.corner_model.len()],
        prefix: Vec::new(),
        own_pull: Vec::new(),
        stats,
        sink,
    };
    for (id, g) in grids.iter().enumerate() {
        if g.nu == 0 {
            continue;
        }
        let w = t.models[id].w;
        for j in 0..g.nv as usize {
            for i in 0..g.nu as usize {
                let pixel = g.offset + j * g.nu as usize + i;
                let (is, ie) = (item_start[pixel] as usize, item_start[pixel + 1] as usize);
                let (es, ee) = (sampled.entry_start[pixel] as usize, sampled.entry_start[pixel + 1] as usize);
                if is == ie || es == ee {
                    continue;
                }
                let centre = [g.u0 + (i as f64 + 0.5) * g.size, g.v0 + (j as f64 + 0.5) * g.size];
                let pixel = Pixel { entries: &sampled.entries[es..ee], items: &items[is..ie], centre, w };
                out.read(t, &pixel, vehicle, pulls);
            }
        }
    }
    out.stats.pixels = items.len() as u64;
    // 6. The pulls by corner, in triangle order.
    let corner_pulls = pulls.map(|_| corner_pulls(t, &sampled.corner_model, &out.raw_pull));
    (Latent { points: out.points, pull: Vec::new() }, corner_pulls)
}

/// Every member point in its model's plane (step 1): the rasters' extent and point spacing, and
/// the core points that read them.
struct Members {
    /// Per model: the members' least and greatest `u`, then `v`.
    bounds: Vec<[f64; 4]>,
    /// Per model: Σ spacing, spacing samples, member points, core points.
    spacing: Vec<[f64; 4]>,
    /// Per point, its plane coordinates and height on its model (zeros for a point on none).
    uvh: Vec<[f64; 3]>,
    /// The core points, in point order (their pass and plane coordinates are looked up when they
    /// are sorted: 4 bytes each here instead of an [`Item`]'s 40).
    core: Vec<u32>,
    /// Per chunk, its first point.
    chunk_start: Vec<usize>,
}

impl Members {
    fn project(t: &Triangles, in_core: &impl Fn(&[f64; 3]) -> bool) -> Self {
        let models = t.models;
        let mut m = Self {
            bounds: vec![[f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY]; models.len()],
            spacing: vec![[0.0f64; 4]; models.len()],
            uvh: vec![[0.0f64; 3]; t.position.len()],
            core: Vec::new(),
            chunk_start: Vec::with_capacity(t.chunks.len()),
        };
        let mut base = 0usize;
        for chunk in t.chunks {
            m.chunk_start.push(base);
            for k in 0..chunk.len() {
                let a = base + k;
                let id = t.model_of[a];
                if id == NONE {
                    continue;
                }
                let p = &t.position[a];
                let (u, v, h) = models[id as usize].project(p);
                m.uvh[a] = [u, v, h];
                let b = &mut m.bounds[id as usize];
                b[0] = b[0].min(u);
                b[1] = b[1].max(u);
                b[2] = b[2].min(v);
                b[3] = b[3].max(v);
                let s = &mut m.spacing[id as usize];
                s[2] += 1.0;
                if in_core(p) {
                    s[3] += 1.0;
                    m.core.push(a as u32);
                }
                let (right, down) = (chunk.right[k], chunk.down[k]);
                if right != NO_NEIGHBOUR && down != NO_NEIGHBOUR {
                    let limit = chunk.edge_limit[k] as f64;
                    let d2 = |q: u32| {
                        let q = &t.position[base + q as usize];
                        let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
                        d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                    };
                    let (along, across) = (d2(right), d2(down));
                    if along <= limit * limit && across <= limit * limit {
                        s[0] += (along * across).sqrt().sqrt();
                        s[1] += 1.0;
                    }
                }
            }
            base += chunk.len();
        }
        m
    }
}

/// One raster per model with core points (step 2); the others are never read (an empty
/// raster). Returns the rasters and their pixels in all.
fn rasters(members: &Members, grid: f64, pixel_share: f64) -> (Vec<PixelGrid>, usize) {
    let mut pixel_count = 0usize;
    let grids = members
        .bounds
        .iter()
        .zip(&members.spacing)
        .map(|(b, s)| {
            if s[3] == 0.0 {
                return PixelGrid { offset: pixel_count, ..PixelGrid::default() };
            }
            let (du, dv) = (b[1] - b[0], b[3] - b[2]);
            let mean_spacing = if s[1] > 0.0 { s[0] / s[1] } else { 0.0 };
            let least = ((du + grid) * (dv + grid) / (PIXELS_PER_POINT * s[2])).sqrt();
            let size = (pixel_share * mean_spacing).max(grid).max(least);
            // The raster starts at the lowest member coordinates: the first centres lie half a
            // pixel inside the members' extent (a centre on its edge is covered by one pass at
            // most; measured: 1.3 points fewer of the surface points used on small seed 1), and
            // the extreme points fall exactly on 0, never on a pixel edge that rounding could
            // move them across between two nearly equal states.
            let g = PixelGrid {
                u0: b[0],
                v0: b[2],
                size,
                inv: 1.0 / size,
                nu: (du / size) as u32 + 1,
                nv: (dv / size) as u32 + 1,
                offset: pixel_count,
            };
            pixel_count += g.nu as usize * g.nv as usize;
            g
        })
        .collect();
    (grids, pixel_count)
}

/// A point's pass: its chunk and anchor.
struct Passes {
    chunk_of: Vec<u32>,
    chunk_start: Vec<usize>,
}

impl Passes {
    fn new(t: &Triangles, chunk_start: Vec<usize>) -> Self {
        let chunk_of =
            t.chunks.iter().enumerate().flat_map(|(c, chunk)| std::iter::repeat_n(c as u32, chunk.len())).collect();
        Self { chunk_of, chunk_start }
    }

    #[inline]
    fn of(&self, t: &Triangles, a: usize) -> (u32, u32) {
        let c = self.chunk_of[a] as usize;
        (c as u32, t.chunks[c].anchor[a - self.chunk_start[c]])
    }
}

/// The triangles sampled at pixel centres (step 3), sorted by pixel.
struct SampledEntries {
    entries: Vec<Entry>,
    /// Per pixel, its first entry (one more closes the last).
    entry_start: Vec<u32>,
    /// Per entry in triangle order, the corner its triangle hangs off and the model it was
    /// sampled on (where its pull goes); empty without pulls.
    corner_model: Vec<(u32, u32)>,
}

/// Every triangle at the pixel centres it covers, in triangle order (which is the order of the
/// corners they hang off), then sorted by pixel (stably: within a pixel, entries stay in chunk
/// and point order, so anchors rise within a chunk).
fn sample_entries(
    t: &Triangles,
    grids: &[PixelGrid],
    pixel_count: usize,
    uvh: &[[f64; 3]],
    passes: &Passes,
    vehicle: Option<&[[f64; 2]]>,
    with_pulls: bool,
) -> SampledEntries {
    let mut raw = RawEntries::new(2 * t.position.len());
    t.for_each(|id, p, corners, _strip, _anchor, first| {
        let g = &grids[id as usize];
        if g.nu == 0 {
            return;
        }
        let Some(plane) = t.plane_triangle(id, &p, corners, uvh) else { return };
        let Some(centres) = g.centres_under(&plane) else { return };
        let (hx, hy) = (plane.hx as f32, plane.hy as f32);
        raw.room(centres.len());
        centres.for_each(|pixel, height, inside| {
            let at = raw.len;
            raw.pixel[at] = pixel as u32;
            raw.corner_model[at] = (first as u32, id);
            raw.height[at] = [height as f32, hx, hy];
            raw.len += inside as usize;
        });
    });
    raw.finish();
    let mut entries = vec![Entry::default(); raw.pixel.len()];
    // An entry's pass and scan head are its corner's: the raw entries are in corner order, so
    // these reads are sequential.
    let entry_start = counting_sort(raw.pixel.iter().copied(), pixel_count, |at, r| {
        let corner = raw.corner_model[r].0 as usize;
        let (chunk, anchor) = passes.of(t, corner);
        let [h, hx, hy] = raw.height[r];
        let vehicle = vehicle.map_or([0.0; 2], |v| v[corner]);
        entries[at] = Entry { chunk, anchor, raw: r as u32, h, hx, hy, vehicle };
    });
    // Where each entry's pull goes, in triangle order; the rest of the raw entries is done with.
    let corner_model = if with_pulls { std::mem::take(&mut raw.corner_model) } else { Vec::new() };
    SampledEntries { entries, entry_start, corner_model }
}

/// The core points sorted by pixel (step 4; stably, so in chunk and point order within a
/// pixel), gathered into pixel order once: the per-pixel loop reads them in sequence. Returns
/// the items and, per pixel, its first item.
fn sort_items(
    t: &Triangles,
    grids: &[PixelGrid],
    pixel_count: usize,
    core: Vec<u32>,
    uvh: &[[f64; 3]],
    passes: &Passes,
) -> (Vec<Item>, Vec<u32>) {
    let pixel_of = |&a: &u32| {
        let [u, v, _] = uvh[a as usize];
        grids[t.model_of[a as usize] as usize].pixel(u, v) as u32
    };
    // The keys once: the sort reads them twice (to count, then to place).
    let keys: Vec<u32> = core.iter().map(pixel_of).collect();
    let mut items = vec![Item::default(); core.len()];
    let item_start = counting_sort(keys.iter().copied(), pixel_count, |at, i| {
        let point = core[i];
        let [u, v, h] = uvh[point as usize];
        let (chunk, anchor) = passes.of(t, point as usize);
        items[at] = Item { point, chunk, anchor, u, v, h };
    });
    (items, item_start)
}

/// One pixel's entries and core points, its centre, and its model's normal.
struct Pixel<'a> {
    entries: &'a [Entry],
    items: &'a [Item],
    centre: [f64; 2],
    w: [f64; 3],
}

/// What step 5 writes, and its per-pixel scratch.
struct PixelOutputs<'s, S> {
    points: Vec<PointLatent>,
    /// Per entry in triangle order, the pull it receives.
    raw_pull: Vec<[f64; 2]>,
    /// Running sums over the pixel's entries.
    prefix: Vec<Sums>,
    /// Per entry: the pulls of the points whose own pass it belongs to, as a difference array.
    own_pull: Vec<[f64; 2]>,
    stats: &'s mut TileStats,
    sink: &'s mut S,
}

impl<S: LatentSink> PixelOutputs<'_, S> {
    /// Each of the pixel's points: its other passes (all entries but its own pass's run), its
    /// latent height, and the pulls its residual sends to those entries' triangles.
    fn read(&mut self, t: &Triangles, pixel: &Pixel, vehicle: Option<&[[f64; 2]]>, pulls: Option<ItemPull>) {
        let pixel_entries = pixel.entries;
        let (centre, w) = (pixel.centre, pixel.w);
        self.prefix.clear();
        self.prefix.push(Sums::default());
        for (k, e) in pixel_entries.iter().enumerate() {
            let next = self.prefix[k].plus(e);
            self.prefix.push(next);
        }
        let all = self.prefix[pixel_entries.len()];
        if pulls.is_some() {
            self.own_pull.clear();
            self.own_pull.resize(pixel_entries.len() + 1, [0.0; 2]);
        }
        let mut total_pull = [0.0f64; 2];
        // The own-pass run [lo, hi) of the current point: entries are sorted by chunk
        // and anchor, so are the points, and both bounds only move forward.
        let (mut lo, mut hi) = (0usize, 0usize);
        let key = |e: &Entry| (e.chunk, e.anchor);
        for item in pixel.items {
            let Item { chunk, anchor, u, v, h, .. } = *item;
            let a = item.point as usize;
            let below = (chunk, anchor.saturating_sub(SAME_PASS_ANCHORS - 1));
            while lo < pixel_entries.len() && key(&pixel_entries[lo]) < below {
                lo += 1;
            }
            hi = hi.max(lo);
            let above = (chunk, anchor.saturating_add(SAME_PASS_ANCHORS - 1));
            while hi < pixel_entries.len() && key(&pixel_entries[hi]) <= above {
                hi += 1;
            }
            let other = all.minus(&self.prefix[hi].minus(&self.prefix[lo]));
            if other.count == 0.0 {
                continue;
            }
            let c = other.count;
            let (gx, gy) = (other.hx / c, other.hy / c);
            // The other passes' heights carried from the centre to the point along
            // their mean slope.
            let step = gx * (u - centre[0]) + gy * (v - centre[1]);
            let sum = other.h + c * step;
            let sum2 = other.h2 + 2.0 * step * other.h + c * step * step;
            let mean = (h + sum) / (c + 1.0);
            let var = ((h * h + sum2) / (c + 1.0) - mean * mean).max(0.0);
            self.stats.pixels_shared += 1;
            self.stats.pixel_std_sum_m += var.sqrt();
            let usable = gx * gx + gy * gy <= MAX_SLOPE * MAX_SLOPE;
            if S::RECORDS {
                self.sink.add(&LatentSample {
                    position: lifted(&t.position[a], w, mean - h),
                    normal: w,
                    residual_m: h - mean,
                    std_m: var.sqrt(),
                    passes: c as u32 + 1,
                    used: usable,
                });
            }
            if !usable {
                continue;
            }
            let others = match vehicle {
                Some(_) => [other.vehicle[0] / c, other.vehicle[1] / c, c / (c + 1.0)],
                None => [0.0; 3],
            };
            self.points[a] = PointLatent { height: mean, others, covering: c as u32 };
            if let Some(ItemPull { threshold, weight }) = pulls {
                let e = h - mean;
                if e.abs() <= threshold {
                    let alpha = weight / (c + 1.0);
                    let pull = [alpha, alpha * e];
                    for k in 0..2 {
                        total_pull[k] += pull[k];
                        self.own_pull[lo][k] += pull[k];
                        self.own_pull[hi][k] -= pull[k];
                    }
                }
            }
        }
        if pulls.is_some() && total_pull[0] > 0.0 {
            // Entry k receives the pulls of every point it was another pass to.
            let mut own = [0.0f64; 2];
            for (k, e) in pixel_entries.iter().enumerate() {
                own[0] += self.own_pull[k][0];
                own[1] += self.own_pull[k][1];
                self.raw_pull[e.raw as usize] = [total_pull[0] - own[0], total_pull[1] - own[1]];
            }
        }
    }
}

/// The pulls by corner (step 6), in triangle order (corners rise): a corner's own model in one
/// sum per point, triangles on another model as separate entries, already sorted.
fn corner_pulls(t: &Triangles, corner_model: &[(u32, u32)], raw_pull: &[[f64; 2]]) -> CornerPulls {
    let mut sums = vec![[0.0f64; 2]; t.position.len()];
    let mut other_models = Vec::new();
    for (&(corner, model), &pull) in corner_model.iter().zip(raw_pull) {
        if pull[0] <= 0.0 {
            continue;
        }
        let corner = corner as usize;
        if t.model_of[corner] == model {
            sums[corner][0] += pull[0];
            sums[corner][1] += pull[1];
        } else {
            other_models.push((corner, model, pull));
        }
    }
    CornerPulls { sums, other_models, next_other: 0 }
}

#[cfg(test)]
mod tests {
    use super::counting_sort;

    /// The counting sort is a stable sort by key, and its starts bound each bucket.
    #[test]
    fn counting_sort_is_stable_and_its_starts_bound_the_buckets() {
        // A fixed pseudo-random sequence (an LCG), with empty buckets and runs of equal keys.
        let mut state = 12345u64;
        for (len, buckets) in [(0usize, 1usize), (1, 1), (7, 3), (1000, 17), (5000, 4096)] {
            let keys: Vec<u32> = (0..len)
                .map(|_| {
                    state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                    ((state >> 33) % buckets as u64) as u32
                })
                .collect();
            let mut sorted = vec![usize::MAX; len];
            let start = counting_sort(keys.iter().copied(), buckets, |at, i| sorted[at] = i);
            let mut expected: Vec<usize> = (0..len).collect();
            expected.sort_by_key(|&i| keys[i]);
            assert_eq!(sorted, expected, "{len} keys in {buckets} buckets");
            assert_eq!(start.len(), buckets + 1);
            assert_eq!((start[0], start[buckets] as usize), (0, len));
            for b in 0..buckets {
                let run = &sorted[start[b] as usize..start[b + 1] as usize];
                assert!(run.iter().all(|&i| keys[i] == b as u32), "bucket {b} of {buckets}");
                assert_eq!(run.len(), keys.iter().filter(|&&k| k == b as u32).count());
            }
        }
    }
}
