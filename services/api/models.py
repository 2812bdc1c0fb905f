"""Response models of the REST API."""

from __future__ import annotations

from pydantic import BaseModel

from shared.geometry import pose_to_tq
from shared.store import LivePose


class PoseOut(BaseModel):
    agent: str
    map_id: str
    stamp_ns: int
    t: float
    position: list[float]
    quaternion_xyzw: list[float]
    kf_ref: int
    tracking: str
    fps: float


class AgentOut(BaseModel):
    # One flight of an agent: ``agent`` is the id its data is stored under (the one the
    # other routes take), ``name`` the id it flew as and ``flight`` which of that
    # id's flights it is (1, 2, ...; a second flight of "A" is stored as "A.s2").
    agent: str
    name: str = ""
    flight: int = 1
    map_id: str
    n_kf: int
    n_mp: int
    scale_to_map: float
    last_pose: PoseOut | None


class KeyframeOut(BaseModel):
    id: int
    stamp_ns: int
    position: list[float]
    quaternion_xyzw: list[float]


class TrajectoryOut(BaseModel):
    agent: str
    name: str = ""
    flight: int = 1
    map_id: str
    frame: str = "map"
    keyframes: list[KeyframeOut]


class MapOut(BaseModel):
    map_id: str
    agents: list[str]
    n_kf: int
    created_ns: int
    keyframes_per_agent: dict[str, int] = {}
    merged_into: str | None = None


class PointsOut(BaseModel):
    map_id: str
    n: int
    n_total: int = 0
    points: list[list[float]]


class ErrorOut(BaseModel):
    error: str
    detail: object | None = None


def pose_out(pose: LivePose) -> PoseOut:
    p, q = pose_to_tq(pose.T_m_c)
    return PoseOut(
        agent=pose.agent, map_id=pose.map_id, stamp_ns=pose.stamp_ns, t=pose.stamp_ns * 1e-9,
        position=p.tolist(), quaternion_xyzw=q.tolist(), kf_ref=pose.kf_ref,
        tracking=pose.tracking, fps=pose.fps,
    )  # fmt: skip
