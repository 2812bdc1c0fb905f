"""Global ids: one int64 names a keyframe or map point across every agent; and where a
merged map id leads.

An agent's keyframe and map-point ids are its own small integers; the mapper gives each
agent an index (``hm:agent_index`` in ``shared.store``) and the global id is
``agent_index << ID_BITS | local_id``, so ids from different agents never collide and
arrays of ids stay plain int64. Every function works on ints and on numpy int arrays.

Local ids restart from 0 in every flight, so each flight of an agent id is stored as an
agent of its own, with its own index (``A``, ``A.s2``, ...: ``services/mapper/sessions.py``);
a second flight never meets the first one's ids.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

ID_BITS = 40  # local ids below 2**40; agent indices above
LOCAL_MASK = (1 << ID_BITS) - 1

IntOrArray = TypeVar("IntOrArray", int, np.ndarray)


def gid(agent_index: IntOrArray, local_id: IntOrArray) -> IntOrArray:
    return (agent_index << ID_BITS) | local_id


def agent_index_of(g: IntOrArray) -> IntOrArray:
    return g >> ID_BITS


def local_id_of(g: IntOrArray) -> IntOrArray:
    return g & LOCAL_MASK


def split_gid(g: int) -> tuple[int, int]:
    """(agent index, local id)."""
    return g >> ID_BITS, g & LOCAL_MASK


def resolve_map(merged_into: dict[str, str], map_id: str) -> str:
    """The map ``map_id`` lives on as: follows ``merged_into`` (map -> the map it was
    merged into) to the end of the chain; a cycle (never written, but read from peers)
    stops where it would repeat."""
    seen = set()
    while map_id in merged_into and map_id not in seen:
        seen.add(map_id)
        map_id = merged_into[map_id]
    return map_id


def resolve_map_scale(
    merged_into: dict[str, str], scale_of: dict[str, float], map_id: str
) -> tuple[str, float | None]:
    """:func:`resolve_map`, and the factor ``map_id``'s units were scaled by on the way
    there (the product of each merge's scale ``scale_of[map]``; None when one of them
    is not known)."""
    seen = set()
    s: float | None = 1.0
    while map_id in merged_into and map_id not in seen:
        seen.add(map_id)
        f = scale_of.get(map_id)
        s = None if s is None or f is None else s * f
        map_id = merged_into[map_id]
    return map_id, s


# Sets of ids as sorted int64 arrays. numpy's unique / isin / setdiff1d hash or merge-sort
# their inputs on every call (~0.5 ms each for a few thousand ids); the mapper does this
# for every keyframe's fusion and feedback chunk, where one sort and binary searches do.
def unique_ids(ids: np.ndarray) -> np.ndarray:
    """The distinct values of ``ids``, sorted (``np.unique`` without the hashing)."""
    s = np.sort(ids)
    if len(s) < 2:
        return s
    keep = np.empty(len(s), bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep]


def in_sorted(ids: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Mask of the ``ids`` found in ``ref``, which is sorted (``np.isin`` by binary
    search)."""
    if len(ref) == 0:
        return np.zeros(len(ids), bool)
    pos = np.searchsorted(ref, ids)
    np.minimum(pos, len(ref) - 1, out=pos)
    return ref[pos] == ids


def present_in(ref: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Mask over ``ref`` (sorted, distinct) of the values that occur in ``ids`` (any
    order, repeats allowed): ``np.isin(ref, ids)`` without sorting ``ids``."""
    out = np.zeros(len(ref), bool)
    if len(ref) == 0 or len(ids) == 0:
        return out
    pos = np.searchsorted(ref, ids)
    np.minimum(pos, len(ref) - 1, out=pos)
    out[pos[ref[pos] == ids]] = True
    return out
