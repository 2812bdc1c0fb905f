"""`hivemap up --placerecs 2 --optimizers 2`: the pools run as separate processes of
one stack, share the work, and the team still ends in one optimized map."""

from __future__ import annotations

import urllib.request

from live_stack import get_json, live_stack, wait_for
from prometheus_client.parser import text_string_to_metric_families

from services.launcher import Scale, service_plan
from shared.jobs import JobQueue
from shared.settings import Settings
from shared.store import Store, connect


def _metrics(port: int) -> dict[tuple[str, tuple], float]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
        text = r.read().decode()
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def test_plan_names_and_ports_of_scaled_services():
    s = Settings()
    plan = {p.name: p for p in service_plan(s, Scale(placerecs=2, optimizers=3))}
    assert {"placerec-1", "placerec-2", "optimizer-1", "optimizer-2", "optimizer-3",
            "mapper"} <= set(plan)  # fmt: skip
    ports = [p.http_port for p in plan.values() if p.http_port is not None]
    assert len(ports) == len(set(ports))
    assert plan["optimizer-3"].http_port == s.optimizer_metrics_port + 20
    assert plan["placerec-2"].env["HIVEMAP_METRICS_PORT"] == str(s.placerec_metrics_port + 10)


def test_scaled_mappers_get_instance_names():
    plan = {p.name: p for p in service_plan(Settings(), Scale(mappers=3))}
    names = {plan[f"mapper-{i}"].env["HIVEMAP_MAPPER__INSTANCE"] for i in (1, 2, 3)}
    assert names == {"mapper-1", "mapper-2", "mapper-3"}


def test_two_placerecs_and_two_optimizers_share_a_team(tmp_path):
    with live_stack(n_agents=2, scale=Scale(placerecs=2, optimizers=2),
                    env={"HIVEMAP_OPTIMIZER__BA_TIME_BUDGET_S": "2"}) as stack:  # fmt: skip
        s = stack.settings
        plan = {p.name: p for p in service_plan(s, stack.scale)}
        api = f"http://{s.api_host}:{s.api_port}"
        r = connect(s.redis_url)
        wait_for(lambda: len(JobQueue(r).workers(within_s=30)) == 2, 60, "two optimizers")
        wait_for(
            lambda: len(get_json(f"{api}/agents", token=stack.api_token)) == 2, 90, "both agents"
        )
        wait_for(lambda: len(Store(r).maps()) == 1, 120, "the team's maps merged")

        def done() -> float:
            return sum(
                _metrics(plan[f"optimizer-{i}"].http_port).get(
                    ("hivemap_optimizer_jobs_total", (("outcome", "done"),)), 0
                )
                for i in (1, 2)
            )

        wait_for(lambda: done() >= 1, 120, "an optimization job done by the pool")
        pr = [_metrics(plan[f"placerec-{i}"].http_port) for i in (1, 2)]

        def kf(m, role):
            return m.get(("hivemap_placerec_keyframes_total", (("role", role),)), 0)

        seen = [kf(m, "stored") + kf(m, "queried") for m in pr]
        queried = [kf(m, "queried") for m in pr]
        print("placerec keyframes seen / queried per instance:", seen, queried,
              "optimizer jobs taken:", JobQueue(r).taken())  # fmt: skip
        assert min(seen) > 0
        # Each keyframe queried by one member (the count is read while keyframes still
        # arrive, so the two instances' totals may differ by a few).
        assert abs(sum(queried) - max(seen)) <= 5, (seen, queried)
        r.close()
