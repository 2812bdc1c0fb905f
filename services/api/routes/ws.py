"""WebSocket /ws/poses: every live pose the mapper places in a map, as JSON."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator, Coroutine

import redis.asyncio as aioredis
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from redis.asyncio.client import PubSub

from shared.messages import DecodeError
from shared.store import POSE_CHANNEL, LivePose

from ..metrics import WS_CLIENTS
from ..models import pose_out
from ..security import refused

log = logging.getLogger(__name__)
router = APIRouter()


@contextlib.asynccontextmanager
async def pose_subscription(ws: WebSocket) -> AsyncIterator[PubSub]:
    """Accept the socket and subscribe to the live poses; closed however the socket ends
    (a client going away is the normal end, not an error). /ws/poses and /ws/viewer."""
    await ws.accept()
    WS_CLIENTS.inc()
    r = aioredis.Redis.from_url(ws.app.state.settings.redis_url)
    pubsub = r.pubsub()
    await pubsub.subscribe(POSE_CHANNEL)
    try:
        yield pubsub
    except WebSocketDisconnect:
        pass
    finally:
        await pubsub.unsubscribe(POSE_CHANNEL)
        await pubsub.aclose()
        await r.aclose()


async def _gone(ws: WebSocket) -> None:
    """Returns when the client has gone (it sends nothing that matters)."""
    while (await ws.receive())["type"] != "websocket.disconnect":
        pass


async def until_gone(ws: WebSocket, what: str, *feeds: Coroutine) -> None:
    """Runs ``feeds`` (what the socket pushes) until one ends or the client goes away.
    A feed notices a client that left only when a send fails, and with nothing to send
    (no agent flying) that was never: a closed or dropped connection kept its handler,
    its Redis subscription and the client gauge for as long as the API ran. The client
    sends nothing, so a ``receive()`` waiting beside the feeds returns at the
    disconnect (a close, the TCP connection ending, or the server's pings going
    unanswered) and ends them."""
    tasks = [asyncio.create_task(c) for c in feeds]
    tasks.append(asyncio.create_task(_gone(ws)))
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for t in done:
            e = t.exception()
            if e is not None and not isinstance(e, (WebSocketDisconnect, OSError, RuntimeError)):
                log.error("%s failed", what, exc_info=e)
    finally:
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(BaseException):
                await t


async def _forward(ws: WebSocket, pubsub: PubSub) -> None:
    while True:
        msg = await pubsub.get_message(ignore_subscribe_messages=True, timeout=1.0)
        if msg is None:
            continue
        try:
            doc = pose_out(LivePose.decode(msg["data"]))
        except DecodeError as e:
            log.warning("bad pose on %s: %s", POSE_CHANNEL, e)
            continue
        await ws.send_text(json.dumps({"type": "pose", **doc.model_dump()}))


@router.websocket("/ws/poses")
async def ws_poses(ws: WebSocket) -> None:
    if await refused(ws):
        return
    async with pose_subscription(ws) as pubsub:
        # The subscription is live before the client hears anything, so a pose
        # published after this message is never missed.
        await ws.send_text(json.dumps({"type": "subscribed"}))
        await until_gone(ws, "pose feed", _forward(ws, pubsub))
