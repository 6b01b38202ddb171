"""deploy/k8s/: the Kubernetes manifests, checked without a cluster.

Every object validates against the Kubernetes schemas that ``kubernetes-validate``
ships (strict: an unknown field fails), for the oldest and newest versions in
``K8S_VERSIONS``; broken copies fail; ``kubectl kustomize`` (offline) renders
them; selectors, claims, secrets, probes and sizes line up; the environment of
every undream container parses as undream's settings.
"""
from __future__ import annotations

import copy
import re
import shutil
import subprocess

import kubernetes_validate
import pytest
import yaml

from deploy_files import (
    K8S, K8S_VERSIONS, OPTIONAL_MANIFESTS, ROOT, SECRET, USER_SECRETS, manifests, objects, pod_specs,
    undream_containers, worker_containers,
)


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


@pytest.mark.skipif(shutil.which("kubectl") is None,
                    reason="kubectl (with its built-in kustomize) is not installed")
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
    readme = (ROOT / "docs" / "deploy.md").read_text()  # where the deploy steps live
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


