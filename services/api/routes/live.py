"""WebSocket /ws/viewer: everything the viewer draws, pushed.

On connect: ``hello``, then a ``state`` (maps, agents with status and live pose,
keyframe trajectories, loop edges) and each live map's ``points``. Then ``poses`` every
100 ms (each agent's newest pose, from the mapper's pose channel), a fresh ``state``
every ``STATE_EVERY_S`` with ``event`` messages for merges and loops that appeared
since the previous one, and a map's ``points`` again when it grew (at most every
``POINTS_EVERY_S``; capped, see feed.POINTS_CAP).
"""

from __future__ import annotations

import asyncio
import json
import logging
import time

from fastapi import APIRouter, WebSocket

from shared.messages import DecodeError
from shared.store import POSE_CHANNEL, LivePose

from .. import feed
from ..models import pose_out
from ..security import refused
from .ws import pose_subscription, until_gone

log = logging.getLogger(__name__)
router = APIRouter()

POSE_FLUSH_S = 0.1
STATE_EVERY_S = 1.5
POINTS_EVERY_S = 5.0


async def _send(ws: WebSocket, msg: dict) -> None:
    await ws.send_text(json.dumps(msg, separators=(",", ":")))


async def _poses(ws: WebSocket, pubsub) -> None:
    newest: dict[str, dict] = {}
    last = time.monotonic()
    while True:
        msg = await pubsub.get_message(ignore_subscribe_messages=True, timeout=POSE_FLUSH_S)
        if msg is not None:
            try:
                doc = LivePose.decode(msg["data"])
                p = pose_out(doc).model_dump()
            except DecodeError as e:
                log.warning("bad pose on %s: %s", POSE_CHANNEL, e)
                continue
            p["status"] = feed.agent_status(doc, time.time_ns())
            newest[p["agent"]] = p
        if newest and time.monotonic() - last >= POSE_FLUSH_S:
            await _send(ws, {"type": "poses", "poses": list(newest.values())})
            newest.clear()
            last = time.monotonic()


async def _state(ws: WebSocket) -> None:
    store = ws.app.state.store
    prev = None
    sent_n: dict[str, int] = {}
    sent_t: dict[str, float] = {}
    while True:
        seen = [m["map_id"] for m in prev["maps"] if not m["merged_into"]] if prev else []
        cur = await asyncio.to_thread(feed.state, store, seen)
        await _send(ws, cur)
        for e in feed.diff_events(prev, cur):
            await _send(ws, e)
        prev = cur
        now = time.monotonic()
        for m in cur["maps"]:
            mid = m["map_id"]
            if m["merged_into"]:
                continue
            if sent_n.get(mid) != m["n_kf"] and now - sent_t.get(mid, -1e9) >= POINTS_EVERY_S:
                await _send(ws, await asyncio.to_thread(feed.points, store, mid))
                sent_n[mid], sent_t[mid] = m["n_kf"], now
        await asyncio.sleep(STATE_EVERY_S)


@router.websocket("/ws/viewer")
async def ws_viewer(ws: WebSocket) -> None:
    if await refused(ws):
        return
    async with pose_subscription(ws) as pubsub:
        await _send(ws, {"type": "hello", "points_cap": feed.POINTS_CAP,
                         "disconnected_after_s": feed.DISCONNECTED_AFTER_S})  # fmt: skip
        await until_gone(ws, "viewer feed", _poses(ws, pubsub), _state(ws))
