"""deploy/: the compose stack, the Kubernetes manifests and the images, checked without a container engine.

- The compose file validates against the Compose specification's JSON schema
  (kept in deploy/schema/, checksum pinned); the manifests against the
  Kubernetes schemas that ``kubernetes-validate`` ships (strict: unknown
  fields fail), for the oldest and newest Kubernetes versions named below.
- What a schema cannot see: every ``UNDREAM_*`` variable is a real setting
  (or one the code reads) and every value parses as that setting; volumes,
  references between objects and health checks line up; the Dockerfile's
  copied paths exist; every ``undream`` command line in the images, the
  compose file and the manifests parses with the real CLI.
No image is built here (no container engine runs on this machine).
"""
from __future__ import annotations

import copy
import hashlib
import importlib.util
import json
import re
import shutil
import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path
from typing import Any, Iterator

import jsonschema
import kubernetes_validate
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
COMPOSE = DEPLOY / "compose.yaml"
K8S = DEPLOY / "k8s"
DOCKERFILE = DEPLOY / "docker" / "Dockerfile"
SCHEMA = DEPLOY / "schema" / "compose-spec.json"
SCHEMA_SHA256 = "1f91e091f16b2dd50ab8860e02bb391d22df553d91c145eacedb1b6eff9c3f0e"
K8S_VERSIONS = ("1.29.0", kubernetes_validate.latest_version())
OPTIONAL_MANIFESTS = {"flower.yaml"}  # applied by hand (README), not by kustomization.yaml
USER_SECRETS = {"undream-postgres", "undream-dashboard"}  # made with kubectl (README), never kept here
SECRET = "s3cret-value"  # stands for a secret's value
UNDREAM_IMAGE = re.compile(r"^undream:(cpu|gpu)$")


def compose() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE.read_text())


def manifests() -> dict[str, list[dict[str, Any]]]:
    """Every Kubernetes object of deploy/k8s/, by file (kustomization.yaml excluded)."""
    return {p.name: [d for d in yaml.safe_load_all(p.read_text()) if d]
            for p in sorted(K8S.glob("*.yaml")) if p.name != "kustomization.yaml"}


def objects() -> list[dict[str, Any]]:
    return [d for docs in manifests().values() for d in docs]


def pod_specs() -> Iterator[tuple[str, dict[str, Any]]]:
    for obj in objects():
        if obj["kind"] in ("Deployment", "StatefulSet"):
            yield obj["metadata"]["name"], obj["spec"]["template"]["spec"]


def undream_containers() -> Iterator[tuple[str, dict[str, Any]]]:
    """(workload, container) for every container that runs an undream image (init containers too)."""
    for name, spec in pod_specs():
        for c in spec.get("initContainers", []) + spec["containers"]:
            if UNDREAM_IMAGE.match(c["image"]):
                yield name, c


def undream_services() -> dict[str, dict[str, Any]]:
    return {n: s for n, s in compose()["services"].items() if UNDREAM_IMAGE.match(s.get("image", ""))}


def worker_containers() -> Iterator[tuple[str, dict[str, Any]]]:
    return ((w, c) for w, c in undream_containers() if c.get("args", [None])[0] == "worker")


# --- the compose file against the Compose specification ---------------------------------------


def test_the_kept_compose_schema_is_the_recorded_copy():
    assert hashlib.sha256(SCHEMA.read_bytes()).hexdigest() == SCHEMA_SHA256
    assert SCHEMA_SHA256 in (DEPLOY / "schema" / "README.md").read_text()
    assert "Apache License" in (DEPLOY / "schema" / "LICENSE").read_text()


def _compose_errors(doc: dict[str, Any]) -> list[str]:
    schema = json.loads(SCHEMA.read_text())
    jsonschema.Draft7Validator.check_schema(schema)
    validator = jsonschema.Draft7Validator(schema)
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(doc)]


def test_the_compose_file_validates_against_the_compose_specification():
    assert _compose_errors(compose()) == []


@pytest.mark.parametrize(("path", "value", "expected"), [
    (("services", "worker", "healthcheck", "intervall"), "30s", "'intervall' does not match any of the regexes"),
    (("services", "worker", "deploy", "replicas"), [2], "is not of type 'integer', 'string'"),
    (("services", "redis", "depends_on"), {"postgres": {"condition": "healthy"}}, "is not valid under any of the given schemas"),
])
def test_a_broken_compose_file_fails_the_schema(path, value, expected):
    doc = copy.deepcopy(compose())
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    errors = _compose_errors(doc)
    assert errors and any(expected in e for e in errors), errors


def test_compose_services_wait_for_healthy_dependencies_and_check_their_own_health():
    services = compose()["services"]
    for name, svc in services.items():
        if name != "flower":
            assert "healthcheck" in svc, name
        for dep, how in svc.get("depends_on", {}).items():
            assert how["condition"] == "service_healthy", (name, dep)
            assert "healthcheck" in services[dep], f"{name} waits for {dep}, which has no health check"
    for name, svc in undream_services().items():
        assert svc["healthcheck"]["test"][:2] == ["CMD", "undream-healthcheck"], name


def test_compose_undream_services_share_the_blob_volume_and_workers_a_cache_per_machine():
    doc = compose()
    assert {"worker", "worker-gpu", "dashboard"} <= set(undream_services())
    for name, svc in undream_services().items():
        env = svc["environment"]
        mounts = dict(reversed(v.split(":")[:2]) for v in svc["volumes"])
        assert mounts[env["UNDREAM_BLOB_URL"]] == "blobs", name
        if svc["command"][0] == "worker":
            assert mounts[env["UNDREAM_CACHE_DIR"]] == "cache", name
        assert set(mounts.values()) <= set(doc["volumes"]), name
    assert {"redis", "postgres", "blobs", "cache"} <= set(doc["volumes"])


def test_compose_dashboard_serves_on_loopback_and_checks_its_health_api():
    dash = compose()["services"]["dashboard"]
    port = dash["command"][dash["command"].index("--port") + 1]
    assert dash["ports"] == [f"127.0.0.1:{port}:{port}"]
    assert dash["healthcheck"]["test"] == ["CMD", "undream-healthcheck", "http",
                                           f"http://127.0.0.1:{port}/api/health"]


def test_compose_gpu_workers_reserve_a_gpu_and_flower_is_optional():
    services = compose()["services"]
    gpu = services["worker-gpu"]
    assert gpu["image"] == "undream:gpu" and gpu["build"]["target"] == "gpu" and gpu["profiles"] == ["gpu"]
    (device,) = gpu["deploy"]["resources"]["reservations"]["devices"]
    assert device["driver"] == "nvidia" and device["capabilities"] == ["gpu"]
    assert services["worker"]["build"]["target"] == "cpu" and "profiles" not in services["worker"]
    assert services["flower"]["profiles"] == ["flower"]


# --- the Kubernetes manifests -------------------------------------------------------------------


@pytest.mark.parametrize("version", K8S_VERSIONS)
def test_every_manifest_validates_against_the_kubernetes_schemas(version):
    seen = []
    for name, docs in manifests().items():
        for doc in docs:
            kubernetes_validate.validate(doc, version, strict=True)
            seen.append(f"{doc['kind']}/{doc['metadata']['name']}")
    assert {"Deployment/undream-worker-cpu", "Deployment/undream-worker-gpu", "Deployment/undream-dashboard",
            "Service/undream-dashboard", "StatefulSet/undream-redis",
            "StatefulSet/undream-postgres", "PersistentVolumeClaim/undream-blobs",
            "HorizontalPodAutoscaler/undream-worker-cpu", "ConfigMap/undream-config"} <= set(seen)


@pytest.mark.parametrize(("mutate", "expected"), [
    (lambda d: d["spec"].__setitem__("replica", 2), "Additional properties are not allowed"),
    (lambda d: d["spec"]["template"]["spec"]["containers"][0].__setitem__("args", "worker"), "is not of type"),
    (lambda d: d["spec"]["template"]["spec"]["containers"][0]["resources"]["limits"].__setitem__("cpu", [2]),
     "is not valid"),
])
def test_a_broken_manifest_fails_validation(mutate, expected):
    doc = copy.deepcopy(next(d for d in manifests()["worker-cpu.yaml"] if d["kind"] == "Deployment"))
    mutate(doc)
    with pytest.raises(kubernetes_validate.ValidationError) as err:
        kubernetes_validate.validate(doc, K8S_VERSIONS[0], strict=True)
    assert expected in str(err.value) or expected in str(getattr(err.value, "caused_by", "")), str(err.value)


def test_kustomization_applies_every_manifest_but_the_optional_ones():
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    assert set(kustomization["resources"]) == set(manifests()) - OPTIONAL_MANIFESTS
    assert all(d["metadata"]["namespace"] == kustomization["namespace"]
               for d in objects() if d["kind"] != "Namespace")


@pytest.mark.skipif(shutil.which("kubectl") is None, reason="kubectl (with its built-in kustomize) is not installed")
def test_kustomize_renders_the_manifests_and_a_registry_keeps_the_image_tags(tmp_path):
    """`kubectl kustomize` (offline) on an overlay like the README's: every object, images renamed."""
    shutil.copytree(K8S, tmp_path / "base")
    (tmp_path / "kustomization.yaml").write_text(yaml.safe_dump({
        "apiVersion": "kustomize.config.k8s.io/v1beta1", "kind": "Kustomization", "resources": ["base"],
        "images": [{"name": "undream", "newName": "registry.example.org/undream"}]}))
    res = subprocess.run(["kubectl", "kustomize", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    rendered = [d for d in yaml.safe_load_all(res.stdout) if d]
    applied = [d for name, docs in manifests().items() if name not in OPTIONAL_MANIFESTS for d in docs]
    key = lambda d: (d["kind"], d["metadata"]["name"])  # noqa: E731
    assert sorted(map(key, rendered)) == sorted(map(key, applied))
    images = set()
    for doc in rendered:
        kubernetes_validate.validate(doc, K8S_VERSIONS[-1], strict=True)
        spec = doc.get("spec", {}).get("template", {}).get("spec", {})
        images |= {c["image"] for c in spec.get("initContainers", []) + spec.get("containers", [])}
    assert {"registry.example.org/undream:cpu", "registry.example.org/undream:gpu"} <= images
    assert not {i for i in images if i.startswith("undream:")}


def test_manifest_references_resolve():
    """Selectors match their pods; config maps, claims and services named exist; secrets are the user's."""
    objs = objects()
    names = {(d["kind"], d["metadata"]["name"]) for d in objs}
    workloads = {d["metadata"]["name"]: d for d in objs if d["kind"] in ("Deployment", "StatefulSet")}
    for name, w in workloads.items():
        labels = w["spec"]["template"]["metadata"]["labels"]
        assert w["spec"]["selector"]["matchLabels"].items() <= labels.items(), name
    for svc in (d for d in objs if d["kind"] == "Service"):
        assert any(svc["spec"]["selector"].items() <= w["spec"]["template"]["metadata"]["labels"].items()
                   for w in workloads.values()), svc["metadata"]["name"]
    readme = (ROOT / "README.md").read_text()
    for wname, spec in pod_specs():
        for c in spec.get("initContainers", []) + spec["containers"]:
            for src in c.get("envFrom", []):
                assert ("ConfigMap", src["configMapRef"]["name"]) in names, wname
            for var in c.get("env", []):
                ref = var.get("valueFrom", {}).get("secretKeyRef")
                if ref:
                    assert ref["name"] in USER_SECRETS, (wname, ref)
                    assert f"create secret generic {ref['name']}" in readme, ref["name"]
        for vol in spec.get("volumes", []):
            if "persistentVolumeClaim" in vol:
                assert ("PersistentVolumeClaim", vol["persistentVolumeClaim"]["claimName"]) in names, wname
    hpa = next(d for d in objs if d["kind"] == "HorizontalPodAutoscaler")
    assert hpa["spec"]["scaleTargetRef"]["name"] in workloads
    config = next(d for d in objs if d["kind"] == "ConfigMap")
    assert hpa["spec"]["maxReplicas"] == int(config["data"]["UNDREAM_FARM_SLOTS"])
    services = {d["metadata"]["name"] for d in objs if d["kind"] == "Service"}
    for url in (config["data"]["UNDREAM_BROKER_URL"],):
        assert re.match(r"redis://([^:/]+):", url).group(1) in services


def test_k8s_workers_mount_the_shared_blob_claim_read_write_many():
    claim = next(d for d in objects() if d["kind"] == "PersistentVolumeClaim")
    assert claim["spec"]["accessModes"] == ["ReadWriteMany"]
    config = next(d for d in objects() if d["kind"] == "ConfigMap")["data"]
    for wname, c in worker_containers():
        mounts = {m["mountPath"]: m["name"] for m in c["volumeMounts"]}
        assert mounts[config["UNDREAM_BLOB_URL"]] == "blobs" and mounts[config["UNDREAM_CACHE_DIR"]] == "cache"
        assert c["livenessProbe"]["exec"]["command"][:2] == ["undream-healthcheck", "worker"], wname
        limits, requests = c["resources"]["limits"], c["resources"]["requests"]
        assert limits["cpu"] == requests["cpu"] and limits["memory"] == requests["memory"], wname  # Guaranteed
        threads = next(v["value"] for v in c["env"] if v["name"] == "UNDREAM_DRJIT_THREADS")
        assert threads == limits["cpu"], f"{wname}: Dr.Jit threads should equal the pod's cores"
    gpu = next(c for w, c in worker_containers() if w == "undream-worker-gpu")
    assert gpu["resources"]["limits"]["nvidia.com/gpu"] == 1 and gpu["image"] == "undream:gpu"
    dash = next(c for w, c in undream_containers() if w == "undream-dashboard")
    assert {m["mountPath"]: m["name"] for m in dash["volumeMounts"]}[config["UNDREAM_BLOB_URL"]] == "blobs"
    port = int(dash["args"][dash["args"].index("--port") + 1])
    assert dash["readinessProbe"]["httpGet"] == {"path": "/api/health", "port": port}
    assert dash["livenessProbe"]["httpGet"] == {"path": "/api/health", "port": port}


# --- UNDREAM_* variables: real settings with values that parse ---------------------------------


def _read_by_code() -> set[str]:
    """UNDREAM_* names the code reads besides the settings fields (found in its source)."""
    found = set()
    for pkg in ("undream", "workers", "scheduler"):
        for path in (ROOT / pkg).rglob("*.py"):
            found |= set(re.findall(r"UNDREAM_[A-Z_]+", path.read_text()))
    return found


def _deploy_texts() -> dict[str, str]:
    paths = [COMPOSE, DEPLOY / "compose.env.example", DOCKERFILE, *sorted(K8S.glob("*.yaml"))]
    return {str(p.relative_to(ROOT)): p.read_text() for p in paths}


# Variables the compose file interpolates itself (never seen by undream).
COMPOSE_ONLY = {"UNDREAM_WORKERS", "UNDREAM_GPU_WORKERS", "UNDREAM_WORKER_CPUS", "UNDREAM_WORKER_MEMORY"}


def test_every_undream_variable_in_deploy_is_a_setting_or_read_by_the_code():
    from undream.settings import ENV_PREFIX, Settings

    known = {ENV_PREFIX + f.upper() for f in Settings.__dataclass_fields__} | _read_by_code() | COMPOSE_ONLY
    for where, text in _deploy_texts().items():
        unknown = set(re.findall(r"UNDREAM_[A-Z_]+", text)) - known
        assert not unknown, f"{where}: {sorted(unknown)} are neither settings nor read by undream"
    compose_text = COMPOSE.read_text()
    for name in COMPOSE_ONLY:
        assert "${" + name in compose_text, f"{name} is not interpolated by the compose file"


def _interpolate(value: str) -> str:
    """Compose's ${VAR:-default} / ${VAR:?error} / ${VAR} with nothing set (a password for :?)."""
    def sub(m: re.Match) -> str:
        op, arg = m.group(2), m.group(3)
        return arg if op in (":-", "-") else SECRET if op in (":?", "?") else ""
    return re.sub(r"\$\{([A-Z_]+)(?:(:?[-?])([^}]*))?\}", sub, value)


def test_the_compose_environment_parses_as_settings():
    from undream.settings import load_settings

    for name, svc in undream_services().items():
        env = {k: _interpolate(str(v)) for k, v in svc["environment"].items()}
        s = load_settings(env=env)
        assert s.broker_url == "redis://redis:6379/0" and s.blob_url == "/data/blobs", name
        assert s.database_url == f"postgresql://undream:{SECRET}@postgres:5432/undream", name
        assert s.farm_slots == 2 and s.drjit_threads == 2, name
    example = dict(ln.split("=", 1) for ln in (DEPLOY / "compose.env.example").read_text().splitlines()
                   if ln and not ln.startswith("#"))
    assert int(example["UNDREAM_FARM_SLOTS"]) == int(example["UNDREAM_WORKERS"])  # CPU workers x concurrency 1


def test_the_manifest_environment_parses_as_settings():
    from undream.settings import load_settings

    config = next(d for d in objects() if d["kind"] == "ConfigMap")["data"]
    containers = [(w, c) for w, c in undream_containers() if c["name"] != "cache-owner"]
    assert {w for w, _ in containers} == {"undream-worker-cpu", "undream-worker-gpu", "undream-dashboard"}
    for wname, c in containers:
        env = dict(config)
        for var in c["env"]:
            env[var["name"]] = var.get("value") or SECRET  # a secretKeyRef
        env = {k: re.sub(r"\$\(([A-Z_]+)\)", lambda m: env[m.group(1)], v) for k, v in env.items()}
        s = load_settings(env=env)
        assert s.database_url == f"postgresql://undream:{SECRET}@undream-postgres:5432/undream", wname
        assert s.broker_url == "redis://undream-redis:6379/0" and s.farm_slots == 8, wname


# --- the images -----------------------------------------------------------------------------------


def _stages() -> dict[str, list[str]]:
    """The Dockerfile's instructions per stage (continuation lines joined)."""
    text = re.sub(r"\\\n\s*", " ", DOCKERFILE.read_text())
    stages: dict[str, list[str]] = {}
    current = None
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        m = re.match(r"FROM\s+\S+\s+AS\s+(\S+)", line, re.I)
        if m:
            current = m.group(1)
            stages[current] = []
        elif current:
            stages[current].append(line)
    return stages


def _env(stage: list[str]) -> dict[str, str]:
    env = {}
    for line in stage:
        if line.startswith("ENV "):
            env.update(dict(kv.split("=", 1) for kv in line[4:].split()))
    return env


def test_the_dockerfile_copies_paths_that_exist_and_are_not_ignored():
    ignored = [ln.strip() for ln in (DEPLOY / "docker" / "Dockerfile.dockerignore").read_text().splitlines()
               if ln.strip() and not ln.startswith("#")]
    copied = []
    for stage in _stages().values():
        for line in stage:
            if line.startswith("COPY "):
                srcs = [a for a in line.split()[1:-1] if not a.startswith("--")]
                copied += srcs
    assert "deploy/docker/healthcheck.py" in copied and "undream" in copied and "workers" in copied
    for src in copied:
        assert (ROOT / src).exists(), f"Dockerfile copies {src}, which does not exist"
        assert not any(src == pat or src.startswith(pat.rstrip("/") + "/") for pat in ignored), src


def test_the_cpu_image_forces_llvm_and_the_gpu_image_prefers_cuda():
    stages = _stages()
    assert {"base", "cpu", "gpu"} <= set(stages)
    base, cpu, gpu = _env(stages["base"]), _env(stages["cpu"]), _env(stages["gpu"])
    assert base["UNDREAM_BLOB_URL"] == "/data/blobs" and base["UNDREAM_CACHE_DIR"] == "/data/cache"
    assert cpu["UNDREAM_MI_VARIANT"] == "llvm_ad_rgb"
    assert "UNDREAM_MI_VARIANT" not in gpu and "UNDREAM_MI_VARIANT" not in base  # undream.variant's order
    assert "graphics" in gpu["NVIDIA_DRIVER_CAPABILITIES"].split(",")  # OptiX is mounted only with it
    cpu_torch = [ln for ln in stages["cpu"] if "torch" in ln]
    gpu_torch = [ln for ln in stages["gpu"] if "torch" in ln]
    assert cpu_torch == ['RUN pip install --index-url https://download.pytorch.org/whl/cpu "torch==2.13.0"']
    assert gpu_torch == ['RUN pip install "torch==2.13.0"']
    assert any("libllvm19" in ln for ln in stages["base"])
    for name in ("cpu", "gpu"):
        assert 'ENTRYPOINT ["undream"]' in stages[name] and "USER undream" in stages[name]


def _undream_commands() -> list[tuple[str, list[str]]]:
    """Every ``undream`` argument list the images, the compose file and the manifests run."""
    cmds = []
    for name, stage in _stages().items():
        for line in stage:
            if line.startswith("CMD "):
                cmds.append((f"Dockerfile {name}", json.loads(line[4:])))
    for name, svc in undream_services().items():
        cmds.append((f"compose {name}", svc["command"]))
    for wname, c in undream_containers():
        if "args" in c:
            cmds.append((f"k8s {wname}/{c['name']}", c["args"]))
    return cmds


def test_every_undream_command_line_parses_with_the_cli():
    import click

    from undream.cli import main

    cmds = _undream_commands()
    assert {c[0] for c in cmds} >= {"Dockerfile cpu", "Dockerfile gpu", "compose worker", "compose worker-gpu",
                                    "compose dashboard", "k8s undream-worker-cpu/worker",
                                    "k8s undream-worker-gpu/worker", "k8s undream-dashboard/dashboard"}
    for where, args in cmds:
        ctx = main.make_context("undream", list(args))
        sub_name, sub, rest = main.resolve_command(ctx, list(args))
        assert sub is not None, where
        sub.make_context(sub_name, rest, parent=ctx)  # raises click.UsageError on a bad flag or value
    with pytest.raises(click.UsageError):  # the check above can fail
        worker = main.get_command(click.Context(main), "worker")
        worker.make_context("worker", ["--concurency", "1"])


@pytest.mark.parametrize("command", ["worker", "dashboard"])
def test_the_cli_help_lists_the_flags_the_deployments_use(command):
    res = subprocess.run([sys.executable, "-m", "undream.cli", command, "--help"], capture_output=True,
                         text=True, cwd=ROOT, timeout=60)
    assert res.returncode == 0, res.stderr
    used = {a for _, args in _undream_commands() if args[0] == command for a in args if a.startswith("--")}
    assert used and all(flag in res.stdout for flag in used), used


def _healthcheck():
    spec = importlib.util.spec_from_file_location("undream_healthcheck", DEPLOY / "docker" / "healthcheck.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_healthcheck_command_lines_parse():
    parser = _healthcheck().build_parser()
    lines = [svc["healthcheck"]["test"][2:] for svc in undream_services().values()]
    lines += [c["livenessProbe"]["exec"]["command"][1:] for _, c in worker_containers()]
    assert lines
    for argv in lines:
        parser.parse_args(argv)


def test_healthcheck_finds_the_oldest_undream_worker_process(tmp_path):
    def proc(pid: int, *argv: str) -> None:
        (tmp_path / str(pid)).mkdir()
        (tmp_path / str(pid) / "cmdline").write_bytes(b"\0".join(a.encode() for a in argv) + b"\0")

    proc(1, "/sbin/docker-init", "--", "undream", "worker", "--concurrency", "1")  # compose's init: true
    proc(4, "/bin/sh", "-c", "undream worker")
    proc(6, "/opt/venv/bin/python", "/opt/venv/bin/undream-healthcheck", "worker")
    proc(7, "/opt/venv/bin/python", "/opt/venv/bin/undream", "worker", "--concurrency", "1")
    proc(9, "/opt/venv/bin/python", "/opt/venv/bin/undream", "worker", "--concurrency", "1")  # its child
    proc(3, "/opt/venv/bin/python", "/opt/venv/bin/undream", "dashboard")
    proc(2, "/usr/bin/python3", "-m", "undream.cli", "status")
    (tmp_path / "self").mkdir()
    hc = _healthcheck()
    assert hc.worker_pid(tmp_path) == 7
    proc(5, "/usr/bin/python3", "-m", "undream.cli", "worker", "--threads", "1")
    assert hc.worker_pid(tmp_path) == 5
    assert hc.worker_pid(tmp_path / "self") is None


def test_healthcheck_http_wants_a_200():
    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            self.send_response(200 if self.path == "/ok" else 503)
            self.end_headers()

        def log_message(self, *args: Any) -> None:
            pass

    server = HTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        hc = _healthcheck()
        base = f"http://127.0.0.1:{server.server_port}"
        assert hc.check_http(f"{base}/ok", 5) is None
        assert hc.check_http(f"{base}/down", 5) == f"GET {base}/down: HTTP 503"
        assert hc.main(["http", f"{base}/ok"]) == 0 and hc.main(["http", f"{base}/down"]) == 1
    finally:
        server.shutdown()
        server.server_close()
