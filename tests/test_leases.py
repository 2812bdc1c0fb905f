"""Map leases with fencing (shared/leases.py) on a real redis-server: one owner at a
time, a dead owner's map taken after the lease time, and an owner paused (SIGSTOP) past
its lease then resumed cannot write to a map another owner has taken."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from functools import partial

import pytest
from procs import wait_until

from shared.leases import Fenced, Leases
from shared.store import connect, k_lease

LEASE_S = 1.0
_wait = partial(wait_until, step=0.02)


def test_one_owner_at_a_time_and_release_hands_over(redis_url):
    r = connect(redis_url)
    a, b = Leases(r, "mapper-a", LEASE_S), Leases(r, "mapper-b", LEASE_S)
    ta = a.acquire("m1")
    assert ta == 1 and a.acquire("m1") == ta  # asking again keeps the token
    assert b.acquire("m1") is None
    assert a.owner_of("m1") == ("mapper-a", ta)
    a.write("m1", lambda p: p.set("hm:test:m1", b"a"))
    with pytest.raises(Fenced):
        b.write("m1", lambda p: p.set("hm:test:m1", b"b"))
    assert a.renew() == [] and a.stats.renewals == 1
    assert a.release("m1") and a.held() == []
    tb = b.acquire("m1")
    assert tb == ta + 1  # every taking gets a new token
    with pytest.raises(Fenced):
        a.write("m1", lambda p: p.set("hm:test:m1", b"a"))
    assert r.get("hm:test:m1") == b"a"
    assert (a.stats.released, a.stats.refused_writes, b.stats.acquired) == (1, 1, 1)
    r.close()


def test_an_expired_lease_is_taken_and_a_write_in_flight_is_refused(redis_url):
    """The owner checked its lease, then stalled inside its write past the lease time;
    another owner took the map: the stalled transaction is not applied."""
    r = connect(redis_url)
    a, b = Leases(r, "a", 0.2), Leases(r, "b", 0.2)
    assert a.acquire("m") is not None
    inside, go = threading.Event(), threading.Event()
    errors: list = []

    def fill(p):
        p.set("hm:test:m", b"a")
        inside.set()
        go.wait(5)

    def stalled():
        try:
            a.write("m", fill)
        except Fenced as e:
            errors.append(e)

    t = threading.Thread(target=stalled)
    t.start()
    assert inside.wait(5)
    assert _wait(lambda: b.acquire("m") is not None, 2)  # a's lease ran out
    b.write("m", lambda p: p.set("hm:test:m", b"b"))
    go.set()
    t.join(5)
    assert len(errors) == 1 and "taken during a write" in str(errors[0])
    assert r.get("hm:test:m") == b"b"
    assert a.renew() == ["m"] and a.held() == []
    r.close()


def test_a_lease_lapsed_unrenewed_that_nobody_took_is_taken_again_at_renewal(redis_url):
    """An owner that could not renew in time (starved of CPU, Redis busy) keeps its map
    when nobody took it meanwhile: a new token, writes go on; one another owner took is
    lost as before (the tests above)."""
    r = connect(redis_url)
    a = Leases(r, "mapper-a", LEASE_S)
    t = a.acquire("m")
    assert _wait(lambda: r.exists(k_lease("m")) == 0, 3 * LEASE_S)  # lapsed
    assert a.renew() == [] and a.held() == ["m"] and a.stats.retaken == 1
    assert a.owner_of("m") == ("mapper-a", t + 1)  # a new fencing token
    a.write("m", lambda p: p.set("hm:test:m", b"a"))
    assert r.get("hm:test:m") == b"a"
    assert Leases(r, "mapper-b", LEASE_S).acquire("m") is None  # held again
    r.close()


OWNER = textwrap.dedent("""
    import sys, time
    from shared.leases import Fenced, Leases
    from shared.store import connect
    r = connect(sys.argv[1])
    lz = Leases(r, "paused-owner", float(sys.argv[2]))
    assert lz.acquire("m") is not None
    print("owner", flush=True)
    renew_every = lz.lease_ms / 3000  # as the mapper renews (a third of the lease)
    last_renew = last_tick = time.monotonic()
    while True:
        # Resumed from a pause, its first act is a write with the lease it believes it
        # holds (the fencing must refuse it, not the renewal): a loop that finds more
        # than a renewal period gone since its last turn writes before it renews,
        # wherever in the loop the pause fell.
        now = time.monotonic()
        resumed, last_tick = now - last_tick > renew_every, now
        if not resumed and now - last_renew > renew_every:
            last_renew = now
            if lz.renew():
                print("lost", flush=True)
        try:
            lz.write("m", lambda p: (p.set("hm:test:last", b"paused-owner"),
                                     p.incr("hm:test:writes")))
        except Fenced as e:
            print("fenced", e, flush=True)
            time.sleep(0.05)
        time.sleep(0.01)
""")


def test_an_owner_paused_past_its_lease_cannot_write_after_resuming(redis_url, tmp_path):
    script = tmp_path / "owner.py"
    script.write_text(OWNER)
    env = {**os.environ, "PYTHONPATH": os.getcwd()}
    proc = subprocess.Popen([sys.executable, str(script), redis_url, str(LEASE_S)],
                            stdout=subprocess.PIPE, text=True, env=env)  # fmt: skip
    r = connect(redis_url)
    try:
        assert proc.stdout.readline().strip() == "owner"
        assert _wait(lambda: int(r.get("hm:test:writes") or 0) > 5, 10)
        taker = Leases(r, "taker", LEASE_S)
        assert taker.acquire("m") is None  # held and renewed
        os.kill(proc.pid, signal.SIGSTOP)
        t0 = time.monotonic()
        assert _wait(lambda: taker.acquire("m") is not None, 3 * LEASE_S)
        took_s = time.monotonic() - t0
        assert took_s < 2 * LEASE_S, took_s
        n_paused = int(r.get("hm:test:writes"))
        taker.write("m", lambda p: p.set("hm:test:last", b"taker"))
        os.kill(proc.pid, signal.SIGCONT)
        lines = []
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not any(x.startswith("fenced") for x in lines):
            lines.append(proc.stdout.readline().strip())
        # Refused at the check, or at EXEC when the pause fell inside a write.
        first = lines[0]
        assert first.startswith("fenced"), lines
        assert "is no longer paused-owner's" in first or "taken during a write" in first, lines
        time.sleep(0.5)  # the resumed owner keeps trying; every try is refused
        assert r.get("hm:test:last") == b"taker"
        assert int(r.get("hm:test:writes")) == n_paused
        print(f"lease taken {took_s:.2f} s after SIGSTOP (lease {LEASE_S} s); resumed "
              f"owner: {lines}")  # fmt: skip
    finally:
        os.kill(proc.pid, signal.SIGCONT)
        proc.kill()
        proc.wait()
        r.close()


def test_a_fenced_pipeline_of_two_maps_fails_when_one_is_taken(redis_url):
    r = connect(redis_url)
    a, b = Leases(r, "a", 0.2), Leases(r, "b", 0.2)
    a.acquire("m1"), a.acquire("m2")
    p = a.pipeline("m1", "m2")
    p.set("hm:test:x", b"a")
    time.sleep(0.3)  # both leases ran out; b takes one
    assert b.acquire("m2") is not None
    import redis

    with pytest.raises(redis.WatchError):
        p.execute()
    assert r.get("hm:test:x") is None
    with pytest.raises(Fenced):
        a.pipeline("m1", "m2")
    r.close()
