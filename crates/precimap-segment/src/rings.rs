//! The ring image of a multi-beam spinning head (Velodyne, Ouster, Hesai style): every firing
//! measures all rings at once, so rows are the rings ordered by elevation and columns are the
//! firings in time. Consecutive firings are neighbouring azimuths, so the image is one long strip
//! of columns through all revolutions; its rows do not wrap.

use crate::image::{dist, ScanImage, DROPPED};
use crate::StripGeometry;

/// Rings of a multi-beam head are numbered 0–255 (the LAS user-data byte).
const RINGS: usize = 256;

impl ScanImage {
    /// Builds the ring image from each point's ring number and GPS time, in acquisition order.
    ///
    /// - **Rows**: the rings that have points, ordered by their mean elevation seen from the
    ///   scan head (the numbering of the lasers need not follow elevation). `angle_step_rad` is
    ///   the median elevation step between neighbouring rings.
    /// - **Columns**: a firing starts where the time has moved on by more than half the firing
    ///   period (the median time step of one ring), so rings written with per-laser time offsets
    ///   within a firing stay in it; a pause skips columns (at most two), so the firings either
    ///   side are not neighbours. `column_step_rad` is the median azimuth step per firing, and
    ///   `revolution_columns` the columns of 360° of it: segments also join a pixel to the same
    ///   ring one revolution later, so that a surface seen in many revolutions is one segment.
    /// - **Standstill**: revolutions (360° of azimuth) taken before the head moved `min_advance`
    ///   metres since the last kept revolution are dropped, as for the profile image.
    pub fn from_rings(geo: &StripGeometry<'_>, ring: &[u8], gps_time: &[f64], min_advance: f64) -> Self {
        let n = geo.len().min(ring.len()).min(gps_time.len());
        let (rows, row_of, angle_step_rad) = rows_by_elevation(geo, &ring[..n]);
        let period_s = firing_period(&ring[..n], &gps_time[..n]);
        // Columns: one per firing.
        let mut column = Vec::with_capacity(n);
        let mut c = 0u32;
        let mut start = gps_time.first().copied().unwrap_or(0.0);
        for &t in &gps_time[..n] {
            let dt = t - start;
            if dt > 0.5 * period_s {
                c += ((dt / period_s).round() as u32).clamp(1, 3);
                start = t;
            }
            column.push(c);
        }
        let columns = if n > 0 { c + 1 } else { 1 };
        let row = ring[..n].iter().map(|&r| row_of[r as usize]).collect();
        let mut image = Self {
            rows,
            columns,
            period_s,
            angle_step_rad,
            column_step_rad: 0.0,
            wraps: false,
            revolution_columns: 0,
            row,
            column,
        };
        let azimuth = column_azimuths(geo, &image);
        image.column_step_rad = azimuth_step(&azimuth);
        if image.column_step_rad > 0.0 {
            image.revolution_columns = (std::f64::consts::TAU / image.column_step_rad).round().min(1e6) as u32;
        }
        image.thin_revolutions(geo.head, &azimuth, min_advance);
        image
    }

    /// Drops whole revolutions at standstill and renumbers the kept columns consecutively.
    fn thin_revolutions(&mut self, head: &[[f64; 3]], azimuth: &[Option<f64>], min_advance: f64) {
        let width = self.columns as usize;
        // Revolution of each column: the azimuth turned through since the strip's first firing.
        let mut revolution = vec![0u32; width];
        let (mut turned, mut last) = (0.0f64, None);
        for (c, a) in azimuth.iter().enumerate() {
            if let Some(a) = *a {
                if let Some(l) = last {
                    turned += wrap_pi(a - l).abs();
                }
                last = Some(a);
            }
            revolution[c] = (turned / std::f64::consts::TAU) as u32;
        }
        let mut first_point = vec![u32::MAX; width];
        for (k, &c) in self.column.iter().enumerate() {
            if first_point[c as usize] == u32::MAX {
                first_point[c as usize] = k as u32;
            }
        }
        let mut keep_revolution = Vec::new();
        let mut kept: Option<[f64; 3]> = None;
        for c in 0..width {
            let r = revolution[c] as usize;
            if r < keep_revolution.len() {
                continue;
            }
            // The first column with a point decides for its revolution.
            let k = first_point[c];
            if k == u32::MAX {
                continue;
            }
            let h = head[k as usize];
            let keep = min_advance <= 0.0 || kept.is_none_or(|p| dist(h, p) >= min_advance);
            if keep {
                kept = Some(h);
            }
            keep_revolution.resize(r, true);
            keep_revolution.push(keep);
        }
        let mut new_index = vec![DROPPED; width];
        let mut next = 0u32;
        for c in 0..width {
            if keep_revolution.get(revolution[c] as usize).copied().unwrap_or(true) {
                new_index[c] = next;
                next += 1;
            }
        }
        for c in self.column.iter_mut() {
            *c = new_index[*c as usize];
        }
        self.columns = next.max(1);
    }
}

/// Rows of the rings present, ordered by mean elevation: (rows, row of each ring number, median
/// elevation step in radians).
fn rows_by_elevation(geo: &StripGeometry<'_>, ring: &[u8]) -> (u32, [u32; RINGS], f64) {
    let mut sum = [0.0f64; RINGS];
    let mut count = [0u64; RINGS];
    for (k, &r) in ring.iter().enumerate() {
        let p = geo.point(k);
        let h = geo.head[k];
        let d = [p[0] - h[0], p[1] - h[1], p[2] - h[2]];
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if len > 0.0 {
            sum[r as usize] += (d[2] / len).clamp(-1.0, 1.0).asin();
            count[r as usize] += 1;
        }
    }
    let mut present: Vec<(f64, usize)> =
        (0..RINGS).filter(|&r| count[r] > 0).map(|r| (sum[r] / count[r] as f64, r)).collect();
    present.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut row_of = [0u32; RINGS];
    for (row, &(_, r)) in present.iter().enumerate() {
        row_of[r] = row as u32;
    }
    let mut steps: Vec<f64> = present.windows(2).map(|w| w[1].0 - w[0].0).collect();
    steps.sort_by(f64::total_cmp);
    let step = steps.get(steps.len() / 2).copied().unwrap_or(0.0);
    (present.len().max(1) as u32, row_of, step)
}

/// Median positive time step between consecutive points of one ring (the firing period).
fn firing_period(ring: &[u8], gps_time: &[f64]) -> f64 {
    let mut last = [f64::NAN; RINGS];
    let mut steps = Vec::with_capacity(ring.len());
    for (&r, &t) in ring.iter().zip(gps_time) {
        let dt = t - last[r as usize];
        if dt > 0.0 {
            steps.push(dt);
        }
        last[r as usize] = t;
    }
    steps.sort_by(f64::total_cmp);
    steps.get(steps.len() / 2).copied().unwrap_or(1.0)
}

/// Horizontal azimuth (radians) from the scan head to the first point of each column.
fn column_azimuths(geo: &StripGeometry<'_>, image: &ScanImage) -> Vec<Option<f64>> {
    let mut azimuth = vec![None; image.columns as usize];
    for (k, &c) in image.column.iter().enumerate() {
        let slot = &mut azimuth[c as usize];
        if slot.is_none() {
            let (p, h) = (geo.point(k), geo.head[k]);
            *slot = Some((p[1] - h[1]).atan2(p[0] - h[0]));
        }
    }
    azimuth
}

/// Median azimuth step per column between columns that both have points.
fn azimuth_step(azimuth: &[Option<f64>]) -> f64 {
    let mut steps = Vec::new();
    let mut last: Option<(usize, f64)> = None;
    for (c, a) in azimuth.iter().enumerate() {
        if let Some(a) = *a {
            if let Some((lc, la)) = last {
                steps.push(wrap_pi(a - la).abs() / (c - lc) as f64);
            }
            last = Some((c, a));
        }
    }
    steps.sort_by(f64::total_cmp);
    steps.get(steps.len() / 2).copied().unwrap_or(0.0)
}

/// `a` wrapped into [−π, π).
fn wrap_pi(a: f64) -> f64 {
    (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{segment_strip, SegmentParams};

    /// x, y, z, head, ring, GPS time.
    type Strip = (Vec<f64>, Vec<f64>, Vec<f64>, Vec<[f64; 3]>, Vec<u8>, Vec<f64>);

    /// A head 2 m above a flat floor and before a wall at x = 8 m, 16 rings over −25..+5°,
    /// numbered out of elevation order, 360 firings per revolution, driving along y at 5 m/s,
    /// standing still for the last 10 revolutions.
    fn strip() -> Strip {
        let (mut x, mut y, mut z, mut head, mut ring, mut t) = (vec![], vec![], vec![], vec![], vec![], vec![]);
        let firings = 360;
        let rate = 10.0;
        for f in 0..firings * 30 {
            let time = f as f64 / (rate * firings as f64);
            let moving = time.min(2.0);
            let h = [0.0, 5.0 * moving, 2.0];
            let az = (f % firings) as f64 * std::f64::consts::TAU / firings as f64;
            for laser in 0..16u8 {
                // Even lasers the lower half, odd the upper: not in elevation order.
                let index = if laser.is_multiple_of(2) { laser / 2 } else { 8 + laser / 2 };
                let el = (-25.0 + 2.0 * index as f64).to_radians();
                let d = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
                let floor = if d[2] < 0.0 { 2.0 / -d[2] } else { f64::INFINITY };
                let wall = if d[0] > 0.0 { 8.0 / d[0] } else { f64::INFINITY };
                let range = floor.min(wall);
                if range > 40.0 {
                    continue;
                }
                x.push(h[0] + range * d[0]);
                y.push(h[1] + range * d[1]);
                z.push(h[2] + range * d[2]);
                head.push(h);
                ring.push(laser);
                t.push(time);
            }
        }
        (x, y, z, head, ring, t)
    }

    #[test]
    fn rings_by_elevation_firings_as_columns_and_standstill_dropped() {
        let (x, y, z, head, ring, t) = strip();
        let geo = StripGeometry { x: &x, y: &y, z: &z, head: &head };
        let image = ScanImage::from_rings(&geo, &ring, &t, 0.03);
        assert_eq!(image.rows, 16);
        assert!(!image.wraps);
        // Lasers 0 and 1 are the lowest and the ninth ring.
        let k0 = ring.iter().position(|&r| r == 0).unwrap();
        let k1 = ring.iter().position(|&r| r == 1).unwrap();
        assert_eq!((image.row[k0], image.row[k1]), (0, 8));
        assert!((image.angle_step_rad.to_degrees() - 2.0).abs() < 0.05, "{}", image.angle_step_rad.to_degrees());
        assert!((image.column_step_rad.to_degrees() - 1.0).abs() < 0.01, "{}", image.column_step_rad.to_degrees());
        assert!((image.period_s - 1.0 / 3600.0).abs() < 1e-9);
        assert_eq!(image.revolution_columns, 360);
        // 20 moving revolutions and the first standing one are kept, the other 9 dropped.
        let dropped = image.column.iter().filter(|&&c| c == DROPPED).count();
        let per_revolution = x.len() / 30;
        assert!(dropped.abs_diff(9 * per_revolution) <= 16, "{dropped} dropped, {per_revolution} per revolution");
        assert!(image.columns.abs_diff(21 * 360) <= 1, "{}", image.columns);
    }

    #[test]
    fn a_ring_image_gets_normals_and_segments_for_floor_and_wall() {
        let (x, y, z, head, ring, t) = strip();
        let geo = StripGeometry { x: &x, y: &y, z: &z, head: &head };
        let image = ScanImage::from_rings(&geo, &ring, &t, 0.03);
        let s = segment_strip(&geo, &image, &SegmentParams::default());
        let in_image = s.stats.points_in_image as f64;
        assert!(s.stats.points_with_normal as f64 > 0.95 * in_image, "{:?}", s.stats);
        for (k, n) in s.normals.iter().enumerate() {
            let Some(n) = n else { continue };
            // Points near the floor–wall corner may take either side's normal.
            let want = if x[k] > 8.0 - 1e-6 && z[k] > 0.3 {
                [-1.0, 0.0, 0.0]
            } else if z[k] < 1e-6 && x[k] < 7.7 {
                [0.0, 0.0, 1.0]
            } else {
                continue;
            };
            let cos = n.normal.iter().zip(want).map(|(a, b)| *a as f64 * b).sum::<f64>();
            assert!(cos > 0.99, "point {k}: {:?} against {want:?}", n.normal);
        }
        // Floor and wall are two segments, never one; the floor of every revolution is one.
        let floors: std::collections::BTreeSet<u32> = (0..x.len())
            .filter(|&k| z[k] < 1e-6 && x[k] < 6.0 && s.segment[k] < crate::DROPPED_SEGMENT)
            .map(|k| s.segment[k])
            .collect();
        assert_eq!(floors.len(), 1, "{floors:?}");
        let floor = (0..x.len()).find(|&k| z[k] < 0.001 && x[k] < 6.0 && s.segment[k] < crate::DROPPED_SEGMENT);
        let wall = (0..x.len()).find(|&k| x[k] > 7.999 && z[k] > 0.5 && s.segment[k] < crate::DROPPED_SEGMENT);
        let (floor, wall) = (floor.unwrap(), wall.unwrap());
        assert_ne!(s.segment[floor], s.segment[wall]);
    }
}
