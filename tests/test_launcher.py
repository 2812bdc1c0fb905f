"""`hivemap up` and `hivemap demo` as a user runs them: real processes, real ports."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from shared.redis_server import free_port

HIVEMAP = str(Path(sys.executable).with_name("hivemap"))


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(d.name))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            if c not in out:
                out.add(c)
                todo.append(c)
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


TOKEN = "launcher-test-token"


def _get(url: str, timeout: float = 2.0):
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {TOKEN}"})
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return json.loads(r.read())


def _env(api_port: int) -> dict[str, str]:
    # Each port free and distinct from the others: free_port twice in a row can give the
    # same one (a suite run had placerec's metrics on the API's port, and /health read
    # Prometheus text).
    ports = {api_port}
    while len(ports) < 4:
        ports.add(free_port())
    mapper, placerec, optimizer = sorted(ports - {api_port})
    return {**os.environ, "HIVEMAP_API_PORT": str(api_port), "HIVEMAP_API_TOKEN": TOKEN,
            "HIVEMAP_MAPPER_METRICS_PORT": str(mapper),
            "HIVEMAP_PLACEREC_METRICS_PORT": str(placerec),
            "HIVEMAP_OPTIMIZER_METRICS_PORT": str(optimizer)}  # fmt: skip


def _stop(proc: subprocess.Popen) -> set[int]:
    kids = _descendants(proc.pid)
    proc.send_signal(signal.SIGTERM)
    proc.wait(30)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(_alive(p) for p in kids):
        time.sleep(0.1)
    return {p for p in kids if _alive(p)}


def _listen() -> list[str]:
    """A free router endpoint: other stacks on this machine may hold the default one."""
    return ["--listen", f"tcp/127.0.0.1:{free_port()}"]


def test_up_serves_and_sigterm_leaves_no_orphans(tmp_path):
    port = free_port()
    proc = subprocess.Popen([HIVEMAP, "up", *_listen()], env=_env(port), stdout=subprocess.PIPE,
                            text=True, cwd=tmp_path)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        health = None
        while time.monotonic() < deadline and health is None:
            try:
                health = _get(f"http://127.0.0.1:{port}/health")
            except OSError:
                time.sleep(0.3)
        assert health is not None, "api never answered"
        names = {Path(Path(f"/proc/{p}/cmdline").read_text().split("\0")[0]).name
                 for p in _descendants(proc.pid) if _alive(p)}  # fmt: skip
        assert any(n.startswith("redis-server") for n in names)
        assert len(_descendants(proc.pid)) >= 4  # redis, router, mapper, api

        # The mapper runs under real-time scheduling where it may (root here), the
        # others under normal scheduling (shared/settings.py MapperSettings.rt_priority).
        def policies() -> dict[str, int]:
            argv = {p: Path(f"/proc/{p}/cmdline").read_text().split("\0")
                    for p in _descendants(proc.pid) if _alive(p)}  # fmt: skip
            return {a[2]: os.sched_getscheduler(p) for p, a in argv.items()
                    if len(a) > 2 and a[1].endswith("hivemap")}  # fmt: skip

        policy = policies()
        if os.geteuid() == 0:
            t_end = time.monotonic() + 15  # it raises itself once its imports are done
            while policy.get("mapper") != os.SCHED_RR and time.monotonic() < t_end:
                time.sleep(0.2)
                policy = policies()
            assert policy.get("mapper") == os.SCHED_RR, policy
        assert policy.get("api") == os.SCHED_OTHER, policy
        assert _get(f"http://127.0.0.1:{port}/agents") == []
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/agents", timeout=2)
            raise AssertionError("the API served /agents without the token")
        except urllib.error.HTTPError as e:
            assert e.code == 401
    finally:
        left = _stop(proc)
    assert proc.returncode == 0
    assert not left, f"orphans after SIGTERM: {left}"
    # It said where to look: the viewer, every service's metrics, Grafana under compose.
    said = proc.stdout.read()
    assert "viewer" in said and f"http://127.0.0.1:{port}/?token={TOKEN}" in said, said
    assert said.count("/metrics") >= 4 and "grafana" in said, said
    # Persistent by default, under the directory it ran in.
    assert (tmp_path / "hivemap-data" / "appendonlydir").is_dir()


def test_sigterm_while_starting_still_stops_everything():
    """A signal before the stack is fully up must not kill the launcher outright and
    orphan the children it already started."""
    proc = subprocess.Popen(
        [HIVEMAP, "up", "--ephemeral", *_listen()], env=_env(free_port()),
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    seen: set[int] = set()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not seen:  # first child = redis, the stack is starting
        seen = _descendants(proc.pid)
        time.sleep(0.02)
    assert seen, "launcher started nothing"
    left = _stop(proc) | {p for p in seen if _alive(p)}
    assert proc.returncode == 0
    assert not left, f"orphans after SIGTERM during start: {left}"


@pytest.mark.slow
def test_demo_lists_three_moving_agents_within_30_s():
    port = free_port()
    proc = subprocess.Popen([HIVEMAP, "demo", *_listen()], env=_env(port),
                            stdout=subprocess.DEVNULL)  # fmt: skip
    t0 = time.monotonic()
    try:
        first: dict[str, list[float]] = {}
        moved: set[str] = set()
        while time.monotonic() - t0 < 30 and len(moved) < 3:
            try:
                agents = _get(f"http://127.0.0.1:{port}/agents")
            except OSError:
                time.sleep(0.5)
                continue
            for a in agents:
                pose = a.get("last_pose")
                if not pose:
                    continue
                p = pose["position"]
                first.setdefault(a["agent"], p)
                if sum((x - y) ** 2 for x, y in zip(p, first[a["agent"]], strict=True)) > 0.01**2:
                    moved.add(a["agent"])
            time.sleep(0.5)
        elapsed = time.monotonic() - t0
        assert len(moved) == 3, f"agents moving after {elapsed:.0f} s: {sorted(moved)}"
        print(f"\nthree agents listed and moving {elapsed:.1f} s after `hivemap demo` started")
    finally:
        left = _stop(proc)
    assert not left


def test_up_listens_where_agents_look_by_default(monkeypatch):
    """`hivemap up`'s router endpoint and API address are the ones `hivemap agent` and a
    browser use when told nothing."""
    from services.cli import build_parser
    from shared.settings import DEFAULT_ROUTER, Settings

    for k in list(os.environ):
        if k.startswith("HIVEMAP_"):
            monkeypatch.delenv(k)
    up = build_parser().parse_args(["up"])
    agent = build_parser().parse_args(["agent", "--id", "A", "--source", "synthetic:MH01"])
    s = Settings()
    assert up.listen == DEFAULT_ROUTER == "tcp/127.0.0.1:7447"
    assert not agent.server and s.zenoh.connect == [up.listen]
    assert (s.api_host, s.api_port) == ("127.0.0.1", 8000)


def _port_free(port: int) -> bool:
    import socket

    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_agent_without_server_flag_joins_hivemap_up(tmp_path):
    """`hivemap up`, then `hivemap agent` with no --server: the server sees the agent.
    The defaults themselves when 7447 is free; else (another stack holds it) the same
    endpoint given to both through the setting the agent's default comes from."""
    api = free_port()
    env = _env(api)
    for k in [k for k in env if k.startswith("HIVEMAP_ZENOH__")]:
        del env[k]
    up_argv = [HIVEMAP, "up", "--ephemeral"]
    if not _port_free(7447):
        ep = f"tcp/127.0.0.1:{free_port()}"
        up_argv += ["--listen", ep]
        env["HIVEMAP_ZENOH__CONNECT"] = json.dumps([ep])
    proc = subprocess.Popen(up_argv, env=env, stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    agent = None
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                _get(f"http://127.0.0.1:{api}/health")
                break
            except OSError:
                time.sleep(0.3)
        agent = subprocess.Popen(
            [HIVEMAP, "agent", "--id", "A", "--source", "synthetic:MH01?frames=0:300",
             "--out", str(tmp_path / "out")],
            env={**env, "HIVEMAP_LOG_LEVEL": "WARNING"}, stdout=subprocess.DEVNULL,
        )  # fmt: skip
        seen: list[str] = []
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and "A" not in seen and agent.poll() is None:
            with contextlib.suppress(OSError):
                seen = [a["agent"] for a in _get(f"http://127.0.0.1:{api}/agents")]
            time.sleep(0.5)
        if "A" not in seen:  # the agent may have finished between two polls
            seen = [a["agent"] for a in _get(f"http://127.0.0.1:{api}/agents")]
        assert "A" in seen, f"GET /agents: {seen}"
    finally:
        if agent is not None and agent.poll() is None:
            agent.terminate()
            agent.wait(60)
        left = _stop(proc)
    assert not left


def test_up_refuses_a_taken_router_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        argv = [HIVEMAP, "up", "--ephemeral", "--listen", f"tcp/127.0.0.1:{port}"]
        r = subprocess.run(argv, env=_env(free_port()), capture_output=True, text=True,
                           timeout=60)  # fmt: skip
    assert r.returncode == 2
    assert f"127.0.0.1:{port} is not free" in r.stderr and "--listen" in r.stderr
