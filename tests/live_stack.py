"""A running HiveMap stack with simulated agents, as `hivemap up` + `hivemap sim-agent` run
it (real router, redis, mapper, placerec, optimizer, api processes on free ports), for
the tests that look at it from outside: Prometheus scraping it, a browser viewing it."""

from __future__ import annotations

import contextlib
import json
import time
import urllib.request
from collections.abc import Iterator

from services.launcher import Scale, Stack
from shared.redis_server import free_port
from shared.settings import Settings

# Two agents flying the same stretch of MH01 (the drone moves from frame ~800 on):
# their maps overlap from the start, so place recognition merges them within seconds
# and the merged map closes loops where the second agent retraces the first.
DEFAULT_FRAMES = "900:1500"


def stack_settings() -> Settings:
    return Settings(
        api_port=free_port(),
        mapper_metrics_port=free_port(),
        placerec_metrics_port=free_port(),
        optimizer_metrics_port=free_port(),
        log_level="WARNING",
    )


def metrics_ports(s: Settings) -> dict[str, int]:
    """The port of every scraped service (the jobs of deploy/prometheus/prometheus.yml)."""
    return {
        "mapper": s.mapper_metrics_port,
        "placerec": s.placerec_metrics_port,
        "optimizer": s.optimizer_metrics_port,
        "api": s.api_port,
    }


@contextlib.contextmanager
def live_stack(
    n_agents: int = 2,
    trajs: str = "MH01",
    frames: str = DEFAULT_FRAMES,
    speed: float = 2.0,
    agent_prefix: str = "agent",
    env: dict[str, str] | None = None,
    scale: Scale | None = None,
) -> Iterator[Stack]:
    """The stack with ``n_agents`` simulated agents in one process (ids
    ``{agent_prefix}-0..``), agents started once the API answers."""
    stack = Stack(stack_settings(), env={"HIVEMAP_LOG_LEVEL": "WARNING", **(env or {})},
                  scale=scale)  # fmt: skip
    try:
        stack.start()
        stack.add(
            "sim-agents",
            ["sim-agent", "--id", agent_prefix, "--count", str(n_agents), "--traj", trajs,
             "--frames", frames, "--speed", str(speed), "--flush-timeout", "20"],
            env={"HIVEMAP_LOG_LEVEL": "WARNING"},
        )  # fmt: skip
        yield stack
    finally:
        stack.stop()


def get_json(url: str, timeout: float = 5.0):
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return json.loads(r.read())


def wait_for(pred, timeout: float, what: str, every: float = 0.5):
    """Poll ``pred`` until it returns something truthy; fail saying what was awaited."""
    deadline = time.monotonic() + timeout
    last_err: Exception | None = None
    while time.monotonic() < deadline:
        try:
            v = pred()
            if v:
                return v
        except OSError as e:  # a service still starting
            last_err = e
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what} ({last_err})")
