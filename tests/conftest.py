"""Fixtures: a private redis-server and a private Zenoh router on free 127.0.0.1 ports."""

from __future__ import annotations

import os

import pytest

from shared.redis_server import RedisServer, free_port
from shared.settings import Settings, ZenohSettings

# Determinism and fairness on 2-core machines: numeric libs use one thread each.
os.environ.setdefault("OMP_NUM_THREADS", "1")

# `make test` runs the suite in two phases: everything not marked "serial" on two
# pytest-xdist workers (most tests wait on sockets and subprocesses more than they
# compute: a one-worker suite used 83 % of one core), then the "serial" tests alone.
# Serial are the live stacks whose assertions are about time (latency percentiles,
# drain and restart deadlines, frames per second), which two workers would halve.
SERIAL_MODULES = {
    "test_compose",
    "test_overload",
    "test_mapper_service",
    "test_mapper_ownership",
    "test_viewer",
    "test_supervised_up",
    "test_e2e_mapper",
    "test_gcpause",
    "test_prometheus",
    "test_lossy_link",
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.module.__name__.rpartition(".")[2] in SERIAL_MODULES:
            item.add_marker(pytest.mark.serial)


@pytest.fixture(scope="session")
def redis_server():
    srv = RedisServer()
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture()
def redis_url(redis_server):
    """A clean database of the session's redis-server for each test."""
    import redis

    r = redis.Redis.from_url(redis_server.url)
    r.flushall()
    r.close()
    return redis_server.url


@pytest.fixture()
def zenoh_router():
    """A real Zenoh router (Python process mode) on a free loopback port."""
    import zenoh

    from shared.transport import zenoh_config

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    zs = ZenohSettings(mode="router", connect=[], listen=[endpoint])
    session = zenoh.open(zenoh_config(zs))
    try:
        yield endpoint
    finally:
        session.close()


@pytest.fixture(scope="module")
def world():
    """The landmark world of seed 0 the simulated agents fly in (one per test module)."""
    from services.agent.sim_agent import LandmarkWorld

    return LandmarkWorld(0)


@pytest.fixture()
def settings(redis_url, zenoh_router) -> Settings:
    return Settings(
        redis_url=redis_url,
        zenoh=ZenohSettings(mode="client", connect=[zenoh_router]),
    )
