"""The Redis store: every keyframe, map point, map and agent, written incrementally.

Layout (prefix ``hm``; ``{a}`` agent id, ``{m}`` map id, ids are decimal):

    hm:agents                SET   agent ids
    hm:agent:{a}             HASH  map, S_m_l (8 f8: t, q xyzw, s), kf_high, n_kf, n_mp,
                                   first_ns, last_ns
    hm:agent:{a}:kfs         ZSET  stored keyframe ids (score = id)
    hm:agent:{a}:pose        STR   msgpack latest pose in its map frame
    hm:kf:{a}:{id}           HASH  map, stamp, pose (T_m_kf 16 f8), pred, parent, T_pred,
                                   T_par, T_l (the agent's local pose), kp (f4 N x 2),
                                   oct (u1), desc (u1 N x 32), mpids (i8)
    hm:mp:{a}                HASH  map point id -> 64-byte record MP_DTYPE: position in
                                   the map frame (3 f8), anchor keyframe gid (i8), descriptor
                                   (32 u1); one field per point so a batch is one HSET
    hm:maps                  SET   map ids
    hm:map:{m}               HASH  created_ns, agents (comma separated)
    hm:map:{m}:kfs           SET   "a:id" of its keyframes
    hm:poses                 PUBSUB channel of live poses (msgpack), for the API's WebSocket

A batch of keyframes and map points goes in one MULTI/EXEC transaction, so a
mapper killed mid-write leaves either all of it or none, and the ack is sent only
after EXEC returns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import redis

from shared.geometry import Sim3
from shared.messages import packb, unpackb

P = "hm"
POSE_CHANNEL = f"{P}:poses"


def k_agent(a: str) -> str:
    return f"{P}:agent:{a}"


def k_agent_kfs(a: str) -> str:
    return f"{P}:agent:{a}:kfs"


def k_mps(a: str) -> str:
    return f"{P}:mp:{a}"


MP_DTYPE = np.dtype([("pos", "<f8", (3,)), ("ref_g", "<i8"), ("desc", "u1", (32,))])


def k_agent_pose(a: str) -> str:
    return f"{P}:agent:{a}:pose"


def k_kf(a: str, i: int) -> str:
    return f"{P}:kf:{a}:{i}"


def k_map(m: str) -> str:
    return f"{P}:map:{m}"


def k_map_kfs(m: str) -> str:
    return f"{P}:map:{m}:kfs"


def _f8(b: bytes | None, shape: tuple[int, ...]) -> np.ndarray | None:
    if b is None:
        return None
    return np.frombuffer(b, dtype="<f8").reshape(shape).copy()


@dataclass
class StoredKeyframe:
    agent: str
    id: int
    map_id: str
    stamp_ns: int
    T_m_kf: np.ndarray
    pred_id: int
    parent_id: int
    T_pred_kf: np.ndarray
    T_par_kf: np.ndarray
    keypoints: np.ndarray | None = None
    octaves: np.ndarray | None = None
    descriptors: np.ndarray | None = None
    mp_ids: np.ndarray | None = None
    T_l_kf: np.ndarray | None = None


@dataclass
class StoredMapPoint:
    agent: str
    id: int
    map_id: str
    ref_kf: int
    p_ref: np.ndarray
    pos: np.ndarray
    descriptor: np.ndarray | None = None


def connect(url: str) -> redis.Redis:
    return redis.Redis.from_url(url, decode_responses=False, socket_timeout=10)


class Store:
    def __init__(self, r: redis.Redis) -> None:
        self.r = r

    # --- writes (mapper) --------------------------------------------------------
    def pipeline(self) -> redis.client.Pipeline:
        return self.r.pipeline(transaction=True)

    @staticmethod
    def add_agent(pipe, agent: str, map_id: str, S_m_l: Sim3, now_ns: int) -> None:
        pipe.sadd(f"{P}:agents", agent)
        pipe.hset(
            k_agent(agent),
            mapping={"map": map_id, "S_m_l": S_m_l.to_array().astype("<f8").tobytes(),
                     "first_ns": now_ns},
        )  # fmt: skip
        pipe.sadd(f"{P}:maps", map_id)
        pipe.hsetnx(k_map(map_id), "created_ns", now_ns)
        pipe.hset(k_map(map_id), "agents", agent)

    @staticmethod
    def put_keyframe(pipe, kf: StoredKeyframe) -> None:
        fields = {
            "map": kf.map_id,
            "stamp": kf.stamp_ns,
            "pose": np.asarray(kf.T_m_kf, "<f8").tobytes(),
            "pred": kf.pred_id,
            "parent": kf.parent_id,
            "T_pred": np.asarray(kf.T_pred_kf, "<f8").tobytes(),
            "T_par": np.asarray(kf.T_par_kf, "<f8").tobytes(),
        }
        if kf.T_l_kf is not None:
            fields["T_l"] = np.asarray(kf.T_l_kf, "<f8").tobytes()
        if kf.keypoints is not None:
            fields.update(
                kp=np.asarray(kf.keypoints, "<f4").tobytes(),
                oct=np.asarray(kf.octaves, np.uint8).tobytes(),
                desc=np.asarray(kf.descriptors, np.uint8).tobytes(),
            )
        if kf.mp_ids is not None:
            fields["mpids"] = np.asarray(kf.mp_ids, "<i8").tobytes()
        pipe.hset(k_kf(kf.agent, kf.id), mapping=fields)
        pipe.zadd(k_agent_kfs(kf.agent), {str(kf.id): kf.id})
        pipe.sadd(k_map_kfs(kf.map_id), f"{kf.agent}:{kf.id}")
        pipe.hset(k_agent(kf.agent), "last_ns", kf.stamp_ns)

    @staticmethod
    def set_keyframe_pose(pipe, agent: str, kf_id: int, T_m_kf: np.ndarray) -> None:
        pipe.hset(k_kf(agent, kf_id), "pose", np.asarray(T_m_kf, "<f8").tobytes())

    @staticmethod
    def put_points(pipe, agent: str, ids, pos, ref_g, desc) -> None:
        """Map points of one agent in one HSET (records of MP_DTYPE)."""
        if len(ids) == 0:
            return
        rec = np.empty(len(ids), MP_DTYPE)
        rec["pos"] = pos
        rec["ref_g"] = ref_g
        rec["desc"] = desc
        raw = rec.tobytes()
        n = MP_DTYPE.itemsize
        pipe.hset(k_mps(agent), mapping={int(i): raw[j * n : (j + 1) * n]
                                         for j, i in enumerate(ids)})  # fmt: skip

    @staticmethod
    def del_points(pipe, agent: str, ids) -> None:
        if len(ids):
            pipe.hdel(k_mps(agent), *[int(i) for i in ids])

    @staticmethod
    def set_kf_high(pipe, agent: str, kf_high: int) -> None:
        pipe.hset(k_agent(agent), "kf_high", kf_high)

    def put_pose(self, agent: str, pose: dict) -> None:
        data = packb(pose)
        p = self.r.pipeline(transaction=False)
        p.set(k_agent_pose(agent), data)
        p.publish(POSE_CHANNEL, data)
        p.execute()

    # --- reads -------------------------------------------------------------------
    def agents(self) -> list[str]:
        return sorted(a.decode() for a in self.r.smembers(f"{P}:agents"))

    def agent_info(self, agent: str) -> dict | None:
        h = self.r.hgetall(k_agent(agent))
        if not h:
            return None
        S = Sim3.from_array(_f8(h[b"S_m_l"], (8,))) if b"S_m_l" in h else Sim3.identity()
        return {
            "agent": agent,
            "map_id": h.get(b"map", b"").decode(),
            "S_m_l": S,
            "kf_high": int(h.get(b"kf_high", -1)),
            "n_kf": int(self.r.zcard(k_agent_kfs(agent))),
            "n_mp": int(self.r.hlen(k_mps(agent))),
            "first_ns": int(h.get(b"first_ns", 0)),
            "last_ns": int(h.get(b"last_ns", 0)),
        }

    def latest_pose(self, agent: str) -> dict | None:
        b = self.r.get(k_agent_pose(agent))
        return None if b is None else unpackb(b)

    def keyframe_ids(self, agent: str) -> list[int]:
        return [int(x) for x in self.r.zrange(k_agent_kfs(agent), 0, -1)]

    def mappoint_ids(self, agent: str) -> list[int]:
        return sorted(int(x) for x in self.r.hkeys(k_mps(agent)))

    def keyframes(self, agent: str, ids: list[int] | None = None, full: bool = False):
        ids = self.keyframe_ids(agent) if ids is None else ids
        names = [b"map", b"stamp", b"pose", b"pred", b"parent", b"T_pred", b"T_par", b"T_l"]
        if full:
            names += [b"kp", b"oct", b"desc", b"mpids"]
        p = self.r.pipeline(transaction=False)
        for i in ids:
            p.hmget(k_kf(agent, i), names)
        out: list[StoredKeyframe] = []
        for i, vals in zip(ids, p.execute(), strict=True):
            if vals[0] is None:
                continue
            kf = StoredKeyframe(
                agent, i, vals[0].decode(), int(vals[1]), _f8(vals[2], (4, 4)),
                int(vals[3]), int(vals[4]), _f8(vals[5], (4, 4)), _f8(vals[6], (4, 4)),
                T_l_kf=_f8(vals[7], (4, 4)),
            )  # fmt: skip
            if full and vals[8] is not None:
                kf.keypoints = np.frombuffer(vals[8], "<f4").reshape(-1, 2).copy()
                kf.octaves = np.frombuffer(vals[9], np.uint8).copy()
                kf.descriptors = np.frombuffer(vals[10], np.uint8).reshape(-1, 32).copy()
                kf.mp_ids = np.frombuffer(vals[11], "<i8").copy()
            out.append(kf)
        return out

    def map_point_records(self, agent: str) -> tuple[np.ndarray, np.ndarray]:
        """(ids, records of MP_DTYPE) of an agent's map points, sorted by id."""
        h = self.r.hgetall(k_mps(agent))
        if not h:
            return np.zeros(0, np.int64), np.zeros(0, MP_DTYPE)
        ids = np.array([int(k) for k in h], np.int64)
        rec = np.frombuffer(b"".join(h.values()), MP_DTYPE)
        order = np.argsort(ids)
        return ids[order], rec[order]

    def map_points(self, agent: str) -> list[StoredMapPoint]:
        info = self.agent_info(agent)
        map_id = info["map_id"] if info else ""
        ids, rec = self.map_point_records(agent)
        return [
            StoredMapPoint(agent, int(i), map_id, int(r["ref_g"]) & ((1 << 40) - 1),
                           np.zeros(3), r["pos"].copy(), r["desc"].copy())
            for i, r in zip(ids, rec, strict=True)
        ]  # fmt: skip

    def trajectory(self, agent: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, stamps_ns, T_m_kf) of the agent's stored keyframes, sorted by id."""
        kfs = self.keyframes(agent)
        if not kfs:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4, 4))
        return (
            np.array([k.id for k in kfs], np.int64),
            np.array([k.stamp_ns for k in kfs], np.int64),
            np.stack([k.T_m_kf for k in kfs]),
        )

    def maps(self) -> list[str]:
        return sorted(m.decode() for m in self.r.smembers(f"{P}:maps"))

    def map_info(self, map_id: str) -> dict | None:
        h = self.r.hgetall(k_map(map_id))
        if not h:
            return None
        members = [m.decode() for m in self.r.smembers(k_map_kfs(map_id))]
        agents = sorted(
            {m.split(":", 1)[0] for m in members}
            | set(a for a in h.get(b"agents", b"").decode().split(",") if a)
        )
        return {
            "map_id": map_id,
            "created_ns": int(h.get(b"created_ns", 0)),
            "agents": agents,
            "n_kf": len(members),
            # Set when the map was fused into another (CCM-SLAM §4.8); it holds nothing then.
            "merged_into": h[b"merged_into"].decode() if b"merged_into" in h else None,
        }

    def map_keyframes(self, map_id: str) -> list[tuple[str, int]]:
        out = []
        for m in self.r.smembers(k_map_kfs(map_id)):
            a, _, i = m.decode().rpartition(":")
            out.append((a, int(i)))
        return sorted(out)
