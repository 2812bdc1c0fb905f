"""The container deployment: compose validates and runs the topology `hivemap up`
runs, and the Prometheus and Grafana files refer only to what the code exports.

These check the files; tests/test_compose.py builds and runs them on a real engine.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest
import yaml

from services import dashboards
from services.cli import build_parser
from services.launcher import service_plan
from shared.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
PROMETHEUS = ROOT / "deploy/prometheus/prometheus.yml"
DASHBOARDS = ROOT / "deploy/grafana/dashboards"
GRAFANA_DS = ROOT / "deploy/grafana/provisioning/datasources/prometheus.yml"
GRAFANA_DASHBOARDS = ROOT / "deploy/grafana/provisioning/dashboards/hivemap.yml"
# What an operator exports before `docker compose up` (README, "Security").
SECRETS = {"HIVEMAP_API_TOKEN": "compose-test-token", "HIVEMAP_REDIS_PASSWORD": "pw"}
REDIS_URL = (
    "redis://:${HIVEMAP_REDIS_PASSWORD:?set HIVEMAP_REDIS_PASSWORD, see README Security}"
    "@redis:6379/0"
)

# The plan's infrastructure: in compose they are the zenohd and redis images.
INFRA = {"router": "zenohd", "redis": "redis"}


@pytest.fixture()
def clean_env(monkeypatch):
    """Settings() in these tests must see defaults, not the caller's HIVEMAP_* variables."""
    import os

    for k in list(os.environ):
        if k.startswith("HIVEMAP_"):
            monkeypatch.delenv(k)
    return monkeypatch


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
        pytest.skip(
            "neither `docker compose` (v2 plugin) nor `docker-compose` (Debian package "
            "docker-compose) exists here: the compose file is only parsed by the other tests"
        )
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIVEMAP_")}
    r = subprocess.run([*tool, "-f", str(COMPOSE), "config", "-q"], capture_output=True,
                       text=True, cwd=ROOT, timeout=120, env=env)  # fmt: skip
    # The secrets come from the environment: without them compose refuses to start.
    assert r.returncode != 0 and "HIVEMAP_" in r.stderr, r.stderr
    env.update(SECRETS)
    r = subprocess.run([*tool, "-f", str(COMPOSE), "config", "-q"], capture_output=True,
                       text=True, cwd=ROOT, timeout=120, env=env)  # fmt: skip
    assert r.returncode == 0, r.stderr


def _compose_services(profiled: bool = False) -> dict[str, dict]:
    """The services `up` starts, and with ``profiled`` also those under a profile (the
    simulated agents), which only run when asked for."""
    # safe_load resolves the `<<: *anchor` merge keys the compose file uses.
    services = yaml.safe_load(COMPOSE.read_text())["services"]
    return {n: s for n, s in services.items() if profiled or not s.get("profiles")}


def _is_hivemap_image(svc: dict) -> bool:
    build = svc.get("build")
    dockerfile = build.get("dockerfile") if isinstance(build, dict) else None
    return dockerfile == "deploy/Dockerfile" or str(svc.get("image", "")).startswith("hivemap:")


def _hivemap_plan() -> dict:
    return {s.name: s for s in service_plan(Settings()) if s.name not in INFRA}


def test_compose_topology_equals_hivemap_up(clean_env):
    compose = _compose_services()
    plan = {s.name for s in service_plan(Settings())}
    assert set(INFRA) <= plan, "the plan lost its router or redis: update INFRA and compose"
    assert set(INFRA.values()) <= set(compose)
    ours = _hivemap_plan()
    built = {n: s for n, s in compose.items() if _is_hivemap_image(s)}
    assert set(built) == set(ours)
    for name, spec in ours.items():
        svc = built[name]
        assert spec.argv[0] == "hivemap"
        # The image's ENTRYPOINT is `hivemap`, so compose's command is the argv after it.
        assert svc["command"] == spec.argv[1:], name
        env = svc["environment"]
        ports = {k: v for k, v in spec.env.items() if k.endswith("_PORT")}
        assert ports, f"{name}: the plan gives it no port"
        for key, value in ports.items():
            assert str(env.get(key)) == value == str(spec.http_port), (name, key)
            # Bound to loopback inside a container, nothing (Prometheus, users) could reach it.
            assert env.get(key.removesuffix("_PORT") + "_HOST") == "0.0.0.0", (name, key)
        assert env["HIVEMAP_ZENOH__MODE"] == "client"
        assert json.loads(env["HIVEMAP_ZENOH__CONNECT"]) == ["tcp/zenohd:7447"]
        assert env["HIVEMAP_REDIS_URL"] == REDIS_URL
        deps = svc["depends_on"]
        assert {"zenohd", "redis"} <= set(deps), name


def test_compose_commands_are_cli_subcommands():
    parser = build_parser()
    assert "sim-agent" in _compose_services(profiled=True)
    for name, svc in _compose_services(profiled=True).items():
        if _is_hivemap_image(svc):
            try:
                args = parser.parse_args(svc["command"])
            except SystemExit:
                pytest.fail(f"{name}: `hivemap {' '.join(svc['command'])}` is no subcommand")
            assert callable(args.func), name


def test_compose_env_names_real_settings(clean_env):
    """Settings ignores unknown variables, so a misspelt one (HIVEMAP_ZENOH_CONNECT with one
    underscore) would silently leave a container talking to 127.0.0.1: load each service's
    environment through Settings and check every variable landed in a field."""
    for name, svc in _compose_services(profiled=True).items():
        if not _is_hivemap_image(svc):
            continue
        env = {k: str(v) for k, v in svc["environment"].items()}
        for k, v in env.items():
            clean_env.setenv(k, v)
        s = Settings()
        for k in env:
            assert k.startswith("HIVEMAP_"), (name, k)
            obj = s
            for part in k.removeprefix("HIVEMAP_").lower().split("__"):
                assert hasattr(obj, part), f"{name}: {k} is no setting"
                obj = getattr(obj, part)
        assert s.zenoh.connect == ["tcp/zenohd:7447"]
        assert s.redis_url == REDIS_URL
        assert s.log_json is True
        for k in env:
            clean_env.delenv(k)


def test_dockerfile_installs_the_cli_and_every_package():
    text = (ROOT / "deploy/Dockerfile").read_text()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "hivemap" in project["project"]["scripts"]
    assert re.search(r'^ENTRYPOINT \["hivemap"\]$', text, re.M)
    # Users have registries: the official Python image unless BASE says otherwise (the
    # offline override's local Debian base).
    assert re.search(r"^ARG BASE=python:3\.11-slim$", text, re.M)
    assert re.search(r"^FROM \$\{BASE\}$", text, re.M)
    assert re.search(r"^USER (?!root)\S+", text, re.M), "services must not run as root"
    # `pip install .` only sees what was copied: every top-level package must be.
    copied = set(re.findall(r"^COPY (\S+) ", text, re.M))
    for pattern in project["tool"]["setuptools"]["packages"]["find"]["include"]:
        pkg = pattern.rstrip("*")
        assert pkg in copied or f"./{pkg}" in copied or "." in copied, pkg
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert {".venv", ".git"} <= set(ignored)


def _scrape_targets() -> dict[str, str]:
    prom = yaml.safe_load(PROMETHEUS.read_text())
    out = {}
    for job in prom["scrape_configs"]:
        for sc in job.get("static_configs", []):
            for t in sc["targets"]:
                out[t] = job.get("metrics_path", "/metrics")
        # Scaled services are found by DNS (every replica's address under one name).
        for sd in job.get("dns_sd_configs", []):
            assert sd["type"] == "A", sd
            for n in sd["names"]:
                out[f"{n}:{sd['port']}"] = job.get("metrics_path", "/metrics")
    return out


def test_prometheus_scrapes_every_service(clean_env):
    targets = _scrape_targets()
    want = {f"{name}:{spec.http_port}" for name, spec in _hivemap_plan().items()}
    # Equal, not a superset: a target left behind for a removed service is down forever.
    assert set(targets) == want
    assert set(targets.values()) == {"/metrics"}
    compose = _compose_services()
    assert {t.split(":")[0] for t in targets} <= set(compose)
    assert (
        "./deploy/prometheus/prometheus.yml:/etc/prometheus/prometheus.yml:ro"
        in (compose["prometheus"]["volumes"])
    )


def test_promtool_checks_prometheus_config():
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool (Debian package prometheus) is not installed")
    r = subprocess.run([promtool, "check", "config", str(PROMETHEUS)], capture_output=True,
                       text=True, timeout=60)  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr


def _metric_names_in_code() -> set[str]:
    """Names given to prometheus_client in the sources (a counter declared without
    `_total` is exported with it)."""
    names = set()
    for p in [*(ROOT / "shared").rglob("*.py"), *(ROOT / "services").rglob("*.py")]:
        names.update(re.findall(r"[\"'](hivemap_[a-z0-9_]+)[\"']", p.read_text()))
    return names | {n + "_total" for n in names}


def _dashboards() -> dict[str, dict]:
    files = sorted(DASHBOARDS.glob("*.json"))
    assert files, f"no dashboards in {DASHBOARDS}"
    return {f.name: json.loads(f.read_text()) for f in files}


def test_dashboards_are_what_the_code_builds():
    """The checked-in JSON is exactly what services/dashboards.py builds with Grafana's
    foundation SDK: a hand edit, or a code change without `hivemap dashboards`, fails."""
    built = dashboards.build_all()
    on_disk = {f.name: f.read_text() for f in DASHBOARDS.glob("*.json")}
    assert set(on_disk) == set(built), "run `hivemap dashboards` to regenerate"
    for name, text in built.items():
        assert on_disk[name] == text, f"{name} differs: run `hivemap dashboards`"
    # and the regeneration is deterministic (panel ids, key order, layout)
    assert dashboards.build_all() == built


def test_dashboards_check_command_detects_a_stale_file(tmp_path):
    """`hivemap dashboards --check` is what CI or a user runs: 0 when current, 1 when a
    file differs or is left over."""
    from services.cli import main

    assert main(["dashboards", "--out", str(tmp_path)]) == 0
    assert main(["dashboards", "--out", str(tmp_path), "--check"]) == 0
    f = tmp_path / "hivemap-team.json"
    f.write_text(f.read_text().replace('"refresh": "10s"', '"refresh": "5s"'))
    assert main(["dashboards", "--out", str(tmp_path), "--check"]) == 1
    assert main(["dashboards", "--out", str(tmp_path)]) == 0
    (tmp_path / "old.json").write_text("{}")
    assert main(["dashboards", "--out", str(tmp_path), "--check"]) == 1


def test_grafana_dashboards_query_exported_metrics():
    ds = yaml.safe_load(GRAFANA_DS.read_text())["datasources"]
    assert len(ds) == 1 and ds[0]["type"] == "prometheus"
    # The compose service name and port Prometheus listens on.
    assert ds[0]["url"] == "http://prometheus:9090"
    uid = ds[0]["uid"]
    assert uid == dashboards.DATASOURCE_UID
    known = _metric_names_in_code()
    used = set()
    uids = set()
    for name, dash in _dashboards().items():
        uids.add(dash["uid"])
        panels = [p for p in dashboards.panels(dash) if p.get("type") != "row"]
        ids = [p["id"] for p in dashboards.panels(dash)]
        assert len(ids) == len(set(ids)), name
        for p in panels:
            assert p["datasource"] == {"type": "prometheus", "uid": uid}, p["title"]
            assert p["targets"], p["title"]
            # units, descriptions: a panel says what it shows and in what
            assert p.get("description"), p["title"]
            assert p["fieldConfig"]["defaults"].get("unit"), p["title"]
            for t in p["targets"]:
                assert t.get("datasource", p["datasource"])["uid"] == uid, p["title"]
                names = re.findall(r"hivemap_[a-z0-9_]+", t["expr"])
                assert names or re.match(r"^(up|changes|rate\(process_|process_)", t["expr"]), (
                    p["title"],
                    t["expr"],
                )
                used.update(names)
    assert len(uids) == len(_dashboards())
    # Histograms are queried through their _bucket/_sum/_count series.
    base = {re.sub(r"_(bucket|sum|count)$", "", u) for u in used}
    missing = base - known
    assert not missing, f"the dashboards query metrics nothing exports: {sorted(missing)}"
    # Only processes Prometheus scrapes export what a panel reads: agents are robots in
    # the field, never scraped, so an agent-side metric would leave its panel empty.
    agent_only = {"hivemap_agent_ack_latency_seconds", "hivemap_resent_total",
                  "hivemap_injected_drops_total"}  # fmt: skip
    assert not base & agent_only, sorted(base & agent_only)
    # The panels the issue asks for: team overview, latency percentiles, traffic,
    # rejections, service health, place recognition and optimization, overload.
    for name in ("hivemap_map_merges_total", "hivemap_matches_applied_total",
                 "hivemap_keyframe_latency_seconds", "hivemap_bytes_total",
                 "hivemap_messages_rejected_total", "hivemap_service_up",
                 "hivemap_api_requests_total", "hivemap_placerec_query_seconds",
                 "hivemap_optimizations_total", "hivemap_map_queue_depth",
                 # agent health, as the agents report it through the mapper
                 "hivemap_agent_state", "hivemap_agent_fps", "hivemap_agent_resends_total",
                 "hivemap_agent_frames_dropped_total", "hivemap_agent_sent_bytes_total",
                 "hivemap_agent_ack_latency_recent_seconds"):  # fmt: skip
        assert name in base, name


def test_dashboard_queries_are_valid_promql(tmp_path):
    """Grafana only shows a bad query as an empty panel at run time; promtool parses each
    expression now, by checking them as recording rules."""
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool (Debian package prometheus) is not installed")
    rules = [
        {"record": f"hivemap:{name.removesuffix('.json').replace('-', '_')}:{i}", "expr": e}
        for name, dash in _dashboards().items()
        for i, (_, e) in enumerate(dashboards.expressions(dash))
    ]
    assert rules
    f = tmp_path / "rules.yml"
    f.write_text(yaml.safe_dump({"groups": [{"name": "dashboard", "rules": rules}]}))
    r = subprocess.run([promtool, "check", "rules", str(f)], capture_output=True, text=True,
                       timeout=60)  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr


def test_grafana_provisioning_matches_compose_volumes():
    prov = yaml.safe_load(GRAFANA_DASHBOARDS.read_text())
    (provider,) = prov["providers"]
    path = provider["options"]["path"]
    vols = _compose_services()["grafana"]["volumes"]
    # The dashboards directory is mounted where the provider looks, and so is provisioning.
    assert f"./deploy/grafana/dashboards:{path}:ro" in vols
    assert "./deploy/grafana/provisioning:/etc/grafana/provisioning:ro" in vols


def test_compose_redis_needs_a_password_and_publishes_no_port():
    redis_svc = _compose_services()["redis"]
    assert "ports" not in redis_svc
    cmd = redis_svc["command"]
    assert cmd[cmd.index("--requirepass") + 1].startswith("${HIVEMAP_REDIS_PASSWORD:?")
