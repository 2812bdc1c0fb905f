"""The Kubernetes manifests (deploy/k8s/) validate offline against the API schemas
(kubernetes-validate bundles them), and they, docker-compose.yml and the `hivemap up`
plan list the same services with the same commands, settings and ports; compose's
scalable services can be scaled (no fixed container name or host port)."""

from __future__ import annotations

import re
from pathlib import Path

import kubernetes_validate
import pytest
import yaml

from services.launcher import service_plan
from shared.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "deploy/k8s"
COMPOSE = ROOT / "docker-compose.yml"
K8S_VERSION = "1.30.0"  # what the manifests promise to run on (and every later one)
INFRA = {"router", "redis"}
SCALABLE = ("mapper", "placerec", "optimizer")


def _docs() -> list[dict]:
    out = []
    for f in sorted(K8S.glob("*.yaml")):
        out += [d for d in yaml.safe_load_all(f.read_text()) if d]
    return out


def _by_kind(kind: str) -> dict[str, dict]:
    return {d["metadata"]["name"]: d for d in _docs() if d["kind"] == kind}


@pytest.fixture()
def clean_env(monkeypatch):
    import os

    for k in list(os.environ):
        if k.startswith("HIVEMAP_"):
            monkeypatch.delenv(k)


def test_manifests_validate_offline():
    docs = _docs()
    assert {d["kind"] for d in docs} >= {"Deployment", "StatefulSet", "Service", "ConfigMap"}
    for d in docs:
        for version in (K8S_VERSION, kubernetes_validate.latest_version()):
            kubernetes_validate.validate(d, version, strict=True)


def test_a_broken_manifest_fails_validation():
    dep = _by_kind("Deployment")["mapper"]
    bad = yaml.safe_load(yaml.safe_dump(dep))
    bad["spec"]["replicas"] = "three"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(bad, K8S_VERSION, strict=True)
    bad = yaml.safe_load(yaml.safe_dump(dep))
    bad["spec"]["template"]["spec"]["containers"][0]["enviroment"] = []
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(bad, K8S_VERSION, strict=True)


def _k8s_services() -> dict[str, tuple[list[str], dict[str, str], int, int]]:
    """name -> (args, environment, container port, replicas) of each hivemap Deployment."""
    config = {n: d.get("data", {}) for n, d in _by_kind("ConfigMap").items()}
    out = {}
    for name, d in _by_kind("Deployment").items():
        (c,) = d["spec"]["template"]["spec"]["containers"]
        if not c["image"].startswith("hivemap:"):
            continue
        env: dict[str, str] = {}
        for src in c.get("envFrom", []):
            env.update(config[src["configMapRef"]["name"]])
        for e in c.get("env", []):
            if "value" in e:
                env[e["name"]] = _placeholders(str(e["value"]))
            else:  # from the Secret: what compose takes from the user's environment
                assert e["valueFrom"]["secretKeyRef"]["name"] == "hivemap-secrets", e
                env[e["name"]] = "{" + e["valueFrom"]["secretKeyRef"]["key"] + "}"
        (port,) = [p["containerPort"] for p in c["ports"]]
        out[name] = (c["args"], env, port, d["spec"]["replicas"])
    return out


def _placeholders(v: str) -> str:
    """Compose's ``${VAR:?why}`` and Kubernetes' ``$(VAR)`` both as ``{VAR}``."""
    v = re.sub(r"\$\{([A-Z0-9_]+)(:\?[^}]*)?\}", r"{\1}", v)
    return re.sub(r"\$\(([A-Z0-9_]+)\)", r"{\1}", v)


def _compose_services() -> dict[str, dict]:
    return yaml.safe_load(COMPOSE.read_text())["services"]


def test_compose_manifests_and_hivemap_up_list_the_same_services(clean_env):
    plan = {s.name: s for s in service_plan(Settings()) if s.name not in INFRA}
    k8s = _k8s_services()
    compose = {n: s for n, s in _compose_services().items()
               if str(s.get("image", "")).startswith("hivemap:")}  # fmt: skip
    assert set(plan) == set(k8s), (set(plan), set(k8s))
    assert set(plan) <= set(compose)
    for name, spec in plan.items():
        args, env, port, _ = k8s[name]
        assert args == spec.argv[1:] == compose[name]["command"], name
        assert port == spec.http_port, name
        c_env = {k: _placeholders(str(v)) for k, v in compose[name]["environment"].items()}
        # The Secret's own variables are what compose interpolates from the environment.
        secret = {k for k, v in env.items() if v == "{" + k + "}"}
        assert {k: v for k, v in env.items() if k not in secret or k in c_env} == c_env, \
            (name, set(env) ^ set(c_env))  # fmt: skip
        # The plan's own settings (ports) are the same value in all three.
        for k, v in spec.env.items():
            if k.endswith("_PORT"):
                assert env[k] == v, (name, k)
    # The infrastructure: a router, Redis with a replica, under compose's names.
    deps, sets = _by_kind("Deployment"), _by_kind("StatefulSet")
    assert "zenohd" in deps and {"redis", "redis-replica"} <= set(sets)
    replica = sets["redis-replica"]["spec"]["template"]["spec"]["containers"][0]["args"]
    assert replica[replica.index("--replicaof") + 1 :][:2] == ["redis", "6379"]
    services = _by_kind("Service")
    assert {"zenohd", "redis", "redis-replica", "api"} <= set(services)
    # The router's logins reach the router and every service that logs in, as in compose.
    zenohd = deps["zenohd"]["spec"]["template"]["spec"]
    assert _compose_services()["zenohd"]["command"][:2] == zenohd["containers"][0]["args"][:2]
    for name in ("zenohd", *SCALABLE):
        pod = deps[name]["spec"]["template"]["spec"]
        assert pod["volumes"] == [{"name": "zenoh-logins",
                                   "secret": {"secretName": "hivemap-zenoh"}}], name  # fmt: skip
        mount = pod["containers"][0]["volumeMounts"][0]
        assert mount["mountPath"] == "/etc/hivemap/zenoh" and mount["readOnly"], name
    assert _compose_services()["zenohd"]["image"] == \
        deps["zenohd"]["spec"]["template"]["spec"]["containers"][0]["image"]  # fmt: skip
    # The pools run several replicas.
    assert k8s["placerec"][3] >= 2 and k8s["optimizer"][3] >= 2


def test_compose_can_scale_the_pools():
    """`docker compose up --scale mapper=3 --scale placerec=2`: a scaled service can have
    neither a container name nor a published host port (two replicas would clash)."""
    svcs = _compose_services()
    for name in SCALABLE:
        s = svcs[name]
        assert "container_name" not in s, name
        assert "ports" not in s, f"{name} publishes a host port: it could not be scaled"
