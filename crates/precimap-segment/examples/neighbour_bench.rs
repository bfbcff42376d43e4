//! Throughput and accuracy of the 3-D neighbour fallback ([`precimap_segment::segment_unordered`])
//! on a synthetic street without a scan pattern: ground, two façades and parked boxes sampled
//! uniformly at random, in time order along the street (a sweep, as an airborne strip or a merged
//! file might be), 5 mm noise. Single-threaded: the figure is points per second per core.
//!
//! `cargo run --release -p precimap-segment --example neighbour_bench -- [POINTS] [REPEAT]`

use precimap_segment::{segment_unordered, SegmentParams, StripGeometry};
use std::time::Instant;

fn main() {
    let mut args = std::env::args().skip(1);
    let points: usize = args.next().and_then(|a| a.parse().ok()).unwrap_or(1_000_000);
    let repeat: usize = args.next().and_then(|a| a.parse().ok()).unwrap_or(3);
    let scene = street(points, 7);
    let geo = StripGeometry { x: &scene.x, y: &scene.y, z: &scene.z, head: &scene.head };
    let params = SegmentParams::default();
    let (mut best, mut best_wall) = (f64::INFINITY, f64::INFINITY);
    let mut out = None;
    for _ in 0..repeat.max(1) {
        let (started, cpu) = (Instant::now(), thread_cpu_s());
        let result = segment_unordered(&geo, &scene.time, &params);
        best = best.min(thread_cpu_s() - cpu);
        best_wall = best_wall.min(started.elapsed().as_secs_f64());
        out = Some(result);
    }
    let out = out.expect("one pass");
    let (mut with, mut sum_deg, mut within_3) = (0usize, 0.0f64, 0usize);
    for (n, truth) in out.segmentation.normals.iter().zip(&scene.normal) {
        let Some(n) = n else { continue };
        with += 1;
        let cos = (0..3).map(|a| f64::from(n.normal[a]) * truth[a]).sum::<f64>().abs().min(1.0);
        let deg = cos.acos().to_degrees();
        sum_deg += deg;
        within_3 += usize::from(deg < 3.0);
    }
    let s = &out.segmentation.stats;
    println!(
        "{points} points, voxel {:.3} m: {:.3} thread CPU s ({:.3} s wall, fastest of {repeat}) = {:.0} k points/s \
         per core\n  \
         with a normal {:.1} %, mean error {:.2}°, within 3° {:.1} %; segmented {:.1} % in {} segments",
        out.voxel_m,
        best,
        best_wall,
        points as f64 / best / 1e3,
        100.0 * with as f64 / points as f64,
        sum_deg / with.max(1) as f64,
        100.0 * within_3 as f64 / with.max(1) as f64,
        100.0 * s.points_segmented as f64 / points as f64,
        s.segments
    );
}

/// CPU seconds of this thread (Linux `/proc/thread-self/schedstat`; wall-clock robust on a
/// shared machine).
fn thread_cpu_s() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<u64>().ok())
        .map_or(f64::NAN, |ns| ns as f64 * 1e-9)
}

struct Scene {
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
    head: Vec<[f64; 3]>,
    time: Vec<f64>,
    normal: Vec<[f64; 3]>,
}

/// `points` samples of a 15 m wide street with 10 m façades and a 4 × 2 × 1.5 m box every 12 m,
/// ~40 points per m² of surface whatever the count (the street grows with it).
fn street(points: usize, seed: u64) -> Scene {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut rand = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    // Surface per metre of street: ground 15, façades 2 × 10, boxes (top + two sides) ≈ 1.8.
    let length = points as f64 / (40.0 * 36.8);
    let mut samples: Vec<([f64; 3], [f64; 3])> = Vec::with_capacity(points);
    while samples.len() < points {
        let x = length * rand();
        let pick = rand() * 36.8;
        let (p, n) = if pick < 15.0 {
            ([x, -7.5 + 15.0 * rand(), 0.0], [0.0, 0.0, 1.0])
        } else if pick < 25.0 {
            ([x, -7.5, 10.0 * rand()], [0.0, 1.0, 0.0])
        } else if pick < 35.0 {
            ([x, 7.5, 10.0 * rand()], [0.0, -1.0, 0.0])
        } else {
            // A box at x mod 12 in 4..8, y in 3..5, 1.5 m high: its top and its street side.
            let bx = (x / 12.0).floor() * 12.0 + 4.0 + 4.0 * rand();
            if rand() < 0.57 {
                ([bx, 3.0 + 2.0 * rand(), 1.5], [0.0, 0.0, 1.0])
            } else {
                ([bx, 3.0, 1.5 * rand()], [0.0, -1.0, 0.0])
            }
        };
        // Ground under a box is hidden.
        if n[2] == 1.0 && p[2] == 0.0 && p[1] > 3.0 && p[1] < 5.0 && (p[0] % 12.0) > 4.0 && (p[0] % 12.0) < 8.0 {
            continue;
        }
        let e = 0.005 * (rand() + rand() + rand() - 1.5) * 2.0;
        samples.push(([p[0] + e * n[0], p[1] + e * n[1], p[2] + e * n[2]], n));
    }
    samples.sort_by(|a, b| a.0[0].total_cmp(&b.0[0]));
    let mut s = Scene { x: vec![], y: vec![], z: vec![], head: vec![], time: vec![], normal: vec![] };
    for (p, n) in samples {
        s.x.push(p[0]);
        s.y.push(p[1]);
        s.z.push(p[2]);
        s.head.push([p[0], 0.0, 2.0]);
        s.time.push(p[0] / 10.0);
        s.normal.push(n);
    }
    s
}
