//! The raster latent map of [`super::estimate_tile`]: every scan-image triangle rasterised into
//! a height raster per surface model, and a point's latent height read bilinearly from the
//! pixels around it ([`raster_latent`]).

use super::point::PointLatent;
use super::triangles::{PlaneTriangle, Triangles};
use super::{floor_i64, lifted, models::pass_tag, MAX_SLOPE, NONE};
use crate::latent::{LatentSample, LatentSink};
use crate::stats::TileStats;
use precimap_core::geom::floor;

/// Pixel tag once two different strip passes contributed.
const MULTI: u32 = u32::MAX;

/// A raster pixel: the heights of the triangles sampled at its centre (sum, sum of squares,
/// count), which passes they came from, and the sum of their scan heads (zeros without the
/// common-mode field). The scan heads are in the pixel, not in a column of their own: at 5 cm
/// a triangle writes ~6 pixels (small s1: 59.4 M writes from 10.2 M triangles into 6.5 MB of
/// rasters per tile), and one scattered write to 32 bytes instead of two to 16 made that pass
/// 1.09× faster.
#[derive(Clone, Copy, Default)]
pub(super) struct Pixel {
    pub(super) sum: f32,
    pub(super) sum2: f32,
    pub(super) count: u32,
    pub(super) tag: u32,
    pub(super) vehicle: [f64; 2],
}

impl Pixel {
    #[inline]
    pub(super) fn add(&mut self, h: f32, tag: u32, vehicle: [f64; 2]) {
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
    pub(super) fn shared(&self) -> bool {
        self.count > 0 && self.tag == MULTI
    }

    #[inline]
    pub(super) fn mean(&self) -> f64 {
        self.sum as f64 / self.count as f64
    }
}

/// One model's raster: pixel (i, j) has its centre at `u0 + (i + ½)·size`, `v0 + (j + ½)·size`,
/// and its index `offset + j·nu + i` in the tile's pixels.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct PixelGrid {
    pub(super) u0: f64,
    pub(super) v0: f64,
    pub(super) size: f64,
    pub(super) inv: f64,
    pub(super) nu: u32,
    pub(super) nv: u32,
    pub(super) offset: usize,
}

impl PixelGrid {
    /// The pixel holding `(u, v)` (clamped to the raster).
    #[inline]
    pub(super) fn pixel(&self, u: f64, v: f64) -> usize {
        let inv = self.inv;
        let i = floor_i64((u - self.u0) * inv).clamp(0, self.nu as i64 - 1) as usize;
        let j = floor_i64((v - self.v0) * inv).clamp(0, self.nv as i64 - 1) as usize;
        self.offset + j * self.nu as usize + i
    }

    /// The four pixel centres around `(u, v)` that bilinear interpolation reads; `None` unless
    /// all four lie in the raster. One look-up for every value read there (height, scan heads).
    #[inline]
    pub(super) fn cell(&self, u: f64, v: f64) -> Option<Cell> {
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
    pub(super) fn centres_under<'a>(&'a self, plane: &'a PlaneTriangle) -> Option<CentreBox<'a>> {
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
pub(super) struct CentreBox<'a> {
    pub(super) grid: &'a PixelGrid,
    pub(super) plane: &'a PlaneTriangle,
    /// The triangle's first corner in pixel coordinates (centre (i, j) at (i, j)).
    pub(super) xs: f64,
    pub(super) ys: f64,
    /// First and last column and row.
    pub(super) i: [i64; 2],
    pub(super) j: [i64; 2],
}

impl CentreBox<'_> {
    /// How far outside an edge (in barycentric coordinates) a centre still counts as inside:
    /// both walks take the same centres.
    const SLACK: f64 = -1e-9;

    /// How many centres [`Self::for_each`] visits.
    #[inline]
    pub(super) fn len(&self) -> usize {
        ((self.i[1] - self.i[0] + 1) * (self.j[1] - self.j[0] + 1)) as usize
    }

    /// `visit(pixel, height, inside)` for every centre in the box, row by row: its index in the
    /// tile's pixels, the plane's height there, and whether it lies in the triangle (by its
    /// barycentric coordinates, with 10⁻⁹ of slack). For triangles of about one centre (the
    /// pixel route's), whose box holds about two (4.46 per point): a caller can write every
    /// one without a branch.
    #[inline]
    pub(super) fn for_each(&self, mut visit: impl FnMut(usize, f64, bool)) {
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
    pub(super) fn for_each_inside(&self, mut visit: impl FnMut(usize, f64)) {
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
pub(super) fn ceil_i64(x: f64) -> i64 {
    let i = x as i64;
    i + ((i as f64) < x) as i64
}

/// The four pixel centres around a point that bilinear interpolation reads: the lower-left
/// one's index in the tile's pixels and the point's fractions of the way to the next column and
/// row ([`PixelGrid::cell`]).
#[derive(Clone, Copy, Debug)]
pub(super) struct Cell {
    pub(super) at: usize,
    pub(super) tu: f64,
    pub(super) tv: f64,
}

/// Latent height in `cell`, bilinear between its four pixel centres, all of which must be
/// shared by two or more strip passes. `None` also where the latent surface is steeper than
/// [`MAX_SLOPE`] against the model plane: there (curbs, recesses, occlusion edges) the distance
/// along the model normal does not measure the distance to the surface, and a lateral offset
/// between strips would be read as a height difference.
#[inline]
pub(super) fn latent_height(r: &PixelGrid, pixels: &[Pixel], cell: Cell) -> Option<f64> {
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

/// Latent heights from height rasters of pixel size `grid`: every triangle is rasterised into
/// the pixels of its models (heights interpolated at the pixel centres), and a point's latent
/// height is the bilinear interpolation of the four pixels around it ([`latent_height`]).
///
/// With `vehicle` it also gives, per point, the mean scan-head position of everything its
/// latent height averages (its own pass included, which makes the field's row
/// `φ(v) − φ(v̄)` carry the other passes' share by itself) and a share of 1, `[x, y, 1]`.
pub(super) fn raster_latent<S: LatentSink>(
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
pub(super) fn raster_std(r: &PixelGrid, pixels: &[Pixel], cell: Cell) -> (f64, u32) {
    let Cell { at, tu, tv } = cell;
    let p = &pixels[at + (tu >= 0.5) as usize + (tv >= 0.5) as usize * r.nu as usize];
    let n = p.count as f64;
    let mean = p.sum as f64 / n;
    ((p.sum2 as f64 / n - mean * mean).max(0.0).sqrt(), p.count)
}

/// Mean scan-head position of the contributions to the four pixels a point's latent height
/// interpolates, weighted like the heights (bilinear), as `[x, y, 1]`.
pub(super) fn raster_vehicle_mean(r: &PixelGrid, pixels: &[Pixel], cell: Cell) -> [f64; 3] {
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
