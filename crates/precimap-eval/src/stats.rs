//! Pure, mergeable statistics the evaluation is built from: error moments with an |error|
//! histogram for percentiles, and per tile–strip means for the strip offset spread.

use precimap_core::hash::FxHashMap;
use precimap_core::histogram::LogBins;
use precimap_core::TileKey;
use std::collections::{BTreeMap, HashMap};

/// Smallest |error| the histogram resolves (1 µm); anything below falls into the first bin.
const HIST_MIN_M: f64 = 1e-6;
/// Largest |error| the histogram resolves (100 m); anything above falls into the last bin.
const HIST_MAX_M: f64 = 100.0;
/// Bin edges grow by this ratio: percentiles are exact to ±0.25 %.
const HIST_RATIO: f64 = 1.005;

/// Histogram of |error| on logarithmic bins: constant memory (~30 KB) whatever the number of
/// points, mergeable across strips and threads, percentiles to ±0.25 %.
#[derive(Clone, Debug, PartialEq)]
pub struct AbsHistogram {
    /// `bins[0]`: |e| < HIST_MIN_M; `bins[k]` for k ≥ 1: HIST_MIN_M·r^(k−1) ≤ |e| < HIST_MIN_M·r^k;
    /// the last bin also takes everything larger.
    bins: Vec<u64>,
}

impl Default for AbsHistogram {
    fn default() -> Self {
        Self::new()
    }
}

impl AbsHistogram {
    fn bins() -> LogBins {
        LogBins::spanning(HIST_MIN_M, HIST_MAX_M, HIST_RATIO)
    }

    pub fn new() -> Self {
        Self { bins: vec![0; Self::bins().count] }
    }

    pub fn add(&mut self, e: f64) {
        self.bins[Self::bins().index(e.abs())] += 1;
    }

    pub fn merge(&mut self, other: &Self) {
        LogBins::merge(&mut self.bins, &other.bins);
    }

    pub fn count(&self) -> u64 {
        self.bins.iter().sum()
    }

    /// The `q`-quantile (0 < q ≤ 1, nearest rank) of |error| as the geometric centre of its bin;
    /// NaN when empty.
    pub fn quantile(&self, q: f64) -> f64 {
        match LogBins::quantile_bin(&self.bins, q) {
            None => f64::NAN,
            Some(0) => 0.5 * HIST_MIN_M,
            Some(k) if k == self.bins.len() - 1 => HIST_MAX_M,
            Some(k) => HIST_MIN_M * HIST_RATIO.powf(k as f64 - 0.5),
        }
    }
}

/// Count, mean, RMS and |error| percentiles of signed errors; mergeable.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ErrorStats {
    count: u64,
    sum: f64,
    sum_sq: f64,
    hist: AbsHistogram,
}

impl ErrorStats {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn add(&mut self, e: f64) {
        self.count += 1;
        self.sum += e;
        self.sum_sq += e * e;
        self.hist.add(e);
    }

    pub fn merge(&mut self, other: &Self) {
        self.count += other.count;
        self.sum += other.sum;
        self.sum_sq += other.sum_sq;
        self.hist.merge(&other.hist);
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    /// NaN when empty.
    pub fn mean(&self) -> f64 {
        self.sum / self.count as f64
    }

    /// Root mean square; NaN when empty.
    pub fn rms(&self) -> f64 {
        (self.sum_sq / self.count as f64).sqrt()
    }

    /// `q`-quantile of |error| (±0.25 %); NaN when empty.
    pub fn abs_quantile(&self, q: f64) -> f64 {
        self.hist.quantile(q)
    }
}

/// Per (group, strip): number of samples, sum of signed errors and sum of the true unit normals
/// (zero where the samples came without one, [`GroupStripMeans::add`]). Groups are tiles
/// ([`TileStripMeans`]) or (tile, true surface) pairs ([`SurfaceStripMeans`]).
#[derive(Clone, Debug, PartialEq)]
pub struct GroupStripMeans<K: Eq + std::hash::Hash> {
    cells: FxHashMap<(K, u32), (u64, f64, [f64; 3])>,
}

/// Strip means per 15 m tile.
pub type TileStripMeans = GroupStripMeans<TileKey>;
/// Strip means per (tile, true surface id): strips compared only where they measured the same
/// surface, so a shift shared by all strips cancels even where strips see differently oriented
/// surfaces (e.g. the two faces of a building corner) — though not on a surface that itself
/// faces several ways (a pole's sides, a car), where [`GroupStripMeans::spread_of_without_shift`]
/// removes it.
pub type SurfaceStripMeans = GroupStripMeans<(TileKey, u32)>;
/// Strip means per (surface class, tile, true surface id): the same-surface spread of one class's
/// points alone (curbs, poles, cars: the thin and two-sided structures where the latent map's
/// surface models are hardest to form).
pub type ClassSurfaceStripMeans = GroupStripMeans<(u8, TileKey, u32)>;

impl<K: Eq + std::hash::Hash> Default for GroupStripMeans<K> {
    fn default() -> Self {
        Self { cells: FxHashMap::default() }
    }
}

impl<K: Copy + Eq + Ord + std::hash::Hash> GroupStripMeans<K> {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn add(&mut self, tile: K, strip: u32, e: f64) {
        self.add_oriented(tile, strip, e, [0.0; 3]);
    }

    /// [`Self::add`] with the sample's true unit normal, for
    /// [`Self::spread_of_without_shift`].
    pub fn add_oriented(&mut self, group: K, strip: u32, e: f64, normal: [f64; 3]) {
        let c = self.cells.entry((group, strip)).or_insert((0, 0.0, [0.0; 3]));
        c.0 += 1;
        c.1 += e;
        (0..3).for_each(|a| c.2[a] += normal[a]);
    }

    pub fn merge(&mut self, other: Self) {
        for (k, (n, s, sn)) in other.cells {
            let c = self.cells.entry(k).or_insert((0, 0.0, [0.0; 3]));
            c.0 += n;
            c.1 += s;
            (0..3).for_each(|a| c.2[a] += sn[a]);
        }
    }

    /// Strip offset spread: for every tile–strip pair with at least `min_points` samples its mean
    /// error; minus the mean of those means over the tile's strips (tiles with one such strip
    /// carry no inter-strip information and are skipped); RMS over all remaining pairs. Returns
    /// `(spread, pairs)`, spread NaN when no pair counts. Deterministic (summed in key order).
    pub fn spread(&self, min_points: usize) -> (f64, usize) {
        self.spread_of(min_points, |_| true)
    }

    /// [`Self::spread`] over the groups `keep` accepts only (e.g. the groups of one surface class).
    pub fn spread_of(&self, min_points: usize, keep: impl Fn(&K) -> bool) -> (f64, usize) {
        self.spread_of_without_shift(min_points, keep, [0.0; 3])
    }

    /// [`Self::spread_of`] after removing the translation `d` from every sample (`e − d·n`, with
    /// the normals of [`Self::add_oriented`]): where a group's surface faces several ways (a
    /// pole seen from both sides), a shift shared by all strips moves their means apart,
    /// and this takes it out again. `d` = 0 gives [`Self::spread_of`] bit for bit.
    pub fn spread_of_without_shift(&self, min_points: usize, keep: impl Fn(&K) -> bool, d: [f64; 3]) -> (f64, usize) {
        self.spread_with(min_points, keep, |_, sum, sn| sum - (d[0] * sn[0] + d[1] * sn[1] + d[2] * sn[2]))
    }

    /// Every (group, strip) pair's distance from its group: `|mean − group mean|` after removing
    /// the translation `d` as [`Self::spread_of_without_shift`] does, over the groups with two or
    /// more strips of at least `min_points` samples that `keep` accepts; sorted ascending. Their
    /// RMS is that spread.
    pub fn deviations_without_shift(&self, min_points: usize, keep: impl Fn(&K) -> bool, d: [f64; 3]) -> Vec<f64> {
        let mut groups: BTreeMap<K, Vec<(u32, f64)>> = BTreeMap::new();
        for (&(group, strip), &(n, e, sn)) in &self.cells {
            if n >= min_points as u64 && n > 0 && keep(&group) {
                let sum = e - (d[0] * sn[0] + d[1] * sn[1] + d[2] * sn[2]);
                groups.entry(group).or_default().push((strip, sum / n as f64));
            }
        }
        let mut out = Vec::new();
        for means in groups.values_mut().filter(|m| m.len() >= 2) {
            means.sort_by_key(|&(strip, _)| strip);
            let mean = means.iter().map(|m| m.1).sum::<f64>() / means.len() as f64;
            out.extend(means.iter().map(|m| (m.1 - mean).abs()));
        }
        out.sort_by(f64::total_cmp);
        out
    }

    /// The spread of the groups `keep` accepts, with each (group, strip) pair's error sum
    /// replaced by `sum(group, Σe, Σn)` before it is divided by the count.
    fn spread_with(
        &self,
        min_points: usize,
        keep: impl Fn(&K) -> bool,
        mut sum: impl FnMut(K, f64, [f64; 3]) -> f64,
    ) -> (f64, usize) {
        let mut tiles: BTreeMap<K, Vec<(u32, f64)>> = BTreeMap::new();
        for (&(tile, strip), &(n, e, sn)) in &self.cells {
            if n >= min_points as u64 && n > 0 && keep(&tile) {
                tiles.entry(tile).or_default().push((strip, sum(tile, e, sn) / n as f64));
            }
        }
        let (mut sum_sq, mut pairs) = (0.0, 0usize);
        for means in tiles.values_mut() {
            if means.len() < 2 {
                continue;
            }
            means.sort_by_key(|&(strip, _)| strip);
            let tile_mean = means.iter().map(|m| m.1).sum::<f64>() / means.len() as f64;
            sum_sq += means.iter().map(|m| (m.1 - tile_mean).powi(2)).sum::<f64>();
            pairs += means.len();
        }
        if pairs == 0 {
            return (f64::NAN, 0);
        }
        ((sum_sq / pairs as f64).sqrt(), pairs)
    }
}

/// A tile, the RMS of its strips' offsets, and each strip's offset from the tile's mean.
pub type TileOffsets = (TileKey, f64, Vec<(u32, f64)>);

impl GroupStripMeans<TileKey> {
    /// The `count` tiles whose strips disagree most (RMS of the strips' mean errors minus the
    /// tile's mean), each with every qualifying strip's offset: `(tile, rms, [(strip, offset)])`,
    /// worst first. Where all strips of one scan head agree and the heads disagree, the error is a
    /// deformation shared by all passes rather than a misalignment between them.
    pub fn worst_tiles(&self, min_points: usize, count: usize) -> Vec<TileOffsets> {
        let mut tiles: BTreeMap<TileKey, Vec<(u32, f64)>> = BTreeMap::new();
        for (&(tile, strip), &(n, sum, _)) in &self.cells {
            if n >= min_points as u64 && n > 0 {
                tiles.entry(tile).or_default().push((strip, sum / n as f64));
            }
        }
        let mut out: Vec<_> = tiles
            .into_iter()
            .filter(|(_, strips)| strips.len() >= 2)
            .map(|(tile, mut strips)| {
                strips.sort_by_key(|s| s.0);
                let mean = strips.iter().map(|s| s.1).sum::<f64>() / strips.len() as f64;
                let offsets: Vec<(u32, f64)> = strips.iter().map(|&(k, m)| (k, m - mean)).collect();
                let rms = (offsets.iter().map(|o| o.1 * o.1).sum::<f64>() / offsets.len() as f64).sqrt();
                (tile, rms, offsets)
            })
            .collect();
        out.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        out.truncate(count);
        out
    }
}

/// Sums that let the strip offset spread be recomputed after removing a translation shared by
/// every strip: per (tile, strip) the count, Σe and Σn; per tile Σnnᵀ and Σne (n the true unit
/// normal, e the signed normal error). A shared translation d shifts a strip's mean error by
/// d·n̄, so where strips see differently oriented surfaces it shows in the spread although the
/// strips agree; these figures tell how much of the spread such a shift explains.
#[derive(Clone, Debug, Default)]
pub struct ShiftFreeMeans {
    pairs: TileStripMeans,
    tiles: FxHashMap<TileKey, ([[f64; 3]; 3], [f64; 3])>,
    /// Per tile Σ of the trajectory position error at each surface point's time, and the count.
    datum: FxHashMap<TileKey, ([f64; 3], u64)>,
}

impl ShiftFreeMeans {
    pub fn new() -> Self {
        Self::default()
    }

    /// `normal` must be a unit vector.
    pub fn add(&mut self, tile: TileKey, strip: u32, e: f64, normal: [f64; 3]) {
        self.pairs.add_oriented(tile, strip, e, normal);
        let t = self.tiles.entry(tile).or_insert(([[0.0; 3]; 3], [0.0; 3]));
        for a in 0..3 {
            t.1[a] += normal[a] * e;
            for b in 0..3 {
                t.0[a][b] += normal[a] * normal[b];
            }
        }
    }

    /// The position error of the trajectory that measured a surface point of `tile`, at the
    /// point's time (for [`Self::spread_of_local_datum`]).
    pub fn add_datum_sample(&mut self, tile: TileKey, error: [f64; 3]) {
        let d = self.datum.entry(tile).or_insert(([0.0; 3], 0));
        (0..3).for_each(|a| d.0[a] += error[a]);
        d.1 += 1;
    }

    pub fn merge(&mut self, other: Self) {
        for (k, (s, n)) in other.datum {
            let d = self.datum.entry(k).or_insert(([0.0; 3], 0));
            (0..3).for_each(|a| d.0[a] += s[a]);
            d.1 += n;
        }
        self.pairs.merge(other.pairs);
        for (k, (nn, ne)) in other.tiles {
            let t = self.tiles.entry(k).or_insert(([[0.0; 3]; 3], [0.0; 3]));
            for a in 0..3 {
                t.1[a] += ne[a];
                (0..3).for_each(|b| t.0[a][b] += nn[a][b]);
            }
        }
    }

    /// The least-squares translation of all points of the campaign (minimum norm in directions
    /// no normal constrains).
    pub fn campaign_shift(&self) -> [f64; 3] {
        let mut keys: Vec<&TileKey> = self.tiles.keys().collect();
        keys.sort();
        let (mut nn, mut ne) = ([[0.0; 3]; 3], [0.0; 3]);
        for k in keys {
            let t = &self.tiles[k];
            for a in 0..3 {
                ne[a] += t.1[a];
                (0..3).for_each(|b| nn[a][b] += t.0[a][b]);
            }
        }
        least_squares_shift(&nn, &ne)
    }

    /// Spread after removing one translation from every point of the campaign.
    pub fn spread_without_campaign_shift(&self, min_points: usize) -> (f64, usize) {
        let d = self.campaign_shift();
        self.spread_without_shift(d, min_points)
    }

    /// Spread after removing the translation `d` from every point (zero: the plain spread). For
    /// the points of one class, `d` is the whole campaign's shift: a class's own least-squares
    /// shift would also absorb real disagreement where the class is seen from one side only.
    pub fn spread_without_shift(&self, d: [f64; 3], min_points: usize) -> (f64, usize) {
        self.spread_without(|_| d, min_points)
    }

    /// Spread after removing, in every tile, the translation shared by all its points: what is
    /// left is disagreement between strips that no common motion explains.
    pub fn spread_without_tile_shift(&self, min_points: usize) -> (f64, usize) {
        self.spread_without(
            |tile| self.tiles.get(&tile).map_or([0.0; 3], |t| least_squares_shift(&t.0, &t.1)),
            min_points,
        )
    }

    /// The spread of strips that differ from the truth by nothing but the translation `d` shared
    /// by every point: what an absolute (datum) error alone puts into the spread.
    pub fn spread_of_shift(&self, d: [f64; 3], min_points: usize) -> (f64, usize) {
        self.spread_with(|_, _, sn| d[0] * sn[0] + d[1] * sn[1] + d[2] * sn[2], min_points)
    }

    /// The spread of strips that differ from the truth, in every tile, by nothing but the mean
    /// trajectory position error of the tile's surface points (the error every pass there
    /// shares, which relative data cannot see). Tiles without samples contribute no shift.
    pub fn spread_of_local_datum(&self, min_points: usize) -> (f64, usize) {
        let shift = |tile: TileKey| {
            self.datum.get(&tile).filter(|d| d.1 > 0).map_or([0.0; 3], |(s, n)| s.map(|v| v / *n as f64))
        };
        self.spread_with(
            |tile, _, sn| {
                let d = shift(tile);
                d[0] * sn[0] + d[1] * sn[1] + d[2] * sn[2]
            },
            min_points,
        )
    }

    fn spread_without(&self, shift: impl Fn(TileKey) -> [f64; 3], min_points: usize) -> (f64, usize) {
        let mut shifts: HashMap<TileKey, [f64; 3]> = HashMap::new();
        self.spread_with(
            |tile, e, sn| {
                let d = *shifts.entry(tile).or_insert_with(|| shift(tile));
                e - (d[0] * sn[0] + d[1] * sn[1] + d[2] * sn[2])
            },
            min_points,
        )
    }

    /// The spread with each (tile, strip) pair's error sum replaced by `sum(tile, Σe, Σn)`.
    fn spread_with(&self, sum: impl FnMut(TileKey, f64, [f64; 3]) -> f64, min_points: usize) -> (f64, usize) {
        self.pairs.spread_with(min_points, |_| true, sum)
    }
}

/// Minimum-norm solution of the 3×3 normal equations `nn·d = ne` (directions carrying less
/// than 10⁻⁶ of the strongest direction's information are left at zero).
fn least_squares_shift(nn: &[[f64; 3]; 3], ne: &[f64; 3]) -> [f64; 3] {
    let m = nalgebra::Matrix3::from_fn(|a, b| nn[a][b]);
    let eig = nalgebra::SymmetricEigen::new(m);
    let max = eig.eigenvalues.max();
    let mut d = nalgebra::Vector3::zeros();
    if max <= 0.0 {
        return [0.0; 3];
    }
    let rhs = nalgebra::Vector3::new(ne[0], ne[1], ne[2]);
    for (j, &lambda) in eig.eigenvalues.iter().enumerate() {
        if lambda > 1e-6 * max {
            let v = eig.eigenvectors.column(j);
            d += v * (v.dot(&rhs) / lambda);
        }
    }
    [d[0], d[1], d[2]]
}

/// [`TileStripMeans::spread`] of `(tile of the true position, strip, signed normal error)` samples.
pub fn strip_offset_spread(samples: impl Iterator<Item = (TileKey, u32, f64)>, min_points: usize) -> (f64, usize) {
    let mut acc = TileStripMeans::new();
    for (tile, strip, e) in samples {
        acc.add(tile, strip, e);
    }
    acc.spread(min_points)
}

/// Signed distance of a measured point from the true surface along the true normal,
/// `(p − p_true)·n / |n|`; `None` for a zero or non-finite normal.
pub fn signed_normal_error(p: [f64; 3], p_true: [f64; 3], n: [f32; 3]) -> Option<f64> {
    let n = [n[0] as f64, n[1] as f64, n[2] as f64];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if !(len.is_finite() && len > 1e-6) {
        return None;
    }
    let d = [p[0] - p_true[0], p[1] - p_true[1], p[2] - p_true[2]];
    Some((d[0] * n[0] + d[1] * n[1] + d[2] * n[2]) / len)
}

#[cfg(test)]
mod tests {
    use super::*;

    const T0: TileKey = TileKey { tx: 0, ty: 0 };
    const T1: TileKey = TileKey { tx: 1, ty: 0 };
    const T2: TileKey = TileKey { tx: 0, ty: 1 };

    fn repeat(tile: TileKey, strip: u32, e: f64, n: usize) -> impl Iterator<Item = (TileKey, u32, f64)> {
        std::iter::repeat_n((tile, strip, e), n)
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn two_strips_offset_plus_minus_d() {
        let d = 0.013;
        let (s, pairs) = strip_offset_spread(repeat(T0, 0, d, 200).chain(repeat(T0, 1, -d, 300)), 200);
        assert!(close(s, d) && pairs == 2, "{s} {pairs}");
    }

    #[test]
    fn common_offset_gives_zero_spread() {
        let samples = repeat(T0, 0, 0.05, 250).chain(repeat(T0, 1, 0.05, 250)).chain(repeat(T0, 2, 0.05, 400));
        let (s, pairs) = strip_offset_spread(samples, 200);
        assert!(close(s, 0.0) && pairs == 3);
        // Different common offsets per tile still give zero: only agreement within a tile counts.
        let samples = repeat(T0, 0, 0.05, 200)
            .chain(repeat(T0, 1, 0.05, 200))
            .chain(repeat(T1, 0, -0.3, 200))
            .chain(repeat(T1, 1, -0.3, 200));
        assert_eq!(strip_offset_spread(samples, 200), (0.0, 4));
    }

    /// A building corner: both strips are shifted alike by (+0.1, −0.1) m, but strip 0 sees mostly
    /// the face with normal +x and strip 1 mostly the face with normal +y. The tile spread reports
    /// the shared shift; compared on the same surface, the strips agree.
    #[test]
    fn shared_shift_at_a_corner_cancels_on_the_same_surface() {
        let (face_x, face_y) = (0.1, -0.1);
        let mut tiles = TileStripMeans::new();
        let mut surfaces = SurfaceStripMeans::new();
        for (strip, on_x, on_y) in [(0u32, 900, 300), (1, 300, 900)] {
            for (surface, e, n) in [(1u32, face_x, on_x), (2, face_y, on_y)] {
                for _ in 0..n {
                    tiles.add(T0, strip, e);
                    surfaces.add((T0, surface), strip, e);
                }
            }
        }
        let (tile_spread, _) = tiles.spread(200);
        let (surface_spread, pairs) = surfaces.spread(200);
        assert!(close(tile_spread, 0.05), "{tile_spread}");
        assert!(close(surface_spread, 0.0) && pairs == 4, "{surface_spread} {pairs}");
    }

    /// A pole seen from opposite sides: both strips are shifted alike by 0.05 m along x, strip 0
    /// sees the face with normal +x and strip 1 the face with normal −x. On the pole as one
    /// surface the shared shift shows as ±0.05 m; with the shift removed the strips agree, while
    /// a real disagreement (strip 1 off by another 4 mm along its normal) is kept.
    #[test]
    fn shared_shift_on_a_two_sided_surface_cancels_once_removed() {
        let d = [0.05, 0.0, 0.0];
        for (extra, expected) in [(0.0, 0.0), (0.004, 0.002)] {
            let mut pole = SurfaceStripMeans::new();
            for (strip, normal, off) in [(0u32, [1.0, 0.0, 0.0], 0.0), (1, [-1.0, 0.0, 0.0], extra)] {
                let e = d[0] * normal[0] + off;
                for _ in 0..300 {
                    pole.add_oriented((T0, 7), strip, e, normal);
                }
            }
            let (with_shift, pairs) = pole.spread_of(200, |_| true);
            let (without, _) = pole.spread_of_without_shift(200, |_| true, d);
            assert!(pairs == 2 && with_shift > 0.045, "{with_shift} {pairs}");
            assert!((without - expected).abs() < 1e-9, "{extra}: {without}");
        }
    }

    /// A class's spread counts that class's groups only: the road agrees, the curb does not.
    #[test]
    fn spread_of_one_class_ignores_the_other_classes() {
        let (road, curb) = (1u8, 3u8);
        let mut classes = GroupStripMeans::<(u8, TileKey)>::new();
        for (strip, curb_offset) in [(0u32, 0.004), (1, -0.004)] {
            for _ in 0..300 {
                classes.add((road, T0), strip, 0.02);
                classes.add((curb, T0), strip, curb_offset);
            }
        }
        let (road_spread, road_pairs) = classes.spread_of(200, |k| k.0 == road);
        let (curb_spread, curb_pairs) = classes.spread_of(200, |k| k.0 == curb);
        assert!(close(road_spread, 0.0) && road_pairs == 2, "{road_spread} {road_pairs}");
        assert!(close(curb_spread, 0.004) && curb_pairs == 2, "{curb_spread} {curb_pairs}");
        assert!(classes.spread_of(301, |k| k.0 == road).0.is_nan(), "groups under the minimum do not count");
    }

    #[test]
    fn noise_averages_out_within_a_tile_strip() {
        // Zero-mean scatter around the strip's offset does not count, only the offset does.
        let samples = (0..400).map(|i| (T0, 0, 0.01 + if i % 2 == 0 { 0.004 } else { -0.004 }));
        let samples = samples.chain((0..400).map(|i| (T0, 1, -0.01 + if i % 2 == 0 { 0.02 } else { -0.02 })));
        let (s, pairs) = strip_offset_spread(samples, 200);
        assert!(close(s, 0.01) && pairs == 2);
    }

    /// A translation shared by all strips at a corner shows in the plain spread; removing the
    /// campaign's shift (or the tile's) leaves only the real disagreement.
    #[test]
    fn shared_shift_at_a_corner_is_removed_by_the_shift_free_spreads() {
        let d = [0.10, -0.13, 0.02];
        let faces = [[0.78f64, 0.22, 0.0], [0.26, 0.74, 0.0], [0.0, 0.0, 1.0]];
        let unit = |n: [f64; 3]| {
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            [n[0] / l, n[1] / l, n[2] / l]
        };
        let mut acc = ShiftFreeMeans::new();
        let mut plain = TileStripMeans::new();
        let mut shift_only = TileStripMeans::new();
        // Strip 0 sees face 0 and the road, strip 1 face 1 and the road; strip 2 is 4 mm off on the road.
        for (strip, face, extra) in [(0u32, 0usize, 0.0), (1, 1, 0.0), (2, 2, 0.004)] {
            for k in 0..400 {
                let n = unit(if k % 2 == 0 { faces[face] } else { faces[2] });
                let e = d[0] * n[0] + d[1] * n[1] + d[2] * n[2] + extra;
                acc.add(T0, strip, e, n);
                plain.add(T0, strip, e);
                // A second tile with another shift, seen by all strips alike.
                acc.add(T1, strip, 0.05 * n[2], n);
                for tile in [T0, T1] {
                    shift_only.add(tile, strip, d[0] * n[0] + d[1] * n[1] + d[2] * n[2]);
                }
            }
        }
        assert!(plain.spread(200).0 > 0.03);
        let (tile_free, pairs) = acc.spread_without_tile_shift(200);
        assert_eq!(pairs, 6);
        // Only strip 2's 4 mm remain in tile 0: the tile's fit takes 2 mm of it into its vertical
        // shift (800 road points, 400 of them 4 mm off), leaving offsets −1, −1, +2 mm; tile 1
        // adds three zero offsets.
        assert!((tile_free - 0.001).abs() < 1e-6, "{tile_free}");
        let campaign = acc.spread_without_campaign_shift(200).0;
        assert!(campaign < plain.spread(200).0 && campaign > tile_free, "{campaign}");
        // What the shift alone contributes: strips that differ from the truth by d only.
        let (of_shift, pairs) = acc.spread_of_shift(d, 200);
        assert_eq!(pairs, 6);
        assert!(of_shift > 0.03 && (of_shift - shift_only.spread(200).0).abs() < 1e-12, "{of_shift}");
        // The same shift as every tile's local datum gives the same spread; a tile without
        // samples contributes none.
        let mut local = acc.clone();
        local.add_datum_sample(T0, [2.0 * d[0], 2.0 * d[1], 2.0 * d[2]]);
        local.add_datum_sample(T0, [0.0; 3]);
        local.add_datum_sample(T1, d);
        assert!((local.spread_of_local_datum(200).0 - of_shift).abs() < 1e-12);
        assert!(acc.spread_of_local_datum(200).0 < 1e-12);
    }

    #[test]
    fn single_strip_tiles_and_sparse_pairs_are_ignored() {
        let d = 0.02;
        let samples = repeat(T0, 0, d, 200)
            .chain(repeat(T0, 1, -d, 200))
            // A third strip with too few points in T0 is ignored (it would pull the tile mean).
            .chain(repeat(T0, 2, 1.0, 199))
            // T1: one strip only (the other has 199 points) → no inter-strip information.
            .chain(repeat(T1, 0, 0.5, 1000))
            .chain(repeat(T1, 1, -0.5, 199))
            // T2: one strip only.
            .chain(repeat(T2, 3, 0.7, 5000));
        let (s, pairs) = strip_offset_spread(samples, 200);
        assert!(close(s, d) && pairs == 2, "{s} {pairs}");
        let (s, pairs) = strip_offset_spread(repeat(T2, 3, 0.7, 5000), 200);
        assert!(s.is_nan() && pairs == 0);
        assert!(strip_offset_spread(std::iter::empty(), 200).0.is_nan());
    }

    #[test]
    fn spread_over_several_tiles_is_rms_of_all_pairs() {
        // T0: strips at +a, −a (deviations ±a); T1: three strips at 0, 0, 3b (mean b; deviations
        // −b, −b, 2b). RMS over 5 pairs = sqrt((2a² + 6b²) / 5).
        let (a, b) = (0.01, 0.004);
        let samples = repeat(T0, 0, a, 200)
            .chain(repeat(T0, 1, -a, 200))
            .chain(repeat(T1, 0, 0.0, 300))
            .chain(repeat(T1, 1, 0.0, 300))
            .chain(repeat(T1, 2, 3.0 * b, 300));
        let (s, pairs) = strip_offset_spread(samples, 200);
        assert!(close(s, ((2.0 * a * a + 6.0 * b * b) / 5.0).sqrt()) && pairs == 5, "{s}");
    }

    #[test]
    fn merging_accumulators_equals_one_pass() {
        let mut worst = TileStripMeans::new();
        for (tile, strip, e) in repeat(T0, 0, 0.01, 250)
            .chain(repeat(T0, 1, -0.01, 250))
            .chain(repeat(T1, 0, 0.002, 250))
            .chain(repeat(T1, 1, 0.0, 250))
        {
            worst.add(tile, strip, e);
        }
        let w = worst.worst_tiles(200, 5);
        assert_eq!(w.len(), 2);
        assert_eq!(w[0].0, T0);
        assert!(
            (w[0].1 - 0.01).abs() < 1e-12 && (w[0].2[0].1 - 0.01).abs() < 1e-12 && (w[0].2[1].1 + 0.01).abs() < 1e-12
        );
        assert!((w[1].1 - 0.001).abs() < 1e-12);
        let mut a = TileStripMeans::new();
        let mut b = TileStripMeans::new();
        for i in 0..300 {
            a.add(T0, 0, 0.01);
            b.add(T0, 1, -0.01 + i as f64 * 1e-6);
        }
        let mut all = a.clone();
        all.merge(b.clone());
        let one: Vec<_> = repeat(T0, 0, 0.01, 300).chain((0..300).map(|i| (T0, 1, -0.01 + i as f64 * 1e-6))).collect();
        let (s1, p1) = strip_offset_spread(one.into_iter(), 200);
        let (s2, p2) = all.spread(200);
        assert!(close(s1, s2) && p1 == p2);
    }

    #[test]
    fn error_stats_moments_and_percentiles() {
        let mut s = ErrorStats::new();
        assert!(s.rms().is_nan() && s.mean().is_nan() && s.abs_quantile(0.95).is_nan());
        // 100 errors ±1..±100 mm: |e| p95 (nearest rank) = 95 mm.
        for k in 1..=100 {
            s.add(if k % 2 == 0 { k as f64 * 1e-3 } else { -(k as f64) * 1e-3 });
        }
        assert_eq!(s.count(), 100);
        assert!(close(s.mean(), 0.5e-3)); // 50 pairs of (+k, −(k−1)) mm
        let rms = ((1..=100).map(|k| (k as f64 * 1e-3).powi(2)).sum::<f64>() / 100.0).sqrt();
        assert!(close(s.rms(), rms));
        let p95 = s.abs_quantile(0.95);
        assert!((p95 / 0.095 - 1.0).abs() < 0.0026, "{p95}");
        let mut t = ErrorStats::new();
        t.add(1e-9);
        t.add(f64::INFINITY);
        assert_eq!(t.abs_quantile(0.5), 0.5e-6);
        assert_eq!(t.abs_quantile(1.0), 100.0);
        let mut m = ErrorStats::new();
        m.merge(&s);
        assert_eq!(m, s);
    }

    #[test]
    fn signed_normal_error_uses_the_normal_direction() {
        let e = signed_normal_error([1.0, 2.0, 3.5], [1.0, 2.0, 3.0], [0.0, 0.0, 2.0]).unwrap();
        assert!(close(e, 0.5));
        let e = signed_normal_error([549_800.3, 5_803_400.0, 0.0], [549_800.0, 5_803_400.2, 0.0], [-1.0, 0.0, 0.0]);
        assert!((e.unwrap() + 0.3).abs() < 1e-9);
        assert!(signed_normal_error([0.0; 3], [0.0; 3], [0.0; 3]).is_none());
        assert!(signed_normal_error([0.0; 3], [0.0; 3], [f32::NAN, 0.0, 1.0]).is_none());
    }
}
