"""`hivemap up` as a supervisor: a killed service comes back and loses nothing acked;
the data directory carries the maps across a stop and a start."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from services.launcher import RESTART_MAX_S, RESTART_MIN_S, STABLE_S, restart_delay
from shared.redis_server import free_port, stop_process

HIVEMAP = str(Path(sys.executable).with_name("hivemap"))


def test_restart_delay_doubles_for_short_lives_and_resets_after_a_stable_run():
    d = restart_delay(0.0, 0.1)
    assert d == RESTART_MIN_S
    seen = [d]
    for _ in range(12):
        d = restart_delay(d, 1.0)
        seen.append(d)
    assert seen[:3] == [RESTART_MIN_S, 2 * RESTART_MIN_S, 4 * RESTART_MIN_S]
    assert max(seen) == seen[-1] == RESTART_MAX_S
    assert restart_delay(RESTART_MAX_S, STABLE_S) == RESTART_MIN_S


class Up:
    """`hivemap up` in a subprocess on free ports, its stderr (the JSON log) in a file."""

    def __init__(self, tmp: Path, data_dir: Path | None, name: str = "up") -> None:
        self.api = free_port()
        self.mapper_port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        env = {k: v for k, v in os.environ.items() if not k.startswith("HIVEMAP_")}
        env.update({"HIVEMAP_API_PORT": str(self.api), "HIVEMAP_API_TOKEN": "supervised-token",
                    "HIVEMAP_MAPPER_METRICS_PORT": str(self.mapper_port),
                    "HIVEMAP_PLACEREC_METRICS_PORT": str(free_port()),
                    "HIVEMAP_OPTIMIZER_METRICS_PORT": str(free_port()),
                    # Culled keyframes leave the stored set; here every acked one must stay.
                    "HIVEMAP_MAPPER__REDUNDANCY": "false"})  # fmt: skip
        data = ["--ephemeral"] if data_dir is None else ["--data-dir", str(data_dir)]
        self.log = tmp / f"{name}.log"
        self._err = open(self.log, "w")  # noqa: SIM115
        argv = [HIVEMAP, "up", "--listen", self.endpoint, *data]
        self.proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=self._err,
                                     text=True)  # fmt: skip
        self.lines: list[str] = []
        try:
            self._wait_ready()
        except BaseException:
            self.stop()  # else a stack whose output we misread outlives the test
            raise

    def _wait_ready(self) -> None:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                raise AssertionError(f"hivemap up exited: {self.log.read_text()[-2000:]}")
            self.lines.append(line)
            if line.startswith("Ctrl-C"):
                break
        self.redis_url = next(m.group(0) for x in self.lines
                              if (m := re.search(r"redis://\S+", x)))  # fmt: skip

    def get(self, path: str):
        import urllib.request

        req = urllib.request.Request(
            f"http://127.0.0.1:{self.api}{path}",
            headers={"Authorization": "Bearer supervised-token"},
        )
        # Generous: one read stalled past 5 s in CI right after a flight (not reproduced
        # here: 370 reads during and after the same flight, slowest 0.17 s; Redis there
        # fsyncs its AOF every second to a shared disk). What is checked is what the API
        # serves, not how fast.
        with urllib.request.urlopen(req, timeout=20) as r:
            return json.loads(r.read())

    def children(self) -> dict[str, int]:
        """Service name -> pid of the launcher's direct children."""
        out = {}
        for d in Path("/proc").iterdir():
            if not d.name.isdigit():
                continue
            try:
                stat = (d / "stat").read_text()
                argv = (d / "cmdline").read_text().split("\0")
            except OSError:
                continue
            fields = stat.rsplit(")", 1)[1].split()
            if int(fields[1]) != self.proc.pid or fields[0] == "Z":
                continue
            names = [Path(a).name for a in argv]
            if names[0].startswith("redis-server"):
                out["redis"] = int(d.name)
            elif "hivemap" in names:  # a console script: python .../hivemap SERVICE
                out[argv[names.index("hivemap") + 1]] = int(d.name)
        return out

    def stop(self) -> None:
        stop_process(self.proc, 30)
        self._err.close()


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _fly(endpoint: str, agent: str, frames: str, speed: float):
    """A simulated agent in this process (so the test sees exactly what was acked),
    flying in a thread."""
    from services.agent.sim_agent import DriftModel, LandmarkWorld, SimAgent
    from services.agent.sim_runner import SimAgentRunner
    from shared.settings import Settings, ZenohSettings
    from shared.trajectory import Trajectory, load_euroc_gt

    gt = load_euroc_gt("MH01")
    a, b = (int(x) for x in frames.split(":"))
    gt = Trajectory(gt.stamps_ns[a:b], gt.poses[a:b])
    s = Settings(zenoh=ZenohSettings(mode="client", connect=[endpoint]))
    stop = threading.Event()  # ends the flight early
    runner = SimAgentRunner(s, agent, SimAgent(gt, LandmarkWorld(0), drift=DriftModel(), seed=1),
                            speed=speed, flush_timeout_s=60, stop=stop)  # fmt: skip
    out: dict = {}
    t = threading.Thread(target=lambda: out.setdefault("stats", runner.run()), daemon=True)
    t.start()
    return runner, t, out, stop


def _acked(runner) -> set[int]:
    while True:
        try:
            return set(runner.comm.acked_kfs)
        except RuntimeError:  # the agent's thread added one while we copied
            continue


def _restarted(up: Up, name: str, old_pid: int, t_kill: float, timeout: float = 30.0,
               ready=lambda: True) -> float | None:  # fmt: skip
    """Seconds from ``t_kill`` until the supervisor runs ``name`` again under a new pid
    (and ``ready()`` says it serves); None if not within ``timeout``."""
    while time.monotonic() - t_kill < timeout:
        if up.children().get(name) not in (None, old_pid) and ready():
            return time.monotonic() - t_kill
        time.sleep(0.05)
    return None


def _acks_resumed(runner, t_kill: float, timeout: float = 40.0) -> float | None:
    """Seconds from ``t_kill`` until the agent gets an ack beyond those it has now;
    None if none comes within ``timeout``."""
    n = len(_acked(runner))
    while time.monotonic() - t_kill < timeout:
        if len(_acked(runner)) > n:
            return time.monotonic() - t_kill
        time.sleep(0.1)
    return None


def _port_answers(port: int) -> bool:
    import socket

    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.3):
            return True
    except OSError:
        return False


@pytest.mark.slow
def test_kill_9_of_the_mapper_restarts_it_and_loses_no_acked_keyframe(tmp_path):
    from shared.store import Store, connect

    up = Up(tmp_path, tmp_path / "data")
    stop = None
    try:
        runner, thread, out, stop = _fly(up.endpoint, "k9", "800:1500", speed=2.0)
        deadline = time.monotonic() + 60
        while len(_acked(runner)) < 15 and time.monotonic() < deadline:
            time.sleep(0.1)
        before = up.children()
        assert {"router", "redis", "mapper", "placerec", "optimizer", "api"} <= set(before)
        acked_before = _acked(runner)
        assert len(acked_before) >= 15
        os.kill(before["mapper"], signal.SIGKILL)
        t_kill = time.monotonic()
        back = _restarted(up, "mapper", before["mapper"], t_kill,
                          ready=lambda: _port_answers(up.mapper_port))  # fmt: skip
        assert back is not None and back <= 10.0, f"mapper back after {back} s"
        # Keyframes made after the kill are acked again: the new mapper took over.
        resumed = _acks_resumed(runner, t_kill)
        assert resumed is not None, "no ack after the restart"
        thread.join(180)
        stats = out["stats"]
        others = {k: v for k, v in before.items() if k != "mapper"}
        assert all(_alive(p) for p in others.values()), "another service died"
        assert {k: v for k, v in up.children().items() if k != "mapper"} == others
        stored = set(Store(connect(up.redis_url)).keyframe_ids("k9"))
        assert acked_before <= stored, f"acked then lost: {sorted(acked_before - stored)}"
        assert stats.all_acked and _acked(runner) == stored
        log = up.log.read_text()
        assert f"mapper (pid {before['mapper']}) killed by SIGKILL" in log
        assert "mapper restarted" in log
        print(f"\nmapper back {back:.1f} s after kill -9, acks resumed after {resumed:.1f} s; "
              f"{len(stored)} keyframes stored, all acked")  # fmt: skip
        # Any service, not only the mapper: the API answers again, with the same data.
        api_pid = up.children()["api"]
        os.kill(api_pid, signal.SIGKILL)
        t_kill = time.monotonic()
        agents = None
        while time.monotonic() - t_kill < 10 and agents is None:
            try:
                agents = up.get("/agents")
            except OSError:
                time.sleep(0.2)
        assert agents is not None and up.children()["api"] != api_pid, "api not back in 10 s"
        assert [a["agent"] for a in agents] == ["k9"]
        print(f"api back {time.monotonic() - t_kill:.1f} s after kill -9")
    finally:
        if stop is not None:
            stop.set()
        up.stop()
    assert up.proc.returncode == 0


@pytest.mark.slow
def test_restart_with_the_same_data_dir_serves_the_same_maps_and_trajectories(tmp_path):
    data = tmp_path / "data"
    up = Up(tmp_path, data, "up1")
    try:
        runner, thread, out, _ = _fly(up.endpoint, "p1", "800:1300", speed=0)
        thread.join(120)
        assert out["stats"].all_acked

        def snapshot():
            maps = up.get("/maps")
            trajs = {a["agent"]: up.get(f"/agents/{a['agent']}/trajectory")
                     for a in up.get("/agents")}  # fmt: skip
            return maps, trajs

        # Wait for background work (optimization) to settle: two equal reads in a row.
        prev, deadline = None, time.monotonic() + 60
        while time.monotonic() < deadline:
            cur = snapshot()
            if cur == prev:
                break
            prev = cur
            time.sleep(2)
        first = cur
    finally:
        up.stop()
    assert up.proc.returncode == 0
    maps, trajs = first
    assert maps and trajs["p1"]["keyframes"]
    up2 = Up(tmp_path, data, "up2")
    try:
        # Another stack on the same directory would corrupt it: refused.
        r = subprocess.run([HIVEMAP, "up", "--data-dir", str(data), "--listen",
                            f"tcp/127.0.0.1:{free_port()}"], capture_output=True, text=True,
                           env={**os.environ, "HIVEMAP_API_PORT": str(free_port())},
                           timeout=60)  # fmt: skip
        assert r.returncode == 2 and "in use" in r.stderr, r.stderr
        again = (up2.get("/maps"),
                 {a["agent"]: up2.get(f"/agents/{a['agent']}/trajectory")
                  for a in up2.get("/agents")})  # fmt: skip
    finally:
        up2.stop()
    assert again == first
