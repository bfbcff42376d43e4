//! The consistent gradient's corner pulls ([`CornerPulls`]): what the used points' residuals pull
//! on the passes whose triangles make their latent heights.

use super::cross;
use super::models::SurfaceModel;
use super::triangles::Triangles;
use crate::blocks::IntervalMoments;
use precimap_core::hash::FxHashMap;

/// What the used points' residuals pull on the triangles that cover them, gathered per corner
/// point the triangles hang off ([`Parameters::consistent_gradient`]). A point `j` with `c`
/// covering triangles and residual `e` has latent height `(own + Σ triangles)/(c+1)`, so moving a
/// triangle's pass by `δ` changes `e` by `−g·δ/(c+1)`. Each covering triangle's pass therefore
/// gets the observation "residual −e, weight ω/(c+1)" with the triangle's Jacobian, that of the
/// corner it hangs off (the other two corners are one point or one revolution away).
pub(super) struct CornerPulls {
    /// Per point: Σ weight and Σ weight × residual, for the point's own model.
    pub(super) sums: Vec<[f64; 2]>,
    /// The same where a triangle lies on another model than its corner's: (corner, model, sums),
    /// sorted.
    pub(super) other_models: Vec<(usize, u32, [f64; 2])>,
    /// First entry of `other_models` not yet passed: points are added in increasing order.
    pub(super) next_other: usize,
}

impl CornerPulls {
    /// The pull on point `a` (a triangle corner) through triangles on its own model, as
    /// (Σ weight, Σ weight × residual), if any; and the pulls through triangles on other models
    /// added to its interval's moments, and to `apart` too where given (they carry no
    /// calibration columns). `a` must increase from call to call.
    #[inline]
    pub(super) fn take(
        &mut self,
        a: usize,
        models: &[SurfaceModel],
        measurement: &[[f64; 3]],
        moments: &mut IntervalMoments,
        mut apart: Option<&mut IntervalMoments>,
        lambda: f64,
    ) -> Option<[f64; 2]> {
        // A cursor, not a binary search per point: the calls come in point order.
        let others = &self.other_models;
        while self.next_other < others.len() && others[self.next_other].0 < a {
            self.next_other += 1;
        }
        while self.next_other < others.len() && others[self.next_other].0 == a {
            let (_, model, [w_sum, we_sum]) = others[self.next_other];
            if w_sum > 0.0 {
                let g = jacobian(models[model as usize].w, measurement[a]);
                moments.add(&g, -we_sum / w_sum, w_sum, lambda);
                if let Some(apart) = apart.as_deref_mut() {
                    apart.add(&g, -we_sum / w_sum, w_sum, lambda);
                }
            }
            self.next_other += 1;
        }
        let sums = self.sums[a];
        (sums[0] > 0.0).then_some(sums)
    }
}

/// The Jacobian row of a point's distance along the normal `w` with respect to its pass's
/// correction (translation, then rotation about the scan head at measurement vector `r`).
#[inline]
pub(super) fn jacobian(w: [f64; 3], r: [f64; 3]) -> [f64; 6] {
    let rw = cross(r, w);
    [w[0], w[1], w[2], rw[0], rw[1], rw[2]]
}

/// Gathers the pulls of [`point_latent`] (`pull`, per item: `ω/(c+1)` and `ω/(c+1)·e` of the
/// points the observation loop will use, else zeros) on the corners their covering triangles
/// hang off.
pub(super) fn corner_pulls(t: &Triangles, covers: &[[u32; 3]], pull: &[[f64; 2]]) -> CornerPulls {
    let mut sums = vec![[0.0; 2]; t.position.len()];
    let mut other: FxHashMap<(usize, u32), [f64; 2]> = FxHashMap::default();
    for &[q, corner, model] in covers {
        let (pull, corner) = (pull[q as usize], corner as usize);
        let s = if model == t.model_of[corner] { &mut sums[corner] } else { other.entry((corner, model)).or_default() };
        s[0] += pull[0];
        s[1] += pull[1];
    }
    let mut other_models: Vec<(usize, u32, [f64; 2])> = other.into_iter().map(|((a, m), s)| (a, m, s)).collect();
    other_models.sort_by_key(|o| (o.0, o.1));
    CornerPulls { sums, other_models, next_other: 0 }
}
