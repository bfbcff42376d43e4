//! The scan image: rows = measurement index within one scanner revolution (from the scan angle),
//! columns = revolutions, one column range per scanner channel. Missing returns stay holes. A
//! multi-beam head's ring image has the same shape with rows = rings and columns = firings
//! ([`ScanImage::from_rings`], in `rings`).

use std::collections::BTreeMap;

/// Quantum of the LAS 1.4 scan-angle field, degrees.
const SCAN_ANGLE_QUANTUM_DEG: f64 = 0.006;

/// Marks "no point" in the pixel grid and in neighbour links.
pub const NO_POINT: u32 = u32::MAX;
/// Column of a point whose revolution is not used (standstill thinning).
pub const DROPPED: u32 = u32::MAX;

/// Row and column of every point of a strip.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanImage {
    /// Measurements per revolution (image height).
    pub rows: u32,
    /// Image width: revolutions of all channels, with one empty column between channels and at
    /// every gap in GPS time, so that only consecutive revolutions are neighbours.
    pub columns: u32,
    /// Median revolution period, seconds.
    pub period_s: f64,
    /// Angular step between consecutive measurements, radians.
    pub angle_step_rad: f64,
    /// Angular step between consecutive columns, radians: 0 for a single-profile head (its
    /// columns are apart by the head's advance alone), the azimuth step per firing for a ring
    /// image.
    pub column_step_rad: f64,
    /// Rows wrap around (a revolution is a circle); a ring image's top and bottom rings do not meet.
    pub wraps: bool,
    /// Columns per revolution of a ring image, whose segments also join the same ring one
    /// revolution later; 0 for a profile image (whose next column is the next revolution).
    pub revolution_columns: u32,
    pub row: Vec<u32>,
    /// Column of each point; [`DROPPED`] for revolutions removed at standstill.
    pub column: Vec<u32>,
}

impl ScanImage {
    /// Builds the image from the scan angle (degrees, ±180°), GPS time and scanner channel of
    /// every point in acquisition order. The angular step is the most frequent positive angle
    /// difference of consecutive measurements of one channel (missing returns only make some
    /// differences multiples of it); a revolution ends where the angle wraps around; a gap in GPS
    /// time longer than ¾ of a period skips as many columns as revolutions elapsed. If the strip
    /// carries no scan angle (all equal), every point is its own row in one column: no scan-image
    /// neighbourhood can be formed; `prepare_strip` therefore passes angles reconstructed from
    /// the beam directions for such strips.
    pub fn build(angles_deg: &[f32], gps_time: &[f64], channel: &[u8]) -> Self {
        let n = angles_deg.len().min(gps_time.len()).min(channel.len());
        let mut histogram: BTreeMap<i64, (u64, f64)> = BTreeMap::new();
        let mut last: [Option<usize>; 256] = [None; 256];
        for k in 0..n {
            let c = channel[k] as usize;
            if let Some(j) = last[c] {
                let diff = angles_deg[k] as f64 - angles_deg[j] as f64;
                let d = round(diff / SCAN_ANGLE_QUANTUM_DEG) as i64;
                if d > 0 && d < 60_000 {
                    let e = histogram.entry(d).or_default();
                    e.0 += 1;
                    e.1 += diff;
                }
            }
            last[c] = Some(k);
        }
        let mode = histogram.iter().max_by_key(|(d, (c, _))| (*c, -**d)).map(|(d, _)| *d).unwrap_or(60_000);
        // 360°/N is rarely a whole number of 0.006° quanta: average the raw steps next to the mode.
        let (mut sum, mut count) = (0.0, 0u64);
        for d in mode - 1..=mode + 1 {
            if let Some(&(c, s)) = histogram.get(&d) {
                sum += s;
                count += c;
            }
        }
        let step_deg = if count > 0 { sum / count as f64 } else { mode as f64 * SCAN_ANGLE_QUANTUM_DEG };
        let rows = ((360.0 / step_deg).round() as u32).clamp(1, 1 << 20);
        // Revolution period: median time between wrap-arounds of one channel.
        let mut periods = Vec::new();
        let mut last: [Option<(usize, Option<f64>)>; 256] = [None; 256];
        for k in 0..n {
            let c = channel[k] as usize;
            if let Some((j, wrap)) = last[c] {
                if angles_deg[k] < angles_deg[j] {
                    if let Some(w) = wrap {
                        periods.push(gps_time[k] - w);
                    }
                    last[c] = Some((k, Some(gps_time[k])));
                    continue;
                }
                last[c] = Some((k, wrap));
            } else {
                last[c] = Some((k, None));
            }
        }
        periods.sort_by(f64::total_cmp);
        let period_s = periods.get(periods.len() / 2).copied().filter(|p| *p > 0.0).unwrap_or_else(|| {
            let span = if n > 0 { gps_time[n - 1] - gps_time[0] } else { 0.0 };
            span.max(1e-3)
        });
        // Columns per channel, then channel ranges laid side by side with an empty column between.
        let mut row = Vec::with_capacity(n);
        let mut column = Vec::with_capacity(n);
        let mut state: [Option<(u32, f32, f64)>; 256] = [None; 256];
        for k in 0..n {
            let ch = channel[k] as usize;
            let c = match state[ch] {
                None => 0,
                Some((c, a, t)) => {
                    let gap = gps_time[k] - t;
                    if gap > 0.75 * period_s {
                        // Missing revolutions: skip as many columns as elapsed, at least two so that
                        // the revolutions either side are not neighbours.
                        c.saturating_add(((gap / period_s).round().min(1e6) as u32).max(2))
                    } else if angles_deg[k] < a {
                        c + 1
                    } else {
                        c
                    }
                }
            };
            state[ch] = Some((c, angles_deg[k], gps_time[k]));
            let r = round((angles_deg[k] as f64 + 180.0) / step_deg) as i64;
            row.push(r.rem_euclid(rows as i64) as u32);
            column.push(c);
        }
        let mut offset = [0u32; 256];
        let mut next = 0u32;
        for ch in 0..256 {
            if let Some((c, _, _)) = state[ch] {
                offset[ch] = next;
                next = next.saturating_add(c + 2);
            }
        }
        for k in 0..n {
            column[k] += offset[channel[k] as usize];
        }
        Self {
            rows,
            columns: next.max(1),
            period_s,
            angle_step_rad: step_deg.to_radians(),
            column_step_rad: 0.0,
            wraps: true,
            revolution_columns: 0,
            row,
            column,
        }
    }

    /// Drops revolutions taken before the scan head moved `min_advance` metres since the last kept
    /// revolution of the same column run and renumbers the kept columns so that consecutive kept
    /// revolutions are neighbours. `head[k]` is the scan-head position at point k. Empty columns
    /// (gaps, channel boundaries) stay empty.
    pub fn thin_standstill(&mut self, head: &[[f64; 3]], min_advance: f64) {
        let width = self.columns as usize;
        let mut first_point = vec![NO_POINT; width];
        for (k, &c) in self.column.iter().enumerate() {
            if c != DROPPED && first_point[c as usize] == NO_POINT {
                first_point[c as usize] = k as u32;
            }
        }
        let mut new_index = vec![DROPPED; width];
        let mut kept: Option<[f64; 3]> = None;
        let mut next = 0u32;
        let mut after_gap = false;
        for c in 0..width {
            let k = first_point[c];
            if k == NO_POINT {
                if kept.is_some() {
                    after_gap = true;
                }
                kept = None;
                continue;
            }
            let h = head[k as usize];
            let keep = match kept {
                None => true,
                Some(p) => dist(h, p) >= min_advance || min_advance <= 0.0,
            };
            if keep {
                if after_gap {
                    next += 1;
                    after_gap = false;
                }
                new_index[c] = next;
                next += 1;
                kept = Some(h);
            }
        }
        for c in self.column.iter_mut() {
            if *c != DROPPED {
                *c = new_index[*c as usize];
            }
        }
        self.columns = next.max(1);
    }

    /// Pixel grid: `grid[column · rows + row]` is the point there, or [`NO_POINT`]. When two
    /// points fall on one pixel (a jitter of the angle), the later one is kept.
    pub fn grid(&self) -> Vec<u32> {
        let mut grid = vec![NO_POINT; self.columns as usize * self.rows as usize];
        for (k, (&c, &r)) in self.column.iter().zip(&self.row).enumerate() {
            if c != DROPPED {
                grid[c as usize * self.rows as usize + r as usize] = k as u32;
            }
        }
        grid
    }
}

/// `x.round()` (half away from zero), inlined: on the baseline x86-64 target `f64::round` is a
/// libm call, which shows in the per-point loops. Exact for |x| < 2⁵²; beyond, and for ±∞ and
/// NaN, equal after the saturating `as i64` cast the callers apply.
#[inline]
fn round(x: f64) -> f64 {
    let t = x as i64 as f64;
    let frac = x - t;
    if frac >= 0.5 {
        t + 1.0
    } else if frac <= -0.5 {
        t - 1.0
    } else {
        t
    }
}

#[inline]
pub(crate) fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_columns_gaps_and_channels() {
        // Two channels interleaved, 8 measurements per revolution, 10 revolutions each, with the
        // 5th revolution of channel 0 missing (GPS gap) and some returns missing.
        let (mut a, mut t, mut ch) = (vec![], vec![], vec![]);
        for rev in 0..10 {
            for j in 0..8 {
                for c in 0..2u8 {
                    if (c == 0 && rev == 4) || (j == 3 && rev % 2 == 0) {
                        continue;
                    }
                    a.push(-180.0 + j as f32 * 45.0);
                    t.push(rev as f64 * 0.01 + j as f64 * 0.01 / 8.0);
                    ch.push(c);
                }
            }
        }
        let img = ScanImage::build(&a, &t, &ch);
        assert_eq!(img.rows, 8);
        assert!((img.period_s - 0.01).abs() < 1e-9);
        // Channel 0: columns 0..3, gap, 5..9, one empty column → 11; channel 1 likewise.
        assert_eq!(img.columns, 11 + 11);
        let first_ch1 = ch.iter().position(|&c| c == 1).unwrap();
        assert_eq!(img.column[first_ch1], 11);
        let k = (0..a.len()).find(|&k| ch[k] == 0 && t[k] > 0.045).unwrap();
        assert_eq!(img.column[k], 5);
        assert_eq!(img.row[k], 0);
        let grid = img.grid();
        assert_eq!(grid.iter().filter(|&&g| g != NO_POINT).count(), a.len());
    }

    #[test]
    fn inlined_round_matches_round() {
        for x in
            [-2.5, -2.4999, -0.5, -0.49999999999999994, -0.0, 0.0, 0.49999999999999994, 0.5, 1.5, 2.5, 1e15 + 0.5, 3e9]
        {
            assert_eq!(round(x), x.round(), "{x}");
        }
        for x in [f64::INFINITY, f64::NEG_INFINITY, f64::NAN, 1e300, -1e300] {
            assert_eq!(round(x) as i64, x.round() as i64, "{x}");
        }
    }

    #[test]
    fn standstill_revolutions_are_dropped() {
        let (mut a, mut t, mut head) = (vec![], vec![], vec![]);
        for rev in 0..10u32 {
            for j in 0..4 {
                a.push(-180.0 + j as f32 * 90.0);
                t.push(rev as f64 * 0.01 + j as f64 * 0.0025);
                // Stands still for revolutions 3..7.
                let x = (rev.min(3) + rev.saturating_sub(7)) as f64 * 0.1;
                head.push([x, 0.0, 0.0]);
            }
        }
        let mut img = ScanImage::build(&a, &t, &vec![0; a.len()]);
        img.thin_standstill(&head, 0.03);
        // Kept: 0,1,2,3, then 8, 9 (7 is at the same place as 3).
        assert_eq!(img.columns, 6);
        assert_eq!(img.column[4 * 4], DROPPED);
        assert_eq!(img.column[8 * 4], 4);
    }
}
