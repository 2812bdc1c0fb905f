"""Who may say what on the Zenoh router: a user and password per agent and per service
(zenoh's ``transport/auth/usrpwd``) and access-control rules (zenoh's
``access_control``), kept in one directory (``DATA_DIR/zenoh`` under ``hivemap up``).

Why user/password and not mutual TLS: an agent's identity is then a line in a file
the launcher writes and ``hivemap credentials add`` extends, with nothing to sign or
renew on a drone; zenoh's ACL matches usernames directly. TLS still encrypts the link
where agents are not on the loopback (README, "Security"): the two combine.

The rules, default deny:

- agent X (user ``X``) may put only under ``hivemap/agent/X/up/**`` and subscribe only
  to ``hivemap/agent/X/down/**``; the router sends it nothing else.
- the services (users ``svc-mapper``, ``svc-placerec``, ``svc-optimizer``) may do
  anything under ``hivemap/**``: they are the server.
- ``sim-fleet``, the simulated fleet of ``hivemap demo`` and the load tests (many agents
  in one process, one session), has the rights of every agent, not a service's.

Zenoh reads the rules at start: a router learns of new credentials when it restarts.
"""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path

from pydantic import SecretStr

from shared import keys

SERVICES = ("svc-mapper", "svc-placerec", "svc-optimizer")
FLEET = "sim-fleet"
ROUTER_USER = "hivemap-router"
CREDENTIALS = "credentials"  # zenoh's dictionary file: one ``user:password`` a line

ALL_MESSAGES = [
    "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
]  # fmt: skip


def _write_private(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    tmp = path.with_suffix(path.suffix + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def read_credentials(auth_dir: str | Path) -> dict[str, str]:
    path = Path(auth_dir) / CREDENTIALS
    out: dict[str, str] = {}
    if path.exists():
        for ln in path.read_text().splitlines():
            user, sep, pw = ln.partition(":")
            if sep and user:
                out[user] = pw
    return out


def ensure_users(auth_dir: str | Path, users: list[str]) -> dict[str, str]:
    """Create a random password for each user that has none yet (the services, the
    fleet and the router always); returns every user's password."""
    creds = read_credentials(auth_dir)
    wanted = [ROUTER_USER, *SERVICES, FLEET, *users]
    for u in wanted:
        if u not in creds:
            if u not in (ROUTER_USER, *SERVICES, FLEET):
                check_agent(u)
            creds[u] = secrets.token_urlsafe(24)
    _write_private(Path(auth_dir) / CREDENTIALS, "".join(f"{u}:{p}\n" for u, p in creds.items()))
    for u, p in creds.items():
        _write_private(Path(auth_dir) / f"{u}.json", json.dumps({"user": u, "password": p}) + "\n")
    return creds


def with_credentials(settings, path: str | Path | None):
    """``settings`` with the Zenoh user and password of a credentials file
    (``DATA_DIR/zenoh/AGENT.json``, written by ``hivemap credentials add``)."""
    if not path:
        return settings
    try:
        doc = json.loads(Path(path).read_text())
        user, password = str(doc["user"]), str(doc["password"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a credentials file ({e})") from e
    zs = settings.zenoh.model_copy(update={"user": user, "password": SecretStr(password)})
    return settings.model_copy(update={"zenoh": zs})


def check_agent(agent: str) -> str:
    keys.check_id(agent, "agent")
    if agent in (ROUTER_USER, FLEET) or agent.startswith("svc-"):
        raise ValueError(f"agent {agent!r}: that name belongs to a service")
    return agent


def agents(creds: dict[str, str]) -> list[str]:
    return sorted(u for u in creds if u not in (ROUTER_USER, *SERVICES, FLEET))


def _agent_rules(rid: str, agent: str) -> list[dict]:
    up = f"{keys.ROOT}/agent/{agent}/up/**"
    down = f"{keys.ROOT}/agent/{agent}/down/**"
    return [
        # What it sends, and the services' subscriptions to it: the mapper subscribes to
        # every agent's uplink with one wildcard, and a client whose router never told
        # it of a matching subscriber stops sending after its first sample.
        {"id": f"{rid}-put", "permission": "allow", "flows": ["ingress"],
         "messages": ["put"], "key_exprs": [up]},
        {"id": f"{rid}-up-interest", "permission": "allow", "flows": ["egress"],
         "messages": ["declare_subscriber"], "key_exprs": [f"{keys.ROOT}/agent/*/up/**"]},
        # What it hears: its own downlink only.
        {"id": f"{rid}-sub", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_subscriber"], "key_exprs": [down]},
        {"id": f"{rid}-down", "permission": "allow", "flows": ["egress"],
         "messages": ["put"], "key_exprs": [down]},
    ]  # fmt: skip


def access_control(agent_ids: list[str]) -> dict:
    rules: list[dict] = [{"id": "services", "permission": "allow", "flows": ["ingress", "egress"],
                          "messages": ALL_MESSAGES, "key_exprs": [f"{keys.ROOT}/**"]}]  # fmt: skip
    subjects: list[dict] = [{"id": "services", "usernames": list(SERVICES)}]
    policies: list[dict] = [{"id": "services", "rules": ["services"], "subjects": ["services"]}]
    for i, (ident, key) in enumerate([(FLEET, "*")] + [(a, a) for a in agent_ids]):
        rid = f"agent{i}"
        r = _agent_rules(rid, key)
        rules += r
        subjects.append({"id": rid, "usernames": [ident]})
        policies.append({"id": rid, "rules": [x["id"] for x in r], "subjects": [rid]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}  # fmt: skip


def router_config(auth_dir: str | Path, dictionary_file: str | None = None) -> dict:
    """The router's auth and ACL sections (zenoh 1.x config keys). ``dictionary_file``:
    where the router finds the credentials file (another path inside a container)."""
    creds = read_credentials(auth_dir)
    if ROUTER_USER not in creds:
        raise FileNotFoundError(
            f"{Path(auth_dir) / CREDENTIALS}: no credentials; run "
            "`hivemap credentials add AGENT` or `hivemap up --agents ...`"
        )
    return {
        "transport": {"auth": {"usrpwd": {
            "user": ROUTER_USER, "password": creds[ROUTER_USER],
            "dictionary_file": dictionary_file or str(Path(auth_dir).resolve() / CREDENTIALS),
        }}},
        "access_control": access_control(agents(creds)),
    }  # fmt: skip


def write_router_config(auth_dir: str | Path, path: str | Path, dictionary_file: str) -> Path:
    """A zenohd config file (JSON is JSON5) with the listener settings compose uses."""
    conf = router_config(auth_dir, dictionary_file)
    conf.update({"mode": "router", "scouting": {"multicast": {"enabled": False}}})
    _write_private(Path(path), json.dumps(conf, indent=2) + "\n")
    return Path(path)
