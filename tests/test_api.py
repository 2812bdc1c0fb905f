"""The REST/WebSocket API against a real Redis filled by the real mapper code."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from feeding import feed

from services.agent.sim_agent import DriftModel, LandmarkWorld, SimAgent
from services.api.main import create_app
from services.mapper.service import MapperService
from shared import keys
from shared.geometry import se3_inv
from shared.messages import PoseUpdate
from shared.metrics import sample_value
from shared.settings import Settings
from shared.trajectory import Trajectory, load_euroc_gt, parse_tum


@pytest.fixture()
def filled(redis_url):
    """Two agents' keyframes stored by the mapper's own processing path."""
    s = Settings(redis_url=redis_url)
    m = MapperService(s)
    world = LandmarkWorld(0)
    last = {}
    for agent, seq in (("A", "MH01"), ("B", "MH02")):
        gt = load_euroc_gt(seq)
        sim = SimAgent(Trajectory(gt.stamps_ns[900:1200], gt.poses[900:1200]), world,
                       drift=DriftModel.zero())  # fmt: skip

        def apply(msg, t, step, agent=agent):
            stamp, T_l_c, kf = step
            last[agent] = (stamp, T_l_c, kf.kf.id, kf.kf.T_l_kf)
            return m.process_kf_bytes(keys.agent_kf(agent), msg.encode(), 0)

        feed(agent, sim, apply)
        stamp, T_l_c, kid, T_l_kf = last[agent]
        p = PoseUpdate(agent, stamp, T_l_c, kid, se3_inv(T_l_kf) @ T_l_c)
        m.process_pose_bytes(keys.agent_pose(agent), p.encode(), 0)
    m.store.r.close()
    return s, last


def test_agents_pose_trajectory_maps(filled):
    s, last = filled
    with TestClient(create_app(s)) as c:
        agents = c.get("/agents").json()
        assert [a["agent"] for a in agents] == ["A", "B"]
        assert all(a["n_kf"] > 5 and a["last_pose"] for a in agents)
        pose = c.get("/agents/A/pose").json()
        assert pose["stamp_ns"] == last["A"][0]
        np.testing.assert_allclose(pose["position"], last["A"][1][:3, 3], atol=1e-9)
        tj = c.get("/agents/A/trajectory?format=json").json()
        assert tj["map_id"] == "map-A" and len(tj["keyframes"]) == agents[0]["n_kf"]
        r = c.get("/agents/A/trajectory?format=tum")
        assert r.headers["content-type"].startswith("text/plain")
        tum = parse_tum(r.text)
        assert len(tum) == len(tj["keyframes"])
        # nanosecond digits survive, so evo associates the file with ground truth
        assert tum.stamps_ns.tolist() == [k["stamp_ns"] for k in tj["keyframes"]]
        np.testing.assert_allclose(tum.positions, [k["position"] for k in tj["keyframes"]],
                                   atol=1e-8)  # fmt: skip
        maps = c.get("/maps").json()
        assert {m["map_id"] for m in maps} == {"map-A", "map-B"}
        one = c.get("/maps/map-B").json()
        assert one["keyframes_per_agent"] == {"B": agents[1]["n_kf"]}
        pts = c.get("/maps/map-A/points?limit=50").json()
        assert pts["n"] == 50 and len(pts["points"][0]) == 3
        assert c.get("/health").json() == {"status": "ok"}
        assert c.get("/ready").json() == {"status": "ready"}
        assert "hivemap_api_requests_total" in c.get("/metrics").text
        assert "<canvas" in c.get("/").text


def test_errors_are_json_and_counted(filled):
    s, _ = filled
    before = sample_value("hivemap_api_rejected_total", {"reason": "unknown_agent"})
    bad = sample_value("hivemap_api_rejected_total", {"reason": "malformed_request"})
    with TestClient(create_app(s)) as c:
        r = c.get("/agents/nobody/pose")
        assert r.status_code == 404 and "nobody" in r.json()["error"]
        assert c.get("/agents/nobody/trajectory").status_code == 404
        assert c.get("/maps/nomap").status_code == 404
        r = c.get("/agents/A/trajectory?format=xml")
        assert r.status_code == 422 and r.json()["error"] == "malformed request"
        assert c.get("/maps/map-A/points?limit=-3").status_code == 422
        assert c.get("/no/such/route").status_code == 404
    assert sample_value("hivemap_api_rejected_total", {"reason": "unknown_agent"}) == before + 2
    assert sample_value("hivemap_api_rejected_total", {"reason": "malformed_request"}) == bad + 2


def test_websocket_streams_live_poses(filled):
    s, last = filled
    from services.mapper.service import MapperService as M

    m = M(s)
    m.load()
    with TestClient(create_app(s)) as c, c.websocket_connect("/ws/poses") as ws:
        assert json.loads(ws.receive_text())["type"] == "subscribed"
        stamp, T_l_c, kid, T_l_kf = last["B"]
        p = PoseUpdate("B", stamp + 1, T_l_c, kid, se3_inv(T_l_kf) @ T_l_c, "ok", 20.0)
        m.process_pose_bytes(keys.agent_pose("B"), p.encode(), 0)
        msg = json.loads(ws.receive_text())
        assert msg["type"] == "pose" and msg["agent"] == "B" and msg["stamp_ns"] == stamp + 1
        np.testing.assert_allclose(msg["position"], T_l_c[:3, 3], atol=1e-9)
    m.store.r.close()


def _until(ws, pred, n: int = 50) -> dict:
    for _ in range(n):
        msg = json.loads(ws.receive_text())
        if pred(msg):
            return msg
    raise AssertionError("message never came")


def test_viewer_feed_over_websocket(filled):
    """What the viewer draws comes over /ws/viewer: state (agents, trajectories, status),
    each map's capped points, then live poses."""
    import time

    from services.api import feed

    s, last = filled
    m = MapperService(s)
    m.load()
    with TestClient(create_app(s)) as c:
        js = c.get("/static/viewer.js")
        assert js.status_code == 200 and "ws/viewer" in js.text
        assert c.get("/static/secrets.txt").status_code == 404
        pts = c.get("/maps/map-A/points?limit=100").json()
        assert pts["n"] == 100 and pts["n_total"] > 100
        with c.websocket_connect("/ws/viewer") as ws:
            assert json.loads(ws.receive_text())["type"] == "hello"
            st = _until(ws, lambda x: x["type"] == "state")
            agents = {a["agent"]: a for a in st["agents"]}
            assert set(agents) == {"A", "B"}
            for a, info in agents.items():
                assert len(st["trajectories"][a]) == info["n_kf"] > 5
                # The fixture's poses were received at time 0: long gone.
                assert info["status"] == "disconnected"
            np.testing.assert_allclose(agents["A"]["position"], last["A"][1][:3, 3], atol=1e-3)
            got = _until(ws, lambda x: x["type"] == "points" and x["map_id"] == "map-B")
            assert 0 < got["n"] <= feed.POINTS_CAP and len(got["xyz"]) == 3 * got["n"]
            stamp, T_l_c, kid, T_l_kf = last["B"]
            p = PoseUpdate("B", stamp + 1, T_l_c, kid, se3_inv(T_l_kf) @ T_l_c, "lost", 20.0)
            m.process_pose_bytes(keys.agent_pose("B"), p.encode(), time.time_ns())
            poses = _until(ws, lambda x: x["type"] == "poses")["poses"]
            assert [(q["agent"], q["status"]) for q in poses] == [("B", "lost")]
    m.store.r.close()


def test_viewer_events_are_merges_and_new_loops():
    from services.api.feed import diff_events

    def st(maps, loops, t=1.0):
        return {"t": t, "agents": [{"agent": "A", "position": [1, 2, 3]}],
                "maps": [{"map_id": k, "agents": ["A"], "merged_into": v} for k, v in maps],
                "loops": loops}  # fmt: skip

    e = {"id": "1:2", "a": [0, 0, 0], "b": [1, 1, 1]}
    a = st([("m0", None), ("m1", None)], {"m0": [], "m1": []})
    b = st([("m0", None), ("m1", "m0")], {"m0": [e], "m1": []})
    c = st([("m0", None), ("m1", "m0")], {"m0": [e, {**e, "id": "3:4"}], "m1": []})
    assert diff_events(None, a) == []
    (merge,) = diff_events(a, b)  # the merge's own edge is no loop event
    assert (merge["kind"], merge["source"], merge["target"], merge["at"]) == (
        "merge", "m1", "m0", [1, 2, 3])  # fmt: skip
    (loop,) = diff_events(b, c)
    assert loop["kind"] == "loop" and loop["map_id"] == "m0"
    assert diff_events(c, c) == []


def test_ws_poses_lets_go_of_a_client_that_left_while_no_pose_came(redis_url):
    """/ws/poses waited only for poses: with none flowing it never noticed a client that
    had gone (closed, or its connection dropped without a close frame), and kept its
    handler and Redis subscription for as long as the API ran."""
    import socket
    import threading

    import redis
    import uvicorn
    import websockets.sync.client as ws_client
    from procs import wait_until

    from shared.redis_server import free_port
    from shared.store import POSE_CHANNEL

    port = free_port()
    app = create_app(Settings(redis_url=redis_url))
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    t = threading.Thread(target=server.run, daemon=True)
    t.start()
    r = redis.Redis.from_url(redis_url)

    def subscribers() -> int:
        return int(r.pubsub_numsub(POSE_CHANNEL)[0][1])

    try:
        assert wait_until(lambda: server.started, 10)
        for polite in (False, True):
            with ws_client.connect(f"ws://127.0.0.1:{port}/ws/poses", open_timeout=10) as ws:
                assert json.loads(ws.recv(timeout=10))["type"] == "subscribed"
                assert subscribers() == 1
                if polite:
                    ws.close()
                else:  # gone without a close frame: the TCP connection just ends
                    ws.socket.shutdown(socket.SHUT_RDWR)
                    ws.socket.close()
                gone = wait_until(lambda: subscribers() == 0, 5)
            assert gone, f"the handler kept its subscription ({polite=})"
    finally:
        server.should_exit = True
        t.join(10)
        r.close()
