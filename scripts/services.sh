#!/usr/bin/env bash
# Starts what the integration tests talk to, when it is not running yet, and prints the
# environment they read (source it: `eval "$(scripts/services.sh)"`):
#   - PostgreSQL on 127.0.0.1:5432 (the machine's cluster);
#   - an S3-compatible server, chosen by PRECIMAP_S3_SERVER (both cached in $CARGO_HOME/bin,
#     ~/.cargo/bin by default, once installed):
#       s3s-fs (default): a single-process S3 server storing objects as files, on a port of
#         127.0.0.1 that the kernel picks; `cargo install s3s-fs` on first use (about 3 CPU-minutes);
#       garage: Garage, a distributed S3 server run as a single node on 127.0.0.1:3900;
#         `cargo install garage` on first use (8 min on a fast machine, 28-77 min on a shared
#         2-core one);
#   - headless Chromium for the dashboard test (Debian's package, installed on first use);
#   - a Python with laspy and LASzip, the independent reader the LAS/LAZ corpus test checks
#     rewritten files with (a cached virtualenv from PyPI, installed on first use).
# `--install-only` installs what is missing and starts nothing.
set -euo pipefail
log() { echo "services: $*" >&2; }

S3_SERVER=${PRECIMAP_S3_SERVER:-s3s-fs}
S3S_FS_VERSION=0.14.1
GARAGE_VERSION=2.5.0
ACCESS_KEY=GK0123456789abcdef01234567
SECRET_KEY=0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef
BUCKET=precimap
export PATH="${CARGO_HOME:-$HOME/.cargo}/bin:$PATH"

port_open() { (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }

install_s3_server() {
    case $S3_SERVER in
    s3s-fs)
        if [ "$(s3s-fs --version 2>/dev/null)" != "s3s-fs $S3S_FS_VERSION" ]; then
            # Unoptimised and without debug info: 203 CPU-seconds to build instead of 388 for a
            # release build, and fast enough for the tests' few megabytes.
            log "installing s3s-fs $S3S_FS_VERSION (first time only; about 3 CPU-minutes)"
            CARGO_PROFILE_DEV_DEBUG=0 cargo install s3s-fs --version "$S3S_FS_VERSION" --features binary \
                --locked --debug >&2
        fi
        ;;
    garage)
        if ! command -v garage >/dev/null; then
            log "installing garage $GARAGE_VERSION (first time only; ~8 min on a fast machine, up to an hour or more on 2 cores)"
            cargo install garage --version "$GARAGE_VERSION" --locked >&2
        fi
        ;;
    *)
        log "PRECIMAP_S3_SERVER=$S3_SERVER is not known; use s3s-fs or garage"
        exit 2
        ;;
    esac
}

install_chromium() {
    if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
        log "installing Debian's chromium and chromedriver for the dashboard tests (first time only, ~1-2 min)"
        SUDO=$([ "$(id -u)" = 0 ] || echo sudo)
        { $SUDO apt-get update -q && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q chromium chromium-driver; } >&2
    fi
}

# Prints the endpoint of the running s3s-fs, starting one (with an empty bucket) if none runs.
# The kernel picks its port; the server's log names it.
start_s3s_fs() {
    local dir=${PRECIMAP_S3S_DIR:-/tmp/precimap-s3s-fs}
    if [ -f "$dir/pid" ] && [ -f "$dir/endpoint" ] \
        && [ "$(cat "/proc/$(cat "$dir/pid")/comm" 2>/dev/null)" = s3s-fs ] \
        && port_open "$(sed 's/.*://' "$dir/endpoint")"; then
        cat "$dir/endpoint"
        return
    fi
    rm -rf "$dir"
    mkdir -p "$dir/root/$BUCKET"
    log "starting s3s-fs"
    # Only its start-up line and errors: the tests make thousands of requests.
    RUST_LOG=error,s3s_fs=info nohup s3s-fs --host 127.0.0.1 --port 0 \
        --access-key "$ACCESS_KEY" --secret-key "$SECRET_KEY" "$dir/root" > "$dir/s3s-fs.log" 2>&1 &
    echo $! > "$dir/pid"
    local endpoint=""
    for _ in $(seq 1 100); do
        endpoint=$(grep -o 'http://127\.0\.0\.1:[0-9]*' "$dir/s3s-fs.log" | head -1 || true)
        [ -n "$endpoint" ] && break
        sleep 0.1
    done
    [ -n "$endpoint" ] && port_open "${endpoint##*:}" \
        || { log "s3s-fs did not start; see $dir/s3s-fs.log"; exit 1; }
    echo "$endpoint" > "$dir/endpoint"
    echo "$endpoint"
}

# Starts Garage on 127.0.0.1:3900 with the bucket, if nothing listens there yet.
start_garage() {
    local dir=${PRECIMAP_GARAGE_DIR:-/tmp/precimap-garage}
    port_open 3900 && return
    mkdir -p "$dir"
    cat > "$dir/garage.toml" <<TOML
metadata_dir = "$dir/meta"
data_dir = "$dir/data"
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
    GARAGE_DEFAULT_ACCESS_KEY=$ACCESS_KEY GARAGE_DEFAULT_SECRET_KEY=$SECRET_KEY GARAGE_DEFAULT_BUCKET=$BUCKET \
        nohup garage -c "$dir/garage.toml" server --single-node --default-bucket \
        > "$dir/garage.log" 2>&1 &
    for _ in $(seq 1 60); do port_open 3900 && break; sleep 0.5; done
    port_open 3900 || { log "garage did not start; see $dir/garage.log"; exit 1; }
    sleep 1
}

# The LAS/LAZ corpus test's independent reader: laspy over LASzip (C++), no code shared with
# the Rust las/laz crates.
LASPY_VENV=${PRECIMAP_LASPY_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/precimap/laspy-venv}
install_laspy() {
    if ! "$LASPY_VENV/bin/python" -c 'import laspy, laszip' 2>/dev/null; then
        log "installing laspy and laszip into $LASPY_VENV (first time only)"
        python3 -m venv "$LASPY_VENV" >&2
        "$LASPY_VENV/bin/pip" install --quiet --disable-pip-version-check laspy==2.7.0 laszip==0.3.0 >&2
    fi
}

install_s3_server
install_chromium
install_laspy
[ "${1:-}" = --install-only ] && exit 0

if ! pg_isready -h 127.0.0.1 -p 5432 -q 2>/dev/null; then
    log "starting PostgreSQL"
    pg_ctlcluster --skip-systemctl-redirect "$(ls /etc/postgresql | head -1)" main start >&2 || true
    for _ in $(seq 1 30); do pg_isready -h 127.0.0.1 -p 5432 -q && break; sleep 1; done
fi
pg_isready -h 127.0.0.1 -p 5432 -q || { log "PostgreSQL is not reachable on 127.0.0.1:5432"; exit 1; }

case $S3_SERVER in
s3s-fs)
    ENDPOINT=$(start_s3s_fs)
    REGION=us-east-1
    ;;
garage)
    start_garage
    ENDPOINT=http://127.0.0.1:3900
    REGION=garage
    ;;
esac

CHROMIUM=$(command -v chromium) || { log "chromium is not installed"; exit 1; }
CHROMEDRIVER=$(command -v chromedriver) || { log "chromedriver is not installed"; exit 1; }

cat <<ENV
export PRECIMAP_TEST_CHROMIUM=$CHROMIUM
export PRECIMAP_TEST_CHROMEDRIVER=$CHROMEDRIVER
export PRECIMAP_TEST_POSTGRES=postgres://postgres@127.0.0.1:5432/postgres
export PRECIMAP_TEST_S3=s3://$BUCKET/test
export PRECIMAP_TEST_LASPY=$LASPY_VENV/bin/python
export AWS_ACCESS_KEY_ID=$ACCESS_KEY
export AWS_SECRET_ACCESS_KEY=$SECRET_KEY
export AWS_REGION=$REGION
export AWS_ENDPOINT=$ENDPOINT
export AWS_ALLOW_HTTP=true
export PRECIMAP_REQUIRE_SERVICES=1
ENV
