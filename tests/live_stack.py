"""A running HiveMap stack with simulated agents, as `hivemap up` + `hivemap sim-agent` run
it (real router, redis, mapper, placerec, optimizer, api processes on free ports), for
the tests that look at it from outside: Prometheus scraping it, a browser viewing it."""

from __future__ import annotations

import contextlib
import json
import threading
import time
import urllib.request
from collections.abc import Iterator

from services.launcher import Scale, Stack
from shared.redis_server import free_port
from shared.runtime import set_autogroup_nice
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
    start_agents: bool = True,
) -> Iterator[Stack]:
    """The stack with ``n_agents`` simulated agents in one process (ids
    ``{agent_prefix}-0..``), agents started once the API answers; with
    ``start_agents=False`` the caller starts them (``add_sim_agents``) when it is ready
    to watch from the first keyframe."""
    stack = Stack(stack_settings(), env={"HIVEMAP_LOG_LEVEL": "WARNING", **(env or {})},
                  scale=scale)  # fmt: skip
    try:
        stack.start()
        if start_agents:
            add_sim_agents(stack, n_agents, trajs, frames, speed, agent_prefix)
        yield stack
    finally:
        stack.stop()


def add_sim_agents(
    stack: Stack,
    n_agents: int = 2,
    trajs: str = "MH01",
    frames: str = DEFAULT_FRAMES,
    speed: float = 2.0,
    agent_prefix: str = "agent",
) -> None:
    stack.add(
        f"sim-agents-{agent_prefix}",
        ["sim-agent", "--id", agent_prefix, "--count", str(n_agents), "--traj", trajs,
         "--frames", frames, "--speed", str(speed), "--flush-timeout", "20"],
        env={"HIVEMAP_LOG_LEVEL": "WARNING"},
    )  # fmt: skip


def get_json(url: str, timeout: float = 5.0, token: str | None = None):
    """GET a JSON document; ``token``: the stack's API token (``Stack.api_token``)."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout) as r:
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


CHROMIUM = "/usr/bin/chromium"  # Debian's (make system-tools); playwright downloads none


def chromium_missing() -> str | None:
    """Why the browser tests cannot run here, or None."""
    import os
    import shutil

    exe = CHROMIUM if os.path.exists(CHROMIUM) else shutil.which("chromium")
    if exe is None:
        return "Debian's chromium is not installed (`make system-tools` installs it)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the playwright package is not installed (pip install -e '.[dev]')"
    return None


@contextlib.contextmanager
def viewer_page(url: str, width: int = 1600, height: int = 900, nice: int = 0):
    """The viewer at ``url`` in headless Chromium, driven through playwright.

    ``nice`` > 0 runs the browser at that lower priority: a user's browser runs on
    their own machine, so where it shares the server's cores in a benchmark it must
    not be counted as the server's load (the viewer's feed, /ws/viewer in the API,
    stays at normal priority)."""
    import os
    import shutil

    from playwright.sync_api import sync_playwright

    exe = CHROMIUM if os.path.exists(CHROMIUM) else shutil.which("chromium")
    with contextlib.ExitStack() as cleanup, sync_playwright() as pw:
        if nice > 0:
            # Chromium (as root) sets its processes' priorities itself (browser -8,
            # renderers 0-5), so a nice wrapper does not stick: hold them down instead.
            stop = threading.Event()
            t = threading.Thread(target=_hold_nice, args=(os.getpid(), nice, stop), daemon=True)
            t.start()
            cleanup.callback(stop.set)
        browser = pw.chromium.launch(
            executable_path=exe, headless=True,
            # root in a container: no sandbox; no GPU here, so Canvas 2D runs in software.
            args=["--no-sandbox", "--disable-dev-shm-usage"],
        )  # fmt: skip
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            page.goto(url)
            yield page
        finally:
            browser.close()


def _hold_nice(root: int, nice: int, stop: threading.Event) -> None:
    """Keep every descendant of ``root`` at priority ``nice`` or lower, until ``stop``."""
    import os

    while not stop.wait(0.5):
        parent: dict[int, int] = {}
        for d in os.listdir("/proc"):
            if d.isdigit():
                try:
                    with open(f"/proc/{d}/stat") as f:
                        parent[int(d)] = int(f.read().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    pass  # exited meanwhile
        for pid in parent:
            p, seen = parent.get(pid), 0
            while p is not None and p != root and p > 1 and seen < 64:
                p, seen = parent.get(p), seen + 1
            if p != root:
                continue
            try:  # nice is per thread on Linux
                tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
            except OSError:
                continue
            for tid in tids:
                try:
                    if os.getpriority(os.PRIO_PROCESS, tid) < nice:
                        os.setpriority(os.PRIO_PROCESS, tid, nice)
                except OSError:
                    pass
            # Chromium starts its processes in sessions of their own, and with autogroup
            # scheduling a session is ranked against the services' sessions by its
            # autogroup's nice alone (shared/runtime.py set_priority): niced threads
            # inside a session at 0 still took 0.5-0.7 of a core from the mapper.
            with contextlib.suppress(OSError):
                if os.getsid(pid) == pid:
                    set_autogroup_nice(nice, pid)


def viewer_fps(page, seconds: float = 5.0) -> float:
    """Frames per second the page drew over ``seconds``, counted in the page."""
    f0, t0 = page.evaluate("[window.hivemapViewer.frames, performance.now()]")
    time.sleep(seconds)
    f1, t1 = page.evaluate("[window.hivemapViewer.frames, performance.now()]")
    return (f1 - f0) * 1000.0 / (t1 - t0)
