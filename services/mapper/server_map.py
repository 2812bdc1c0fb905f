"""The server map: keyframes, map points, observations, covisibility, spanning tree.

Pure data structure (no transport, no storage). Keyframes and map points are
identified map-wide by integer gids (``shared.ids``: agent index high, local id low), so ids from
different agents never collide and arrays of ids stay plain int64.

Graph definitions follow ORB-SLAM, as CCM-SLAM uses them (§4.2):
- covisibility: weight = number of map points two keyframes both observe; an edge
  exists from ``COVIS_MIN`` (15) shared points;
- spanning tree: each keyframe's parent is the keyframe it shared most points with
  when it was inserted;
- essential graph: spanning tree + covisibility edges of weight >= ``STRONG`` (100)
  + loop edges.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
from itertools import chain, compress, repeat
from operator import attrgetter, is_, is_not

import numpy as np

from shared.ids import agent_index_of, local_id_of, split_gid

COVIS_MIN = 15
STRONG = 100
NO_MP = -1

_dtype = attrgetter("dtype")
_obs = attrgetter("obs")


def stack_rows(rows: list[np.ndarray], dtype: np.dtype, width: int) -> np.ndarray:
    """``np.concatenate(rows).reshape(-1, width)`` of small arrays (points' positions or
    descriptors), as ``dtype``.

    Their bytes are joined and read back: numpy's per-array overhead in ``concatenate``
    (~300 ns each) was most of what gathering a few thousand points cost (point fusion,
    feedback chunks, keyframe events). Only when every row has ``dtype`` and is
    contiguous; anything else goes through ``concatenate``, so the values are the same."""
    dt = np.dtype(dtype)
    if set(map(_dtype, rows)) <= {dt}:
        try:
            # bytearray, not bytes: the result is writable, as concatenate's is.
            buf = bytearray().join(rows)
        except (TypeError, BufferError, ValueError):
            pass  # a non-contiguous row
        else:
            if len(buf) % (width * dt.itemsize) == 0:
                return np.frombuffer(buf, dt).reshape(-1, width)
    if not rows:
        return np.zeros((0, width), dt)
    return np.concatenate(rows).astype(dt, copy=False).reshape(-1, width)


@dataclass
class ServerKeyframe:
    gid: int
    agent: str
    id: int
    stamp_ns: int
    T_m_kf: np.ndarray
    T_l_kf: np.ndarray
    keypoints: np.ndarray  # (N, 2) float32 distorted pixels
    xy: np.ndarray  # (N, 2) undistorted normalized coordinates
    octaves: np.ndarray
    descriptors: np.ndarray  # (N, 32) uint8
    mp: np.ndarray  # (N,) int64 gid of the map point of each keypoint, -1 none
    parent: int = -1  # spanning-tree parent gid
    children: set[int] = field(default_factory=set)
    loop_edges: set[int] = field(default_factory=set)
    # Went through an optimization, global or windowed (its pose is settled, not the
    # frontier's first guess): the frame correction is fitted on such keyframes only.
    optimized: bool = False

    def observed(self) -> np.ndarray:
        return np.unique(self.mp[self.mp >= 0])


class ServerMapPoint:
    """A map point: ``pos`` (3,) in the map frame, ``descriptor`` (32,) uint8, ``ref_kf``
    the gid of the keyframe its position is anchored to, ``obs`` kf gid -> keypoint.

    ``pos`` and ``descriptor`` are mirrored into the :class:`PointTable` of the map that
    holds the point on every assignment (positions are replaced, never edited in
    place), so the map's hot paths gather thousands of them as arrays."""

    __slots__ = ("gid", "_pos", "_desc", "ref_kf", "obs", "_tab")

    def __init__(self, gid: int, pos: np.ndarray, descriptor: np.ndarray, ref_kf: int,
                 obs: dict[int, int] | None = None) -> None:  # fmt: skip
        self.gid = gid
        self._pos = pos
        self._desc = descriptor
        self.ref_kf = ref_kf
        self.obs: dict[int, int] = {} if obs is None else obs
        self._tab: PointTable | None = None

    @property
    def pos(self) -> np.ndarray:
        return self._pos

    @pos.setter
    def pos(self, v: np.ndarray) -> None:
        self._pos = v
        if self._tab is not None:
            self._tab.set_row(self.gid, "pos", v)

    @property
    def descriptor(self) -> np.ndarray:
        return self._desc

    @descriptor.setter
    def descriptor(self, v: np.ndarray) -> None:
        self._desc = v
        if self._tab is not None:
            self._tab.set_row(self.gid, "desc", v)

    def __repr__(self) -> str:
        return (f"ServerMapPoint(gid={self.gid}, pos={self._pos!r}, ref_kf={self.ref_kf}, "
                f"obs={self.obs!r})")  # fmt: skip


_raw_pos = attrgetter("_pos")
_raw_desc = attrgetter("_desc")
_set_raw_pos = ServerMapPoint._pos.__set__  # C speed, no mirroring (the caller mirrors)
_tab_of = attrgetter("_tab")
_set_tab = ServerMapPoint._tab.__set__
_gid_of = attrgetter("gid")
LOCAL_CAP = 1 << 22  # local ids a table mirrors (an agent's points over a long flight)
AGENT_CAP = 1 << 16  # agent indices a table mirrors (the store hands them out from 1)


class PointTable:
    """The positions and descriptors of a map's points as arrays, a block of rows per
    agent index with a row per local id (gids are ``agent_index << ID_BITS | local_id``
    and local ids count up from 0 in every flight), all blocks in one flat array, so a
    gather of thousands of gids is one fancy indexing instead of a dict lookup and an
    attribute read per point (those were about a third of the mapper's CPU per
    keyframe at 16 agents: point fusion, feedback chunks and keyframe events each
    gathered a few thousand points from a dict of 300k objects; a block per agent in
    arrays of their own cost a pass per agent, 6 % of the mapper at 24 agents). A
    mirror only: the map's dict of points stays the truth, and a gid the table does not
    hold (not yet mirrored, a local id past ``LOCAL_CAP``, an agent index past
    ``AGENT_CAP``) makes a gather return None, so the caller reads the objects."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self._pos = np.zeros((0, 3))
        self._desc = np.zeros((0, 32), np.uint8)
        self._has = np.zeros(0, bool)
        self._start = np.zeros(0, np.int64)  # agent index -> its block's first row
        self._cap = np.zeros(0, np.int64)  # agent index -> its block's rows (0: none)
        self._used = 0  # rows of the flat arrays given to blocks

    def _rows(self, ai: np.ndarray, li: np.ndarray) -> np.ndarray | None:
        """Flat rows of (agent index, local id) pairs; None when one is outside every
        block."""
        if len(ai) and (ai.min() < 0 or ai.max() >= len(self._start)):
            return None
        if (li >= self._cap[ai]).any():  # li >= 0 always: the low bits of a gid
            return None
        return self._start[ai] + li

    def _block(self, a: int, li_max: int) -> bool:
        """Makes the block of agent index ``a`` hold local id ``li_max`` (a new block at
        the end, twice the size, when it is full); False when it may not."""
        if not 0 <= a < AGENT_CAP or not 0 <= li_max < LOCAL_CAP:
            return False
        if a >= len(self._start):
            k = a + 1 - len(self._start)
            self._start = np.concatenate([self._start, np.zeros(k, np.int64)])
            self._cap = np.concatenate([self._cap, np.zeros(k, np.int64)])
        n, s0 = int(self._cap[a]), int(self._start[a])
        if li_max < n:
            return True
        m = min(max(2 * n, li_max + 1, 1024), LOCAL_CAP)
        need = self._used + m
        if need > len(self._has):
            size = max(2 * len(self._has), need)
            pos, desc, has = (
                np.zeros((size, 3)),
                np.zeros((size, 32), np.uint8),
                np.zeros(size, bool),
            )
            u = self._used
            pos[:u], desc[:u], has[:u] = self._pos[:u], self._desc[:u], self._has[:u]
            self._pos, self._desc, self._has = pos, desc, has
        s = self._used
        if n:
            for arr in (self._pos, self._desc, self._has):
                arr[s : s + n] = arr[s0 : s0 + n]
            self._has[s0 : s0 + n] = False
        self._start[a], self._cap[a], self._used = s, m, need
        return True

    def bind(self, points: list[ServerMapPoint]) -> None:
        """Mirror ``points`` (which the map now holds); a point another table mirrored
        leaves that one."""
        if not points:
            return
        # Binding at C speed: a batch brings ~100 new points (bound to no table yet).
        for p in compress(points, map(is_not, map(_tab_of, points), repeat(None))):
            if p._tab is not self:
                p._tab.unbind(p)
        deque(map(_set_tab, points, repeat(self)), maxlen=0)
        if len(points) < 16:  # one by one costs less than the arrays' setup
            for p in points:
                self._put(p)
            return
        g = np.fromiter(map(_gid_of, points), np.int64, len(points))
        P = stack_rows(list(map(_raw_pos, points)), np.float64, 3)
        D = stack_rows(list(map(_raw_desc, points)), np.uint8, 32)
        ai, li = agent_index_of(g), local_id_of(g)
        ok = len(P) == len(g) and len(D) == len(g)
        for a in np.unique(ai).tolist() if ok else ():
            ok = self._block(a, int(li[ai == a].max())) and ok
        rows = self._rows(ai, li) if ok else None
        if rows is None:
            for p in points:  # a malformed row or an id past the caps: whatever mirrors
                self._put(p)
            return
        self._pos[rows], self._desc[rows], self._has[rows] = P, D, True

    def _put(self, p: ServerMapPoint) -> None:
        a, i = split_gid(p.gid)
        if not self._block(a, i):
            return
        r = int(self._start[a]) + i
        try:
            self._pos[r], self._desc[r] = p._pos, p._desc
        except (ValueError, TypeError):
            self._has[r] = False
            return
        self._has[r] = True

    def _row(self, g: int) -> int:
        """The flat row of gid ``g``, or -1 when no block holds it."""
        a, i = split_gid(g)
        if 0 <= a < len(self._start) and i < self._cap[a]:
            return int(self._start[a]) + i
        return -1

    def unbind(self, p: ServerMapPoint) -> None:
        if p._tab is self:
            p._tab = None
        r = self._row(p.gid)
        if r >= 0:
            self._has[r] = False

    def set_row(self, g: int, what: str, v: np.ndarray) -> None:
        """Row ``what`` ("pos" or "desc") of gid ``g`` is now ``v`` (a value that does
        not fit leaves the row unheld: gathers then read the object)."""
        r = self._row(g)
        if r < 0:
            return
        try:
            (self._pos if what == "pos" else self._desc)[r] = v
        except (ValueError, TypeError):
            self._has[r] = False

    def set_positions(self, g: np.ndarray, P: np.ndarray) -> None:
        ai, li = agent_index_of(g), local_id_of(g)
        ok = (ai >= 0) & (ai < len(self._start))
        ok[ok] &= li[ok] < self._cap[ai[ok]]
        self._pos[self._start[ai[ok]] + li[ok]] = P[ok]

    def gather(self, g: np.ndarray, what: str) -> np.ndarray | None:
        """Rows ``what`` ("pos" or "desc") of gids ``g`` (int64), or None when the table
        does not hold every one of them."""
        src = self._pos if what == "pos" else self._desc
        rows = self._rows(agent_index_of(g), local_id_of(g))
        if rows is None or not self._has[rows].all():
            return None
        return src[rows]


class PointDict(dict):
    """A map's points by gid (a dict, read at C speed as before) that keeps the map's
    :class:`PointTable` mirrored through every insertion and removal."""

    __slots__ = ("table",)

    def __init__(self, *a, **kw) -> None:
        super().__init__()
        self.table = PointTable()
        if a or kw:
            self.update(*a, **kw)

    def __setitem__(self, g: int, p: ServerMapPoint) -> None:
        old = dict.get(self, g)
        if old is not None and old is not p:
            self.table.unbind(old)
        dict.__setitem__(self, g, p)
        self.table.bind([p])

    def __delitem__(self, g: int) -> None:
        p = dict.pop(self, g)
        self.table.unbind(p)

    def pop(self, g: int, *default):
        if g in self:
            p = dict.pop(self, g)
            self.table.unbind(p)
            return p
        if default:
            return default[0]
        raise KeyError(g)

    def popitem(self):
        g, p = dict.popitem(self)
        self.table.unbind(p)
        return g, p

    def setdefault(self, g: int, p: ServerMapPoint | None = None):
        if g in self:
            return dict.__getitem__(self, g)
        self[g] = p
        return p

    def update(self, *a, **kw) -> None:
        other = a[0] if len(a) == 1 and not kw and type(a[0]) is dict else dict(*a, **kw)
        for g in self.keys() & other.keys():  # replaced ones (almost never)
            old = dict.__getitem__(self, g)
            if old is not other[g]:
                self.table.unbind(old)
        dict.update(self, other)
        self.table.bind(list(other.values()))

    def __ior__(self, other):
        self.update(other)
        return self

    def clear(self) -> None:
        for p in dict.values(self):
            if p._tab is self.table:
                p._tab = None
        dict.clear(self)
        self.table.clear()

    def copy(self) -> dict:
        """A plain dict of the same points (a snapshot; it mirrors nothing)."""
        return dict(self)


class ServerMap:
    def __init__(self, map_id: str) -> None:
        self.map_id = map_id
        self.kfs: dict[int, ServerKeyframe] = {}
        self._mps = PointDict()
        self.covis: dict[int, Counter] = {}
        self.agents: set[str] = set()
        # Culled keyframes: gid -> (anchor gid, T_anchor_kf), so later keyframes that
        # name one as predecessor still register, and trajectories keep it.
        self.culled: dict[int, tuple[int, np.ndarray]] = {}
        self.version = 0  # bumped on every change; optimizers compare it
        # Gids of points added while a correction is worked out off the map's lock
        # (see ``record_new_points``).
        self._journals: list[list[int]] = []

    @property
    def mps(self) -> PointDict:
        """Points by gid. Assigning a plain dict makes it a :class:`PointDict`."""
        return self._mps

    @mps.setter
    def mps(self, d: dict) -> None:
        self._mps = d if isinstance(d, PointDict) else PointDict(d)

    def positions(self, gids: np.ndarray) -> np.ndarray:
        """(N, 3) positions of points ``gids`` (int64; KeyError for one the map lacks)."""
        g = np.asarray(gids, np.int64)
        P = self._mps.table.gather(g, "pos")
        if P is None:
            P = stack_rows(list(map(_raw_pos, map(self._mps.__getitem__, g.tolist()))),
                           np.float64, 3)  # fmt: skip
        return P

    def descriptors(self, gids: np.ndarray) -> np.ndarray:
        """(N, 32) uint8 descriptors of points ``gids`` (KeyError for one the map lacks)."""
        g = np.asarray(gids, np.int64)
        D = self._mps.table.gather(g, "desc")
        if D is None:
            D = stack_rows(list(map(_raw_desc, map(self._mps.__getitem__, g.tolist()))),
                           np.uint8, 32)  # fmt: skip
        return D

    def set_positions(self, points: list[ServerMapPoint], P: np.ndarray,
                      rows: list[np.ndarray] | None = None) -> None:  # fmt: skip
        """``points[i].pos = P[i]`` for each ((N, 3) array; each point's position becomes
        a row view of it, or ``rows[i]`` when given: views made ahead, off the lock), at C
        speed and mirrored in one write per table: a correction or merge moves up to 330k
        points under the map's lock."""
        P = np.asarray(P, np.float64).reshape(-1, 3)
        if len(P) != len(points):
            raise ValueError(f"{len(points)} points, {len(P)} positions")
        if not points:
            return
        deque(map(_set_raw_pos, points, P if rows is None else rows), maxlen=0)
        tabs = list(map(_tab_of, points))
        g = np.fromiter(map(_gid_of, points), np.int64, len(points))
        # The tables at C speed (a comprehension over 60k points cost more than the
        # writes); a table hashes by identity.
        held = set(tabs) - {None}
        if held == {tabs[0]} and None not in tabs:  # all in one table (the usual case)
            tabs[0].set_positions(g, P)
            return
        for t in held:
            m = np.fromiter(map(is_, tabs, repeat(t)), bool, len(tabs))
            t.set_positions(g[m], P[m])

    # --- keyframes ------------------------------------------------------------------------
    def add_keyframe(self, kf: ServerKeyframe) -> None:
        """Insert a keyframe; its ``mp`` entries that name known points become observations."""
        if kf.gid in self.kfs:
            raise KeyError(f"keyframe {kf.gid} already in map {self.map_id}")
        self.kfs[kf.gid] = kf
        self.agents.add(kf.agent)
        mp = kf.mp
        g = kf.gid
        idx = np.nonzero(mp >= 0)[0]
        # A second keypoint on the same point is dropped (numpy, not a Python set: this
        # runs over every keypoint of every keyframe). A plain sort tells whether there
        # is one at all (almost never), at a fraction of unique's return_index.
        s = np.sort(mp[idx])
        if len(s) > 1 and (s[1:] == s[:-1]).any():
            _, first = np.unique(mp[idx], return_index=True)
            dup = np.ones(len(idx), dtype=bool)
            dup[first] = False
            mp[idx[dup]] = NO_MP
            idx = idx[~dup]
        # Lookups, the unknown points' mask, the observer dicts and the writes into them
        # go through map() at C speed: Python loops over the ~1000 keypoints were a
        # third of an insertion.
        pts = list(map(self.mps.get, mp[idx].tolist()))
        known = np.fromiter(map(is_not, pts, repeat(None)), bool, len(pts))
        if not known.all():
            mp[idx[~known]] = NO_MP  # unknown points
            idx = idx[known]
            pts = list(compress(pts, known.tolist()))
        obs = list(map(_obs, pts))
        # A new keyframe has no edges yet: count all co-observers at C speed, then
        # mirror the counts (this is the hot path of every keyframe insertion).
        c = Counter(chain.from_iterable(obs))
        self.covis[g] = c
        covis = self.covis
        for o, n in c.items():
            covis[o][g] = n
        deque(map(dict.__setitem__, obs, repeat(g), idx.tolist()), maxlen=0)
        best = self.best_covisible(kf.gid, exclude_newer=False)
        if best is not None:
            kf.parent = best
            self.kfs[best].children.add(kf.gid)
        self.version += 1

    def _observe(self, kf: ServerKeyframe, j: int, p: ServerMapPoint) -> None:
        c = self.covis[kf.gid]
        for other in p.obs:
            c[other] += 1
            self.covis[other][kf.gid] += 1
        p.obs[kf.gid] = j
        kf.mp[j] = p.gid

    def add_observation(self, kf_gid: int, kp: int, mp_gid: int) -> bool:
        kf = self.kfs.get(kf_gid)
        p = self.mps.get(mp_gid)
        if kf is None or p is None or kf_gid in p.obs or not 0 <= kp < len(kf.mp):
            return False
        if kf.mp[kp] >= 0:
            self._unobserve(kf, kp)
        self._observe(kf, kp, p)
        self.version += 1
        return True

    def drop_observation(self, kf_gid: int, mp_gid: int) -> bool:
        """Remove keyframe ``kf_gid``'s observation of point ``mp_gid`` (an outlier the
        optimizer found), unless it is one of the point's last two."""
        kf, p = self.kfs.get(kf_gid), self.mps.get(mp_gid)
        if kf is None or p is None or kf_gid not in p.obs or len(p.obs) <= 2:
            return False
        self._unobserve(kf, p.obs[kf_gid])
        return True

    def _unobserve(self, kf: ServerKeyframe, j: int) -> None:
        p = self.mps.get(int(kf.mp[j]))
        kf.mp[j] = NO_MP
        if p is None or p.obs.get(kf.gid) != j:
            return
        del p.obs[kf.gid]
        c = self.covis[kf.gid]
        for other in p.obs:
            c[other] -= 1
            if c[other] <= 0:
                del c[other]
            oc = self.covis[other]
            oc[kf.gid] -= 1
            if oc[kf.gid] <= 0:
                del oc[kf.gid]

    def remove_keyframe(self, kf_gid: int) -> list[int]:
        """Remove a keyframe with its observations; points left with no observation go
        too (their gids are returned). Children move to their best covisible keyframe."""
        kf = self.kfs[kf_gid]
        seen = kf.observed().tolist()
        # Every edge of this keyframe goes, so its observations are dropped without
        # the per-observer counter updates of _unobserve (which made a removal cost
        # points x observers); the edges are cut below in one pass over its row.
        idx = np.nonzero(kf.mp >= 0)[0]
        get = self.mps.get
        for j, p in zip(idx.tolist(), map(get, kf.mp[idx].tolist()), strict=True):
            if p is not None and p.obs.get(kf_gid) == j:
                del p.obs[kf_gid]
        kf.mp[idx] = NO_MP
        dead = []
        for g, p in zip(seen, map(get, seen), strict=True):
            if p is None:
                continue
            if not p.obs:
                dead.append(g)
                del self.mps[g]
            elif p.ref_kf == kf_gid:
                # Its position stays; only the anchor for later corrections moves.
                p.ref_kf = next(iter(p.obs))
        for other in list(self.covis.pop(kf_gid, {})):
            self.covis[other].pop(kf_gid, None)
        del self.kfs[kf_gid]
        if kf.parent in self.kfs:
            self.kfs[kf.parent].children.discard(kf_gid)
        for ch in kf.children:
            c = self.kfs.get(ch)
            if c is None:
                continue
            new_parent = self.best_covisible(ch, exclude=set(kf.children) | {kf_gid})
            if new_parent is None and kf.parent in self.kfs:
                new_parent = kf.parent
            c.parent = -1 if new_parent is None else new_parent
            if new_parent is not None:
                self.kfs[new_parent].children.add(ch)
        for other in kf.loop_edges:
            if other in self.kfs:
                self.kfs[other].loop_edges.discard(kf_gid)
        self.version += 1
        return dead

    # --- map points ----------------------------------------------------------------------
    def add_map_point(self, p: ServerMapPoint) -> None:
        if p.gid in self.mps:
            raise KeyError(f"map point {p.gid} already in map {self.map_id}")
        self.mps[p.gid] = p
        for j in self._journals:
            j.append(p.gid)
        self.version += 1

    def add_map_points(self, points: list[ServerMapPoint]) -> None:
        """:meth:`add_map_point` of each, in order, in one dict update (a keyframe brings
        ~100 new points)."""
        gids = [p.gid for p in points]
        if len(set(gids)) < len(gids) or not self.mps.keys().isdisjoint(gids):
            for p in points:  # raises at the first one the map has, as one by one
                self.add_map_point(p)
            return
        self.mps.update(zip(gids, points, strict=True))
        for j in self._journals:
            j.extend(gids)
        self.version += len(points)

    def absorb_points(self, points: dict[int, ServerMapPoint]) -> None:
        """Take in another map's points (a merge)."""
        self.mps.update(points)
        for j in self._journals:
            j.extend(points)

    def record_new_points(self) -> list[int]:
        """From now on, the gid of every point added to this map is appended to the list
        returned, until :meth:`stop_recording` (a correction planned off the map's lock
        learns from it which points came in meanwhile without a pass over all of them)."""
        j: list[int] = []
        self._journals.append(j)
        return j

    def stop_recording(self, journal: list[int]) -> None:
        # In place, not a rebuilt list: called again off the lock (a correction's
        # ``finally``), a rebuild could drop a journal another thread began meanwhile.
        for i, j in enumerate(self._journals):
            if j is journal:
                del self._journals[i]
                return

    def fuse(self, keep: int, drop: int) -> None:
        """Merge duplicate point ``drop`` into ``keep`` (observations move over; a
        keyframe that observes both keeps its observation of ``keep``).

        Covisibility changes only where the two points' observers differ: with D and K
        their observers, a pair of keyframes in D & K loses the one point it shared
        through ``drop``, and a keyframe of D - K gains one with each of K - D; every
        other pair loses ``drop`` and gains ``keep``. Counting just that, instead of
        unobserving and observing each of D's keyframes (|D| x (|D| + |K|) counter
        updates), matters because matched points are the most observed ones: a merge's
        or loop's fusion held the map's lock for up to half a second."""
        if keep == drop or keep not in self.mps or drop not in self.mps:
            return
        pk, pd = self.mps[keep], self.mps[drop]
        kobs = pk.obs
        both = [g for g in pd.obs if g in kobs]
        new = [g for g in pd.obs if g not in kobs]
        only_k = [g for g in kobs if g not in pd.obs]
        covis = self.covis
        for i, a in enumerate(both):
            ca = covis[a]
            for b in both[i + 1 :]:
                cb = covis[b]
                ca[b] -= 1
                if ca[b] <= 0:
                    del ca[b]
                cb[a] -= 1
                if cb[a] <= 0:
                    del cb[a]
        if new and only_k:
            # Counter.update of an iterable counts at C speed.
            for a in new:
                covis[a].update(only_k)
            for b in only_k:
                covis[b].update(new)
        for g, j in pd.obs.items():
            kf = self.kfs[g]
            if g in kobs:
                kf.mp[j] = NO_MP
            else:
                kf.mp[j] = keep
                kobs[g] = j
        pd.obs = {}
        del self.mps[drop]
        self.version += 1

    # --- queries -------------------------------------------------------------------------
    def best_covisible(
        self, kf_gid: int, exclude: set[int] | None = None, exclude_newer: bool = False
    ) -> int | None:
        c = self.covis.get(kf_gid)
        if not c:
            return None
        best, w = None, 0
        for other, n in c.items():
            if exclude and other in exclude:
                continue
            if n > w:
                best, w = other, n
        return best

    def covisible(self, kf_gid: int, k: int | None = None, min_weight: int = COVIS_MIN):
        """Neighbours with at least ``min_weight`` shared points, strongest first."""
        c = self.covis.get(kf_gid, {})
        items = sorted(((n, o) for o, n in c.items() if n >= min_weight), reverse=True)
        return [o for _, o in items[:k]] if k else [o for _, o in items]

    def essential_edges(self) -> list[tuple[int, int, str]]:
        edges: set[tuple[int, int, str]] = set()
        for g, kf in self.kfs.items():
            if kf.parent in self.kfs:
                edges.add((min(g, kf.parent), max(g, kf.parent), "tree"))
            for o, n in self.covis[g].items():
                if n >= STRONG and g < o:
                    edges.add((g, o, "strong"))
            for o in kf.loop_edges:
                if o in self.kfs:
                    edges.add((min(g, o), max(g, o), "loop"))
        return sorted(edges)

    def recount_covisibility(self) -> dict[int, Counter]:
        """Covisibility recomputed from observations (the invariant check's reference)."""
        out: dict[int, Counter] = {g: Counter() for g in self.kfs}
        for p in self.mps.values():
            obs = list(p.obs)
            for i, a in enumerate(obs):
                for b in obs[i + 1 :]:
                    out[a][b] += 1
                    out[b][a] += 1
        return out

    def check_invariants(self) -> list[str]:
        """Every observation points at an existing point and back; covisibility equals a
        recount. Returns the violations (empty when the map is consistent)."""
        errs = []
        for g, kf in self.kfs.items():
            for j in np.nonzero(kf.mp >= 0)[0].tolist():
                p = self.mps.get(int(kf.mp[j]))
                if p is None:
                    errs.append(f"kf {g} kp {j} -> missing point {int(kf.mp[j])}")
                elif p.obs.get(g) != j:
                    errs.append(f"kf {g} kp {j} -> point {p.gid} without back reference")
        for pg, p in self.mps.items():
            for kg, j in p.obs.items():
                kf = self.kfs.get(kg)
                if kf is None or kf.mp[j] != pg:
                    errs.append(f"point {pg} -> kf {kg} kp {j} without back reference")
        errs += self._table_errors()
        ref = self.recount_covisibility()
        for g in self.kfs:
            got = {o: n for o, n in self.covis.get(g, {}).items() if n > 0}
            want = {o: n for o, n in ref[g].items() if n > 0}
            if got != want:
                errs.append(f"covisibility of kf {g} differs from recount")
        return errs

    def _table_errors(self) -> list[str]:
        """The point table mirrors every point's position and descriptor."""
        errs = []
        tab = self._mps.table
        for g, p in self._mps.items():
            if p.gid != g:
                errs.append(f"point {p.gid} stored under gid {g}")
            elif p._tab is not tab:
                errs.append(f"point {g} not mirrored by its map's table")
        g = np.fromiter(self._mps.keys(), np.int64, len(self._mps))
        pts = list(self._mps.values())
        for what, get, dt, w in (("pos", _raw_pos, np.float64, 3),
                                 ("desc", _raw_desc, np.uint8, 32)):  # fmt: skip
            got = tab.gather(g, what)
            want = stack_rows(list(map(get, pts)), dt, w)
            if got is None:
                if len(g) and max(local_id_of(g).tolist()) < LOCAL_CAP:
                    errs.append(f"point table lacks some of the map's points ({what})")
            elif not np.array_equal(got, want):
                errs.append(f"point table's {what} differs from the points'")
        return errs


def digest(smap: ServerMap) -> dict:
    """A comparable summary of a map: ids, point positions, observations, covisibility."""
    import hashlib

    h = hashlib.sha256()
    for g in sorted(smap.kfs):
        kf = smap.kfs[g]
        h.update(np.int64(g).tobytes())
        h.update(np.round(kf.T_m_kf, 9).tobytes())
        h.update(kf.mp.astype(np.int64).tobytes())
    kf_hash = h.hexdigest()
    h = hashlib.sha256()
    for g in sorted(smap.mps):
        h.update(np.int64(g).tobytes())
        h.update(np.round(smap.mps[g].pos, 9).tobytes())
    mp_hash = h.hexdigest()
    h = hashlib.sha256()
    for a in sorted(smap.covis):
        for b, w in sorted(smap.covis[a].items()):
            if w > 0:
                h.update(np.array([a, b, w], np.int64).tobytes())
    return {
        "map": smap.map_id, "n_kf": len(smap.kfs), "n_mp": len(smap.mps),
        "kf_hash": kf_hash, "mp_hash": mp_hash, "covis_hash": h.hexdigest(),
        "parents_hash": hashlib.sha256(np.array(
            [[g, smap.kfs[g].parent] for g in sorted(smap.kfs)], np.int64).tobytes()).hexdigest(),
    }  # fmt: skip
