"""Incremental Redis writes of server maps and agent handlers, and the rebuild after a
restart: mapper objects to and from ``shared.store``'s records (its docstring is the
schema; no key is named here).
"""

from __future__ import annotations

import time
from itertools import compress, repeat
from operator import attrgetter, is_not

import numpy as np

from shared.camera import PinholeRadTan
from shared.geometry import Sim3
from shared.ids import agent_index_of, gid, local_id_of
from shared.store import AgentState, Store, StoredKeyframe

from .registration import AgentHandler, IngestResult, MapperParams
from .server_map import ServerKeyframe, ServerMap, ServerMapPoint, stack_rows

_pos = attrgetter("pos")
_desc = attrgetter("descriptor")
_ref_kf = attrgetter("ref_kf")


# S_m_l.to_array() by value (R, t and s as bytes): a handler's S_m_l changes only at a
# merge or correction, and its quaternion (scipy) cost ~0.2 ms on every batch's store.
_S_ARRAYS: dict[bytes, np.ndarray] = {}
_S_ARRAYS_MAX = 1024


def _sim3_array(S: Sim3) -> np.ndarray:
    R, t = S.R, S.t
    if R.dtype != np.float64 or t.dtype != np.float64 or R.shape != (3, 3) or t.shape != (3,):
        return S.to_array()  # not what the bytes key assumes
    key = R.tobytes() + t.tobytes() + np.float64(S.s).tobytes()
    a = _S_ARRAYS.get(key)
    if a is None:
        a = S.to_array()
        if len(_S_ARRAYS) >= _S_ARRAYS_MAX:
            _S_ARRAYS.clear()
        _S_ARRAYS[key] = a
    return a


def write_handler(pipe, h: AgentHandler, new: bool = False, map_agents: bool = True) -> None:
    """``map_agents``: with the map's agent list (``write_handlers`` writes it once)."""
    if new:
        Store.new_agent(pipe, h.agent, h.map_id, time.time_ns())
    st = AgentState(h.map_id, h.S_m_l, h.lam, h.index, h.kf_high, h.camera.to_array())
    Store.put_agent(pipe, h.agent, st, _sim3_array(h.S_m_l))
    if map_agents:
        Store.set_map_agents(pipe, h.map_id, h.smap.agents | {h.agent})


def write_handlers(pipe, handlers: list[AgentHandler]) -> None:
    """``write_handler`` of each, in one MULTI/EXEC: a hash field written twice in it
    ends as its last write, so each agent's state and each map's agent list is written
    once, as the last of them would be (a batch group wrote its map's list 8 times)."""
    last_of_map = {}
    for h in {h.agent: h for h in handlers}.values():
        write_handler(pipe, h, map_agents=False)
    for h in handlers:
        last_of_map[h.map_id] = h
    for h in last_of_map.values():
        Store.set_map_agents(pipe, h.map_id, h.smap.agents | {h.agent})


def kf_state(kf: ServerKeyframe, map_id: str) -> StoredKeyframe:
    """The fields a pose, association or map change rewrites."""
    return StoredKeyframe(kf.agent, kf.id, map_id, kf.T_m_kf, kf.gid, kf.mp, kf.parent,
                          optimized=kf.optimized)  # fmt: skip


def write_kf_state(pipe, kf: ServerKeyframe, map_id: str) -> None:
    Store.set_keyframe_state(pipe, kf_state(kf, map_id))


def write_result(pipe, h: AgentHandler, res: IngestResult, names: dict[int, str],
                 handler: bool = True) -> None:  # fmt: skip
    """Everything ``res`` changed, in the caller's MULTI/EXEC pipeline; ``handler``:
    with the agent's state (else the caller writes it, see ``write_handlers``)."""
    smap = h.smap
    for g in res.new_kfs:
        kf = smap.kfs.get(g)
        if kf is None:
            continue
        src = res.sources[g]
        rec = kf_state(kf, smap.map_id)
        rec.stamp_ns, rec.pred_id, rec.parent_id = kf.stamp_ns, src.pred_id, src.parent_id
        rec.T_pred_kf, rec.T_par_kf, rec.T_l_kf = src.T_pred_kf, src.T_par_kf, kf.T_l_kf
        rec.keypoints, rec.octaves, rec.descriptors = kf.keypoints, kf.octaves, kf.descriptors
        Store.put_keyframe(pipe, rec)
    for g in res.changed_kfs - set(res.new_kfs):
        kf = smap.kfs.get(g)
        if kf is not None:
            write_kf_state(pipe, kf, smap.map_id)
    write_points(pipe, smap, list(res.new_mps) + sorted(res.changed_mps), names)
    delete_points(pipe, res.removed_mps, names)
    Store.put_aliases(pipe, res.aliases)
    if handler:
        write_handler(pipe, h)


def write_points(pipe, smap: ServerMap, gids, names: dict[int, str]) -> None:
    # Grouped by agent with numpy and gathered by map(): a new keyframe brings ~100
    # points, and a Python loop per point was most of this.
    gids = list(gids)
    pts = list(map(smap.mps.get, gids))
    have = np.fromiter(map(is_not, pts, repeat(None)), bool, len(pts))
    g = np.array(gids, np.int64).reshape(-1)
    if not have.all():
        pts, g = list(compress(pts, have.tolist())), g[have]
    ai = agent_index_of(g)
    agents = dict.fromkeys(ai.tolist())  # in order of first appearance
    for a in agents:
        sel = np.nonzero(ai == a)[0] if len(agents) > 1 else np.arange(len(g))
        ps = list(map(pts.__getitem__, sel.tolist()))
        Store.put_points(
            pipe, names[a], local_id_of(g[sel]).tolist(),
            stack_rows(list(map(_pos, ps)), np.float64, 3),
            np.fromiter(map(_ref_kf, ps), np.int64, len(ps)),
            stack_rows(list(map(_desc, ps)), np.uint8, 32),
        )  # fmt: skip


def delete_points(pipe, gids, names: dict[int, str]) -> None:
    by_agent: dict[int, list[int]] = {}
    for g in gids:
        by_agent.setdefault(agent_index_of(g), []).append(local_id_of(g))
    for ai, ids in by_agent.items():
        Store.del_points(pipe, names[ai], ids)


def write_removed_kf(pipe, h: AgentHandler, kf: ServerKeyframe, dead_mps: list[int],
                     names: dict[int, str]) -> None:  # fmt: skip
    Store.remove_keyframe(pipe, kf.agent, kf.id, h.map_id)
    if kf.id in h.removed:
        Store.put_removed(pipe, kf.agent, kf.id, *h.removed[kf.id])
    delete_points(pipe, dead_mps, names)


def load_all(
    store: Store, params: MapperParams, only: set[str] | None = None
) -> tuple[dict[str, ServerMap], dict[str, AgentHandler]]:
    """Rebuild maps, covisibility and agent handlers from Redis (of the maps in
    ``only`` when given: the ones this mapper owns)."""
    maps: dict[str, ServerMap] = {}
    handlers: dict[str, AgentHandler] = {}
    aliases = store.aliases()
    kfs_by_map: dict[str, list] = {}
    for agent in store.agents():
        st = store.agent_state(agent)
        if st is None:
            continue
        map_id = st.map_id
        if only is not None and map_id not in only:
            continue
        smap = maps.setdefault(map_id, ServerMap(map_id))
        ah = AgentHandler(agent, st.index, smap, st.S_m_l, params, st.lam)
        ah.aliases = aliases
        ah.name = st.name or agent
        if st.calib is not None:
            ah.camera = PinholeRadTan.from_array(st.calib)
        for kid, entry in store.removed(agent).items():
            ah.removed[kid] = entry
            smap.culled[ah.kf_gid(kid)] = entry
        handlers[agent] = ah
        smap.mps.update({mp.gid: mp for mp in _points(store, agent, st.index)})
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
    return maps, handlers


def _keyframes(store: Store, agent: str, ah: AgentHandler):
    out = []
    for s in store.keyframes(agent, full=True):
        kf = ServerKeyframe(
            s.gid, agent, s.id, s.stamp_ns, s.T_m_kf, s.T_l_kf, s.keypoints,
            ah.camera.undistort_points(s.keypoints), s.octaves, s.descriptors, s.mp_gids,
        )  # fmt: skip
        kf.optimized = s.optimized
        ah.local_poses[s.id] = kf.T_l_kf
        out.append((kf, s.gparent))
    return out


def _points(store: Store, agent: str, index: int) -> list[ServerMapPoint]:
    ids, rec = store.map_point_records(agent)
    return [
        ServerMapPoint(gid(index, int(i)), r["pos"].copy(), r["desc"].copy(), int(r["ref_g"]))
        for i, r in zip(ids, rec, strict=True)
    ]
