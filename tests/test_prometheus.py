"""Every Grafana panel shows data: a real Prometheus (Debian's `prometheus`) scrapes a
running stack with two simulated agents through the project's own scrape config, and
every expression of every dashboard panel is evaluated through Prometheus's HTTP API.

The check is what Grafana does when it draws a panel: a range query over the time the
stack ran; a panel "returns data" when some series has a finite value in that range
(NaN, e.g. a quantile of a histogram with no observations, draws nothing).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest
import yaml
from live_stack import add_sim_agents, get_json, live_stack, metrics_ports, wait_for

from services import dashboards
from shared import keys
from shared.redis_server import free_port, stop_process
from shared.settings import ZenohSettings
from shared.transport import open_session

ROOT = Path(__file__).resolve().parents[1]
SCRAPE_CONFIG = ROOT / "deploy/prometheus/prometheus.yml"
DASHBOARDS = ROOT / "deploy/grafana/dashboards"


def scrape_config_for(ports: dict[str, int], interval: str = "1s") -> dict:
    """The project's scrape config with each job's compose target (``mapper:9101``)
    replaced by where that service listens here; jobs, paths and everything else kept.
    The interval is shortened so a test does not wait minutes for rate() windows."""
    cfg = yaml.safe_load(SCRAPE_CONFIG.read_text())
    cfg["global"]["scrape_interval"] = interval
    cfg["global"]["evaluation_interval"] = interval
    for job in cfg["scrape_configs"]:
        name = job["job_name"]
        assert name in ports, f"the scrape config has a job {name!r} this stack does not run"
        for sd in job.pop("dns_sd_configs", []):  # scaled services: one A name each
            assert sd["names"] == [name], sd
            job.setdefault("static_configs", []).append({"targets": [f"{name}:{sd['port']}"]})
        for sc in job["static_configs"]:
            assert all(t.split(":")[0] == name for t in sc["targets"]), sc["targets"]
            sc["targets"] = [f"127.0.0.1:{ports[name]}"]
    return cfg


class Prometheus:
    def __init__(self, exe: str, config: dict, workdir: Path) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        cfg = workdir / "prometheus.yml"
        cfg.write_text(yaml.safe_dump(config))
        self.log = workdir / "prometheus.log"
        self.proc = subprocess.Popen(
            [exe, f"--config.file={cfg}", f"--storage.tsdb.path={workdir / 'data'}",
             f"--web.listen-address=127.0.0.1:{self.port}", "--log.level=warn"],
            stdout=subprocess.DEVNULL, stderr=self.log.open("w"),
        )  # fmt: skip

    def api(self, path: str, **params) -> dict:
        url = f"{self.url}/api/v1/{path}?{urllib.parse.urlencode(params)}"
        with urllib.request.urlopen(url, timeout=10) as r:
            body = json.loads(r.read())
        assert body["status"] == "success", body
        return body["data"]

    def scalar(self, expr: str) -> float:
        res = self.api("query", query=expr)["result"]
        return float(res[0]["value"][1]) if res else math.nan

    def stop(self) -> None:
        stop_process(self.proc, 10)


def _finite_points(data: dict) -> int:
    return sum(
        1 for series in data["result"] for _, v in series["values"] if math.isfinite(float(v))
    )


def _exercise_rejections(endpoint: str, api: str, token: str) -> None:
    """What the rejection panels count: one undecodable keyframe batch on an agent's key,
    one request for an agent nobody knows. And one WebSocket connection."""
    import websockets.sync.client as ws_client

    zs = ZenohSettings(mode="client", connect=[endpoint])
    with open_session(zs) as session:
        session.put(keys.agent_kf("agent-0"), b"\x93not a keyframe batch")
    try:
        req = urllib.request.Request(
            f"{api}/agents/nobody/pose", headers={"Authorization": f"Bearer {token}"}
        )
        urllib.request.urlopen(req, timeout=5)
    except urllib.error.HTTPError as e:
        assert e.code == 404
    url = api.replace("http://", "ws://") + f"/ws/poses?token={token}"
    with ws_client.connect(url, open_timeout=10) as ws:
        assert json.loads(ws.recv(timeout=10))["type"] == "subscribed"


def test_every_panel_returns_data(tmp_path):
    exe = shutil.which("prometheus")
    if exe is None:
        pytest.skip(
            "Debian's prometheus is not installed (`make system-tools` installs it where "
            "apt-get runs as root): no real Prometheus to evaluate the panels against"
        )
    t0 = time.time()
    # A short BA budget: the optimization panels need one finished run, not a converged one.
    env = {"HIVEMAP_OPTIMIZER__BA_TIME_BUDGET_S": "2"}
    with live_stack(n_agents=2, env=env, start_agents=False) as stack:
        s = stack.settings
        api = f"http://127.0.0.1:{s.api_port}"
        prom = Prometheus(exe, scrape_config_for(metrics_ports(s)), tmp_path)
        try:
            wait_for(lambda: prom.api("targets")["activeTargets"]
                     and all(t["health"] == "up" for t in prom.api("targets")["activeTargets"]),
                     60, f"every target up ({prom.log.read_text()[-2000:]})")  # fmt: skip
            # Agents start once every target was scraped: a merge and an optimization
            # within the first seconds would otherwise be in the first sample of their
            # counters, where rate() sees no increase.
            add_sim_agents(stack, 2)
            wait_for(lambda: get_json(f"{api}/agents", token=stack.api_token), 60,
                     "agents in the API")  # fmt: skip
            _exercise_rejections(stack.zenoh_endpoint, api, stack.api_token)
            # The rare events the overview counts: a merge, and an optimization finished.
            # (Deadlines are for a machine shared with other work; quiet, both come within
            # 20 s of the agents' start.)
            wait_for(lambda: prom.scalar("sum(hivemap_map_merges_total)") >= 1, 120, "a merge")
            wait_for(lambda: prom.scalar("sum(hivemap_optimizations_total)") >= 1, 180,
                     "an optimization")  # fmt: skip
            time.sleep(3)  # a few more scrapes, so every rate() window holds two samples
            end = time.time()
            missing = []
            n = 0
            for f in sorted(DASHBOARDS.glob("*.json")):
                dash = json.loads(f.read_text())
                for title, expr in dashboards.expressions(dash):
                    n += 1
                    data = prom.api("query_range", query=expr, start=f"{t0:.3f}",
                                    end=f"{end:.3f}", step="1")  # fmt: skip
                    if _finite_points(data) == 0:
                        missing.append(f"{f.name} / {title}: {expr}")
            assert n >= 40
            assert not missing, "panels without data:\n" + "\n".join(missing)
            # Both agents' health came through the mapper, and says they track.
            states = prom.api("query", query="hivemap_agent_state")["result"]
            assert sorted(r["metric"]["agent"] for r in states) == ["agent-0", "agent-1"]
            fps = prom.api("query", query="max_over_time(hivemap_agent_fps[1m])")["result"]
            assert len(fps) == 2 and all(float(r["value"][1]) > 5 for r in fps), fps
        finally:
            prom.stop()
