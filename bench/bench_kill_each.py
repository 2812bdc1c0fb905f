"""``kill -9`` of every service under ``hivemap up``, one after another, during one flight
(issue 18 item 4). The test suite kills the mapper and the API
(tests/test_supervised_up.py); this does the same to each of router, redis, placerec,
optimizer, mapper and API in turn, while a simulated agent keeps flying, and says per
service: how long until the supervisor had it running again, whether every other
service stayed up, how long until the agent's keyframes were acked again, and whether
any keyframe acked before the kill was missing from Redis afterwards. At the end: every
keyframe the agent made acked and stored, and the agent listed by the API.

    .venv/bin/python bench/bench_kill_each.py [--name kill_each]

Writes bench/results/NAME.json.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "tests"))  # the supervised-stack helpers of the tests

from common import table, write_report  # noqa: E402
from test_supervised_up import Up, _acked, _acks_resumed, _alive, _fly, _restarted  # noqa: E402

from shared.store import Store, connect  # noqa: E402

SERVICES = ("router", "redis", "placerec", "optimizer", "mapper", "api")


def kill_one(up: Up, runner, name: str, agent: str) -> dict:
    before = up.children()
    acked0 = _acked(runner)
    pid = before[name]
    os.kill(pid, signal.SIGKILL)
    t = time.monotonic()
    back = _restarted(up, name, pid, t)
    others = all(_alive(p) for n, p in before.items() if n != name)
    # None when no ack came within the wait (it read as the wait's length before).
    resumed = _acks_resumed(runner, t)
    stored = set(Store(connect(up.redis_url)).keyframe_ids(agent))
    return {"service": name, "back_s": back, "others_alive": others,
            "acks_resumed_s": resumed, "acked_before_missing": len(acked0 - stored)}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--name", default="kill_each")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="hivemap-kill-"))
    up = Up(tmp, tmp / "data")
    agent = "k9"
    try:
        runner, thread, res, stop = _fly(up.endpoint, agent, "0:3000", speed=1.0)
        while len(_acked(runner)) < 10:
            time.sleep(0.2)
        rows = []
        for name in SERVICES:
            rows.append(kill_one(up, runner, name, agent))
            print(rows[-1], flush=True)
            time.sleep(4)
        stop.set()
        thread.join(120)
        st = res["stats"]
        acked = _acked(runner)
        stored = set(Store(connect(up.redis_url)).keyframe_ids(agent))
        end = {"all_acked": st.all_acked, "acked": len(acked), "stored": len(stored),
               "acked_not_stored": len(acked - stored),
               "api_agents": [a["agent"] for a in up.get("/agents")]}  # fmt: skip
    finally:
        up.stop()
    ok = (all(r["back_s"] is not None and r["back_s"] <= 10 and r["others_alive"]
              and r["acks_resumed_s"] is not None and r["acked_before_missing"] == 0
              for r in rows)
          and end["all_acked"] and end["acked_not_stored"] == 0)  # fmt: skip
    path = write_report(args.name, {"rows": rows, "end": end, "pass": ok})
    print(table(rows, ["service", "back_s", "others_alive", "acks_resumed_s",
                       "acked_before_missing"]))  # fmt: skip
    print(end, "pass" if ok else "FAIL")
    print(f"written {path}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
