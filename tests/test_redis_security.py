"""Redis under `hivemap up`: loopback only, and no client without the password."""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path

import pytest
import redis

from services.launcher import Stack
from shared.redis_server import RedisServer, free_port
from shared.settings import Settings


def _refused(port: int, password: str | None = None) -> None:
    # retry=None: redis-py retries a refused command with backoff (3.5 s each here).
    c = redis.Redis(host="127.0.0.1", port=port, password=password, socket_connect_timeout=2,
                    retry=None)  # fmt: skip
    try:
        with pytest.raises(redis.AuthenticationError):
            c.ping()
        with pytest.raises(redis.AuthenticationError):
            c.get("anything")
    finally:
        c.close()


def test_a_client_without_the_password_is_refused():
    srv = RedisServer(password="s3cret-pass")
    url = srv.start()
    try:
        assert url == f"redis://:s3cret-pass@127.0.0.1:{srv.port}/0"
        _refused(srv.port)
        _refused(srv.port, "wrong")
        ok = redis.Redis.from_url(url)
        assert ok.ping() and ok.config_get("bind")["bind"] == "127.0.0.1"
        assert ok.config_get("protected-mode")["protected-mode"] == "yes"
        ok.close()
        # The password is in an owner-only file, not on the command line ps shows.
        assert b"s3cret-pass" not in Path(f"/proc/{srv.proc.pid}/cmdline").read_bytes()
    finally:
        srv.stop()


def test_hivemap_up_redis_needs_its_password():
    s = Settings(api_port=free_port(), mapper_metrics_port=free_port(),
                 placerec_metrics_port=free_port(), optimizer_metrics_port=free_port(),
                 log_level="WARNING")  # fmt: skip
    stack = Stack(s)
    try:
        stack.start()
        url = stack.settings.redis_url
        assert stack.redis.password and f":{stack.redis.password}@127.0.0.1:" in url
        _refused(stack.redis.port)
        # The services got it: the API answers ready only once it reads Redis.
        req = urllib.request.Request(f"http://127.0.0.1:{s.api_port}/ready")
        with urllib.request.urlopen(req, timeout=5) as r:
            assert json.loads(r.read()) == {"status": "ready"}
    finally:
        stack.stop()
