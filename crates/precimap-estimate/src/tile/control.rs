//! Step 2c of [`super::estimate_tile`]: the control targets near the tile, observed by the core
//! points on surfaces through them ([`crate::control::observe_targets`]).

use super::models::pass_tag;
use super::triangles::Triangles;
use super::NONE;
use crate::control::{observe_targets, TargetObservation, TilePoints};
use precimap_core::{ControlSums, ControlTarget, Parameters};

/// The targets' observations among the tile's core points (sorted by point), and what the points
/// measured at every target, control and check alike (sorted by id).
pub(super) fn observe_control(
    control: &[ControlTarget],
    t: &Triangles,
    in_core: &impl Fn(&[f64; 3]) -> bool,
    origin: [f64; 2],
    params: &Parameters,
    threshold: f64,
) -> (Vec<TargetObservation>, Vec<ControlSums>) {
    if control.is_empty() {
        return (Vec::new(), Vec::new());
    }
    // Each point's strip pass: the chunks are consecutive runs of the points.
    let mut starts = Vec::with_capacity(t.chunks.len());
    let mut base = 0;
    for c in t.chunks {
        starts.push(base);
        base += c.len();
    }
    let pass = |i: usize| {
        let c = starts.partition_point(|&s| s <= i) - 1;
        pass_tag(t.chunks[c].strip, t.chunks[c].anchor[i - starts[c]])
    };
    let model = |i: usize| {
        let id = t.model_of[i];
        (id != NONE && in_core(&t.position[i])).then(|| (t.models[id as usize].w, t.models[id as usize].o))
    };
    let points = TilePoints { origin, position: t.position, model, pass };
    observe_targets(control, &points, params, threshold)
}
