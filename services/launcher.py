"""``hivemap up``, ``hivemap demo`` and ``hivemap router``: the whole stack as child processes.

The process plan built here is the same topology as docker-compose.yml (a test
compares them), so a run of ``hivemap up`` proves the compose deployment too.
Children run in their own process group; Ctrl-C or SIGTERM stops all of them and
waits, so no orphan is left.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from shared.redis_server import RedisServer, free_port
from shared.runtime import set_priority
from shared.settings import DEFAULT_ROUTER, Settings

log = logging.getLogger(__name__)


@dataclass
class ServiceSpec:
    name: str
    argv: list[str]
    env: dict[str, str] = field(default_factory=dict)
    http_port: int | None = None


def service_plan(settings: Settings) -> list[ServiceSpec]:
    """Every process of the stack, in start order. ``router`` and ``redis`` are the
    infrastructure (zenohd and redis images in compose); the rest are hivemap services."""
    router_ep = settings.zenoh.connect[0] if settings.zenoh.connect else DEFAULT_ROUTER
    common = {
        "HIVEMAP_ZENOH__MODE": "client",
        "HIVEMAP_ZENOH__CONNECT": json.dumps([router_ep]),
        "HIVEMAP_REDIS_URL": settings.redis_url,
    }
    return [
        ServiceSpec("router", ["hivemap", "router", "--listen", router_ep]),
        ServiceSpec("redis", ["redis-server"]),
        ServiceSpec(
            "mapper",
            ["hivemap", "mapper"],
            {**common, "HIVEMAP_METRICS_PORT": str(settings.mapper_metrics_port)},
            settings.mapper_metrics_port,
        ),
        ServiceSpec(
            "placerec",
            ["hivemap", "placerec"],
            {**common, "HIVEMAP_METRICS_PORT": str(settings.placerec_metrics_port)},
            settings.placerec_metrics_port,
        ),
        ServiceSpec(
            "optimizer",
            ["hivemap", "optimizer"],
            {**common, "HIVEMAP_METRICS_PORT": str(settings.optimizer_metrics_port)},
            settings.optimizer_metrics_port,
        ),
        ServiceSpec(
            "api",
            ["hivemap", "api"],
            {
                **common,
                "HIVEMAP_API_PORT": str(settings.api_port),
                "HIVEMAP_API_HOST": settings.api_host,
            },
            settings.api_port,
        ),  # fmt: skip
    ]


def _hivemap_exe() -> list[str]:
    exe = Path(sys.executable).with_name("hivemap")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "services.cli"]


def tcp_host_port(endpoint: str) -> tuple[str, int]:
    """``tcp/HOST:PORT`` -> (HOST, PORT); a clear error for anything else."""
    proto, _, addr = endpoint.partition("/")
    host, _, port = addr.rpartition(":")
    if proto != "tcp" or not host or not port.isdigit():
        raise ValueError(f"router endpoint {endpoint!r} is not tcp/HOST:PORT")
    return host.strip("[]"), int(port)


def check_free(host: str, port: int, what: str, hint: str) -> None:
    """Fail before starting anything when a fixed port is taken: otherwise the router
    would exit while the launcher's readiness check found the other process listening,
    and agents would talk to whoever holds the port."""
    import socket

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        # As a listening server binds: a port in TIME_WAIT is free, a listener is not.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            raise PortInUse(f"{what} {host}:{port} is not free ({e.strerror}); {hint}") from None


class PortInUse(RuntimeError):
    pass


class Stack:
    """Starts the plan's processes and stops them all, in reverse order.

    ``listen`` is the router's endpoint; None picks a free port (tests and benches run
    several stacks side by side), ``hivemap up`` passes tcp/127.0.0.1:7447, where
    agents look by default."""

    def __init__(
        self,
        settings: Settings,
        data_dir: str | None = None,
        env: dict[str, str] | None = None,
        listen: str | None = None,
    ) -> None:
        self.settings = settings
        self.data_dir = data_dir
        self.env = dict(env or {})  # extra HIVEMAP_* variables for every service
        self.listen = listen
        self.redis: RedisServer | None = None
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, with_api: bool = True) -> None:
        s = self.settings
        if self.listen is not None:
            host, port = tcp_host_port(self.listen)
            check_free(host, port, "router endpoint", "is another `hivemap up` running? "
                       "Stop it or pick another with --listen")  # fmt: skip
            endpoint = self.listen
        else:
            host, port = "127.0.0.1", free_port()
            endpoint = f"tcp/{host}:{port}"
        if with_api:
            check_free(s.api_host, s.api_port, "API address",
                       "set HIVEMAP_API_PORT to use another port")  # fmt: skip
        self.redis = RedisServer(data_dir=self.data_dir, persist=self.data_dir is not None)
        redis_url = self.redis.start()
        self.settings = s.model_copy(
            update={"redis_url": redis_url,
                    "zenoh": s.zenoh.model_copy(update={"connect": [endpoint]})}
        )  # fmt: skip
        for spec in service_plan(self.settings):
            if spec.name == "redis" or (spec.name == "api" and not with_api):
                continue
            argv = _hivemap_exe() + spec.argv[1:]
            env = {**os.environ, **self.env, **spec.env}
            proc = subprocess.Popen(argv, env=env, start_new_session=True)
            self.procs.append((spec.name, proc))
            if spec.name == "router":
                _wait_port(host, port, 15.0)
        if with_api:
            _wait_port(self.settings.api_host, self.settings.api_port, 30.0)

    @property
    def zenoh_endpoint(self) -> str:
        return self.settings.zenoh.connect[0]

    def add(
        self, name: str, argv: list[str], env: dict[str, str] | None = None, nice: int = 0
    ) -> None:
        """Start one more process on the stack's network. ``nice`` > 0 lowers its CPU
        priority: agents are other computers in the field, and on one test machine they
        must not starve the server of the CPU it would have on its own."""
        e = {
            **os.environ,
            "HIVEMAP_ZENOH__MODE": "client",
            "HIVEMAP_ZENOH__CONNECT": json.dumps([self.zenoh_endpoint]),
            "HIVEMAP_REDIS_URL": self.settings.redis_url,
            **(env or {}),
        }
        pre = (lambda: set_priority(nice)) if nice > 0 else None
        proc = subprocess.Popen(_hivemap_exe() + argv, env=e, start_new_session=True,
                                preexec_fn=pre)  # fmt: skip
        self.procs.append((name, proc))

    def failed(self) -> list[str]:
        return [n for n, p in self.procs if p.poll() is not None and p.returncode != 0]

    def stop(self, timeout: float = 10.0) -> None:
        for _, p in reversed(self.procs):
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for _, p in reversed(self.procs):
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        self.procs.clear()
        if self.redis:
            self.redis.stop()
            self.redis = None


def _wait_port(host: str, port: int, timeout: float) -> None:
    import socket

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise TimeoutError(f"nothing listens on {host}:{port} after {timeout:.0f} s")


def _stop_on_signal() -> threading.Event:
    """Route SIGINT/SIGTERM to an event. Installed before any child starts: a signal
    that arrived between the API answering and the handler going in would kill the
    launcher outright and leave its children, each in its own session, orphaned."""
    stop = threading.Event()

    def handler(signum, frame):  # noqa: ARG001
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def _run_until_signal(stack: Stack, stop: threading.Event) -> int:
    try:
        while not stop.wait(0.5):
            bad = stack.failed()
            if bad:
                print(f"hivemap: {', '.join(bad)} exited with an error; stopping", file=sys.stderr)
                return 1
        return 0
    finally:
        stack.stop()


def _print_urls(stack: Stack) -> None:
    s = stack.settings
    print(f"zenoh router : {stack.zenoh_endpoint}")
    print(f"redis        : {s.redis_url}")
    print(f"api          : http://{s.api_host}:{s.api_port}/  (viewer), /agents, /docs")
    print(f"mapper       : http://127.0.0.1:{s.mapper_metrics_port}/metrics")
    print(f"placerec     : http://127.0.0.1:{s.placerec_metrics_port}/metrics")
    print(f"optimizer    : http://127.0.0.1:{s.optimizer_metrics_port}/metrics")
    print("Ctrl-C stops everything.", flush=True)


def _start_or_explain(stack: Stack) -> bool:
    try:
        stack.start()
    except (PortInUse, ValueError) as e:
        stack.stop()
        print(f"hivemap: {e}", file=sys.stderr)
        return False
    except Exception:
        stack.stop()
        raise
    return True


def cmd_up(args: argparse.Namespace, settings: Settings) -> int:
    stop = _stop_on_signal()
    stack = Stack(settings, data_dir=args.data_dir, listen=args.listen)
    if not _start_or_explain(stack):
        return 2
    _print_urls(stack)
    return _run_until_signal(stack, stop)


def cmd_demo(args: argparse.Namespace, settings: Settings) -> int:
    stop = _stop_on_signal()
    stack = Stack(settings, data_dir=args.data_dir, listen=args.listen)
    if not _start_or_explain(stack):
        return 2
    _print_urls(stack)
    for i, seq in enumerate(args.trajs.split(",")):
        agent = f"agent{i + 1}"
        stack.add(
            f"sim-{agent}",
            ["sim-agent", "--id", agent, "--traj", seq, "--speed", str(args.speed),
             "--seed", str(i + 1)],
        )  # fmt: skip
        print(f"agent        : {agent} flying {seq} at {args.speed}x real time")
    sys.stdout.flush()
    return _run_until_signal(stack, stop)


def cmd_router(args: argparse.Namespace, settings: Settings) -> int:
    import zenoh

    from shared.settings import ZenohSettings
    from shared.transport import zenoh_config

    zs = ZenohSettings(mode="router", connect=[], listen=args.listen)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with zenoh.open(zenoh_config(zs)):
        log.info("zenoh router listening on %s", ", ".join(args.listen))
        stop.wait()
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="start router, redis and every service on this machine")
    p.add_argument("--data-dir", default=None, help="keep Redis data here (append-only file)")
    _add_listen(p)
    p.set_defaults(func=cmd_up)

    p = sub.add_parser("demo", help="`up` plus simulated agents flying EuRoC MH trajectories")
    p.add_argument("--trajs", default="MH01,MH02,MH03")
    p.add_argument("--speed", type=float, default=1.0, help="real-time factor")
    p.add_argument("--data-dir", default=None)
    _add_listen(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("router", help="a Zenoh router in this Python process")
    p.add_argument("--listen", action="append", default=None, help="endpoint, repeatable")
    p.set_defaults(func=lambda a, s: cmd_router(_default_listen(a), s))


def _add_listen(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", default=DEFAULT_ROUTER,
                   help=f"the Zenoh router's endpoint (default {DEFAULT_ROUTER}, where "
                   "`hivemap agent` looks unless given --server)")  # fmt: skip


def _default_listen(args: argparse.Namespace) -> argparse.Namespace:
    if not args.listen:
        args.listen = [DEFAULT_ROUTER]
    return args
