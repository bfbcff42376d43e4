#!/usr/bin/env bash
# The project's test command (README).
#   ./scripts/test.sh           formatting, lints, the deployment files against their schemas,
#                               and every test of the workspace, with PostgreSQL, an S3 server
#                               (s3s-fs) and Chromium started for the integration tests
#                               (scripts/services.sh installs what is missing)
#   ./scripts/test.sh --garage  the same against Garage instead of s3s-fs
#   ./scripts/test.sh --quick   formatting, lints and the unit tests only: no services
# Clippy runs as the compiler of the workspace's crates during the test build (see below);
# `cargo clippy --workspace --all-targets -- -D warnings` gives the same verdict interactively.
# Each step's wall and CPU time is printed to stderr as it ends.
set -euo pipefail
cd "$(dirname "$0")/.."

usage() { sed -n '2,11s/^# \{0,1\}//p' "$0"; }
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

if [ $mode = full ]; then
    # Installing the S3 server, Chromium and laspy (first run only) overlaps the build: the build
    # leaves a core idle in its serial stretches, and the downloads need none.
    mkdir -p target
    ./scripts/services.sh --install-only > target/services-install.log 2>&1 &
    installer=$!
fi

# Clippy's lints run inside the test build: clippy-driver wraps the workspace's own crates, as
# `cargo clippy` does in check mode, so the dependencies are compiled once instead of checked and
# then built. The same environment for the test run keeps Cargo from rebuilding.
export RUSTC_WORKSPACE_WRAPPER="$(rustc --print sysroot)/bin/clippy-driver"
export CLIPPY_ARGS="-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__"
step "clippy + test build" cargo test --workspace --all-targets --locked --no-run

if [ $mode = quick ]; then
    step "unit tests" cargo test --workspace --locked --lib --bins
else
    step "services install" wait $installer || { cat target/services-install.log >&2; exit 1; }
    # Assigned first: a failing services.sh then stops the run (inside `eval "$(…)"` its exit
    # status would be lost and the integration tests would skip instead of failing).
    services_env=$(./scripts/services.sh)
    eval "$services_env"
    step "deployment files" ./scripts/validate-deploy.sh
    step "tests" cargo test --workspace --locked
fi
echo "test.sh: $mode run passed in $(($(date +%s) - started)) s" >&2
