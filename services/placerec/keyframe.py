"""Plain keyframe data for place recognition, copied out of a server map.

Nothing here refers to live map objects: a service builds a :class:`KeyframeData`
from a keyframe and its map points (positions expressed in that keyframe's own
camera frame, so two maps of different scale can be compared) and hands it to the
database and to geometric verification::

    voc = Vocabulary.load()                       # shipped data/orb_k10_l5.npz
    db = KeyframeDatabase(voc.n_words)
    kf = KeyframeData(gid, map_id, agent, xy, octaves, desc, mp, p_c, fx).compute_bow(voc)
    cands = db.query(kf.bow, neighbours=covis(kf.gid), covisible=covis, query_gid=kf.gid,
                     maps=[kf.map_id])            # intra-map loop; exclude_maps= for merging
    db.add(kf.gid, kf.map_id, kf.bow)
    for gid in checker.update([c.gid for c in cands], covis):   # one checker per stream
        res = verify(kf, kf_data(gid), neighbourhood_points(gid))
        if res.accepted: ...                      # res.S_q_c, res.kp_q/kp_c/mp_q/mp_c
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .vocabulary import BowVector, FeatureVector, Vocabulary


@dataclass
class KeyframeData:
    gid: int  # keyframe gid (int64), unique over all maps
    map_id: str  # server map this keyframe belongs to
    agent: str
    xy: np.ndarray  # (N, 2) float64 undistorted normalized image coordinates
    octaves: np.ndarray  # (N,) uint8 ORB pyramid level of each keypoint
    descriptors: np.ndarray  # (N, 32) uint8
    mp: np.ndarray  # (N,) int64 map-point gid per keypoint, -1 where none
    p_c: np.ndarray  # (N, 3) float64 map point in this keyframe's camera frame, NaN where none
    fx: float  # focal length in pixels, turns normalized errors into pixel thresholds
    bow: BowVector | None = None
    fv: FeatureVector | None = None
    _tree: cKDTree | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = len(self.descriptors)
        self.xy = np.asarray(self.xy, dtype=np.float64).reshape(n, 2)
        self.octaves = np.asarray(self.octaves, dtype=np.uint8).reshape(n)
        self.descriptors = np.ascontiguousarray(self.descriptors, dtype=np.uint8).reshape(n, 32)
        self.mp = np.asarray(self.mp, dtype=np.int64).reshape(n)
        self.p_c = np.asarray(self.p_c, dtype=np.float64).reshape(n, 3)

    def __len__(self) -> int:
        return len(self.descriptors)

    @property
    def has_point(self) -> np.ndarray:
        """Keypoints with a usable 3D map point in front of the camera."""
        p = self.p_c
        # Column by column: numpy's .all(axis=1) over 3 values per row was 3x slower, and
        # this runs for every keyframe of every candidate's neighbourhood.
        finite = np.isfinite(p[:, 0]) & np.isfinite(p[:, 1]) & np.isfinite(p[:, 2])
        return (self.mp >= 0) & finite & (p[:, 2] > 0)

    @property
    def pixel_tree(self) -> cKDTree:
        """k-d tree over all keypoints in pixels (``xy * fx``), built once: a database
        keyframe is searched by projection in every confirmation it neighbours."""
        if self._tree is None:
            self._tree = cKDTree(self.xy * self.fx)
        return self._tree

    def compute_bow(self, voc: Vocabulary) -> KeyframeData:
        """Fill ``bow`` and ``fv`` from the descriptors (in place; returns self)."""
        self.bow, self.fv = voc.transform(self.descriptors)
        return self


@dataclass
class MapPoints:
    """Map points around a candidate keyframe (its covisible neighbourhood), expressed
    in the candidate's camera frame, for guided matching into the query keyframe."""

    mp: np.ndarray  # (M,) int64 map-point gids
    p_c: np.ndarray  # (M, 3) float64 positions in the candidate keyframe's camera frame
    descriptors: np.ndarray  # (M, 32) uint8 representative descriptor of each point

    def __post_init__(self) -> None:
        m = len(self.mp)
        self.mp = np.asarray(self.mp, dtype=np.int64).reshape(m)
        self.p_c = np.asarray(self.p_c, dtype=np.float64).reshape(m, 3)
        self.descriptors = np.ascontiguousarray(self.descriptors, dtype=np.uint8).reshape(m, 32)

    def __len__(self) -> int:
        return len(self.mp)

    @staticmethod
    def of_keyframe(kf: KeyframeData) -> MapPoints:
        ok = kf.has_point
        return MapPoints(kf.mp[ok], kf.p_c[ok], kf.descriptors[ok])
