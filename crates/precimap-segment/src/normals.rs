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
/// Largest window (half-width 3 → 7×7 = 48 neighbours).
const MAX_NEIGHBOURS: usize = 48;

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
    let w = params.window.min(3) as i64;
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
        for dc in -w..=w {
            let cc = c + dc;
            if cc < 0 || cc >= columns as i64 {
                continue;
            }
            for dr in -w..=w {
                let rr = r + dr;
                if (dc == 0 && dr == 0) || rr < 0 || rr >= rows as i64 {
                    continue;
                }
                let j = grid[cc as usize * rows + rr as usize];
                if j == NO_POINT {
                    continue;
                }
                let q = geo.point(j as usize);
                let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
                if (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() <= gate * dc.abs().max(dr.abs()) as f64 {
                    cand[m] = d;
                    m += 1;
                    has_along |= dc == 0;
                    has_across |= dr == 0;
                }
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
            if inliers as usize == pts.len() + 1 {
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
fn plane_fit<'a>(pts: impl Iterator<Item = &'a [f64; 3]> + Clone) -> Option<[f64; 3]> {
    let mut count = 1.0;
    let mut sum = [0.0; 3];
    for q in pts.clone() {
        count += 1.0;
        for a in 0..3 {
            sum[a] += q[a];
        }
    }
    let mean = sum.map(|s| s / count);
    let mut cov = nalgebra::Matrix3::<f64>::zeros();
    let mut add = |q: &[f64; 3]| {
        let d = nalgebra::Vector3::new(q[0] - mean[0], q[1] - mean[1], q[2] - mean[2]);
        cov += d * d.transpose();
    };
    add(&[0.0; 3]);
    for q in pts {
        add(q);
    }
    let eig = nalgebra::SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let (l0, l1) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
    if l0.is_nan() || l1 <= 0.0 || l0 > 0.1 * l1 {
        return None;
    }
    let v = eig.eigenvectors.column(order[0]);
    Some([v[0], v[1], v[2]])
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
