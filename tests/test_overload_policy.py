"""The mapper's shedding order and keyframe admission (services/mapper/overload.py)."""

from __future__ import annotations

import pytest

from services.mapper.overload import BACKGROUND, FEEDBACK, KEYFRAMES, POSES, Overload


def test_levels_rise_with_the_queue_wait_in_order_and_decay():
    o = Overload((0.1, 0.25, 0.4), shed_after_s=0.6, decay_s=2.0)
    assert o.level(0.0) == 0
    seen = []
    for t, w in enumerate([0.05, 0.15, 0.3, 0.5]):
        o.observe(w, float(t) * 0.01)
        seen.append(o.level(float(t) * 0.01))
    assert seen == [0, POSES, FEEDBACK, BACKGROUND]
    # No more late batches: back to normal within a few decay times.
    assert o.level(0.03 + 2.0) < BACKGROUND
    assert o.level(10.0) == 0
    with pytest.raises(ValueError):
        Overload((0.3, 0.2, 0.4), 0.6)


def test_one_long_wait_is_not_overload():
    """A batch that waited behind one long lock hold is registered: keyframes are shed
    only once waits stayed high for sustain_s."""
    o = Overload((0.1, 0.25, 0.4), shed_after_s=0.6, sustain_s=2.0)
    o.observe(0.9, 0.0)
    assert o.admit("A", [0], 0.9, 0.0)
    o.observe(0.05, 0.5)  # the queue emptied: not sustained
    o.observe(0.9, 1.0)
    assert o.admit("A", [1], 0.9, 1.0)
    o.observe(0.5, 2.0)
    o.observe(0.9, 3.1)
    assert not o.admit("A", [2], 0.9, 3.1)


def _overloaded(o: Overload, now: float) -> None:
    o.observe(0.5, now - 3.0)
    o.observe(0.5, now)


def test_a_shed_batch_holds_back_the_agents_later_ones_until_it_comes_back():
    o = Overload((0.1, 0.25, 0.4), shed_after_s=0.6, hole_max_s=10.0)
    assert o.admit("A", [0, 1], 0.1, 0.0)
    _overloaded(o, 1.0)
    assert not o.admit("A", [2, 3], 0.8, 1.0)  # waited too long: shed
    assert o.level(1.0) == KEYFRAMES
    assert not o.admit("A", [4], 0.1, 1.1)  # fresh, but behind the hole: shed too
    assert o.admit("B", [7], 0.1, 1.1)  # other agents are not held back
    assert o.admit("A", [], 0.9, 1.2)  # updates only: always registered
    assert o.admit("A", [2, 3, 4], 0.2, 3.0)  # the resend fills the hole
    assert o.admit("A", [5], 0.2, 3.1)
    assert o.level(3.1) < KEYFRAMES


def test_a_hole_the_agent_cannot_fill_closes():
    o = Overload((0.1, 0.25, 0.4), shed_after_s=0.6, hole_max_s=10.0)
    _overloaded(o, 0.0)
    assert not o.admit("A", [2], 0.8, 0.0)
    assert not o.admit("A", [5], 0.1, 5.0)
    assert o.admit("A", [5], 0.1, 10.5)  # keyframe 2 was dropped by the agent's buffer
    assert not o.admit("C", [1], 0.9, 11.0)
    assert o.level(11.0) == KEYFRAMES
    assert o.level(21.5) < KEYFRAMES  # C went quiet: its hole does not pin the level
