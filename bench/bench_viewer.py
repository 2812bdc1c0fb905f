"""Viewer under load: the whole stack (router, redis, mapper, placerec, optimizer, api),
N simulated agents flying MH01..MH05 in real time, and the viewer open in Debian's
headless Chromium (playwright, executable_path; no browser download).

Measured: frames per second the page draws (counted in the page, 5 s windows), what it
shows (agents, points), the mapper's keyframe latency per agent while it runs (its
histogram, received -> stored + acked; the bar is p95 <= 200 ms over all keyframes, as
bench_ramp's steps; the worst agent's p95 is reported beside it),
the mapper's traffic over time; every agent's server trajectory against ground truth.
Writes bench/results/NAME.json, NAME.png (screenshot) and the plots beside them.

    flock /tmp/hivemap-cpu.lock .venv/bin/python bench/bench_viewer.py [--agents 16]
        [--seconds 60] [--no-viewer]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import numpy as np  # noqa: E402
from bench_mapper import AGENT_NICE, hist_quantile, pooled_quantile  # noqa: E402
from common import LAT, RESULTS, scrape, table, write_report  # noqa: E402
from live_stack import chromium_missing, stack_settings, viewer_page  # noqa: E402
from plots import (  # noqa: E402
    TrafficSampler,
    aligned_trajectories,
    traffic_over_time,
    trajectories,
)

from services.launcher import Stack  # noqa: E402
from services.team_cli import collect  # noqa: E402
from shared.progress import progress  # noqa: E402
from shared.trajectory import SEQUENCES  # noqa: E402

LATENCY_BAR_MS = 200.0


def run(n_agents: int, seconds: float, name: str, with_viewer: bool) -> dict:
    stack = Stack(stack_settings(), env={"HIVEMAP_LOG_LEVEL": "WARNING"})
    stack.start()
    s = stack.settings
    api = f"http://127.0.0.1:{s.api_port}"
    mapper = f"http://127.0.0.1:{s.mapper_metrics_port}/metrics"
    fps: list[dict] = []
    shot = RESULTS / f"{name}.png"
    shot.unlink(missing_ok=True)
    load_before = os.getloadavg()
    out = Path(tempfile.mkdtemp(prefix="hivemap-viewer-"))
    try:
        sampler = TrafficSampler(mapper)
        with viewer_page(stack.viewer_url, nice=AGENT_NICE) if with_viewer else _no_page() as page:
            stack.add(
                "sim-agents",
                ["sim-agent", "--id", "agent", "--count", str(n_agents),
                 "--traj", ",".join(SEQUENCES), "--frames", f"0:{int(seconds * 20)}",
                 "--speed", "1", "--flush-timeout", "20", "--out", str(out)],
                {"HIVEMAP_LOG_LEVEL": "WARNING"}, AGENT_NICE,
            )  # fmt: skip
            agents = stack.procs[-1][1]
            t0 = time.monotonic()
            with progress(f"{n_agents} agents flying", seconds, "s") as update:
                while agents.poll() is None and time.monotonic() - t0 < 3 * seconds + 120:
                    if page is None:
                        time.sleep(1.0)
                    else:
                        f0, w0 = page.evaluate("[hivemapViewer.frames, performance.now()]")
                        time.sleep(5.0)
                        f1, w1 = page.evaluate("[hivemapViewer.frames, performance.now()]")
                        d = page.evaluate("hivemapViewer.drawn")
                        fps.append({"t": round(time.monotonic() - t0, 1),
                                    "fps": round((f1 - f0) * 1000 / (w1 - w0), 1),
                                    "draw_ms": round(page.evaluate("hivemapViewer.drawMs"), 2),
                                    "agents": d["agents"], "points": d["points"]})  # fmt: skip
                        # The last view while most agents still fly (on a loaded machine
                        # the flight takes longer than its nominal seconds).
                        if page.inner_text("#agents tbody").count("tracking") > n_agents // 2:
                            page.screenshot(path=str(shot))
                        update(info=f"viewer {fps[-1]['fps']:.0f} fps, {d['agents']} agents")
                    update(completed=min(seconds, time.monotonic() - t0))
            if page is not None and not shot.exists():
                page.screenshot(path=str(shot))
        traffic = sampler.stop()
        load_after = os.getloadavg()
        m = scrape(mapper)
        a = scrape(f"{api}/metrics")
        trajs = collect(s.redis_url)
    finally:
        stack.stop()
    stats = [json.loads(f.read_text()) for f in sorted(out.glob("*_stats.json"))]
    ids = sorted({k.split('"')[1] for k in m if k.startswith(f"{LAT}_count{{")})
    rows = [{"agent": i,
             "keyframes": m.get(f'{LAT}_count{{agent="{i}"}}', 0),
             "mapper_median_ms": 1e3 * hist_quantile(m, LAT, f'agent="{i}"', 0.5),
             "mapper_p95_ms": 1e3 * hist_quantile(m, LAT, f'agent="{i}"', 0.95)}
            for i in ids]  # fmt: skip
    p95 = [r["mapper_p95_ms"] for r in rows if np.isfinite(r["mapper_p95_ms"])]
    all_p95 = 1e3 * pooled_quantile(m, LAT, 0.95)
    steady = [f["fps"] for f in fps[1:]] or [f["fps"] for f in fps]
    draw = [f["draw_ms"] for f in fps[1:]] or [f["draw_ms"] for f in fps]
    return {
        "agents": n_agents, "seconds": seconds, "viewer": with_viewer,
        "viewer_fps": {"median": float(np.median(steady)) if steady else None,
                       "min": float(min(steady)) if steady else None,
                       "cap": 30, "draw_ms_median": float(np.median(draw)) if draw else None,
                       "draw_ms_max": float(max(draw)) if draw else None, "series": fps},
        "mapper_latency": rows,
        # The bar (issue 18 item 1, which issue 21 item 4 says must still hold) is on the
        # p95 over every keyframe of the step, as bench_ramp reports it; the worst
        # single agent's p95 (the quantile of ~80-200 keyframes) is kept beside it.
        "mapper_p95_ms": all_p95,
        "mapper_median_ms": 1e3 * pooled_quantile(m, LAT, 0.5),
        "mapper_p95_max_ms": max(p95) if p95 else None,
        "latency_pass": bool(np.isfinite(all_p95)) and all_p95 <= LATENCY_BAR_MS,
        "latency_pass_every_agent": bool(p95) and max(p95) <= LATENCY_BAR_MS,
        "api_ws_connections": a.get("hivemap_api_ws_connections_total", 0.0),
        "loadavg_1m_before_after": [load_before[0], load_after[0]],
        # How far behind real time the simulated agents fell (the load offered is below
        # what 16 real-time agents make when they did): flight beyond the trajectory's
        # duration and the p95 of how late a frame was stepped, worst agent; and their
        # keyframes per second (real time: ~2.3 each).
        "agents_behind_s_max": max((s["flight_s"] - s.get("nominal_flight_s", s["flight_s"])
                                    for s in stats), default=None),
        "agents_frame_late_p95_ms_max": max((1e3 * s.get("latency_s_p95", 0.0) for s in stats),
                                            default=None),
        "agents_kf_per_s": (sum(s["keyframes"] for s in stats)
                            / max(sum(s["flight_s"] for s in stats), 1e-9)) if stats else None,
        "traffic": {f"{n_agents} agents": traffic},
        "trajectories": aligned_trajectories(trajs),
        "screenshot": str(shot.relative_to(RESULTS.parents[1])) if with_viewer else None,
    }  # fmt: skip


class _no_page:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--agents", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=60.0, help="flight time per agent")
    ap.add_argument("--no-viewer", action="store_true", help="baseline: no browser")
    ap.add_argument("--name", default="")
    args = ap.parse_args()
    if not args.no_viewer and chromium_missing():
        print(f"bench_viewer: {chromium_missing()}", file=sys.stderr)
        return 2
    name = args.name or f"viewer_{args.agents}" + ("_noviewer" if args.no_viewer else "")
    r = run(args.agents, args.seconds, name, not args.no_viewer)
    path = write_report(name, r)
    print(table(r["mapper_latency"], ["agent", "keyframes", "mapper_median_ms", "mapper_p95_ms"]))
    verdict = "pass" if r["latency_pass"] else "FAIL"
    print(f"viewer fps median {r['viewer_fps']['median']}, min {r['viewer_fps']['min']} "
          f"(cap 30), draw {r['viewer_fps']['draw_ms_median']} ms per frame; "
          f"mapper p95 {r['mapper_p95_ms']:.1f} ms over all keyframes (bar "
          f"{LATENCY_BAR_MS:.0f} ms: {verdict}), worst agent's p95 "
          f"{r['mapper_p95_max_ms']:.1f} ms; load {r['loadavg_1m_before_after']}; "
          f"agents behind real time by "
          f"{r['agents_behind_s_max']} s, {r['agents_kf_per_s']} keyframes/s each")  # fmt: skip
    print(f"written {path}")
    print("plot", traffic_over_time(r["traffic"], path.with_name(f"{name}_traffic.png"),
                                    f"Mapper traffic over time, {args.agents} agents"))  # fmt: skip
    if r["trajectories"]:
        print("plot", trajectories(r["trajectories"], path.with_name(f"{name}_trajectories.png"),
                                   f"{args.agents} simulated agents"))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
