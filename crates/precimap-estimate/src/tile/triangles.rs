//! The scan-image triangles of a tile's strips on its surface models ([`Triangles`]), and one
//! triangle in a model's plane ([`PlaneTriangle`]): what every latent-map route samples.

use super::models::SurfaceModel;
use super::{cross, dot, NONE};
use crate::chunk::{TileChunk, NO_NEIGHBOUR};

/// A scan-image triangle is rasterised only if its facet is within 15° of the model's normal:
/// steeper facets bridge a step (curb, window recess, occlusion) and would bias the heights.
const FACET_COS: f64 = 0.965_925_826_289_068_3;

/// The scan-image triangles of a tile's strips (point, next in revolution, same row next
/// revolution, and the opposite triangle of that quad), each with the surface models it lies on.
pub(super) struct Triangles<'a> {
    pub(super) chunks: &'a [TileChunk],
    pub(super) models: &'a [SurfaceModel],
    pub(super) position: &'a [[f64; 3]],
    pub(super) model_of: &'a [u32],
    pub(super) cos_group: f64,
    /// Only triangles whose three corners lie in one scan-image segment: one whose corners the
    /// segmentation split (a C0 or C1 break: a curb, a window reveal, a bridge over the far curb
    /// at grazing incidence) interpolates across that break, and the points of other passes
    /// under it get a latent height centimetres off, so they are rejected as outliers.
    pub(super) within_segment: bool,
}

impl Triangles<'_> {
    /// Calls `visit(model, corners, indices, strip, anchor, first)` (the corners' positions and
    /// point indices; `first`: index of the corner the triangle hangs off) for every triangle and
    /// every surface model one of its corners belongs to, provided the triangle is continuous
    /// surface (short edges) lying on that model (facet and model normals agree, and the
    /// corners' models are not at odds) and, with `within_segment`, within one segment.
    pub(super) fn for_each(&self, mut visit: impl FnMut(u32, [[f64; 3]; 3], [usize; 3], u32, u32, usize)) {
        let mut base = 0usize;
        for chunk in self.chunks {
            for k in 0..chunk.len() {
                let (right, down) = (chunk.right[k], chunk.down[k]);
                if right == NO_NEIGHBOUR || down == NO_NEIGHBOUR {
                    continue;
                }
                let (a, b, c) = (base + k, base + right as usize, base + down as usize);
                let limit =
                    chunk.edge_limit[k].max(chunk.edge_limit[right as usize]).max(chunk.edge_limit[down as usize]);
                let anchor = chunk.anchor[k];
                let segment = &chunk.segment;
                let joined = |i: u32, j: u32| !self.within_segment || segment[i as usize] == segment[j as usize];
                if joined(k as u32, right) && joined(k as u32, down) {
                    self.triangle([a, b, c], limit as f64, |m, p, v| visit(m, p, v, chunk.strip, anchor, a));
                }
                let diagonal = chunk.down[right as usize];
                if diagonal != NO_NEIGHBOUR && joined(diagonal, right) && joined(diagonal, down) {
                    let d = base + diagonal as usize;
                    let limit = limit.max(chunk.edge_limit[diagonal as usize]);
                    self.triangle([b, d, c], limit as f64, |m, p, v| visit(m, p, v, chunk.strip, anchor, a));
                }
            }
            base += chunk.len();
        }
    }

    #[inline]
    pub(super) fn triangle(&self, v: [usize; 3], limit: f64, mut visit: impl FnMut(u32, [[f64; 3]; 3], [usize; 3])) {
        let ids = [self.model_of[v[0]], self.model_of[v[1]], self.model_of[v[2]]];
        if ids.contains(&NONE) {
            return;
        }
        let [pa, pb, pc] = [self.position[v[0]], self.position[v[1]], self.position[v[2]]];
        let ab = [pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2]];
        let ac = [pc[0] - pa[0], pc[1] - pa[1], pc[2] - pa[2]];
        let bc = [pc[0] - pb[0], pc[1] - pb[1], pc[2] - pb[2]];
        let limit2 = limit * limit;
        if dot(ab, ab) > limit2 || dot(ac, ac) > limit2 || dot(bc, bc) > limit2 {
            return;
        }
        let face = cross(ab, ac);
        let area2_sq = dot(face, face);
        if area2_sq < 1e-24 {
            return;
        }
        // |cos| of the facet against a unit model normal, compared squared: no root, no division.
        let facet_limit = FACET_COS * FACET_COS * area2_sq;
        for (slot, &id) in ids.iter().enumerate() {
            if ids[..slot].contains(&id) {
                continue;
            }
            let m = &self.models[id as usize];
            let along = dot(face, m.w);
            if along * along < facet_limit
                || ids.iter().any(|&other| other != id && dot(self.models[other as usize].w, m.w) < self.cos_group)
            {
                continue;
            }
            visit(id, [pa, pb, pc], v);
        }
    }

    /// A visited triangle in model `id`'s plane: corners on that model from `uvh` (their
    /// projections, computed once per point), a corner on another (agreeing) model projected
    /// here. `None` for a triangle without area in the plane. Always inlined: out of line it
    /// cost the 2 cm pass 1.8 % more instructions (callgrind).
    #[inline(always)]
    pub(super) fn plane_triangle(
        &self,
        id: u32,
        p: &[[f64; 3]; 3],
        corners: [usize; 3],
        uvh: &[[f64; 3]],
    ) -> Option<PlaneTriangle> {
        let mut plane = [[0.0; 3]; 3];
        for (k, (&a, at)) in corners.iter().zip(&mut plane).enumerate() {
            *at = if self.model_of[a] == id {
                uvh[a]
            } else {
                let (u, v, h) = self.models[id as usize].project(&p[k]);
                [u, v, h]
            };
        }
        PlaneTriangle::new(plane)
    }
}

/// A triangle in a surface model's plane: its first corner `(u, v, h)`, the other two relative
/// to it, and its slope `(∂h/∂u, ∂h/∂v)`; what both sampled routes evaluate at points or pixel
/// centres.
#[derive(Clone, Copy, Debug)]
pub(super) struct PlaneTriangle {
    pub(super) origin: [f64; 3],
    pub(super) d1: [f64; 3],
    pub(super) d2: [f64; 3],
    pub(super) inv_area: f64,
    pub(super) hx: f64,
    pub(super) hy: f64,
}

impl PlaneTriangle {
    /// `None` for a triangle without area in the plane (seen edge-on).
    #[inline]
    pub(super) fn new([c0, c1, c2]: [[f64; 3]; 3]) -> Option<Self> {
        let d1 = [c1[0] - c0[0], c1[1] - c0[1], c1[2] - c0[2]];
        let d2 = [c2[0] - c0[0], c2[1] - c0[1], c2[2] - c0[2]];
        let area = d1[0] * d2[1] - d2[0] * d1[1];
        if area.abs() < 1e-12 {
            return None;
        }
        let inv_area = 1.0 / area;
        let hx = (d1[2] * d2[1] - d2[2] * d1[1]) * inv_area;
        let hy = (d2[2] * d1[0] - d1[2] * d2[0]) * inv_area;
        Some(Self { origin: c0, d1, d2, inv_area, hx, hy })
    }

    /// Barycentric coordinates `(l1, l2)` of the corners 1 and 2 at `(du, dv)` from corner 0.
    #[inline]
    pub(super) fn barycentric(&self, du: f64, dv: f64) -> (f64, f64) {
        let (d1, d2) = (&self.d1, &self.d2);
        ((du * d2[1] - d2[0] * dv) * self.inv_area, (d1[0] * dv - du * d1[1]) * self.inv_area)
    }

    /// Height at the barycentric coordinates `(l1, l2)`.
    #[inline]
    pub(super) fn height(&self, l1: f64, l2: f64) -> f64 {
        self.origin[2] + l1 * self.d1[2] + l2 * self.d2[2]
    }
}
