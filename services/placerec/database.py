"""Inverted-file keyframe database over all maps, and loop-candidate consistency.

One database holds the BoW vectors of every keyframe of every server map (CCM-SLAM
§4.7); a query can be restricted to some maps or exclude some (intra-map place
recognition vs. map matching). Scoring and candidate selection follow ORB-SLAM's
``KeyFrameDatabase::DetectLoopCandidates``:

1. keyframes sharing words with the query, except the excluded ones (the query's
   covisible neighbours); keep those with more than 0.8x the most shared words;
2. their DBoW2 L1 score; drop those below ``min_score``, which defaults to the
   lowest score between the query and its own covisible neighbours;
3. accumulate each survivor's score with those of its best covisible neighbours
   that also passed step 1; the group is represented by its best keyframe;
4. return the groups scoring above 0.75x the best group.

The inverted file is flat numpy arrays (a word-sorted base and a short tail of the
newest keyframes, see ``KeyframeDatabase.__init__``), so adding a keyframe is a few
slice assignments and a query a vectorized gather and one ``np.bincount`` whatever the
number of keyframes. Removal marks a slot dead; entries are compacted once dead ones
outnumber live ones. Not thread-safe: one worker owns a database.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .vocabulary import BowVector

log = logging.getLogger(__name__)


def ranges(starts: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """Concatenated ``arange(s, s + n)`` for each (s, n): the entries of several ranges
    gathered at once (the inverted file's words, a feature vector's nodes)."""
    return np.repeat(starts - (np.cumsum(lens) - lens), lens) + np.arange(int(lens.sum()))


Covisibility = Callable[[int], Sequence[int]] | Mapping[int, Sequence[int]]


def _getter(covisible: Covisibility) -> Callable[[int], Sequence[int]]:
    if isinstance(covisible, Mapping):
        return lambda g: covisible.get(g, ())
    return covisible


@dataclass(frozen=True)
class Candidate:
    gid: int  # best keyframe of the group
    map_id: str
    score: float  # its own BoW score against the query
    group_score: float  # accumulated over its covisibility group
    common_words: int


@dataclass(frozen=True)
class QueryParams:
    min_common_ratio: float = 0.8
    group_size: int = 10  # best covisible neighbours accumulated per candidate
    retain_ratio: float = 0.75


class KeyframeDatabase:
    def __init__(self, n_words: int) -> None:
        self.n_words = int(n_words)
        # Inverted file in two parts. The base holds every entry (slot, weight) sorted
        # by word, with ``_b_start[w]:_b_start[w + 1]`` the entries of word w; the
        # tail holds the newest keyframes' entries as they came (slot by slot), and is
        # merged into the base once it grows past ``_TAIL_MAX`` entries or a quarter of
        # the base. A query takes its words' base ranges in one vectorized gather and
        # scans the short tail, so neither adding nor querying loops over words in
        # Python (per-word ``array.array`` lists cost a Python append per entry and a
        # ``np.frombuffer`` per word and query: a third of place recognition's CPU at
        # 8 agents).
        self._b_slot = np.zeros(0, np.int32)
        self._b_val = np.zeros(0, np.float64)
        self._b_start = np.zeros(self.n_words + 1, np.int64)
        self._t_word = np.zeros(0, np.int32)
        self._t_slot = np.zeros(0, np.int32)
        self._t_val = np.zeros(0, np.float64)
        self._t_len = 0
        self._in_query = np.zeros(self.n_words, bool)  # scratch: the query's words
        self._q_weight = np.zeros(self.n_words)  # scratch: the query's weight per word
        self._slot_of: dict[int, int] = {}
        self._gid = np.zeros(0, np.int64)
        self._map = np.zeros(0, np.int32)
        self._alive = np.zeros(0, bool)
        self._bows: list[BowVector | None] = []
        self._map_index: dict[str, int] = {}
        self._map_names: list[str] = []
        self._map_slots: dict[int, set[int]] = {}
        self._live_entries = 0
        self._dead_entries = 0

    # Entries (~80 keyframes), or a quarter of the base when larger: a merge is
    # O(database) and a query's scan O(tail), so a tail growing with the base keeps
    # the merges' total cost linear in the number of keyframes.
    _TAIL_MAX = 32768

    # -- bookkeeping -----------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._slot_of)

    def __contains__(self, gid: int) -> bool:
        return int(gid) in self._slot_of

    @property
    def n_entries(self) -> int:
        """Inverted-file entries held, dead ones not yet compacted away included."""
        return len(self._b_slot) + self._t_len

    def map_of(self, gid: int) -> str:
        return self._map_names[self._map[self._slot_of[int(gid)]]]

    def bow_of(self, gid: int) -> BowVector:
        bow = self._bows[self._slot_of[int(gid)]]
        assert bow is not None
        return bow

    def keyframes_of(self, map_id: str) -> list[int]:
        mi = self._map_index.get(map_id)
        if mi is None:
            return []
        return sorted(int(self._gid[s]) for s in self._map_slots[mi])

    def maps(self) -> list[str]:
        return [m for m, i in self._map_index.items() if self._map_slots[i]]

    def _map_idx(self, map_id: str) -> int:
        mi = self._map_index.get(map_id)
        if mi is None:
            mi = len(self._map_names)
            self._map_index[map_id] = mi
            self._map_names.append(map_id)
            self._map_slots[mi] = set()
        return mi

    def add(self, gid: int, map_id: str, bow: BowVector) -> None:
        """Insert a keyframe (re-adding a gid replaces its entry)."""
        gid = int(gid)
        if gid in self._slot_of:
            self.remove(gid)
        slot = len(self._bows)
        if slot >= len(self._gid):
            cap = max(64, 2 * len(self._gid))
            self._gid = np.resize(self._gid, cap)
            self._map = np.resize(self._map, cap)
            alive = np.zeros(cap, bool)
            alive[: len(self._alive)] = self._alive
            self._alive = alive
        mi = self._map_idx(map_id)
        self._gid[slot] = gid
        self._map[slot] = mi
        self._alive[slot] = True
        self._bows.append(bow)
        self._slot_of[gid] = slot
        self._map_slots[mi].add(slot)
        n, t = len(bow), self._t_len
        if t + n > len(self._t_word):
            cap = max(1024, 2 * (t + n))
            self._t_word = np.resize(self._t_word, cap)
            self._t_slot = np.resize(self._t_slot, cap)
            self._t_val = np.resize(self._t_val, cap)
        self._t_word[t : t + n] = bow.words
        self._t_slot[t : t + n] = slot
        self._t_val[t : t + n] = bow.weights
        self._t_len = t + n
        self._live_entries += n
        if self._t_len > max(self._TAIL_MAX, len(self._b_slot) // 4):
            self._merge_tail()

    def _merge_tail(self) -> None:
        """Move the tail into the base, after the base's entries of each word (so a
        word's entries stay in insertion order)."""
        t = self._t_len
        if t == 0:
            return
        order = np.argsort(self._t_word[:t], kind="stable")
        w = self._t_word[:t][order]
        # Tail entry i lands before the base entry that follows its word's range, i.e.
        # at that entry's index plus the i tail entries placed before it.
        to = self._b_start[w + 1] + np.arange(t)
        from_base = np.ones(len(self._b_slot) + t, bool)
        from_base[to] = False
        for name, tail in (("_b_slot", self._t_slot), ("_b_val", self._t_val)):
            base = getattr(self, name)
            merged = np.empty(len(from_base), base.dtype)
            merged[from_base] = base
            merged[to] = tail[:t][order]
            setattr(self, name, merged)
        counts = np.bincount(w, minlength=self.n_words)
        self._b_start[1:] += np.cumsum(counts)
        self._t_len = 0

    def remove(self, gid: int) -> bool:
        slot = self._slot_of.pop(int(gid), None)
        if slot is None:
            return False
        self._alive[slot] = False
        self._map_slots[int(self._map[slot])].discard(slot)
        n = len(self._bows[slot] or ())
        self._bows[slot] = None
        self._live_entries -= n
        self._dead_entries += n
        if self._dead_entries > max(self._live_entries, 10000):
            self._compact()
        return True

    def relabel_map(self, old: str, new: str) -> int:
        """All keyframes of map ``old`` now belong to ``new`` (map fusion); O(kfs of old)."""
        if old == new or old not in self._map_index:
            return 0
        mo, mn = self._map_index[old], self._map_idx(new)
        slots = self._map_slots[mo]
        if slots:
            idx = np.fromiter(slots, np.int64, len(slots))
            self._map[idx] = mn
        self._map_slots[mn] |= slots
        self._map_slots[mo] = set()
        return len(slots)

    def _compact(self) -> None:
        """Drop dead slots' entries (amortized by the doubling rule)."""
        keep = self._alive[self._b_slot]
        word = np.repeat(np.arange(self.n_words), np.diff(self._b_start))
        self._b_slot, self._b_val = self._b_slot[keep], self._b_val[keep]
        self._b_start = np.zeros(self.n_words + 1, np.int64)
        np.cumsum(np.bincount(word[keep], minlength=self.n_words), out=self._b_start[1:])
        t = self._t_len
        keep = self._alive[self._t_slot[:t]]
        k = int(keep.sum())
        self._t_word[:k] = self._t_word[:t][keep]
        self._t_slot[:k] = self._t_slot[:t][keep]
        self._t_val[:k] = self._t_val[:t][keep]
        self._t_len = k
        self._dead_entries = 0

    # -- queries -----------------------------------------------------------------------
    def score_all(
        self,
        bow: BowVector,
        exclude: Iterable[int] = (),
        maps: Iterable[str] | None = None,
        exclude_maps: Iterable[str] = (),
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(gids, L1 scores, shared word counts) of every allowed keyframe sharing a word."""
        words, weights = bow.words, bow.weights
        # Base: each word's range, gathered at once.
        start = self._b_start[words]
        lens = self._b_start[words + 1] - start
        pos = ranges(start, lens)
        slots, vals = self._b_slot[pos], self._b_val[pos]
        q = np.repeat(weights, lens)
        t = self._t_len
        if t:
            # Tail: its entries of the query's words. A slot's entries are all in the base
            # or all in the tail, each in word order, so every keyframe's sum below
            # adds its terms in the order the per-word lists did (the same floats).
            self._in_query[words] = True
            self._q_weight[words] = weights
            tw = self._t_word[:t]
            hit = np.flatnonzero(self._in_query[tw])
            q_hit = self._q_weight[tw[hit]]
            self._in_query[words] = False
            self._q_weight[words] = 0.0
            if len(hit):
                slots = np.concatenate([slots, self._t_slot[hit]])
                vals = np.concatenate([vals, self._t_val[hit]])
                q = np.concatenate([q, q_hit])
        if len(slots) == 0:
            e = np.zeros(0)
            return e.astype(np.int64), e, e.astype(np.int64)
        contrib = q + vals - np.abs(q - vals)
        n = len(self._bows)
        ok = self._allowed(n, exclude, maps, exclude_maps)
        acc = np.bincount(slots, weights=contrib, minlength=n)
        common = np.bincount(slots, minlength=n)
        sel = np.nonzero(ok & (common > 0))[0]
        return self._gid[sel].copy(), 0.5 * acc[sel], common[sel]

    def _allowed(
        self,
        n: int,
        exclude: Iterable[int],
        maps: Iterable[str] | None,
        exclude_maps: Iterable[str],
    ) -> np.ndarray:
        ok = self._alive[:n].copy()
        if maps is not None:
            want = [self._map_index[m] for m in maps if m in self._map_index]
            ok &= np.isin(self._map[:n], want)
        bad = [self._map_index[m] for m in exclude_maps if m in self._map_index]
        if bad:
            ok &= ~np.isin(self._map[:n], bad)
        ex = [self._slot_of[g] for g in map(int, exclude) if g in self._slot_of]
        if ex:
            ok[ex] = False
        return ok

    def min_neighbour_score(self, bow: BowVector, neighbours: Iterable[int]) -> float:
        """ORB-SLAM's minScore: the lowest score between the query and its covisible kfs."""
        slots = [self._slot_of.get(int(g)) for g in neighbours]
        bows = [b for s in slots if s is not None and (b := self._bows[s]) is not None]
        if not bows:
            return 0.0
        # ``bow_score`` per neighbour without its ``np.intersect1d`` (a sort per pair,
        # ~60 neighbours per query): the query's weights are looked up by word, for all
        # neighbours at once. The shared words come out in the same (ascending) order
        # with the same values and each neighbour's terms are summed on their own (a
        # slice, the same pairwise summation), so every score is the same float.
        words = bow.words
        self._in_query[words] = True
        self._q_weight[words] = bow.weights
        try:
            w = np.concatenate([b.words for b in bows])
            shared = np.flatnonzero(self._in_query[w])
            va = self._q_weight[w[shared]]
            vb = np.concatenate([b.weights for b in bows])[shared]
        finally:
            self._in_query[words] = False
            self._q_weight[words] = 0.0
        terms = np.abs(va) + np.abs(vb) - np.abs(va - vb)
        # Each neighbour's shared terms end before the first shared word past its own.
        ends = np.searchsorted(shared, np.cumsum([len(b) for b in bows])).tolist()
        scores = [float(0.5 * terms[a:b].sum()) for a, b in zip([0, *ends[:-1]], ends, strict=True)]
        return min(scores)

    def query(
        self,
        bow: BowVector,
        neighbours: Iterable[int],
        covisible: Covisibility,
        *,
        query_gid: int | None = None,
        exclude: Iterable[int] = (),
        maps: Iterable[str] | None = None,
        exclude_maps: Iterable[str] = (),
        min_score: float | None = None,
        params: QueryParams | None = None,
    ) -> list[Candidate]:
        """Loop / map-matching candidates for a query keyframe, best group first.

        ``neighbours``: the query's covisible keyframes (excluded, and they set the
        minimum score unless ``min_score`` is given). ``covisible(g)``: keyframe g's
        covisible keyframes, best first (only the first ``group_size`` are used).
        """
        p = params or QueryParams()
        neighbours = [int(g) for g in neighbours]
        if min_score is None:
            min_score = self.min_neighbour_score(bow, neighbours)
        excl = set(neighbours) | {int(g) for g in exclude}
        if query_gid is not None:
            excl.add(int(query_gid))
        gids, scores, common = self.score_all(bow, excl, maps, exclude_maps)
        if len(gids) == 0:
            return []
        min_common = p.min_common_ratio * common.max()
        eligible = common > min_common
        gids, scores, common = gids[eligible], scores[eligible], common[eligible]
        score_of = dict(zip(gids.tolist(), scores.tolist(), strict=True))
        cand = np.nonzero(scores >= min_score)[0]
        if len(cand) == 0:
            return []
        get = _getter(covisible)
        groups: dict[int, tuple[float, float, int]] = {}
        for i in cand.tolist():
            g = int(gids[i])
            best_g, best_s = g, float(scores[i])
            acc = best_s
            for nb in list(get(g))[: p.group_size]:
                s = score_of.get(int(nb))
                if s is None:
                    continue
                acc += s
                if s > best_s:
                    best_g, best_s = int(nb), s
            # Several candidates can elect the same best keyframe; keep its best group.
            if best_g not in groups or groups[best_g][0] < acc:
                groups[best_g] = (acc, best_s, 0)
        best_acc = max(v[0] for v in groups.values())
        keep = p.retain_ratio * best_acc
        common_of = dict(zip(gids.tolist(), common.tolist(), strict=True))
        out = [
            Candidate(g, self.map_of(g), s, acc, int(common_of[g]))
            for g, (acc, s, _) in groups.items()
            if acc > keep or acc == best_acc
        ]
        out.sort(key=lambda c: -c.group_score)
        return out


class ConsistencyChecker:
    """ORB-SLAM ``DetectLoop`` temporal consistency for one stream of queries (one
    agent or one map; the service keeps one checker per stream).

    A candidate's group is the candidate plus its covisible keyframes. Two groups
    are consistent when they share a keyframe. A candidate is accepted once its
    group continues a chain of consistent groups found by ``min_consecutive``
    consecutive queries (the query that first saw it counts as 1). A query with no
    candidate breaks every chain.
    """

    def __init__(self, min_consecutive: int = 3) -> None:
        self.min_consecutive = int(min_consecutive)
        self._groups: list[tuple[frozenset[int], int]] = []

    def reset(self) -> None:
        self._groups = []

    @property
    def groups(self) -> list[tuple[frozenset[int], int]]:
        return list(self._groups)

    def update(self, candidates: Iterable[int], covisible: Covisibility) -> list[int]:
        """Feed one query's candidate gids; returns those consistent enough."""
        get = _getter(covisible)
        current: list[tuple[frozenset[int], int]] = []
        used = [False] * len(self._groups)
        accepted: list[int] = []
        for c in candidates:
            c = int(c)
            group = frozenset([c, *map(int, get(c))])
            enough = False
            continued = False
            for i, (prev, n) in enumerate(self._groups):
                if group.isdisjoint(prev):
                    continue
                continued = True
                count = n + 1
                if not used[i]:
                    current.append((group, count))
                    used[i] = True
                if count >= self.min_consecutive and not enough:
                    accepted.append(c)
                    enough = True
            if not continued:
                current.append((group, 1))
        self._groups = current
        return accepted
