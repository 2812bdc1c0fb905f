"""Team evaluation: per-agent and joint ATE of server-map keyframe trajectories.

Joint ATE is what a collaborative SLAM paper reports: the keyframes of every agent in
one map, aligned to ground truth under ONE Sim(3) (Umeyama, as ``evo_ape -as`` does
per trajectory), RMSE of the position errors. Agents in different server maps can't
share a frame, so the joint figure is per map; a team that ended in one map has one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from shared.geometry import umeyama
from shared.trajectory import SEQUENCES, Trajectory, associate, ate, load_euroc_gt


def identify_sequence(stamps_ns: np.ndarray) -> str | None:
    """The EuRoC MH sequence whose ground-truth stamps these are (the five flights were
    recorded at different times, so their stamps never overlap)."""
    best, n_best = None, 0
    for seq in SEQUENCES:
        gt = load_euroc_gt(seq)
        ie, _ = associate(Trajectory(stamps_ns, np.zeros((len(stamps_ns), 4, 4))), gt)
        if len(ie) > n_best:
            best, n_best = seq, len(ie)
    return best if n_best >= max(3, len(stamps_ns) // 2) else None


@dataclass
class AgentEval:
    agent: str
    map_id: str
    seq: str
    keyframes: int
    ate_m: float
    path_m: float  # ground-truth path length between the agent's first and last keyframe

    @property
    def ate_pct(self) -> float:
        return 100.0 * self.ate_m / self.path_m if self.path_m > 0 else float("nan")


@dataclass
class MapEval:
    map_id: str
    agents: list[str]
    keyframes: int
    joint_ate_m: float
    path_m: float
    scale: float
    agents_eval: list[AgentEval] = field(default_factory=list)

    @property
    def joint_ate_pct(self) -> float:
        return 100.0 * self.joint_ate_m / self.path_m if self.path_m > 0 else float("nan")


def _gt_span(gt: Trajectory, stamps: np.ndarray) -> float:
    """GT path length over the flight span the keyframes cover."""
    sel = (gt.stamps_ns >= stamps.min()) & (gt.stamps_ns <= stamps.max())
    return Trajectory(gt.stamps_ns[sel], gt.poses[sel]).path_length()


def evaluate_team(
    trajs: dict[str, tuple[str, Trajectory]], gts: dict[str, Trajectory] | None = None
) -> list[MapEval]:
    """``trajs``: agent -> (map id, keyframe trajectory in that map's frame). ``gts``:
    agent -> ground truth (default: identified among the EuRoC MH sequences)."""
    by_map: dict[str, list[str]] = {}
    for agent, (map_id, _) in sorted(trajs.items()):
        by_map.setdefault(map_id, []).append(agent)
    out = []
    for map_id, agents in sorted(by_map.items()):
        P, G, evals, path = [], [], [], 0.0
        for a in agents:
            tr = trajs[a][1]
            if len(tr) < 3:
                continue
            seq = "custom"
            gt = (gts or {}).get(a)
            if gt is None:
                seq = identify_sequence(tr.stamps_ns) or "?"
                if seq == "?":
                    continue
                gt = load_euroc_gt(seq)
            ie, ir = associate(tr, gt)
            P.append(tr.positions[ie])
            G.append(gt.positions[ir])
            span = _gt_span(gt, tr.stamps_ns[ie])
            path += span
            r = ate(tr, gt)
            evals.append(AgentEval(a, map_id, seq, len(tr), r.rmse, span))
        if not P:
            continue
        Pc, Gc = np.concatenate(P), np.concatenate(G)
        S = umeyama(Pc, Gc)
        err = np.linalg.norm(S.apply(Pc) - Gc, axis=1)
        out.append(MapEval(map_id, [e.agent for e in evals], len(Pc),
                           float(np.sqrt((err**2).mean())), path, S.s, evals))  # fmt: skip
    return out


def format_report(maps: list[MapEval]) -> str:
    lines = [f"{'map':<16} {'agent':<12} {'seq':<5} {'kfs':>5} {'ATE m':>9} {'% path':>8}"]
    for m in maps:
        for e in m.agents_eval:
            lines.append(f"{m.map_id:<16} {e.agent:<12} {e.seq:<5} {e.keyframes:>5} "
                         f"{e.ate_m:>9.4f} {e.ate_pct:>8.4f}")  # fmt: skip
        lines.append(f"{m.map_id:<16} {'JOINT':<12} {'':<5} {m.keyframes:>5} "
                     f"{m.joint_ate_m:>9.4f} {m.joint_ate_pct:>8.4f}  "
                     f"(path {m.path_m:.1f} m, {len(m.agents)} agents)")  # fmt: skip
    return "\n".join(lines)
