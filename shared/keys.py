"""Every Zenoh key expression HiveMap uses, built in one place.

One chunk per id, ``/`` as the only separator, never a wildcard inside an id.
"""

from __future__ import annotations

import re

ROOT = "hivemap"
_ID = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


def check_id(value: str, what: str = "id") -> str:
    if not isinstance(value, str) or not _ID.match(value):
        raise ValueError(f"{what} {value!r}: use 1-64 characters from A-Z a-z 0-9 _ . -")
    return value


def _agent(agent: str, leaf: str) -> str:
    return f"{ROOT}/agent/{check_id(agent, 'agent')}/{leaf}"


def _map(map_id: str, leaf: str) -> str:
    return f"{ROOT}/map/{check_id(map_id, 'map')}/{leaf}"


def agent_kf(agent: str) -> str:
    return _agent(agent, "up/kf")


def agent_pose(agent: str) -> str:
    return _agent(agent, "up/pose")


def agent_ack(agent: str) -> str:
    return _agent(agent, "down/ack")


def agent_map(agent: str) -> str:
    return _agent(agent, "down/map")


def map_kf(map_id: str) -> str:
    return _map(map_id, "kf")


def map_correction(map_id: str) -> str:
    return _map(map_id, "correction")


def map_merged(map_id: str) -> str:
    return _map(map_id, "merged")


def _chunk(key: str, kind: str) -> str | None:
    parts = str(key).split("/")
    if len(parts) >= 3 and parts[0] == ROOT and parts[1] == kind:
        return parts[2]
    return None


def map_of(key: str) -> str | None:
    """The map chunk of ``hivemap/map/{map}/...``."""
    return _chunk(key, "map")


MATCH = f"{ROOT}/match"
MAPPER_STATE = f"{ROOT}/mapper/state"  # queryable: digest of every map and handler

# Subscriptions.
ALL_AGENT_KF = f"{ROOT}/agent/*/up/kf"
ALL_AGENT_POSE = f"{ROOT}/agent/*/up/pose"
ALL_MAP_KF = f"{ROOT}/map/*/kf"
ALL_MAP_CORRECTION = f"{ROOT}/map/*/correction"
ALL_MAP_MERGED = f"{ROOT}/map/*/merged"


def agent_of(key: str) -> str | None:
    """The agent chunk of ``hivemap/agent/{agent}/...``."""
    return _chunk(key, "agent")
