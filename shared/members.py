"""Who is in a pool of service instances, and which one a piece of work belongs to.

Membership is Zenoh's liveliness: each instance declares a token
``hivemap/pool/{pool}/{id}``, and every instance subscribes to the pool's tokens (with
history, so it learns the ones declared before it came). The router withdraws a token
when its session ends, a ``kill -9`` included (the TCP connection drops), so a dead
instance leaves every view within the router's notice of the drop -- no heartbeat of
our own, no expiry to tune.

Work is assigned by rendezvous hashing (highest random weight): ``owner(key)`` is the
member with the highest hash of (member, key). Every instance computes the same owner
from the same view without talking to the others, and when a member leaves only its
keys move (each to the member that was second for it); when one joins, only the keys
it now wins move to it. Views differ for a moment around a change (each instance hears
of it separately), so a key may briefly have two owners or none: users of this class
must tolerate a piece of work done twice or once late.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import threading
import uuid

import zenoh

from shared import keys

log = logging.getLogger(__name__)


def _weight(member: str, key: str) -> int:
    h = hashlib.blake2b(f"{member}\x00{key}".encode(), digest_size=8).digest()
    return int.from_bytes(h, "big")


def rendezvous(members: list[str] | set[str], key: str) -> str | None:
    """The member ``key`` belongs to (None when there is none)."""
    return max(members, key=lambda m: (_weight(m, key), m), default=None)


class Members:
    """This instance's membership of ``pool`` on an open Zenoh session, and its view of
    the others."""

    def __init__(self, session: zenoh.Session, pool: str, member_id: str | None = None) -> None:
        self.pool = keys.check_id(pool, "pool")
        self.id = keys.check_id(member_id or uuid.uuid4().hex[:12], "member")
        self._lock = threading.Lock()
        self._live: set[str] = {self.id}
        self.changes = 0  # membership changes seen (joins and leaves)
        prefix = f"{keys.ROOT}/pool/{self.pool}"
        self._token = session.liveliness().declare_token(f"{prefix}/{self.id}")
        self._sub = session.liveliness().declare_subscriber(
            f"{prefix}/*", self._on_sample, history=True
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        member = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                new = member not in self._live
                self._live.add(member)
            else:
                new = member in self._live and member != self.id
                self._live.discard(member)
                self._live.add(self.id)
            if new:
                self.changes += 1
        if new:
            log.info("pool %s: %s %s (%d members)", self.pool, member,
                     "joined" if sample.kind == zenoh.SampleKind.PUT else "left",
                     len(self._live))  # fmt: skip

    def live(self) -> list[str]:
        with self._lock:
            return sorted(self._live)

    def owner(self, key: str) -> str | None:
        with self._lock:
            return rendezvous(self._live, key)

    def mine(self, key: str) -> bool:
        return self.owner(key) == self.id

    def close(self) -> None:
        for x in (self._sub, self._token):
            with contextlib.suppress(Exception):  # the session may be closing already
                x.undeclare()
