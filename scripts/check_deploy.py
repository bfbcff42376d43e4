"""Checks of the deployment files that no schema makes.

- Every PRECIMAP_* variable the compose file and the Kubernetes manifests set is one the
  `precimap` binary reads (a misspelt name would be silently ignored).
- The KEDA objects (keda.sh CRDs, unknown to the Kubernetes schemas) refer to objects that exist:
  the scaled Deployment, the TriggerAuthentication, the Secret key holding the connection string;
  a ScaledJob's job template is validated as a batch/v1 Job.
- Each scaler query runs against the job store's real schema (migrations/postgres applied to a
  scratch database) and counts what it should on a seeded queue.
"""

import glob
import os
import re
import subprocess
import sys
import uuid

import kubernetes_validate
import yaml

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
K8S = os.path.join(ROOT, "deploy", "kubernetes")
failures = []


def fail(message):
    failures.append(message)
    print(f"check_deploy: FAIL {message}", file=sys.stderr)


def documents(pattern):
    for path in sorted(glob.glob(os.path.join(K8S, pattern), recursive=True)):
        with open(path) as f:
            for doc in yaml.safe_load_all(f):
                if doc:
                    yield os.path.relpath(path, ROOT), doc


def env_names(container):
    return [e["name"] for e in container.get("env", [])]


def binary_env_names():
    names = set()
    for path in glob.glob(os.path.join(ROOT, "crates", "precimap-cli", "src", "**", "*.rs"), recursive=True):
        with open(path) as f:
            names.update(re.findall(r'env\s*=\s*"(PRECIMAP_[A-Z0-9_]+)"', f.read()))
    return names


def check_variables(all_docs):
    known = binary_env_names()
    used = {}
    for path, doc in all_docs:
        if doc["kind"] in ("ConfigMap", "Secret"):
            for name in list(doc.get("data", {})) + list(doc.get("stringData", {})):
                used.setdefault(name, path)
        spec = doc.get("spec", {})
        template = spec.get("template") or spec.get("jobTargetRef", {}).get("template") or {}
        for container in template.get("spec", {}).get("containers", []):
            for name in env_names(container):
                used.setdefault(name, path)
    with open(os.path.join(ROOT, "docker", "compose.yaml")) as f:
        compose = yaml.safe_load(f)
    for service in compose["services"].values():
        env = service.get("environment", {})
        for name in env if isinstance(env, dict) else [e.split("=")[0] for e in env]:
            if name != "<<":
                used.setdefault(name, "docker/compose.yaml")
    for name, path in sorted(used.items()):
        if name.startswith("PRECIMAP_") and name not in known:
            fail(f"{path} sets {name}, which precimap does not read")
    print(f"check_deploy: {len(used)} variables checked against the binary's {len(known)}", file=sys.stderr)


def check_keda(all_docs):
    by_kind = {}
    for path, doc in all_docs:
        by_kind.setdefault(doc["kind"], {})[doc["metadata"]["name"]] = (path, doc)
    secrets = by_kind.get("Secret", {})
    auths = by_kind.get("TriggerAuthentication", {})
    queries = []
    for name, (path, auth) in auths.items():
        for ref in auth["spec"]["secretTargetRef"]:
            _, secret = secrets.get(ref["name"], (None, None))
            if secret is None or ref["key"] not in secret.get("stringData", {}):
                fail(f"{path}: TriggerAuthentication {name} reads {ref['name']}/{ref['key']}, which no Secret holds")
    for kind in ("ScaledObject", "ScaledJob"):
        for name, (path, obj) in by_kind.get(kind, {}).items():
            spec = obj["spec"]
            if kind == "ScaledObject":
                target = spec["scaleTargetRef"]["name"]
                if target not in by_kind.get("Deployment", {}):
                    fail(f"{path}: ScaledObject {name} scales {target}, which is no Deployment here")
            else:
                job = {"apiVersion": "batch/v1", "kind": "Job", "metadata": {"name": name}, "spec": spec["jobTargetRef"]}
                try:
                    kubernetes_validate.validate(job, "1.37.0", strict=True)
                except Exception as e:  # the validator's own error types carry the message
                    fail(f"{path}: ScaledJob {name}'s job template is not a valid Job: {e}")
            if not spec.get("triggers"):
                fail(f"{path}: {kind} {name} has no trigger")
            for trigger in spec.get("triggers", []):
                if trigger["type"] != "postgresql":
                    fail(f"{path}: {kind} {name}: unexpected trigger type {trigger['type']}")
                    continue
                auth = trigger.get("authenticationRef", {}).get("name")
                if auth not in auths:
                    fail(f"{path}: {kind} {name} authenticates with {auth}, which is no TriggerAuthentication here")
                float(trigger["metadata"]["targetQueryValue"])
                queries.append((f"{path}: {kind} {name}", kind, trigger["metadata"]["query"]))
    return queries


def psql(dsn, sql):
    result = subprocess.run(
        ["psql", dsn, "-v", "ON_ERROR_STOP=1", "-q", "-t", "-A", "-c", sql], capture_output=True, text=True
    )
    if result.returncode != 0:
        raise RuntimeError(result.stderr.strip())
    return result.stdout.strip()


def check_queries(queries):
    admin = os.environ.get("PRECIMAP_TEST_POSTGRES", "postgres://postgres@127.0.0.1:5432/postgres")
    scratch = f"precimap_deploy_{uuid.uuid4().hex[:12]}"
    dsn = admin.rsplit("/", 1)[0] + "/" + scratch
    psql(admin, f"CREATE DATABASE {scratch}")
    try:
        for migration in sorted(glob.glob(os.path.join(ROOT, "migrations", "postgres", "*.sql"))):
            with open(migration) as f:
                psql(dsn, f.read())
        campaign = uuid.uuid4()
        psql(
            dsn,
            "INSERT INTO campaigns (id, name, state, stage, iteration, iterations_planned, spec, plan_state,"
            " object_prefix, max_attempts, backoff_base_ms, backoff_max_ms, created_at_ms, updated_at_ms)"
            f" VALUES ('{campaign}', 'deploy-check', 'running', 'prepare', 0, 18, '{{}}', '{{}}', 'c/x', 3, 0, 0, 0, 0)",
        )
        # 3 queued, 2 leased, 4 done, 1 dead: executors are needed for the 5 open tasks.
        states = ["queued"] * 3 + ["leased"] * 2 + ["done"] * 4 + ["dead"]
        for i, state in enumerate(states):
            psql(
                dsn,
                "INSERT INTO tasks (campaign, stage, iteration, kind, key, input, state, not_before_ms,"
                f" created_at_ms, updated_at_ms) VALUES ('{campaign}', 'prepare', 0, 'segment_strip', 's{i}',"
                f" '{{}}', '{state}', 0, 0, 0)",
            )
        # A long-lived executor serves queued and leased tasks alike; a Job per task, queued ones.
        expected = {"ScaledObject": 5, "ScaledJob": 3}
        for where, kind, query in queries:
            count = int(psql(dsn, query))
            if count != expected[kind]:
                fail(f"{where}: its query counts {count} on a queue of 3 queued and 2 leased tasks, not {expected[kind]}")
            else:
                print(f"check_deploy: {where}: query counts {count}", file=sys.stderr)
    finally:
        psql(admin, f"DROP DATABASE IF EXISTS {scratch}")


def main():
    all_docs = list(documents("**/*.yaml"))
    check_variables(all_docs)
    check_queries(check_keda(all_docs))
    if failures:
        sys.exit(f"check_deploy: {len(failures)} problem(s)")
    print("check_deploy: deployment files consistent", file=sys.stderr)


if __name__ == "__main__":
    main()
