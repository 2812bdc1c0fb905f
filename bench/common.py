"""Helpers shared by the bench scripts: JSON reports and plain tables, a stack's
settings on free ports, the mapper's metrics, and an agent run's files."""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def git_rev() -> str:
    try:
        return subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], text=True,
                                       cwd=RESULTS.parent).strip()  # fmt: skip
    except Exception:
        return "unknown"


def machine() -> dict:
    """What a timing depends on: the same code measured 2.5x slower mapper latencies on
    one 2-core machine than on another, so reports name the CPU and the load."""
    info = {"cpus": os.cpu_count(), "python": platform.python_version()}
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            k, _, v = (x.strip() for x in line.partition(":"))
            if k in ("model name", "cpu MHz"):
                info.setdefault(k, v)  # the first CPU's line; the others repeat it
    with contextlib.suppress(OSError):
        info["loadavg_1m_at_write"] = os.getloadavg()[0]
    return info


def write_report(name: str, data: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    data = {
        "bench": name,
        "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "commit": git_rev(),
        "machine": machine(),
        **data,
    }
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(data, indent=2, default=float) + "\n")
    return path


def synthetic_spec(seq: str, frames: str = "", seed: int = 0) -> str:
    """The agent's ``--source`` for a rendered sequence of world ``seed``."""
    q = ([f"seed={seed}"] if seed else []) + ([f"frames={frames}"] if frames else [])
    return f"synthetic:{seq}" + (f"?{'&'.join(q)}" if q else "")


def table(rows: list[dict], cols: list[str]) -> str:
    cells = [[str(c) for c in cols]] + [[_fmt(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(cols))]
    lines = ["  ".join(v.rjust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def stack_settings(**kw):
    """Settings of a stack with every HTTP port free (``kw``: more settings)."""
    from shared.redis_server import free_port
    from shared.settings import Settings

    return Settings(api_port=free_port(), mapper_metrics_port=free_port(),
                    placerec_metrics_port=free_port(), optimizer_metrics_port=free_port(),
                    **kw)  # fmt: skip


def scrape(url: str) -> dict[str, float]:
    """A Prometheus text page: ``name{labels}`` (labels sorted by name:
    ``shared.metrics.series_key``) -> value."""
    from shared.metrics import parse_exposition

    return parse_exposition(urllib.request.urlopen(url, timeout=5).read().decode())


def mapper_metrics(stack) -> dict[str, float]:
    return scrape(f"http://127.0.0.1:{stack.settings.mapper_metrics_port}/metrics")


LAT = "hivemap_keyframe_latency_seconds"  # the mapper's keyframe latency histogram


def mapper_latency_mean_ms(metrics: dict[str, float], agent: str, missing=float("nan")):
    """The mapper's mean keyframe latency (received -> stored and acked) for ``agent``."""
    cnt = metrics.get(f'{LAT}_count{{agent="{agent}"}}', 0)
    tot = metrics.get(f'{LAT}_sum{{agent="{agent}"}}', 0)
    return 1e3 * tot / cnt if cnt else missing


def wait_agents(procs: list, seconds: float, what: str) -> None:
    """Waits for the agent processes (``(agent, seq, Popen)`` rows) to end, showing
    progress over their ``seconds`` of flight; gives up after three times that and two
    minutes more."""
    from shared.progress import progress

    with progress(what, seconds, "s") as update:
        t0, limit = time.monotonic(), 3 * seconds + 120
        while any(p.poll() is None for *_, p in procs) and time.monotonic() - t0 < limit:
            time.sleep(0.5)
            update(completed=min(seconds, time.monotonic() - t0))


def stop_agents(procs: list, stack) -> None:
    """Kills the agent processes still running, then stops the stack."""
    for _, _, p in procs:
        if p.poll() is None:
            p.kill()
    stack.stop()


def agent_stats(out: Path, agent: str) -> dict:
    """What ``hivemap agent/sim-agent --out OUT`` wrote of ``agent``'s run."""
    return json.loads((out / f"{agent}_stats.json").read_text())


def run_agent(argv: list[str], out: Path, agent: str):
    """Runs an agent (``argv``, writing to ``out``) to its end, quiet and with one numeric
    thread; its stats and the ground truth it flew."""
    from shared.trajectory import read_tum

    env = {**os.environ, "HIVEMAP_LOG_LEVEL": "WARNING", "OMP_NUM_THREADS": "1"}
    subprocess.run(argv, env=env, check=True, stdout=subprocess.DEVNULL)
    return agent_stats(out, agent), read_tum(out / f"{agent}_gt.tum")


class ProcWatch:
    """CPU and run-queue wait of a process and its descendants (every thread's, summed),
    sampled in the background until they exit, so the figures survive the processes:
    how much CPU the simulated agents got, and how long their threads were ready to
    run but waited for a core (``/proc/PID/task/*/schedstat``: on-CPU ns, run-queue
    wait ns, slices). ``kind(pid)`` names what a process is, for :meth:`cpu_by_kind`."""

    def __init__(self, pid: int, interval: float = 0.5, children: bool = True,
                 kind: Callable[[int], str] | None = None) -> None:  # fmt: skip
        self.pid = pid
        self.children = children  # follow child processes (a scan of /proc per sample)
        self._tasks: dict[tuple[int, str], tuple[int, int]] = {}  # (pid, tid) -> cpu, wait
        self.pids: set[int] = {pid}
        self._kind = kind
        self._kinds: dict[int, str] = {}
        self._lock = threading.Lock()  # the background thread and cpu_by_kind both sample
        self._interval = interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _descendants(self) -> set[int]:
        parent: dict[int, int] = {}
        for d in Path("/proc").iterdir():
            if d.name.isdigit():
                with contextlib.suppress(OSError, ValueError, IndexError):
                    parent[int(d.name)] = int(
                        (d / "stat").read_text().rpartition(")")[2].split()[1]
                    )
        out, todo = {self.pid}, [self.pid]
        while todo:
            p = todo.pop()
            kids = [c for c, pp in parent.items() if pp == p and c not in out]
            out.update(kids)
            todo.extend(kids)
        return out

    def _sample(self) -> bool:
        with self._lock:
            return self._sample_locked()

    def _sample_locked(self) -> bool:
        alive = False
        if self.children:
            self.pids |= self._descendants()
        for pid in self.pids:
            if self._kind is not None and pid not in self._kinds:
                with contextlib.suppress(OSError):
                    self._kinds[pid] = self._kind(pid)
            base = Path(f"/proc/{pid}/task")
            try:
                tids = [t.name for t in base.iterdir()]
            except OSError:
                continue
            alive = True
            for tid in tids:
                with contextlib.suppress(OSError, ValueError):
                    run, wait, _ = (base / tid / "schedstat").read_text().split()
                    self._tasks[(pid, tid)] = (int(run), int(wait))
        return alive

    def _run(self) -> None:
        while not self._stop.is_set() and self._sample():
            self._stop.wait(self._interval)

    def cpu_by_kind(self) -> dict[str, float]:
        """CPU seconds so far (a fresh sample) per ``kind`` of process; the difference of
        two calls is what each kind used between them."""
        self._sample()
        with self._lock:
            out: dict[str, float] = {}
            for (pid, _), (run, _) in self._tasks.items():
                k = self._kinds.get(pid, "?")
                out[k] = out.get(k, 0.0) + run * 1e-9
            return out

    def stop(self) -> dict:
        self._stop.set()
        self._thread.join(5)
        self._sample()
        return {
            "cpu_s": sum(r for r, _ in self._tasks.values()) * 1e-9,
            "runqueue_wait_s": sum(w for _, w in self._tasks.values()) * 1e-9,
            "threads": len(self._tasks),
            "processes": len(self.pids),
        }
