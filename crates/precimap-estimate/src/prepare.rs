//! Per-strip preparation (the `segment_strip` map task of DESIGN §3, before segmentation lands):
//! point geometry against the trajectory, the scan image (rows = measurement within a scanner
//! revolution, columns = revolutions), scan-image neighbours, normals from the scan-image
//! neighbourhood, and the points keyed into tiles with a border overlap.

use crate::chunk::{TileChunk, NO_NEIGHBOUR};
use precimap_core::{Parameters, TileKey, Trajectory, Vec3};
use std::collections::BTreeMap;

/// A strip's points in acquisition order (struct of arrays, as read from LAS).
#[derive(Clone, Copy, Debug)]
pub struct StripSamples<'a> {
    pub x: &'a [f64],
    pub y: &'a [f64],
    pub z: &'a [f64],
    pub gps_time: &'a [f64],
    pub scan_angle_deg: &'a [f32],
}

impl StripSamples<'_> {
    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PrepareError {
    #[error("point {index}: GPS time {time:.6} s lies outside the trajectory's span {start:.6}–{end:.6} s; supply a trajectory that covers the whole strip")]
    NotCovered { index: usize, time: f64, start: f64, end: f64 },
    #[error("point {index}: {field} is not a finite number")]
    NotFinite { index: usize, field: &'static str },
    #[error("point {index}: GPS time {time:.6} s is earlier than the previous point's {previous:.6} s; strips must be in acquisition order")]
    NotInOrder { index: usize, time: f64, previous: f64 },
    #[error("the strip has no points")]
    Empty,
    #[error("columns differ in length ({0})")]
    Shape(String),
}

/// Geometry of one measurement relative to its trajectory (DESIGN §2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeasurementGeometry {
    /// Scan-head position `t0 = c + R·ℓ` (absolute).
    pub t0: [f64; 3],
    /// Measurement vector `r = p − t0`.
    pub r: [f64; 3],
    /// Anchor index `⌊s/Δ⌋` and fraction.
    pub anchor: u32,
    pub lambda: f32,
    /// Vehicle speed at the measurement, m/s.
    pub speed: f64,
}

/// Geometry of the point `p` measured at time `t` by a scanner with lever arm `lever_arm`.
/// `None` when the trajectory does not cover `t`.
pub fn measurement_geometry(
    trajectory: &Trajectory,
    lever_arm: &Vec3,
    anchor_spacing_m: f64,
    t: f64,
    p: [f64; 3],
) -> Option<MeasurementGeometry> {
    let (i, lambda) = trajectory.locate(t)?;
    let pose = trajectory.pose_in_segment(i, lambda);
    let t0 = pose.position + pose.rotation * lever_arm;
    let arcs = trajectory.arc_lengths();
    let s = arcs[i] + (arcs[i + 1] - arcs[i]) * lambda;
    let times = trajectory.times();
    let speed = (arcs[i + 1] - arcs[i]) / (times[i + 1] - times[i]);
    let u = (s / anchor_spacing_m).max(0.0);
    let anchor = u.floor();
    Some(MeasurementGeometry {
        t0: [t0.x, t0.y, t0.z],
        r: [p[0] - t0.x, p[1] - t0.y, p[2] - t0.z],
        anchor: anchor as u32,
        lambda: (u - anchor) as f32,
        speed,
    })
}

/// Everything a strip contributes to estimation.
#[derive(Debug)]
pub struct PreparedStrip {
    pub chunks: Vec<TileChunk>,
    pub stats: PrepareStats,
}

#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PrepareStats {
    pub points: u64,
    /// Points with a usable normal (they go to the tiles).
    pub points_with_normal: u64,
    /// Emitted point copies, including border duplicates.
    pub points_emitted: u64,
    pub revolutions: u64,
    pub rows_per_revolution: u32,
    pub revolution_period_s: f64,
    pub first_anchor: u32,
    pub last_anchor: u32,
    pub time_start: f64,
    pub time_end: f64,
}

/// Identity of a strip inside a campaign.
#[derive(Clone, Copy, Debug)]
pub struct StripContext<'a> {
    pub strip: u32,
    pub trajectory: u32,
    pub trajectory_data: &'a Trajectory,
    pub lever_arm: Vec3,
    pub params: &'a Parameters,
}

/// Quantum of the LAS 1.4 scan-angle field, degrees.
const SCAN_ANGLE_QUANTUM_DEG: f64 = 0.006;

pub fn prepare_strip(samples: &StripSamples<'_>, ctx: &StripContext<'_>) -> Result<PreparedStrip, PrepareError> {
    let n = samples.len();
    if [samples.y.len(), samples.z.len(), samples.gps_time.len(), samples.scan_angle_deg.len()].iter().any(|&l| l != n)
    {
        return Err(PrepareError::Shape(format!("{n} points")));
    }
    if n == 0 {
        return Err(PrepareError::Empty);
    }
    let geometry = strip_geometry(samples, ctx)?;
    let mut image = ScanImage::build(samples);
    image.thin_standstill(&geometry, ctx.params.min_revolution_advance_m);
    let links = Links::build(&image);
    let normals = estimate_normals(samples, &geometry, &image, &links, ctx.params.min_revolution_advance_m);
    let chunks = emit_tiles(samples, ctx, &geometry, &links, &normals);
    let with_normal = normals.iter().filter(|n| n.is_some()).count() as u64;
    let emitted = chunks.iter().map(|c| c.len() as u64).sum();
    let first_anchor = geometry.iter().map(|g| g.anchor).min().unwrap_or(0);
    let last_anchor = geometry.iter().map(|g| g.anchor).max().unwrap_or(0) + 1;
    Ok(PreparedStrip {
        chunks,
        stats: PrepareStats {
            points: n as u64,
            points_with_normal: with_normal,
            points_emitted: emitted,
            revolutions: image.columns as u64,
            rows_per_revolution: image.rows,
            revolution_period_s: image.period_s,
            first_anchor,
            last_anchor,
            time_start: samples.gps_time[0],
            time_end: samples.gps_time[n - 1],
        },
    })
}

fn strip_geometry(
    samples: &StripSamples<'_>,
    ctx: &StripContext<'_>,
) -> Result<Vec<MeasurementGeometry>, PrepareError> {
    let (start, end) = ctx.trajectory_data.time_span();
    let mut out = Vec::with_capacity(samples.len());
    let mut previous = f64::NEG_INFINITY;
    for k in 0..samples.len() {
        let t = samples.gps_time[k];
        let p = [samples.x[k], samples.y[k], samples.z[k]];
        for (v, field) in [(t, "GPS time"), (p[0], "x"), (p[1], "y"), (p[2], "z")] {
            if !v.is_finite() {
                return Err(PrepareError::NotFinite { index: k, field });
            }
        }
        if !samples.scan_angle_deg[k].is_finite() {
            return Err(PrepareError::NotFinite { index: k, field: "scan angle" });
        }
        if t < previous {
            return Err(PrepareError::NotInOrder { index: k, time: t, previous });
        }
        previous = t;
        let g = measurement_geometry(ctx.trajectory_data, &ctx.lever_arm, ctx.params.anchor_spacing_m, t, p)
            .ok_or(PrepareError::NotCovered { index: k, time: t, start, end })?;
        out.push(g);
    }
    Ok(out)
}

/// Row and column of every point in the strip's scan image.
#[derive(Debug)]
struct ScanImage {
    rows: u32,
    columns: u32,
    period_s: f64,
    row: Vec<u32>,
    /// Column of each point; [`DROPPED`] for revolutions skipped at standstill.
    column: Vec<u32>,
    angle_step_rad: f64,
}

/// Column of a point whose revolution is not used.
const DROPPED: u32 = u32::MAX;

impl ScanImage {
    fn build(samples: &StripSamples<'_>) -> Self {
        let n = samples.len();
        let angles = samples.scan_angle_deg;
        // The angular step is the most frequent positive difference between consecutive
        // measurements (missing returns only make some differences multiples of it).
        let mut histogram: BTreeMap<i64, (u64, f64)> = BTreeMap::new();
        for w in angles.windows(2) {
            let diff = w[1] as f64 - w[0] as f64;
            let d = (diff / SCAN_ANGLE_QUANTUM_DEG).round() as i64;
            if d > 0 && d < 60_000 {
                let e = histogram.entry(d).or_default();
                e.0 += 1;
                e.1 += diff;
            }
        }
        let mode = histogram.iter().max_by_key(|(d, (c, _))| (*c, -**d)).map(|(d, _)| *d).unwrap_or(60_000);
        // 360°/N is rarely a whole number of 0.006° quanta, so quantised steps alternate between
        // neighbouring values: average the raw steps next to the mode.
        let (mut sum, mut count) = (0.0, 0u64);
        for d in mode - 1..=mode + 1 {
            if let Some(&(c, s)) = histogram.get(&d) {
                sum += s;
                count += c;
            }
        }
        let step_deg = if count > 0 { sum / count as f64 } else { mode as f64 * SCAN_ANGLE_QUANTUM_DEG };
        let rows = ((360.0 / step_deg).round() as u32).max(1);
        // Revolution period: median time between angle wrap-arounds.
        let mut wraps = Vec::new();
        for k in 1..n {
            if angles[k] < angles[k - 1] {
                wraps.push(samples.gps_time[k]);
            }
        }
        let mut periods: Vec<f64> = wraps.windows(2).map(|w| w[1] - w[0]).collect();
        periods.sort_by(f64::total_cmp);
        let period_s = periods.get(periods.len() / 2).copied().unwrap_or_else(|| {
            let span = samples.gps_time[n - 1] - samples.gps_time[0];
            span.max(1e-3)
        });
        let mut row = Vec::with_capacity(n);
        let mut column = Vec::with_capacity(n);
        let mut c: u32 = 0;
        for k in 0..n {
            if k > 0 {
                let gap = samples.gps_time[k] - samples.gps_time[k - 1];
                if gap > 0.75 * period_s {
                    // Missing revolutions (a data gap): skip as many columns as elapsed.
                    c += ((gap / period_s).round() as u32).max(1);
                } else if angles[k] < angles[k - 1] {
                    c += 1;
                }
            }
            let r = ((angles[k] as f64 + 180.0) / step_deg).round() as i64;
            row.push(r.rem_euclid(rows as i64) as u32);
            column.push(c);
        }
        Self { rows, columns: c + 1, period_s, row, column, angle_step_rad: step_deg.to_radians() }
    }

    /// Drops revolutions taken before the scan head moved `min_advance` since the last kept one
    /// and renumbers the kept columns so that consecutive kept revolutions are neighbours.
    /// Columns separated by a data gap stay separated.
    fn thin_standstill(&mut self, geometry: &[MeasurementGeometry], min_advance: f64) {
        if min_advance <= 0.0 || self.column.is_empty() {
            return;
        }
        let mut kept_position: Option<[f64; 3]> = None;
        let mut last_original = u32::MAX;
        let mut new_column = 0u32;
        let mut keep = true;
        let mut first = true;
        // A jump in the original numbering (missing revolutions) since the last kept column.
        let mut gap = false;
        for k in 0..self.column.len() {
            let c = self.column[k];
            if c != last_original {
                if last_original != u32::MAX && c > last_original + 1 {
                    gap = true;
                }
                let head = geometry[k].t0;
                keep = match kept_position {
                    None => true,
                    Some(p) => {
                        let d = ((head[0] - p[0]).powi(2) + (head[1] - p[1]).powi(2) + (head[2] - p[2]).powi(2)).sqrt();
                        d >= min_advance
                    }
                };
                if keep {
                    if !first {
                        new_column += if gap { 2 } else { 1 };
                    }
                    first = false;
                    gap = false;
                    kept_position = Some(head);
                }
                last_original = c;
            }
            self.column[k] = if keep { new_column } else { DROPPED };
        }
        self.columns = new_column + 1;
    }
}

/// Scan-image neighbour links: next/previous row in the same revolution, same row in the
/// next/previous revolution.
#[derive(Debug)]
struct Links {
    right: Vec<u32>,
    left: Vec<u32>,
    down: Vec<u32>,
    up: Vec<u32>,
}

impl Links {
    fn build(image: &ScanImage) -> Self {
        let n = image.row.len();
        let mut right = vec![NO_NEIGHBOUR; n];
        let mut left = vec![NO_NEIGHBOUR; n];
        let mut down = vec![NO_NEIGHBOUR; n];
        let mut up = vec![NO_NEIGHBOUR; n];
        let rows = image.rows as usize;
        let mut previous_column = vec![NO_NEIGHBOUR; rows];
        let mut current_column = vec![NO_NEIGHBOUR; rows];
        let mut current = image.column.first().copied().unwrap_or(0);
        for k in 0..n {
            let c = image.column[k];
            if c == DROPPED {
                continue;
            }
            if c != current {
                if c == current + 1 {
                    std::mem::swap(&mut previous_column, &mut current_column);
                } else {
                    previous_column.fill(NO_NEIGHBOUR);
                }
                current_column.fill(NO_NEIGHBOUR);
                current = c;
            }
            let r = image.row[k] as usize;
            if k + 1 < n && image.column[k + 1] == c && image.row[k + 1] as usize == r + 1 {
                right[k] = (k + 1) as u32;
                left[k + 1] = k as u32;
            }
            let above = previous_column[r];
            if above != NO_NEIGHBOUR {
                up[k] = above;
                down[above as usize] = k as u32;
            }
            current_column[r] = k as u32;
        }
        Self { right, left, down, up }
    }
}

/// A point's normal (unit, facing the scanner) and the longest scan-image edge that still
/// counts as continuous surface around it.
#[derive(Clone, Copy, Debug)]
struct PointNormal {
    normal: [f32; 3],
    edge_limit: f32,
}

/// Longest continuous edge: 2.5 times the larger of the along-profile spacing (range × angular
/// step) and the across-profile spacing (distance driven per revolution), plus 1 cm for noise.
fn edge_limit(range: f64, angle_step_rad: f64, speed: f64, period_s: f64) -> f64 {
    2.5 * (range * angle_step_rad).max(speed * period_s).max(0.005) + 0.01
}

fn estimate_normals(
    samples: &StripSamples<'_>,
    geometry: &[MeasurementGeometry],
    image: &ScanImage,
    links: &Links,
    min_advance: f64,
) -> Vec<Option<PointNormal>> {
    let n = samples.len();
    let p = |k: usize| Vec3::new(samples.x[k], samples.y[k], samples.z[k]);
    let step = |k: u32, f: &dyn Fn(usize) -> u32| if k == NO_NEIGHBOUR { NO_NEIGHBOUR } else { f(k as usize) };
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        if image.column[k] == DROPPED {
            out.push(None);
            continue;
        }
        let g = &geometry[k];
        let r = Vec3::from(g.r);
        let range = r.norm();
        let limit = edge_limit(range, image.angle_step_rad, g.speed.max(min_advance / image.period_s), image.period_s);
        let (u, d) = (links.up[k], links.down[k]);
        let neighbours = [
            links.left[k],
            links.right[k],
            u,
            d,
            step(u, &|j| links.left[j]),
            step(u, &|j| links.right[j]),
            step(d, &|j| links.left[j]),
            step(d, &|j| links.right[j]),
        ];
        let centre = p(k);
        let mut pts = [Vec3::zeros(); 9];
        pts[0] = centre;
        let mut m = 1;
        let (mut along, mut across) = (false, false);
        for (slot, &j) in neighbours.iter().enumerate() {
            if j == NO_NEIGHBOUR {
                continue;
            }
            let q = p(j as usize);
            if (q - centre).norm() <= limit {
                pts[m] = q;
                m += 1;
                if slot < 2 {
                    along = true;
                } else if slot < 4 {
                    across = true;
                }
            }
        }
        if m < 4 || !(along && across) {
            out.push(None);
            continue;
        }
        let mean = pts[..m].iter().sum::<Vec3>() / m as f64;
        let mut cov = nalgebra::Matrix3::<f64>::zeros();
        for q in &pts[..m] {
            let d = q - mean;
            cov += d * d.transpose();
        }
        let eig = nalgebra::SymmetricEigen::new(cov);
        let mut order = [0usize, 1, 2];
        order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
        let (l0, l1) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
        // Not planar (foliage, edges, corners): no reliable normal.
        if l0.is_nan() || l0 > 0.1 * l1 || l1 <= 0.0 {
            out.push(None);
            continue;
        }
        let mut normal: Vec3 = eig.eigenvectors.column(order[0]).into();
        if normal.dot(&r) > 0.0 {
            normal = -normal;
        }
        out.push(Some(PointNormal {
            normal: [normal.x as f32, normal.y as f32, normal.z as f32],
            edge_limit: limit as f32,
        }));
    }
    out
}

fn emit_tiles(
    samples: &StripSamples<'_>,
    ctx: &StripContext<'_>,
    geometry: &[MeasurementGeometry],
    links: &Links,
    normals: &[Option<PointNormal>],
) -> Vec<TileChunk> {
    let params = ctx.params;
    // Points per tile, in acquisition order.
    let mut members: BTreeMap<TileKey, Vec<u32>> = BTreeMap::new();
    let max_range2 = params.max_range_m * params.max_range_m;
    for k in 0..samples.len() {
        let r = geometry[k].r;
        if normals[k].is_none() || r[0] * r[0] + r[1] * r[1] + r[2] * r[2] > max_range2 {
            continue;
        }
        for key in TileKey::with_overlap(samples.x[k], samples.y[k], params.tile_size_m, params.tile_overlap_m) {
            members.entry(key).or_default().push(k as u32);
        }
    }
    members
        .into_iter()
        .map(|(key, globals)| {
            let (ox, oy) = key.origin(params.tile_size_m);
            let origin = [ox, oy, 0.0];
            let mut chunk = TileChunk::with_capacity(key, ctx.strip, ctx.trajectory, origin, globals.len());
            let local = |g: u32| -> u32 {
                if g == NO_NEIGHBOUR {
                    return NO_NEIGHBOUR;
                }
                globals.binary_search(&g).map(|i| i as u32).unwrap_or(NO_NEIGHBOUR)
            };
            for &g in &globals {
                let k = g as usize;
                let geo = &geometry[k];
                let nrm = normals[k].expect("only points with normals are emitted");
                chunk.push(
                    [(geo.t0[0] - ox) as f32, (geo.t0[1] - oy) as f32, geo.t0[2] as f32],
                    [geo.r[0] as f32, geo.r[1] as f32, geo.r[2] as f32],
                    nrm.normal,
                    geo.anchor,
                    geo.lambda,
                    local(links.right[k]),
                    local(links.down[k]),
                    nrm.edge_limit,
                );
            }
            chunk
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A straight drive over flat ground scanned by one rotating head: the scan image must have
    /// the simulated rows and columns, and normals must point up.
    #[test]
    fn scan_image_links_and_normals_on_flat_ground() {
        let speed = 10.0;
        let times: Vec<f64> = (0..=400).map(|i| 1000.0 + i as f64 * 0.005).collect();
        let positions = times.iter().map(|t| Vec3::new((t - 1000.0) * speed, 0.0, 2.0)).collect();
        let traj = Trajectory::new(times, positions, vec![[0.0; 3]; 401]).unwrap();
        let rows = 360u32;
        let rate = 50.0;
        let (mut x, mut y, mut z, mut t, mut a) = (vec![], vec![], vec![], vec![], vec![]);
        for rev in 0..60 {
            for j in 0..rows {
                let phi = -180.0 + j as f64 * 360.0 / rows as f64;
                let time = 1000.1 + rev as f64 / rate + j as f64 / (rate * rows as f64);
                let c = (time - 1000.0) * speed;
                // Beam in the y–z plane; only downward beams hit the ground (z = 0).
                let dir = Vec3::new(0.0, phi.to_radians().sin(), phi.to_radians().cos());
                if dir.z > -0.3 {
                    continue;
                }
                let s = -2.0 / dir.z;
                x.push(c);
                y.push(dir.y * s);
                z.push(0.0);
                t.push(time);
                a.push(phi as f32);
            }
        }
        let samples = StripSamples { x: &x, y: &y, z: &z, gps_time: &t, scan_angle_deg: &a };
        let params = Parameters::default();
        let ctx =
            StripContext { strip: 3, trajectory: 1, trajectory_data: &traj, lever_arm: Vec3::zeros(), params: &params };
        let prepared = prepare_strip(&samples, &ctx).unwrap();
        assert_eq!(prepared.stats.rows_per_revolution, rows);
        assert_eq!(prepared.stats.revolutions, 60);
        assert!((prepared.stats.revolution_period_s - 0.02).abs() < 1e-9);
        // Interior points all get upward normals; only the image border loses some.
        assert!(prepared.stats.points_with_normal as f64 > 0.9 * prepared.stats.points as f64);
        for chunk in &prepared.chunks {
            for nrm in &chunk.normal {
                assert!(nrm[2] > 0.999, "{nrm:?}");
            }
            assert!(chunk.right.iter().filter(|&&r| r != NO_NEIGHBOUR).count() > chunk.len() / 2);
        }
        // The anchor coordinate follows arc length: first point at 1 m → anchor 2.
        assert_eq!(prepared.stats.first_anchor, 2);
    }

    #[test]
    fn uncovered_and_unordered_points_are_reported() {
        let traj =
            Trajectory::new(vec![0.0, 1.0], vec![Vec3::zeros(), Vec3::new(1.0, 0.0, 0.0)], vec![[0.0; 3]; 2]).unwrap();
        let params = Parameters::default();
        let ctx =
            StripContext { strip: 0, trajectory: 0, trajectory_data: &traj, lever_arm: Vec3::zeros(), params: &params };
        let xs = [0.0, 0.0];
        let samples = StripSamples { x: &xs, y: &xs, z: &xs, gps_time: &[0.5, 2.0], scan_angle_deg: &[0.0, 1.0] };
        assert_eq!(
            prepare_strip(&samples, &ctx).unwrap_err(),
            PrepareError::NotCovered { index: 1, time: 2.0, start: 0.0, end: 1.0 }
        );
        let samples = StripSamples { x: &xs, y: &xs, z: &xs, gps_time: &[0.5, 0.4], scan_angle_deg: &[0.0, 1.0] };
        assert!(matches!(prepare_strip(&samples, &ctx).unwrap_err(), PrepareError::NotInOrder { index: 1, .. }));
        let samples =
            StripSamples { x: &[0.0, f64::NAN], y: &xs, z: &xs, gps_time: &[0.5, 0.6], scan_angle_deg: &[0.0, 1.0] };
        assert_eq!(prepare_strip(&samples, &ctx).unwrap_err(), PrepareError::NotFinite { index: 1, field: "x" });
    }
}
