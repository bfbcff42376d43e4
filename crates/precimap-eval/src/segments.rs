//! Segmentation quality against the truth: purity, removed surface and foliage points, and how
//! many segments the road surface of one strip falls into.
//!
//! **What a true surface is.** The simulator builds a façade from overlapping boxes (piers between
//! the windows, bands between the floors, the wall above): one physical wall plane carries many
//! simulator surface ids, and no continuity segmentation could (or should) tell them apart. For
//! purity, simulator surfaces of one class whose planes coincide (normals within 1°, offsets
//! within 1 cm, each surface planar) count as one true surface; curved surfaces (poles, trunks,
//! crowns) keep their ids. The purity by raw simulator id is reported alongside.

use precimap_core::hash::FxHashMap;
use precimap_sim::truth::SurfaceClass;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};

/// Segment id of a point in no segment (`precimap_segment::NO_SEGMENT`).
const NO_SEGMENT: u32 = u32::MAX;
/// Segment id of a point whose revolution was dropped at standstill (never segmented).
const DROPPED: u32 = u32::MAX - 1;

/// One strip's counts.
#[derive(Clone, Debug, Default)]
pub struct SegmentTally {
    /// (segment, true surface id) → points.
    per_segment_surface: FxHashMap<(u32, u32), u64>,
    /// Road points per segment.
    road_per_segment: FxHashMap<u32, u64>,
    /// Per simulator surface id: class, Σ normal, Σ normal·position, points.
    surfaces: FxHashMap<u32, SurfaceSums>,
    surface_points: u64,
    surface_removed: u64,
    foliage_points: u64,
    foliage_removed: u64,
    dropped: u64,
}

#[derive(Clone, Copy, Debug)]
struct SurfaceSums {
    class: SurfaceClass,
    normal: [f64; 3],
    offset: f64,
    count: u64,
}

impl SegmentTally {
    /// Adds one point: its segment id, and its true surface, class, normal and position.
    pub fn add(&mut self, segment: u32, surface_id: u32, class: SurfaceClass, normal: [f32; 3], position: [f64; 3]) {
        let n = normal.map(f64::from);
        let e =
            self.surfaces.entry(surface_id).or_insert(SurfaceSums { class, normal: [0.0; 3], offset: 0.0, count: 0 });
        for a in 0..3 {
            e.normal[a] += n[a];
        }
        e.offset += n[0] * position[0] + n[1] * position[1] + n[2] * position[2];
        e.count += 1;
        if segment == DROPPED {
            self.dropped += 1;
            return;
        }
        let removed = segment == NO_SEGMENT;
        if class.is_surface() {
            self.surface_points += 1;
            self.surface_removed += removed as u64;
        } else {
            self.foliage_points += 1;
            self.foliage_removed += removed as u64;
        }
        if !removed {
            *self.per_segment_surface.entry((segment, surface_id)).or_default() += 1;
            if class == SurfaceClass::Road {
                *self.road_per_segment.entry(segment).or_default() += 1;
            }
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SegmentEvaluation {
    /// Share of a segment's points on its dominant true surface (coplanar simulator surfaces of
    /// one class joined, see the module notes), weighted by points.
    pub purity: f64,
    /// The same with every simulator surface id a surface of its own.
    pub purity_by_simulator_id: f64,
    pub surface_points_removed: f64,
    pub foliage_points_removed: f64,
    /// Segments over all strips.
    pub segments: u64,
    /// Points in segments.
    pub points_segmented: u64,
    /// Points of revolutions dropped at standstill (not segmented, not counted above).
    pub points_dropped_at_standstill: u64,
    /// Per strip, the fewest segments holding 90 % of its segmented road points (the whole town's
    /// road network is one true surface in the simulator): mean and largest over strips.
    pub road_segments_for_90pct_mean: f64,
    pub road_segments_for_90pct_max: u64,
    /// Share of a strip's segmented road points in its largest segment, mean over strips.
    pub road_share_in_largest_segment_mean: f64,
}

impl SegmentEvaluation {
    pub fn from_tallies(tallies: &[SegmentTally]) -> Self {
        let canonical = coplanar_surfaces(tallies);
        let (mut dominant, mut total, mut segments) = (0u64, 0u64, 0u64);
        let mut dominant_raw = 0u64;
        let (mut road90_sum, mut road90_max, mut largest_sum) = (0u64, 0u64, 0.0);
        for t in tallies {
            let mut by_segment: BTreeMap<u32, (u64, u64)> = BTreeMap::new();
            let mut joined: HashMap<(u32, u32), u64> = HashMap::new();
            for (&(seg, sid), &n) in &t.per_segment_surface {
                let e = by_segment.entry(seg).or_default();
                e.0 = e.0.max(n);
                e.1 += n;
                *joined.entry((seg, canonical.get(&sid).copied().unwrap_or(sid))).or_default() += n;
            }
            let mut best_joined: HashMap<u32, u64> = HashMap::new();
            for (&(seg, _), &n) in &joined {
                let b = best_joined.entry(seg).or_default();
                *b = (*b).max(n);
            }
            dominant += best_joined.values().sum::<u64>();
            segments += by_segment.len() as u64;
            for (d, n) in by_segment.values() {
                dominant_raw += d;
                total += n;
            }
            let mut road: Vec<u64> = t.road_per_segment.values().copied().collect();
            road.sort_unstable_by(|a, b| b.cmp(a));
            let road_total: u64 = road.iter().sum();
            let mut acc = 0;
            let mut needed = 0u64;
            for r in &road {
                if acc as f64 >= 0.9 * road_total as f64 {
                    break;
                }
                acc += r;
                needed += 1;
            }
            road90_sum += needed;
            road90_max = road90_max.max(needed);
            largest_sum += road.first().map_or(0.0, |&l| l as f64 / road_total as f64);
        }
        let share = |a: u64, b: u64| if b > 0 { a as f64 / b as f64 } else { f64::NAN };
        let sum = |f: fn(&SegmentTally) -> u64| tallies.iter().map(f).sum::<u64>();
        let strips = tallies.len().max(1) as f64;
        Self {
            purity: share(dominant, total),
            purity_by_simulator_id: share(dominant_raw, total),
            surface_points_removed: share(sum(|t| t.surface_removed), sum(|t| t.surface_points)),
            foliage_points_removed: share(sum(|t| t.foliage_removed), sum(|t| t.foliage_points)),
            segments,
            points_segmented: total,
            points_dropped_at_standstill: sum(|t| t.dropped),
            road_segments_for_90pct_mean: road90_sum as f64 / strips,
            road_segments_for_90pct_max: road90_max,
            road_share_in_largest_segment_mean: largest_sum / strips,
        }
    }
}

/// Maps every planar simulator surface id to the smallest id of its coplanar group (same class,
/// normals within 1°, plane offsets within 1 cm).
pub(crate) fn coplanar_surfaces(tallies: &[SegmentTally]) -> HashMap<u32, u32> {
    let mut sums: BTreeMap<u32, SurfaceSums> = BTreeMap::new();
    for t in tallies {
        for (&id, s) in &t.surfaces {
            let e = sums.entry(id).or_insert(SurfaceSums { class: s.class, normal: [0.0; 3], offset: 0.0, count: 0 });
            for a in 0..3 {
                e.normal[a] += s.normal[a];
            }
            e.offset += s.offset;
            e.count += s.count;
        }
    }
    // (id, class, unit normal, offset) of the planar ones: the mean of unit normals is a unit
    // vector only if they all agree.
    let planes: Vec<(u32, u8, [f64; 3], f64)> = sums
        .iter()
        .filter_map(|(&id, s)| {
            let c = s.count as f64;
            let m = s.normal.map(|v| v / c);
            let len = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
            (len > 0.9999).then(|| (id, s.class as u8, m.map(|v| v / len), s.offset / c))
        })
        .collect();
    let cos_max = 1f64.to_radians().cos();
    let mut parent: Vec<usize> = (0..planes.len()).collect();
    fn find(parent: &mut [usize], mut x: usize) -> usize {
        while parent[x] != x {
            parent[x] = parent[parent[x]];
            x = parent[x];
        }
        x
    }
    for i in 0..planes.len() {
        for j in i + 1..planes.len() {
            let (a, b) = (&planes[i], &planes[j]);
            let cos = a.2[0] * b.2[0] + a.2[1] * b.2[1] + a.2[2] * b.2[2];
            if a.1 == b.1 && cos > cos_max && (a.3 - b.3).abs() < 0.01 {
                let (ri, rj) = (find(&mut parent, i), find(&mut parent, j));
                if ri != rj {
                    parent[ri.max(rj)] = ri.min(rj);
                }
            }
        }
    }
    (0..planes.len()).map(|i| (planes[i].0, planes[find(&mut parent, i)].0)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn purity_and_removal_shares() {
        let mut t = SegmentTally::default();
        let up = [0.0, 0.0, 1.0];
        let side = [1.0, 0.0, 0.0];
        // Segment 0: 9 road points and 1 curb point; segment 1: 5 curb points.
        for _ in 0..9 {
            t.add(0, 1, SurfaceClass::Road, up, [0.0; 3]);
        }
        t.add(0, 7, SurfaceClass::Curb, side, [0.0; 3]);
        for _ in 0..5 {
            t.add(1, 7, SurfaceClass::Curb, side, [0.0; 3]);
        }
        t.add(NO_SEGMENT, 7, SurfaceClass::Curb, side, [0.0; 3]);
        for _ in 0..3 {
            t.add(NO_SEGMENT, 9, SurfaceClass::Foliage, side, [0.0; 3]);
        }
        t.add(2, 9, SurfaceClass::Foliage, up, [0.0; 3]);
        t.add(DROPPED, 1, SurfaceClass::Road, up, [0.0; 3]);
        // Segment 3: two coplanar façade pieces (ids 20, 21) and a parallel one 5 cm behind (22).
        for (id, x, n) in [(20, 5.0, 4), (21, 5.0, 4), (22, 5.05, 2)] {
            for _ in 0..n {
                t.add(3, id, SurfaceClass::Facade, side, [x, 1.0, 2.0]);
            }
        }
        let e = SegmentEvaluation::from_tallies(&[t]);
        assert!((e.purity - 23.0 / 26.0).abs() < 1e-12, "{}", e.purity);
        assert!((e.purity_by_simulator_id - 19.0 / 26.0).abs() < 1e-12);
        assert!((e.surface_points_removed - 1.0 / 26.0).abs() < 1e-12);
        assert!((e.foliage_points_removed - 0.75).abs() < 1e-12);
        assert_eq!(e.segments, 4);
        assert_eq!(e.points_dropped_at_standstill, 1);
        assert_eq!(e.road_segments_for_90pct_max, 1);
    }
}
