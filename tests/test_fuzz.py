"""Property-based fuzzing (hypothesis) of every wire decoder and file loader, small budget.

Random bytes and mutations of a valid message (bytes flipped, cut or inserted; fields
deleted, added or replaced by odd values, arrays with wrong dtypes, shapes, NaN) go to
the decoder and to the real service path that receives it: nothing but the project's
DecodeError may come out of the decoder, nothing at all out of the service, and each
rejection is counted once in hivemap_messages_rejected_total. The loaders (calibration
YAML, PNG images, EuRoC and TUM indexes) may only raise their own error. The bench
(bench/bench_fuzz.py) runs >= 10,000 inputs per target.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import pytest
from fuzz_targets import (
    DECODERS,
    LOADERS,
    file_targets,
    mutate,
    rejected,
    run_file,
    run_one,
    targets,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

# derandomize: the same inputs every run, so the suite is not flaky; bench_fuzz explores.
BUDGET = settings(max_examples=150, deadline=None, database=None, derandomize=True,
                  suppress_health_check=[HealthCheck.too_slow])  # fmt: skip


@pytest.fixture(scope="module")
def wire(redis_server):
    logging.disable(logging.WARNING)  # thousands of "rejected ..." warnings
    try:
        yield {t.name: t for t in targets(redis_server.url)}
    finally:
        logging.disable(logging.NOTSET)


@pytest.fixture(scope="module")
def files():
    return {t.name: t for t in file_targets()}


def test_every_decoder_has_a_target(wire):
    assert sorted(wire) == sorted(DECODERS)


@pytest.mark.parametrize("name", DECODERS)
def test_decoder_rejects_only_with_decode_error_and_counts(wire, name):
    t = wire[name]
    assert run_one(t, t.seed) is False  # the seed is a valid message
    seen = {"rejected": 0}
    before = rejected(t.service, t.key)

    @BUDGET
    @given(rng=st.randoms(use_true_random=False), raw=st.binary(max_size=600),
           use_raw=st.integers(0, 9))  # fmt: skip
    def prop(rng, raw, use_raw):
        data = raw if use_raw == 0 else mutate(t.seed, rng)
        seen["rejected"] += run_one(t, data)

    prop()
    assert seen["rejected"] > 50, seen
    if t.receive is not None:  # the service counted at least every decoder rejection
        assert rejected(t.service, t.key) - before >= seen["rejected"]


@pytest.mark.parametrize("name", LOADERS)
def test_loader_refuses_only_with_its_own_error(files, name):
    t = files[name]
    with tempfile.TemporaryDirectory() as d:
        assert run_file(t, Path(d), t.seed) is False
    seen = {"refused": 0}

    @settings(max_examples=60, deadline=None, database=None, derandomize=True,
              suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
    @given(rng=st.randoms(use_true_random=False))
    def prop(rng):
        with tempfile.TemporaryDirectory() as d:
            seen["refused"] += run_file(t, Path(d), t.mutate(t.seed, rng))

    prop()
    assert seen["refused"] > 5, seen
