#!/usr/bin/env bash
# What a crate costs a build: a minimal program using it against the same program without it,
# each built from clean with one job in the workspace's release profile. Prints the crates it
# compiles (and how many of them the product does not compile yet), the CPU seconds
# (user + system) of the clean build, and the stripped binary's size.
#   benches/libraries/build-cost.sh   indicatif, plotters (svg_backend, line_series), faer (sparse-linalg)
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# crate NAME DEPENDENCY-LINE MAIN-BODY
crate() {
    mkdir -p "$work/$1/src"
    cat > "$work/$1/Cargo.toml" <<EOF
[package]
name = "cost-$1"
version = "0.1.0"
edition = "2021"
publish = false
[workspace]
[dependencies]
$2
[profile.release]
debug = 1
codegen-units = 4
EOF
    printf '%s\n' "$3" > "$work/$1/src/main.rs"
}

crate none "" '
use std::io::{IsTerminal, Write};
fn main() {
    let tty = std::io::stderr().is_terminal();
    let mut err = std::io::stderr().lock();
    for done in 1..=200u32 {
        if tty { let _ = write!(err, "\r\x1b[2Kpreparing strips {done}/200"); }
    }
    let _ = writeln!(err, "{}prepared 200 strips", if tty { "\r\x1b[2K" } else { "" });
    println!("<svg xmlns=\"http://www.w3.org/2000/svg\"><polyline points=\"{}\"/></svg>", std::f64::consts::PI);
}'

crate indicatif 'indicatif = "0.18"' '
use indicatif::{ProgressBar, ProgressStyle};
fn main() {
    // Hidden when stderr is not a terminal: the plain lines stay the caller'"'"'s.
    let bar = ProgressBar::new(200).with_style(ProgressStyle::with_template("{msg} {pos}/{len} {wide_bar} {eta}").unwrap());
    bar.set_message("preparing strips");
    for _ in 0..200 { bar.inc(1); }
    bar.finish_and_clear();
    eprintln!("prepared 200 strips");
}'

crate faer 'faer = { version = "=0.24.4", default-features = false, features = ["std", "sparse-linalg"] }' '
use faer::prelude::*;
use faer::sparse::{SparseColMat, Triplet};
fn main() {
    let n = 100;
    let mut t: Vec<Triplet<usize, usize, f64>> = (0..n).map(|i| Triplet { row: i, col: i, val: 4.0 }).collect();
    t.extend((1..n).map(|i| Triplet { row: i, col: i - 1, val: -1.0 }));
    let a = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &t).unwrap();
    let x = a.sp_cholesky(faer::Side::Lower).unwrap().solve(Mat::<f64>::from_fn(n, 1, |_, _| 1.0));
    println!("{}", x[(0, 0)]);
}'

crate plotters 'plotters = { version = "0.3.7", default-features = false, features = ["svg_backend", "line_series"] }' '
use plotters::prelude::*;
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (960, 300)).into_drawing_area();
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root).caption("residuals", ("sans-serif", 14))
            .x_label_area_size(30).y_label_area_size(50).build_cartesian_2d(0.0..10.0, -1.0..1.0)?;
        chart.configure_mesh().x_desc("arc length (m)").draw()?;
        chart.draw_series(LineSeries::new((0..100).map(|i| (i as f64 / 10.0, (i as f64 / 10.0).sin())), &BLUE))?;
        root.present()?;
    }
    println!("{out}");
    Ok(())
}'

# The names of the crates a build compiles for this machine (normal and build dependencies).
host=$(rustc -vV | sed -n 's/^host: //p')
packages() { cargo tree -q "$@" --target "$host" -e normal,build --prefix none | sed 's/ .*//' | sort -u; }
(cd "$root" && packages --workspace --locked) > "$work/product.txt"

printf '%-10s %8s %8s %12s %14s\n' crate crates new clean-CPU-s stripped-bytes
for name in none indicatif plotters faer; do
    (
        cd "$work/$name"
        cargo generate-lockfile -q
        cargo fetch -q
        export CARGO_TARGET_DIR="$work/$name/target" CARGO_BUILD_JOBS=1
        /usr/bin/time -f '%U %S' -o "$work/$name.time" cargo build -q --release --offline
        strip -o "$work/$name.bin" "target/release/cost-$name"
    )
    (cd "$work/$name" && packages --offline) | grep -v "^cost-" > "$work/$name.txt" || true
    brought=$(wc -l < "$work/$name.txt")
    new=$(comm -23 "$work/$name.txt" "$work/product.txt" | wc -l)
    cpu=$(awk '{printf "%.1f", $1 + $2}' "$work/$name.time")
    printf '%-10s %8s %8s %12s %14s\n' "$name" "$brought" "$new" "$cpu" "$(stat -c %s "$work/$name.bin")"
    if [ "$name" != none ]; then
        echo "           not yet in the product: $(comm -23 "$work/$name.txt" "$work/product.txt" | tr '\n' ' ')"
    fi
done
