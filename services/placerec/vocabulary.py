"""Bag-of-words vocabulary for 256-bit ORB descriptors (DBoW2 style).

A k-ary tree of binary cluster centres built by hierarchical k-majority (k-medians
on bits: a centre is the bitwise majority of its members) with k-means++ seeding.
Leaves are the words; each word carries an idf weight, and an image becomes an
L1-normalized tf-idf vector. Like ORB-SLAM, every keypoint also remembers the
node it passed at ``fv_level`` (the "feature vector"), which restricts descriptor
matching between two keyframes to keypoints under the same node.

Descriptors are handled as (N, 4) uint64 so a Hamming distance is one XOR and
``np.bitwise_count`` per word (``shared.orb.hamming_u64``); the tree descent is vectorized over all
descriptors one level at a time (no per-descriptor Python loop).
"""

from __future__ import annotations

import json
import logging
from collections import deque
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from shared.orb import as_u64, hamming_u64

__all__ = ["as_u64", "hamming_u64"]  # where the place-recognition modules find them

log = logging.getLogger(__name__)

DEFAULT_FILE = "orb_k10_l5.npz"
FORMAT = "hivemap.vocab/1"


def default_path() -> Path:
    return Path(str(resources.files("services.placerec") / "data" / DEFAULT_FILE))


@dataclass(frozen=True)
class BowVector:
    """Sparse L1-normalized tf-idf vector: sorted word ids and their weights."""

    words: np.ndarray  # (M,) int32, sorted, unique
    weights: np.ndarray  # (M,) float64, sum 1 (empty for an empty image)

    def __len__(self) -> int:
        return len(self.words)


@dataclass(frozen=True)
class FeatureVector:
    """Keypoints grouped by their vocabulary node at ``fv_level`` (CSR layout).

    Keypoints ``order[offsets[i]:offsets[i + 1]]`` descend through node ``nodes[i]``.
    """

    nodes: np.ndarray  # (G,) int32, sorted node ids
    offsets: np.ndarray  # (G + 1,) int64
    order: np.ndarray  # (N,) int64 keypoint indices grouped by node

    @staticmethod
    def from_nodes(node_of_kp: np.ndarray) -> FeatureVector:
        order = np.argsort(node_of_kp, kind="stable")
        nodes, start = np.unique(node_of_kp[order], return_index=True)
        offsets = np.r_[start, len(order)].astype(np.int64)
        return FeatureVector(nodes.astype(np.int32), offsets, order.astype(np.int64))

    def __len__(self) -> int:
        return len(self.nodes)


def bow_score(a: BowVector, b: BowVector) -> float:
    """DBoW2 L1 score in [0, 1]: 1 - |a - b|_1 / 2 for L1-normalized vectors."""
    _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    va, vb = a.weights[ia], b.weights[ib]
    return float(0.5 * (np.abs(va) + np.abs(vb) - np.abs(va - vb)).sum())


class Vocabulary:
    """A trained vocabulary tree. Node 0 is the root; words are the leaves.

    ``children[n]`` holds up to k child node ids (-1 pads), ``word_of_node[n]`` the
    word id of a leaf (-1 for inner nodes), ``idf[w]`` the weight of word w.
    """

    def __init__(
        self,
        k: int,
        levels: int,
        node_desc: np.ndarray,
        children: np.ndarray,
        depth: np.ndarray,
        idf: np.ndarray,
        word_of_node: np.ndarray,
        fv_level: int = 2,
        meta: dict | None = None,
    ) -> None:
        self.k = int(k)
        self.levels = int(levels)
        self.node_desc = np.ascontiguousarray(node_desc, dtype=np.uint8)  # (n_nodes, 32)
        self.children = np.asarray(children, dtype=np.int32)  # (n_nodes, k)
        self.depth = np.asarray(depth, dtype=np.int8)  # (n_nodes,)
        self.idf = np.asarray(idf, dtype=np.float64)  # (n_words,)
        self.word_of_node = np.asarray(word_of_node, dtype=np.int32)
        self.fv_level = int(fv_level)
        self.meta = dict(meta or {})
        self._has_children = self.children[:, 0] >= 0
        # The descent's tables per inner node: its children's ids, their descriptors as
        # one (k, 4) block (a row gather copies a block where a gather of node ids
        # copied k scattered rows), and which of its slots are padding (only ~200
        # nodes have fewer than k children). A padded slot's descriptor is the root's
        # and its distance is overwritten, so it is never nearest.
        inner = np.nonzero(self._has_children)[0]
        self._inner_of = np.full(len(self.children), -1, np.int64)
        self._inner_of[inner] = np.arange(len(inner))
        kids = np.where(self.children >= 0, self.children, 0)[inner].astype(np.int64)
        self._inner_children = kids
        self._inner_desc = np.ascontiguousarray(self.node_desc.view(np.uint64)[kids])
        self._inner_pad = self.children[inner] < 0
        self._inner_partial = self._inner_pad.any(axis=1)

    @property
    def n_words(self) -> int:
        return len(self.idf)

    @property
    def n_nodes(self) -> int:
        return len(self.node_desc)

    # -- conversion --------------------------------------------------------------
    def descend(self, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Leaf word id and the node at ``fv_level`` for every descriptor."""
        d = as_u64(desc)
        n, k = len(d), self.children.shape[1]
        # Each descriptor once per child slot: XOR of two contiguous (n, k, 4) arrays
        # is ~5x faster than one broadcast over the slots (an inner loop of 4 words).
        d = np.repeat(d, k, axis=0).reshape(n, k, 4)
        cur = np.zeros(n, dtype=np.int64)
        fv = np.zeros(n, dtype=np.int64)
        for level in range(1, self.levels + 1):
            active: np.ndarray | None = None  # None: every descriptor (no row selection)
            if level == 1:
                if not self._has_children[0]:
                    break
                # Everyone is at the root: its children's block, broadcast.
                r = int(self._inner_of[0])
                dist = hamming_u64(d, self._inner_desc[r])
                if self._inner_partial[r]:
                    dist[:, self._inner_pad[r]] = 1 << 20
                cur = self._inner_children[r][dist.argmin(axis=1)]
            else:
                inner = self._inner_of[cur]
                active = np.nonzero(inner >= 0)[0]
                if len(active) == 0:
                    break
                if len(active) == n:
                    active = None
                else:
                    inner = inner[active]
                dk = d if active is None else d[active]
                dist = hamming_u64(dk, self._inner_desc.take(inner, axis=0))
                part = np.nonzero(self._inner_partial[inner])[0]
                if len(part):
                    dist[part] = np.where(self._inner_pad[inner[part]], 1 << 20, dist[part])
                nxt = self._inner_children[inner, dist.argmin(axis=1)]
                if active is None:
                    cur = nxt
                else:
                    cur[active] = nxt
            if level <= self.fv_level:
                if active is None:
                    fv = cur.copy()
                else:
                    fv[active] = cur[active]
        return self.word_of_node[cur], fv

    def transform(self, desc: np.ndarray) -> tuple[BowVector, FeatureVector]:
        """Descriptors (N, 32) uint8 -> (BoW vector, feature vector)."""
        if len(desc) == 0:
            empty = np.zeros(0, np.int32)
            return (BowVector(empty, np.zeros(0)),
                    FeatureVector(empty, np.zeros(1, np.int64), np.zeros(0, np.int64)))  # fmt: skip
        words, fv = self.descend(desc)
        return self.bow_from_words(words), FeatureVector.from_nodes(fv)

    def bow_from_words(self, words: np.ndarray) -> BowVector:
        u, counts = np.unique(words, return_counts=True)
        # tf-idf: summing idf per occurrence is tf * idf up to the 1/N that L1 removes.
        w = counts * self.idf[u]
        total = w.sum()
        if total > 0:
            w = w / total
        keep = w > 0
        return BowVector(u[keep].astype(np.int32), w[keep])

    def score(self, a: BowVector, b: BowVector) -> float:
        return bow_score(a, b)

    # -- persistence ---------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        # The tree is stored as parent ids: children rebuild from them in order,
        # which halves the file against storing the padded (n, k) child table.
        parent = np.full(self.n_nodes, -1, np.int32)
        for c in range(self.k):
            ok = self.children[:, c] >= 0
            parent[self.children[ok, c]] = np.nonzero(ok)[0]
        np.savez_compressed(
            path,
            format=np.array(FORMAT),
            k=np.int32(self.k),
            levels=np.int32(self.levels),
            fv_level=np.int32(self.fv_level),
            node_desc=self.node_desc,
            parent=parent,
            idf=self.idf.astype(np.float32),
            word_of_node=self.word_of_node,
            meta=np.array(json.dumps(self.meta)),
        )
        return path

    @staticmethod
    def load(path: str | Path | None = None) -> Vocabulary:
        path = default_path() if path is None else Path(path)
        with np.load(path, allow_pickle=False) as z:
            if str(z["format"]) != FORMAT:
                raise ValueError(f"{path}: not a {FORMAT} file")
            k = int(z["k"])
            parent = z["parent"]
            node_desc = z["node_desc"]
            n = len(parent)
            children = np.full((n, k), -1, np.int32)
            # Nodes were numbered breadth-first, so children of a node are consecutive.
            kids = np.nonzero(parent >= 0)[0]
            par = parent[kids]
            first = np.searchsorted(par, par, side="left")
            slot = np.arange(len(kids)) - first
            children[par, slot] = kids
            depth = np.zeros(n, np.int8)
            for _ in range(int(z["levels"])):
                depth[kids] = depth[par] + 1
            meta = json.loads(str(z["meta"]))
            return Vocabulary(k, int(z["levels"]), node_desc, children, depth,
                              z["idf"].astype(np.float64), z["word_of_node"],
                              int(z["fv_level"]), meta)  # fmt: skip


# -- training ------------------------------------------------------------------------
def _majority(desc_u8: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """Bitwise majority of each cluster's descriptors -> (k, 32) uint8."""
    bits = np.unpackbits(desc_u8, axis=1)  # (n, 256)
    onehot = np.zeros((k, len(labels)), np.float32)
    onehot[labels, np.arange(len(labels))] = 1.0
    ones = onehot @ bits.astype(np.float32)  # (k, 256) set-bit counts
    counts = onehot.sum(axis=1, keepdims=True)
    # Ties go to 1 like DBoW2's "sum >= N/2".
    return np.packbits((2 * ones >= counts).astype(np.uint8), axis=1)


def _seed_pp(d: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding on Hamming distance (squared, as DBoW2 does)."""
    n = len(d)
    centers = [int(rng.integers(n))]
    mind = hamming_u64(d, d[centers[0]]).astype(np.float64)
    for _ in range(1, k):
        p = mind**2
        tot = p.sum()
        if tot <= 0:
            break  # every remaining descriptor equals a centre
        c = int(rng.choice(n, p=p / tot))
        centers.append(c)
        mind = np.minimum(mind, hamming_u64(d, d[c]))
    return np.array(centers)


def kmajority(
    desc_u8: np.ndarray, k: int, rng: np.random.Generator, max_iter: int = 15, max_fit: int = 60000
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster (n, 32) uint8 descriptors into <= k majority centres.

    Returns (centres (c, 32) uint8, labels (n,)). Nodes bigger than ``max_fit`` fit
    the centres on a random subset and then assign everyone: the top levels have
    hundreds of thousands of members and the centres barely move past that.
    """
    n = len(desc_u8)
    d_all = as_u64(desc_u8)
    if n > max_fit:
        fit_idx = rng.choice(n, max_fit, replace=False)
        d8 = desc_u8[fit_idx]
    else:
        d8 = desc_u8
    d = as_u64(d8)
    cen = d8[_seed_pp(d, k, rng)]
    labels = None
    for _ in range(max_iter):
        new = assign(d, as_u64(cen))
        if labels is not None and np.array_equal(new, labels):
            break
        labels = new
        used = np.unique(labels)
        # Empty clusters are dropped (DBoW2 keeps fewer children in that case).
        remap = np.full(len(cen), -1)
        remap[used] = np.arange(len(used))
        labels = remap[labels]
        cen = _majority(d8, labels, len(used))
    return cen, assign(d_all, as_u64(cen))


def assign(d: np.ndarray, centres: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Nearest centre of each (n, 4) uint64 descriptor, in chunks so the (n, k, 4)
    XOR table of a million descriptors never sits in memory at once."""
    out = np.empty(len(d), np.int64)
    for a in range(0, len(d), chunk):
        out[a : a + chunk] = hamming_u64(d[a : a + chunk, None, :], centres[None]).argmin(axis=1)
    return out


def train(
    desc: np.ndarray,
    image_of_desc: np.ndarray,
    k: int = 10,
    levels: int = 5,
    fv_level: int = 2,
    seed: int = 0,
    max_iter: int = 15,
) -> Vocabulary:
    """Build the tree breadth-first from all training descriptors, then idf weights
    from how many training images contain each word (DBoW2 IDF)."""
    desc = np.ascontiguousarray(desc, dtype=np.uint8)
    rng = np.random.default_rng(seed)
    node_desc = [np.zeros(32, np.uint8)]
    depth = [0]
    children: list[list[int]] = [[]]
    queue: deque[tuple[int, np.ndarray]] = deque([(0, np.arange(len(desc)))])
    while queue:
        node, idx = queue.popleft()
        if depth[node] >= levels or len(idx) <= 1:
            continue  # DBoW2 does not split singletons further
        sub = desc[idx]
        if len(idx) <= k:
            # DBoW2's trivial case: every (distinct) descriptor becomes a child.
            cen, lab = np.unique(sub, axis=0, return_inverse=True)
            lab = lab.ravel()
        else:
            cen, lab = kmajority(sub, k, rng, max_iter=max_iter)
        if len(cen) <= 1:
            continue  # identical descriptors: splitting gains nothing, keep as leaf
        order = np.argsort(lab, kind="stable")
        bounds = np.searchsorted(lab[order], np.arange(len(cen) + 1))
        for c in range(len(cen)):
            child = len(node_desc)
            node_desc.append(cen[c])
            depth.append(depth[node] + 1)
            children.append([])
            children[node].append(child)
            queue.append((child, idx[order[bounds[c] : bounds[c + 1]]]))
    n = len(node_desc)
    ch = np.full((n, k), -1, np.int32)
    for i, c in enumerate(children):
        ch[i, : len(c)] = c
    leaves = np.nonzero(ch[:, 0] < 0)[0]
    word_of_node = np.full(n, -1, np.int32)
    word_of_node[leaves] = np.arange(len(leaves))
    voc = Vocabulary(k, levels, np.stack(node_desc), ch, np.array(depth), np.ones(len(leaves)),
                     word_of_node, fv_level)  # fmt: skip
    words = np.concatenate([voc.descend(desc[a : a + 65536])[0]
                            for a in range(0, len(desc), 65536)])  # fmt: skip
    n_images = len(np.unique(image_of_desc))
    # Images containing each word: unique (image, word) keys, counted per word.
    keys = np.unique(image_of_desc.astype(np.int64) * len(leaves) + words)
    n_i = np.bincount(keys % len(leaves), minlength=len(leaves))
    # A word no training image reached gets the largest weight (seen in at most one).
    voc.idf = np.log(n_images / np.maximum(n_i, 1)).astype(np.float64)
    log.info("vocabulary: %d nodes, %d words from %d descriptors of %d images",
             n, len(leaves), len(desc), n_images)  # fmt: skip
    return voc
