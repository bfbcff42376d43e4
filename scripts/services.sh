#!/usr/bin/env bash
# Starts what the integration tests talk to, when it is not running yet, and prints the
# environment they read (source it: `eval "$(scripts/services.sh)"`):
#   - PostgreSQL on 127.0.0.1:5432 (the machine's cluster);
#   - Garage, a single-node S3-compatible server on 127.0.0.1:3900, installed with
#     `cargo install garage` on first use (~8 min on a fast machine; 65-77 min on this project's
#     2-core machine beside other builds; the binary is cached in ~/.cargo/bin);
#   - headless Chromium for the dashboard test (Debian's package, installed on first use).
set -euo pipefail
log() { echo "services: $*" >&2; }

if ! pg_isready -h 127.0.0.1 -p 5432 -q 2>/dev/null; then
    log "starting PostgreSQL"
    pg_ctlcluster --skip-systemctl-redirect "$(ls /etc/postgresql | head -1)" main start >&2 || true
    for _ in $(seq 1 30); do pg_isready -h 127.0.0.1 -p 5432 -q && break; sleep 1; done
fi
pg_isready -h 127.0.0.1 -p 5432 -q || { log "PostgreSQL is not reachable on 127.0.0.1:5432"; exit 1; }

GARAGE_DIR=${PRECIMAP_GARAGE_DIR:-/tmp/precimap-garage}
ACCESS_KEY=GK0123456789abcdef01234567
SECRET_KEY=0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef
export PATH="$HOME/.cargo/bin:$PATH"
port_open() { (exec 3<>/dev/tcp/127.0.0.1/3900) 2>/dev/null; }
if ! port_open; then
    if ! command -v garage >/dev/null; then
        log "installing garage 2.5.0 (first time only; ~8 min on a fast machine, up to an hour or more on 2 cores)"
        cargo install garage --version 2.5.0 --locked >&2
    fi
    mkdir -p "$GARAGE_DIR"
    cat > "$GARAGE_DIR/garage.toml" <<TOML
metadata_dir = "$GARAGE_DIR/meta"
data_dir = "$GARAGE_DIR/data"
db_engine = "sqlite"
replication_factor = 1
rpc_bind_addr = "127.0.0.1:3901"
rpc_secret = "$(printf '%064d' 7)"
[s3_api]
s3_region = "garage"
api_bind_addr = "127.0.0.1:3900"
[admin]
api_bind_addr = "127.0.0.1:3903"
admin_token = "precimap-test-admin"
TOML
    log "starting garage"
    GARAGE_DEFAULT_ACCESS_KEY=$ACCESS_KEY GARAGE_DEFAULT_SECRET_KEY=$SECRET_KEY GARAGE_DEFAULT_BUCKET=precimap \
        nohup garage -c "$GARAGE_DIR/garage.toml" server --single-node --default-bucket \
        > "$GARAGE_DIR/garage.log" 2>&1 &
    for _ in $(seq 1 60); do port_open && break; sleep 0.5; done
    port_open || { log "garage did not start; see $GARAGE_DIR/garage.log"; exit 1; }
    sleep 1
fi

if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
    log "installing Debian's chromium and chromedriver for the dashboard tests (first time only, ~1-2 min)"
    SUDO=$([ "$(id -u)" = 0 ] || echo sudo)
    { $SUDO apt-get update -q && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q chromium chromium-driver; } >&2
fi
CHROMIUM=$(command -v chromium) || { log "chromium is not installed"; exit 1; }
CHROMEDRIVER=$(command -v chromedriver) || { log "chromedriver is not installed"; exit 1; }

cat <<ENV
export PRECIMAP_TEST_CHROMIUM=$CHROMIUM
export PRECIMAP_TEST_CHROMEDRIVER=$CHROMEDRIVER
export PRECIMAP_TEST_POSTGRES=postgres://postgres@127.0.0.1:5432/postgres
export PRECIMAP_TEST_S3=s3://precimap/test
export AWS_ACCESS_KEY_ID=$ACCESS_KEY
export AWS_SECRET_ACCESS_KEY=$SECRET_KEY
export AWS_REGION=garage
export AWS_ENDPOINT=http://127.0.0.1:3900
export AWS_ALLOW_HTTP=true
export PRECIMAP_REQUIRE_SERVICES=1
ENV
