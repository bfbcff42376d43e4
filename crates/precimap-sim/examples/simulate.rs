//! `cargo run --release -p precimap-sim --example simulate -- SCALE SEED DIR [--laz]`: simulates a
//! campaign and prints the summary with the throughput.

use precimap_sim::{simulate, Scale, SimConfig};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let scale: Scale = args.first().map_or("tiny", String::as_str).parse().expect("scale");
    let seed: u64 = args.get(1).map_or(Ok(1), |s| s.parse()).expect("seed");
    let out = std::path::PathBuf::from(args.get(2).map_or("/tmp/precimap-sim", String::as_str));
    let laz = args.iter().any(|a| a == "--laz");
    let cfg = SimConfig::for_scale(scale, seed);
    let s = simulate(&cfg, &out, laz).expect("simulate");
    println!("{}", serde_json::to_string_pretty(&s).expect("json"));
    println!(
        "{scale}: {} points in {:.2} s = {:.2} M points/s ({} threads)",
        s.points,
        s.wall_seconds,
        s.points as f64 / s.wall_seconds / 1e6,
        rayon::current_num_threads()
    );
}
