"""`docker compose up`, for real: the compose deployment built and run on a private engine.

The test starts its own dockerd inside network and mount namespaces it creates
(`unshare --net --mount`): every bridge, veth and published port lives in that network
namespace, which has no route out, and every overlay mount dies with it. Registries are
unreachable, so it builds with deploy/compose.offline.yml from a Debian base image and a
wheelhouse that deploy/offline-base.sh makes once and keeps in a cache directory
(HIVEMAP_DOCKER_CACHE, default ~/.cache/hivemap-docker): only the first run fetches
Debian packages (debootstrap, from apt's mirror) and wheels (pip). The engine's data
root (its images and build cache) is kept there too, under a lock, so a later run
rebuilds only the layers whose inputs changed (deploy/Dockerfile installs the
dependencies in a layer before the sources); a run that finds it locked uses a
temporary one.

The deployment runs scaled, `--scale mapper=2 --scale placerec=2` (issue 20 item 6):
every healthcheck passes and both mappers say they live in Redis; two simulated agents
run inside the compose network and are assigned one to each mapper; GET /agents lists
both with moving poses and Prometheus has every replica's target up (through the
published ports 8000 and 9090, from inside the namespace); every server map is owned by
a lease of a live mapper, and both placerecs hold the keyframes (replicated database).
The agents fly the same place, so their maps merge across the two owners (one is handed
over through Redis). Then a `kill -9` of the main process of the merged map's owner:
the map is owned again (the other mapper takes it over, or the restarted one takes it
back with a new fencing token), the restart policy brings the container back, both
mappers are live again and the agents' keyframes keep being acked to the end; `down -v`
and the engine's shutdown leave nothing behind. One stack, scaled: a second one would
cost the suite another two minutes.
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CACHE = Path(os.environ.get("HIVEMAP_DOCKER_CACHE", Path.home() / ".cache/hivemap-docker"))
# What the image build needs of the project; tests, venvs and caches stay out.
COPY_IGNORE = shutil.ignore_patterns(
    ".git", ".venv", "__pycache__", ".pytest_cache", ".ruff_cache", "*.egg-info", "build",
    "results", "tests", "*.whl", "hivemap-data",
)  # fmt: skip
CLONE_NEWNET = 0x40000000
IMAGE_UID = 10001  # the user deploy/Dockerfile runs everything as
# Two agents flying MH01 from where the drone moves: 2000 frames at 20 Hz, 2x real time,
# 50 s, long enough for the mapper to be killed and come back while they fly (8 s here,
# more on a loaded machine).
AGENT_FRAMES = "900:2900"
AGENT_SPEED = "2"
MAPPERS, PLACERECS = 2, 2
LEASE_S = 3.0  # mapper.lease_s, the default compose runs with
# Run in the api container (its image has the project; HIVEMAP_REDIS_URL is set there):
# the live mappers, the agents' assignments and every live map's lease and fencing token.
OWNERSHIP_PY = """
import json, os, time
from shared.store import K_ASSIGN, K_MAPPERS, Store, connect, k_fence, k_lease
r = connect(os.environ["HIVEMAP_REDIS_URL"])
s = Store(r)
now = time.time() * 1000
out = {"mappers": {}, "assign": {}, "maps": {}}
for k, v in r.hgetall(K_MAPPERS).items():
    d = json.loads(v)
    d["age_ms"] = now - d.pop("t")
    out["mappers"][k.decode()] = d
out["assign"] = {k.decode(): v.decode() for k, v in r.hgetall(K_ASSIGN).items()}
for m in s.maps():
    info = s.map_info(m) or {}
    lease = r.get(k_lease(m))
    owner, _, token = lease.decode().rpartition(" ") if lease else (None, "", "0")
    out["maps"][m] = {"n_kf": info.get("n_kf"), "agents": info.get("agents"),
                      "owner": owner, "token": int(token), "fence": int(r.get(k_fence(m)) or 0)}
print(json.dumps(out))
"""


def _missing_tools() -> str | None:
    if os.geteuid() != 0:
        return "dockerd needs root here (no rootless engine is set up)"
    for tool, pkg in (("dockerd", "docker.io"), ("docker", "docker.io"),
                      ("docker-compose", "docker-compose"), ("unshare", "util-linux"),
                      ("ip", "iproute2")):  # fmt: skip
        if shutil.which(tool) is None:
            return f"no {tool} (Debian package {pkg}; `make system-tools` installs it as root)"
    return None


class Engine:
    """A dockerd of our own: its sockets, data and state under one temporary directory,
    its network namespace and mount namespace made for it."""

    def __init__(self, data_root: Path | None = None) -> None:
        # Short: containerd's socket path under exec-root must fit a sockaddr_un.
        self.dir = Path(tempfile.mkdtemp(prefix="hm-dockerd-"))
        self.data_root = data_root or self.dir / "data"
        self.sock = self.dir / "docker.sock"
        self.pidfile = self.dir / "dockerd.pid"
        self.log = self.dir / "dockerd.log"
        # The secrets docker-compose.yml refuses to start without (README, "Security").
        self.token = secrets.token_urlsafe(24)
        self.env = {**os.environ, "DOCKER_HOST": f"unix://{self.sock}",
                    "HIVEMAP_API_TOKEN": self.token,
                    "HIVEMAP_REDIS_PASSWORD": secrets.token_urlsafe(18)}  # fmt: skip
        self.proc: subprocess.Popen | None = None
        self.dockerd_pid: int | None = None
        self._http: ThreadPoolExecutor | None = None

    def start(self, timeout: float = 60.0) -> None:
        dockerd = [
            "dockerd", "--bridge=none", "--iptables=false", "--ip6tables=false",
            "--data-root", str(self.data_root), "--exec-root", str(self.dir / "exec"),
            "-H", f"unix://{self.sock}", "--pidfile", str(self.pidfile),
        ]  # fmt: skip
        # lo up, so the ports published in the namespace answer on its 127.0.0.1.
        script = 'ip link set lo up && exec "$@"'
        self.proc = subprocess.Popen(
            ["unshare", "--net", "--mount", "--propagation", "private", "--fork",
             "--kill-child", "sh", "-c", script, "sh", *dockerd],
            stdout=subprocess.DEVNULL, stderr=self.log.open("w"), start_new_session=True,
        )  # fmt: skip
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"dockerd exited: {self.log.read_text()[-1500:]}")
            if self.sock.exists() and self.pidfile.exists():
                r = self.docker("version", check=False)
                if r.returncode == 0:
                    self.dockerd_pid = int(self.pidfile.read_text())
                    return
            time.sleep(0.3)
        raise RuntimeError(f"dockerd did not answer in {timeout:.0f} s: "
                           f"{self.log.read_text()[-1500:]}")  # fmt: skip

    def docker(
        self, *args: str, check: bool = True, timeout: float = 120
    ) -> subprocess.CompletedProcess:
        r = subprocess.run(["docker", *args], env=self.env, capture_output=True, text=True,
                           timeout=timeout)  # fmt: skip
        if check and r.returncode != 0:
            raise AssertionError(f"docker {' '.join(args)}: {r.stdout}{r.stderr}")
        return r

    def _enter(self) -> None:
        # setns moves only the calling thread: this executor's one thread lives in the
        # engine's network namespace, the rest of pytest stays where it was.
        fd = os.open(f"/proc/{self.dockerd_pid}/ns/net", os.O_RDONLY)
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.setns(fd, CLONE_NEWNET) != 0:
                raise OSError(ctypes.get_errno(), "setns")
        finally:
            os.close(fd)

    def get_json(self, url: str, timeout: float = 5.0):
        """GET ``url`` from inside the engine's network namespace, where compose
        published its ports."""
        if self._http is None:
            self._http = ThreadPoolExecutor(1, initializer=self._enter)

        req = urllib.request.Request(url, headers={"Authorization": f"Bearer {self.token}"})

        def get():
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return json.loads(r.read())

        return self._http.submit(get).result()

    def processes(self) -> list[str]:
        """Processes that are this engine's: dockerd, its containerd, shims, proxies."""
        out = []
        for p in Path("/proc").iterdir():
            if not p.name.isdigit():
                continue
            with contextlib.suppress(OSError):
                cmd = (p / "cmdline").read_bytes().replace(b"\0", b" ").decode()
                if str(self.dir) in cmd:
                    out.append(f"{p.name}: {cmd[:160]}")
        return out

    def stop(self, timeout: float = 60.0) -> None:
        if self._http is not None:
            self._http.shutdown()
            self._http = None
        if self.proc is None:
            return
        if self.dockerd_pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.dockerd_pid, signal.SIGTERM)
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            # unshare --kill-child takes dockerd down with it
            self.proc.kill()
            self.proc.wait(10)

    def reset(self) -> None:
        """Nothing of an earlier run on a kept data root: one killed mid-test may have left
        containers (with restart policies), networks or volumes; images stay."""
        ids = self.docker("ps", "-aq").stdout.split()
        if ids:
            self.docker("rm", "-f", "-v", *ids, timeout=180)
        self.docker("network", "prune", "-f")
        # Debian's engine speaks API 1.41: no `volume prune --all`, so by name.
        vols = self.docker("volume", "ls", "-q").stdout.split()
        if vols:
            self.docker("volume", "rm", "-f", *vols)

    def remove(self) -> None:
        # The overlay mounts were in the engine's mount namespace, gone with it.
        shutil.rmtree(self.dir, ignore_errors=True)


def wait_for(pred, timeout: float, what: str, every: float = 1.0):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            v = pred()
            if v:
                return v
            last = v
        except (OSError, AssertionError, ValueError) as e:
            last = e
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what} (last: {last})")


class Compose:
    def __init__(self, engine: Engine, project_dir: Path, name: str) -> None:
        self.engine = engine
        self.dir = project_dir
        self.base = ["docker-compose", "-p", name, "-f", str(project_dir / "docker-compose.yml"),
                     "-f", str(project_dir / "deploy/compose.offline.yml")]  # fmt: skip

    def run(self, *args: str, timeout: float = 600, check: bool = True):
        r = subprocess.run([*self.base, *args], env=self.engine.env, cwd=self.dir,
                           capture_output=True, text=True, timeout=timeout)  # fmt: skip
        if check and r.returncode != 0:
            raise AssertionError(f"docker-compose {' '.join(args)} failed:\n"
                                 f"{r.stdout[-4000:]}\n{r.stderr[-4000:]}")  # fmt: skip
        return r

    def popen(self, *args: str, **kw) -> subprocess.Popen:
        return subprocess.Popen([*self.base, *args], env=self.engine.env, cwd=self.dir, **kw)

    def containers(self, service: str | None = None) -> list[str]:
        return self.run("ps", "-q", *([service] if service else [])).stdout.split()

    def inspect(self, cid: str) -> dict:
        return json.loads(self.engine.docker("inspect", cid).stdout)[0]

    def logs(self) -> str:
        return self.run("logs", "--no-color", "--tail", "30", check=False).stdout[-8000:]


def _unhealthy(compose: Compose) -> list[str]:
    """Containers not yet up, or not yet healthy where they have a healthcheck."""
    bad = []
    for cid in compose.containers():
        st = compose.inspect(cid)["State"]
        health = st.get("Health", {}).get("Status")
        if not st["Running"] or health not in (None, "healthy"):
            bad.append(f"{compose.inspect(cid)['Name']}:{health or st['Status']}")
    return bad


def _agents(engine: Engine) -> dict[str, dict]:
    return {a["agent"]: a for a in engine.get_json("http://127.0.0.1:8000/agents")}


def _prom(engine: Engine, query: str) -> dict[str, float]:
    """A Prometheus instant query: value per scraped instance (host:port)."""
    got = engine.get_json("http://127.0.0.1:9090/api/v1/query?query=" + query)
    return {r["metric"]["instance"]: float(r["value"][1]) for r in got["data"]["result"]}


def _ownership(compose: Compose) -> dict:
    """Who owns what, read from Redis inside the api container (OWNERSHIP_PY)."""
    (api,) = compose.containers("api")
    r = compose.engine.docker("exec", api, "python", "-c", OWNERSHIP_PY, timeout=60)
    return json.loads(r.stdout)


def _live(own: dict) -> set[str]:
    """Mappers that said they lived within a lease time (ownership.Ownership.live)."""
    return {m for m, d in own["mappers"].items() if d["age_ms"] <= 1000 * LEASE_S}


def _prepare(engine: Engine, tmp_path: Path) -> Path:
    """A copy of the project to build from, its deploy/wheelhouse filled from the cache
    and the base image imported (deploy/offline-base.sh, as a user would run it)."""
    ctx = tmp_path / "hivemap"
    shutil.copytree(ROOT, ctx, ignore=COPY_IGNORE)
    t0 = time.monotonic()
    r = subprocess.run(
        ["sh", str(ctx / "deploy/offline-base.sh"), "--cache", str(CACHE)],
        env={**engine.env, "PYTHON": sys.executable}, capture_output=True, text=True,
        timeout=900,
    )  # fmt: skip
    assert r.returncode == 0, f"offline-base.sh failed:\n{r.stdout}\n{r.stderr[-4000:]}"
    print(f"offline base and wheelhouse ready in {time.monotonic() - t0:.1f} s: {r.stdout}")
    # The router's logins, as README "Security" has a user make them for compose. They
    # are owner-only files: the image's user (uid 10001) must own them to read them.
    r = subprocess.run(
        [sys.executable, "-m", "services.cli", "credentials", "add", "--data-dir",
         str(ctx / "deploy"), "--zenohd", str(ctx / "deploy/zenoh/router.json5")],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    for p in [ctx / "deploy/zenoh", *(ctx / "deploy/zenoh").iterdir()]:
        os.chown(p, IMAGE_UID, -1)
    return ctx


def _run_deployment(engine: Engine, project: Path) -> None:
    compose = Compose(engine, project, "hivemaptest")
    timings: dict[str, float] = {}
    t = time.monotonic()
    try:
        compose.run("build")
        # Images an earlier build left untagged would pile up in the kept data root.
        engine.docker("image", "prune", "-f", timeout=300)
        timings["build"] = time.monotonic() - t
        t = time.monotonic()
        compose.run("up", "-d", "--no-build", "--scale", f"mapper={MAPPERS}",
                    "--scale", f"placerec={PLACERECS}")  # fmt: skip
        wait_for(lambda: not _unhealthy(compose), 180, "every container healthy")
        services = {compose.inspect(c)["Config"]["Labels"]["com.docker.compose.service"]
                    for c in compose.containers()}  # fmt: skip
        assert services == {"zenohd", "redis", "mapper", "placerec", "optimizer", "api",
                            "prometheus"}, services  # fmt: skip
        assert len(compose.containers("placerec")) == PLACERECS
        # A mapper's id in the leases is its host name: the container's, unique per replica.
        mapper_ids = {compose.inspect(c)["Config"]["Hostname"]: c
                      for c in compose.containers("mapper")}  # fmt: skip
        assert len(mapper_ids) == MAPPERS, mapper_ids
        wait_for(lambda: _live(_ownership(compose)) == mapper_ids.keys(), 60,
                 "both mappers live in Redis (hm:mappers)")  # fmt: skip
        timings["up_healthy"] = time.monotonic() - t
        t = time.monotonic()

        # Two agents in one container of the hivemap image on the compose network:
        # they reach the router and Redis by service name, as the services do.
        log = project / "agents.log"
        agents = compose.popen(
            "run", "--rm", "-T", "sim-agent", "sim-agent", "--id", "agent", "--count", "2",
            "--traj", "MH01", "--frames", AGENT_FRAMES, "--speed", AGENT_SPEED,
            "--flush-timeout", "60",
            stdout=subprocess.PIPE, stderr=log.open("w"), text=True,
        )  # fmt: skip
        try:
            first = wait_for(lambda: (a := _agents(engine)).keys() >= {"agent-0", "agent-1"}
                             and all(x["last_pose"] for x in a.values()) and a,
                             90, "both agents in GET /agents with a pose")  # fmt: skip

            def moved():
                now = _agents(engine)
                pos = {k: v["last_pose"]["position"] for k, v in now.items()}
                ok = all(pos[k] != first[k]["last_pose"]["position"]
                         and now[k]["n_kf"] > first[k]["n_kf"] for k in first)  # fmt: skip
                assert ok, {k: (first[k]["n_kf"], now[k]["n_kf"], pos[k]) for k in first}
                return ok

            # Generous: an overloaded mapper sheds live poses (never keyframes).
            wait_for(moved, 120, "both agents' poses moving and keyframes growing")

            def targets_up():
                got = engine.get_json("http://127.0.0.1:9090/api/v1/targets")
                # one target per replica (the scaled services are found by DNS)
                health = [(t["labels"]["job"], t["health"]) for t in got["data"]["activeTargets"]]
                assert {j for j, _ in health} == {"mapper", "placerec", "optimizer", "api"}, health
                assert sum(j == "mapper" for j, _ in health) == MAPPERS, health
                assert sum(j == "placerec" for j, _ in health) == PLACERECS, health
                return all(h == "up" for _, h in health)

            wait_for(targets_up, 60, "every Prometheus target up")

            # The agents went one to each mapper (hm:assign, least assigned first), and
            # every live map is owned by a lease of a live mapper (a map handed over for
            # a merge has none until the asker's next lease round: retried).
            def all_owned():
                got = _ownership(compose)
                assert got["maps"] and all(m["owner"] in _live(got) and m["token"] == m["fence"]
                                           for m in got["maps"].values()), got  # fmt: skip
                return got

            own = wait_for(all_owned, 15, "every map owned by a live mapper", every=0.5)
            print("ownership before the kill:", json.dumps(own))
            assert set(own["assign"].values()) == mapper_ids.keys(), own["assign"]

            # The placerec pool: every member holds every keyframe (its database is
            # replicated; the owner of a map alone queries it).
            def both_placerecs_hold_keyframes():
                db = _prom(engine, "hivemap_placerec_db_keyframes")
                assert len(db) == PLACERECS and all(v > 0 for v in db.values()), db
                return db

            wait_for(both_placerecs_hold_keyframes, 30, "keyframes in both placerecs")
            timings["agents_seen"] = time.monotonic() - t
            t = time.monotonic()

            # The two agents fly the same place from two mappers' maps: place recognition
            # matches them across owners, one map is handed over and they merge.
            def merged():
                got = _ownership(compose)
                return len(got["maps"]) == 1 and got

            own = wait_for(merged, 60, "the two maps merged across their owners")
            wait_for(lambda: sum(_prom(engine, "hivemap_mapper_handovers").values()) >= 1, 30,
                     "the hand-over counted")  # fmt: skip
            ((merged_map, info),) = own["maps"].items()
            assert sorted(info["agents"]) == ["agent-0", "agent-1"], own
            timings["merged"] = time.monotonic() - t

            # kill -9 of the main process (PID 1 of its container) of the mapper that owns
            # the merged map: the other takes it over, and the restart policy brings it back.
            victim_id = info["owner"]
            mapper = mapper_ids[victim_id]
            before = compose.inspect(mapper)
            os.kill(before["State"]["Pid"], signal.SIGKILL)
            t_kill = time.monotonic()
            kfs_at_kill = {k: v["n_kf"] for k, v in _agents(engine).items()}
            fence_at_kill = {m: v["fence"] for m, v in own["maps"].items()}

            def restarted():
                st = compose.inspect(mapper)
                return (st["RestartCount"] > before["RestartCount"]
                        and st["State"]["Pid"] != before["State"]["Pid"]
                        and st["State"].get("Health", {}).get("Status") == "healthy")  # fmt: skip

            def owned_again():
                # Taken over by the other mapper, or (if it came back first) taken back by
                # the restarted one -- its host name, so its id, is the same -- with a new
                # fencing token; or, once two leases went by, held by the restarted one at
                # all (it could only have asked before the old lease ran out, keeping the
                # token).
                got = _ownership(compose)
                late = time.monotonic() - t_kill > 2 * LEASE_S and restarted()
                ok = got["maps"] and all(
                    m["owner"] in mapper_ids
                    and (m["owner"] != victim_id or m["fence"] > fence_at_kill.get(k, 0) or late)
                    for k, m in got["maps"].items()
                )  # fmt: skip
                return ok and got

            got = wait_for(owned_again, 60, "every map owned again after the kill", every=0.5)
            timings["maps_owned_again"] = time.monotonic() - t_kill
            print(f"maps owned again {timings['maps_owned_again']:.1f} s after the kill of "
                  f"{victim_id} (lease {LEASE_S:.0f} s):", json.dumps(got["maps"]))  # fmt: skip
            assert merged_map in got["maps"], got
            wait_for(restarted, 90, "the restart policy bringing the mapper back, healthy")
            assert agents.poll() is None, "the agents landed before the mapper was back"
            timings["mapper_back"] = time.monotonic() - t_kill
            wait_for(lambda: _live(_ownership(compose)) == mapper_ids.keys(), 30,
                     "both mappers live again")  # fmt: skip
            wait_for(lambda: all(v["n_kf"] > kfs_at_kill[k] for k, v in _agents(engine).items()),
                     60, "keyframes accepted after the kill")  # fmt: skip

            # Every keyframe of both agents acked, those sent while it was down included.
            out, _ = agents.communicate(timeout=180)
        finally:
            if agents.poll() is None:
                agents.kill()
                agents.wait()
        stats = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
        assert agents.returncode == 0 and len(stats) == 2, (agents.returncode, out,
                                                            log.read_text()[-3000:])  # fmt: skip
        for st in stats:
            assert st["all_acked"], st
        timings["agents_done"] = time.monotonic() - t
        # Still one owner per live map, a live one, after the agents landed.
        own = _ownership(compose)
        print("ownership at the end:", json.dumps(own))
        print("per mapper instance:", {q: _prom(engine, q) for q in (
            "hivemap_mapper_maps_owned", "hivemap_mapper_takeovers", "hivemap_mapper_handovers",
            "hivemap_mapper_fenced_writes")})  # fmt: skip
        assert all(m["owner"] in _live(own) for m in own["maps"].values()), own
    except BaseException:
        print(compose.logs())
        raise
    finally:
        t = time.monotonic()
        compose.run("down", "-v", "--remove-orphans", timeout=180, check=False)
        timings["down"] = time.monotonic() - t
        print("timings (s):", {k: round(v, 1) for k, v in timings.items()})

    # Item 4: nothing of the deployment is left in the engine.
    assert engine.docker("ps", "-aq").stdout.split() == []
    nets = engine.docker("network", "ls", "--format", "{{.Name}}").stdout.split()
    assert set(nets) <= {"bridge", "host", "none"}, nets  # the engine's built-in ones
    assert engine.docker("volume", "ls", "-q").stdout.split() == []


@pytest.mark.timeout(1800)
def test_compose_up_offline(tmp_path):
    why = _missing_tools()
    if why:
        pytest.skip(why)
    # One engine at a time on the kept data root (two dockerds on one would corrupt it).
    CACHE.mkdir(parents=True, exist_ok=True)
    lock = (CACHE / "engine.lock").open("w")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        data_root: Path | None = CACHE / "engine"
    except BlockingIOError:
        data_root = None
    engine = Engine(data_root)
    try:
        try:
            engine.start()
        except RuntimeError as e:
            pytest.skip(f"dockerd cannot start here: {e}")
        engine.reset()
        _run_deployment(engine, _prepare(engine, tmp_path))
    finally:
        pid = engine.dockerd_pid
        engine.stop()
        left = engine.processes()
        mounted = [m for m in Path("/proc/self/mountinfo").read_text().splitlines()
                   if str(engine.dir) in m]  # fmt: skip
        engine.remove()
        lock.close()
    # Item 4, at the engine level: no dockerd, containerd, shim or proxy of ours runs,
    # its namespaces went with it (nothing of it is mounted here), its directory is gone.
    assert pid is None or not Path(f"/proc/{pid}").exists(), pid
    assert left == [], left
    assert mounted == [], mounted
    assert not engine.dir.exists()
