"""What keeps the mapper's CPU per keyframe flat as agents are added (issue 18, capacity):
background work sleeps on one backlog count instead of polling every actor's queue, and
global optimizations of a big map are spaced by what they cost the optimizer."""

from __future__ import annotations

import threading
import time

from services.mapper.service import MapperService
from shared.settings import Settings


def test_background_work_sleeps_until_every_actor_queue_is_empty(redis_url):
    svc = MapperService(Settings(redis_url=redis_url))  # no session: actors not started
    reg = svc.registry
    a, b = (reg.actor(reg.ensure_map(m).map_id) for m in ("map-a", "map-b"))
    assert not reg.batches_waiting()
    a.q.put("batch 1")
    b.q.put("batch 2")
    b.q.put("batch 3")
    assert reg.batches_waiting()
    woke: list[float] = []
    waiter = threading.Thread(target=lambda: (reg.wait_for_batches(max_s=10.0),
                                              woke.append(time.monotonic())))  # fmt: skip
    waiter.start()
    time.sleep(0.1)
    assert not woke  # still queued: it sleeps
    a.q.get_nowait()
    b.q.get_nowait()
    time.sleep(0.1)
    assert not woke and reg.batches_waiting()
    t_empty = time.monotonic()
    b.q.get_nowait()
    waiter.join(5.0)
    assert woke and woke[0] - t_empty < 1.0  # woken by the last get, not the timeout
    assert not reg.batches_waiting()
    # The bound holds under sustained load.
    a.q.put("batch 4")
    t0 = time.monotonic()
    reg.wait_for_batches(max_s=0.2)
    assert 0.15 < time.monotonic() - t0 < 2.0
    # A map handed to another mapper takes its unapplied batches out of the count.
    reg.drop("map-a")
    assert not reg.batches_waiting()


def test_global_optimizations_of_a_map_are_spaced_by_their_run_time(redis_url):
    svc = MapperService(Settings(redis_url=redis_url))
    c = svc.collab
    svc.registry.ensure_map("map-a")
    now = time.monotonic()
    c.mark_dirty("map-a", "loop")
    assert c.due(now) == [("map-a", "loop")]  # never asked before
    c._spacing("map-a", "loop").sent = now
    c.mark_dirty("map-a", "loop")
    assert c.due(now + c.min_interval + 0.1) == [("map-a", "loop")]  # a cheap map
    # The optimizer ran the map's last optimization for 8 s: with at most
    # optimizer_share of a core for it, the next request waits 8 / share.
    c._spacing("map-a", "loop").run_s = 8.0
    c._spacing("map-a", "loop").sent = now
    c.mark_dirty("map-a", "loop")
    gap = 8.0 / c.optimizer_share
    assert c.due(now + c.min_interval + 0.1) == []
    assert c.due(now + gap - 0.5) == []
    assert c.due(now + gap + 0.1) == [("map-a", "loop")]


def test_windowed_bas_of_a_map_are_spaced_by_their_own_runs(redis_url):
    """A windowed BA ("local") is spaced by its own run time, not by the map's global
    runs nor by what their copies and corrections cost the mapper; and the other way
    round."""
    svc = MapperService(Settings(redis_url=redis_url))
    c = svc.collab
    svc.registry.ensure_map("map-a")
    now = time.monotonic()
    g = c._spacing("map-a", "loop")
    g.sent, g.run_s, g.copy_s, g.corr_s = now, 20.0, 2.0, 2.0
    c.mark_dirty("map-a", "local")
    assert c.due(now + c.min_interval + 0.1) == [("map-a", "local")]
    w = c._spacing("map-a", "local")
    assert w is not g and w.run_s == 0.0
    w.sent, w.run_s = now, 2.0
    c.mark_dirty("map-a", "local")
    assert c.due(now + 2.0 / c.optimizer_share - 0.5) == []
    assert c.due(now + 2.0 / c.optimizer_share + 0.1) == [("map-a", "local")]
    g.sent = now - 1e3
    c.mark_dirty("map-a", "settle")
    assert c.due(now) == [("map-a", "settle")]  # a window out does not hold a global run


def test_deferred_keyframe_events_go_out_a_slice_per_call(redis_url):
    """Events held back through an overload are published a few at a time (each call
    holds the map's lock for its slice): all at once held it 1.8 s at 32 agents."""
    from services.mapper.service import EVENTS_PER_BATCH, EVENTS_PER_IDLE

    svc = MapperService(Settings(redis_url=redis_url))
    a = svc.registry.actor(svc.registry.ensure_map("map-a").map_id)
    a.queue_events("map-a", list(range(100)))
    a._publish_events(force=True)
    assert len(a.events) == 100 - EVENTS_PER_IDLE
    a.q.put("a batch waiting")
    a._publish_events(force=True)
    assert len(a.events) == 100 - EVENTS_PER_IDLE - EVENTS_PER_BATCH
    assert a.events[0] == ("map-a", EVENTS_PER_IDLE + EVENTS_PER_BATCH)  # oldest first


def test_a_map_held_back_by_the_spacing_counts_as_pending(redis_url):
    """hivemap_optimize_pending shows a request still to go out (what ``hivemap run-team``
    waits for before it evaluates: requests and corrections alone looked settled while a
    1000-keyframe map's loop closure waited 80 s for its turn)."""
    from shared.metrics import sample_value

    svc = MapperService(Settings(redis_url=redis_url))
    c = svc.collab
    svc.registry.ensure_map("map-a")
    now = time.monotonic()
    c._spacing("map-a", "loop").run_s = 20.0
    c._spacing("map-a", "loop").sent = now
    c.mark_dirty("map-a", "loop")
    assert c.due(now + 10.0) == []
    assert sample_value("hivemap_optimize_pending", {}) == 1
    assert c.due(now + 20.0 / c.optimizer_share + 0.1) == [("map-a", "loop")]
    assert sample_value("hivemap_optimize_pending", {}) == 0
    c._continue("map-a")  # a BA that stopped on its time budget asks for another run
    assert sample_value("hivemap_optimize_pending", {}) == 1
