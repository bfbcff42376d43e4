//! Steps 3–4 of [`super::estimate_tile`]: every point of the tile's core compared with the
//! latent map, and the observations within the outlier threshold summed into per-anchor
//! normal-equation blocks and the common-mode field's rows.

use super::point::PointLatent;
use super::pulls::{jacobian, CornerPulls};
use super::triangles::Triangles;
use super::{UsedPoint, NONE};
use crate::blocks::{AnchorBlock, IntervalMoments, TrajectoryBlocks};
use crate::calibration::{interval_terms, AttitudeRows, CalibrationNormals, TileCalibration};
use crate::control::TargetObservation;
use crate::field::{FieldAccumulator, FieldRow};
use crate::stats::{ResidualHistogram, TileStats};
use precimap_core::CalibrationUnknown;
use std::collections::BTreeMap;

/// What the observation loop reads: the tile's points on their surface models, per point the
/// measurement vector, the scan head (common-mode field only) and the latent map, and the
/// observations' weight and outlier threshold.
pub(super) struct Observations<'a> {
    pub(super) t: &'a Triangles<'a>,
    pub(super) measurement: &'a [[f64; 3]],
    /// Per chunk the body attitude at each anchor of its range, where the campaign estimates
    /// the calibration.
    pub(super) anchor_attitude: &'a [Vec<[[f64; 3]; 3]>],
    pub(super) vehicle: &'a [[f64; 2]],
    pub(super) latent: &'a [PointLatent],
    pub(super) weight: f64,
    pub(super) threshold: f64,
    /// The points' observations of control targets, sorted by point.
    pub(super) control: &'a [TargetObservation],
    /// The calibration, where the campaign estimates it.
    pub(super) calibration: Option<&'a TileCalibration<'a>>,
}

/// One chunk's calibration terms while its points are observed: the scanner's place among the
/// campaign's unknowns, the attitude rows at the chunk's anchors, with a range offset its index
/// in the scanner's block and its per-point cross moments per anchor interval (`Σ w·g_ρ·g` and
/// `Σ w·λ·g_ρ·g`), and the calibration's own normal equations (upper triangle of the scanner's
/// block, at most 7 × 7). The boresight's and lever arm's terms come per interval from its
/// moments ([`interval_terms`]).
struct ChunkCalibration<'a> {
    layout: &'a precimap_core::CalibrationLayout,
    per_scanner: usize,
    offset: usize,
    rows: Vec<AttitudeRows>,
    range: Option<usize>,
    range_moments: Vec<[[f64; 6]; 2]>,
    /// Per anchor interval, the consistent gradient's pulls across surface models: in the
    /// interval's moments, but without calibration columns.
    pulls_apart: Vec<IntervalMoments>,
    h: [f64; 28],
    b: [f64; 7],
}

impl ChunkCalibration<'_> {
    /// One observation along `w` of a point with beam `m`, with Jacobian row `g`, weighted
    /// residual `we` and weight `weight`: its range offset's column `m̂·w`, the one per point.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn add(&mut self, interval: usize, g: &[f64; 6], m: [f64; 3], w: [f64; 3], we: f64, weight: f64, lambda: f64) {
        let Some(j) = self.range else { return };
        let n = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
        let gr = if n > 0.0 { (m[0] * w[0] + m[1] * w[1] + m[2] * w[2]) / n } else { 0.0 };
        let [m0, m1] = &mut self.range_moments[interval];
        let (wg, wlg) = (weight * gr, weight * lambda * gr);
        for a in 0..6 {
            m0[a] += wg * g[a];
            m1[a] += wlg * g[a];
        }
        // (j, j) is the last entry of the upper triangle.
        let last = j * (j + 1) / 2 + j;
        self.h[last] += wg * gr;
        self.b[j] -= we * gr;
    }

    /// Interval `interval`'s terms ([`interval_terms`]) into the cross blocks of its anchors
    /// (`at`, `after`: 6 × the campaign's unknowns) and this chunk's normal equations.
    fn scatter(&mut self, interval: usize, moments: &IntervalMoments, at: &mut Vec<f64>, after: &mut Vec<f64>) {
        let (mut block, mut rhs) = moments.block();
        if let Some(apart) = self.pulls_apart.get(interval).filter(|a| !a.is_empty()) {
            let (b, r) = apart.block();
            for (row, other) in block.iter_mut().zip(&b) {
                row.iter_mut().zip(other).for_each(|(v, o)| *v -= o);
            }
            rhs.iter_mut().zip(&r).for_each(|(v, o)| *v -= o);
        }
        let range = self.range.map(|_| {
            let [m0, m1] = &self.range_moments[interval];
            let column: [f64; 12] = std::array::from_fn(|c| if c < 6 { m0[c] - m1[c] } else { m1[c - 6] });
            column
        });
        let mut cross = [[0.0; 7]; 12];
        let (rows_at, rows_next) = (&self.rows[interval], &self.rows[interval + 1]);
        interval_terms(&block, &rhs, rows_at, rows_next, range.as_ref(), &mut cross, &mut self.h, &mut self.b);
        let total = self.layout.len();
        for target in [&mut *at, &mut *after] {
            if target.is_empty() {
                target.resize(6 * total, 0.0);
            }
        }
        for (c, row) in cross.iter().enumerate() {
            let (target, a) = if c < 6 { (&mut *at, c) } else { (&mut *after, c - 6) };
            for (j, v) in row.iter().enumerate().take(self.per_scanner) {
                target[a * total + self.offset + j] += v;
            }
        }
    }

    /// The chunk's normal equations at the scanner's place among the campaign's unknowns.
    fn normals(&self) -> CalibrationNormals {
        let (k, total) = (self.per_scanner, self.layout.len());
        let mut n = CalibrationNormals::zeros(total);
        let mut at = 0;
        for i in 0..k {
            for j in i..k {
                let (r, c) = (self.offset + i, self.offset + j);
                n.h[r * total + c] = self.h[at];
                n.h[c * total + r] = self.h[at];
                at += 1;
            }
            n.b[self.offset + i] = self.b[i];
        }
        n
    }
}

/// Observes every point of the tile's core: its height above its model's plane minus the latent
/// height there. Observations within the threshold are linearised into the blocks of their
/// trajectory's anchors and, with `field`, into the common-mode field's rows; with `pulls` (the
/// consistent gradient) a point also carries what the other points' residuals pull on it. A
/// point that observes a control target adds that observation to its blocks and, against the
/// fixed target, to the field's rows. Counts
/// and the residual histogram go to `stats`, every used point to `used`.
pub(super) fn observe_points(
    o: &Observations,
    in_core: &impl Fn(&[f64; 3]) -> bool,
    mut pulls: Option<&mut CornerPulls>,
    mut field: Option<&mut FieldAccumulator>,
    stats: &mut TileStats,
    mut used: Option<&mut Vec<UsedPoint>>,
) -> Vec<TrajectoryBlocks> {
    let (chunks, models, position, model_of) = (o.t.chunks, o.t.models, o.t.position, o.t.model_of);
    let (measurement, vehicle, weight, threshold) = (o.measurement, o.vehicle, o.weight, o.threshold);
    let mut histogram = ResidualHistogram::default();
    let mut per_trajectory: BTreeMap<u32, BTreeMap<u32, AnchorBlock>> = BTreeMap::new();
    let mut calibration_normals: BTreeMap<u32, CalibrationNormals> = BTreeMap::new();
    let mut base = 0usize;
    let mut control = o.control.iter().peekable();
    let with_pulls = pulls.is_some();
    for (index, chunk) in chunks.iter().enumerate() {
        let Some((first, last)) = chunk.anchor_range() else { continue };
        let mut intervals = vec![IntervalMoments::default(); (last - first) as usize];
        let mut cal = o.calibration.and_then(|c| {
            let (scanner, _) = c.of_strip(chunk.strip)?;
            let k = c.layout.per_scanner();
            assert!(k <= 7, "at most 7 calibration unknowns per scanner");
            let rows: Vec<AttitudeRows> =
                o.anchor_attitude.get(index)?.iter().map(|r| AttitudeRows::new(c.layout, r)).collect();
            let range = c.layout.kinds.contains(&CalibrationUnknown::RangeOffset).then_some(k - 1);
            Some(ChunkCalibration {
                layout: c.layout,
                per_scanner: k,
                offset: scanner as usize * k,
                rows,
                range,
                range_moments: if range.is_some() { vec![[[0.0; 6]; 2]; intervals.len()] } else { Vec::new() },
                pulls_apart: if with_pulls { vec![IntervalMoments::default(); intervals.len()] } else { Vec::new() },
                h: [0.0; 28],
                b: [0.0; 7],
            })
        });
        for k in 0..chunk.len() {
            let a = base + k;
            let lambda = chunk.lambda[k] as f64;
            let interval = (chunk.anchor[k] - first) as usize;
            let moments = &mut intervals[interval];
            // With a consistent gradient, what the other points' residuals pull on this one
            // through the triangles it is a corner of; on its own model the pull shares the
            // point's own Jacobian row, so it joins the point's observation below.
            let mut own_pull = match &mut pulls {
                Some(pulls) => {
                    let apart = cal.as_mut().map(|c| &mut c.pulls_apart[interval]);
                    pulls.take(a, models, measurement, moments, apart, lambda)
                }
                None => None,
            };
            let p = &position[a];
            let core = in_core(p);
            stats.points += core as u64;
            let id = model_of[a];
            let at = &o.latent[a];
            let latent = if core && id != NONE { at.height } else { f64::NAN };
            if !latent.is_nan() {
                let m = &models[id as usize];
                let h = m.height(p);
                stats.points_modelled += 1;
                let e = h - latent;
                histogram.add(e);
                if e.abs() <= threshold {
                    stats.points_used += 1;
                    if let Some(used) = used.as_deref_mut() {
                        used.push(UsedPoint { strip: chunk.strip, source: chunk.source[k], model: id });
                    }
                    stats.residual_sum_m += e;
                    stats.residual_sum2_m2 += e * e;
                    let w = m.w;
                    let g = jacobian(w, measurement[a]);
                    // With a consistent gradient the point pulls on its own pass by its share in
                    // the latent height; the covering passes get the rest (`corner_pulls`).
                    let own_weight = match &pulls {
                        Some(_) => weight * at.covering as f64 / (at.covering as f64 + 1.0),
                        None => weight,
                    };
                    // Both observations in one: weights add, and so do weight × residual.
                    let (total, weighted, observations) = match own_pull.take() {
                        Some([w_sum, we_sum]) => (own_weight + w_sum, own_weight * e - we_sum, 2),
                        None => (own_weight, own_weight * e, 1),
                    };
                    moments.add_weighted(&g, weighted, total, lambda, observations);
                    if let Some(cal) = cal.as_mut() {
                        cal.add(interval, &g, measurement[a], w, weighted, total, lambda);
                    }
                    if let Some(field) = field.as_deref_mut() {
                        let [x, y, share] = at.others;
                        field.add(FieldRow {
                            vehicle: vehicle[a],
                            others: [x, y],
                            k: share,
                            w,
                            e,
                            weight,
                            lever: [g[3], g[4], g[5]],
                            anchored: false,
                        });
                    }
                }
            }
            if let Some([w_sum, we_sum]) = own_pull {
                let w = models[id as usize].w;
                let g = jacobian(w, measurement[a]);
                moments.add(&g, -we_sum / w_sum, w_sum, lambda);
                if let Some(cal) = cal.as_mut() {
                    cal.add(interval, &g, measurement[a], w, -we_sum, w_sum, lambda);
                }
            }
            while let Some(c) = control.next_if(|c| c.point == a) {
                let g = jacobian(c.w, measurement[a]);
                moments.add_weighted(&g, c.weight * c.e, c.weight, lambda, 1);
                if let Some(cal) = cal.as_mut() {
                    cal.add(interval, &g, measurement[a], c.w, c.weight * c.e, c.weight, lambda);
                }
                if let Some(field) = field.as_deref_mut() {
                    field.add(FieldRow {
                        vehicle: vehicle[a],
                        others: vehicle[a],
                        k: 1.0,
                        w: c.w,
                        e: c.e,
                        weight: c.weight,
                        lever: [g[3], g[4], g[5]],
                        anchored: true,
                    });
                }
            }
        }
        let blocks = per_trajectory.entry(chunk.trajectory).or_default();
        scatter_intervals(blocks, first, &intervals, cal.as_mut());
        if let Some(cal) = cal {
            calibration_normals.entry(chunk.trajectory).or_default().add(&cal.normals());
        }
        base += chunk.len();
    }
    stats.histogram = histogram;
    per_trajectory
        .into_iter()
        .map(|(trajectory, map)| TrajectoryBlocks {
            trajectory,
            blocks: map.into_values().collect(),
            calibration: calibration_normals.remove(&trajectory),
        })
        .collect()
}

/// Adds the moments of a chunk's anchor intervals (the first from anchor `first`) to the blocks
/// of the anchors either side of each, and with a calibration their cross terms.
fn scatter_intervals(
    blocks: &mut BTreeMap<u32, AnchorBlock>,
    first: u32,
    intervals: &[IntervalMoments],
    mut cal: Option<&mut ChunkCalibration>,
) {
    for (offset, moments) in intervals.iter().enumerate() {
        if moments.is_empty() {
            continue;
        }
        let i = first + offset as u32;
        let mut at = blocks.remove(&i).unwrap_or_else(|| AnchorBlock::new(i));
        let after = blocks.entry(i + 1).or_insert_with(|| AnchorBlock::new(i + 1));
        moments.scatter(&mut at, after);
        if let Some(cal) = cal.as_deref_mut() {
            cal.scatter(offset, moments, &mut at.cross, &mut after.cross);
        }
        blocks.insert(i, at);
    }
}
