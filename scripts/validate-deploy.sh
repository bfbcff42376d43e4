#!/usr/bin/env bash
# Validates the deployment files against their schemas, offline:
#   - docker/compose.yaml against the Compose specification (check-jsonschema's vendored schema);
#   - deploy/kubernetes/**/*.yaml against the Kubernetes API schemas (kubernetes-validate, strict);
#   - the KEDA objects (CRDs the Kubernetes schemas do not know) by scripts/check_deploy.py, which
#     also runs their scaler queries against the real job-store schema on PostgreSQL.
# The validators install once into a cached virtualenv from PyPI.
set -euo pipefail
cd "$(dirname "$0")/.."
log() { echo "validate-deploy: $*" >&2; }

VENV=${PRECIMAP_DEPLOY_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/precimap/deploy-venv}
if [ ! -x "$VENV/bin/kubernetes-validate" ] || [ ! -x "$VENV/bin/check-jsonschema" ]; then
    log "installing check-jsonschema and kubernetes-validate into $VENV (first time only)"
    python3 -m venv "$VENV"
    "$VENV/bin/pip" install --quiet --disable-pip-version-check \
        check-jsonschema==0.39.0 kubernetes-validate==1.37.0 >&2
fi

"$VENV/bin/check-jsonschema" --builtin-schema vendor.compose-spec docker/compose.yaml
mapfile -t manifests < <(find deploy/kubernetes -name '*.yaml' -not -path '*/keda/*' | sort)
"$VENV/bin/kubernetes-validate" --strict --quiet "${manifests[@]}"
log "${#manifests[@]} Kubernetes manifests valid"
"$VENV/bin/python" scripts/check_deploy.py
