//! What the kernel knows about this process and its threads (Linux `/proc`): CPU time, page
//! faults and peak memory. Elsewhere the figures are absent (`None`, NaN or 0, as documented).

/// CPU seconds (user + system) this process has used so far (Linux `/proc/self/stat`, clock
/// ticks of 1/100 s); 0 elsewhere.
pub fn cpu_seconds() -> f64 {
    // utime and stime, in clock ticks of 10 ms (USER_HZ is 100 on Linux).
    proc_stat_fields("/proc/self/stat", [14, 15]).map_or(0.0, |[user, system]| (user + system) as f64 / 100.0)
}

/// CPU time (user + system) of process `pid` (`self` for this one) in ms, from `/proc`; `None`
/// where there is no such file (another OS, a server on another machine).
pub fn process_cpu_ms(pid: &str) -> Option<f64> {
    // utime and stime, in clock ticks of 10 ms (USER_HZ is 100 on Linux).
    proc_stat_fields(&format!("/proc/{pid}/stat"), [14, 15]).map(|[user, system]| (user + system) as f64 * 10.0)
}

/// The numeric fields `numbers` (1-based, as in `proc(5)`) of a `/proc/…/stat` file; `None`
/// where it is missing or shorter.
fn proc_stat_fields<const N: usize>(path: &str, numbers: [usize; N]) -> Option<[u64; N]> {
    let stat = std::fs::read_to_string(path).ok()?;
    // The command name (field 2) is in parentheses and may hold spaces: count from after it,
    // where field 3 (the state) comes first.
    let fields: Vec<&str> = stat.get(stat.rfind(')')? + 1..)?.split_whitespace().collect();
    let mut out = [0; N];
    for (value, n) in out.iter_mut().zip(numbers) {
        *value = fields.get(n.checked_sub(3)?)?.parse().ok()?;
    }
    Some(out)
}

/// Resets the kernel's peak-RSS mark so it covers only what follows (Linux; a no-op elsewhere).
pub fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// Peak resident memory since the process started or [`reset_peak_rss`] (0 where unknown).
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<u64>().ok()).map(|kb| kb * 1024))
        })
        .unwrap_or(0)
}

/// CPU time the calling thread has spent on a core (first field of
/// `/proc/thread-self/schedstat`, nanoseconds), `None` where unavailable.
pub fn thread_cpu_s() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse::<u64>().ok().map(|ns| ns as f64 * 1e-9)
}

/// A thread's minor page faults and its user and kernel CPU in clock ticks
/// (`/proc/thread-self/stat`), read before and after a task.
#[derive(Clone, Copy, Debug, Default)]
pub struct ThreadKernelUse {
    pub minor_faults: u64,
    pub user_ticks: u64,
    pub system_ticks: u64,
}

impl ThreadKernelUse {
    /// `None` where there is no such file.
    pub fn now() -> Option<Self> {
        // minflt, utime and stime.
        let [minor_faults, user_ticks, system_ticks] = proc_stat_fields("/proc/thread-self/stat", [10, 14, 15])?;
        Some(Self { minor_faults, user_ticks, system_ticks })
    }

    /// What the thread used since `before` was read.
    pub fn since(before: Option<Self>) -> Option<Self> {
        let (before, after) = (before?, Self::now()?);
        Some(Self {
            minor_faults: after.minor_faults.saturating_sub(before.minor_faults),
            user_ticks: after.user_ticks.saturating_sub(before.user_ticks),
            system_ticks: after.system_ticks.saturating_sub(before.system_ticks),
        })
    }

    pub fn plus(self, other: Self) -> Self {
        Self {
            minor_faults: self.minor_faults + other.minor_faults,
            user_ticks: self.user_ticks + other.user_ticks,
            system_ticks: self.system_ticks + other.system_ticks,
        }
    }

    /// The kernel's share of the CPU ticks (NaN without any).
    pub fn system_share(&self) -> f64 {
        match self.user_ticks + self.system_ticks {
            0 => f64::NAN,
            all => self.system_ticks as f64 / all as f64,
        }
    }
}

/// The `q` quantile of `v` (sorted in place; the nearest rank), NaN when empty.
pub fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    #[test]
    fn own_cpu_time_is_read() {
        let before = process_cpu_ms("self").expect("/proc/self/stat");
        let mut x = 0u64;
        let t = Instant::now();
        while t.elapsed() < Duration::from_millis(100) {
            x = x.wrapping_add(std::hint::black_box(1));
        }
        assert!(x > 0);
        let spent = process_cpu_ms("self").unwrap() - before;
        // 100 ms of spinning; the tick is 10 ms and a busy machine may take CPU away from us.
        assert!((10.0..=1000.0).contains(&spent), "{spent} ms");
        assert_eq!(process_cpu_ms("0"), None);
    }

    #[test]
    fn percentiles() {
        let mut v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&mut v, 0.5), 51.0);
        assert_eq!(percentile(&mut v, 0.99), 99.0);
        assert!(percentile(&mut [], 0.5).is_nan());
    }
}
