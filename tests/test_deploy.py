"""deploy/: the compose stack, the images and their health checks, checked without a container engine.

- The compose file validates against the Compose specification's JSON schema
  (kept in deploy/schema/, checksum pinned); broken copies fail.
- What a schema cannot see: every ``UNDREAM_*`` variable in deploy/ is a real
  setting (or one the code reads) and every compose value parses as that
  setting; volumes and health checks line up; the Dockerfile's copied paths
  exist and its targets choose their Mitsuba variant as documented; every
  ``undream`` command line in the images, the compose file and the manifests
  parses with the real CLI. The manifests: tests/test_deploy_k8s.py.
No image is built here (no container engine runs on this machine).
"""
from __future__ import annotations

import copy
import hashlib
import json
import re
import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer
from typing import Any

import jsonschema
import pytest

from deploy_files import (
    COMPOSE, DEPLOY, DOCKERFILE, K8S, ROOT, SCHEMA, SCHEMA_SHA256, SECRET, compose, healthcheck_module,
    stage_env, stages, undream_containers, undream_services, worker_containers,
)


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
    (("services", "redis", "depends_on"), {"postgres": {"condition": "healthy"}},
     "is not valid under any of the given schemas"),
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


# --- UNDREAM_* variables: real settings with values that parse ---------------------------------


def _read_by_code() -> set[str]:
    """UNDREAM_* names the code reads besides the settings fields (found in its source)."""
    found = set()
    for pkg in ("undream", "workers", "scheduler"):
        for path in (ROOT / pkg).rglob("*.py"):
            found |= set(re.findall(r"UNDREAM_[A-Z_]+", path.read_text()))
    return found


def _deploy_texts() -> dict[str, str]:
    paths = [COMPOSE, DEPLOY / "compose.s3.yaml", DEPLOY / "compose.env.example", DOCKERFILE,
             *sorted(K8S.glob("*.yaml")), *sorted((DEPLOY / "k8s-object-store").glob("*.yaml"))]
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


# --- the images -----------------------------------------------------------------------------------


def test_the_dockerfile_copies_paths_that_exist_and_are_not_ignored():
    ignored = [ln.strip() for ln in (DEPLOY / "docker" / "Dockerfile.dockerignore").read_text().splitlines()
               if ln.strip() and not ln.startswith("#")]
    copied = []
    for stage in stages().values():
        for line in stage:
            if line.startswith("COPY "):
                srcs = [a for a in line.split()[1:-1] if not a.startswith("--")]
                copied += srcs
    assert "deploy/docker/healthcheck.py" in copied and "undream" in copied and "workers" in copied
    for src in copied:
        assert (ROOT / src).exists(), f"Dockerfile copies {src}, which does not exist"
        assert not any(src == pat or src.startswith(pat.rstrip("/") + "/") for pat in ignored), src


def test_the_cpu_image_forces_llvm_and_the_gpu_image_prefers_cuda():
    found = stages()
    assert {"base", "cpu", "gpu"} <= set(found)
    base, cpu, gpu = stage_env(found["base"]), stage_env(found["cpu"]), stage_env(found["gpu"])
    assert base["UNDREAM_BLOB_URL"] == "/data/blobs" and base["UNDREAM_CACHE_DIR"] == "/data/cache"
    assert cpu["UNDREAM_MI_VARIANT"] == "llvm_ad_rgb"
    assert "UNDREAM_MI_VARIANT" not in gpu and "UNDREAM_MI_VARIANT" not in base  # undream.variant's order
    assert "graphics" in gpu["NVIDIA_DRIVER_CAPABILITIES"].split(",")  # OptiX is mounted only with it
    cpu_torch = [ln for ln in found["cpu"] if "torch" in ln]
    gpu_torch = [ln for ln in found["gpu"] if "torch" in ln]
    assert cpu_torch == ['RUN pip install --index-url https://download.pytorch.org/whl/cpu "torch==2.13.0"']
    assert gpu_torch == ['RUN pip install "torch==2.13.0"']
    assert any("libllvm19" in ln for ln in found["base"])
    for name in ("cpu", "gpu"):
        assert 'ENTRYPOINT ["undream"]' in found[name] and "USER undream" in found[name]


def _undream_commands() -> list[tuple[str, list[str]]]:
    """Every ``undream`` argument list the images, the compose file and the manifests run."""
    cmds = []
    for name, stage in stages().items():
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


def test_healthcheck_command_lines_parse():
    parser = healthcheck_module().build_parser()
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
    hc = healthcheck_module()
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
        hc = healthcheck_module()
        base = f"http://127.0.0.1:{server.server_port}"
        assert hc.check_http(f"{base}/ok", 5) is None
        assert hc.check_http(f"{base}/down", 5) == f"GET {base}/down: HTTP 503"
        assert hc.main(["http", f"{base}/ok"]) == 0 and hc.main(["http", f"{base}/down"]) == 1
    finally:
        server.shutdown()
        server.server_close()
