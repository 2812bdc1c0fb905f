"""The API's bearer token, its refusal to serve the network without one, and its bounds."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse

from services.api.main import create_app
from services.api.security import InsecureConfig, is_loopback
from services.launcher import api_token
from shared.metrics import sample_value
from shared.redis_server import free_port
from shared.settings import Settings

TOKEN = "t0k3n-for-tests"


@pytest.fixture()
def client(redis_url):
    with TestClient(create_app(Settings(redis_url=redis_url, api_token=TOKEN))) as c:
        yield c


def test_rest_needs_the_token_except_probes(client):
    before = sample_value("hivemap_api_rejected_total", {"reason": "unauthorized"})
    r = client.get("/agents")
    assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    assert r.json()["error"] == "missing or wrong API token"
    assert client.get("/agents", headers={"Authorization": "Bearer wrong"}).status_code == 401
    assert client.get("/agents", headers={"Authorization": f"Basic {TOKEN}"}).status_code == 401
    assert client.get("/maps").status_code == 401
    assert client.get("/agents/A/pose").status_code == 401  # no hint whether A exists
    assert client.get("/").status_code == 401
    assert sample_value("hivemap_api_rejected_total", {"reason": "unauthorized"}) == before + 6

    auth = {"Authorization": f"Bearer {TOKEN}"}
    assert client.get("/agents", headers=auth).json() == []
    assert client.get("/maps", headers=auth).json() == []
    assert client.get("/agents/nobody/pose", headers=auth).status_code == 404
    assert client.get(f"/agents?token={TOKEN}").status_code == 200
    page = client.get(f"/?token={TOKEN}")
    assert page.status_code == 200 and "static/viewer.js" in page.text
    # The page's script holds no data and loads without it (a browser sends no token
    # there); it passes the page's token on to the WebSocket.
    js = client.get("/static/viewer.js")
    assert js.status_code == 200 and "?token=" in js.text

    assert client.get("/health").json() == {"status": "ok"}
    assert client.get("/ready").json() == {"status": "ready"}
    assert "hivemap_api_requests_total" in client.get("/metrics").text


@pytest.mark.parametrize(("path", "first"), [("/ws/poses", "subscribed"), ("/ws/viewer", "hello")])
def test_websocket_needs_the_token(client, path, first):
    with pytest.raises(WebSocketDenialResponse) as e, client.websocket_connect(path):
        pass
    assert e.value.status_code == 401
    with pytest.raises(WebSocketDenialResponse), client.websocket_connect(f"{path}?token=no"):
        pass
    with client.websocket_connect(f"{path}?token={TOKEN}") as ws:
        assert json.loads(ws.receive_text())["type"] == first
    hdr = {"Authorization": f"Bearer {TOKEN}"}
    with client.websocket_connect(path, headers=hdr) as ws:
        assert json.loads(ws.receive_text())["type"] == first


def test_openapi_documents_the_security_schemes(client):
    doc = client.get("/openapi.json").json()
    assert set(doc["components"]["securitySchemes"]) == {"bearer", "token"}
    assert "security" in doc["paths"]["/agents"]["get"]
    assert "security" not in doc["paths"]["/health"]["get"]


def test_no_token_only_on_loopback(redis_url):
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("::") and not is_loopback("myhost")
    with pytest.raises(InsecureConfig, match="HIVEMAP_API_TOKEN"):
        create_app(Settings(redis_url=redis_url, api_host="0.0.0.0"))
    create_app(Settings(redis_url=redis_url, api_host="0.0.0.0", api_token=TOKEN))


def test_api_process_bound_to_any_address_without_token_refuses_to_start(redis_url):
    port = free_port()
    env = {**os.environ, "HIVEMAP_API_HOST": "0.0.0.0", "HIVEMAP_API_PORT": str(port),
           "HIVEMAP_REDIS_URL": redis_url}  # fmt: skip
    env.pop("HIVEMAP_API_TOKEN", None)
    t0 = time.monotonic()
    p = subprocess.run([str(Path(sys.executable).with_name("hivemap")), "api"], env=env,
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert p.returncode == 2, p.stderr
    assert "refusing to start" in p.stderr and "HIVEMAP_API_TOKEN" in p.stderr
    print(f"\nrefused in {time.monotonic() - t0:.1f} s")


def test_cors_off_and_bodies_bounded(client):
    r = client.get("/health", headers={"Origin": "http://evil.example"})
    assert "access-control-allow-origin" not in r.headers
    r = client.request("GET", "/health", content=b"x" * 20_000)
    assert r.status_code == 413


def test_cors_only_for_configured_origins(redis_url):
    s = Settings(redis_url=redis_url, api_token=TOKEN, api_cors_origins=["http://ok.example"])
    with TestClient(create_app(s)) as c:
        ok = c.get("/health", headers={"Origin": "http://ok.example"})
        assert ok.headers["access-control-allow-origin"] == "http://ok.example"
        bad = c.get("/health", headers={"Origin": "http://evil.example"})
        assert "access-control-allow-origin" not in bad.headers


def test_launcher_keeps_one_token_in_the_data_dir(tmp_path):
    s = Settings()
    first = api_token(s, str(tmp_path))
    assert len(first) >= 40 and api_token(s, str(tmp_path)) == first
    assert stat.S_IMODE((tmp_path / "api_token").stat().st_mode) == 0o600
    assert api_token(s, None) != api_token(s, None)  # no data dir: a fresh one per run
    assert api_token(Settings(api_token="given"), str(tmp_path)) == "given"
