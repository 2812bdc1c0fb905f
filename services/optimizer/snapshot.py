"""The copy of a server map that a global optimization works on, and its result.

Both are plain dataclasses of numpy arrays (plus a few scalars), so the optimizer
never touches live map objects and a service can put them on the wire as they are.

Conventions (every 4x4 is a numpy float64 array):
- ``T_m_kf``: SE(3), camera to map (``p_m = R p_kf + t``).
- ``S_loop[i]`` for loop edge ``loops[i] = (a, b)``: Sim(3) ``S_a_b`` as
  ``[[s R, t], [0, 1]]``, mapping points in keyframe b's camera frame into keyframe
  a's camera frame (``p_a = s R p_b + t``).
- ``kf_scale``: the scale ``s`` of each keyframe's optimized camera-to-map Sim(3)
  ``S_m_kf = [[s R, t], [0, 1]]``; the corrected SE(3) pose is ``[R, t]``. A length
  measured in the keyframe's camera frame before the correction is ``s`` times as
  long in the corrected map (ORB-SLAM keeps world-to-camera ``S_cw`` and writes
  ``[R, t/s]``; that is the same pose seen from the other side).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from services.mapper.server_map import STRONG, ServerMap

log = logging.getLogger(__name__)

EUROC_FX = 458.654  # EuRoC cam0, the default camera of the project


@dataclass
class MapSnapshot:
    map_id: str
    version: int
    kf_gids: np.ndarray  # (K,) int64
    T_m_kf: np.ndarray  # (K, 4, 4) float64, camera to map
    fixed_gids: np.ndarray  # (F,) int64, gauge keyframes
    edges: np.ndarray  # (E, 2) int64 gids: spanning tree + strong covisibility
    loops: np.ndarray  # (Lp, 2) int64 gids (a, b)
    S_loop: np.ndarray  # (Lp, 4, 4) float64, S_a_b measured
    mp_gids: np.ndarray  # (M,) int64
    mp_pos: np.ndarray  # (M, 3) float64, map frame
    mp_ref: np.ndarray  # (M,) int64 gid of each point's reference keyframe
    obs_kf: np.ndarray  # (O,) int32 index into kf_gids
    obs_mp: np.ndarray  # (O,) int32 index into mp_gids
    obs_xy: np.ndarray  # (O, 2) float64 undistorted normalized image coordinates
    obs_octave: np.ndarray  # (O,) uint8
    fx: float = EUROC_FX  # focal length in pixels: observation noise is 1.2**octave / fx

    @property
    def n_kf(self) -> int:
        return len(self.kf_gids)

    def kf_index(self) -> dict[int, int]:
        return {int(g): i for i, g in enumerate(self.kf_gids.tolist())}

    def check(self) -> list[str]:
        """Shape and index consistency; returns the problems (empty when consistent)."""
        errs = []
        K, M, O = len(self.kf_gids), len(self.mp_gids), len(self.obs_kf)
        if self.T_m_kf.shape != (K, 4, 4):
            errs.append(f"T_m_kf shape {self.T_m_kf.shape}, expected {(K, 4, 4)}")
        if self.mp_pos.shape != (M, 3) or self.mp_ref.shape != (M,):
            errs.append("mp_pos / mp_ref shape")
        if (
            self.obs_mp.shape != (O,)
            or self.obs_xy.shape != (O, 2)
            or self.obs_octave.shape != (O,)
        ):
            errs.append("observation arrays differ in length")
        if O and (self.obs_kf.min() < 0 or self.obs_kf.max() >= K):
            errs.append("obs_kf out of range")
        if O and (self.obs_mp.min() < 0 or self.obs_mp.max() >= M):
            errs.append("obs_mp out of range")
        known = set(self.kf_gids.tolist())
        for name, arr in (("edges", self.edges), ("loops", self.loops)):
            if arr.size and not set(arr.ravel().tolist()) <= known:
                errs.append(f"{name} name unknown keyframes")
        if not set(self.fixed_gids.tolist()) <= known:
            errs.append("fixed_gids name unknown keyframes")
        if self.S_loop.shape != (len(self.loops), 4, 4):
            errs.append("S_loop shape")
        if len(np.unique(self.kf_gids)) != K or len(np.unique(self.mp_gids)) != M:
            errs.append("duplicate gids")
        return errs


@dataclass
class Correction:
    map_id: str
    base_version: int  # the snapshot's map version
    kf_gids: np.ndarray  # (K,) int64
    T_m_kf: np.ndarray  # (K, 4, 4) corrected SE(3) camera-to-map poses
    kf_scale: np.ndarray  # (K,) float64 scale of each keyframe's Sim(3) (1.0 if none)
    mp_gids: np.ndarray  # (M,) int64
    mp_pos: np.ndarray  # (M, 3) corrected positions in the map frame
    stats: dict = field(default_factory=dict)
    # Observations still outliers after BA, (kf gid, mp gid) pairs the caller may drop.
    outliers: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))


def oldest_keyframe(smap: ServerMap) -> int:
    """The gauge keyframe: earliest stamp, lowest gid among equals."""
    return min(smap.kfs.values(), key=lambda k: (k.stamp_ns, k.gid)).gid


@dataclass
class MapCapture:
    """What a snapshot needs from a live map, taken in a few milliseconds under the map's
    lock: poses and observation index arrays copied, immutable arrays referenced. The
    expensive part (essential graph, observation tables) is built from it off-lock by
    :func:`build_snapshot`, so keyframe ingestion is not held up by a large copy."""

    map_id: str
    version: int
    gids: list[int]
    T: np.ndarray  # (K, 4, 4) copies
    kf_mp: list[np.ndarray]  # copies (fusion rewrites them in place)
    kf_xy: list[np.ndarray]  # never rewritten after a keyframe is made
    kf_oct: list[np.ndarray]
    parents: list[int]
    covis: list[dict[int, int]]  # copies
    loop_edges: list[set[int]]
    points: dict  # gid -> ServerMapPoint (shallow copy; a position is replaced, not edited)
    loops: list[tuple[int, int, np.ndarray]]
    fixed: list[int]


def capture_map(
    smap: ServerMap, loops: list[tuple[int, int, np.ndarray]], fixed: list[int] | None = None
) -> MapCapture:
    gids = sorted(smap.kfs)
    kfs = [smap.kfs[g] for g in gids]
    if fixed is None:
        fixed = [oldest_keyframe(smap)] if gids else []
    return MapCapture(
        map_id=smap.map_id, version=smap.version, gids=gids,
        T=np.array([k.T_m_kf for k in kfs], np.float64).reshape(-1, 4, 4),
        kf_mp=[k.mp.copy() for k in kfs], kf_xy=[k.xy for k in kfs],
        kf_oct=[k.octaves for k in kfs], parents=[k.parent for k in kfs],
        covis=[dict(smap.covis.get(g, {})) for g in gids],
        loop_edges=[set(k.loop_edges) for k in kfs], points=dict(smap.mps),
        loops=list(loops), fixed=list(fixed),
    )  # fmt: skip


def _essential_edges(cap: MapCapture) -> np.ndarray:
    """Spanning tree + strong covisibility (ServerMap.essential_edges without its 'loop'
    edges, which come with their measurements through ``loops``)."""
    known = set(cap.gids)
    edges = []
    for g, parent, covis in zip(cap.gids, cap.parents, cap.covis, strict=True):
        if parent in known and parent != g:
            edges.append((min(g, parent), max(g, parent)))
        edges.extend((g, o) for o, n in covis.items() if n >= STRONG and g < o and o in known)
    # Tree and strong edges can name the same pair; one measurement per pair is enough.
    return np.unique(np.array(edges, np.int64).reshape(-1, 2), axis=0)


def build_snapshot(cap: MapCapture, fx: float = EUROC_FX, pause=None) -> MapSnapshot:
    """``pause``: called between the steps (each ~0.1 s for a 1500-keyframe map) so the
    mapper can give its actors the GIL meanwhile."""
    pause = pause or (lambda: None)
    gids = np.array(cap.gids, dtype=np.int64)
    K = len(gids)
    idx = {g: i for i, g in enumerate(cap.gids)}
    edges_arr = _essential_edges(cap)
    pause()
    loops = cap.loops
    lp = [(int(a), int(b), S) for a, b, S in loops if a in idx and b in idx and a != b]
    if len(lp) < len(loops):
        log.info("snapshot %s: %d loop edges name missing keyframes", cap.map_id,
                 len(loops) - len(lp))  # fmt: skip
    loops_arr = np.array([(a, b) for a, b, _ in lp], np.int64).reshape(-1, 2)
    S_loop = np.array([np.asarray(S, np.float64) for _, _, S in lp]).reshape(-1, 4, 4)

    mp_gids = np.array(sorted(cap.points), dtype=np.int64)
    M = len(mp_gids)
    pts = [cap.points[g] for g in mp_gids.tolist()]
    mp_pos = np.array([p.pos for p in pts], np.float64).reshape(M, 3)
    mp_ref = np.array([p.ref_kf for p in pts], np.int64)
    pause()

    # Observations straight from the keyframes' keypoint arrays, all keyframes at once:
    # one searchsorted maps point gids to indices.
    counts = np.array([len(m) for m in cap.kf_mp], np.int64)
    okf = np.repeat(np.arange(K, dtype=np.int32), counts) if K else np.zeros(0, np.int32)
    cat = np.concatenate
    allmp = cat(cap.kf_mp).astype(np.int64) if K else np.zeros(0, np.int64)
    oxy = cat([np.asarray(x, np.float64) for x in cap.kf_xy]) if K else np.zeros((0, 2))
    ooct = cat([np.asarray(o) for o in cap.kf_oct]).astype(np.uint8) if K else np.zeros(0)
    pause()
    pos = np.searchsorted(mp_gids, allmp)
    ok = (allmp >= 0) & (pos < M)
    ok[ok] &= mp_gids[pos[ok]] == allmp[ok]
    return MapSnapshot(
        map_id=cap.map_id,
        version=cap.version,
        kf_gids=gids,
        T_m_kf=cap.T,
        fixed_gids=np.array([g for g in cap.fixed if g in idx], np.int64),
        edges=edges_arr,
        loops=loops_arr,
        S_loop=S_loop,
        mp_gids=mp_gids,
        mp_pos=mp_pos,
        mp_ref=mp_ref,
        obs_kf=okf[ok],
        obs_mp=pos[ok].astype(np.int32),
        obs_xy=oxy[ok].reshape(-1, 2),
        obs_octave=ooct[ok].astype(np.uint8),
        fx=float(fx),
    )


def snapshot_from_map(
    smap: ServerMap,
    loops: list[tuple[int, int, np.ndarray]],
    fixed: list[int] | None = None,
    fx: float = EUROC_FX,
) -> MapSnapshot:
    """Copy ``smap`` into a :class:`MapSnapshot`.

    ``loops``: (a, b, S_a_b) loop edges with their measured Sim(3); the map's own
    'loop' essential edges carry no measurement, so they come only through here
    (edges naming keyframes that are no longer in the map are dropped).
    ``fixed``: gauge keyframes, the oldest keyframe when None.
    """
    return build_snapshot(capture_map(smap, loops, fixed), fx)
