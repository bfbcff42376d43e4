#!/usr/bin/env bash
# The service's acceptance run, rerunnable: a simulated campaign (default: small) through
# `precimap serve` on PostgreSQL + S3 (scripts/services.sh's server) with 4 separate `precimap work` processes, compared
# byte for byte with `precimap run --in-process`. Usage: scripts/serve-acceptance.sh [SCALE] [SEED]
set -euo pipefail
cd "$(dirname "$0")/.."
SCALE=${1:-small}; SEED=${2:-1}
export PRECIMAP_S3_SERVER=${PRECIMAP_S3_SERVER:-s3s-fs}
eval "$(./scripts/services.sh)"
cargo build --release -p precimap-cli >&2
BIN=$PWD/target/release/precimap
WORK=$(mktemp -d /tmp/precimap-acceptance.XXXXXX)
DB=precimap_acceptance_$(date +%s)
psql "$PRECIMAP_TEST_POSTGRES" -qc "CREATE DATABASE $DB"
export PRECIMAP_DB=${PRECIMAP_TEST_POSTGRES%/*}/$DB
export PRECIMAP_STORE=$PRECIMAP_TEST_S3/acceptance-$(date +%s)
export PRECIMAP_TOKEN=acceptance-token PRECIMAP_LOG=warn
PORT=$((20000 + RANDOM % 20000))
export PRECIMAP_SERVER=http://127.0.0.1:$PORT
pids=()
cleanup() { kill "${pids[@]}" 2>/dev/null || true; psql "$PRECIMAP_TEST_POSTGRES" -qc "DROP DATABASE IF EXISTS $DB WITH (FORCE)" || true; }
trap cleanup EXIT
"$BIN" simulate --scale "$SCALE" --seed "$SEED" --out "$WORK/campaign" >&2
start=$(date +%s.%N)
"$BIN" run --in-process "$WORK/campaign/manifest.json" --out "$WORK/in-process" >&2
inproc=$(echo "$(date +%s.%N) - $start" | bc)
"$BIN" serve --listen 127.0.0.1:$PORT >&2 & pids+=($!)
sleep 2
start=$(date +%s.%N)
for _ in 1 2 3 4; do "$BIN" work --concurrency 1 & pids+=($!); done
ID=$("$BIN" submit "$WORK/campaign/manifest.json")
"$BIN" status "$ID" --watch > "$WORK/status.log"
served=$(echo "$(date +%s.%N) - $start" | bc)
"$BIN" results "$ID" --out "$WORK/served" >&2
for f in $(cd "$WORK/in-process" && find strips trajectories segments -type f | sort); do
    cmp -s "$WORK/in-process/$f" "$WORK/served/$f" || { echo "DIFFERENT: $f"; exit 1; }
done
echo "identical results (strips, trajectories, segments) for $SCALE seed $SEED"
echo "in-process $inproc s; serve + 4 work processes on PostgreSQL + $PRECIMAP_S3_SERVER S3 $served s"
