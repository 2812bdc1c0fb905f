"""What the viewer page costs the machine it runs on, against a fixed feed.

The page (services/api/static, served as the API serves it) in Debian's headless
Chromium, with its WebSocket replaced by a scripted feed shaped like a 16-agent team:
a ``state`` every 1.5 s (N agents, a keyframe trajectory of K keyframes each, one map),
``poses`` every 100 ms (every agent moving), ``points`` every 5 s (P points). No server
runs, so the figure is the browser's alone and does not vary with a stack's timing.

Measured over ``--seconds``: frames per second the page draws, how many of them redrew
the top view's still layer (points, trajectories, grid), the JavaScript time of a frame
(``drawMs``, the page's own median), and the CPU the browser's processes used (cores,
per process type: the renderer rasterizes the canvases in software here, which
``drawMs`` does not include). ``--js FILE`` draws with another viewer.js (an older
version, to compare). Writes bench/results/NAME.json.

    .venv/bin/python bench/bench_viewer_draw.py [--js FILE] [--seconds 10] [--name N]
"""

from __future__ import annotations

import argparse
import functools
import http.server
import json
import math
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import numpy as np  # noqa: E402
from common import ProcWatch, table, write_report  # noqa: E402
from live_stack import chromium_missing, viewer_page  # noqa: E402

STATIC = Path(__file__).resolve().parents[1] / "services" / "api" / "static"


def feed(n_agents: int, n_kf: int, n_points: int) -> tuple[dict, dict]:
    """A state and a points message like the API's (services/api/feed.py)."""
    rng = np.random.default_rng(0)
    trajs = {
        f"agent-{a}": [[round(math.cos(i / 20 + a) * (3 + a / 4), 3),
                        round(math.sin(i / 20 + a) * (3 + a / 4), 3),
                        round(1 + 0.3 * math.sin(i / 7), 3)] for i in range(n_kf)]
        for a in range(n_agents)
    }  # fmt: skip
    agents = [{"agent": a, "map_id": "m", "n_kf": n_kf, "n_mp": 13000, "status": "tracking",
               "position": t[-1], "quaternion_xyzw": [0, 0, 0, 1], "fps": 20, "age_s": 0.05}
              for a, t in trajs.items()]  # fmt: skip
    state = {"type": "state", "t": 0,
             "maps": [{"map_id": "m", "agents": list(trajs), "n_kf": n_agents * n_kf,
                       "merged_into": None, "up": [0, 0, 1]}],
             "agents": agents, "trajectories": trajs, "loops": {"m": []}}  # fmt: skip
    xyz = rng.uniform([-8, -8, -1], [8, 8, 3], (n_points, 3)).round(3)
    points = {"type": "points", "map_id": "m", "n": n_points, "n_total": 10 * n_points,
              "xyz": xyz.reshape(-1).tolist(), "up": [0, 0, 1]}  # fmt: skip
    return state, points


# Stands in for the browser's WebSocket: the page's own handlers get the messages.
FAKE_WS = """
(() => {
  const STATE = %s, POINTS = %s;
  class FeedSocket {
    constructor() {
      setTimeout(() => {
        this.onopen && this.onopen();
        const send = (m) => this.onmessage({ data: JSON.stringify(m) });
        send({ type: "hello" }); send(STATE); send(POINTS);
        let k = 0;
        setInterval(() => {
          k++;
          const at = (j) => [Math.cos(k / 30 + j) * 4, Math.sin(k / 30 + j) * 4, 1];
          send({ type: "poses", poses: Object.keys(STATE.trajectories).map((a, j) => ({
            agent: a, map_id: "m", position: at(j), quaternion_xyzw: [0, 0, 0, 1], fps: 20,
            tracking: "ok", status: "tracking", stamp: 0 })) });
        }, 100);
        setInterval(() => { STATE.t += 1.5; send(STATE); }, 1500);
        setInterval(() => send(POINTS), 5000);
      }, 50);
    }
    send() {}
    close() {}
  }
  window.WebSocket = FeedSocket;
})();
"""


def chromium_kind(pid: int) -> str:
    """A Chromium process's type (renderer, gpu-process, ...) from its command line;
    "bench" for this process, whose CPU is not the page's."""
    if pid == os.getpid():
        return "bench"
    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    return next((k for k in ("renderer", "gpu-process", "utility", "zygote")
                 if f"--type={k}" in cmd), "browser")  # fmt: skip


def measure(js: Path, seconds: float, n_agents: int, n_kf: int, n_points: int) -> dict:
    site = Path(tempfile.mkdtemp(prefix="hivemap-viewer-draw-"))
    (site / "static").mkdir()
    shutil.copy(STATIC / "viewer.html", site / "viewer.html")
    shutil.copy(STATIC / "viewer.css", site / "static" / "viewer.css")
    shutil.copy(js, site / "static" / "viewer.js")
    state, points = feed(n_agents, n_kf, n_points)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(site))
    handler.log_message = lambda *a: None  # type: ignore[attr-defined]
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    watch = ProcWatch(os.getpid(), kind=chromium_kind)
    try:
        with viewer_page("about:blank") as page:
            page.add_init_script(FAKE_WS % (json.dumps(state), json.dumps(points)))
            page.goto(f"http://127.0.0.1:{srv.server_address[1]}/viewer.html")
            shown = f"window.hivemapViewer.drawn.agents == {n_agents}"
            page.wait_for_function(shown, timeout=30_000)
            time.sleep(2.0)
            c0, t0 = watch.cpu_by_kind(), time.monotonic()
            now = "[hivemapViewer.frames, performance.now(), hivemapViewer.layers]"
            f0, w0, l0 = page.evaluate(now)
            time.sleep(seconds)
            f1, w1, l1 = page.evaluate(now)
            c1, dt = watch.cpu_by_kind(), time.monotonic() - t0
            d = page.evaluate("({ms: hivemapViewer.drawMs, points: hivemapViewer.drawn.points})")
    finally:
        watch.stop()
        srv.shutdown()
        shutil.rmtree(site, ignore_errors=True)
    cores = {k: round((v - c0.get(k, 0.0)) / dt, 3) for k, v in c1.items() if k != "bench"}
    # An older viewer.js has no layer (None).
    layers = None if l0 is None or l1 is None else (l1 - l0) * 1000 / (w1 - w0)
    return {"js": str(js), "fps": (f1 - f0) * 1000 / (w1 - w0), "draw_ms": d["ms"],
            "layer_redraws_per_s": layers,
            "points_drawn": d["points"], "browser_cores": round(sum(cores.values()), 3),
            "cores_by_process": cores}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--js", action="append", help="viewer.js to draw with (repeatable)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--agents", type=int, default=16)
    ap.add_argument("--keyframes", type=int, default=110, help="per agent")
    ap.add_argument("--points", type=int, default=20_000)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--name", default="viewer_draw")
    args = ap.parse_args()
    if (why := chromium_missing()) is not None:
        print(f"cannot run: {why}", file=sys.stderr)
        return 2
    files = [Path(j) for j in (args.js or [STATIC / "viewer.js"])]
    rows = []
    for _ in range(args.repeat):  # interleaved, so a change in the machine's load hits all
        for js in files:
            rows.append(measure(js, args.seconds, args.agents, args.keyframes, args.points))
    load = os.getloadavg()
    path = write_report(args.name, {"agents": args.agents, "keyframes_per_agent": args.keyframes,
                                    "points": args.points, "seconds": args.seconds,
                                    "loadavg_1m_at_end": load[0], "rows": rows})  # fmt: skip
    print(table(rows, ["js", "fps", "layer_redraws_per_s", "draw_ms", "points_drawn",
                       "browser_cores"]))  # fmt: skip
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
