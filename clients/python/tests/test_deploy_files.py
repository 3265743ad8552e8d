"""The shipped deployment files, checked without a cluster or a Docker registry: the Kubernetes
overlay renders with ``kubectl kustomize`` and every object validates against the Kubernetes
1.32 schemas (``kubernetes-validate``, offline), with the pieces an operator needs; the compose
file builds the image, bounds each replica and keeps Redis behind a password."""

from __future__ import annotations

import shutil
import subprocess
from typing import Any

import kubernetes_validate
import pytest
import yaml

from .conftest import REPO

DEPLOY = REPO / "deploy"
KUBERNETES_VERSION = "1.32"


def _rendered_overlay() -> list[dict[str, Any]]:
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("SKIPPED: kubectl is not installed (its `kubectl kustomize` renders the overlay)")
    run = subprocess.run(
        [kubectl, "kustomize", str(DEPLOY / "k8s" / "overlays" / "example")], capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    return [d for d in yaml.safe_load_all(run.stdout) if d]


def _by_kind(docs: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    kinds: dict[str, list[dict[str, Any]]] = {}
    for d in docs:
        kinds.setdefault(d["kind"], []).append(d)
    return kinds


def test_the_kubernetes_overlay_renders_and_every_object_validates() -> None:
    docs = _rendered_overlay()
    for d in docs:
        kubernetes_validate.validate(d, KUBERNETES_VERSION, strict=True)
    # The validation is not vacuous: a misspelt field fails it.
    broken = yaml.safe_load(yaml.safe_dump(_by_kind(docs)["Deployment"][0]))
    broken["spec"]["template"]["spec"]["containers"][0]["startupProbes"] = {}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(broken, KUBERNETES_VERSION, strict=True)
    kinds = _by_kind(docs)
    assert {"Deployment", "StatefulSet", "Service", "Ingress", "PodDisruptionBudget", "NetworkPolicy"} <= set(
        kinds
    )
    assert "HorizontalPodAutoscaler" in kinds
    assert all(d["metadata"].get("namespace") == "murk" for d in docs)


def test_the_overlay_sets_the_image_and_the_replicas_have_probes_limits_and_secrets() -> None:
    kinds = _by_kind(_rendered_overlay())
    (murk,) = kinds["Deployment"]
    (container,) = murk["spec"]["template"]["spec"]["containers"]
    assert container["image"] == "registry.example.com/murk:0.1.0"
    assert {"startupProbe", "readinessProbe", "livenessProbe"} <= set(container)
    assert container["resources"]["limits"]["memory"]
    env = {e["name"]: e for e in container["env"]}
    assert env["REDIS_PASSWORD"]["valueFrom"]["secretKeyRef"]["name"] == "murk-redis"
    assert env["MURK_REDIS_URL"]["value"].startswith("redis://:$(REDIS_PASSWORD)@")
    names = [e["name"] for e in container["env"]]
    assert names.index("REDIS_PASSWORD") < names.index("MURK_REDIS_URL"), "$(VAR) needs an earlier entry"
    (redis,) = kinds["StatefulSet"]
    args = redis["spec"]["template"]["spec"]["containers"][0]["args"]
    assert "--requirepass" in args and "--protected-mode" not in args
    (ingress,) = kinds["Ingress"]
    assert ingress["spec"]["tls"][0]["secretName"] == "murk-tls"
    assert ingress["metadata"]["annotations"]["nginx.ingress.kubernetes.io/backend-protocol"] == "GRPC"
    policies = {p["metadata"]["name"]: p for p in kinds["NetworkPolicy"]}
    (redis_from,) = policies["murk-redis"]["spec"]["ingress"][0]["from"]
    assert redis_from["podSelector"]["matchLabels"] == {"app.kubernetes.io/name": "murk"}


def test_the_prometheus_adapter_rule_is_a_valid_manifest() -> None:
    doc = yaml.safe_load((DEPLOY / "k8s" / "prometheus-adapter" / "adapter-config.yaml").read_text())
    kubernetes_validate.validate(doc, KUBERNETES_VERSION, strict=True)
    config = yaml.safe_load(doc["data"]["config.yaml"])
    (rule,) = config["externalRules"]
    assert "murk_queue_depth" in rule["seriesQuery"]


def test_compose_builds_the_image_and_bounds_every_replica() -> None:
    compose = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())
    services = compose["services"]
    murk = services["murk"]
    assert murk["build"]["context"] == ".." and murk["build"]["dockerfile"] == "Dockerfile"
    assert (DEPLOY / murk["build"]["context"] / murk["build"]["dockerfile"]).is_file()
    assert murk["cpus"] and murk["mem_limit"]
    assert murk["environment"]["MURK_REDIS_URL"].startswith("redis://:${REDIS_PASSWORD}@")
    assert "--requirepass" in services["redis"]["command"]
    assert "--protected-mode" not in services["redis"]["command"]
    for name in ("prometheus", "grafana"):
        assert services[name]["profiles"] == ["observability"]
        for volume in services[name]["volumes"]:
            source = volume.split(":")[0]
            if source.startswith("./"):
                assert (DEPLOY / source).exists(), f"{name} mounts {source}, which is not in deploy/"
    tokens = (DEPLOY / "tokens.example").read_text()
    assert all(line.startswith("#") or not line.strip() for line in tokens.splitlines()), "no usable token"
