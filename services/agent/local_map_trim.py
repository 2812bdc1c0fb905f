"""Trimming of the agent's local map (CCM-SLAM §4.2), as a pure function.

Keep KF_ref and the N-1 newest keyframes. Older ones go if the server acknowledged
them; unacknowledged ones stay as a buffer of at most B. When the map holds more
than N + B keyframes, keyframes that came from other agents (through the server,
so the server has them) go first, then the oldest unacknowledged ones.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class KfInfo:
    id: int  # insertion order (larger = newer)
    own: bool  # created by this agent (False: received from the server)
    acked: bool  # the server confirmed it (always True for foreign keyframes)


def trim(kfs: list[KfInfo], kf_ref: int, n: int, b: int) -> list[int]:
    """Ids of the keyframes to remove."""
    if len(kfs) <= n:
        return []
    by_age = sorted(kfs, key=lambda k: k.id)
    others = [k for k in by_age if k.id != kf_ref]
    newest = {k.id for k in others[-(n - 1) :]} if n > 1 else set()
    keep = newest | {kf_ref}
    old = [k for k in by_age if k.id not in keep]
    remove = [k.id for k in old if k.acked]
    left = [k for k in old if not k.acked]
    # Unacknowledged own keyframes may stay as a buffer of at most b.
    excess = len(kfs) - len(remove) - (n + b)
    if excess > 0:
        # Foreign keyframes are on the server for sure: they go first, even recent
        # and strongly covisible ones (only KF_ref stays).
        foreign = [k.id for k in by_age if not k.own and k.id != kf_ref and k.id not in remove]
        take = foreign[:excess]
        remove += take
        excess -= len(take)
    if excess > 0:
        remove += [k.id for k in left if k.own][:excess]
    return sorted(set(remove))
