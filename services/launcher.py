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
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from pydantic import SecretStr

from shared.redis_server import RedisServer, free_port
from shared.runtime import set_priority
from shared.settings import DEFAULT_ROUTER, Settings
from shared.zenoh_auth import CREDENTIALS, FLEET, check_agent

log = logging.getLogger(__name__)

DEFAULT_DATA_DIR = "hivemap-data"  # relative to where `hivemap up` runs


@dataclass
class ServiceSpec:
    name: str
    argv: list[str]
    env: dict[str, str] = field(default_factory=dict)
    http_port: int | None = None


@dataclass(frozen=True)
class Scale:
    """Instances of each scalable service (``hivemap up --mappers N --placerecs M
    --optimizers K``; compose's ``--scale``, the Deployments' ``replicas``)."""

    mappers: int = 1
    placerecs: int = 1
    optimizers: int = 1

    def __post_init__(self) -> None:
        for name in ("mappers", "placerecs", "optimizers"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name} must be at least 1")


# Instance i (from 0) of a service listens for metrics on its base port + 10 i: the
# bases are consecutive (mapper 9101, placerec 9102, optimizer 9103), so the second
# instances get 9111, 9112, 9113 and no two collide up to ten instances each.
PORT_STRIDE = 10


def service_plan(settings: Settings, scale: Scale | None = None) -> list[ServiceSpec]:
    """Every process of the stack, in start order. ``router`` and ``redis`` are the
    infrastructure (zenohd and redis images in compose); the rest are hivemap services.
    A service with one instance has its plain name; several are ``name-1``, ``name-2``."""
    scale = scale or Scale()
    router_ep = settings.zenoh.connect[0] if settings.zenoh.connect else DEFAULT_ROUTER
    common = {
        "HIVEMAP_ZENOH__MODE": "client",
        "HIVEMAP_ZENOH__CONNECT": json.dumps([router_ep]),
        "HIVEMAP_REDIS_URL": settings.redis_url,
    }
    plan = [
        ServiceSpec("router", ["hivemap", "router", "--listen", router_ep]),
        ServiceSpec("redis", ["redis-server"]),
    ]
    for name, n, base in (
        ("mapper", scale.mappers, settings.mapper_metrics_port),
        ("placerec", scale.placerecs, settings.placerec_metrics_port),
        ("optimizer", scale.optimizers, settings.optimizer_metrics_port),
    ):
        for i in range(n):
            port = base + PORT_STRIDE * i
            env = {**common, "HIVEMAP_METRICS_PORT": str(port)}
            if name == "mapper" and n > 1:
                # Each holds map leases under its own name (services/mapper/ownership.py);
                # one host name would make them one owner.
                env["HIVEMAP_MAPPER__INSTANCE"] = f"mapper-{i + 1}"
            plan.append(ServiceSpec(name if n == 1 else f"{name}-{i + 1}", ["hivemap", name],
                                    env, port))  # fmt: skip
    plan.append(
        ServiceSpec(
            "api",
            ["hivemap", "api"],
            {
                **common,
                "HIVEMAP_API_PORT": str(settings.api_port),
                "HIVEMAP_API_HOST": settings.api_host,
                "HIVEMAP_API_TOKEN": settings.api_token.get_secret_value(),
            },
            settings.api_port,
        )
    )
    return plan


def api_token(settings: Settings, data_dir: str | None) -> str:
    """The API token of a run: HIVEMAP_API_TOKEN if set; else the one kept in the data
    directory, created there (owner-only) on first start; else a fresh one for this run."""
    given = settings.api_token.get_secret_value()
    if given:
        return given
    if data_dir is None:
        return secrets.token_urlsafe(32)
    path = Path(data_dir) / "api_token"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_urlsafe(32) + "\n")
    return path.read_text().strip()


def _hivemap_exe() -> list[str]:
    exe = Path(sys.executable).with_name("hivemap")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "services.cli"]


def tcp_host_port(endpoint: str) -> tuple[str, int]:
    """``tcp/HOST:PORT`` or ``tls/HOST:PORT`` -> (HOST, PORT); a clear error otherwise."""
    proto, _, addr = endpoint.partition("/")
    host, _, port = addr.rpartition(":")
    if proto not in ("tcp", "tls") or not host or not port.isdigit():
        raise ValueError(f"router endpoint {endpoint!r} is not tcp/HOST:PORT or tls/HOST:PORT")
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


# A dead service comes back after RESTART_MIN_S, twice as long after each death that
# follows a short life, at most RESTART_MAX_S later; a service that ran STABLE_S
# starts over at RESTART_MIN_S. A service that cannot start (bad config) so costs a
# restart every half minute, not a busy loop, and one killed by accident is back at once.
RESTART_MIN_S = 0.5
RESTART_MAX_S = 30.0
STABLE_S = 60.0


def restart_delay(previous: float, ran_s: float) -> float:
    if previous <= 0 or ran_s >= STABLE_S:
        return RESTART_MIN_S
    return min(previous * 2, RESTART_MAX_S)


def describe_exit(returncode: int) -> str:
    if returncode < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-returncode).name}"
        return f"killed by signal {-returncode}"
    return f"exit code {returncode}"


@dataclass
class Child:
    """One process of the stack. ``supervised`` ones (the plan's services) are restarted
    when they die; added ones (agents) are not: they finish."""

    name: str
    argv: list[str]
    env: dict[str, str]
    proc: subprocess.Popen
    supervised: bool
    started: float = field(default_factory=time.monotonic)
    restarts: int = 0
    delay: float = 0.0
    restart_at: float | None = None  # set while dead and waiting for its restart
    preexec: object = None


class DataDirBusy(RuntimeError):
    pass


class Stack:
    """Starts the plan's processes, restarts one that dies (``supervise``), and stops
    them all, in reverse order.

    ``listen`` is the router's endpoint; None picks a free port (tests and benches run
    several stacks side by side), ``hivemap up`` passes tcp/127.0.0.1:7447, where
    agents look by default. ``data_dir`` keeps Redis's append-only file there, so the
    maps outlive the stack; None keeps nothing."""

    def __init__(
        self,
        settings: Settings,
        data_dir: str | None = None,
        env: dict[str, str] | None = None,
        listen: str | None = None,
        scale: Scale | None = None,
        auth_agents: list[str] | None = None,
    ) -> None:
        self.settings = settings
        # Not None: the router asks every client for a user and password, with per-agent
        # rules (shared/zenoh_auth.py); credentials are made for these agents.
        self.auth_agents = auth_agents
        self.auth_dir: str | None = None
        self._auth_tmp: tempfile.TemporaryDirectory | None = None
        self.credentials: dict[str, str] = {}
        self.scale = scale or Scale()
        self.data_dir = data_dir
        self.env = dict(env or {})  # extra HIVEMAP_* variables for every service
        self.listen = listen
        self.redis: RedisServer | None = None
        self.children: list[Child] = []
        self._lock_file = None
        self._redis_delay = 0.0
        self._redis_started = 0.0

    @property
    def procs(self) -> list[tuple[str, subprocess.Popen]]:
        return [(c.name, c.proc) for c in self.children]

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
        if self.data_dir is not None:
            self._lock_data_dir()
        # A fresh password each start: the services get it in their environment (readable
        # by this user only), and nothing else on the machine reaches the data without it.
        self.redis = RedisServer(data_dir=self.data_dir, persist=self.data_dir is not None,
                                 password=secrets.token_urlsafe(24))  # fmt: skip
        redis_url = self.redis.start()
        self._redis_started = time.monotonic()
        self.settings = s.model_copy(
            update={"redis_url": redis_url,
                    "zenoh": s.zenoh.model_copy(update={"connect": [endpoint]}),
                    "api_token": SecretStr(api_token(s, self.data_dir))}
        )  # fmt: skip
        if self.auth_agents is not None:
            self._make_credentials()
        for spec in service_plan(self.settings, self.scale):
            if spec.name == "redis" or (spec.name == "api" and not with_api):
                continue
            argv = _hivemap_exe() + spec.argv[1:]
            env = {**os.environ, **self.env, **spec.env}
            if self.auth_dir is not None:
                if spec.name == "router":
                    argv += ["--auth", self.auth_dir]
                env.update(self.zenoh_identity(f"svc-{spec.argv[1]}"))
            self._spawn(spec.name, argv, env, supervised=True)
            if spec.name == "router":
                _wait_port(host, port, 15.0)
        if with_api:
            _wait_port(self.settings.api_host, self.settings.api_port, 30.0)

    def _make_credentials(self) -> None:
        from shared.zenoh_auth import ensure_users

        if self.data_dir is not None:
            self.auth_dir = str(Path(self.data_dir) / "zenoh")
        else:
            self._auth_tmp = tempfile.TemporaryDirectory(prefix="hivemap-zenoh-")
            self.auth_dir = self._auth_tmp.name
        self.credentials = ensure_users(self.auth_dir, list(self.auth_agents or []))

    def zenoh_identity(self, user: str) -> dict[str, str]:
        """The environment that makes a hivemap process log in to the router as ``user``
        (nothing when the router asks for no credentials)."""
        if not self.credentials or user not in self.credentials:
            return {}
        return {"HIVEMAP_ZENOH__USER": user, "HIVEMAP_ZENOH__PASSWORD": self.credentials[user]}

    def _lock_data_dir(self) -> None:
        """Two stacks appending to one Redis file would corrupt it."""
        import fcntl

        d = Path(self.data_dir)
        d.mkdir(parents=True, exist_ok=True)
        f = open(d / "hivemap.lock", "a+")  # noqa: SIM115 -- held for the stack's life
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            raise DataDirBusy(f"data directory {d} is in use by another `hivemap up`; "
                              "stop it or pass another --data-dir") from None  # fmt: skip
        self._lock_file = f

    def _spawn(self, name: str, argv: list[str], env: dict[str, str], supervised: bool,
               preexec=None) -> Child:  # fmt: skip
        proc = subprocess.Popen(argv, env=env, start_new_session=True, preexec_fn=preexec)
        c = Child(name, argv, env, proc, supervised, preexec=preexec)
        self.children.append(c)
        return c

    @property
    def api_token(self) -> str:
        return self.settings.api_token.get_secret_value()

    @property
    def viewer_url(self) -> str:
        s = self.settings
        return f"http://{s.api_host}:{s.api_port}/?token={self.api_token}"

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
            # With authentication, the simulated fleet's identity unless env names one.
            **self.zenoh_identity(FLEET),
            **(env or {}),
        }
        pre = (lambda: set_priority(nice)) if nice > 0 else None
        self._spawn(name, _hivemap_exe() + argv, e, supervised=False, preexec=pre)

    def failed(self) -> list[str]:
        return [n for n, p in self.procs if p.poll() is not None and p.returncode != 0]

    def supervise(self, now: float | None = None) -> None:
        """One round: note each supervised process that died and restart it when its
        backoff is over. The others go on meanwhile: agents buffer and resend what the
        dead one did not acknowledge, and the mapper reloads its maps from Redis."""
        now = time.monotonic() if now is None else now
        self._supervise_redis(now)
        for c in self.children:
            if not c.supervised or c.proc.poll() is None:
                continue
            if c.restart_at is None:
                ran = now - c.started
                c.delay = restart_delay(c.delay, ran)
                c.restart_at = now + c.delay
                log.warning("%s (pid %d) %s after %.0f s; restarting it in %.1f s",
                            c.name, c.proc.pid, describe_exit(c.proc.returncode), ran,
                            c.delay)  # fmt: skip
            elif now >= c.restart_at:
                c.proc = subprocess.Popen(c.argv, env=c.env, start_new_session=True,
                                          preexec_fn=c.preexec)  # fmt: skip
                c.started, c.restart_at = now, None
                c.restarts += 1
                log.warning("%s restarted (pid %d, restart %d)", c.name, c.proc.pid,
                            c.restarts)  # fmt: skip

    def _supervise_redis(self, now: float) -> None:
        r = self.redis
        if r is None or r.proc is None or r.proc.poll() is None:
            return
        ran = now - self._redis_started
        self._redis_delay = restart_delay(self._redis_delay, ran)
        log.warning(
            "redis-server %s after %.0f s; restarting it on port %d in %.1f s",
            describe_exit(r.proc.returncode),
            ran,
            r.port,
            self._redis_delay,
        )
        time.sleep(self._redis_delay)  # everything else waits on Redis anyway
        try:
            r.start()
        except (RuntimeError, TimeoutError) as e:
            log.error("redis-server did not come back: %s", e)
            return
        self._redis_started = time.monotonic()
        log.warning("redis-server restarted (pid %d)", r.proc.pid)

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
        self.children.clear()
        if self.redis:
            self.redis.stop()
            self.redis = None
        if self._auth_tmp is not None:
            self._auth_tmp.cleanup()
            self._auth_tmp = None
        if self._lock_file is not None:
            self._lock_file.close()
            self._lock_file = None


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
    """Keep the stack up until Ctrl-C or SIGTERM: a service that dies is restarted, not
    the stack stopped (one crashed service must not take a mission's map down)."""
    reported: set[int] = set()
    try:
        while not stop.wait(0.5):
            stack.supervise()
            for c in stack.children:
                if not c.supervised and c.proc.poll() is not None and c.proc.pid not in reported:
                    reported.add(c.proc.pid)
                    if c.proc.returncode != 0:
                        log.warning("%s %s", c.name, describe_exit(c.proc.returncode))
        return 0
    finally:
        stack.stop()


def _print_urls(stack: Stack) -> None:
    """Where to look: the viewer first, then the API, each service's metrics, and where
    Grafana and Prometheus are when the stack runs under docker compose."""
    from rich.console import Console
    from rich.table import Table

    s = stack.settings
    api = f"http://{s.api_host}:{s.api_port}"
    t = Table(title="HiveMap is up: where to look", title_justify="left", show_header=False,
              box=None, padding=(0, 2))  # fmt: skip
    t.add_column(style="bold")
    t.add_column()
    # The viewer URL carries the API token, as notebook servers print theirs.
    url = stack.viewer_url
    t.add_row("viewer", f"[link={url}]{url}[/link]  (live map, agents, merges and loops)")
    t.add_row(
        "api",
        f"{api}/docs  (REST: /agents, /maps; header Authorization: Bearer <token>), "
        f"WebSocket {api.replace('http', 'ws', 1)}/ws/viewer?token=<token>",
    )
    for spec in service_plan(s, stack.scale):
        if spec.name not in ("router", "redis", "api"):
            t.add_row(f"{spec.name} metrics", f"http://127.0.0.1:{spec.http_port}/metrics")
    t.add_row("api metrics", f"{api}/metrics")
    t.add_row(
        "grafana",
        "with `docker compose up`: http://localhost:3000 (dashboards "
        "HiveMap / team and HiveMap / server; Prometheus at http://localhost:9090)",
    )
    t.add_row("zenoh router", stack.zenoh_endpoint)
    t.add_row("redis", s.redis_url)
    # In a log (no terminal) lines stay whole instead of wrapping at 80 columns.
    console = Console(width=None if sys.stdout.isatty() else 200)
    console.print(t)
    console.print("Ctrl-C stops everything.")
    sys.stdout.flush()


def _start_or_explain(stack: Stack) -> bool:
    try:
        stack.start()
    except (PortInUse, DataDirBusy, ValueError) as e:
        stack.stop()
        print(f"hivemap: {e}", file=sys.stderr)
        return False
    except Exception:
        stack.stop()
        raise
    return True


def cmd_up(args: argparse.Namespace, settings: Settings) -> int:
    stop = _stop_on_signal()
    data_dir = None if args.ephemeral else str(Path(args.data_dir).resolve())
    try:
        scale = Scale(args.mappers, args.placerecs, args.optimizers)
    except ValueError as e:
        print(f"hivemap: {e}", file=sys.stderr)
        return 2
    agents = [a for a in (args.agents or "").split(",") if a]
    try:
        for a in agents:
            check_agent(a)
    except ValueError as e:
        print(f"hivemap: {e}", file=sys.stderr)
        return 2
    # Authentication on request (--agents, --auth) or once credentials exist in the data
    # directory; a router listening beyond loopback must have it.
    auth = (
        bool(agents)
        or args.auth
        or (data_dir is not None and (Path(data_dir) / "zenoh" / CREDENTIALS).exists())
    )
    if not auth and not _loopback_endpoint(args.listen):
        print("hivemap: refusing to listen beyond loopback without router authentication "
              "(anyone could publish as any agent): add --auth or --agents A,B,...",
              file=sys.stderr)  # fmt: skip
        return 2
    stack = Stack(settings, data_dir=data_dir, listen=args.listen, scale=scale,
                  auth_agents=agents if auth else None)  # fmt: skip
    if not _start_or_explain(stack):
        return 2
    _print_urls(stack)
    print(f"data         : {data_dir or 'none kept (--ephemeral)'}", flush=True)
    if stack.auth_dir is not None:
        print(f"zenoh auth   : {stack.auth_dir} (agents: `hivemap agent --credentials "
              f"{stack.auth_dir}/AGENT.json`)", flush=True)  # fmt: skip
    return _run_until_signal(stack, stop)


def cmd_demo(args: argparse.Namespace, settings: Settings) -> int:
    stop = _stop_on_signal()
    seqs = args.trajs.split(",")
    names = [f"agent{i + 1}" for i in range(len(seqs))]
    # Each simulated agent logs in to the router as itself, with its own rights.
    stack = Stack(settings, data_dir=args.data_dir, listen=args.listen, auth_agents=names)
    if not _start_or_explain(stack):
        return 2
    _print_urls(stack)
    for i, (agent, seq) in enumerate(zip(names, seqs, strict=True)):
        stack.add(
            f"sim-{agent}",
            ["sim-agent", "--id", agent, "--traj", seq, "--speed", str(args.speed),
             "--seed", str(i + 1)],
            env=stack.zenoh_identity(agent),
        )  # fmt: skip
        print(f"agent        : {agent} flying {seq} at {args.speed}x real time")
    sys.stdout.flush()
    return _run_until_signal(stack, stop)


def cmd_router(args: argparse.Namespace, settings: Settings) -> int:
    import zenoh

    from shared.settings import ZenohSettings
    from shared.transport import zenoh_config

    # config_file (HIVEMAP_ZENOH__CONFIG_FILE): TLS certificates for a tls/ listener.
    zs = ZenohSettings(mode="router", connect=[], listen=args.listen, auth_dir=args.auth or "",
                       config_file=settings.zenoh.config_file)  # fmt: skip
    if not args.auth and not all(_loopback_endpoint(e) for e in args.listen):
        print(
            "hivemap router: refusing to listen beyond loopback without --auth DIR "
            "(anyone could publish as any agent); see README, Security",
            file=sys.stderr,
        )
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with zenoh.open(zenoh_config(zs)):
        log.info("zenoh router listening on %s", ", ".join(args.listen))
        stop.wait()
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="start router, redis and every service on this machine")
    p.add_argument("--data-dir", default=DEFAULT_DATA_DIR,
                   help="maps and trajectories persist here (Redis append-only file); "
                   "the next `hivemap up` with the same directory serves them again "
                   f"(default ./{DEFAULT_DATA_DIR})")  # fmt: skip
    p.add_argument("--ephemeral", action="store_true", help="keep no data (overrides --data-dir)")
    p.add_argument("--agents", default=None, metavar="A,B,C",
                   help="turn on router authentication and make credentials for these "
                   "agents (DATA_DIR/zenoh/AGENT.json)")  # fmt: skip
    p.add_argument(
        "--auth",
        action="store_true",
        help="router authentication with the credentials already made",
    )
    p.add_argument("--mappers", type=int, default=1, help="mapper instances (default 1)")
    p.add_argument("--placerecs", type=int, default=1,
                   help="place-recognition instances sharing the work (default 1)")  # fmt: skip
    p.add_argument("--optimizers", type=int, default=1,
                   help="optimizer instances taking jobs from one queue (default 1)")  # fmt: skip
    _add_listen(p)
    p.set_defaults(func=cmd_up)

    p = sub.add_parser("demo", help="`up` plus simulated agents flying EuRoC MH trajectories")
    p.add_argument("--trajs", default="MH01,MH02,MH03")
    p.add_argument("--speed", type=float, default=1.0, help="real-time factor")
    p.add_argument("--data-dir", default=None)
    _add_listen(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("credentials", help="router credentials (user/password per agent)")
    csub = p.add_subparsers(dest="action", required=True)
    c = csub.add_parser("add", help="make credentials for agents (and the services)")
    c.add_argument("agents", nargs="*", help="agent ids")
    c.add_argument("--data-dir", default=DEFAULT_DATA_DIR)
    c.add_argument(
        "--zenohd",
        default=None,
        metavar="FILE",
        help="also write a zenohd config with these users and rules (compose)",
    )
    c.add_argument("--dictionary", default="/etc/hivemap/zenoh/credentials",
                   help="where that zenohd finds the credentials file")  # fmt: skip
    c.set_defaults(func=cmd_credentials)

    p = sub.add_parser("router", help="a Zenoh router in this Python process")
    p.add_argument("--listen", action="append", default=None, help="endpoint, repeatable")
    p.add_argument("--auth", default=None, metavar="DIR",
                   help="credentials directory (shared/zenoh_auth.py): users, passwords and "
                   "per-agent access rules")  # fmt: skip
    p.set_defaults(func=lambda a, s: cmd_router(_default_listen(a), s))


def cmd_credentials(args: argparse.Namespace, settings: Settings) -> int:
    from shared.zenoh_auth import check_agent, ensure_users, write_router_config

    auth_dir = Path(args.data_dir) / "zenoh"
    try:
        for a in args.agents:
            check_agent(a)
        ensure_users(auth_dir, args.agents)
    except ValueError as e:
        print(f"hivemap credentials: {e}", file=sys.stderr)
        return 2
    for a in args.agents:
        print(f"{a}: {auth_dir / (a + '.json')}  (hivemap agent --id {a} --credentials FILE)")
    if args.zenohd:
        path = write_router_config(auth_dir, args.zenohd, args.dictionary)
        print(f"zenohd config: {path} (reads the credentials at {args.dictionary})")
    print("a running router learns of new credentials when it restarts", file=sys.stderr)
    return 0


def _add_listen(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", default=DEFAULT_ROUTER,
                   help=f"the Zenoh router's endpoint (default {DEFAULT_ROUTER}, where "
                   "`hivemap agent` looks unless given --server)")  # fmt: skip


def _loopback_endpoint(endpoint: str) -> bool:
    import ipaddress

    host = endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")
    try:
        return host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _default_listen(args: argparse.Namespace) -> argparse.Namespace:
    if not args.listen:
        args.listen = [DEFAULT_ROUTER]
    return args
