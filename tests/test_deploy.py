"""The container deployment: compose validates, matches `hivemap up`, and the
Prometheus and Grafana files refer only to what the code exports."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from services.launcher import service_plan
from shared.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"


def _compose_tool() -> list[str] | None:
    if shutil.which("docker"):
        r = subprocess.run(["docker", "compose", "version"], capture_output=True)
        if r.returncode == 0:
            return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return None


def test_compose_config_validates():
    tool = _compose_tool()
    if tool is None:
        pytest.skip("neither `docker compose` (v2 plugin) nor Debian's docker-compose exists here")
    r = subprocess.run([*tool, "-f", str(COMPOSE), "config", "-q"], capture_output=True,
                       text=True, cwd=ROOT)  # fmt: skip
    assert r.returncode == 0, r.stderr


def _compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def test_compose_topology_equals_hivemap_up():
    c = _compose()["services"]
    plan = service_plan(Settings())
    ours = {s.name: s for s in plan if s.argv[0] == "hivemap" and s.name != "router"}
    built = {n: s for n, s in c.items() if s.get("image") == "hivemap:latest"}
    assert set(built) == set(ours)
    for name, spec in ours.items():
        assert built[name]["command"] == spec.argv[1:], name
        env = built[name]["environment"]
        port = env.get("HIVEMAP_API_PORT") or env.get("HIVEMAP_METRICS_PORT")
        assert int(port) == (spec.http_port if name != "mapper" else 9101)
        assert env["HIVEMAP_ZENOH__CONNECT"] == '["tcp/zenohd:7447"]'
        assert env["HIVEMAP_REDIS_URL"].startswith("redis://redis:")
    assert "zenohd" in c and "redis" in c  # router and redis of the plan
    assert {s.name for s in plan} >= {"router", "redis"}
    assert built["mapper"]["build"]["dockerfile"] == "deploy/Dockerfile"


def test_prometheus_scrapes_every_service():
    prom = yaml.safe_load((ROOT / "deploy/prometheus/prometheus.yml").read_text())
    targets = {t for job in prom["scrape_configs"] for sc in job["static_configs"]
               for t in sc["targets"]}  # fmt: skip
    c = _compose()["services"]
    for name, s in c.items():
        if s.get("image") != "hivemap:latest":
            continue
        env = s["environment"]
        port = env.get("HIVEMAP_METRICS_PORT") or env.get("HIVEMAP_API_PORT")
        assert f"{name}:{port}" in targets
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool (Debian package prometheus) not installed: config parsed only")
    cfg = str(ROOT / "deploy/prometheus/prometheus.yml")
    r = subprocess.run([promtool, "check", "config", cfg], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def _metric_names_in_code() -> set[str]:
    names = set()
    for p in list((ROOT / "shared").rglob("*.py")) + list((ROOT / "services").rglob("*.py")):
        names.update(re.findall(r'"(hivemap_[a-z_]+)"', p.read_text()))
    return names


def test_grafana_dashboard_queries_existing_metrics():
    dash = json.loads((ROOT / "deploy/grafana/dashboards/hivemap.json").read_text())
    ds = yaml.safe_load((ROOT / "deploy/grafana/provisioning/datasources/prometheus.yml")
                        .read_text())["datasources"][0]  # fmt: skip
    ids = [p["id"] for p in dash["panels"]]
    assert len(ids) == len(set(ids)) >= 10
    known = _metric_names_in_code()
    used = set()
    for p in dash["panels"]:
        assert p["datasource"]["uid"] == ds["uid"]
        for t in p["targets"]:
            used.update(re.findall(r"hivemap_[a-z_]+", t["expr"]))
    base = {re.sub(r"_(bucket|sum|count)$", "", u) for u in used}
    missing = {u for u in base if u not in known}
    assert not missing, f"dashboard queries metrics nobody exports: {missing}"
    prov = yaml.safe_load((ROOT / "deploy/grafana/provisioning/dashboards/hivemap.yml")
                          .read_text())  # fmt: skip
    path = prov["providers"][0]["options"]["path"]
    vols = _compose()["services"]["grafana"]["volumes"]
    assert any(v.endswith(":" + path + ":ro") for v in vols)
