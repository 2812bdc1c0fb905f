"""/agents: live poses and server-map trajectories."""

from __future__ import annotations

from enum import StrEnum

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse

from shared.geometry import pose_to_tq
from shared.store import Store
from shared.trajectory import format_tum

from ..deps import StoreDep
from ..errors import NotFound, found
from ..models import AgentOut, KeyframeOut, PoseOut, TrajectoryOut, pose_out

router = APIRouter(prefix="/agents", tags=["agents"])


class TrajFormat(StrEnum):
    tum = "tum"
    json = "json"


def _info(store: Store, agent: str) -> dict:
    return found(store.agent_info(agent), "agent", agent)


@router.get("", response_model=list[AgentOut])
def list_agents(store: StoreDep) -> list[AgentOut]:
    out = []
    for a in store.agents():
        info = store.agent_info(a)
        if info is None:
            continue
        doc = store.latest_pose(a)
        out.append(AgentOut(
            agent=a, name=info["name"], flight=info["flight"], map_id=info["map_id"],
            n_kf=info["n_kf"], n_mp=info["n_mp"],
            scale_to_map=info["S_m_l"].s, last_pose=pose_out(doc) if doc else None,
        ))  # fmt: skip
    return out


@router.get("/{agent}/pose", response_model=PoseOut)
def latest_pose(agent: str, store: StoreDep) -> PoseOut:
    _info(store, agent)
    doc = store.latest_pose(agent)
    if doc is None:
        raise NotFound("pose of agent", agent)
    return pose_out(doc)


@router.get("/{agent}/trajectory", response_model=TrajectoryOut)
def trajectory(agent: str, store: StoreDep, format: TrajFormat = TrajFormat.json):
    """Keyframe trajectory of one flight (``agent`` as ``GET /agents`` lists it) in its
    current server-map frame. ``format=tum``
    gives ``t x y z qx qy qz qw`` lines, t in seconds with nanosecond digits."""
    info = _info(store, agent)
    ids, stamps, poses = store.trajectory(agent)
    if format is TrajFormat.tum:
        return PlainTextResponse(format_tum(stamps, poses))
    kfs = []
    for i, t, T in zip(ids.tolist(), stamps.tolist(), poses, strict=True):
        p, q = pose_to_tq(T)
        kfs.append(KeyframeOut(id=i, stamp_ns=t, position=p.tolist(), quaternion_xyzw=q.tolist()))
    return TrajectoryOut(agent=agent, name=info["name"], flight=info["flight"],
                         map_id=info["map_id"], keyframes=kfs)  # fmt: skip
