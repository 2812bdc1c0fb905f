"""The Redis store: the one owner of every key and field HiveMap keeps in Redis.

The mapper writes, the API and the CLIs read; nothing else names a key. Layout (prefix
``hm``; ``{a}`` agent id, ``{m}`` map id, ids decimal, gids as in ``shared.ids``,
matrices little-endian float64 row-major):

    hm:agents                SET   agent ids (the ids keyframes are stored under: one
                                   per flight, see hm:flights)
    hm:agent_index           HASH  agent -> its index, the high bits of its gids
    hm:agent_index_next      STR   counter that hands out agent indices
    hm:agent:{a}             HASH  map, S_m_l (8 f8: t, q xyzw, s: agent's local frame ->
                                   map), lam (repr float: scale correction of its VO,
                                   CSfM eq. 2-4), index, kf_high (every keyframe id below
                                   it is stored), calib (10 f8: w, h, fx, fy, cx, cy,
                                   k1, k2, p1, p2), first_ns (first contact);
                                   name (the agent id it flies as), session, flight
                                   (1, 2, ...): set when the flight is named (absent:
                                   stored before sessions, name is {a}, flight 1)
    hm:agent:{a}:sessions    HASH  session (the agent process's random id, in its
                                   batches) -> the agent id that flight of agent {a}
                                   is stored under: {a} for its first, {a}.s2, {a}.s3,
                                   ... for later ones (services/mapper/sessions.py)
    hm:flights               HASH  stored agent id -> the agent id it flies as; an id is
                                   given to one flight only
    hm:agent:{a}:kfs         ZSET  stored keyframe ids (score = id)
    hm:agent:{a}:removed     HASH  culled keyframe id -> msgpack [anchor gid, T_anchor_kf
                                   (4x4 f8 array)]: registration chains through it
    hm:agent:{a}:pose        STR   msgpack LivePose: the newest pose in its map frame
    hm:kf:{a}:{id}           HASH  written once: stamp, pred, parent (agent keyframe ids,
                                   -1 none), T_pred, T_par (16 f8 each), T_l (pose in the
                                   agent's local map), kp (f4 N x 2 distorted pixels),
                                   oct (u1 N), desc (u1 N x 32);
                                   rewritten on every change by the server: map, gid,
                                   pose (T_m_kf), mpg (i8 N: map-point gid per keypoint,
                                   -1 none), gparent (spanning-tree parent gid, -1 none),
                                   opt (1: an optimization, global or windowed, settled
                                   it; absent in stores written before 2026-11-26)
    hm:mp:{a}                HASH  map point id -> 64-byte record MP_DTYPE: position in
                                   the map frame (3 f8), anchor keyframe gid (i8), descriptor
                                   (32 u1); one field per point so a batch is one HSET
    hm:alias                 HASH  fused-away point gid -> surviving gid
    hm:maps                  SET   live map ids (a merged map leaves it)
    hm:map:{m}               HASH  created_ns, agents (comma separated), merged_into (set
                                   when the map was fused into that map, CCM-SLAM §4.8:
                                   it holds nothing then), merge_scale (repr float: the
                                   scale that merge applied to its units; absent in
                                   stores written before 2026-11-29)
    hm:retired               SET   map ids that were merged into another map
    hm:map:{m}:kfs           SET   "a:id" of its keyframes
    hm:map:{m}:loops         HASH  "q:c" (keyframe gids) -> S_q_c (16 f8): a loop
                                   constraint, the Sim(3) mapping keyframe c's camera
                                   frame into q's (the pose graph's loop edges)
    hm:poses                 PUBSUB channel of live poses (msgpack LivePose), for the
                                   API's WebSocket

Keys of the protocols that coordinate through the same Redis: each is built here (the
``k_*`` functions and ``K_*`` names below) and used by the module named, which explains
the protocol.

Map ownership (``shared/leases.py``; a Redis Cluster keeps one map's keys on one shard
if map keys use the hash tag ``{m}``, see the README):

    hm:lease:{m}             STR   "owner token", expires after the lease time unless
                                   renewed
    hm:fence:{m}             STR   the map's fencing counter: the token of its latest
                                   taking

Several mappers (``services/mapper/ownership.py``):

    hm:mappers               HASH  mapper id -> JSON {t: unix ms, agents, maps}: live
                                   mappers and their load, rewritten every renewal
    hm:assign                HASH  new agent -> the mapper it was assigned to
    hm:assigned              HASH  mapper id -> agents assigned to it
    hm:handover:{m}          STR   the mapper id that asked for map m; expires after 10
                                   leases

The optimization job queue the optimizer pool reads (``shared/jobs.py``):

    hm:opt:jobs              STREAM entries {map, data: encoded OptimizeRequest}; group
                                   "optimizers"; an entry is deleted once acknowledged
    hm:opt:latest            HASH  map -> id of its newest job (an older one is stale)
    hm:opt:restarts          HASH  map -> runs of it abandoned in a row for a newer copy
    hm:opt:taken             HASH  consumer -> jobs it took (claims included)
    hm:opt:workers           HASH  consumer -> unix ms it last said it was alive (every
                                   claim_idle_s / 4; for people and tests, nothing
                                   relies on it)
    hm:opt:applied:{job}     STR   set once by the mapper that applied the job's
                                   correction; expires after a day

A batch of keyframes and map points goes in one MULTI/EXEC transaction (the writers
take the caller's ``pipeline()``), so a mapper killed mid-write leaves either all of it
or none, and the ack is sent only after EXEC returns.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import redis

from shared.geometry import Sim3
from shared.ids import local_id_of
from shared.messages import DecodeError, packb, unpackb

_P = "hm"
POSE_CHANNEL = f"{_P}:poses"
_AGENTS, _MAPS, _ALIAS = f"{_P}:agents", f"{_P}:maps", f"{_P}:alias"
_AGENT_INDEX, _AGENT_INDEX_NEXT = f"{_P}:agent_index", f"{_P}:agent_index_next"
_RETIRED = f"{_P}:retired"

MP_DTYPE = np.dtype([("pos", "<f8", (3,)), ("ref_g", "<i8"), ("desc", "u1", (32,))])


# KEYS: hm:agent:{a}:sessions, hm:flights, hm:agents, hm:agent:{a}:kfs,
# hm:agent:{a}:removed. ARGV: a, session, "hm:agent:" (the new name's hash gets name,
# session and flight in the same step). The name of a new flight: {a} for the first,
# else {a}.sN with N its flight number, skipping names another flight or agent holds;
# {a} itself is skipped when it names a flight already or holds keyframes (stored by an
# agent from before sessions: that data is its flight 1), not for an agent registered
# without any (a handler made ahead of the flight). A suffixed name is cut to 60
# characters, so its map id ("map-" + name) is a valid id.
_NAME_FLIGHT = """
local got = redis.call('HGET', KEYS[1], ARGV[2])
if got then return got end
local e = 1
while true do
  local name = ARGV[1]
  if e > 1 then
    local suffix = '.s' .. e
    name = string.sub(ARGV[1], 1, 60 - #suffix) .. suffix
  end
  local taken = redis.call('HEXISTS', KEYS[2], name) == 1
  if e == 1 then
    taken = taken or redis.call('EXISTS', KEYS[4], KEYS[5]) > 0
  else
    taken = taken or redis.call('SISMEMBER', KEYS[3], name) == 1
  end
  if not taken then
    redis.call('HSET', KEYS[2], name, ARGV[1])
    redis.call('HSET', KEYS[1], ARGV[2], name)
    redis.call('HSET', ARGV[3] .. name, 'name', ARGV[1], 'session', ARGV[2], 'flight', e)
    return name
  end
  e = e + 1
end
"""
_FLIGHTS = f"{_P}:flights"


def _k(*parts: object) -> str:
    """``hm:part:part...``: every key of the layout above is built here."""
    return ":".join((_P, *map(str, parts)))


# Map ownership (shared/leases.py).
def k_lease(map_id: str) -> str:
    return _k("lease", map_id)


def k_fence(map_id: str) -> str:
    return _k("fence", map_id)


# Several mappers (services/mapper/ownership.py).
K_MAPPERS, K_ASSIGN, K_ASSIGNED = _k("mappers"), _k("assign"), _k("assigned")


def k_handover(map_id: str) -> str:
    return _k("handover", map_id)


# The optimization job queue (shared/jobs.py).
K_OPT_JOBS, K_OPT_LATEST, K_OPT_RESTARTS = (_k("opt", x) for x in ("jobs", "latest", "restarts"))
K_OPT_TAKEN, K_OPT_WORKERS = _k("opt", "taken"), _k("opt", "workers")


def k_opt_applied(job: str) -> str:
    return _k("opt", "applied", job)


def k_opt_data(token: str) -> str:
    """A large job's map copy, written in slices (``JobQueue.submit``)."""
    return _k("opt", "data", token)


def _f8(b: bytes | None, shape: tuple[int, ...]) -> np.ndarray | None:
    if b is None:
        return None
    return np.frombuffer(b, dtype="<f8").reshape(shape).copy()


def _b8(a: np.ndarray) -> bytes:
    return np.asarray(a, "<f8").tobytes()


@dataclass
class LivePose:
    """An agent's live camera pose placed in its server map (``hm:agent:{a}:pose`` and
    the ``hm:poses`` channel)."""

    agent: str
    map_id: str
    stamp_ns: int
    T_m_c: np.ndarray  # (4, 4) camera to map
    kf_ref: int  # the agent keyframe it was placed through
    tracking: str  # ok | lost | init
    fps: float
    recv_ns: int

    def encode(self) -> bytes:
        return packb(asdict(self))

    @staticmethod
    def decode(data: bytes) -> LivePose:
        d = unpackb(data)
        if not isinstance(d, dict):
            raise DecodeError("live pose: expected a map")
        try:
            T = np.asarray(d["T_m_c"], np.float64).reshape(4, 4)
            return LivePose(
                str(d["agent"]), str(d["map_id"]), int(d["stamp_ns"]), T, int(d["kf_ref"]),
                str(d["tracking"]), float(d["fps"]), int(d["recv_ns"]),
            )  # fmt: skip
        except (KeyError, TypeError, ValueError, OverflowError) as e:  # int(inf): Overflow
            raise DecodeError(f"live pose: {type(e).__name__}: {e}") from e


@dataclass
class AgentState:
    """What the mapper keeps of an agent (``hm:agent:{a}``)."""

    map_id: str
    S_m_l: Sim3
    lam: float
    index: int
    kf_high: int
    calib: np.ndarray | None = None  # (10,), see the layout
    name: str | None = None  # the agent id it flies as (read only: set with its flight)


@dataclass
class StoredKeyframe:
    """One ``hm:kf:{a}:{id}``. The server-map state (``map_id`` to ``gparent``) is
    rewritten on every change; the rest is written once and None where not read."""

    agent: str
    id: int
    map_id: str
    T_m_kf: np.ndarray
    gid: int = -1
    mp_gids: np.ndarray | None = None
    gparent: int = -1
    stamp_ns: int = 0
    pred_id: int = -1
    parent_id: int = -1
    T_pred_kf: np.ndarray | None = None
    T_par_kf: np.ndarray | None = None
    T_l_kf: np.ndarray | None = None
    keypoints: np.ndarray | None = None
    octaves: np.ndarray | None = None
    descriptors: np.ndarray | None = None
    optimized: bool = False  # an optimization settled it (corrections are fitted on these)


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
        self._name_flight = r.register_script(_NAME_FLIGHT)

    def ping(self) -> bool:
        return bool(self.r.ping())

    def close(self) -> None:
        self.r.close()

    # --- writes (mapper) ------------------------------------------------------------
    def pipeline(self) -> redis.client.Pipeline:
        return self.r.pipeline(transaction=True)

    def agent_index(self, agent: str) -> int:
        """The agent's index, handed out on first call (atomic across processes)."""
        v = self.r.hget(_AGENT_INDEX, agent)
        if v is not None:
            return int(v)
        n = int(self.r.incr(_AGENT_INDEX_NEXT))
        self.r.hsetnx(_AGENT_INDEX, agent, n)
        return int(self.r.hget(_AGENT_INDEX, agent))

    def flight(self, agent: str, session: int) -> str:
        """The agent id the flight ``session`` of ``agent`` is stored under, named on
        first call (atomic across mappers; see ``_NAME_FLIGHT``)."""
        ks = [_k("agent", agent, "sessions"), _FLIGHTS, _AGENTS, _k("agent", agent, "kfs"),
              _k("agent", agent, "removed")]  # fmt: skip
        got = self._name_flight(keys=ks, args=[agent, str(session), _k("agent", "")])
        return got.decode() if isinstance(got, bytes) else got

    def flight_of(self, agent: str, session: int) -> str | None:
        """The agent id of flight ``session`` of ``agent`` if it is named yet (a read)."""
        got = self.r.hget(_k("agent", agent, "sessions"), str(session))
        return None if got is None else got.decode()

    @staticmethod
    def new_agent(pipe, agent: str, map_id: str, now_ns: int) -> None:
        pipe.sadd(_AGENTS, agent)
        pipe.hset(_k("agent", agent), "first_ns", now_ns)
        Store.new_map(pipe, map_id, now_ns)

    @staticmethod
    def new_map(pipe, map_id: str, now_ns: int) -> None:
        pipe.sadd(_MAPS, map_id)
        pipe.hsetnx(_k("map", map_id), "created_ns", now_ns)

    @staticmethod
    def put_agent(pipe, agent: str, st: AgentState, S_m_l_array: np.ndarray | None = None
                  ) -> None:  # fmt: skip
        """``S_m_l_array``: ``st.S_m_l.to_array()`` if the caller has it (its quaternion
        costs ~0.2 ms, and the mapper writes an agent's state with every batch)."""
        S = st.S_m_l.to_array() if S_m_l_array is None else S_m_l_array
        fields = {"map": st.map_id, "S_m_l": _b8(S),
                  "lam": repr(float(st.lam)), "index": st.index, "kf_high": st.kf_high}  # fmt: skip
        if st.calib is not None:
            fields["calib"] = _b8(st.calib)
        pipe.hset(_k("agent", agent), mapping=fields)

    @staticmethod
    def set_map_agents(pipe, map_id: str, agents) -> None:
        pipe.hset(_k("map", map_id), "agents", ",".join(sorted(agents)))

    @staticmethod
    def put_keyframe(pipe, kf: StoredKeyframe) -> None:
        """A new keyframe, every field, and its entries in the agent's and map's sets."""
        # One HSET with the state's fields too (they are distinct): a command less per
        # keyframe in the batch's transaction, the same hash after it.
        fields = Store._state_fields(kf) | {
            "stamp": kf.stamp_ns, "pred": kf.pred_id, "parent": kf.parent_id,
            "T_pred": _b8(kf.T_pred_kf), "T_par": _b8(kf.T_par_kf), "T_l": _b8(kf.T_l_kf),
            "kp": np.asarray(kf.keypoints, "<f4").tobytes(),
            "oct": np.asarray(kf.octaves, np.uint8).tobytes(),
            "desc": np.asarray(kf.descriptors, np.uint8).tobytes(),
        }  # fmt: skip
        pipe.hset(_k("kf", kf.agent, kf.id), mapping=fields)
        pipe.zadd(_k("agent", kf.agent, "kfs"), {str(kf.id): kf.id})
        Store.add_map_keyframe(pipe, kf.map_id, kf.agent, kf.id)

    @staticmethod
    def set_keyframe_state(pipe, kf: StoredKeyframe) -> None:
        """The fields a pose, association or map change rewrites."""
        pipe.hset(_k("kf", kf.agent, kf.id), mapping=Store._state_fields(kf))

    @staticmethod
    def _state_fields(kf: StoredKeyframe) -> dict:
        return {
            "map": kf.map_id, "gid": kf.gid, "pose": _b8(kf.T_m_kf),
            "mpg": np.asarray(kf.mp_gids, "<i8").tobytes(), "gparent": kf.gparent,
            "opt": int(kf.optimized),
        }  # fmt: skip

    @staticmethod
    def set_keyframe_parent(pipe, agent: str, kf_id: int, gparent: int) -> None:
        pipe.hset(_k("kf", agent, kf_id), "gparent", gparent)

    @staticmethod
    def add_map_keyframe(pipe, map_id: str, agent: str, kf_id: int) -> None:
        pipe.sadd(_k("map", map_id, "kfs"), f"{agent}:{kf_id}")

    @staticmethod
    def remove_keyframe(pipe, agent: str, kf_id: int, map_id: str) -> None:
        pipe.delete(_k("kf", agent, kf_id))
        pipe.zrem(_k("agent", agent, "kfs"), str(kf_id))
        pipe.srem(_k("map", map_id, "kfs"), f"{agent}:{kf_id}")

    @staticmethod
    def put_removed(pipe, agent: str, kf_id: int, anchor_gid: int, T_anchor_kf) -> None:
        """A culled keyframe's anchor, so registration can still chain through it."""
        pipe.hset(_k("agent", agent, "removed"), str(kf_id), packb([int(anchor_gid), T_anchor_kf]))

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
        pipe.hset(_k("mp", agent), mapping={int(i): raw[j * n : (j + 1) * n]
                                          for j, i in enumerate(ids)})  # fmt: skip

    @staticmethod
    def del_points(pipe, agent: str, ids) -> None:
        if len(ids):
            pipe.hdel(_k("mp", agent), *[int(i) for i in ids])

    @staticmethod
    def put_aliases(pipe, aliases: dict[int, int]) -> None:
        if aliases:
            pipe.hset(_ALIAS, mapping={str(d): str(k) for d, k in aliases.items()})

    @staticmethod
    def put_loops(pipe, map_id: str, loops) -> None:
        """Loop constraints ``(q, c, S_q_c)`` of a map."""
        for q, c, S in loops:
            pipe.hset(_k("map", map_id, "loops"), f"{q}:{c}", _b8(S))

    @staticmethod
    def retire_map(pipe, source: str, target: str, scale: float) -> None:
        """``source`` was fused into ``target`` (whose writes carry its keyframes), its
        units scaled by ``scale``."""
        pipe.hset(_k("map", source), mapping={"merged_into": target, "agents": "",
                                              "merge_scale": repr(float(scale))})  # fmt: skip
        pipe.srem(_MAPS, source)
        pipe.sadd(_RETIRED, source)
        pipe.delete(_k("map", source, "kfs"), _k("map", source, "loops"))

    def put_pose(self, pose: LivePose) -> None:
        self.put_poses([pose])

    def put_poses(self, poses: list[LivePose]) -> None:
        """Agents' newest live poses, all in one round trip."""
        if not poses:
            return
        p = self.r.pipeline(transaction=False)
        for pose in poses:
            data = pose.encode()
            p.set(_k("agent", pose.agent, "pose"), data)
            p.publish(POSE_CHANNEL, data)
        p.execute()

    # --- reads (mapper restart) ------------------------------------------------------
    def agent_names(self) -> dict[int, str]:
        """Agent index -> agent id."""
        return {int(v): k.decode() for k, v in self.r.hgetall(_AGENT_INDEX).items()}

    def agent_state(self, agent: str) -> AgentState | None:
        h = self.r.hgetall(_k("agent", agent))
        if not h or b"index" not in h:
            return None
        return AgentState(
            h[b"map"].decode(), Sim3.from_array(_f8(h[b"S_m_l"], (8,))),
            float(h.get(b"lam", 1.0)), int(h[b"index"]), int(h.get(b"kf_high", -1)),
            _f8(h.get(b"calib"), (10,)), h.get(b"name", agent.encode()).decode(),
        )  # fmt: skip

    def removed(self, agent: str) -> dict[int, tuple[int, np.ndarray]]:
        """Culled keyframe id -> (anchor gid, T_anchor_kf)."""
        out = {}
        for kid, v in self.r.hgetall(_k("agent", agent, "removed")).items():
            g, T = unpackb(v)
            out[int(kid)] = (int(g), np.array(T))
        return out

    def aliases(self) -> dict[int, int]:
        return {int(k): int(v) for k, v in self.r.hgetall(_ALIAS).items()}

    def loops(self, map_id: str) -> list[tuple[int, int, np.ndarray]]:
        out = []
        for field, v in self.r.hgetall(_k("map", map_id, "loops")).items():
            q, c = (int(x) for x in field.decode().split(":"))
            out.append((q, c, _f8(v, (4, 4))))
        return out

    # --- reads -------------------------------------------------------------------
    def agents(self) -> list[str]:
        return sorted(a.decode() for a in self.r.smembers(_AGENTS))

    def agent_info(self, agent: str) -> dict | None:
        h = self.r.hgetall(_k("agent", agent))
        if not h:
            return None
        S = Sim3.from_array(_f8(h[b"S_m_l"], (8,))) if b"S_m_l" in h else Sim3.identity()
        return {
            "agent": agent,
            "map_id": h.get(b"map", b"").decode(),
            "S_m_l": S,
            "kf_high": int(h.get(b"kf_high", -1)),
            "n_kf": int(self.r.zcard(_k("agent", agent, "kfs"))),
            "n_mp": int(self.r.hlen(_k("mp", agent))),
            "first_ns": int(h.get(b"first_ns", 0)),
            "name": h.get(b"name", agent.encode()).decode(),
            "flight": int(h.get(b"flight", 1)),
        }

    def latest_pose(self, agent: str) -> LivePose | None:
        b = self.r.get(_k("agent", agent, "pose"))
        return None if b is None else LivePose.decode(b)

    def keyframe_ids(self, agent: str) -> list[int]:
        return [int(x) for x in self.r.zrange(_k("agent", agent, "kfs"), 0, -1)]

    def mappoint_ids(self, agent: str) -> list[int]:
        return sorted(int(x) for x in self.r.hkeys(_k("mp", agent)))

    def keyframes(self, agent: str, ids: list[int] | None = None, full: bool = False):
        """The agent's stored keyframes (``ids``, default all), sorted by id. Without
        ``full`` only the pose graph (map, stamp, poses, pred/parent); with it also
        the server-map state and keypoints (the mapper's restart)."""
        ids = self.keyframe_ids(agent) if ids is None else ids
        names = [b"map", b"stamp", b"pose", b"pred", b"parent", b"T_pred", b"T_par", b"T_l"]
        if full:
            names += [b"gid", b"mpg", b"gparent", b"kp", b"oct", b"desc", b"opt"]
        p = self.r.pipeline(transaction=False)
        for i in ids:
            p.hmget(_k("kf", agent, i), names)
        out: list[StoredKeyframe] = []
        for i, v in zip(ids, p.execute(), strict=True):
            if v[0] is None:
                continue
            kf = StoredKeyframe(
                agent, i, v[0].decode(), _f8(v[2], (4, 4)), stamp_ns=int(v[1]),
                pred_id=int(v[3]), parent_id=int(v[4]), T_pred_kf=_f8(v[5], (4, 4)),
                T_par_kf=_f8(v[6], (4, 4)), T_l_kf=_f8(v[7], (4, 4)),
            )  # fmt: skip
            if full:
                kf.gid, kf.gparent = int(v[8]), int(v[10])
                kf.mp_gids = np.frombuffer(v[9], "<i8").copy()
                kf.keypoints = np.frombuffer(v[11], "<f4").reshape(-1, 2).copy()
                kf.octaves = np.frombuffer(v[12], np.uint8).copy()
                kf.descriptors = np.frombuffer(v[13], np.uint8).reshape(-1, 32).copy()
                kf.optimized = v[14] is not None and int(v[14]) == 1  # absent: stored before
            out.append(kf)
        return out

    def map_point_records(self, agent: str) -> tuple[np.ndarray, np.ndarray]:
        """(ids, records of MP_DTYPE) of an agent's map points, sorted by id."""
        h = self.r.hgetall(_k("mp", agent))
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
            StoredMapPoint(agent, int(i), map_id, int(local_id_of(int(r["ref_g"]))),
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
        return sorted(m.decode() for m in self.r.smembers(_MAPS))

    def merges(self) -> dict[str, tuple[str, float | None]]:
        """Every merge stored: retired map -> (the map it was merged into, the scale
        applied to its units, None when stored before scales were)."""
        ids = sorted(m.decode() for m in self.r.smembers(_RETIRED))
        pipe = self.r.pipeline(transaction=False)
        for m in ids:
            pipe.hmget(_k("map", m), "merged_into", "merge_scale")
        out = {}
        for m, (into, scale) in zip(ids, pipe.execute(), strict=True):
            if into is not None:
                out[m] = (into.decode(), None if scale is None else float(scale))
        return out

    def map_info(self, map_id: str) -> dict | None:
        h = self.r.hgetall(_k("map", map_id))
        if not h:
            return None
        members = [m.decode() for m in self.r.smembers(_k("map", map_id, "kfs"))]
        agents = sorted(
            {m.split(":", 1)[0] for m in members}
            | set(a for a in h.get(b"agents", b"").decode().split(",") if a)
        )
        return {
            "map_id": map_id,
            "created_ns": int(h.get(b"created_ns", 0)),
            "agents": agents,
            "n_kf": len(members),
            "merged_into": h[b"merged_into"].decode() if b"merged_into" in h else None,
        }

    def map_keyframes(self, map_id: str) -> list[tuple[str, int]]:
        out = []
        for m in self.r.smembers(_k("map", map_id, "kfs")):
            a, _, i = m.decode().rpartition(":")
            out.append((a, int(i)))
        return sorted(out)

    # --- reads for the viewer (the API) -----------------------------------------------
    def map_loops(self, map_id: str) -> list[tuple[int, int]]:
        """(query gid, candidate gid) of every loop edge of ``map_id``, without reading
        the constraints themselves."""
        out = []
        for f in self.r.hkeys(_k("map", map_id, "loops")):
            q, _, c = f.decode().partition(":")
            out.append((int(q), int(c)))
        return sorted(out)

    def agents_by_index(self) -> dict[int, str]:
        """Agent index (the high bits of its gids, ``shared.ids``) -> agent id."""
        return {int(v): k.decode() for k, v in self.r.hgetall(_AGENT_INDEX).items()}

    def point_sample(self, agent: str, cap: int) -> tuple[np.ndarray, int]:
        """((n, 3) map-frame positions, how many there are) of at most ``cap`` of the
        agent's map points: all of them up to ``cap``, else an even selection in id order
        (the same points from one call to the next, so a viewer does not flicker). Past
        ``cap`` only the chosen records are read (ids first): a viewer's refresh must not
        pull every point of a 16-agent team out of Redis."""
        if cap <= 0:
            return np.zeros((0, 3)), int(self.r.hlen(_k("mp", agent)))
        ids = np.sort(np.array([int(x) for x in self.r.hkeys(_k("mp", agent))], np.int64))
        n_total = len(ids)
        if n_total > cap:
            ids = ids[np.linspace(0, n_total - 1, cap).round().astype(np.int64)]
        raw = self.r.hmget(_k("mp", agent), [int(i) for i in ids]) if len(ids) else []
        # A point removed between the two reads is simply left out.
        rec = np.frombuffer(b"".join(b for b in raw if b is not None), MP_DTYPE)
        return np.asarray(rec["pos"], float).reshape(-1, 3), n_total

    def keyframe_poses(self, agent: str) -> tuple[np.ndarray, np.ndarray]:
        """(ids, (n, 4, 4) T_m_kf) of the agent's stored keyframes: only the pose field of
        each, for the viewer's frequent refresh."""
        ids = self.keyframe_ids(agent)
        p = self.r.pipeline(transaction=False)
        for i in ids:
            p.hget(_k("kf", agent, i), "pose")
        keep, poses = [], []
        for i, b in zip(ids, p.execute(), strict=True):
            if b is not None:
                keep.append(i)
                poses.append(np.frombuffer(b, "<f8").reshape(4, 4))
        if not keep:
            return np.zeros(0, np.int64), np.zeros((0, 4, 4))
        return np.array(keep, np.int64), np.stack(poses)
