//! precimap's random numbers (`precimap_sim::rng`) against `rand` 0.10, `rand_distr`,
//! `rand_chacha` and `rand_pcg`: throughput per core, and whether `rand`'s xoshiro256++ gives
//! the same stream as precimap's from the same state.

use crate::thread_cpu_s;
use precimap_sim::rng::{hash2, normal, splitmix64, unit, Rng as Ours};
use rand::rngs::{StdRng, Xoshiro256PlusPlus};
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rand_pcg::Pcg64Mcg;
use std::hint::black_box;

/// Millions of values per CPU-second from `count` calls of `next`, best of three.
fn rate(count: u64, mut next: impl FnMut(u64) -> f64) -> f64 {
    let mut best = f64::INFINITY;
    for _ in 0..3 {
        let start = thread_cpu_s();
        let mut sum = 0.0;
        for k in 0..count {
            sum += next(k);
        }
        black_box(sum);
        best = best.min(thread_cpu_s() - start);
    }
    count as f64 / best / 1e6
}

/// `rand`'s xoshiro256++ from the state precimap's `Rng::new(seed, stream)` starts from.
fn rand_xoshiro_like_ours(seed: u64, stream: u64) -> Xoshiro256PlusPlus {
    let mut sm = hash2(seed, stream);
    let mut bytes = [0u8; 32];
    for word in bytes.chunks_exact_mut(8) {
        word.copy_from_slice(&splitmix64(&mut sm).to_le_bytes());
    }
    Xoshiro256PlusPlus::from_seed(bytes)
}

pub fn run(count: u64) {
    println!("# random numbers: millions per CPU-second of one thread (best of 3, {count} values each)");
    let bits = |x: u64| (x >> 11) as f64;
    let mut ours = Ours::new(1, 2);
    let mut xo = Xoshiro256PlusPlus::seed_from_u64(1);
    let mut pcg = Pcg64Mcg::seed_from_u64(1);
    let mut chacha8 = ChaCha8Rng::seed_from_u64(1);
    let mut std_rng = StdRng::seed_from_u64(1);
    let rows: Vec<(&str, f64)> = vec![
        ("u64: precimap xoshiro256++", rate(count, |_| bits(ours.next_u64()))),
        ("u64: rand Xoshiro256PlusPlus", rate(count, |_| bits(xo.next_u64()))),
        ("u64: rand_pcg Pcg64Mcg", rate(count, |_| bits(pcg.next_u64()))),
        ("u64: rand_chacha ChaCha8Rng", rate(count, |_| bits(chacha8.next_u64()))),
        ("u64: rand StdRng (ChaCha12, not portable)", rate(count, |_| bits(std_rng.next_u64()))),
        ("f64 [0,1): precimap Rng::f64", rate(count, |_| ours.f64())),
        ("f64 [0,1): rand random::<f64>() on xoshiro", rate(count, |_| xo.random::<f64>())),
        ("normal: precimap Rng::normal (Box-Muller)", rate(count, |_| ours.normal())),
        (
            "normal: rand_distr StandardNormal (ziggurat) on xoshiro",
            rate(count, |_| xo.sample::<f64, _>(StandardNormal)),
        ),
        ("keyed uniform: precimap unit(hash2(seed, key))", rate(count, |k| unit(hash2(7, k)))),
        ("keyed normal: precimap normal(hash2(seed, key))", rate(count, |k| normal(hash2(7, k)))),
        (
            "keyed normal: rand, a xoshiro seeded per key + StandardNormal",
            rate(count, |k| Xoshiro256PlusPlus::seed_from_u64(hash2(7, k)).sample::<f64, _>(StandardNormal)),
        ),
    ];
    for (name, mps) in rows {
        println!("{name:<62} {mps:>8.1}");
    }
    // Equal streams from equal states: rand's generator could stand in for precimap's sequential
    // one without changing a campaign.
    let (mut a, mut b) = (Ours::new(0x5EED, 3), rand_xoshiro_like_ours(0x5EED, 3));
    let same = (0..count).all(|_| a.next_u64() == b.next_u64());
    println!("rand Xoshiro256PlusPlus seeded with precimap's state gives precimap's stream ({count} values): {same}");
}
