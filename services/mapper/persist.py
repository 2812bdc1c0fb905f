"""Incremental Redis writes of server maps and agent handlers, and the rebuild after a
restart. Layout: shared/store.py's docstring; this module adds the mapper's fields:

    hm:agent_index            HASH  agent -> small integer (the high bits of gids)
    hm:agent_index_next       STR   counter
    hm:agent:{a}              HASH  + index, lam
    hm:agent:{a}:removed      HASH  culled kf id -> msgpack (anchor gid, T_anchor_kf)
    hm:kf:{a}:{id}            HASH  + gid, mpg (i8 point gid per keypoint), gparent
    hm:alias                  HASH  fused point gid -> surviving gid
"""

from __future__ import annotations

import numpy as np

from shared.camera import PinholeRadTan
from shared.geometry import Sim3
from shared.messages import packb, unpackb
from shared.store import (
    P,
    Store,
    k_agent,
    k_agent_kfs,
    k_kf,
    k_map,
    k_map_kfs,
)

from .registration import AgentHandler, IngestResult, MapperParams
from .server_map import ServerKeyframe, ServerMap, ServerMapPoint, split_gid

K_INDEX = f"{P}:agent_index"
K_ALIAS = f"{P}:alias"


def agent_index(store: Store, agent: str) -> int:
    r = store.r
    v = r.hget(K_INDEX, agent)
    if v is not None:
        return int(v)
    n = int(r.incr(f"{P}:agent_index_next"))
    r.hsetnx(K_INDEX, agent, n)
    return int(r.hget(K_INDEX, agent))


def index_names(store: Store) -> dict[int, str]:
    return {int(v): k.decode() for k, v in store.r.hgetall(K_INDEX).items()}


def write_handler(pipe, h: AgentHandler, new: bool = False) -> None:
    fields = {"map": h.map_id, "S_m_l": h.S_m_l.to_array().astype("<f8").tobytes(),
              "lam": repr(float(h.lam)), "index": h.index, "kf_high": h.kf_high,
              "calib": h.camera.to_array().astype("<f8").tobytes()}  # fmt: skip
    pipe.hset(k_agent(h.agent), mapping=fields)
    if new:
        pipe.sadd(f"{P}:agents", h.agent)
        pipe.sadd(f"{P}:maps", h.map_id)
        pipe.hsetnx(k_map(h.map_id), "created_ns", 0)
    pipe.hset(k_map(h.map_id), "agents", ",".join(sorted(h.smap.agents | {h.agent})))


def _kf_fields(kf: ServerKeyframe, map_id: str) -> dict:
    return {
        "map": map_id, "gid": kf.gid, "pose": kf.T_m_kf.astype("<f8").tobytes(),
        "mpg": kf.mp.astype("<i8").tobytes(), "gparent": kf.parent,
    }  # fmt: skip


kf_fields = _kf_fields  # the fields a pose or association change rewrites


def write_result(pipe, h: AgentHandler, res: IngestResult, names: dict[int, str]) -> None:
    """Everything ``res`` changed, in the caller's MULTI/EXEC pipeline."""
    smap = h.smap
    for g in res.new_kfs:
        kf = smap.kfs.get(g)
        if kf is None:
            continue
        src = res.sources[g]
        fields = _kf_fields(kf, smap.map_id)
        fields.update(
            stamp=kf.stamp_ns, pred=src.pred_id, parent=src.parent_id,
            T_pred=src.T_pred_kf.astype("<f8").tobytes(),
            T_par=src.T_par_kf.astype("<f8").tobytes(),
            T_l=kf.T_l_kf.astype("<f8").tobytes(),
            kp=kf.keypoints.astype("<f4").tobytes(), oct=kf.octaves.astype(np.uint8).tobytes(),
            desc=kf.descriptors.astype(np.uint8).tobytes(),
        )  # fmt: skip
        pipe.hset(k_kf(kf.agent, kf.id), mapping=fields)
        pipe.zadd(k_agent_kfs(kf.agent), {str(kf.id): kf.id})
        pipe.sadd(k_map_kfs(smap.map_id), f"{kf.agent}:{kf.id}")
    for g in res.changed_kfs - set(res.new_kfs):
        kf = smap.kfs.get(g)
        if kf is not None:
            pipe.hset(k_kf(kf.agent, kf.id), mapping=_kf_fields(kf, smap.map_id))
    write_points(pipe, smap, list(res.new_mps) + sorted(res.changed_mps), names)
    delete_points(pipe, res.removed_mps, names)
    for drop, keep in res.aliases.items():
        pipe.hset(K_ALIAS, str(drop), str(keep))
    write_handler(pipe, h)


def write_points(pipe, smap: ServerMap, gids, names: dict[int, str]) -> None:
    by_agent: dict[int, list[int]] = {}
    for g in gids:
        if g in smap.mps:
            by_agent.setdefault(g >> 40, []).append(g)
    for ai, gs in by_agent.items():
        pts = [smap.mps[g] for g in gs]
        Store.put_points(
            pipe, names[ai], [split_gid(g)[1] for g in gs],
            np.array([p.pos for p in pts]), np.array([p.ref_kf for p in pts]),
            np.array([p.descriptor for p in pts]),
        )  # fmt: skip


def delete_points(pipe, gids, names: dict[int, str]) -> None:
    by_agent: dict[int, list[int]] = {}
    for g in gids:
        by_agent.setdefault(g >> 40, []).append(split_gid(g)[1])
    for ai, ids in by_agent.items():
        Store.del_points(pipe, names[ai], ids)


def write_removed_kf(pipe, h: AgentHandler, kf: ServerKeyframe, dead_mps: list[int],
                     names: dict[int, str]) -> None:  # fmt: skip
    pipe.delete(k_kf(kf.agent, kf.id))
    pipe.zrem(k_agent_kfs(kf.agent), str(kf.id))
    pipe.srem(k_map_kfs(h.map_id), f"{kf.agent}:{kf.id}")
    if kf.id in h.removed:
        g, T = h.removed[kf.id]
        pipe.hset(f"{k_agent(kf.agent)}:removed", str(kf.id), packb([g, T]))
    delete_points(pipe, dead_mps, names)


def load_all(
    store: Store, params: MapperParams
) -> tuple[dict[str, ServerMap], dict[str, AgentHandler]]:
    """Rebuild maps, covisibility and agent handlers from Redis."""
    r = store.r
    names = index_names(store)
    maps: dict[str, ServerMap] = {}
    handlers: dict[str, AgentHandler] = {}
    aliases = {int(k): int(v) for k, v in r.hgetall(K_ALIAS).items()}
    kfs_by_map: dict[str, list] = {}
    for agent in store.agents():
        h = r.hgetall(k_agent(agent))
        if not h or b"index" not in h:
            continue
        map_id = h[b"map"].decode()
        smap = maps.setdefault(map_id, ServerMap(map_id))
        S = Sim3.from_array(np.frombuffer(h[b"S_m_l"], "<f8"))
        ah = AgentHandler(agent, int(h[b"index"]), smap, S, params, float(h.get(b"lam", 1.0)))
        ah.aliases = aliases
        if b"calib" in h:
            ah.camera = PinholeRadTan.from_array(np.frombuffer(h[b"calib"], "<f8"))
        for kid, v in r.hgetall(f"{k_agent(agent)}:removed").items():
            g, T = unpackb(v)
            ah.removed[int(kid)] = (int(g), np.array(T))
            smap.culled[ah.kf_gid(int(kid))] = ah.removed[int(kid)]
        handlers[agent] = ah
        for mp in _points(store, agent):
            smap.mps[mp.gid] = mp
        kfs_by_map.setdefault(map_id, []).extend(_keyframes(store, agent, ah))
    for map_id, kfs in kfs_by_map.items():
        smap = maps[map_id]
        parents = {}
        for kf, gparent in sorted(kfs, key=lambda x: (x[0].stamp_ns, x[0].gid)):
            smap.add_keyframe(kf)
            parents[kf.gid] = gparent
        for g, kf in smap.kfs.items():
            old = kf.parent
            if old in smap.kfs:
                smap.kfs[old].children.discard(g)
            kf.parent = parents[g]
            if kf.parent in smap.kfs:
                smap.kfs[kf.parent].children.add(g)
    for ah in handlers.values():
        ah.latest_kf = max([kf.id for kf in ah.smap.kfs.values() if kf.agent == ah.agent]
                           + list(ah.removed), default=-1)  # fmt: skip
    del names
    return maps, handlers


def _keyframes(store: Store, agent: str, ah: AgentHandler):
    out = []
    ids = store.keyframe_ids(agent)
    p = store.r.pipeline(transaction=False)
    for i in ids:
        p.hmget(k_kf(agent, i), [b"gid", b"stamp", b"pose", b"T_l", b"kp", b"oct", b"desc",
                                 b"mpg", b"gparent"])  # fmt: skip
    for i, v in zip(ids, p.execute(), strict=True):
        if v[0] is None:
            continue
        kp = np.frombuffer(v[4], "<f4").reshape(-1, 2).copy()
        kf = ServerKeyframe(
            int(v[0]), agent, i, int(v[1]), np.frombuffer(v[2], "<f8").reshape(4, 4).copy(),
            np.frombuffer(v[3], "<f8").reshape(4, 4).copy(), kp,
            ah.camera.undistort_points(kp), np.frombuffer(v[5], np.uint8).copy(),
            np.frombuffer(v[6], np.uint8).reshape(-1, 32).copy(),
            np.frombuffer(v[7], "<i8").copy(),
        )  # fmt: skip
        ah.local_poses[i] = kf.T_l_kf
        out.append((kf, int(v[8])))
    return out


def _points(store: Store, agent: str) -> list[ServerMapPoint]:
    ids, rec = store.map_point_records(agent)
    if len(ids) == 0:
        return []
    idx = int(store.r.hget(K_INDEX, agent))
    return [
        ServerMapPoint((idx << 40) | int(i), r["pos"].copy(), r["desc"].copy(), int(r["ref_g"]))
        for i, r in zip(ids, rec, strict=True)
    ]
