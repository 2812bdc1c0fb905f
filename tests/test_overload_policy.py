"""The mapper's shedding order and keyframe admission (services/mapper/overload.py)."""

from __future__ import annotations

import math
import time

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


def test_a_busy_map_is_overloaded_whatever_the_quiet_maps_do():
    """Sustained is judged per queue: quick batches of small maps (their own actors) do
    not reset the clock of the one big map whose queue waits for seconds."""
    o = Overload((0.1, 0.25, 0.4), shed_after_s=0.6, sustain_s=2.0)
    shed = []
    for i in range(40):
        t = i * 0.1
        o.observe(0.01, t, "small")
        assert o.admit(f"S{i}", [i], 0.01, t, "small")
        o.observe(1.5, t + 0.05, "big")
        shed.append(not o.admit("B", [i], 1.5, t + 0.05, "big"))
    # Registered while the wait could still be one long hold, shed once it lasted 2 s.
    assert not any(shed[:20]) and shed[21]
    # The small map's agents are never held back by the big map's overload.
    o.observe(0.01, 4.1, "small")
    assert o.admit("S99", [99], 0.01, 4.1, "small")


def test_overload_lasts_until_the_queue_stayed_calm():
    """Shedding drains the queue: the first quick batch after that does not end the
    overload (else the next sustain_s of batches went through unshed however long they
    had waited); waits that stay low for calm_s do."""
    o = Overload((0.1, 0.25, 0.4), shed_after_s=0.6, sustain_s=2.0, calm_s=3.0)
    _overloaded(o, 5.0)
    assert o.shedding("", 5.0)
    o.observe(0.05, 5.1)  # the queue emptied once
    o.observe(0.9, 5.5)
    assert not o.admit("A", [1], 0.9, 5.5)  # still shed: not after another 2 s
    o.observe(0.05, 6.0)
    o.observe(0.3, 7.0)  # neither high nor low: calm goes on
    o.observe(0.05, 8.9)
    assert o.shedding("", 8.9)
    o.observe(0.05, 9.1)  # 3 s without a wait over the background threshold
    assert not o.shedding("", 9.1)
    o.observe(0.9, 9.2)
    assert o.admit("B", [1], 0.9, 9.2)  # one long hold again, not overload


def test_the_retry_after_follows_the_backlog_within_bounds():
    o = Overload((0.1, 0.25, 0.4), shed_after_s=0.6, decay_s=2.0, retry_min_s=0.5,
                 retry_max_s=5.0)  # fmt: skip
    assert o.retry_after(0.0, "q") == 0.5
    o.observe(2.6, 0.0, "q")
    assert o.retry_after(0.0, "q") == pytest.approx(2.0)
    assert o.retry_after(0.0, "other") == 0.5  # per queue
    assert o.retry_after(1.0, "q") == pytest.approx(2.6 * math.exp(-0.5) - 0.6)
    o.observe(30.0, 2.0, "q")
    assert o.retry_after(2.0, "q") == 5.0
    with pytest.raises(ValueError):
        Overload(retry_min_s=0.0)


class _Bus:
    def __init__(self) -> None:
        self.sent: list[tuple[str, bytes]] = []

    def put(self, key: str, payload: bytes, reliable: bool = True) -> bool:
        self.sent.append((key, payload))
        return True


def test_the_mapper_nacks_a_shed_batch_with_a_retry_after(redis_url):
    """A batch shed by an overloaded map actor is answered at once: an ack of no
    keyframe naming the batch, with when to send it again (its successors, shed behind
    the hole, too); an admitted batch gets no NACK."""
    from messages_fixtures import sample_batch

    from services.mapper.service import MapperService
    from shared import keys
    from shared.messages import Ack
    from shared.settings import Settings

    svc = MapperService(Settings(redis_url=redis_url))
    svc.bus = bus = _Bus()
    h = svc.handler("A")
    batch = sample_batch()
    now = time.monotonic()
    ns = time.time_ns()
    assert svc.admit(h, batch, ns, now, "q")  # a fresh batch, no overload
    assert not bus.sent
    svc.overload.observe(2.0, now - 3.0, "q")
    svc.overload.observe(2.0, now, "q")  # waits over the threshold for 3 s
    assert not svc.admit(h, batch, ns - int(2e9), now, "q")  # waited 2 s: shed
    later = sample_batch()
    later.seq, later.new_kfs[0].id = batch.seq + 1, batch.new_kfs[0].id + 1
    assert not svc.admit(h, later, time.time_ns(), now, "q")  # behind the hole
    assert [k for k, _ in bus.sent] == [keys.agent_ack("A")] * 2
    nacks = [Ack.decode(p) for _, p in bus.sent]
    assert [n.seq for n in nacks] == [batch.seq, later.seq]
    assert all(len(n.kf_ids) == 0 and 0.5 <= n.retry_after_s <= 5.0 for n in nacks)
    assert nacks[0].retry_after_s == pytest.approx(2.0 - svc.overload.shed_after_s, abs=0.1)
    # A resend of keyframes the map has is only acknowledged: admitted, and it opens no
    # hole (the agent would never send them again to fill it).
    svc.overload.holes.clear()
    old = sample_batch()
    old.new_kfs[0].id = 0
    h.has_kf = lambda i: i == 0
    assert svc.admit(h, old, ns - int(2e9), now, "q")
    assert not svc.overload.holes and len(bus.sent) == 2
    svc.store.close()
