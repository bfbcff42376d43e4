//! The exported latent map (`OUT/latent/*.las`) against the true surfaces: how far the map
//! itself, the product, lies from where the surfaces really are.
//!
//! The map keeps the campaign's absolute datum error (tens of millimetres to decimetres on the
//! simulated campaigns, more than the distance between map points), which no relative
//! adjustment observes. So each map point, moved back by the campaign's shift (the translation
//! that best explains the corrected strips' surface errors), is compared with the nearest
//! noise-free truth point within [`MATCH_RADIUS_M`] whose true normal agrees with the map
//! point's (|cos| ≥ [`MATCH_MIN_COS`]): its error is the distance from that point's tangent
//! plane along the true normal (turned to face the map normal's way), and the shift's share
//! along that normal is added back for the absolute error. Memory holds the map, not the
//! truth: the truth streams past it strip by strip.

use crate::{AbsHistogram, ErrorStats, EvalError};
use precimap_core::hash::FxHashMap;
use precimap_core::LatentMapPoint;
use precimap_sim::truth::{SurfaceClass, TruthReader};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};

/// Farthest truth point a map point is compared with (half the default voxel).
pub const MATCH_RADIUS_M: f64 = 0.05;
/// The true normal must agree with the map's to within ~37°.
pub const MATCH_MIN_COS: f64 = 0.8;
/// A tile takes part in the figure without its shift with at least this many matched points.
pub const TILE_MIN_POINTS: usize = 50;

/// The latent map's error against the truth, in metres.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LatentMapEvaluation {
    /// Map points (all tiles).
    pub points: u64,
    /// Of those, points with a true surface point within the match radius.
    pub matched: u64,
    /// RMS of the signed error: the map's absolute error, the datum included.
    pub error_rms_m: f64,
    pub error_mean_m: f64,
    /// RMS without the campaign's shift (the absolute datum).
    pub error_without_campaign_shift_rms_m: f64,
    /// 95th percentile of |error| without the campaign's shift (±0.25 %, as the surface errors').
    pub error_without_campaign_shift_p95_abs_m: f64,
    /// RMS after removing each 15 m tile's mean error (tiles with at least [`TILE_MIN_POINTS`]
    /// matched points): how precise the map is where one datum holds, what relative
    /// adjustment can reach.
    pub error_without_tile_shift_rms_m: f64,
    /// Median of the map points' `StdDev` (the strips' spread about the map; ±0.25 %).
    pub std_median_m: f64,
    /// By surface class of the matched truth point.
    pub per_class: BTreeMap<String, LatentClassFigures>,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LatentClassFigures {
    pub matched: u64,
    pub error_rms_m: f64,
    pub error_without_campaign_shift_rms_m: f64,
    pub error_without_tile_shift_rms_m: f64,
}

/// The best truth match of one map point so far: its error without the campaign's shift, the
/// shift's share along the true normal, and the strip and surface class of the truth point.
/// Of equally distant truth points the first strip's wins (then the first in that strip), so the
/// figures do not depend on which thread matched which strip.
#[derive(Clone, Copy)]
struct Match {
    distance2: f32,
    error: f32,
    shift_along: f32,
    /// Strip index × 256 + surface class ([`NO_CLASS`]: no match).
    strip_class: u32,
}

/// The class of a map point without a match.
const NO_CLASS: u8 = u8::MAX;
/// Strips a campaign may have for [`Match::strip_class`].
const MAX_STRIPS: usize = 1 << 24;
const NO_MATCH: Match = Match { distance2: f32::INFINITY, error: 0.0, shift_along: 0.0, strip_class: NO_CLASS as u32 };

impl Match {
    fn class(&self) -> u8 {
        self.strip_class as u8
    }

    /// Whether this match beats `other`: nearer, or as near from an earlier strip.
    #[inline]
    fn beats(&self, other: &Match) -> bool {
        self.distance2 < other.distance2
            || (self.distance2 == other.distance2 && self.strip_class >> 8 < other.strip_class >> 8)
    }
}

/// The map points by cell of twice the match radius: their indices sorted by cell, and per
/// occupied cell its run of them: 4 bytes per point plus 24–48 per cell (the table's load
/// varies), where a hash map of one `Vec` per cell took 87–142 per cell, a third of them in the
/// cell's own allocation (about one map point per cell at the default voxel).
struct CellIndex {
    /// The lowest cell: keys are relative to it, in `i32`.
    origin: [i64; 3],
    order: Vec<u32>,
    runs: FxHashMap<[i32; 3], (u32, u32)>,
}

impl CellIndex {
    fn new(n: usize, cell_of: impl Fn(usize) -> [i64; 3]) -> Result<Self, EvalError> {
        let mut origin = [i64::MAX; 3];
        for i in 0..n {
            let c = cell_of(i);
            for k in 0..3 {
                origin[k] = origin[k].min(c[k]);
            }
        }
        let mut keyed = Vec::with_capacity(n);
        for i in 0..n {
            let key =
                relative(cell_of(i), origin).ok_or_else(|| EvalError::LatentMapExtent { cells: cell_of(i), origin })?;
            keyed.push((key, i as u32));
        }
        keyed.sort_unstable();
        let mut runs = FxHashMap::default();
        runs.reserve(keyed.chunk_by(|a, b| a.0 == b.0).count());
        let mut start = 0u32;
        for run in keyed.chunk_by(|a, b| a.0 == b.0) {
            runs.insert(run[0].0, (start, run.len() as u32));
            start += run.len() as u32;
        }
        let order = keyed.into_iter().map(|(_, i)| i).collect();
        Ok(Self { origin, order, runs })
    }

    /// The map points in `cell`.
    #[inline]
    fn members(&self, cell: [i64; 3]) -> &[u32] {
        match relative(cell, self.origin).and_then(|key| self.runs.get(&key)) {
            Some(&(start, len)) => &self.order[start as usize..(start + len) as usize],
            None => &[],
        }
    }
}

/// `cell` relative to `origin`, if that fits an `i32` per axis.
#[inline]
fn relative(cell: [i64; 3], origin: [i64; 3]) -> Option<[i32; 3]> {
    let mut r = [0i32; 3];
    for k in 0..3 {
        r[k] = i32::try_from(cell[k].checked_sub(origin[k])?).ok()?;
    }
    Some(r)
}

/// Reads `OUT/latent/*.las`; `None` when the folder does not exist (a result without a map).
pub fn read_latent_maps(result_dir: &Path) -> Result<Option<Vec<LatentMapPoint>>, EvalError> {
    let dir = result_dir.join("latent");
    if !dir.is_dir() {
        return Ok(None);
    }
    let io = |source| EvalError::Report { path: dir.clone(), message: format!("cannot list the latent map: {source}") };
    let mut files: Vec<PathBuf> =
        std::fs::read_dir(&dir).map_err(io)?.map(|e| e.map(|e| e.path())).collect::<Result<_, _>>().map_err(io)?;
    files.retain(|p| p.extension().is_some_and(|e| e == "las"));
    files.sort();
    // A few tiles at a time, each moved into one array and freed, so that what is in flight
    // besides the map is a few tiles' maps, not all of them. The array grows by remapping its
    // pages, not by copying them.
    let mut all = Vec::new();
    for group in files.chunks(4 * rayon::current_num_threads()) {
        let maps = group.par_iter().map(|p| precimap_formats::read_latent_map(p)).collect::<Result<Vec<_>, _>>()?;
        for tile in maps {
            all.extend(tile);
        }
    }
    Ok(Some(all))
}

/// Compares `map` with the truth of every strip (`CAMP/truth/{strip}.truth`), the map moved
/// back by `campaign_shift` (metres) first. A second pass over the truth after the strips' own:
/// the shift is known only once every strip has been compared.
pub fn evaluate_latent_map(
    map: &[LatentMapPoint],
    strip_ids: &[String],
    truth_dir: &Path,
    campaign_shift: [f64; 3],
) -> Result<LatentMapEvaluation, EvalError> {
    if strip_ids.len() > MAX_STRIPS {
        return Err(EvalError::TooManyStrips { strips: strip_ids.len(), most: MAX_STRIPS });
    }
    let cell = 2.0 * MATCH_RADIUS_M;
    let key = |p: [f64; 3]| p.map(|v| (v / cell).floor() as i64);
    // Computed where used rather than held: a copy of every map point would cost 24 bytes each.
    let shifted = |i: usize| [0, 1, 2].map(|k| map[i].position[k] - campaign_shift[k]);
    let cells = CellIndex::new(map.len(), |i| key(shifted(i)))?;
    // One array of best matches per thread, updated in place by every strip the thread takes
    // (on a campaign of 10 M map points each is 160 MB): what matches which strip then does not
    // change how many arrays there are, and ties are settled by strip order ([`Match::beats`]).
    let per_thread: Vec<Mutex<Vec<Match>>> = (0..rayon::current_num_threads()).map(|_| Mutex::default()).collect();
    strip_ids.par_iter().enumerate().try_for_each(|(strip, id)| -> Result<(), EvalError> {
        let thread = rayon::current_thread_index().unwrap_or(0) % per_thread.len();
        // Uncontended: only this thread takes this lock, and nothing below waits on rayon.
        let mut best = per_thread[thread].lock().unwrap_or_else(PoisonError::into_inner);
        if best.is_empty() {
            *best = vec![NO_MATCH; map.len()];
        }
        let strip = (strip as u32) << 8;
        // Consecutive truth points (along a scan line, centimetres apart) mostly reach the same
        // cells, whose runs are then looked up once (the look-ups miss the cache: the run table
        // is hundreds of megabytes).
        let mut reached = ([i64::MIN; 3], [0i64; 3]);
        let mut runs: [&[u32]; 8] = [&[]; 8];
        let mut truth = TruthReader::open(&truth_dir.join(format!("{id}.truth")))?;
        while let Some(t) = truth.next_point()? {
            if !t.class.is_surface() {
                continue;
            }
            let n = t.normal.map(f64::from);
            // The cells a sphere of the match radius can reach: the point's own and, per
            // axis, the neighbour on its nearer side (cells are twice the radius).
            let base = key(t.position);
            let toward = [0, 1, 2].map(|k| {
                let f = t.position[k] / cell - base[k] as f64;
                if f < 0.5 {
                    -1
                } else {
                    1
                }
            });
            if (base, toward) != reached {
                reached = (base, toward);
                for (corner, run) in runs.iter_mut().enumerate() {
                    *run = cells.members([0, 1, 2].map(|k| base[k] + if corner >> k & 1 == 1 { toward[k] } else { 0 }));
                }
            }
            for run in runs {
                for &i in run {
                    let m = &map[i as usize];
                    let shifted = shifted(i as usize);
                    let d = [0, 1, 2].map(|k| shifted[k] - t.position[k]);
                    let d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                    let cos = n[0] * m.normal[0] as f64 + n[1] * m.normal[1] as f64 + n[2] * m.normal[2] as f64;
                    let slot = &mut best[i as usize];
                    if d2 > MATCH_RADIUS_M * MATCH_RADIUS_M || cos.abs() < MATCH_MIN_COS {
                        continue;
                    }
                    let along = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
                    let shift = campaign_shift[0] * n[0] + campaign_shift[1] * n[1] + campaign_shift[2] * n[2];
                    let candidate = Match {
                        distance2: d2 as f32,
                        error: (along * cos.signum()) as f32,
                        shift_along: (shift * cos.signum()) as f32,
                        strip_class: strip | t.class as u32,
                    };
                    if candidate.beats(slot) {
                        *slot = candidate;
                    }
                }
            }
        }
        Ok(())
    })?;
    drop(cells);
    let mut arrays = per_thread.into_iter().map(|a| a.into_inner().unwrap_or_else(PoisonError::into_inner));
    let mut best = arrays.find(|a| !a.is_empty()).unwrap_or_else(|| vec![NO_MATCH; map.len()]);
    for other in arrays.filter(|a| !a.is_empty()) {
        for (x, y) in best.iter_mut().zip(other) {
            if y.beats(x) {
                *x = y;
            }
        }
    }
    Ok(figures(map, &best))
}

fn figures(map: &[LatentMapPoint], best: &[Match]) -> LatentMapEvaluation {
    let tile_of = |p: &LatentMapPoint| {
        let t = crate::SPREAD_TILE_M;
        ((p.position[0] / t).floor() as i64, (p.position[1] / t).floor() as i64)
    };
    // Per tile: sum and count of the errors, for its shift.
    let mut tiles: HashMap<(i64, i64), (f64, usize)> = HashMap::new();
    for (p, m) in map.iter().zip(best).filter(|(_, m)| m.class() != NO_CLASS) {
        let t = tiles.entry(tile_of(p)).or_default();
        t.0 += m.error as f64;
        t.1 += 1;
    }
    let mut all = Errors::default();
    let mut classes: BTreeMap<u8, Errors> = BTreeMap::new();
    for (p, m) in map.iter().zip(best).filter(|(_, m)| m.class() != NO_CLASS) {
        let e = m.error as f64;
        let (sum, count) = tiles[&tile_of(p)];
        let tile_free = (count >= TILE_MIN_POINTS).then(|| e - sum / count as f64);
        let absolute = e + m.shift_along as f64;
        all.add(absolute, e, tile_free);
        classes.entry(m.class()).or_default().add(absolute, e, tile_free);
    }
    let mut std = AbsHistogram::new();
    map.iter().for_each(|p| std.add(p.std_m as f64));
    LatentMapEvaluation {
        points: map.len() as u64,
        matched: all.absolute.count(),
        error_rms_m: all.absolute.rms(),
        error_mean_m: all.absolute.mean(),
        error_without_campaign_shift_rms_m: all.campaign_free.rms(),
        error_without_campaign_shift_p95_abs_m: all.campaign_free.abs_quantile(0.95),
        error_without_tile_shift_rms_m: all.tile_free.rms(),
        std_median_m: std.quantile(0.5),
        per_class: classes
            .into_iter()
            .map(|(c, t)| {
                let name = SurfaceClass::from_u8(c).map_or("unknown", SurfaceClass::name).to_string();
                (
                    name,
                    LatentClassFigures {
                        matched: t.absolute.count(),
                        error_rms_m: t.absolute.rms(),
                        error_without_campaign_shift_rms_m: t.campaign_free.rms(),
                        error_without_tile_shift_rms_m: t.tile_free.rms(),
                    },
                )
            })
            .collect(),
    }
}

/// The three error figures of a set of map points: absolute, without the campaign's shift and
/// (where the point's tile has enough points) without the tile's.
#[derive(Default)]
struct Errors {
    absolute: ErrorStats,
    campaign_free: ErrorStats,
    tile_free: ErrorStats,
}

impl Errors {
    fn add(&mut self, absolute: f64, campaign_free: f64, tile_free: Option<f64>) {
        self.absolute.add(absolute);
        self.campaign_free.add(campaign_free);
        if let Some(e) = tile_free {
            self.tile_free.add(e);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use precimap_sim::truth::{TruthPoint, TruthWriter};

    fn map_point(position: [f64; 3], normal: [f32; 3]) -> LatentMapPoint {
        LatentMapPoint { position, normal, std_m: 0.002, observations: 5, passes: 3 }
    }

    /// Writes the test's truth (a road, a wall and foliage over the road) into `dir`, dealt
    /// round-robin into `strips` strips `s1`, `s2`, …; returns their ids.
    fn write_truth(dir: &Path, strips: usize) -> Vec<String> {
        std::fs::create_dir_all(dir).unwrap();
        let ids: Vec<String> = (1..=strips).map(|k| format!("s{k}")).collect();
        let mut writers: Vec<_> =
            ids.iter().map(|id| TruthWriter::create(&dir.join(format!("{id}.truth"))).unwrap()).collect();
        let point = |position, normal, class| TruthPoint { position, normal, surface_id: class as u32, class };
        let mut next = 0usize;
        let mut push = |p: TruthPoint| {
            writers[next % strips].push(&p).unwrap();
            next += 1;
        };
        for i in 0..100 {
            for j in 0..100 {
                let (x, y) = (1.0 + 0.02 * i as f64, 1.0 + 0.02 * j as f64);
                push(point([x, y, 0.0], [0.0, 0.0, -1.0], SurfaceClass::Road));
                push(point([3.0, x, 0.5 + 0.02 * j as f64], [-1.0, 0.0, 0.0], SurfaceClass::Facade));
                push(point([x, y, 0.004], [0.0, 0.0, 1.0], SurfaceClass::Foliage));
            }
        }
        for w in writers {
            w.finish().unwrap();
        }
        ids
    }

    /// A map 3 ± 1 mm above a true road whose normals face down, 1 mm in front of a wall, plus a
    /// point far from any truth and one whose normal agrees with no surface near it: the road
    /// and the wall are measured along the map's normals, per class, and the tile's shift
    /// comes off; foliage beside the map is never a match. The same truth dealt into seven
    /// strips gives the same figures.
    #[test]
    fn map_points_are_measured_against_the_nearest_agreeing_true_surface() {
        let dir = std::env::temp_dir().join(format!("precimap-eval-latent-{}", std::process::id()));
        let ids = write_truth(&dir, 1);
        let mut map = Vec::new();
        for i in 0..100 {
            let (x, y) = (1.05 + 0.1 * (i % 10) as f64, 1.05 + 0.1 * (i / 10) as f64);
            let z = if i % 2 == 0 { 0.004 } else { 0.002 };
            map.push(map_point([x, y, z], [0.0, 0.0, 1.0]));
            map.push(map_point([3.001, x, 0.6 + 0.1 * (i / 10) as f64], [1.0, 0.0, 0.0]));
        }
        map.push(map_point([5.0, 5.0, 5.0], [0.0, 0.0, 1.0]));
        map.push(map_point([1.5, 1.5, 0.003], [0.0, 1.0, 0.0]));
        // The map as the strips would place it with a datum error of (+40, −30, +20) mm.
        let shift = [0.04, -0.03, 0.02];
        for p in &mut map {
            for k in 0..3 {
                p.position[k] += shift[k];
            }
        }
        let f = evaluate_latent_map(&map, &ids, &dir, shift).unwrap();
        // The same truth dealt into 7 strips: each strip's best matches merge into the same
        // figures (the strips are matched in parallel, several into one array of matches).
        let dealt = std::env::temp_dir().join(format!("precimap-eval-latent-dealt-{}", std::process::id()));
        let dealt_ids = write_truth(&dealt, 7);
        let from_seven = evaluate_latent_map(&map, &dealt_ids, &dealt, shift).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        std::fs::remove_dir_all(&dealt).unwrap();
        assert_eq!(from_seven, f);
        assert_eq!((f.points, f.matched), (202, 200), "{f:?}");
        let road = &f.per_class["road"];
        let facade = &f.per_class["facade"];
        assert_eq!((road.matched, facade.matched), (100, 100), "{f:?}");
        let rms = |a: f64, b: f64| ((a * a + b * b) / 2.0).sqrt();
        assert!((road.error_without_campaign_shift_rms_m - rms(0.004, 0.002)).abs() < 1e-5, "{f:?}");
        assert!((facade.error_without_campaign_shift_rms_m - 0.001).abs() < 1e-5, "{f:?}");
        // With the datum: the road 20 mm higher, the wall 40 mm further out.
        assert!((road.error_rms_m - rms(0.024, 0.022)).abs() < 1e-5, "{f:?}");
        assert!((facade.error_rms_m - 0.041).abs() < 1e-5, "{f:?}");
        assert!((f.error_mean_m - (0.023 + 0.041) / 2.0).abs() < 1e-5, "{f:?}");
        // One tile: its mean (2 mm) comes off every point.
        let want = ((100.0 * 0.001f64.powi(2) + 100.0 * 0.001f64.powi(2) + 100.0 * 0.001f64.powi(2)) / 200.0).sqrt();
        assert!((f.error_without_tile_shift_rms_m - want).abs() < 1e-5, "{} {want}", f.error_without_tile_shift_rms_m);
    }

    /// Truth points equally far from a map point in several strips: the first strip's is the
    /// match, whichever thread matched which strip (each strip puts its point on another side,
    /// so each would give another error). Repeated 200 times: a race shows only sometimes (a
    /// comparison by distance alone failed 4 runs in 5).
    #[test]
    fn equally_near_truth_points_resolve_to_the_first_strip() {
        let dir = std::env::temp_dir().join(format!("precimap-eval-latent-ties-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let strips = 12;
        let ids: Vec<String> = (0..strips).map(|k| format!("t{k}")).collect();
        // Map points on a 10 cm grid at z = 0; strip k's truth point at each lies 1 cm away,
        // above (even k) or below (odd k), with a class that tells four strips in a row apart.
        let map: Vec<LatentMapPoint> = (0..400)
            .map(|i| map_point([0.05 + 0.1 * (i % 20) as f64, 0.05 + 0.1 * (i / 20) as f64, 0.0], [0.0, 0.0, 1.0]))
            .collect();
        let classes = [SurfaceClass::Sidewalk, SurfaceClass::Road, SurfaceClass::Curb, SurfaceClass::Car];
        for (k, id) in ids.iter().enumerate() {
            let mut w = TruthWriter::create(&dir.join(format!("{id}.truth"))).unwrap();
            let z = if k % 2 == 0 { 0.01 } else { -0.01 };
            for m in &map {
                let [x, y, _] = m.position;
                let class = classes[k % 4];
                w.push(&TruthPoint { position: [x, y, z], normal: [0.0, 0.0, 1.0], surface_id: k as u32, class })
                    .unwrap();
            }
            w.finish().unwrap();
        }
        for _ in 0..200 {
            let f = evaluate_latent_map(&map, &ids, &dir, [0.0; 3]).unwrap();
            assert_eq!(f.matched, 400);
            // t0's point lies 1 cm above each map point: the map is 1 cm below it.
            assert!((f.error_mean_m + 0.01).abs() < 1e-6, "{f:?}");
            assert_eq!(f.per_class.keys().collect::<Vec<_>>(), ["sidewalk"], "{f:?}");
        }
        let later: Vec<String> = ids[1..].to_vec();
        let f = evaluate_latent_map(&map, &later, &dir, [0.0; 3]).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        // Without t0, t1's point below each map point.
        assert!((f.error_mean_m - 0.01).abs() < 1e-6, "{f:?}");
        assert_eq!(f.per_class.keys().collect::<Vec<_>>(), ["road"], "{f:?}");
    }
}
