"""Real-time scheduling of the mapper (shared.runtime.set_realtime), in a child process
so the test runner keeps its own scheduling."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

CHILD = """
import json, os, resource, sys, threading
from shared.runtime import set_realtime
if len(sys.argv) > 1:  # drop to an unprivileged user with this RLIMIT_RTPRIO
    try:
        resource.setrlimit(resource.RLIMIT_RTPRIO, (int(sys.argv[1]),) * 2)
    except (ValueError, OSError) as e:  # raising it needs CAP_SYS_RESOURCE
        print(json.dumps({"skip": f"RLIMIT_RTPRIO {sys.argv[1]}: {e}"}))
        sys.exit(0)
    os.setgid(65534)
    os.setuid(65534)
before = threading.Event()
threading.Thread(target=before.wait, daemon=True).start()  # exists before the call
err = set_realtime(10)
pol = {}
def later():
    pol["later"] = os.sched_getscheduler(0)
t = threading.Thread(target=later); t.start(); t.join()
pol["self"] = os.sched_getscheduler(0)
pol["threads"] = sorted({os.sched_getscheduler(int(t)) for t in os.listdir("/proc/self/task")})
pol["priority"] = os.sched_getparam(0).sched_priority
print(json.dumps({"err": err, **pol}))
"""


def _child(*args: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True,
                         text=True, timeout=60)  # fmt: skip
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_set_realtime_covers_existing_and_later_threads():
    r = _child()
    if r["err"] is not None:
        assert os.geteuid() != 0, f"root could not set SCHED_RR: {r['err']}"
        pytest.skip(f"not permitted here: {r['err']}")
    assert r["self"] == r["later"] == os.SCHED_RR
    assert r["threads"] == [os.SCHED_RR]  # the thread started before the call too
    assert r["priority"] == 10


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to drop to an unprivileged user")
def test_set_realtime_without_privilege_says_why_and_changes_nothing():
    r = _child("0")
    assert "skip" not in r, r  # lowering a limit needs no privilege
    assert r["err"] and "SCHED_RR 10" in r["err"], r
    assert r["self"] == r["later"] == os.SCHED_OTHER
    assert r["threads"] == [os.SCHED_OTHER]


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to drop to an unprivileged user")
def test_set_realtime_within_the_rtprio_limit_needs_no_privilege():
    """What an RLIMIT_RTPRIO grants a non-root user (limits.conf, compose's ``ulimits``)."""

    r = _child("10")
    if "skip" in r:
        pytest.skip(r["skip"])
    assert r["err"] is None, r
    assert r["threads"] == [os.SCHED_RR]
