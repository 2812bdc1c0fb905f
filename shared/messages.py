"""Every HiveMap wire message, encoded with msgpack.

Each message is a map with a ``schema`` entry (``"hivemap.<name>/<version>"``).
Within a version only optional fields are added. numpy arrays travel as
``{"nd": dtype, "shape": [...], "b": raw bytes}``, never as lists, so a 1000-keypoint
keyframe stays about 40 kB and decodes without a Python loop over keypoints.

Decoding never trusts its input: anything malformed raises :class:`DecodeError`
naming what was wrong, which services count and log before dropping the sample.
Conventions for poses: ``T_a_b`` is a 4x4 float64 matrix mapping frame b into a.
Keyframe and map-point ids are integers unique per agent; across agents an id is
the pair (agent, id).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import msgpack
import numpy as np

from shared import keys

_ALLOWED_DTYPES = {"<f8", "<f4", "<i8", "<i4", "|u1", "<u2", "<u4", "|i1", "|b1"}


class DecodeError(ValueError):
    """Bytes that are not a valid HiveMap message."""


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
        return {"nd": a.dtype.str, "shape": list(a.shape), "b": a.tobytes()}
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _object_hook(d: dict) -> Any:
    if "nd" in d and "b" in d:
        dt = d["nd"]
        if dt not in _ALLOWED_DTYPES:
            raise DecodeError(f"array dtype {dt!r} not allowed")
        shape = tuple(int(x) for x in d.get("shape", ()))
        if any(s < 0 for s in shape):
            raise DecodeError("negative array dimension")
        a = np.frombuffer(d["b"], dtype=np.dtype(dt))
        if a.size != math.prod(shape):
            raise DecodeError(f"array of {a.size} items does not fit shape {shape}")
        return a.reshape(shape)
    return d


# The largest binary field a decoder accepts (a bound on what a malformed or hostile
# message can make it allocate). Senders of big messages check against it
# (services/mapper/collab.py: an optimization request of a very large map).
MAX_BIN_BYTES = 64 << 20


def packb(obj: Any) -> bytes:
    return msgpack.packb(obj, default=_default, use_bin_type=True)


# Bytes copied per step of :func:`packb_sliced`.
PACK_SLICE_BYTES = 1 << 20


def _bin_header(n: int) -> bytes:
    """msgpack's header of a bin of ``n`` bytes (the smallest of bin 8/16/32, as packb)."""
    if n < 1 << 8:
        return struct.pack(">BB", 0xC4, n)
    if n < 1 << 16:
        return struct.pack(">BH", 0xC5, n)
    return struct.pack(">BI", 0xC6, n)


def packb_sliced(
    d: dict[str, Any], pause: Callable[[], None], slice_bytes: int = PACK_SLICE_BYTES
) -> bytearray:
    """``packb(d)``, the same bytes, for a map of big arrays (an optimization request):
    made in steps of at most ``slice_bytes`` copied, ``pause`` called between them.

    ``packb`` is one C call that holds the GIL throughout: for the 2700-keyframe,
    330k-point map of 24 agents it held it for over 200 ms per request (a keyframe
    batch's actor, holding its map's lock, waited as long: 432 ms holds of the lock by
    ``_apply_queued`` with 23 ms of its own CPU). Here each array's bytes are read in
    place (no ``tobytes``) and copied a slice at a time into a growing bytearray."""
    packer = msgpack.Packer(default=_default, use_bin_type=True)
    parts: list = [packer.pack_map_header(len(d))]
    for k, v in d.items():
        parts.append(packer.pack(k))
        if not isinstance(v, np.ndarray):
            parts.append(packer.pack(v))
            continue
        # As _default writes it: {"nd": dtype, "shape": [...], "b": bytes}.
        a = np.ascontiguousarray(v)
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
        raw = memoryview(a.reshape(-1).view(np.uint8))
        parts += [packer.pack_map_header(3), packer.pack("nd"), packer.pack(a.dtype.str),
                  packer.pack("shape"), packer.pack(list(a.shape)), packer.pack("b"),
                  _bin_header(len(raw)), raw]  # fmt: skip
    out = bytearray()
    for part in parts:
        mv = memoryview(part)
        for i in range(0, len(mv), slice_bytes):
            out += mv[i : i + slice_bytes]
            if len(mv) > slice_bytes:
                pause()
    return out


def unpackb(data: bytes) -> Any:
    try:
        return msgpack.unpackb(
            data, object_hook=_object_hook, raw=False, strict_map_key=False,
            max_bin_len=MAX_BIN_BYTES, max_str_len=1 << 20, max_array_len=1 << 20,
            max_map_len=1 << 20,
        )  # fmt: skip
    except DecodeError:
        raise
    except Exception as e:  # msgpack raises several unrelated types on bad input
        raise DecodeError(f"not msgpack: {type(e).__name__}: {e}") from e


# --- field validation ---------------------------------------------------------


def _arr(v: Any, name: str, dtype: str, shape: tuple[int | None, ...]) -> np.ndarray:
    if not isinstance(v, np.ndarray):
        raise DecodeError(f"{name}: expected an array")
    if v.dtype != np.dtype(dtype):
        raise DecodeError(f"{name}: dtype {v.dtype} != {dtype}")
    fits = all(s is None or s == d for s, d in zip(shape, v.shape, strict=False))
    if v.ndim != len(shape) or not fits:
        raise DecodeError(f"{name}: shape {v.shape} does not match {shape}")
    return v


# np.allclose(T[3], [0, 0, 0, 1]) with its default tolerances, written out: allclose's
# own overhead was most of a batch's decode (every pose of every keyframe and update).
_HOMOGENEOUS = np.array([0.0, 0.0, 0.0, 1.0])
_HOMOGENEOUS_TOL = 1e-8 + 1e-5 * _HOMOGENEOUS


def _pose(v: Any, name: str) -> np.ndarray:
    T = _arr(v, name, "<f8", (4, 4))
    if not np.isfinite(T).all() or not (np.abs(T[3] - _HOMOGENEOUS) <= _HOMOGENEOUS_TOL).all():
        raise DecodeError(f"{name}: not a finite homogeneous transform")
    return T


def _calib(v: Any) -> np.ndarray:
    c = _arr(v, "calib", "<f8", (10,))
    if not np.all(np.isfinite(c)) or c[0] <= 0 or c[1] <= 0 or c[2] <= 0 or c[3] <= 0:
        raise DecodeError("calib: needs positive size and focal lengths")
    return c


def _opt_ids(d: dict, key: str) -> np.ndarray | None:
    v = d.get(key)
    return None if v is None else _arr(v, key, "<i8", (None,))


def _int(v: Any, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise DecodeError(f"{name}: expected an integer")
    # Every integer is stored as int64 (numpy, Redis): a larger one would overflow there.
    if not -(2**63) <= v < 2**63:
        raise DecodeError(f"{name}: out of the int64 range")
    return v


def _id(v: Any, name: str) -> str:
    """An agent or map id: it becomes part of key expressions and Redis keys."""
    try:
        return keys.check_id(_str(v, name), name)
    except DecodeError:
        raise
    except ValueError as e:
        raise DecodeError(str(e)) from None


def _str(v: Any, name: str) -> str:
    if not isinstance(v, str):
        raise DecodeError(f"{name}: expected a string")
    return v


def _get(d: dict, key: str) -> Any:
    try:
        return d[key]
    except KeyError:
        raise DecodeError(f"missing field {key!r}") from None


# --- compact form ---------------------------------------------------------------
# Added within v1, what agents send (``KeyframeBatch.encode(compact=True)``): keypoints
# as uint16 in 1/KP_QUANT px (half the bytes, at most 1/16 px off, far below the
# keypoints' own noise), ids as int32 where they fit, point positions as float32 (7
# significant digits). Decoding widens either form to the same arrays.
KP_QUANT = 8


def _narrow_ids(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if len(a) and (a.min() < -(1 << 31) or a.max() >= 1 << 31):
        return a
    return a.astype(np.int32)


def _ids(v: Any, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    if isinstance(v, np.ndarray) and v.dtype == np.dtype("<i4"):
        return _arr(v, name, "<i4", shape).astype(np.int64)
    return _arr(v, name, "<i8", shape)


def _keypoints(v: Any) -> np.ndarray:
    if isinstance(v, np.ndarray) and v.dtype == np.dtype("<u2"):
        return _arr(v, "keypoints", "<u2", (None, 2)).astype(np.float32) / KP_QUANT
    return _arr(v, "keypoints", "<f4", (None, 2))


# --- messages -------------------------------------------------------------------


@dataclass
class NewKeyframe:
    """A keyframe sent once, with everything that never changes."""

    id: int
    stamp_ns: int
    T_l_kf: np.ndarray  # pose in the agent's local map; used only to seed a new server map
    pred_id: int  # -1: none (the agent's first keyframe)
    T_pred_kf: np.ndarray
    parent_id: int  # -1: none
    T_par_kf: np.ndarray
    keypoints: np.ndarray  # (N, 2) float32, distorted pixel coordinates
    octaves: np.ndarray  # (N,) uint8 pyramid level
    descriptors: np.ndarray  # (N, 32) uint8, 256-bit ORB
    mp_ids: np.ndarray  # (N,) int64 map point of each keypoint, -1 none
    # Optional (added within v1): w, h, fx, fy, cx, cy, k1, k2, p1, p2 of the camera.
    calib: np.ndarray | None = None

    def to_dict(self, compact: bool = False) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        if d["calib"] is None:
            del d["calib"]
        if compact:
            q = np.rint(np.asarray(self.keypoints, np.float64) * KP_QUANT)
            d["keypoints"] = np.clip(q, 0, 65535).astype(np.uint16)
            d["mp_ids"] = _narrow_ids(self.mp_ids)
        return d

    @staticmethod
    def from_dict(d: dict) -> NewKeyframe:
        if not isinstance(d, dict):
            raise DecodeError("keyframe: expected a map")
        kp = _keypoints(_get(d, "keypoints"))
        n = len(kp)
        return NewKeyframe(
            id=_int(_get(d, "id"), "id"),
            stamp_ns=_int(_get(d, "stamp_ns"), "stamp_ns"),
            T_l_kf=_pose(_get(d, "T_l_kf"), "T_l_kf"),
            pred_id=_int(_get(d, "pred_id"), "pred_id"),
            T_pred_kf=_pose(_get(d, "T_pred_kf"), "T_pred_kf"),
            parent_id=_int(_get(d, "parent_id"), "parent_id"),
            T_par_kf=_pose(_get(d, "T_par_kf"), "T_par_kf"),
            keypoints=kp,
            octaves=_arr(_get(d, "octaves"), "octaves", "|u1", (n,)),
            descriptors=_arr(_get(d, "descriptors"), "descriptors", "|u1", (n, 32)),
            mp_ids=_ids(_get(d, "mp_ids"), "mp_ids", (n,)),
            calib=None if d.get("calib") is None else _calib(d["calib"]),
        )


@dataclass
class KeyframeUpdate:
    """A changed keyframe: new relative poses, and the full association list if it changed."""

    id: int
    pred_id: int
    T_pred_kf: np.ndarray
    parent_id: int
    T_par_kf: np.ndarray
    mp_ids: np.ndarray | None = None

    def to_dict(self, compact: bool = False) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        if compact and self.mp_ids is not None:
            d["mp_ids"] = _narrow_ids(self.mp_ids)
        return d

    @staticmethod
    def from_dict(d: dict) -> KeyframeUpdate:
        if not isinstance(d, dict):
            raise DecodeError("keyframe update: expected a map")
        mp = d.get("mp_ids")
        return KeyframeUpdate(
            id=_int(_get(d, "id"), "id"),
            pred_id=_int(_get(d, "pred_id"), "pred_id"),
            T_pred_kf=_pose(_get(d, "T_pred_kf"), "T_pred_kf"),
            parent_id=_int(_get(d, "parent_id"), "parent_id"),
            T_par_kf=_pose(_get(d, "T_par_kf"), "T_par_kf"),
            mp_ids=None if mp is None else _ids(mp, "mp_ids", (None,)),
        )


@dataclass
class MapPoints:
    """Map points, column-wise. Positions are relative to a reference keyframe
    (``p_ref`` in that keyframe's camera frame), so an optimization on the server
    carries them along (CCM-SLAM Fig. 4). Descriptors only on new points."""

    ids: np.ndarray  # (M,) int64
    ref_kf: np.ndarray  # (M,) int64
    p_ref: np.ndarray  # (M, 3) float64
    descriptors: np.ndarray | None = None  # (M, 32) uint8

    def __len__(self) -> int:
        return len(self.ids)

    @staticmethod
    def empty(with_descriptors: bool = True) -> MapPoints:
        return MapPoints(
            np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)),
            np.zeros((0, 32), np.uint8) if with_descriptors else None,
        )  # fmt: skip

    def to_dict(self, compact: bool = False) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        if compact:
            d["ids"], d["ref_kf"] = _narrow_ids(self.ids), _narrow_ids(self.ref_kf)
            d["p_ref"] = np.asarray(self.p_ref, np.float32)
        return d

    @staticmethod
    def from_dict(d: dict, need_descriptors: bool) -> MapPoints:
        if not isinstance(d, dict):
            raise DecodeError("map points: expected a map")
        ids = _ids(_get(d, "ids"), "mp ids", (None,))
        m = len(ids)
        desc = d.get("descriptors")
        if need_descriptors and desc is None:
            raise DecodeError("new map points need descriptors")
        p = _get(d, "p_ref")
        if isinstance(p, np.ndarray) and p.dtype == np.dtype("<f4"):
            p = _arr(p, "p_ref", "<f4", (m, 3)).astype(np.float64)
        p = _arr(p, "p_ref", "<f8", (m, 3))
        if not np.all(np.isfinite(p)):
            raise DecodeError("p_ref: not finite")
        return MapPoints(
            ids=ids,
            ref_kf=_ids(_get(d, "ref_kf"), "ref_kf", (m,)),
            p_ref=p,
            descriptors=None if desc is None else _arr(desc, "mp descriptors", "|u1", (m, 32)),
        )


@dataclass
class KeyframeBatch:
    """Agent -> mapper on ``hivemap/agent/{agent}/up/kf``: everything new or changed
    since the previous message, keyframes sorted by id (CCM-SLAM §4.5).

    ``session`` (optional, added within v1): the agent process's session, a random id
    drawn when it starts. Keyframe ids are the agent's own small integers, counted from
    0 in every flight, so the server tells a second flight under the same agent id
    from a resend of the first by it (``services/mapper/sessions.py``). None: an agent
    of the first version (its flights all count as one)."""

    SCHEMA: ClassVar[str] = "hivemap.kf_batch/1"
    agent: str
    seq: int
    sent_ns: int
    kf_ref: int
    new_kfs: list[NewKeyframe] = field(default_factory=list)
    kf_updates: list[KeyframeUpdate] = field(default_factory=list)
    new_mps: MapPoints = field(default_factory=MapPoints.empty)
    mp_updates: MapPoints = field(default_factory=lambda: MapPoints.empty(False))
    session: int | None = None

    def encode(self, compact: bool = False) -> bytes:
        """``compact``: the smaller form agents send (see ``KP_QUANT``)."""
        c = compact
        d = {"schema": self.SCHEMA, "agent": self.agent}
        if self.session is not None:
            d["session"] = self.session
        d.update({
            "seq": self.seq,
            "sent_ns": self.sent_ns,
            "kf_ref": self.kf_ref,
            "new_kfs": [k.to_dict(c) for k in self.new_kfs],
            "kf_updates": [u.to_dict(c) for u in self.kf_updates],
            "new_mps": self.new_mps.to_dict(c),
            "mp_updates": self.mp_updates.to_dict(c),
        })  # fmt: skip
        return packb(d)

    @staticmethod
    def decode(data: bytes) -> KeyframeBatch:
        d = _envelope(data, KeyframeBatch.SCHEMA)
        kfs, ups = _get(d, "new_kfs"), _get(d, "kf_updates")
        if not isinstance(kfs, list) or not isinstance(ups, list):
            raise DecodeError("new_kfs and kf_updates must be lists")
        return KeyframeBatch(
            agent=_str(_get(d, "agent"), "agent"),
            seq=_int(_get(d, "seq"), "seq"),
            sent_ns=_int(_get(d, "sent_ns"), "sent_ns"),
            kf_ref=_int(_get(d, "kf_ref"), "kf_ref"),
            new_kfs=[NewKeyframe.from_dict(k) for k in kfs],
            kf_updates=[KeyframeUpdate.from_dict(u) for u in ups],
            new_mps=MapPoints.from_dict(_get(d, "new_mps"), need_descriptors=True),
            mp_updates=MapPoints.from_dict(_get(d, "mp_updates"), need_descriptors=False),
            session=_session(d),
        )


@dataclass
class Ack:
    """Mapper -> agent on ``hivemap/agent/{agent}/down/ack``: ids now stored.

    ``kf_ids``/``mp_ids`` list what was stored since the previous ack; ``kf_high``
    is the highest keyframe id below which every id the server ever saw from
    this agent is stored, so a lost ack is repaired by the next one."""

    SCHEMA: ClassVar[str] = "hivemap.ack/1"
    agent: str
    map_id: str
    kf_ids: np.ndarray
    mp_ids: np.ndarray
    kf_high: int
    sent_ns: int
    # Optional (added within v1): keyframes the server holds because their predecessor
    # and parent are missing, and those missing ones, so the agent resends exactly
    # what blocks registration instead of waiting for its timeout.
    held_kf_ids: np.ndarray | None = None
    missing_kf_ids: np.ndarray | None = None
    # Optional (added within v1): the ``seq`` of the agent's batch this ack answers, -1
    # not said. The agent learns from it which of its (unacknowledged) updates arrived.
    seq: int = -1
    # Optional (added within v1): set, batch ``seq`` was shed by an overloaded server --
    # nothing it carried was taken -- and the agent should send it again, and nothing
    # new, only after this many seconds (back-pressure instead of its resend timeout).
    retry_after_s: float | None = None
    # Optional (added within v1): seconds the server held batch ``seq``, from its arrival
    # to this ack (its queue and its registration): what of the ack latency is the
    # server's, the rest being the link's. The agent's window answers the server's part
    # only (services/agent/comm.py): a long link is not a slow server.
    held_s: float | None = None

    def encode(self) -> bytes:
        d = {
            "schema": self.SCHEMA, "agent": self.agent, "map_id": self.map_id,
            "kf_ids": np.asarray(self.kf_ids, np.int64),
            "mp_ids": np.asarray(self.mp_ids, np.int64),
            "kf_high": self.kf_high, "sent_ns": self.sent_ns,
        }  # fmt: skip
        if self.held_kf_ids is not None and len(self.held_kf_ids):
            d["held_kf_ids"] = np.asarray(self.held_kf_ids, np.int64)
        if self.missing_kf_ids is not None and len(self.missing_kf_ids):
            d["missing_kf_ids"] = np.asarray(self.missing_kf_ids, np.int64)
        if self.seq >= 0:
            d["seq"] = self.seq
        if self.retry_after_s is not None:
            d["retry_after_s"] = float(self.retry_after_s)
        if self.held_s is not None:
            d["held_s"] = float(self.held_s)
        return packb(d)

    @staticmethod
    def decode(data: bytes) -> Ack:
        d = _envelope(data, Ack.SCHEMA)
        return Ack(
            agent=_str(_get(d, "agent"), "agent"),
            map_id=_str(_get(d, "map_id"), "map_id"),
            kf_ids=_arr(_get(d, "kf_ids"), "kf_ids", "<i8", (None,)),
            mp_ids=_arr(_get(d, "mp_ids"), "mp_ids", "<i8", (None,)),
            kf_high=_int(_get(d, "kf_high"), "kf_high"),
            sent_ns=_int(_get(d, "sent_ns"), "sent_ns"),
            held_kf_ids=_opt_ids(d, "held_kf_ids"),
            missing_kf_ids=_opt_ids(d, "missing_kf_ids"),
            seq=_int(d["seq"], "seq") if "seq" in d else -1,
            retry_after_s=_seconds(d.get("retry_after_s"), "retry_after_s"),
            held_s=_seconds(d.get("held_s"), "held_s"),
        )


def _seconds(v: Any, name: str) -> float | None:
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 3600:
        raise DecodeError(f"{name}: expected seconds in [0, 3600]")
    return float(v)


@dataclass
class PoseUpdate:
    """Agent -> all on ``hivemap/agent/{agent}/up/pose``: the live camera pose, small and lossy.

    It also carries the agent's health, since agents are never scraped: the mapper
    exports what they report (``services.mapper.agent_health``). The health fields were
    added within v1 and are optional; counters are cumulative since the agent started,
    so a lost pose message loses nothing."""

    SCHEMA: ClassVar[str] = "hivemap.pose/1"
    HEALTH_INTS: ClassVar[tuple[str, ...]] = (
        "frames_dropped", "kf_lost", "bytes_sent", "resent",
    )  # fmt: skip
    HEALTH_FLOATS: ClassVar[tuple[str, ...]] = ("ack_p50_s", "ack_p95_s")
    agent: str
    stamp_ns: int
    T_l_c: np.ndarray  # in the agent's local map
    kf_ref: int  # -1 before the first keyframe
    T_ref_c: np.ndarray  # relative to kf_ref, so the server places it in its own map
    tracking: str = "ok"  # ok | lost | init
    fps: float = 0.0
    # Health (optional): frames not tracked in time (a live camera would have dropped
    # them), keyframes dropped unacknowledged when the buffer was full, payload bytes
    # sent, keyframes and map points sent again, and the publish -> ack latency of the
    # most recent acknowledged keyframes (median and 95th percentile).
    frames_dropped: int | None = None
    kf_lost: int | None = None
    bytes_sent: int | None = None
    resent: int | None = None
    ack_p50_s: float | None = None
    ack_p95_s: float | None = None
    # Optional (added within v1): the agent's session, as in ``KeyframeBatch``: which of
    # the flights under this agent id ``kf_ref`` belongs to.
    session: int | None = None

    def encode(self) -> bytes:
        d = {
            "schema": self.SCHEMA, "agent": self.agent, "stamp_ns": self.stamp_ns,
            "T_l_c": self.T_l_c, "kf_ref": self.kf_ref, "T_ref_c": self.T_ref_c,
            "tracking": self.tracking, "fps": float(self.fps),
        }  # fmt: skip
        if self.session is not None:
            d["session"] = self.session
        for name in self.HEALTH_INTS:
            if (v := getattr(self, name)) is not None:
                d[name] = int(v)
        for name in self.HEALTH_FLOATS:
            if (v := getattr(self, name)) is not None:
                d[name] = float(v)
        return packb(d)

    @staticmethod
    def decode(data: bytes) -> PoseUpdate:
        d = _envelope(data, PoseUpdate.SCHEMA)
        fps = d.get("fps", 0.0)
        if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps >= 0:
            raise DecodeError("fps: expected a non-negative number")
        health: dict[str, Any] = {}
        for name in PoseUpdate.HEALTH_INTS:
            if (v := d.get(name)) is not None:
                if _int(v, name) < 0:
                    raise DecodeError(f"{name}: negative")
                health[name] = v
        for name in PoseUpdate.HEALTH_FLOATS:
            if (v := d.get(name)) is not None:
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < 1e6:
                    raise DecodeError(f"{name}: expected a non-negative number of seconds")
                health[name] = float(v)
        return PoseUpdate(
            agent=_str(_get(d, "agent"), "agent"),
            stamp_ns=_int(_get(d, "stamp_ns"), "stamp_ns"),
            T_l_c=_pose(_get(d, "T_l_c"), "T_l_c"),
            kf_ref=_int(_get(d, "kf_ref"), "kf_ref"),
            T_ref_c=_pose(_get(d, "T_ref_c"), "T_ref_c"),
            tracking=_str(d.get("tracking", "ok"), "tracking"),
            fps=float(fps),
            session=_session(d),
            **health,
        )


@dataclass
class MapChunk:
    """Mapper -> agent on ``hivemap/agent/{agent}/down/map``: the k keyframes most
    covisible with the agent's KF_ref and their map points, all relative to KF_ref
    in the agent's local scale (CCM-SLAM §4.5), and the correction ``S_g_l`` of the
    agent's VO frame by the server's map (optional; see
    ``services.mapper.feedback.frame_correction``)."""

    SCHEMA: ClassVar[str] = "hivemap.map_chunk/1"
    agent: str
    map_id: str
    kf_ref: int
    kf_agents: list[str]
    kf_ids: np.ndarray  # (K,) int64
    T_ref_kf: np.ndarray  # (K, 4, 4) float64
    kf_keypoints: list[np.ndarray]  # K x (N, 2) float32
    kf_descriptors: list[np.ndarray]  # K x (N, 32) uint8
    kf_mp_index: list[np.ndarray]  # K x (N,) int64 index into the chunk's points, -1 none
    mp_agents: list[str]
    mp_ids: np.ndarray  # (M,) int64
    p_ref: np.ndarray  # (M, 3) float64, in KF_ref's camera frame
    mp_descriptors: np.ndarray  # (M, 32) uint8
    sent_ns: int = 0
    S_g_l: np.ndarray | None = None  # (4, 4) [[s R, t], [0, 1]]: VO frame -> corrected

    def encode(self) -> bytes:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        if self.S_g_l is None:
            del d["S_g_l"]  # optional: peers of the first version never see it
        d["schema"] = self.SCHEMA
        return packb(d)

    @staticmethod
    def decode(data: bytes) -> MapChunk:
        d = _envelope(data, MapChunk.SCHEMA)
        ids = _arr(_get(d, "kf_ids"), "kf_ids", "<i8", (None,))
        k = len(ids)
        mids = _arr(_get(d, "mp_ids"), "mp_ids", "<i8", (None,))
        m = len(mids)
        lists = [_get(d, n) for n in ("kf_agents", "kf_keypoints", "kf_descriptors", "kf_mp_index")]
        if any(not isinstance(x, list) or len(x) != k for x in lists):
            raise DecodeError("per-keyframe lists must match kf_ids")
        mp_agents = _get(d, "mp_agents")
        if not isinstance(mp_agents, list) or len(mp_agents) != m:
            raise DecodeError("mp_agents must match mp_ids")
        return MapChunk(
            agent=_str(_get(d, "agent"), "agent"),
            map_id=_str(_get(d, "map_id"), "map_id"),
            kf_ref=_int(_get(d, "kf_ref"), "kf_ref"),
            kf_agents=[_str(a, "kf_agents") for a in lists[0]],
            kf_ids=ids,
            T_ref_kf=_arr(_get(d, "T_ref_kf"), "T_ref_kf", "<f8", (k, 4, 4)),
            kf_keypoints=[_arr(a, "kf_keypoints", "<f4", (None, 2)) for a in lists[1]],
            kf_descriptors=[_arr(a, "kf_descriptors", "|u1", (None, 32)) for a in lists[2]],
            kf_mp_index=[_arr(a, "kf_mp_index", "<i8", (None,)) for a in lists[3]],
            mp_agents=[_str(a, "mp_agents") for a in mp_agents],
            mp_ids=mids,
            p_ref=_arr(_get(d, "p_ref"), "p_ref", "<f8", (m, 3)),
            mp_descriptors=_arr(_get(d, "mp_descriptors"), "mp_descriptors", "|u1", (m, 32)),
            sent_ns=_int(d.get("sent_ns", 0), "sent_ns"),
            S_g_l=None if d.get("S_g_l") is None else _sim3(d["S_g_l"], "S_g_l"),
        )


def _sim3(v: Any, name: str) -> np.ndarray:
    """A 4x4 similarity [[s R, t], [0, 1]] with a positive scale."""
    S = _pose(v, name)
    A = S[:3, :3]
    det = float(np.linalg.det(A))
    if det <= 0:
        raise DecodeError(f"{name}: not a similarity (det {det:.3g})")
    s = np.cbrt(det)
    if not np.allclose(A.T @ A, s * s * np.eye(3), atol=1e-6 * s * s):
        raise DecodeError(f"{name}: not a similarity (rotation part not orthogonal)")
    return S


# --- server-side collaboration messages ------------------------------------------------
# Column-wise records: every field is a scalar or an array with a fixed dtype, described
# once in ``FIELDS`` so encoding, validation and golden tests share one definition.
# Shapes use None for a free dimension and a field name for "as long as that field".


class _Record:
    SCHEMA: ClassVar[str] = ""
    # name -> ("int" | "str" | "id" | "float" | "dict") or (dtype, shape)
    FIELDS: ClassVar[dict[str, Any]] = {}
    OPTIONAL: ClassVar[tuple[str, ...]] = ()

    def encode(self) -> bytes:
        return packb(self._fields())

    def encode_sliced(self, pause: Callable[[], None]) -> bytearray:
        """``encode()``'s bytes, made in slices with ``pause`` between (:func:`packb_sliced`)."""
        return packb_sliced(self._fields(), pause)

    def _fields(self) -> dict[str, Any]:
        d = {"schema": self.SCHEMA}
        for name in self.FIELDS:
            v = getattr(self, name)
            if v is None and name in self.OPTIONAL:
                continue
            d[name] = v
        return d

    @classmethod
    def decode(cls, data: bytes):
        d = _envelope(data, cls.SCHEMA)
        out: dict[str, Any] = {}
        lengths: dict[str, int] = {}
        for name, spec in cls.FIELDS.items():
            if name not in d and name in cls.OPTIONAL:
                out[name] = None
                continue
            v = _get(d, name)
            if spec == "int":
                out[name] = _int(v, name)
            elif spec == "str":
                out[name] = _str(v, name)
            elif spec == "id":
                out[name] = _id(v, name)
            elif spec == "float":
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    raise DecodeError(f"{name}: expected a number")
                out[name] = float(v)
            elif spec == "dict":
                if not isinstance(v, dict):
                    raise DecodeError(f"{name}: expected a map")
                out[name] = v
            else:
                dtype, shape = spec
                shp = tuple(lengths.get(x, -1) if isinstance(x, str) else x for x in shape)
                if any(x == -1 for x in shp):
                    raise DecodeError(f"{name}: length field missing")
                a = _arr(v, name, dtype, shp)
                if a.dtype.kind == "f" and name not in cls.NAN_OK and not np.all(np.isfinite(a)):
                    raise DecodeError(f"{name}: not finite")
                out[name] = a
                lengths[name] = len(a) if a.ndim else 0
        return cls(**out)

    NAN_OK: ClassVar[tuple[str, ...]] = ()


@dataclass
class KeyframeEvent(_Record):
    """Mapper -> placerec on ``hivemap/map/{map}/kf``: a keyframe was registered. Carries
    what place recognition needs, points in the keyframe's own camera frame (so a later
    map correction does not make them stale) and its covisible neighbours."""

    SCHEMA: ClassVar[str] = "hivemap.kf_event/1"
    FIELDS: ClassVar[dict[str, Any]] = {
        "map_id": "id", "agent": "id", "gid": "int", "kf_id": "int", "stamp_ns": "int",
        "T_m_kf": ("<f8", (4, 4)), "fx": "float",
        "xy": ("<f8", (None, 2)), "octaves": ("|u1", ("xy",)),
        "descriptors": ("|u1", ("xy", 32)), "mp": ("<i8", ("xy",)),
        "p_c": ("<f8", ("xy", 3)), "covis": ("<i8", (None,)),
    }  # fmt: skip
    NAN_OK: ClassVar[tuple[str, ...]] = ("p_c",)
    map_id: str
    agent: str
    gid: int
    kf_id: int
    stamp_ns: int
    T_m_kf: np.ndarray
    fx: float
    xy: np.ndarray  # (N, 2) undistorted normalized coordinates
    octaves: np.ndarray
    descriptors: np.ndarray
    mp: np.ndarray  # (N,) map-point gid per keypoint, -1 none
    p_c: np.ndarray  # (N, 3) map point in this keyframe's camera frame, NaN none
    covis: np.ndarray  # covisible keyframe gids (weight >= 15)


@dataclass
class Match(_Record):
    """Placerec -> mapper on ``hivemap/match``: a verified place match between a query
    keyframe and a candidate (same map: a loop; different maps: a merge).
    ``S_q_c`` maps points in the candidate's camera frame into the query's:
    p_q = s R p_c + t, as the matrix [[sR, t], [0, 1]]."""

    SCHEMA: ClassVar[str] = "hivemap.match/1"
    FIELDS: ClassVar[dict[str, Any]] = {
        "query_map": "id", "query_gid": "int", "cand_map": "id", "cand_gid": "int",
        "S_q_c": ("<f8", (4, 4)), "mp_q": ("<i8", (None,)), "mp_c": ("<i8", ("mp_q",)),
        "inliers": "int", "score": "float", "sent_ns": "int",
    }  # fmt: skip
    query_map: str
    query_gid: int
    cand_map: str
    cand_gid: int
    S_q_c: np.ndarray
    mp_q: np.ndarray  # matched map-point gids, pairwise
    mp_c: np.ndarray
    inliers: int
    score: float
    sent_ns: int


@dataclass
class OptimizeRequest(_Record):
    """Mapper -> optimizer pool as a job on the Redis stream of ``shared/jobs.py``: a
    copy of the map to optimize (CCM-SLAM: the optimization works on a copy so
    ingestion goes on). A newer request for the same map supersedes one in progress.
    The optimizer's algorithms take this message as it is (``services/mapper/capture.py``
    builds it).

    Conventions (every 4x4 is float64):
    - ``T_m_kf``: SE(3), camera to map (``p_m = R p_kf + t``).
    - ``fixed_gids``: gauge keyframes; ``edges``: spanning tree + strong covisibility.
    - ``S_loop[i]`` for loop edge ``loops[i] = (a, b)``: Sim(3) ``S_a_b`` as
      ``[[s R, t], [0, 1]]``, mapping points in keyframe b's camera frame into keyframe
      a's camera frame (``p_a = s R p_b + t``).
    - ``odo[i] = (a, b)`` (optional): the VO's relative pose ``T_odo[i]`` of keyframe b
      in keyframe a's camera (SE(3), map units), with standard deviations
      ``odo_sigma[i]`` (rotation in rad, translation); all three or none.
    - ``mp_ref``: gid of each point's reference keyframe; ``obs_kf``/``obs_mp`` index
      ``kf_gids``/``mp_gids``; ``obs_xy``: undistorted normalized image coordinates;
      ``fx``: focal length in pixels (observation noise is 1.2**octave / fx).
    """

    SCHEMA: ClassVar[str] = "hivemap.optimize/1"
    REASONS: ClassVar[tuple[str, ...]] = ("merge", "loop", "continue")  # why it was asked
    FIELDS: ClassVar[dict[str, Any]] = {
        "map_id": "id", "version": "int", "reason": "str", "sent_ns": "int", "fx": "float",
        "kf_gids": ("<i8", (None,)), "T_m_kf": ("<f8", ("kf_gids", 4, 4)),
        "fixed_gids": ("<i8", (None,)), "edges": ("<i8", (None, 2)),
        "loops": ("<i8", (None, 2)), "S_loop": ("<f8", ("loops", 4, 4)),
        "mp_gids": ("<i8", (None,)), "mp_pos": ("<f8", ("mp_gids", 3)),
        "mp_ref": ("<i8", ("mp_gids",)),
        "obs_kf": ("<i4", (None,)), "obs_mp": ("<i4", ("obs_kf",)),
        "obs_xy": ("<f8", ("obs_kf", 2)), "obs_octave": ("|u1", ("obs_kf",)),
        "odo": ("<i8", (None, 2)), "T_odo": ("<f8", ("odo", 4, 4)),
        "odo_sigma": ("<f8", ("odo", 2)),
    }  # fmt: skip
    # Added within v1: VO relative-pose edges for a windowed BA (reason "local").
    OPTIONAL: ClassVar[tuple[str, ...]] = ("odo", "T_odo", "odo_sigma")
    map_id: str
    version: int
    reason: str
    sent_ns: int
    fx: float
    kf_gids: np.ndarray
    T_m_kf: np.ndarray
    fixed_gids: np.ndarray
    edges: np.ndarray
    loops: np.ndarray
    S_loop: np.ndarray
    mp_gids: np.ndarray
    mp_pos: np.ndarray
    mp_ref: np.ndarray
    obs_kf: np.ndarray
    obs_mp: np.ndarray
    obs_xy: np.ndarray
    obs_octave: np.ndarray
    odo: np.ndarray | None = None
    T_odo: np.ndarray | None = None
    odo_sigma: np.ndarray | None = None

    @property
    def n_kf(self) -> int:
        return len(self.kf_gids)

    def kf_index(self) -> dict[int, int]:
        return {int(g): i for i, g in enumerate(self.kf_gids.tolist())}

    def check(self) -> list[str]:
        """Index consistency beyond what ``decode`` checks (gids unique, edges, loops,
        gauge and observations naming what the copy holds); returns the problems."""
        errs = []
        K, M, O = len(self.kf_gids), len(self.mp_gids), len(self.obs_kf)
        if self.T_m_kf.shape != (K, 4, 4):
            errs.append(f"T_m_kf shape {self.T_m_kf.shape}, expected {(K, 4, 4)}")
        if self.mp_pos.shape != (M, 3) or self.mp_ref.shape != (M,):
            errs.append("mp_pos / mp_ref shape")
        if (
            self.obs_mp.shape != (O,)
            or self.obs_xy.shape != (O, 2)
            or self.obs_octave.shape != (O,)
        ):
            errs.append("observation arrays differ in length")
        if O and (self.obs_kf.min() < 0 or self.obs_kf.max() >= K):
            errs.append("obs_kf out of range")
        if O and (self.obs_mp.min() < 0 or self.obs_mp.max() >= M):
            errs.append("obs_mp out of range")
        known = set(self.kf_gids.tolist())
        for name, arr in (("edges", self.edges), ("loops", self.loops)):
            if arr.size and not set(arr.ravel().tolist()) <= known:
                errs.append(f"{name} name unknown keyframes")
        if not set(self.fixed_gids.tolist()) <= known:
            errs.append("fixed_gids name unknown keyframes")
        if self.S_loop.shape != (len(self.loops), 4, 4):
            errs.append("S_loop shape")
        odo = (self.odo, self.T_odo, self.odo_sigma)
        if any(a is not None for a in odo):
            if any(a is None for a in odo):
                errs.append("odo, T_odo and odo_sigma: all three or none")
            elif self.odo.size and not set(self.odo.ravel().tolist()) <= known:
                errs.append("odo names unknown keyframes")
            elif self.odo_sigma.size and not (self.odo_sigma > 0).all():
                errs.append("odo_sigma not positive")
        if len(np.unique(self.kf_gids)) != K or len(np.unique(self.mp_gids)) != M:
            errs.append("duplicate gids")
        return errs


@dataclass
class CorrectionMsg(_Record):
    """Optimizer -> mapper on ``hivemap/map/{map}/correction``: optimized keyframe poses
    (SE(3), camera to map) with the Sim(3) scale each got, and point positions.
    The mapper applies it and carries keyframes that arrived meanwhile along through
    their relative poses (CCM-SLAM Fig. 4); the optimizer's algorithms return it.

    ``kf_scale``: the scale ``s`` of each keyframe's optimized camera-to-map Sim(3)
    ``S_m_kf = [[s R, t], [0, 1]]`` (1 where none); the corrected SE(3) pose is
    ``[R, t]``. A length measured in the keyframe's camera frame before the correction
    is ``s`` times as long in the corrected map. ``stats``: numbers, strings and
    lists/maps of them, for logs. ``job``: the optimization job it answers
    (``shared/jobs.py``); a job's correction is applied once."""

    SCHEMA: ClassVar[str] = "hivemap.correction/1"
    FIELDS: ClassVar[dict[str, Any]] = {
        "map_id": "id", "base_version": "int", "sent_ns": "int",
        "kf_gids": ("<i8", (None,)), "T_m_kf": ("<f8", ("kf_gids", 4, 4)),
        "kf_scale": ("<f8", ("kf_gids",)),
        "mp_gids": ("<i8", (None,)), "mp_pos": ("<f8", ("mp_gids", 3)),
        "outlier_kf": ("<i8", (None,)), "outlier_mp": ("<i8", ("outlier_kf",)),
        "stats": "dict", "job": "str",
    }  # fmt: skip
    OPTIONAL: ClassVar[tuple[str, ...]] = ("job",)
    map_id: str
    base_version: int
    sent_ns: int
    kf_gids: np.ndarray
    T_m_kf: np.ndarray
    kf_scale: np.ndarray
    mp_gids: np.ndarray
    mp_pos: np.ndarray
    outlier_kf: np.ndarray  # observations the optimization found to be outliers:
    outlier_mp: np.ndarray  # (keyframe gid, map-point gid) pairs
    stats: dict
    job: str | None = None

    @property
    def outliers(self) -> np.ndarray:
        """(O, 2) int64 (keyframe gid, map-point gid) pairs."""
        return np.stack([self.outlier_kf, self.outlier_mp], axis=1).reshape(-1, 2)

    @staticmethod
    def of(req: OptimizeRequest, T_m_kf: np.ndarray, kf_scale: np.ndarray,
           mp_pos: np.ndarray, stats: dict | None = None,
           outliers: np.ndarray | None = None) -> CorrectionMsg:  # fmt: skip
        """The correction of ``req``'s map copy: same keyframes and points, same order."""
        out = np.zeros((0, 2), np.int64) if outliers is None else outliers
        out = np.asarray(out, np.int64).reshape(-1, 2)
        return CorrectionMsg(
            map_id=req.map_id, base_version=int(req.version), sent_ns=0,
            kf_gids=req.kf_gids.astype(np.int64), T_m_kf=np.asarray(T_m_kf, np.float64),
            kf_scale=np.asarray(kf_scale, np.float64), mp_gids=req.mp_gids.astype(np.int64),
            mp_pos=np.asarray(mp_pos, np.float64), outlier_kf=out[:, 0].copy(),
            outlier_mp=out[:, 1].copy(), stats=dict(stats or {}),
        )  # fmt: skip


@dataclass
class MapMerged(_Record):
    """Mapper -> all on ``hivemap/map/{source}/merged``: map ``source`` became part of
    ``target``; ``S_t_s`` (4x4 [[sR, t], [0, 1]]) carried its frame into the target's."""

    SCHEMA: ClassVar[str] = "hivemap.map_merged/1"
    FIELDS: ClassVar[dict[str, Any]] = {
        "source": "id", "target": "id", "S_t_s": ("<f8", (4, 4)), "sent_ns": "int",
    }  # fmt: skip
    source: str
    target: str
    S_t_s: np.ndarray
    sent_ns: int


def _session(d: dict) -> int | None:
    v = d.get("session")
    if v is None:
        return None
    s = _int(v, "session")
    if s < 0:
        raise DecodeError("session: negative")
    return s


def peek_session(data: bytes) -> int | None:
    """The ``session`` of an encoded ``KeyframeBatch`` or ``PoseUpdate`` without decoding
    the rest (a few microseconds where a decode takes a millisecond or more: every
    mapper reads it to route each batch before deciding to decode it). None when
    there is none, and for anything malformed (the decode then says what is wrong)."""
    try:
        u = msgpack.Unpacker(
            raw=False, strict_map_key=False, max_bin_len=MAX_BIN_BYTES, max_str_len=1 << 20,
            max_array_len=1 << 20, max_map_len=1 << 20,
        )  # fmt: skip
        u.feed(data)
        out = None
        for _ in range(u.read_map_header()):
            if u.unpack() == "session":
                out = u.unpack()  # the last one, as a decode into a dict takes it
            else:
                u.skip()
    except Exception:  # msgpack raises several unrelated types on bad input
        return None
    if isinstance(out, bool) or not isinstance(out, int) or not 0 <= out < 2**63:
        return None
    return out


def _envelope(data: bytes, schema: str) -> dict:
    d = unpackb(data)
    if not isinstance(d, dict):
        raise DecodeError("message is not a map")
    got = d.get("schema")
    # isinstance first: an array in the schema field would make != elementwise (found by
    # tests/test_fuzz.py; it escaped as a plain ValueError).
    if not isinstance(got, str) or got != schema:
        name = schema.split("/")[0]
        if isinstance(got, str) and got.split("/")[0] == name:
            raise DecodeError(f"unsupported version {got!r}; this build speaks {schema!r}")
        raise DecodeError(f"expected schema {schema!r}, got {got!r}")
    return d
