//! Normal accuracy against the truth: the angle between a point's estimated normal and its true
//! surface normal (orientation ignored), per surface class, and how many points got a normal.
//! Foliage has no true surface and is left out.

use precimap_sim::truth::SurfaceClass;
use serde::Serialize;
use std::collections::BTreeMap;

/// Histogram resolution, degrees (angles are 0–90°).
const BIN_DEG: f64 = 0.01;
const BINS: usize = 9001;

/// Counts of one or more strips; [`NormalTally::merge`] joins them.
#[derive(Clone, Debug, Default)]
pub struct NormalTally {
    per_class: BTreeMap<&'static str, ClassTally>,
}

#[derive(Clone, Debug)]
struct ClassTally {
    points: u64,
    with_normal: u64,
    sum_deg: f64,
    histogram: Vec<u64>,
}

impl Default for ClassTally {
    fn default() -> Self {
        Self { points: 0, with_normal: 0, sum_deg: 0.0, histogram: vec![0; BINS] }
    }
}

impl ClassTally {
    fn add(&mut self, angle_deg: Option<f64>) {
        self.points += 1;
        if let Some(a) = angle_deg {
            self.with_normal += 1;
            self.sum_deg += a;
            self.histogram[((a / BIN_DEG).round() as usize).min(BINS - 1)] += 1;
        }
    }

    fn merge(&mut self, other: &ClassTally) {
        self.points += other.points;
        self.with_normal += other.with_normal;
        self.sum_deg += other.sum_deg;
        for (a, b) in self.histogram.iter_mut().zip(&other.histogram) {
            *a += b;
        }
    }

    fn quantile(&self, q: f64) -> f64 {
        let target = (q * self.with_normal as f64).ceil().max(1.0) as u64;
        let mut acc = 0;
        for (i, &c) in self.histogram.iter().enumerate() {
            acc += c;
            if acc >= target {
                return i as f64 * BIN_DEG;
            }
        }
        f64::NAN
    }

    fn figures(&self) -> NormalFigures {
        NormalFigures {
            points: self.points,
            with_normal_share: self.with_normal as f64 / self.points.max(1) as f64,
            mean_deg: self.sum_deg / self.with_normal.max(1) as f64,
            p50_deg: self.quantile(0.5),
            p95_deg: self.quantile(0.95),
        }
    }
}

impl NormalTally {
    /// Adds one point: its class, its estimated normal (if any) and its true normal.
    pub fn add(&mut self, class: SurfaceClass, estimated: Option<[f32; 3]>, truth: [f32; 3]) {
        if !class.is_surface() {
            return;
        }
        let angle = estimated.map(|n| angle_deg(n, truth));
        self.per_class.entry(class.name()).or_default().add(angle);
    }

    pub fn merge(&mut self, other: &NormalTally) {
        for (class, t) in &other.per_class {
            self.per_class.entry(class).or_default().merge(t);
        }
    }

    pub fn evaluate(&self) -> NormalEvaluation {
        let mut all = ClassTally::default();
        for t in self.per_class.values() {
            all.merge(t);
        }
        NormalEvaluation {
            surfaces: all.figures(),
            per_class: self.per_class.iter().map(|(c, t)| (c.to_string(), t.figures())).collect(),
        }
    }
}

/// Angle between two directions, ignoring their orientation, degrees.
fn angle_deg(a: [f32; 3], b: [f32; 3]) -> f64 {
    let (a, b) = (a.map(f64::from), b.map(f64::from));
    let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let len = ((a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) * (b[0] * b[0] + b[1] * b[1] + b[2] * b[2])).sqrt();
    (dot.abs() / len.max(1e-300)).min(1.0).acos().to_degrees()
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct NormalEvaluation {
    /// All surface points (foliage excluded).
    pub surfaces: NormalFigures,
    pub per_class: BTreeMap<String, NormalFigures>,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct NormalFigures {
    pub points: u64,
    /// Share of the points that got a normal.
    pub with_normal_share: f64,
    /// Angle to the true normal over the points with a normal: mean, median, 95th percentile
    /// (0.01° bins).
    pub mean_deg: f64,
    pub p50_deg: f64,
    pub p95_deg: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angles_per_class_and_quantiles() {
        let mut t = NormalTally::default();
        let up = [0.0, 0.0, 1.0];
        // Road: 10 points, 9 with normals at 0°, 1°, …, 8° (one of them pointing down), one without.
        for i in 0..9 {
            let a = (i as f32).to_radians();
            let s = if i == 4 { -1.0 } else { 1.0 };
            t.add(SurfaceClass::Road, Some([a.sin() * s, 0.0, a.cos() * s]), up);
        }
        t.add(SurfaceClass::Road, None, up);
        t.add(SurfaceClass::Foliage, Some([1.0, 0.0, 0.0]), up);
        let mut other = NormalTally::default();
        other.add(SurfaceClass::Curb, Some([1.0, 0.0, 0.0]), up);
        t.merge(&other);
        let e = t.evaluate();
        let road = &e.per_class["road"];
        assert_eq!(road.points, 10);
        assert!((road.with_normal_share - 0.9).abs() < 1e-12);
        assert!((road.mean_deg - 4.0).abs() < 1e-3, "{road:?}");
        assert!((road.p50_deg - 4.0).abs() < 0.011, "{road:?}");
        assert!((road.p95_deg - 8.0).abs() < 0.011, "{road:?}");
        assert!((e.per_class["curb"].mean_deg - 90.0).abs() < 1e-3);
        assert!(!e.per_class.contains_key("foliage"));
        assert_eq!(e.surfaces.points, 11);
    }
}
