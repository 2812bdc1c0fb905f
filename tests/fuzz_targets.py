"""Fuzz targets shared by tests/test_fuzz.py (hypothesis, small budget) and
bench/bench_fuzz.py (>= 10,000 inputs per decoder): every wire decoder, a valid seed
message for each, the mutations fed to it, and the real service entry point that
receives it on the wire and counts a rejection in ``hivemap_messages_rejected_total``.

The mutators take a ``random.Random`` so hypothesis (``st.randoms()``, which shrinks)
and the bench's seeded loop drive the same code.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import msgpack
import numpy as np

from shared import keys
from shared.messages import (
    Ack,
    CorrectionMsg,
    KeyframeEvent,
    MapChunk,
    MapMerged,
    Match,
    OptimizeRequest,
    PoseUpdate,
    _Record,
    packb,
)
from shared.metrics import REJECTED
from shared.store import LivePose

GOLDEN = Path(__file__).parent / "golden"


def record_seed(cls: type[_Record], n: int = 3, seed: int = 0) -> bytes:
    """A valid message of a record class, built from its FIELDS spec."""
    rng = np.random.default_rng(seed)
    d: dict = {"schema": cls.SCHEMA}
    lengths: dict[str, int] = {}
    for name, spec in cls.FIELDS.items():
        if spec == "int":
            d[name] = int(rng.integers(0, 1000))
        elif spec in ("str", "id"):
            d[name] = "map-A" if "map" in name or name in ("source", "target") else "A"
        elif spec == "float":
            d[name] = 458.0
        elif spec == "dict":
            d[name] = {"iterations": 3, "cost": 1.5}
        else:
            dtype, shape = spec
            shp = tuple(lengths[x] if isinstance(x, str) else (n if x is None else x)
                        for x in shape)  # fmt: skip
            dt = np.dtype(dtype)
            if shp[-2:] == (4, 4):
                a = np.broadcast_to(np.eye(4), shp).astype(dt)
            elif dt.kind == "f":
                a = rng.normal(size=shp).astype(dt)
            else:
                a = rng.integers(0, min(np.iinfo(dt).max, n), size=shp, endpoint=False).astype(dt)
            d[name] = np.ascontiguousarray(a)
            lengths[name] = shp[0] if shp else 0
    return packb(d)


def chunk_seed() -> bytes:
    rng = np.random.default_rng(1)
    return MapChunk(
        "A", "map-A", 7, ["A", "B"], np.array([7, 2], np.int64),
        np.stack([np.eye(4)] * 2), [rng.random((3, 2)).astype(np.float32)] * 2,
        [np.zeros((3, 32), np.uint8)] * 2, [np.array([0, -1, 1], np.int64)] * 2,
        ["A", "B"], np.array([1, 2], np.int64), rng.random((2, 3)),
        np.zeros((2, 32), np.uint8),
    ).encode()  # fmt: skip


def live_pose_seed() -> bytes:
    return LivePose("A", "map-A", 1, np.eye(4), 3, "ok", 20.0, 2).encode()


# --- mutations -------------------------------------------------------------------------


def _odd_value(rng: random.Random, depth: int = 0):
    """Any msgpack value, biased towards what breaks validators."""
    k = rng.randrange(14 if depth < 2 else 11)
    if k == 0:
        return None
    if k == 1:
        return rng.choice([True, False])
    if k == 2:
        return rng.choice([0, -1, 1, 2**31, -(2**63), 2**64 - 1, rng.randrange(-1000, 1000)])
    if k == 3:
        return rng.choice([0.0, -0.0, math.nan, math.inf, -math.inf, 1e308, rng.random()])
    if k == 4:
        return rng.choice(["", "A", "x" * 100, "../../etc", "a/b", "*", "é", "\x00"])
    if k == 5:
        return rng.randbytes(rng.randrange(0, 64))
    if k == 6:
        return {"nd": rng.choice(["<f8", "|u1", "<i8", "<i4", "<f4", "|O", ">f8", "x"]),
                "shape": [rng.choice([0, 1, 2, 3, 4, -1, 2**40]) for _ in range(rng.randrange(4))],
                "b": rng.randbytes(rng.choice([0, 8, 16, 32, 128]))}  # fmt: skip
    if k == 7:
        return {"nd": "<f8", "shape": [4, 4], "b": np.full(16, rng.choice(
            [math.nan, math.inf, 0.0, 1e300])).tobytes()}  # fmt: skip
    if k == 8:
        return {"nd": "<f8", "shape": "ab", "b": b""}
    if k == 9:
        return rng.randrange(-(2**63), 2**63)
    if k == 10:
        return rng.choice(["hivemap.kf_batch/1", "hivemap.kf_batch/2", "hivemap.ack/1"])
    if k == 11:
        return [_odd_value(rng, depth + 1) for _ in range(rng.randrange(4))]
    if k == 12:
        return {_odd_key(rng): _odd_value(rng, depth + 1) for _ in range(rng.randrange(3))}
    return {"nd": "<f8", "b": b"", "shape": []}


def _odd_key(rng: random.Random):
    return rng.choice(["nd", "b", "shape", "schema", "x", "", 0, -1, 2**63, 1.5, None, b"k"])


def _raw_tree(data: bytes):
    return msgpack.unpackb(data, raw=False, strict_map_key=False)


def _paths(obj, prefix=()):
    """Every (container, key) inside a decoded message tree."""
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append((obj, k))
            out.extend(_paths(v, prefix + (k,)))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.append((obj, i))
            out.extend(_paths(v, prefix + (i,)))
    return out


def mutate_structure(seed: bytes, rng: random.Random) -> bytes:
    """Replace, delete or add fields anywhere in a valid message (arrays included)."""
    tree = _raw_tree(seed)
    for _ in range(rng.randrange(1, 4)):
        spots = _paths(tree)
        if not spots:
            break
        container, k = rng.choice(spots)
        op = rng.randrange(4)
        if op == 0 and isinstance(container, dict):
            del container[k]
        elif op == 1 and isinstance(container, dict):
            container[_odd_key(rng)] = _odd_value(rng)
        elif op == 2 and isinstance(container[k], bytes) and container[k]:
            b = bytearray(container[k])
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
            container[k] = bytes(b[: rng.randrange(len(b) + 1)] if rng.random() < 0.3 else b)
        else:
            container[k] = _odd_value(rng)
    try:
        return msgpack.packb(tree, use_bin_type=True)
    except (TypeError, ValueError, OverflowError):  # an odd key msgpack can't write
        return seed


def mutate_bytes(seed: bytes, rng: random.Random) -> bytes:
    """Flip, drop, insert, repeat or truncate bytes of a valid message."""
    b = bytearray(seed)
    for _ in range(rng.randrange(1, 6)):
        op = rng.randrange(5)
        i = rng.randrange(len(b) + 1)
        if op == 0 and b:
            b[min(i, len(b) - 1)] ^= 1 << rng.randrange(8)
        elif op == 1:
            del b[i : i + rng.randrange(1, 16)]
        elif op == 2:
            b[i:i] = rng.randbytes(rng.randrange(1, 16))
        elif op == 3:
            b[i:i] = rng.choice(
                [
                    b"\xc1",
                    b"\xdd\xff\xff\xff\xff",
                    b"\xc6\x7f\xff\xff\xff",
                    b"\xcf\xff\xff\xff\xff\xff\xff\xff\xff",
                    b"\xd4\x01\x00",
                ]
            )
        else:
            del b[i:]
    return bytes(b)


def mutate(seed: bytes, rng: random.Random) -> bytes:
    k = rng.randrange(10)
    if k == 0:
        return rng.randbytes(rng.randrange(0, 256))
    if k < 4:
        return mutate_bytes(seed, rng)
    return mutate_structure(seed, rng)


# --- targets ---------------------------------------------------------------------------


@dataclass
class Target:
    name: str
    decode: Callable[[bytes], object]
    seed: bytes
    service: str  # label of the rejection counter
    key: str  # the key expression (or job stream) it arrives on
    # The service's own receive path for one sample (None: the decoder has no counted
    # receiver, e.g. LivePose travels between the mapper and the API inside Redis).
    receive: Callable[[bytes], object] | None = None


DECODERS = ["kf_batch", "pose", "match", "correction", "kf_event", "map_merged", "optimize",
            "ack", "map_chunk", "live_pose"]  # fmt: skip
LOADERS = ["calibration_yaml", "image_png", "euroc_index", "tum_index"]


def rejected(service: str, key: str) -> float:
    total = 0.0
    for metric in REJECTED.collect():
        for s in metric.samples:
            if (s.name.endswith("_total") and s.labels.get("service") == service
                    and s.labels.get("key") == key):  # fmt: skip
                total += s.value
    return total


def targets(redis_url: str) -> list[Target]:
    """Every decoder with the real service that receives it (mapper, placerec, optimizer,
    agent) built on ``redis_url``."""
    from services.agent.runner import Agent
    from services.agent.sources import open_source
    from services.mapper.service import MapperService
    from services.optimizer.service import K_JOBS, OptimizerService
    from services.placerec.service import PlacerecService
    from shared.jobs import Job
    from shared.messages import KeyframeBatch
    from shared.settings import Settings

    s = Settings(redis_url=redis_url)
    mapper = MapperService(s)
    placerec = PlacerecService(s)
    optimizer = OptimizerService(s)
    agent = Agent(s, "A", open_source("synthetic:MH01?frames=1200:1210"), use_server=False)
    k_kf, k_pose = keys.agent_kf("A"), keys.agent_pose("A")
    k_ack, k_map = keys.agent_ack("A"), keys.agent_map("A")
    k_event, k_merged = keys.map_kf("map-A"), keys.map_merged("map-A")
    k_corr = keys.map_correction("map-A")
    return [
        Target("kf_batch", KeyframeBatch.decode, (GOLDEN / "kf_batch_v1.bin").read_bytes(),
               "mapper", k_kf, lambda b: mapper.decode_kf(k_kf, b)),
        Target("pose", PoseUpdate.decode, (GOLDEN / "pose_v1.bin").read_bytes(),
               "mapper", k_pose, lambda b: mapper.decode_pose(k_pose, b)),
        Target("match", Match.decode, record_seed(Match), "mapper", keys.MATCH,
               lambda b: mapper.collab.on_match_bytes(keys.MATCH, b)),
        Target("correction", CorrectionMsg.decode, record_seed(CorrectionMsg), "mapper",
               k_corr, lambda b: mapper.collab.on_correction_bytes(k_corr, b)),
        Target("kf_event", KeyframeEvent.decode, record_seed(KeyframeEvent), "placerec",
               k_event, lambda b: placerec.handle(k_event, b)),
        Target("map_merged", MapMerged.decode, record_seed(MapMerged), "placerec", k_merged,
               lambda b: placerec.handle(k_merged, b)),
        Target("optimize", OptimizeRequest.decode, record_seed(OptimizeRequest), "optimizer",
               K_JOBS, lambda b: optimizer.decode(Job("1-0", "map-A", b, 1, False))),
        Target("ack", Ack.decode, (GOLDEN / "ack_v1.bin").read_bytes(), "agent", k_ack,
               lambda b: agent._on_message(b, k_ack)),
        Target("map_chunk", MapChunk.decode, chunk_seed(), "agent", k_map,
               lambda b: agent._on_message(b, k_map)),
        Target("live_pose", LivePose.decode, live_pose_seed(), "api", "pose-channel"),
    ]  # fmt: skip


def run_one(t: Target, data: bytes) -> bool:
    """Feed one input to the decoder and to the service's receive path. Returns whether
    the decoder rejected it. Raises AssertionError when anything but the project's
    DecodeError escaped, or a rejection went uncounted."""
    from shared.messages import DecodeError

    try:
        t.decode(data)
        bad = False
    except DecodeError:
        bad = True
    except Exception as e:
        raise AssertionError(f"{t.name}: {type(e).__name__} escaped the decoder: {e}") from e
    if t.receive is None:
        return bad
    before = rejected(t.service, t.key)
    try:
        t.receive(data)
    except Exception as e:
        raise AssertionError(f"{t.name}: {type(e).__name__} escaped {t.service}: {e}") from e
    counted = rejected(t.service, t.key) - before
    if bad and counted != 1:
        raise AssertionError(f"{t.name}: a rejected message counted {counted} times")
    return bad


# --- file loaders ----------------------------------------------------------------------

_TOKENS = [
    "nan",
    "inf",
    "-1",
    "0",
    "1e400",
    "",
    "../x.png",
    "x" * 300,
    "1.2.3",
    "١٢٣",
    "18446744073709551616",
    "#",
    ",",
    "\t",
    "\x00",
    "[",
    "{",
    ":",
    "- ",
    "!!python/none",
]


def mutate_text(seed: bytes, rng: random.Random) -> bytes:
    """Line and token edits of a text file (CSV, YAML, TUM index), or byte edits."""
    if rng.random() < 0.3:
        return mutate_bytes(seed, rng)
    lines = seed.decode().split("\n")
    for _ in range(rng.randrange(1, 4)):
        i = rng.randrange(len(lines))
        op = rng.randrange(4)
        if op == 0:
            del lines[i]
        elif op == 1:
            lines.insert(i, lines[rng.randrange(len(lines))])
        else:
            toks = lines[i].replace(",", " , ").split(" ") if lines[i] else [""]
            toks[rng.randrange(len(toks))] = rng.choice(_TOKENS)
            lines[i] = " ".join(toks).replace(" , ", ",")
        if not lines:
            lines = [""]
    return "\n".join(lines).encode(errors="surrogateescape")


@dataclass
class FileTarget:
    name: str
    seed: bytes
    load: Callable[[Path, bytes], object]  # writes the mutated file under dir, loads it
    error: type[Exception]
    mutate: Callable[[bytes, random.Random], bytes]


def _png() -> bytes:
    import cv2

    img = (np.arange(480 * 752, dtype=np.uint32) % 251).astype(np.uint8).reshape(480, 752)
    return cv2.imencode(".png", img)[1].tobytes()


def file_targets() -> list[FileTarget]:
    from services.agent.sources import EurocSource, SourceError, TumSource, _read_gray
    from shared.camera import CalibrationError, PinholeRadTan

    cam = PinholeRadTan.euroc_cam0()
    yaml_text = cam.to_euroc_yaml().encode()
    png = _png()
    euroc_csv = b"#timestamp [ns],filename\n1403636579763555584,a.png\n1403636579813555584,b.png\n"
    tum_txt = b"# color images\n1305031102.175304 rgb/a.png\n1305031102.211214 rgb/b.png\n"

    def euroc(d: Path, data: bytes) -> object:
        c = d / "mav0" / "cam0"
        (c / "data").mkdir(parents=True, exist_ok=True)
        (c / "sensor.yaml").write_bytes(yaml_text)
        (c / "data.csv").write_bytes(data)
        for n in ("a.png", "b.png"):
            (c / "data" / n).write_bytes(png)
        return [f.stamp_ns for f in EurocSource(d)]

    def tum(d: Path, data: bytes) -> object:
        (d / "rgb").mkdir(parents=True, exist_ok=True)
        (d / "camera.yaml").write_bytes(yaml_text)
        (d / "rgb.txt").write_bytes(data)
        for n in ("a.png", "b.png"):
            (d / "rgb" / n).write_bytes(png)
        return [f.stamp_ns for f in TumSource(d)]

    def calib(d: Path, data: bytes) -> object:
        (d / "sensor.yaml").write_bytes(data)
        return PinholeRadTan.from_yaml(d / "sensor.yaml")

    def image(d: Path, data: bytes) -> object:
        (d / "img.png").write_bytes(data)
        return _read_gray(d / "img.png", cam)

    return [
        FileTarget("calibration_yaml", yaml_text, calib, CalibrationError, mutate_text),
        FileTarget("image_png", png, image, SourceError, mutate_bytes),
        FileTarget("euroc_index", euroc_csv, euroc, SourceError, mutate_text),
        FileTarget("tum_index", tum_txt, tum, SourceError, mutate_text),
    ]


def run_file(t: FileTarget, d: Path, data: bytes) -> bool:
    """Load one mutated file; True when refused with the loader's own error."""
    try:
        t.load(d, data)
        return False
    except t.error:
        return True
    except Exception as e:
        raise AssertionError(f"{t.name}: {type(e).__name__} escaped the loader: {e}") from e
