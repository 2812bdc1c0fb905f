"""For the tests that run service processes and simulated agents of their own against
the test's redis-server and Zenoh router (the ``settings`` fixture): the ``hivemap``
console script, polling for a condition, one ``hivemap SERVICE`` process with its log,
and simulated agents flown on EuRoC ground truth, each in a thread."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from services.agent.sim_agent import DriftModel, LandmarkWorld, SimAgent
from services.agent.sim_runner import SimAgentRunner
from shared.redis_server import stop_process
from shared.settings import Settings
from shared.trajectory import Trajectory, load_euroc_gt

HIVEMAP = str(Path(sys.executable).with_name("hivemap"))


def wait_until(cond, timeout: float, step: float = 0.05):
    """Poll ``cond`` until it returns something truthy: that value, or None after
    ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(step)
    return None


def service_env(settings: Settings, extra: dict[str, str] | None = None) -> dict[str, str]:
    """This environment without its own ``HIVEMAP_*`` settings, pointed at the test's
    redis-server and router, with plain-text logs; ``extra`` on top."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIVEMAP_")}
    env.update({"HIVEMAP_REDIS_URL": settings.redis_url, "HIVEMAP_LOG_JSON": "false",
                "HIVEMAP_ZENOH__CONNECT": f'["{settings.zenoh.connect[0]}"]',
                **(extra or {})})  # fmt: skip
    return env


class ServiceProcess:
    """``hivemap SERVICE`` in a process of its own, its output in ``tmp/NAME.log``."""

    def __init__(self, service: str, settings: Settings, tmp: Path, name: str,
                 env: dict[str, str] | None = None) -> None:  # fmt: skip
        self.name = name
        self.log = tmp / f"{name}.log"
        self._out = open(self.log, "w")  # noqa: SIM115
        self.proc = subprocess.Popen([HIVEMAP, service], env=service_env(settings, env),
                                     stdout=self._out, stderr=subprocess.STDOUT)  # fmt: skip

    def close(self) -> None:
        """Stops it, resumed first (a test may have paused it with SIGSTOP)."""
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGCONT)
        stop_process(self.proc, 20)
        self._out.close()


def gt_part(seq: str, a: int | None, b: int | None) -> Trajectory:
    """Frames ``a:b`` of ``seq``'s ground truth."""
    gt = load_euroc_gt(seq)
    return Trajectory(gt.stamps_ns[a:b], gt.poses[a:b])


def sim_agent(world: LandmarkWorld, seq: str, frames: slice, seed: int) -> SimAgent:
    """A simulated agent with drift flying ``frames`` of ``seq``'s ground truth."""
    return SimAgent(gt_part(seq, frames.start, frames.stop), world, drift=DriftModel(),
                    seed=seed)  # fmt: skip


def fly(runner, results: dict) -> threading.Thread:
    """``runner.run()`` (a ``SimAgentRunner``) in a thread of its own, started; its
    result lands in ``results[runner.agent]``."""
    t = threading.Thread(target=lambda: results.setdefault(runner.agent, runner.run()))
    t.start()
    return t


def fly_two_agents(settings: Settings, world: LandmarkWorld) -> tuple[dict, dict]:
    """Agents A and B on the first 900 frames of MH01 and MH02, which start in one place
    (their maps merge once place recognition finds it), flown at once at 4x; returns
    each one's ``SimAgentRunner`` result and the ground truth it flew, once both are
    done (two minutes at most)."""
    results: dict = {}
    sims = {a: sim_agent(world, seq, slice(900), seed=20 + i)
            for i, (a, seq) in enumerate((("A", "MH01"), ("B", "MH02")))}  # fmt: skip
    threads = [fly(SimAgentRunner(settings, a, sim, speed=4.0), results)
               for a, sim in sims.items()]  # fmt: skip
    for t in threads:
        t.join(120)
    return results, {a: sim.traj for a, sim in sims.items()}
