"""PNG plots beside the benches' JSON (matplotlib, drawn off screen).

The benches call these when they write their report; ``python bench/plots.py`` draws
them again from every JSON under bench/results/ that holds what a plot needs:

- ``latency`` rows (bench_mapper): keyframe latency against team size;
- ``traffic`` series (bench_mapper, bench_viewer): bytes per second over time;
- ``trajectories`` (bench_team, bench_viewer): every agent against ground truth, one
  figure per map, aligned as the ATE is (one similarity per map for all its agents).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = RESULTS.parents[1]
sys.path.insert(0, str(ROOT))

LATENCY_BAR_MS = 200.0  # issue 18: mapper p95 per agent


def aligned_trajectories(trajs: dict, max_points: int = 400) -> dict:
    """``trajs``: agent -> (map id, keyframe Trajectory in the map's frame). Returns
    agent -> {"map", "seq", "est", "gt"} with positions (decimated), the estimate
    carried into the ground-truth frame by one similarity per map (as evaluate_team)."""
    from shared.evaluation import identify_sequence
    from shared.geometry import umeyama
    from shared.trajectory import associate, load_euroc_gt

    by_map: dict[str, list] = {}
    for agent, (map_id, tr) in sorted(trajs.items()):
        seq = identify_sequence(tr.stamps_ns) if len(tr) >= 3 else None
        if seq is None:
            continue
        gt = load_euroc_gt(seq)
        ie, ir = associate(tr, gt)
        if len(ie) >= 3:
            by_map.setdefault(map_id, []).append((agent, seq, tr.positions[ie], gt.positions[ir]))
    out = {}
    for map_id, items in by_map.items():
        S = umeyama(np.concatenate([p for *_, p, _ in items]),
                    np.concatenate([g for *_, g in items]))  # fmt: skip
        for agent, seq, P, G in items:
            k = np.unique(np.linspace(0, len(P) - 1, min(len(P), max_points)).round().astype(int))
            out[agent] = {"map": map_id, "seq": seq,
                          "est": np.round(S.apply(P[k]), 4).tolist(),
                          "gt": np.round(G[k], 4).tolist()}  # fmt: skip
    return out


def _save(fig, path: Path, ax=None, title: str = "") -> Path:
    """``fig`` laid out, written to ``path`` and closed; ``ax`` (if given) titled, with a
    light grid and a small legend first."""
    if ax is not None:
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def trajectories(data: dict, path: Path, title: str) -> Path:
    """Every agent's estimate (solid, its colour) against its ground truth (dashed),
    top-down (x, y of the EuRoC world), one panel per map."""
    maps = sorted({d["map"] for d in data.values()})
    fig, axes = plt.subplots(1, len(maps), figsize=(7 * len(maps), 6.5), squeeze=False)
    cmap = plt.get_cmap("tab20" if len(data) > 10 else "tab10")
    for ax, map_id in zip(axes[0], maps, strict=True):
        for i, (agent, d) in enumerate(sorted(data.items())):
            if d["map"] != map_id:
                continue
            c = cmap(i % cmap.N)
            e, g = np.asarray(d["est"]), np.asarray(d["gt"])
            err = np.sqrt(((e - g) ** 2).sum(1).mean())
            ax.plot(g[:, 0], g[:, 1], "--", color=c, lw=1, alpha=0.6)
            ax.plot(e[:, 0], e[:, 1], "-", color=c, lw=1.6,
                    label=f"{agent} ({d['seq']}) {err * 1000:.1f} mm")  # fmt: skip
        ax.set_title(f"{title}: {map_id}")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best", title_fontsize=7,
                  title="solid: server map, dashed: ground truth\n"
                        "(one similarity per map; RMS error per agent)")  # fmt: skip
    return _save(fig, path)


def latency_vs_team(rows: list[dict], path: Path, title: str = "Keyframe latency") -> Path:
    """Per agent: the mapper's p95 (received -> stored + acked) and the agents' round-trip
    p95 (publish -> ack), against the number of agents, with the 200 ms bar."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ns = sorted({r["agents"] for r in rows})
    for key, label, m in (("mapper_p95_ms", "mapper p95 (received -> stored + acked)", "o"),
                          ("p95_ms", "agent round trip p95 (publish -> ack)", "s"),
                          ("mapper_median_ms", "mapper median", "^")):  # fmt: skip
        xs, ys = [], []
        for r in rows:
            if r.get(key) is not None and np.isfinite(r[key]):
                xs.append(r["agents"])
                ys.append(r[key])
        if not xs:
            continue
        ax.scatter(xs, ys, marker=m, alpha=0.6, label=label)
        worst = [max(y for x, y in zip(xs, ys, strict=True) if x == n) for n in ns if n in xs]
        ax.plot([n for n in ns if n in xs], worst, alpha=0.5)
    ax.axhline(LATENCY_BAR_MS, color="red", ls="--", lw=1, label="200 ms bar (p95)")
    ax.set_xlabel("agents in the team")
    ax.set_ylabel("latency per agent [ms]")
    ax.set_xticks(ns)
    ax.set_ylim(bottom=0)
    return _save(fig, path, ax, title)


def traffic_over_time(series: dict[str, list], path: Path, title: str = "Mapper traffic") -> Path:
    """``series``: label -> [[t_s, in, out to agents, out to services], ...] in bytes per
    second (older reports: [t_s, in, out])."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for i, (label, s) in enumerate(sorted(series.items())):
        a = np.asarray(s, float)
        if len(a) == 0:
            continue
        c = f"C{i}"
        ax.plot(a[:, 0], a[:, 1] / 1e3, "-", color=c, label=f"{label}: agents -> mapper")
        if a.shape[1] >= 4:
            ax.plot(
                a[:, 0],
                a[:, 2] / 1e3,
                ":",
                color=c,
                label=f"{label}: mapper -> agents (acks, map chunks)",
            )
            ax.plot(a[:, 0], a[:, 3] / 1e3, "--", color=c, alpha=0.5,
                    label=f"{label}: mapper -> placerec, optimizer")  # fmt: skip
        else:
            ax.plot(a[:, 0], a[:, 2] / 1e3, ":", color=c, label=f"{label}: mapper out")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("kB/s")
    ax.set_ylim(bottom=0)
    return _save(fig, path, ax, title)


class TrafficSampler:
    """Bytes per second in and out of a service, from its /metrics once a second."""

    def __init__(self, metrics_url: str, service: str = "mapper", every: float = 1.0) -> None:
        import threading
        import time

        self.url, self.service, self.every = metrics_url, service, every
        self.series: list[list[float]] = []
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _totals(self) -> list[float]:
        """Bytes in, out to agents (``hivemap/agent/*/down/*``), out to services."""
        import urllib.request

        with urllib.request.urlopen(self.url, timeout=2) as r:
            text = r.read().decode()
        tot = [0.0, 0.0, 0.0]
        for ln in text.splitlines():
            if ln.startswith("hivemap_bytes_total{") and f'service="{self.service}"' in ln:
                i = 0 if 'direction="in"' in ln else 1 if "/down/" in ln else 2
                tot[i] += float(ln.rsplit(" ", 1)[1])
        return tot

    def _run(self) -> None:
        import time

        prev = None
        while not self._stop.wait(self.every):
            try:
                now, tot = time.monotonic(), self._totals()
            except OSError:
                continue
            if prev is not None:
                dt = now - prev[0]
                rates = [round((a - b) / dt) for a, b in zip(tot, prev[1], strict=True)]
                self.series.append([round(now - self._t0, 2), *rates])
            prev = (now, tot)

    def stop(self) -> list[list[float]]:
        self._stop.set()
        self._thread.join(5)
        return self.series


def draw_all(results: Path = RESULTS) -> list[Path]:
    """Every plot the JSON reports under ``results`` hold the data for."""
    out = []
    for f in sorted(results.glob("*.json")):
        try:
            d = json.loads(f.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if not isinstance(d, dict):
            continue
        name = f.stem
        if isinstance(d.get("latency"), list) and d["latency"]:
            out.append(latency_vs_team(d["latency"], results / f"{name}_vs_team.png",
                                       f"Keyframe latency against team size ({name})"))  # fmt: skip
        if d.get("traffic"):
            out.append(traffic_over_time(d["traffic"], results / f"{name}_traffic.png",
                                         f"Mapper traffic over time ({name})"))  # fmt: skip
        if d.get("trajectories"):
            out.append(trajectories(d["trajectories"], results / f"{name}_trajectories.png",
                                    name))  # fmt: skip
        runs = d.get("runs") or {}
        # Most reports key their runs by name; a few (bench_scale) list them.
        named = runs.items() if isinstance(runs, dict) else enumerate(runs)
        for run, r in named:
            if isinstance(r, dict) and r.get("trajectories"):
                png = results / f"{name}_{run}_trajectories.png"
                out.append(trajectories(r["trajectories"], png, run))
    return out


if __name__ == "__main__":
    for p in draw_all():
        print(f"wrote {p}")
