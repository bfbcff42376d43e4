#!/usr/bin/env bash
# The measurements behind docs/design/libraries.md, on one core each (the machine's other core
# left to the rest). Builds this crate (outside the workspace: the product's build and
# Cargo.lock do not change) into the workspace's target directory.
#   benches/libraries/run.sh            all of them
#   benches/libraries/run.sh sparse 60  one of: sparse [BLOCKS…], rng [COUNT], plots [ANCHORS], build-cost
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$here/../../target}
if [ "${1:-}" = build-cost ]; then exec "$here/build-cost.sh"; fi
CARGO_BUILD_JOBS=${CARGO_BUILD_JOBS:-1} cargo build -q --release --manifest-path "$here/Cargo.toml"
bench="$CARGO_TARGET_DIR/release/precimap-library-bench"
if [ $# -gt 0 ]; then exec "$bench" "$@"; fi
"$bench" sparse
"$bench" rng
"$bench" plots
"$here/build-cost.sh"
