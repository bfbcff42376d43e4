#!/usr/bin/env bash
# The project's test command (README).
#   ./scripts/test.sh           formatting, lints, the deployment files against their schemas,
#                               and every test of the workspace, with PostgreSQL, an S3 server
#                               (s3s-fs) and Chromium started for the integration tests
#                               (scripts/services.sh installs what is missing)
#   ./scripts/test.sh --garage  the same against Garage instead of s3s-fs
#   ./scripts/test.sh --quick   formatting, lints and the unit tests only: no services
# Each step's wall and CPU time is printed to stderr as it ends.
set -euo pipefail
cd "$(dirname "$0")/.."

usage() { sed -n '2,9s/^# \{0,1\}//p' "$0"; }
mode=full
export PRECIMAP_S3_SERVER=${PRECIMAP_S3_SERVER:-s3s-fs}
for arg in "$@"; do
    case $arg in
    --quick) mode=quick ;;
    --garage) PRECIMAP_S3_SERVER=garage ;;
    -h | --help) usage; exit 0 ;;
    *) echo "test.sh: unknown option $arg" >&2; usage >&2; exit 2 ;;
    esac
done

started=$(date +%s)
# Runs a step, then prints its wall and CPU time (its child processes' user + system) and the
# machine's load average, so that a slow run shows where its time went.
step() {
    local name=$1
    shift
    local TIMEFORMAT="test.sh: $name: %0R s wall, %0U s user + %0S s system CPU"
    time "$@"
    echo "test.sh: load average $(cut -d' ' -f1-3 /proc/loadavg)" >&2
}

step fmt cargo fmt --all -- --check
step "doc links" python3 scripts/check-links.py
step clippy cargo clippy --workspace --all-targets --locked -- -D warnings
if [ $mode = quick ]; then
    step "unit tests" cargo test --workspace --locked --lib --bins
else
    step "services install" ./scripts/services.sh --install-only
    # Assigned first: a failing services.sh then stops the run (inside `eval "$(…)"` its exit
    # status would be lost and the integration tests would skip instead of failing).
    services_env=$(./scripts/services.sh)
    eval "$services_env"
    step "deployment files" ./scripts/validate-deploy.sh
    step "test build" cargo test --workspace --locked --no-run
    step "tests" cargo test --workspace --locked
fi
echo "test.sh: $mode run passed in $(($(date +%s) - started)) s" >&2
