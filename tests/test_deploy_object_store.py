"""deploy/'s object-store variant: blobs in S3-compatible storage, no shared blob volume.

- compose: ``deploy/compose.s3.yaml`` over ``deploy/compose.yaml`` (a MinIO
  server and its bucket in the stack); the merged file validates against the
  Compose specification and its environment parses as S3 settings.
- Kubernetes: the overlay ``deploy/k8s-object-store`` (the base without the
  ReadWriteMany claim or any blob mount; the bucket's keys from a Secret the
  user makes), rendered offline with ``kubectl kustomize`` where kubectl is
  installed, each object validated against the Kubernetes schemas.
No container runs here; like tests/test_deploy.py, everything is checked statically.
"""
from __future__ import annotations

import re
import shutil
import subprocess
from typing import Any

import kubernetes_validate
import pytest
import yaml

from deploy_files import DEPLOY, K8S_VERSIONS, ROOT, SECRET, UNDREAM_IMAGE, compose
from test_deploy import _compose_errors, _interpolate
from undream.store import BlobOptions, parse_blob_url

COMPOSE_S3 = DEPLOY / "compose.s3.yaml"
OVERLAY = DEPLOY / "k8s-object-store"
S3_SECRET = "undream-s3"  # made with kubectl (docs/deploy.md), never kept in deploy/


def _merge(base: Any, override: Any) -> Any:
    """Compose's merge of two files for what compose.s3.yaml overrides (mappings key by key)."""
    if isinstance(base, dict) and isinstance(override, dict):
        return {**base, **{k: _merge(base.get(k), v) for k, v in override.items()}}
    return override


def merged() -> dict[str, Any]:
    return _merge(compose(), yaml.safe_load(COMPOSE_S3.read_text()))


def test_the_s3_compose_override_validates_and_its_services_parse_as_s3_settings():
    from undream.settings import load_settings

    doc = merged()
    assert _compose_errors(doc) == []
    undream = {n: s for n, s in doc["services"].items() if UNDREAM_IMAGE.match(s.get("image", ""))}
    assert set(undream) == {"worker", "worker-gpu", "dashboard"}
    for name, svc in undream.items():
        raw = svc["environment"]
        assert raw["UNDREAM_S3_SECRET_ACCESS_KEY"].startswith("${MINIO_ROOT_PASSWORD:?"), name  # no literal key
        s = load_settings(env={k: _interpolate(str(v)) for k, v in raw.items()})
        assert parse_blob_url(s.blob_url).kind == "s3" and s.s3_endpoint_url == "http://minio:9000", name
        assert s.s3_secret_access_key == SECRET and SECRET not in repr(BlobOptions.of(s)), name
        assert "s3_secret_access_key" not in repr(s) and "s3_access_key_id" not in repr(s), name
        assert s.database_url == f"postgresql://undream:{SECRET}@postgres:5432/undream", name
        assert svc["depends_on"]["minio-init"] == {"condition": "service_completed_successfully"}, name
    init = doc["services"]["minio-init"]
    bucket = parse_blob_url(load_settings(env={"UNDREAM_BLOB_URL": undream["worker"]["environment"]
                                                ["UNDREAM_BLOB_URL"]}).blob_url).bucket
    assert f"mc mb --ignore-existing farm/{bucket}" in init["entrypoint"][-1]
    assert init["depends_on"] == {"minio": {"condition": "service_healthy"}}
    assert doc["services"]["minio"]["healthcheck"]["test"] == ["CMD", "mc", "ready", "local"]
    assert all(p.startswith("127.0.0.1:") for p in doc["services"]["minio"]["ports"])
    assert "minio" in doc["volumes"]
    example = (DEPLOY / "compose.env.example").read_text()
    assert "MINIO_ROOT_PASSWORD=" in example and "compose.s3.yaml" in (ROOT / "docs" / "deploy.md").read_text()


def test_the_overlay_lists_its_patches_and_keeps_no_key():
    kustomization = yaml.safe_load((OVERLAY / "kustomization.yaml").read_text())
    assert kustomization["resources"] == ["../k8s"]
    assert sorted(p["path"] for p in kustomization["patches"]) == sorted(
        p.name for p in OVERLAY.glob("*.yaml") if p.name != "kustomization.yaml")
    text = "".join(p.read_text() for p in OVERLAY.glob("*.yaml"))
    assert "AWS_SECRET_ACCESS_KEY=..." in text and not re.search(r"SECRET_ACCESS_KEY:\s*\S", text)
    assert f"create secret generic {S3_SECRET}" in (ROOT / "docs" / "deploy.md").read_text()


@pytest.fixture(scope="module")
def rendered() -> list[dict[str, Any]]:
    if shutil.which("kubectl") is None:
        pytest.skip("kubectl (with its built-in kustomize) is not installed")
    res = subprocess.run(["kubectl", "kustomize", str(OVERLAY)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    return [d for d in yaml.safe_load_all(res.stdout) if d]


def test_the_overlay_renders_valid_objects_with_no_shared_volume(rendered):
    for doc in rendered:
        kubernetes_validate.validate(doc, K8S_VERSIONS[-1], strict=True)
    assert not [d for d in rendered if d["kind"] == "PersistentVolumeClaim"]
    pods = {d["metadata"]["name"]: d["spec"]["template"]["spec"] for d in rendered
            if d["kind"] in ("Deployment", "StatefulSet")}
    undream = {name: c for name, spec in pods.items() for c in spec["containers"] if UNDREAM_IMAGE.match(c["image"])}
    assert set(undream) == {"undream-worker-cpu", "undream-worker-gpu", "undream-dashboard"}
    for name, spec in pods.items():
        for vol in spec.get("volumes", []):
            claim = vol.get("persistentVolumeClaim", {}).get("claimName")
            assert claim is None and vol["name"] != "blobs", name
    for name, c in undream.items():
        assert "/data/blobs" not in {m["mountPath"] for m in c.get("volumeMounts", [])}, name
        assert {"secretRef": {"name": S3_SECRET}} in c["envFrom"], name


def test_the_overlay_environment_parses_as_s3_settings(rendered):
    from undream.settings import load_settings

    config = next(d for d in rendered if d["kind"] == "ConfigMap")["data"]
    for d in rendered:
        if d["kind"] != "Deployment" or d["metadata"]["name"] == "undream-redis":
            continue
        for c in d["spec"]["template"]["spec"]["containers"]:
            if not UNDREAM_IMAGE.match(c["image"]):
                continue
            env = {**config, "AWS_ACCESS_KEY_ID": "AKIDEXAMPLE", "AWS_SECRET_ACCESS_KEY": SECRET}  # the Secret
            for var in c.get("env", []):
                env[var["name"]] = var.get("value") or SECRET
            env = {k: re.sub(r"\$\(([A-Z_]+)\)", lambda m: env[m.group(1)], v) for k, v in env.items()}
            s = load_settings(env=env)
            assert parse_blob_url(s.blob_url).kind == "s3" and s.s3_secret_access_key == SECRET
            assert s.s3_access_key_id == "AKIDEXAMPLE" and s.transport_cache_mb == 2048
