#!/usr/bin/env bash
# The project's test command (README): formatting, lints, and every test of the workspace,
# with PostgreSQL and a local S3 server (Garage) started for the integration tests.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo fmt --all -- --check
cargo clippy --workspace --all-targets --locked -- -D warnings
eval "$(./scripts/services.sh)"
cargo test --workspace --locked
