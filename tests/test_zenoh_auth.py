"""The Zenoh router with per-agent credentials and access rules (shared/zenoh_auth.py),
a real router and the real mapper: agent A can't speak or listen for B, nor inject a
map correction, and nobody without credentials connects."""

from __future__ import annotations

import json
import queue
import time

import pytest
import zenoh
from messages_fixtures import sample_batch

from services.mapper.service import MapperService
from shared import keys
from shared.metrics import sample_value
from shared.redis_server import free_port
from shared.settings import Settings, ZenohSettings
from shared.store import Store, connect
from shared.transport import open_session, zenoh_config
from shared.zenoh_auth import access_control, ensure_users


@pytest.fixture()
def auth_router(tmp_path):
    creds = ensure_users(tmp_path / "zenoh", ["A", "B"])
    ep = f"tcp/127.0.0.1:{free_port()}"
    zs = ZenohSettings(mode="router", connect=[], listen=[ep], auth_dir=str(tmp_path / "zenoh"))
    with zenoh.open(zenoh_config(zs)):
        yield ep, creds


def _client(ep: str, user: str = "", password: str = "", timeout_ms: int = 3000) -> zenoh.Session:
    return open_session(ZenohSettings(connect=[ep], user=user, password=password,
                                      connect_timeout_ms=timeout_ms))  # fmt: skip


@pytest.mark.parametrize("who", [("", ""), ("A", "wrong"), ("C", "whatever")])
def test_no_or_wrong_credentials_cannot_connect(auth_router, who):
    ep, _ = auth_router
    t0 = time.monotonic()
    with pytest.raises(zenoh.ZError):
        _client(ep, *who, timeout_ms=1500)
    assert time.monotonic() - t0 < 10


def _drain(q: queue.Queue, wait: float) -> list:
    time.sleep(wait)
    out = []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out


def test_agent_a_cannot_speak_or_listen_for_b_and_the_mapper_sees_nothing(auth_router, redis_url):
    ep, creds = auth_router
    s = Settings(redis_url=redis_url,
                 zenoh=ZenohSettings(connect=[ep], user="svc-mapper",
                                     password=creds["svc-mapper"]))  # fmt: skip
    # The metrics registry is the process's: other tests in this run may have counted
    # B's and A's keys already, so the assertions compare with what was there before.
    heard_b = {"service": "mapper", "direction": "in", "key": keys.agent_kf("B")}
    heard = {"service": "mapper", "direction": "in", "key": keys.agent_kf("A")}
    b0, a0 = (
        sample_value("hivemap_messages_total", heard_b),
        sample_value("hivemap_messages_total", heard),
    )
    mapper = MapperService(s)
    mapper.start()
    svc = _client(ep, "svc-placerec", creds["svc-placerec"])
    a = _client(ep, "A", creds["A"])
    try:
        got: queue.Queue = queue.Queue()
        svc.declare_subscriber(keys.ALL_MAP_CORRECTION, lambda x: got.put(("svc", str(x.key_expr))))
        a.declare_subscriber(keys.agent_ack("B"), lambda x: got.put(("A:B-ack", str(x.key_expr))))
        a.declare_subscriber(keys.agent_map("B"), lambda x: got.put(("A:B-map", str(x.key_expr))))
        a.declare_subscriber(keys.agent_ack("A"), lambda x: got.put(("A:A-ack", str(x.key_expr))))
        time.sleep(1.0)
        batch = sample_batch()  # agent "A"'s keyframe batch
        batch.agent = "B"
        a.put(keys.agent_kf("B"), batch.encode())  # publish as B
        a.put(keys.map_correction("map-B"), b"\x93forged correction")
        svc.put(keys.agent_ack("B"), b"B's ack")  # B's downlink
        svc.put(keys.agent_map("B"), b"B's map chunk")
        seen = _drain(got, 2.0)
        assert seen == [], seen
        assert Store(connect(redis_url)).keyframe_ids("B") == []
        assert sample_value("hivemap_messages_total", heard_b) == b0
        # Control: the same client on its own keys is heard, and hears its own downlink.
        batch.agent = "A"
        a.put(keys.agent_kf("A"), batch.encode())
        svc.put(keys.agent_ack("A"), b"A's ack")
        deadline = time.monotonic() + 10
        while (
            time.monotonic() < deadline and sample_value("hivemap_messages_total", heard) < a0 + 1
        ):
            time.sleep(0.1)
        assert sample_value("hivemap_messages_total", heard) == a0 + 1
        assert ("A:A-ack", keys.agent_ack("A")) in _drain(got, 0.5)
    finally:
        a.close()
        svc.close()
        mapper.stop()


def test_a_wildcard_subscription_hears_only_the_agents_own_downlink(auth_router):
    """``hivemap/**`` is not inside A's downlink, so the router drops that declaration
    (zenoh's ACL matches by inclusion); what reaches A's session at all is its downlink,
    which its session then hands to every matching subscriber of its own."""
    ep, creds = auth_router
    svc = _client(ep, "svc-mapper", creds["svc-mapper"])
    a = _client(ep, "A", creds["A"])
    try:
        got: queue.Queue = queue.Queue()
        a.declare_subscriber("hivemap/**", lambda x: got.put(("all", str(x.key_expr))))
        a.declare_subscriber("hivemap/agent/A/down/**", lambda x: got.put(("own", str(x.key_expr))))
        time.sleep(1.0)
        for k in (keys.agent_ack("B"), keys.agent_map("B"), keys.map_correction("map-A"),
                  keys.map_kf("map-A"), keys.MATCH, keys.agent_ack("A")):  # fmt: skip
            svc.put(k, b"x")
        heard = _drain(got, 1.5)
        assert {k for _, k in heard} == {keys.agent_ack("A")}, heard
    finally:
        a.close()
        svc.close()


def test_rules_name_the_project_keys():
    acl = access_control(["A"])
    a_rules = [r for r in acl["rules"] if r["id"].startswith("agent1")]
    by_id = {r["id"].split("-", 1)[1]: r for r in a_rules}
    assert by_id["put"]["key_exprs"] == ["hivemap/agent/A/up/**"]
    assert by_id["put"]["flows"] == ["ingress"] and by_id["put"]["messages"] == ["put"]
    assert by_id["sub"]["key_exprs"] == by_id["down"]["key_exprs"] == ["hivemap/agent/A/down/**"]
    assert keys.agent_kf("A").startswith("hivemap/agent/A/up/")
    assert keys.agent_ack("A").startswith("hivemap/agent/A/down/")
    assert json.loads(json.dumps(acl)) == acl  # goes into the router's config as JSON


def test_router_and_up_refuse_the_network_without_authentication(tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    exe = str(Path(sys.executable).with_name("hivemap"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIVEMAP_")}
    ep = f"tcp/0.0.0.0:{free_port()}"
    for argv in (["router", "--listen", ep], ["up", "--ephemeral", "--listen", ep]):
        p = subprocess.run([exe, *argv], env=env, capture_output=True, text=True, timeout=60,
                           cwd=tmp_path)  # fmt: skip
        assert p.returncode == 2 and "refusing to listen beyond loopback" in p.stderr, p.stderr


def test_stack_with_authentication_serves_each_agent_as_itself(tmp_path):
    """`hivemap up --agents A` as the launcher runs it: services log in with their own
    identity; a simulated agent with A's credentials is mapped, one claiming to be B with
    A's credentials is not."""
    from services.launcher import Stack
    from shared.zenoh_auth import read_credentials

    s = Settings(api_port=free_port(), mapper_metrics_port=free_port(),
                 placerec_metrics_port=free_port(), optimizer_metrics_port=free_port(),
                 log_level="WARNING")  # fmt: skip
    stack = Stack(s, data_dir=str(tmp_path / "data"), auth_agents=["A"])
    try:
        stack.start(with_api=False)
        creds = read_credentials(tmp_path / "data" / "zenoh")
        assert {"A", "svc-mapper", "svc-placerec", "svc-optimizer", "sim-fleet"} <= set(creds)
        a_file = tmp_path / "data" / "zenoh" / "A.json"
        assert oct(a_file.stat().st_mode & 0o777) == "0o600"
        sim = ["sim-agent", "--traj", "MH01", "--frames", "900:1400", "--speed", "4",
               "--flush-timeout", "10", "--credentials", str(a_file)]  # fmt: skip
        stack.add("sim-A", [*sim[:1], "--id", "A", *sim[1:]], env={"HIVEMAP_LOG_LEVEL": "ERROR"})
        stack.add("sim-B", [*sim[:1], "--id", "B", *sim[1:]], env={"HIVEMAP_LOG_LEVEL": "ERROR"})
        store = Store(connect(stack.settings.redis_url))
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and len(store.keyframe_ids("A")) < 3:
            time.sleep(0.5)
        assert len(store.keyframe_ids("A")) >= 3
        time.sleep(3)
        assert store.keyframe_ids("B") == [] and "B" not in store.agents()
    finally:
        stack.stop()


def test_zenohd_config_file_is_what_a_router_enforces(tmp_path):
    """What `hivemap credentials add ... --zenohd FILE` writes for compose's zenohd: a real
    router loads it and enforces it; the services log in from their credentials files."""
    import subprocess
    import sys
    from pathlib import Path

    import yaml

    exe = str(Path(sys.executable).with_name("hivemap"))
    zdir = tmp_path / "zenoh"
    p = subprocess.run([exe, "credentials", "add", "A", "--data-dir", str(tmp_path), "--zenohd",
                        str(zdir / "router.json5"), "--dictionary", str(zdir / "credentials")],
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert p.returncode == 0, p.stderr
    conf = zenoh.Config.from_file(str(zdir / "router.json5"))
    ep = f"tcp/127.0.0.1:{free_port()}"
    conf.insert_json5("listen/endpoints", json.dumps([ep]))
    with zenoh.open(conf):
        with pytest.raises(zenoh.ZError):
            _client(ep, timeout_ms=1500)
        zs = ZenohSettings(connect=[ep], credentials=str(zdir / "svc-mapper.json"),
                           connect_timeout_ms=3000)  # fmt: skip
        open_session(zs).close()
    compose = yaml.safe_load((Path(__file__).parents[1] / "docker-compose.yml").read_text())
    svcs = compose["services"]
    assert svcs["zenohd"]["command"][:2] == ["-c", "/etc/hivemap/zenoh/router.json5"]
    for name in ("mapper", "placerec", "optimizer"):
        cred = svcs[name]["environment"]["HIVEMAP_ZENOH__CREDENTIALS"]
        assert cred == f"/etc/hivemap/zenoh/svc-{name}.json"
    bad = subprocess.run([exe, "credentials", "add", "svc-mapper", "--data-dir", str(tmp_path)],
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert bad.returncode == 2 and "belongs to a service" in bad.stderr


def test_tls_listener_with_the_readme_certificates(tmp_path):
    """The README's openssl commands and config snippets: a router on tls/ with them, an
    agent trusting the CA logs in; one without the CA cannot connect."""
    import shutil
    import subprocess

    if shutil.which("openssl") is None:
        pytest.skip("no openssl to make certificates with")
    d = tmp_path
    for cmd in (
        "openssl req -x509 -newkey rsa:2048 -nodes -days 365 -subj /CN=hivemap-ca "
        "-keyout ca.key -out ca.pem",
        "openssl req -newkey rsa:2048 -nodes -subj /CN=localhost -keyout router.key "
        "-out router.csr",
        "openssl x509 -req -in router.csr -CA ca.pem -CAkey ca.key -CAcreateserial -days 365 "
        "-extfile san.ext -out router.pem",
    ):
        (d / "san.ext").write_text("subjectAltName=DNS:localhost\n")
        subprocess.run(cmd.split(), cwd=d, check=True, capture_output=True, timeout=60)
    (d / "router-tls.json5").write_text(json.dumps({"transport": {"link": {"tls": {
        "listen_private_key": str(d / "router.key"),
        "listen_certificate": str(d / "router.pem")}}}}))  # fmt: skip
    (d / "agent-tls.json5").write_text(json.dumps({"transport": {"link": {"tls": {
        "root_ca_certificate": str(d / "ca.pem")}}}}))  # fmt: skip
    creds = ensure_users(d / "zenoh", ["A"])
    port = free_port()
    zs = ZenohSettings(mode="router", connect=[], listen=[f"tls/127.0.0.1:{port}"],
                       auth_dir=str(d / "zenoh"),
                       config_file=str(d / "router-tls.json5"))  # fmt: skip
    ep = f"tls/localhost:{port}"
    with zenoh.open(zenoh_config(zs)):
        ok = ZenohSettings(connect=[ep], user="A", password=creds["A"], connect_timeout_ms=5000,
                           config_file=str(d / "agent-tls.json5"))  # fmt: skip
        open_session(ok).close()
        with pytest.raises(zenoh.ZError):  # does not trust the router's certificate
            open_session(ZenohSettings(connect=[ep], user="A", password=creds["A"],
                                       connect_timeout_ms=1500))  # fmt: skip
