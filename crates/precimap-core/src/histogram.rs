//! Logarithmic histogram bins shared by the mergeable histograms of the workspace (the anchors'
//! change per iteration, the evaluation's |error| percentiles): constant memory whatever the
//! number of values, mergeable by adding counts.

/// Bin 0 holds values below `smallest`; bin k ≥ 1 holds `[smallest·ratio^(k−1), smallest·ratio^k)`;
/// the last bin also holds everything larger, +∞ included. NaN falls into bin 0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogBins {
    pub smallest: f64,
    pub ratio: f64,
    pub count: usize,
}

impl LogBins {
    /// Bins from `smallest` up to at least `largest`, each `ratio` wide, plus the two end bins.
    pub fn spanning(smallest: f64, largest: f64, ratio: f64) -> Self {
        Self { smallest, ratio, count: ((largest / smallest).ln() / ratio.ln()).ceil() as usize + 2 }
    }

    pub fn index(&self, v: f64) -> usize {
        if v.is_nan() || v < self.smallest {
            return 0;
        }
        let k = ((v / self.smallest).ln() / self.ratio.ln()).floor();
        // `as` saturates, so +∞ lands in the last bin too.
        ((k as usize).saturating_add(1)).min(self.count - 1)
    }

    /// Upper edge of bin `k` (bin 0: `smallest`).
    pub fn upper_edge(&self, k: usize) -> f64 {
        self.smallest * self.ratio.powf(k as f64)
    }

    /// The bin holding the `q`-quantile (nearest rank, 0 ≤ q ≤ 1) of `counts`; `None` when empty.
    pub fn quantile_bin(counts: &[u64], q: f64) -> Option<usize> {
        let n: u64 = counts.iter().sum();
        if n == 0 {
            return None;
        }
        let rank = ((q.clamp(0.0, 1.0) * n as f64).ceil() as u64).clamp(1, n);
        let mut seen = 0;
        counts.iter().position(|&c| {
            seen += c;
            seen >= rank
        })
    }

    /// Adds `other`'s counts to `counts` (both of these bins).
    pub fn merge(counts: &mut [u64], other: &[u64]) {
        for (a, b) in counts.iter_mut().zip(other) {
            *a += b;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bins_edges_and_ranks() {
        let bins = LogBins::spanning(1e-6, 10.0, 10f64.powf(0.1));
        assert_eq!(bins.count, 72);
        assert_eq!(bins.index(0.0), 0);
        assert_eq!(bins.index(f64::NAN), 0);
        assert_eq!(bins.index(f64::INFINITY), 71);
        assert_eq!(bins.index(1e3), 71);
        // 50 mm lies in [10^4.6, 10^4.7) µm: bin 47, whose upper edge is 50.1 mm.
        assert_eq!(bins.index(0.05), 47);
        assert!((bins.upper_edge(47) - 0.0501).abs() < 1e-4);
        assert_eq!(LogBins::quantile_bin(&[0, 0, 0], 0.5), None);
        assert_eq!(LogBins::quantile_bin(&[1, 0, 3], 0.25), Some(0));
        assert_eq!(LogBins::quantile_bin(&[1, 0, 3], 0.5), Some(2));
        let mut a = vec![1, 2, 3];
        LogBins::merge(&mut a, &[1, 1, 1]);
        assert_eq!(a, vec![2, 3, 4]);
    }
}
