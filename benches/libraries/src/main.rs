//! `precimap-library-bench`: the measurements behind docs/design/libraries.md.
//!
//!   precimap-library-bench sparse [BLOCKS…]   sparse Cholesky, precimap's settings vs faer's defaults
//!   precimap-library-bench rng [COUNT]        random numbers, precimap vs rand
//!   precimap-library-bench plots [ANCHORS]    a QC plot, precimap vs plotters
//!
//! `./benches/libraries/run.sh` runs both and the build-cost figures for indicatif and plotters.

mod alloc;
mod plots;
mod rng;
mod sparse;

/// CPU seconds of the calling thread so far (`/proc/thread-self/schedstat`): on a shared
/// machine the wall time counts the other processes' turns, the thread's CPU time does not.
pub fn thread_cpu_s() -> f64 {
    let stat = std::fs::read_to_string("/proc/thread-self/schedstat").unwrap_or_default();
    stat.split_whitespace().next().and_then(|ns| ns.parse::<f64>().ok()).map_or(f64::NAN, |ns| ns * 1e-9)
}

#[global_allocator]
static COUNTING: alloc::Counting = alloc::Counting;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let numbers: Vec<usize> = args.iter().skip(1).filter_map(|a| a.parse().ok()).collect();
    match args.first().map(String::as_str) {
        Some("sparse") => {
            let blocks = if numbers.is_empty() { vec![15, 30, 60] } else { numbers };
            sparse::run(&blocks, 3, 3);
        }
        Some("plots") => plots::run(numbers.first().copied().unwrap_or(20_000)),
        Some("rng") => rng::run(numbers.first().map_or(20_000_000, |&n| n as u64)),
        _ => {
            eprintln!("usage: precimap-library-bench sparse [BLOCKS…] | rng [COUNT] | plots [ANCHORS]");
            std::process::exit(2);
        }
    }
}
