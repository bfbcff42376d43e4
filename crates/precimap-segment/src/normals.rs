//! Per-pixel normals from the pixel's scan-image neighbourhood.
//!
//! RANSAC: plane hypotheses through the centre point and two neighbours, scored by the number of
//! neighbours within the inlier tolerance, refined by a least-squares (PCA) fit to the inliers of
//! the best one. At a sharp edge (curb, façade corner) the pixel's own side of the edge wins, so
//! the normal stays that side's normal; a least-squares fit to the whole window (the
//! [`NormalMethod::LeastSquares`] variant, kept for comparison) tilts towards the other side.

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
/// Plane hypotheses tried per pixel.
const HYPOTHESES: u32 = 16;
/// Largest neighbourhood (3×3 ring plus 4 axial pixels per step out to half-width 8).
const MAX_NEIGHBOURS: usize = 8 + 4 * 7;

/// Normals of every point of the image (`None` for dropped points and failed fits).
pub fn estimate_normals(
    geo: &StripGeometry<'_>,
    image: &ScanImage,
    grid: &[u32],
    params: &SegmentParams,
) -> Vec<Option<PixelNormal>> {
    let rows = image.rows as usize;
    let columns = image.columns as usize;
    // Scan-head advance per revolution, from the first point of each column.
    let mut column_head: Vec<Option<[f64; 3]>> = vec![None; columns];
    for c in 0..columns {
        column_head[c] = grid[c * rows..(c + 1) * rows].iter().find(|&&k| k != NO_POINT).map(|&k| geo.head[k as usize]);
    }
    let advance: Vec<f64> = (0..columns)
        .map(|c| {
            let h = column_head[c];
            let d = |o: Option<&Option<[f64; 3]>>| match (h, o.copied().flatten()) {
                (Some(a), Some(b)) => dist(a, b),
                _ => 0.0,
            };
            d(c.checked_sub(1).map(|i| &column_head[i])).max(d(column_head.get(c + 1)))
        })
        .collect();
    // The neighbourhood: the 3×3 ring plus the pixels along the row and the column out to the
    // window's half-width (a cross-shaped 5×5 window has 12 neighbours instead of 24: half the
    // cost, and still both directions at two scales).
    let w = params.window.clamp(1, 8) as i64;
    let mut offsets: Vec<(i64, i64)> = Vec::new();
    for dc in -1..=1 {
        for dr in -1..=1 {
            if (dc, dr) != (0, 0) {
                offsets.push((dc, dr));
            }
        }
    }
    for d in 2..=w {
        offsets.extend([(d, 0), (-d, 0), (0, d), (0, -d)]);
    }
    let mut out = Vec::with_capacity(geo.len());
    let mut cand = [[0.0f64; 3]; MAX_NEIGHBOURS];
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
        let across = advance[c as usize];
        // Candidates for the fit: gaps up to those of a surface seen at grazing incidence
        // (cos ≥ MIN_INCIDENCE_COS); the RANSAC fit sorts out which lie on the pixel's plane.
        let gate = params.gap_factor * (along / MIN_INCIDENCE_COS).max(across).max(0.005) + params.gap_base_m;
        let tol = params.inlier_base_m + params.inlier_per_range * range;
        let mut m = 0usize;
        let (mut has_along, mut has_across) = (false, false);
        for &(dc, dr) in &offsets {
            // Rows wrap around: the last and the first measurement of a revolution are neighbours.
            let (cc, rr) = (c + dc, (r + dr).rem_euclid(rows as i64));
            if cc < 0 || cc >= columns as i64 || dr.unsigned_abs() as usize >= rows {
                continue;
            }
            let j = grid[cc as usize * rows + rr as usize];
            if j == NO_POINT {
                continue;
            }
            let q = geo.point(j as usize);
            let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
            let reach = gate * dc.abs().max(dr.abs()) as f64;
            if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= reach * reach {
                cand[m] = d;
                m += 1;
                has_along |= dc == 0;
                has_across |= dr == 0;
            }
        }
        if m + 1 < params.min_inliers as usize || !(has_along && has_across) {
            out.push(None);
            continue;
        }
        let pts = &cand[..m];
        let normal = match params.method {
            NormalMethod::LeastSquares => plane_fit(pts.iter()),
            NormalMethod::Ransac => ransac(pts, tol, k as u64, params.min_inliers),
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

/// Best plane through the origin (the centre point) and two neighbours, refined on its inliers.
fn ransac(pts: &[[f64; 3]], tol: f64, seed: u64, min_inliers: u32) -> Option<[f64; 3]> {
    let m = pts.len() as u64;
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let mut best: Option<([f64; 3], u32)> = None;
    for _ in 0..HYPOTHESES {
        let i = (next() % m) as usize;
        let j = (next() % m) as usize;
        if i == j {
            continue;
        }
        let (a, b) = (pts[i], pts[j]);
        let n = cross(a, b);
        let len = norm(n);
        // Nearly collinear with the centre: no plane.
        if len < 0.25 * norm(a) * norm(b) {
            continue;
        }
        let n = [n[0] / len, n[1] / len, n[2] / len];
        let inliers = 1 + pts.iter().filter(|q| dot(n, **q).abs() <= tol).count() as u32;
        if best.is_none_or(|(_, s)| inliers > s) {
            best = Some((n, inliers));
            // A plane through the centre that most neighbours lie on is the centre's plane.
            if inliers as usize * 5 >= (pts.len() + 1) * 4 {
                break;
            }
        }
    }
    let (n, inliers) = best?;
    if inliers < min_inliers {
        return None;
    }
    plane_fit(pts.iter().filter(|q| dot(n, **q).abs() <= tol))
}

/// Least-squares plane (smallest-eigenvalue direction of the scatter) of the centre (origin) and
/// the given points; `None` unless clearly planar (not a line, not a blob).
fn plane_fit<'a>(pts: impl Iterator<Item = &'a [f64; 3]>) -> Option<[f64; 3]> {
    // Sums about the centre (the origin), then the scatter about the mean.
    let (mut count, mut s, mut ss) = (1.0, [0.0; 3], [0.0; 6]);
    for q in pts {
        count += 1.0;
        for a in 0..3 {
            s[a] += q[a];
        }
        ss[0] += q[0] * q[0];
        ss[1] += q[0] * q[1];
        ss[2] += q[0] * q[2];
        ss[3] += q[1] * q[1];
        ss[4] += q[1] * q[2];
        ss[5] += q[2] * q[2];
    }
    let m = s.map(|v| v / count);
    let cov = [
        ss[0] - count * m[0] * m[0],
        ss[1] - count * m[0] * m[1],
        ss[2] - count * m[0] * m[2],
        ss[3] - count * m[1] * m[1],
        ss[4] - count * m[1] * m[2],
        ss[5] - count * m[2] * m[2],
    ];
    let (l0, l1, l2, n) = smallest_eigen(cov)?;
    // A line (second extent under 1 % of the first) or a blob is no plane.
    if l1.is_nan() || l1 <= 1e-4 * l2 || l0 > 0.1 * l1 {
        return None;
    }
    Some(n)
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
mod tests {
    use super::*;

    #[test]
    fn closed_form_eigenvector_of_a_plane_scatter() {
        // Points on the plane z = 0.1·x + 0.2·y, scattered along two directions.
        let mut pts = vec![];
        for i in -3..=3 {
            for j in -3..=3 {
                let (x, y) = (i as f64 * 0.1, j as f64 * 0.07);
                pts.push([x, y, 0.1 * x + 0.2 * y]);
            }
        }
        let n = plane_fit(pts.iter()).unwrap();
        let expect = [-0.1, -0.2, 1.0];
        let len = norm(expect);
        assert!((dot(n, expect).abs() / len - 1.0).abs() < 1e-9, "{n:?}");
        // A line is not a plane.
        let line: Vec<[f64; 3]> = (1..6).map(|i| [i as f64, 2.0 * i as f64, 0.0]).collect();
        assert!(plane_fit(line.iter()).is_none());
        // Eigenvalues of a diagonal matrix.
        let (l0, l1, _, v) = smallest_eigen([3.0, 0.0, 0.0, 1.0, 0.0, 2.0]).unwrap();
        assert!((l0 - 1.0).abs() < 1e-12 && (l1 - 2.0).abs() < 1e-12 && (v[1].abs() - 1.0).abs() < 1e-12);
    }
}
