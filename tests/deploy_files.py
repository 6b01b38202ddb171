"""The files of deploy/ as data, for tests/test_deploy*.py: the compose file, the Kubernetes
objects, the Dockerfile's stages and the health-check script."""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from typing import Any, Iterator

import kubernetes_validate
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


def stages() -> dict[str, list[str]]:
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


def stage_env(stage: list[str]) -> dict[str, str]:
    env = {}
    for line in stage:
        if line.startswith("ENV "):
            env.update(dict(kv.split("=", 1) for kv in line[4:].split()))
    return env


def healthcheck_module() -> Any:
    """deploy/docker/healthcheck.py (the images' undream-healthcheck) imported from its path."""
    spec = importlib.util.spec_from_file_location("undream_healthcheck", DEPLOY / "docker" / "healthcheck.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
