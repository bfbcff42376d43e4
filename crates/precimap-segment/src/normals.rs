//! Per-pixel normals from the pixel's scan-image neighbourhood.
//!
//! RANSAC: plane hypotheses through the centre point and two neighbours, scored by their MSAC
//! cost (Torr & Zisserman: each neighbour costs its squared distance, at most the squared inlier
//! tolerance), refined by a least-squares (PCA) fit to the inliers of the best one. At a sharp
//! edge (curb, façade corner) the pixel's own side of the edge wins, so the normal stays that
//! side's normal; a least-squares fit to the whole window (the [`NormalMethod::LeastSquares`]
//! variant, kept for comparison) tilts towards the other side. Scoring by the inlier count alone
//! (instead of MSAC's cost) lets a plane tilted across a step tie with the pixel's own plane: at the
//! simulator's 1.5° angular step a curb seen at grazing incidence is a 13 cm rise over metres
//! between two profile samples, and both planes can hold as many neighbours within the tolerance;
//! the tilted one holds them worse.

use crate::image::{dist, ScanImage, DROPPED, NO_POINT};
use crate::{SegmentParams, StripGeometry};

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NormalMethod {
    Ransac,
    LeastSquares,
}

/// A pixel's normal (unit, facing the scanner), the longest image edge from it that still counts
/// as continuous surface, and its plane tolerance (metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelNormal {
    pub normal: [f32; 3],
    pub edge_limit: f32,
    pub tolerance: f32,
}

/// Most grazing incidence at which a surface is still followed (cos 0.15 ≈ 81°).
const MIN_INCIDENCE_COS: f64 = 0.15;
/// Longest step (rows) between the window's pixels along the profile.
const MAX_STRIDE: i64 = 16;
/// Plane hypotheses tried per pixel.
const HYPOTHESES: u32 = 16;
/// Largest neighbourhood (3×3 ring plus 4 axial pixels per step out to half-width 8).
const MAX_NEIGHBOURS: usize = 8 + 4 * 7;
/// Neighbours scored together (one SSE register of f32).
const LANES: usize = 4;
// The lane groups must fit the candidate arrays, and the inlier masks a u64.
const _: () = assert!(MAX_NEIGHBOURS.is_multiple_of(LANES) && MAX_NEIGHBOURS < 64);
/// A hypothesis plane through the centre and neighbours a, b needs sin∠(a, b) ≥ 0.25.
const MIN_SIN2: f32 = 0.25 * 0.25;
/// Inverse-iteration steps of the final least-squares fit (each shrinks the angle to the
/// least-squares normal by the ratio of the two smallest scatter eigenvalues, < 0.1 for a plane).
const REFINE_STEPS: usize = 3;

/// A neighbour in the image window.
#[derive(Clone, Copy, Debug)]
struct Offset {
    /// Column and row offset.
    dc: i64,
    dr: i64,
    /// Chebyshev ring (1 or the axial distance): the gate grows with it.
    ring: usize,
}

/// Candidate neighbours of one pixel, relative to the centre point, struct of arrays (f32: the
/// offsets are under a few metres, so f32 keeps them to a micrometre).
struct Candidates {
    x: [f32; MAX_NEIGHBOURS],
    y: [f32; MAX_NEIGHBOURS],
    z: [f32; MAX_NEIGHBOURS],
    /// Squared length.
    len2: [f32; MAX_NEIGHBOURS],
    m: usize,
    /// Per window offset, its candidate's index or [`ABSENT`].
    slot: [u8; MAX_NEIGHBOURS],
}

impl Candidates {
    fn new() -> Self {
        Self {
            x: [0.0; MAX_NEIGHBOURS],
            y: [0.0; MAX_NEIGHBOURS],
            z: [0.0; MAX_NEIGHBOURS],
            len2: [0.0; MAX_NEIGHBOURS],
            m: 0,
            slot: [ABSENT; MAX_NEIGHBOURS],
        }
    }

    /// The number of candidates, as a bound the compiler can see (`m` never exceeds it): the
    /// loops over them index the arrays without bounds checks.
    #[inline]
    fn len(&self) -> usize {
        self.m.min(MAX_NEIGHBOURS)
    }

    #[inline]
    fn point(&self, i: usize) -> [f32; 3] {
        [self.x[i], self.y[i], self.z[i]]
    }

    /// Bit i set: neighbour i lies within `tol` of the plane through the centre with
    /// (unnormalised) normal `n`; and the number of inliers, centre included (counted alongside:
    /// cheaper than a population count without the POPCNT instruction of the baseline target).
    /// The same test as [`Self::scored`], neighbour by neighbour: run for a hypothesis's winner
    /// only, not for every hypothesis.
    #[inline]
    fn inliers_counted(&self, n: [f32; 3], tol: f32) -> (u64, u32) {
        let limit = tol * tol * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        let (mut mask, mut count) = (0u64, 1u32);
        for i in 0..self.len() {
            let d = n[0] * self.x[i] + n[1] * self.y[i] + n[2] * self.z[i];
            let inlier = d * d <= limit;
            mask |= (inlier as u64) << i;
            count += inlier as u32;
        }
        (mask, count)
    }

    /// The number of inliers of [`Self::inliers_counted`] and the plane's MSAC cost
    /// `Σ min(d², tol²)` over the neighbours (in units of |n|², which one hypothesis shares:
    /// comparable between hypotheses only after the division at the end).
    ///
    /// In groups of [`LANES`] neighbours with a count and a partial cost per lane, which the
    /// compiler keeps in vector registers: the inlier mask's variable shifts, one sum in
    /// candidate order (a chain of dependent adds), and `f32::min` (which must return the number
    /// when one side is NaN: a compare, a select and a NaN test) kept the loop scalar. Lanes from
    /// `m` to the group's end read the zeros [`Self::close`] wrote: they cost nothing and count as
    /// inliers, which is taken off again.
    #[inline]
    fn scored(&self, n: [f32; 3], tol: f32) -> (u32, f32) {
        let norm2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
        let limit = tol * tol * norm2;
        let mut count = [0u32; LANES];
        let mut cost = [0.0f32; LANES];
        for group in 0..self.len().div_ceil(LANES) {
            for lane in 0..LANES {
                let i = group * LANES + lane;
                let d = n[0] * self.x[i] + n[1] * self.y[i] + n[2] * self.z[i];
                let d2 = d * d;
                count[lane] += (d2 <= limit) as u32;
                // Both sides are finite: a plain select is the minimum.
                cost[lane] += if d2 < limit { d2 } else { limit };
            }
        }
        let padding = (self.m.next_multiple_of(LANES) - self.m) as u32;
        let inliers = 1 + count.iter().sum::<u32>() - padding;
        let total = (cost[0] + cost[1]) + (cost[2] + cost[3]);
        (inliers, total / norm2)
    }

    /// Zeroes the lanes from `m` to the end of its group (see [`Self::scored`]).
    #[inline]
    fn close(&mut self) {
        for i in self.m..self.m.next_multiple_of(LANES) {
            (self.x[i], self.y[i], self.z[i]) = (0.0, 0.0, 0.0);
        }
    }

    /// Scatter sums of the centre and every neighbour: [`Self::scatter`] with every bit set (the
    /// same sums in the same order), without walking a mask.
    fn scatter_all(&self) -> Scatter {
        Scatter::of((0..self.len()).map(|i| self.point(i)))
    }

    /// Scatter sums of the centre and the neighbours in `mask`.
    fn scatter(&self, mut mask: u64) -> Scatter {
        Scatter::of(std::iter::from_fn(|| {
            (mask != 0).then(|| {
                let i = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                self.point(i)
            })
        }))
    }
}

/// Normals of every point of the image (`None` for dropped points and failed fits).
pub fn estimate_normals(
    geo: &StripGeometry<'_>,
    image: &ScanImage,
    grid: &[u32],
    params: &SegmentParams,
) -> Vec<Option<PixelNormal>> {
    let rows = image.rows as usize;
    let columns = image.columns as usize;
    let advance = column_advance(geo, grid, rows, columns);
    let w = params.window.clamp(1, 8) as i64;
    let offsets = window_offsets(w, rows);
    let pairs = structured_pairs(&offsets);
    // At fine angular steps neighbouring measurements of a profile lie closer together than the
    // noise: a window a few beam spacings long along the profile holds a blob, not a plane (0.3°
    // steps and 5 mm noise left 27 % of the road without a normal). The window therefore steps
    // `stride` rows along the profile, enough for its first ring to span twice the inlier
    // tolerance; never so far that it meets the centre's revolution again.
    let max_stride = ((rows as i64 - 1) / (2 * w)).clamp(1, MAX_STRIDE);
    // Pixel-index step of each offset per stride, for windows that neither wrap nor leave the image.
    let steps_by_stride: Vec<Vec<isize>> = (1..=max_stride)
        .map(|stride| offsets.iter().map(|o| (o.dc * rows as i64 + o.dr * stride) as isize).collect())
        .collect();
    let coords = pixel_coords(geo, grid);
    let outside = grid.len();
    // Per offset, as fixed-size arrays and bit sets (the gathering below indexes them without
    // bounds checks): its window pixel, its ring, and whether it lies along the profile (same
    // column) or across it (same row).
    let count = offsets.len().min(MAX_NEIGHBOURS);
    let mut pixel = [outside; MAX_NEIGHBOURS];
    let mut ring_of = [0usize; MAX_NEIGHBOURS];
    let (mut along_bits, mut across_bits) = (0u64, 0u64);
    for (index, o) in offsets.iter().enumerate().take(count) {
        ring_of[index] = o.ring;
        along_bits |= u64::from(o.dc == 0) << index;
        across_bits |= u64::from(o.dr == 0) << index;
    }
    let window = Window {
        offsets: &offsets,
        steps_by_stride,
        rows: rows as i64,
        columns: columns as i64,
        w,
        outside,
        wraps: image.wraps,
    };
    let mut out = Vec::with_capacity(geo.len());
    let mut cand = Candidates::new();
    let budget = Budget::new();
    // Indexed by ring (≤ 8): sized to a power of two so that a masked ring needs no bounds check.
    let mut reach2 = [0.0f64; 16];
    for k in 0..geo.len() {
        let c = image.column[k];
        if c == DROPPED {
            out.push(None);
            continue;
        }
        let (c, r) = (c as i64, image.row[k] as i64);
        let p = geo.point(k);
        let head = geo.head[k];
        let range = dist(p, head);
        let along = range * image.angle_step_rad;
        // A ring image's columns are also apart by the azimuth step (0 for a profile head).
        let across = advance[c as usize] + range * image.column_step_rad;
        // Candidates for the fit: gaps up to those of a surface seen at grazing incidence
        // (cos ≥ MIN_INCIDENCE_COS); the RANSAC fit sorts out which lie on the pixel's plane.
        let gate = params.gap_factor * (along / MIN_INCIDENCE_COS).max(across).max(0.005) + params.gap_base_m;
        for (ring, r2) in reach2.iter_mut().enumerate().take(w as usize + 1).skip(1) {
            *r2 = (gate * ring as f64).powi(2);
        }
        let tol = params.inlier_base_m + params.inlier_per_range * range;
        let stride = if along > 0.0 { ((2.0 * tol / along).ceil() as i64).clamp(1, max_stride) } else { 1 };
        cand.m = 0;
        window.fill(&mut pixel[..count], c, r, stride);
        // Offsets kept, as bits.
        let mut kept = 0u64;
        for index in 0..count {
            // Without branches on the data (holes and gaps are hard to predict): every neighbour
            // is written, but only a kept one advances `m`; a hole's or an outside pixel's NaN
            // gap is never within reach.
            let q = coords[pixel[index]];
            let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
            let len2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            let keep = len2 <= reach2[ring_of[index] & 15];
            // `m` ≤ `index` < MAX_NEIGHBOURS: the bound only spares the compiler's checks.
            let i = cand.m.min(MAX_NEIGHBOURS - 1);
            cand.slot[index] = if keep { i as u8 } else { ABSENT };
            cand.x[i] = d[0] as f32;
            cand.y[i] = d[1] as f32;
            cand.z[i] = d[2] as f32;
            cand.len2[i] = len2 as f32;
            cand.m += keep as usize;
            kept |= u64::from(keep) << index;
        }
        let (has_along, has_across) = (kept & along_bits != 0, kept & across_bits != 0);
        if cand.m + 1 < params.min_inliers as usize || !(has_along && has_across) {
            out.push(None);
            continue;
        }
        cand.close();
        let normal = match params.method {
            NormalMethod::LeastSquares => plane_fit((0..cand.m).map(|i| cand.point(i))),
            NormalMethod::Ransac => ransac(&cand, tol as f32, k as u64, params.min_inliers, &budget, &pairs),
        };
        let Some(mut n) = normal else {
            out.push(None);
            continue;
        };
        let to_point = [p[0] - head[0], p[1] - head[1], p[2] - head[2]];
        let along_n = n[0] * to_point[0] + n[1] * to_point[1] + n[2] * to_point[2];
        if along_n > 0.0 {
            n = [-n[0], -n[1], -n[2]];
        }
        // C0: the longest continuous edge is the beam spacing on this surface (stretched by the
        // incidence angle) or the advance per revolution, times the gap factor.
        let cos_incidence = (along_n.abs() / range.max(1e-9)).max(MIN_INCIDENCE_COS);
        let limit = params.gap_factor * (along / cos_incidence).max(across).max(0.005) + params.gap_base_m;
        out.push(Some(PixelNormal {
            normal: [n[0] as f32, n[1] as f32, n[2] as f32],
            edge_limit: limit as f32,
            tolerance: tol as f32,
        }));
    }
    out
}

/// Scan-head advance per revolution at every column of the image: the larger distance to the
/// neighbouring columns' heads, each from the first point of its column.
fn column_advance(geo: &StripGeometry<'_>, grid: &[u32], rows: usize, columns: usize) -> Vec<f64> {
    let mut column_head: Vec<Option<[f64; 3]>> = vec![None; columns];
    for c in 0..columns {
        column_head[c] = grid[c * rows..(c + 1) * rows].iter().find(|&&k| k != NO_POINT).map(|&k| geo.head[k as usize]);
    }
    (0..columns)
        .map(|c| {
            let h = column_head[c];
            let d = |o: Option<&Option<[f64; 3]>>| match (h, o.copied().flatten()) {
                (Some(a), Some(b)) => dist(a, b),
                _ => 0.0,
            };
            d(c.checked_sub(1).map(|i| &column_head[i])).max(d(column_head.get(c + 1)))
        })
        .collect()
}

/// The window's neighbour offsets for a half-width `w` in an image of `rows` rows.
fn window_offsets(w: i64, rows: usize) -> Vec<Offset> {
    // The neighbourhood: the 3×3 ring plus the pixels along the row and the column out to the
    // window's half-width (a cross-shaped 5×5 window has 12 neighbours instead of 24: half the
    // cost, and still both directions at two scales). Rows wrap around (the revolution is a
    // circle), but a window taller than the image would meet the centre's own revolution again.
    let mut offsets: Vec<Offset> = Vec::new();
    for dc in -1..=1 {
        for dr in -1..=1 {
            if (dc, dr) != (0, 0) {
                offsets.push(Offset { dc, dr, ring: 1 });
            }
        }
    }
    for d in 2..=w {
        for (dc, dr) in [(d, 0), (-d, 0), (0, d), (0, -d)] {
            offsets.push(Offset { dc, dr, ring: d as usize });
        }
    }
    offsets.retain(|o| (o.dr.unsigned_abs() as usize) < rows);
    offsets
}

/// The coordinates in pixel order, holes NaN, and one NaN entry past the end that window pixels
/// outside the image read. A neighbour is then one load away from its pixel (not two, through
/// the grid) and a profile's neighbours are adjacent in memory; a hole's NaN gap fails the reach
/// test, so holes need no test of their own.
fn pixel_coords(geo: &StripGeometry<'_>, grid: &[u32]) -> Vec<[f64; 3]> {
    let mut coords = vec![[f64::NAN; 3]; grid.len() + 1];
    for (q, &j) in coords.iter_mut().zip(grid) {
        if j != NO_POINT {
            *q = geo.point(j as usize);
        }
    }
    coords
}

/// The window of a pixel's neighbours in the image: its offsets, their pixel-index steps per
/// stride, and what the edges do.
struct Window<'a> {
    offsets: &'a [Offset],
    /// Pixel-index step of each offset per stride, for windows that neither wrap nor leave the
    /// image.
    steps_by_stride: Vec<Vec<isize>>,
    rows: i64,
    columns: i64,
    /// Half-width.
    w: i64,
    /// The pixel past the end (a NaN entry of the coordinates).
    outside: usize,
    /// Rows wrap around (the revolution is a circle).
    wraps: bool,
}

impl Window<'_> {
    /// The window's pixels around column `c`, row `r` with rows `stride` apart, one per offset:
    /// away from the image's edges (nearly every pixel) a fixed step from the centre's, else with
    /// the columns checked and the rows wrapped.
    #[inline]
    fn fill(&self, pixel: &mut [usize], c: i64, r: i64, stride: i64) {
        let centre = c as usize * self.rows as usize + r as usize;
        let reach_rows = self.w * stride;
        if c >= self.w && c + self.w < self.columns && r >= reach_rows && r + reach_rows < self.rows {
            for (px, &step) in pixel.iter_mut().zip(&self.steps_by_stride[stride as usize - 1]) {
                *px = centre.wrapping_add_signed(step);
            }
        } else {
            for (px, o) in pixel.iter_mut().zip(self.offsets) {
                let cc = c + o.dc;
                let mut rr = r + o.dr * stride;
                let beyond = rr < 0 || rr >= self.rows;
                if rr < 0 {
                    rr += self.rows;
                } else if rr >= self.rows {
                    rr -= self.rows;
                }
                *px = if cc < 0 || cc >= self.columns || (beyond && !self.wraps) {
                    self.outside
                } else {
                    cc as usize * self.rows as usize + rr as usize
                };
            }
        }
    }
}

/// The plane through the origin (a centre point) and neighbours `rel` (relative to it, at most
/// [`MAX_NEIGHBOURS`]; more are ignored), by `method`, with the planarity test of the scan-image
/// fit: the normal of a point whose neighbours come from somewhere other than a scan image.
pub(crate) fn fit_neighbourhood(
    rel: &[[f32; 3]],
    tol: f32,
    seed: u64,
    params: &SegmentParams,
    budget: &Budget,
) -> Option<[f64; 3]> {
    let mut cand = Candidates::new();
    for q in rel.iter().take(MAX_NEIGHBOURS) {
        let i = cand.m;
        (cand.x[i], cand.y[i], cand.z[i]) = (q[0], q[1], q[2]);
        cand.len2[i] = q[0] * q[0] + q[1] * q[1] + q[2] * q[2];
        cand.slot[i] = i as u8;
        cand.m += 1;
    }
    if cand.m + 1 < params.min_inliers as usize {
        return None;
    }
    cand.close();
    match params.method {
        NormalMethod::LeastSquares => plane_fit((0..cand.m).map(|i| cand.point(i))),
        NormalMethod::Ransac => ransac(&cand, tol, seed, params.min_inliers, budget, &[]),
    }
}

/// Most neighbours [`fit_neighbourhood`] uses.
pub(crate) const MAX_FIT_NEIGHBOURS: usize = MAX_NEIGHBOURS;

/// RANSAC's adaptive stopping rule: once the best plane holds a share w of the neighbours, a
/// further hypothesis is all-inlier with probability ≈ w², so after N = ln(1 − p) / ln(1 − w²)
/// hypotheses one of them was with probability p = 99 %: more would most likely find the same
/// plane again (a pixel next to an edge, whose own side has 50–75 % of the window).
pub(crate) struct Budget {
    /// `[m][inliers]` → hypotheses, at most [`HYPOTHESES`].
    table: Vec<[u32; MAX_NEIGHBOURS + 2]>,
}

impl Budget {
    const CONFIDENCE: f64 = 0.99;

    pub(crate) fn new() -> Self {
        let table = (0..=MAX_NEIGHBOURS)
            .map(|m| {
                let mut row = [HYPOTHESES; MAX_NEIGHBOURS + 2];
                for (inliers, n) in row.iter_mut().enumerate().take(m + 2).skip(1) {
                    // Inliers count the centre; the pair is drawn from the m neighbours.
                    let w = (inliers - 1) as f64 / m.max(1) as f64;
                    let all_inlier = w * w;
                    *n = if all_inlier >= 1.0 {
                        1
                    } else if all_inlier > 0.0 {
                        let need = ((1.0 - Self::CONFIDENCE).ln() / (1.0 - all_inlier).ln()).ceil();
                        (need as u32).clamp(1, HYPOTHESES)
                    } else {
                        HYPOTHESES
                    };
                }
                row
            })
            .collect();
        Self { table }
    }

    #[inline]
    fn hypotheses(&self, m: usize, inliers: u32) -> u32 {
        self.table[m][inliers as usize]
    }
}

/// Best plane through the origin (the centre point) and two neighbours, refined on its inliers.
///
/// Pairs: first the image-structured `pairs` (indices into the window's offsets, resolved to
/// candidates through `cand.slot`; see [`structured_pairs`]), then pairs from a xorshift
/// generator seeded by the point index (deterministic), drawn without division and never the same
/// neighbour twice. A hypothesis costs a cross product and one multiply–add per neighbour: the
/// inlier test compares squared distances against the unnormalised normal, so there is no square
/// root in the loop and one division per hypothesis. The winner is the plane of least MSAC cost
/// among those with at least `min_inliers` inliers. It stops at the first best plane that most
/// (80 %) of the neighbours lie on, or by the adaptive rule of [`Budget`] (fed the most inliers
/// seen, the estimate of the inlier share). The winner is refined by a least-squares fit to
/// its inliers, and once more to the inliers of that fit if they differ and are not fewer (the
/// "local optimisation" of LO-RANSAC: the result depends little on which noisy triple won).
fn ransac(
    cand: &Candidates,
    tol: f32,
    seed: u64,
    min_inliers: u32,
    budget: &Budget,
    pairs: &[(u8, u8)],
) -> Option<[f64; 3]> {
    let m = cand.m;
    if m < 2 {
        return None;
    }
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = |bound: usize| -> usize {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        // Lemire's multiply–shift: uniform enough for a dozen candidates, and no division.
        (((state >> 32) * bound as u64) >> 32) as usize
    };
    let all = m as u32 + 1;
    let good = (4 * all).div_ceil(5);
    // (normal, inliers, MSAC cost) of the best hypothesis so far.
    let mut best: Option<([f32; 3], u32, f32)> = None;
    // The most inliers any hypothesis had: what the adaptive stopping rule estimates from.
    let mut most = 0;
    let mut enough = HYPOTHESES;
    let mut tried = 0;
    let mut structured = pairs.iter();
    while tried < enough {
        let (i, j) = match structured.next() {
            Some(&(a, b)) => {
                let (i, j) = (cand.slot[a as usize], cand.slot[b as usize]);
                if i == ABSENT || j == ABSENT {
                    continue;
                }
                (i as usize, j as usize)
            }
            None => {
                let i = next(m);
                let j = next(m - 1);
                (i, if j >= i { j + 1 } else { j })
            }
        };
        tried += 1;
        let (a, b) = (cand.point(i), cand.point(j));
        let n = cross32(a, b);
        // Nearly collinear with the centre: no plane.
        if n[0] * n[0] + n[1] * n[1] + n[2] * n[2] < MIN_SIN2 * cand.len2[i] * cand.len2[j] {
            continue;
        }
        let (inliers, cost) = cand.scored(n, tol);
        if inliers > most {
            most = inliers;
            enough = budget.hypotheses(m, inliers);
        }
        // MSAC: of the planes with enough inliers to give a normal, the one the neighbours lie
        // closest to (below that, the most inliers, as a fit that fails anyway).
        let better = best.is_none_or(|(_, best_inliers, best_cost)| {
            let (eligible, best_eligible) = (inliers >= min_inliers, best_inliers >= min_inliers);
            if eligible != best_eligible {
                eligible
            } else if eligible {
                cost < best_cost
            } else {
                inliers > best_inliers
            }
        });
        if better {
            best = Some((n, inliers, cost));
            // A plane through the centre that most neighbours lie on is the centre's plane.
            if inliers >= good {
                break;
            }
        }
    }
    let (n, inliers, _) = best?;
    if inliers < min_inliers {
        return None;
    }
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    let start = [n[0] / len, n[1] / len, n[2] / len].map(f64::from);
    if inliers == all {
        // Every neighbour already (the count is `inliers_counted`'s test, neighbour by
        // neighbour): no mask to find, and the fit's inliers cannot be more.
        return cand.scatter_all().plane_from(start);
    }
    let (mask, _) = cand.inliers_counted(n, tol);
    let fitted = cand.scatter(mask).plane_from(start)?;
    let (refined, count) = cand.inliers_counted(fitted.map(|v| v as f32), tol);
    if refined == mask || count < inliers {
        return Some(fitted);
    }
    cand.scatter(refined).plane_from(fitted).or(Some(fitted))
}

/// Marks an offset of the window without a candidate.
const ABSENT: u8 = u8::MAX;

/// Well-conditioned pairs of window offsets for the first hypotheses, as indices into `offsets`:
/// one neighbour along the profile (same column) and one across (same row), at distance 2 (the
/// longest baselines: the least noisy planes) and then 1, in all four quadrants, then the
/// diagonal pairs. Next to an edge, at least one quadrant lies wholly on the centre's side.
fn structured_pairs(offsets: &[Offset]) -> Vec<(u8, u8)> {
    let index = |dc: i64, dr: i64| offsets.iter().position(|o| (o.dc, o.dr) == (dc, dr)).map(|i| i as u8);
    let mut pairs = Vec::new();
    let mut add = |a: (i64, i64), b: (i64, i64)| {
        if let (Some(i), Some(j)) = (index(a.0, a.1), index(b.0, b.1)) {
            pairs.push((i, j));
        }
    };
    for d in [2, 1] {
        add((0, d), (d, 0));
        add((0, -d), (-d, 0));
        add((0, d), (-d, 0));
        add((0, -d), (d, 0));
    }
    add((1, 1), (1, -1));
    add((-1, 1), (-1, -1));
    add((1, 1), (-1, 1));
    add((1, -1), (-1, -1));
    pairs.truncate(HYPOTHESES as usize);
    pairs
}

#[inline]
fn cross32(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// Sums of the centre (the origin) and the added points, for a least-squares plane.
struct Scatter {
    count: f64,
    s: [f64; 3],
    ss: [f64; 6],
}

impl Scatter {
    fn new() -> Self {
        Self { count: 1.0, s: [0.0; 3], ss: [0.0; 6] }
    }

    /// The centre and `points`, added in order.
    #[inline]
    fn of(points: impl Iterator<Item = [f32; 3]>) -> Self {
        let mut sums = Self::new();
        for q in points {
            sums.add(q);
        }
        sums
    }

    #[inline]
    fn add(&mut self, q: [f32; 3]) {
        let q = q.map(f64::from);
        self.count += 1.0;
        for a in 0..3 {
            self.s[a] += q[a];
        }
        self.ss[0] += q[0] * q[0];
        self.ss[1] += q[0] * q[1];
        self.ss[2] += q[0] * q[2];
        self.ss[3] += q[1] * q[1];
        self.ss[4] += q[1] * q[2];
        self.ss[5] += q[2] * q[2];
    }

    /// Scatter about the mean, `[a00 a01 a02 a11 a12 a22]`.
    fn covariance(&self) -> [f64; 6] {
        let (count, s, ss) = (self.count, self.s, self.ss);
        let inv = 1.0 / count;
        let m = s.map(|v| v * inv);
        [
            ss[0] - count * m[0] * m[0],
            ss[1] - count * m[0] * m[1],
            ss[2] - count * m[0] * m[2],
            ss[3] - count * m[1] * m[1],
            ss[4] - count * m[1] * m[2],
            ss[5] - count * m[2] * m[2],
        ]
    }

    /// The least-squares plane's normal by inverse iteration from `start` (a unit vector near it):
    /// the adjugate of the scatter has the scatter's eigenvectors with eigenvalues
    /// (λ1λ2, λ0λ2, λ0λ1), so each product with it shrinks the angle to the smallest-eigenvalue
    /// direction by λ0/λ1. The eigenvalues for the planarity test follow from the Rayleigh
    /// quotient (λ0), the trace and the sum of the principal 2×2 minors. No trigonometry, and
    /// no scaling of the scatter first: the direction and the eigenvalue ratios the test uses do
    /// not depend on scale, and a division at the head of this chain of dependent steps (its
    /// cost is latency, not throughput) made the normal phase ~10 % slower.
    fn plane_from(&self, start: [f64; 3]) -> Option<[f64; 3]> {
        let c = self.covariance();
        let trace = c[0] + c[3] + c[5];
        if trace.is_nan() || trace <= 1e-300 {
            return None;
        }
        let [a00, a01, a02, a11, a12, a22] = c;
        let adj = [
            a11 * a22 - a12 * a12,
            a02 * a12 - a01 * a22,
            a01 * a12 - a02 * a11,
            a00 * a22 - a02 * a02,
            a01 * a02 - a00 * a12,
            a00 * a11 - a01 * a01,
        ];
        let mut v = start;
        for _ in 0..REFINE_STEPS {
            v = [
                adj[0] * v[0] + adj[1] * v[1] + adj[2] * v[2],
                adj[1] * v[0] + adj[3] * v[1] + adj[4] * v[2],
                adj[2] * v[0] + adj[4] * v[1] + adj[5] * v[2],
            ];
        }
        // Each step scales by up to trace²: degenerate is small against that.
        let scale = trace * trace;
        let len = norm(v);
        if !(len.is_finite() && len > 1e-200 * scale * scale * scale) {
            return None;
        }
        let inv = 1.0 / len;
        let n = v.map(|x| x * inv);
        // Eigenvalues of the scatter: λ0 + λ1 + λ2 = trace.
        let l0 = a00 * n[0] * n[0]
            + a11 * n[1] * n[1]
            + a22 * n[2] * n[2]
            + 2.0 * (a01 * n[0] * n[1] + a02 * n[0] * n[2] + a12 * n[1] * n[2]);
        let minors = adj[0] + adj[3] + adj[5];
        let rest = trace - l0;
        let product = minors - l0 * rest;
        let half_gap = (0.25 * rest * rest - product).max(0.0).sqrt();
        let (l1, l2) = (0.5 * rest - half_gap, 0.5 * rest + half_gap);
        planar(l0, l1, l2).then_some(n)
    }
}

/// A line (second extent under 1 % of the first) or a blob is no plane.
#[inline]
fn planar(l0: f64, l1: f64, l2: f64) -> bool {
    !(l1.is_nan() || l1 <= 1e-4 * l2 || l0 > 0.1 * l1)
}

/// Least-squares plane (smallest-eigenvalue direction of the scatter) of the centre (origin) and
/// the given points by the closed-form eigen-solver; `None` unless clearly planar (not a line,
/// not a blob). The [`NormalMethod::LeastSquares`] comparison.
fn plane_fit(pts: impl Iterator<Item = [f32; 3]>) -> Option<[f64; 3]> {
    let (l0, l1, l2, n) = smallest_eigen(Scatter::of(pts).covariance())?;
    planar(l0, l1, l2).then_some(n)
}

/// Eigenvalues (ascending) of the symmetric 3×3 matrix `[a00 a01 a02 a11 a12 a22]` and the unit
/// eigenvector of the smallest (closed form: trigonometric eigenvalues, the eigenvector
/// as the longest cross product of two rows of `A − λI`).
pub(crate) fn smallest_eigen(a: [f64; 6]) -> Option<(f64, f64, f64, [f64; 3])> {
    let [a00, a01, a02, a11, a12, a22] = a;
    let q = (a00 + a11 + a22) / 3.0;
    let p1 = a01 * a01 + a02 * a02 + a12 * a12;
    let p2 = (a00 - q).powi(2) + (a11 - q).powi(2) + (a22 - q).powi(2) + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    if p.is_nan() || p <= 1e-300 {
        return None;
    }
    let b = [(a00 - q) / p, a01 / p, a02 / p, (a11 - q) / p, a12 / p, (a22 - q) / p];
    let det =
        b[0] * (b[3] * b[5] - b[4] * b[4]) - b[1] * (b[1] * b[5] - b[4] * b[2]) + b[2] * (b[1] * b[4] - b[3] * b[2]);
    let phi = (det / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
    let l_max = q + 2.0 * p * phi.cos();
    let l_min = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
    let l_mid = 3.0 * q - l_max - l_min;
    let r0 = [a00 - l_min, a01, a02];
    let r1 = [a01, a11 - l_min, a12];
    let r2 = [a02, a12, a22 - l_min];
    let mut best = cross(r0, r1);
    for c in [cross(r0, r2), cross(r1, r2)] {
        if dot(c, c) > dot(best, best) {
            best = c;
        }
    }
    let len = norm(best);
    if len.is_nan() || len <= 0.0 {
        return None;
    }
    Some((l_min, l_mid, l_max, best.map(|v| v / len)))
}

#[inline]
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

#[inline]
fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

#[cfg(test)]
mod tests;
