"""The life of a long-running service process: metrics endpoint, start, wait for
SIGINT/SIGTERM, stop (which closes its Zenoh session: a process with a Python-callback
subscriber hangs at exit otherwise)."""

from __future__ import annotations

import errno
import logging
import os
import signal
import threading
from typing import Protocol

from shared.metrics import serve_metrics
from shared.settings import Settings


class Service(Protocol):
    def start(self) -> None: ...
    def stop(self) -> None: ...


log = logging.getLogger(__name__)


def set_autogroup_nice(nice: int, pid: int | str = "self") -> None:
    """Set the nice of the autogroup (scheduling group of a session) that ``pid`` leads;
    raises OSError where there is none (ENOENT) or it may not be changed."""
    with open(f"/proc/{pid}/autogroup", "w") as f:
        f.write(str(nice))


def set_priority(niceness: int) -> str | None:
    """Raise this process's niceness by ``niceness``; returns why it could not, or None.

    Linux with autogroup scheduling (the default on desktop and most server kernels)
    shares the CPU fairly between sessions first and applies nice only inside one: a
    service started in a session of its own (``hivemap up`` starts each so) would get
    as much CPU as the mapper whatever its nice value. So a session leader also sets
    its autogroup's nice, which is what ranks it against the other services. Safe to
    call between fork and exec (no logging, no locks)."""
    if niceness <= 0:
        return None
    try:
        new = os.nice(niceness)
    except OSError as e:
        return f"nice: {e}"
    if os.getsid(0) != os.getpid():
        return None  # the session is shared (a shell's): its group is not ours to change
    try:
        set_autogroup_nice(new)
    except OSError as e:
        # No autogroup (kernel without it, or containers where the file is read-only):
        # plain nice is then what the scheduler uses.
        return None if e.errno == errno.ENOENT else f"autogroup: {e}"
    return None


def set_realtime(priority: int) -> str | None:
    """Put every thread of this process under SCHED_RR at ``priority`` (threads created
    later inherit it from their creator); returns why it could not, or None. Where the
    process may not (no CAP_SYS_NICE and RLIMIT_RTPRIO below ``priority``; a container
    without SYS_NICE), nothing changes: it keeps normal scheduling."""
    if priority <= 0:
        return None
    param = os.sched_param(priority)
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        tids = [0]
    for tid in tids:
        try:
            os.sched_setscheduler(tid, os.SCHED_RR, param)
        except ProcessLookupError:
            continue  # the thread ended meanwhile
        except (OSError, AttributeError) as e:  # AttributeError: no SCHED_RR (not Linux)
            return f"SCHED_RR {priority}: {e}"
    return None


def raise_to_realtime(priority: int) -> bool:
    """:func:`set_realtime`, said in the log either way; True when it took effect."""
    if priority <= 0:
        return False
    err = set_realtime(priority)
    if err is not None:
        log.warning("normal scheduling (could not set %s); on a host whose cores are all "
                    "busy keyframe latency grows (grant CAP_SYS_NICE or an RLIMIT_RTPRIO "
                    "of %d, or set rt_priority 0 to silence this)", err, priority)  # fmt: skip
        return False
    log.info("real-time scheduling: SCHED_RR priority %d", priority)
    return True


def lower_priority(niceness: int) -> int:
    """Background services (place recognition, optimization) yield the CPU to the
    mapper. Set in-process so `hivemap up` and compose match."""
    err = set_priority(niceness)
    if err is not None:
        log.warning("could not lower priority by %d: %s", niceness, err)
    return os.nice(0)


def run_service(svc: Service, settings: Settings, niceness: int = 0) -> int:
    lower_priority(niceness)
    serve_metrics(settings.metrics_host, settings.metrics_port)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    svc.start()
    try:
        stop.wait()
    finally:
        svc.stop()
    return 0
