"""Wire messages: round trips, golden bytes, and rejection of bad input."""

from __future__ import annotations

from pathlib import Path

import msgpack
import numpy as np
import pytest
from messages_fixtures import sample_ack, sample_batch, sample_pose

from shared.geometry import Sim3, exp_so3
from shared.messages import (
    Ack,
    DecodeError,
    KeyframeBatch,
    MapChunk,
    PoseUpdate,
    packb,
    packb_sliced,
)

GOLDEN = Path(__file__).parent / "golden"


@pytest.mark.parametrize(
    ("name", "make", "cls"),
    [("kf_batch_v1", sample_batch, KeyframeBatch), ("ack_v1", sample_ack, Ack),
     ("pose_v1", sample_pose, PoseUpdate)],
)  # fmt: skip
def test_golden_bytes(name, make, cls):
    """A change that breaks peers running the released protocol fails here."""
    golden = (GOLDEN / f"{name}.bin").read_bytes()
    assert make().encode() == golden
    decoded = cls.decode(golden)
    assert decoded.encode() == golden


@pytest.mark.parametrize("field", ["retry_after_s", "held_s"])
def test_ack_seconds_fields_are_optional_both_ways(field):
    """A NACK's retry-after and the time the server held a batch (both added within
    v1): an old peer's ack has neither, a new one's has them, and a value that is not
    seconds is a clear decode error."""
    old = sample_ack()
    assert getattr(Ack.decode(old.encode()), field) is None
    new = sample_ack()
    new.seq = 7
    setattr(new, field, 1.5)
    back = Ack.decode(new.encode())
    assert (back.seq, getattr(back, field)) == (7, 1.5)
    for bad in (-1.0, float("nan"), "soon", True, 1e9):
        d = msgpack.unpackb(old.encode(), raw=False, strict_map_key=False)
        d[field] = bad
        with pytest.raises(DecodeError, match=field):
            Ack.decode(msgpack.packb(d, use_bin_type=True))


def test_batch_round_trip_values():
    b = sample_batch()
    d = KeyframeBatch.decode(b.encode())
    kf, kf0 = d.new_kfs[0], b.new_kfs[0]
    assert d.agent == "A" and d.seq == 4 and kf.id == 3
    np.testing.assert_array_equal(kf.keypoints, kf0.keypoints)
    np.testing.assert_array_equal(kf.descriptors, kf0.descriptors)
    np.testing.assert_array_equal(kf.mp_ids, kf0.mp_ids)
    np.testing.assert_array_equal(kf.T_l_kf, kf0.T_l_kf)
    np.testing.assert_array_equal(d.new_mps.p_ref, b.new_mps.p_ref)
    assert kf.stamp_ns == 1403636580863555584  # all 19 digits survive


def test_map_chunk_round_trip():
    rng = np.random.default_rng(1)
    c = MapChunk(
        "A", "map-A", 7, ["A", "B"], np.array([7, 2], np.int64),
        np.stack([np.eye(4)] * 2), [rng.random((3, 2)).astype(np.float32)] * 2,
        [np.zeros((3, 32), np.uint8)] * 2, [np.array([0, -1, 1], np.int64)] * 2,
        ["A", "B"], np.array([1, 2], np.int64), rng.random((2, 3)),
        np.zeros((2, 32), np.uint8),
    )  # fmt: skip
    d = MapChunk.decode(c.encode())
    assert d.kf_agents == ["A", "B"]
    np.testing.assert_array_equal(d.p_ref, c.p_ref)
    assert d.S_g_l is None and "S_g_l" not in msgpack.unpackb(c.encode(), raw=False)
    # The optional frame correction travels as a similarity and nothing else does.
    S = Sim3(exp_so3(np.array([0.01, -0.02, 0.03])), np.array([0.1, 0.2, -0.3]), 1.02)
    c.S_g_l = S.matrix()
    np.testing.assert_array_equal(MapChunk.decode(c.encode()).S_g_l, S.matrix())
    for bad in (np.diag([1.0, 1.0, 2.0, 1.0]), np.diag([-1.0, 1.0, 1.0, 1.0]),
                np.full((4, 4), np.nan)):  # fmt: skip
        c.S_g_l = bad
        with pytest.raises(DecodeError, match="S_g_l"):
            MapChunk.decode(c.encode())


def _corruptions(good: bytes) -> list[bytes]:
    d = msgpack.unpackb(good, raw=False)
    wrong_version = dict(d, schema=d["schema"].split("/")[0] + "/99")
    no_field = {k: v for k, v in d.items() if k != "agent"}
    return [
        b"",
        b"\xff\x00garbage",
        good[: len(good) // 2],
        packb(wrong_version),
        packb(no_field),
        packb([1, 2, 3]),
        packb({"schema": "hivemap.other/1"}),
    ]


@pytest.mark.parametrize("cls,make", [(KeyframeBatch, sample_batch), (Ack, sample_ack),
                                      (PoseUpdate, sample_pose)])  # fmt: skip
def test_bad_bytes_raise_decode_error(cls, make):
    for bad in _corruptions(make().encode()):
        with pytest.raises(DecodeError):
            cls.decode(bad)


def test_array_shape_lies_are_rejected():
    b = sample_batch()
    d = msgpack.unpackb(b.encode(), raw=False)
    d["new_kfs"][0]["keypoints"]["shape"] = [6, 2]  # 5 keypoints claimed as 6
    with pytest.raises(DecodeError, match="shape"):
        KeyframeBatch.decode(packb(d))
    d = msgpack.unpackb(b.encode(), raw=False)
    d["new_kfs"][0]["descriptors"]["nd"] = "<f8"
    with pytest.raises(DecodeError):
        KeyframeBatch.decode(packb(d))
    d = msgpack.unpackb(b.encode(), raw=False)
    d["new_kfs"][0]["T_pred_kf"]["b"] = np.full((4, 4), np.nan).tobytes()
    with pytest.raises(DecodeError, match="finite"):
        KeyframeBatch.decode(packb(d))


def test_wrong_version_names_versions():
    d = msgpack.unpackb(sample_ack().encode(), raw=False)
    d["schema"] = "hivemap.ack/2"
    with pytest.raises(DecodeError, match="unsupported version"):
        Ack.decode(packb(d))


def test_pose_health_fields_are_optional_both_ways():
    """Health rides in the pose message within v1: a peer of the first version decodes a
    pose with health (it ignores the fields), and a pose without them decodes as before."""
    p = sample_pose()
    p.frames_dropped, p.kf_lost, p.bytes_sent, p.resent = 2, 0, 123_456, 7
    p.ack_p50_s, p.ack_p95_s = 0.021, 0.064
    data = p.encode()
    d = PoseUpdate.decode(data)
    assert (d.frames_dropped, d.kf_lost, d.bytes_sent, d.resent) == (2, 0, 123_456, 7)
    assert (d.ack_p50_s, d.ack_p95_s) == (0.021, 0.064)
    # What a first-version peer reads: the v1 fields only, unchanged.
    v1 = {k: v for k, v in msgpack.unpackb(data, raw=False).items()
          if k not in PoseUpdate.HEALTH_INTS + PoseUpdate.HEALTH_FLOATS}  # fmt: skip
    assert packb(v1) == (GOLDEN / "pose_v1.bin").read_bytes()
    old = PoseUpdate.decode(packb(v1))
    assert old.frames_dropped is None and old.ack_p95_s is None
    for name, bad in (("resent", -1), ("bytes_sent", 1.5), ("ack_p95_s", -0.1),
                      ("ack_p50_s", "fast"), ("fps", float("nan"))):  # fmt: skip
        with pytest.raises(DecodeError, match=name):
            PoseUpdate.decode(packb({**msgpack.unpackb(data, raw=False), name: bad}))


def test_compact_form_decodes_to_the_same_batch():
    """What agents send: keypoints in 1/8 px, int32 ids, float32 positions; the mapper
    decodes it to the arrays of the full form (keypoints within 1/16 px)."""
    b = sample_batch()
    rng = np.random.default_rng(3)
    n = 500  # a keyframe's worth of keypoints, so the arrays dominate the bytes
    kf = b.new_kfs[0]
    kf.keypoints = rng.uniform(0, 751.9, (n, 2)).astype(np.float32)
    kf.octaves = rng.integers(0, 8, n).astype(np.uint8)
    kf.descriptors = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    kf.mp_ids = np.where(rng.random(n) < 0.5, rng.integers(0, 10**6, n), -1).astype(np.int64)
    full, small = b.encode(), b.encode(compact=True)
    assert len(small) < 0.85 * len(full)
    d, c = KeyframeBatch.decode(full), KeyframeBatch.decode(small)
    for kf_d, kf_c in zip(d.new_kfs, c.new_kfs, strict=True):
        assert kf_c.keypoints.dtype == np.float32 and kf_c.mp_ids.dtype == np.int64
        assert np.abs(kf_c.keypoints - kf_d.keypoints).max() <= 1 / 16 + 1e-6
        np.testing.assert_array_equal(kf_c.mp_ids, kf_d.mp_ids)
        np.testing.assert_array_equal(kf_c.descriptors, kf_d.descriptors)
    np.testing.assert_array_equal(c.new_mps.ids, d.new_mps.ids)
    np.testing.assert_allclose(c.new_mps.p_ref, d.new_mps.p_ref, rtol=1e-6)
    assert c.new_mps.p_ref.dtype == np.float64


@pytest.mark.parametrize("n", [0, 1, 255, 256, 65_535, 65_536, 300_000])
def test_sliced_packing_gives_packb_bytes(n):
    """packb_sliced (an optimization request, packed in slices so that no one call holds
    the GIL for long) writes the same bytes as packb, whatever the bin header's size."""
    rng = np.random.default_rng(n)
    d = {"schema": "x/1", "ints": np.arange(n, dtype=">i4"), "pos": rng.normal(size=(n, 3)),
         "oct": np.arange(n, dtype=np.uint8), "empty": np.zeros((0, 4, 4)),
         "flag": np.ones(3, bool), "stats": {"s": np.float64(1.5), "a": np.ones(2)},
         "name": "m", "none": None, "k": 7}  # fmt: skip
    pauses = []
    out = packb_sliced(d, lambda: pauses.append(1), slice_bytes=4096)
    assert bytes(out) == packb(d)
    assert len(pauses) >= (n * 24) // 4096 - 1
