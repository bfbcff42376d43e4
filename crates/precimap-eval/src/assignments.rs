//! The assignment audit: how many of the points that became observations in the last map pass
//! (`OUT/assignments`, written by `precimap run --in-process --assignments`) were compared with a
//! surface model built mostly from *another* true surface, e.g. a curb's top joined with the
//! road beside it, or the two faces of a thin wall in one model.

use precimap_sim::truth::SurfaceClass;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};

/// The observations of the strips: (campaign-wide model id, true surface id, true class).
#[derive(Clone, Debug, Default)]
pub struct AssignmentTally {
    points: Vec<(u32, u32, u8)>,
}

impl AssignmentTally {
    /// Adds one point; `model == u32::MAX` (not an observation) is skipped.
    pub fn add(&mut self, model: u32, surface_id: u32, class: SurfaceClass) {
        if model != u32::MAX {
            self.points.push((model, surface_id, class as u8));
        }
    }

    pub fn merge(&mut self, other: AssignmentTally) {
        self.points.extend(other.points);
    }

    /// Every model's dominant true surface (most of its points), then the share of points on
    /// another surface, overall and by the point's true class. `canonical` maps simulator
    /// surfaces to one id per coplanar group (as segment purity does: a pier flush with its wall
    /// is the same plane to the estimation); ids it lacks stand for themselves.
    pub fn evaluate(&self, canonical: &HashMap<u32, u32>) -> AssignmentEvaluation {
        let surface_of = |s: u32| canonical.get(&s).copied().unwrap_or(s);
        let mut per_model: HashMap<u32, HashMap<u32, u64>> = HashMap::new();
        for &(model, surface, _) in &self.points {
            *per_model.entry(model).or_default().entry(surface_of(surface)).or_default() += 1;
        }
        // Ties go to the smaller surface id, so the figure does not depend on hash order.
        let dominant: HashMap<u32, u32> = per_model
            .iter()
            .map(|(&model, counts)| {
                let best = counts.iter().max_by_key(|(&s, &n)| (n, std::cmp::Reverse(s))).map_or(u32::MAX, |(&s, _)| s);
                (model, best)
            })
            .collect();
        let mut by_class: BTreeMap<u8, (u64, u64)> = BTreeMap::new();
        for &(model, surface, class) in &self.points {
            let c = by_class.entry(class).or_default();
            c.0 += 1;
            if dominant.get(&model) != Some(&surface_of(surface)) {
                c.1 += 1;
            }
        }
        let (points, wrong) = by_class.values().fold((0, 0), |a, c| (a.0 + c.0, a.1 + c.1));
        AssignmentEvaluation {
            points,
            models: per_model.len() as u64,
            wrong_share: if points > 0 { wrong as f64 / points as f64 } else { 0.0 },
            wrong_share_by_class: by_class
                .into_iter()
                .map(|(class, (n, w))| {
                    let name =
                        SurfaceClass::from_u8(class).map_or_else(|| format!("class-{class}"), |c| c.name().to_string());
                    (name, ClassAssignments { points: n, wrong_share: w as f64 / n.max(1) as f64 })
                })
                .collect(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AssignmentEvaluation {
    /// Observations of the last map pass.
    pub points: u64,
    /// Surface models they were compared with.
    pub models: u64,
    /// Share of the observations whose true surface is not their model's dominant one (0–1).
    pub wrong_share: f64,
    pub wrong_share_by_class: BTreeMap<String, ClassAssignments>,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ClassAssignments {
    pub points: u64,
    pub wrong_share: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_off_their_models_dominant_surface_are_wrong() {
        use std::collections::HashMap;
        let mut t = AssignmentTally::default();
        // Model 0: three road points and one curb point; model 1: two curb points.
        for _ in 0..3 {
            t.add(0, 10, SurfaceClass::Road);
        }
        t.add(0, 11, SurfaceClass::Curb);
        t.add(1, 11, SurfaceClass::Curb);
        t.add(1, 11, SurfaceClass::Curb);
        t.add(u32::MAX, 12, SurfaceClass::Facade);
        let e = t.evaluate(&HashMap::new());
        assert_eq!((e.points, e.models), (6, 2));
        assert!((e.wrong_share - 1.0 / 6.0).abs() < 1e-12);
        assert_eq!(e.wrong_share_by_class["road"].wrong_share, 0.0);
        assert!((e.wrong_share_by_class["curb"].wrong_share - 1.0 / 3.0).abs() < 1e-12);
        assert!(!e.wrong_share_by_class.contains_key("facade"), "not an observation");
        // Curb 11 coplanar with road 10: one surface, nothing wrong.
        let e = t.evaluate(&HashMap::from([(11, 10)]));
        assert_eq!(e.wrong_share, 0.0);
    }
}
