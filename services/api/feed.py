"""What the viewer draws, read from Redis: per map its agents, keyframe trajectories,
loop edges and a capped sample of its points; per agent its status and live pose.

Plain functions on a Store (the WebSocket handler runs them in a thread), so each
refresh is a handful of pipelined reads however many clients watch.
"""

from __future__ import annotations

import time

import numpy as np

from shared.ids import agent_index_of, local_id_of
from shared.store import LivePose, Store

from .models import pose_out

# No pose for this long: the agent is shown as disconnected (agents send at 10-20 Hz;
# the mapper's agent-health export uses the same limit).
DISCONNECTED_AFTER_S = 3.0
# Map points sent per map at most (issue 21: served with a cap).
POINTS_CAP = 20_000


def _r(a: np.ndarray, nd: int = 3) -> list:
    return np.round(np.asarray(a, float), nd).tolist()


def agent_status(pose: LivePose | None, now_ns: int) -> str:
    """tracking | initializing | lost | disconnected, from the agent's latest pose."""
    if pose is None or (now_ns - pose.recv_ns) * 1e-9 > DISCONNECTED_AFTER_S:
        return "disconnected"
    return {"ok": "tracking", "init": "initializing"}.get(pose.tracking, "lost")


def up_direction(kf_pos: np.ndarray, R: np.ndarray, pts: np.ndarray | None = None) -> np.ndarray:
    """A map's "up" (unit 3-vector in its frame), for drawing it top-down.

    Robots and drones move mostly level, so the axis is the direction the keyframe
    positions vary least along, once there are enough of them; before, the cameras'
    mean -y (a map's frame is a camera frame, y down). The sign: a camera sees more of
    the floor than of the ceiling, so most map points lie below the keyframes; without
    points, the cameras' -y decides."""
    down = R[:, :, 1].mean(0) if len(R) else np.array([0.0, 1.0, 0.0])
    up = -down / max(np.linalg.norm(down), 1e-9)
    if len(kf_pos) >= 10:
        w, v = np.linalg.eigh(np.cov(np.asarray(kf_pos, float).T))
        # Only a spread that is flat: a take-off or a straight run is a line, whose
        # least-varying direction is as likely level as vertical.
        if w[0] < 0.35 * w[1] and w[1] > 0.1 * w[2]:
            up = v[:, 0]
    if pts is not None and len(pts) >= 50 and len(kf_pos):
        below = np.median(pts @ up) < np.median(np.asarray(kf_pos) @ up)
        return up if below else -up
    return up if up @ down <= 0 else -up


def state(store: Store, seen_live: list[str] | tuple[str, ...] = ()) -> dict:
    """Maps, agents (status, live pose, counts), keyframe trajectories and loop edges.
    ``seen_live``: maps the caller last saw live; one merged since is listed once more,
    with its ``merged_into`` (the store lists live maps only), so the merge is seen."""
    now_ns = time.time_ns()
    agents_out, trajs = [], {}
    kf_pos: dict[tuple[str, int], list[float]] = {}
    rots: dict[str, list[np.ndarray]] = {}
    names = store.agents()
    for a in names:
        info = store.agent_info(a)
        if info is None:
            continue
        doc = store.latest_pose(a)
        ids, T = store.keyframe_poses(a)
        trajs[a] = _r(T[:, :3, 3])
        rots.setdefault(info["map_id"], []).append(T)
        for i, p in zip(ids.tolist(), trajs[a], strict=True):
            kf_pos[(a, i)] = p
        out = {"agent": a, "map_id": info["map_id"], "n_kf": info["n_kf"],
               "n_mp": info["n_mp"], "status": agent_status(doc, now_ns)}  # fmt: skip
        if doc is not None:
            po = pose_out(doc)
            out.update(position=_r(po.position), quaternion_xyzw=_r(po.quaternion_xyzw, 4),
                       fps=round(po.fps, 1), tracking=po.tracking,
                       age_s=round((now_ns - doc.recv_ns) * 1e-9, 2))  # fmt: skip
        agents_out.append(out)
    by_index = store.agents_by_index()
    maps, loops = [], {}
    for m in sorted(set(store.maps()) | set(seen_live)):
        info = store.map_info(m)
        if info is None:
            continue
        maps.append({k: info[k] for k in ("map_id", "agents", "n_kf", "merged_into")})
        if m in rots:
            T = np.concatenate(rots[m])
            maps[-1]["up"] = _r(up_direction(T[:, :3, 3], T[:, :3, :3]), 4)
        edges = []
        for q, c in store.map_loops(m):
            ends = [
                kf_pos.get((by_index.get(agent_index_of(g), ""), local_id_of(g))) for g in (q, c)
            ]
            if ends[0] is not None and ends[1] is not None:
                edges.append({"id": f"{q}:{c}", "a": ends[0], "b": ends[1]})
        loops[m] = edges
    return {"type": "state", "t": now_ns * 1e-9, "maps": maps, "agents": agents_out,
            "trajectories": trajs, "loops": loops}  # fmt: skip


def points(store: Store, map_id: str, cap: int = POINTS_CAP) -> dict:
    """A sample of at most ``cap`` of the map's points, shared out evenly among its
    agents, as a flat [x0, y0, z0, x1, ...] list (millimetres are enough to draw)."""
    info = store.map_info(map_id)
    agents = info["agents"] if info else []
    n_total = 0
    parts = []
    left = cap
    for k, a in enumerate(agents):
        share = left // (len(agents) - k)
        p, n = store.point_sample(a, share)
        n_total += n
        left -= len(p)
        parts.append(p)
    pts = np.concatenate(parts) if parts else np.zeros((0, 3))
    poses = [store.keyframe_poses(a)[1] for a in agents]
    T = np.concatenate(poses) if poses else np.zeros((0, 4, 4))
    up = up_direction(T[:, :3, 3], T[:, :3, :3], pts)
    return {"type": "points", "map_id": map_id, "n": len(pts), "n_total": n_total,
            "xyz": _r(pts.reshape(-1)) if len(pts) else [], "up": _r(up, 4)}  # fmt: skip


def diff_events(prev: dict | None, cur: dict) -> list[dict]:
    """Merges and loops that appeared between two states, as viewer events."""
    if prev is None:
        return []
    out = []
    was_merged = {m["map_id"]: m["merged_into"] for m in prev["maps"]}
    pose_of = {a["agent"]: a.get("position") for a in cur["agents"]}
    for m in cur["maps"]:
        if m["merged_into"] and not was_merged.get(m["map_id"]):
            # Where it happened: an agent of the merged map, else any agent of the target.
            target = next((t for t in cur["maps"] if t["map_id"] == m["merged_into"]), None)
            near = list(m["agents"]) + (target["agents"] if target else [])
            at = next((pose_of[a] for a in near if pose_of.get(a)), None)
            out.append({"type": "event", "kind": "merge", "t": cur["t"], "map_id": m["merged_into"],
                        "source": m["map_id"], "target": m["merged_into"], "at": at})  # fmt: skip
    merged_now = {e["target"] for e in out}
    for map_id, edges in cur["loops"].items():
        if map_id in merged_now:
            continue  # the merge's own constraint is stored as a loop edge too
        seen = {e["id"] for es in prev["loops"].values() for e in es}
        for e in edges:
            if e["id"] not in seen:
                out.append({"type": "event", "kind": "loop", "t": cur["t"], "map_id": map_id,
                            "at": e["a"], "to": e["b"]})  # fmt: skip
    return out
