"""The Grafana dashboards, as code: ``hivemap dashboards`` writes deploy/grafana/dashboards/.

Built with Grafana's own foundation SDK (``grafana-foundation-sdk``, pinned to the
Grafana 11.2 branch the compose deployment runs), so every field has the type and name
Grafana's schema gives it. Two dashboards:

- **HiveMap / team**: what a mission operator watches. Team overview (agents, maps,
  merges, loops), keyframe latency p50/p95/p99 against the 200 ms bar, each agent's
  tracking and traffic (selectable with the ``agent`` variable).
- **HiveMap / server**: what whoever runs the server watches. Service health and
  restarts, overload and shedding, place recognition and optimization, traffic and
  the API.

Every expression reads only metrics that a process Prometheus scrapes exports
(mapper, placerec, optimizer, api, and Prometheus's own ``up``): agents are robots in
the field and are never scraped, so what they know reaches Prometheus through the
mapper. ``tests/test_prometheus.py`` evaluates every expression against a real
Prometheus scraping a running stack; ``tests/test_deploy.py`` fails when the checked-in
JSON differs from what this module builds (run ``hivemap dashboards`` after a change).

Dashboard variables are ``$agent`` (a regex of agent ids; "All" is ``.*``) and nothing
else, so a test can substitute them.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from services.mapper.agent_health import DISCONNECTED_AFTER_S

DATASOURCE_UID = "hivemap-prometheus"  # deploy/grafana/provisioning/datasources/prometheus.yml
# The scrape jobs of deploy/prometheus/prometheus.yml: one per hivemap service.
JOBS = 'job=~"mapper|placerec|optimizer|api"'
# The mapper's keyframe latency bar (issue 18: p95 <= 200 ms) and where it gets tight.
LATENCY_BAR_S = 0.2
LATENCY_WARN_S = 0.1
# What "All" selects in the $agent variable, and what tests substitute for it.
VARIABLES = {"agent": ".*"}
AGENTS = '{agent=~"$agent"}'  # the label selector of the agents the variable selects

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "deploy" / "grafana" / "dashboards"


@dataclass(frozen=True)
class Q:
    """One query of a panel: a PromQL expression and its legend."""

    expr: str
    legend: str = ""


def _sdk():
    """The SDK is a development dependency: the services never import it."""
    try:
        from grafana_foundation_sdk.builders import common as common_b
        from grafana_foundation_sdk.builders import dashboard as dash_b
        from grafana_foundation_sdk.builders import prometheus as prom_b
        from grafana_foundation_sdk.builders import stat as stat_b
        from grafana_foundation_sdk.builders import statetimeline as stl_b
        from grafana_foundation_sdk.builders import timeseries as ts_b
        from grafana_foundation_sdk.cog.encoder import JSONEncoder
        from grafana_foundation_sdk.models import common as common_m
        from grafana_foundation_sdk.models import dashboard as dash_m
    except ImportError as e:  # pragma: no cover - only without the dev extras
        raise SystemExit(
            "hivemap dashboards needs grafana-foundation-sdk: pip install -e '.[dev]'"
        ) from e
    return dash_b, ts_b, stat_b, stl_b, prom_b, common_b, common_m, dash_m, JSONEncoder


class _Builder:
    """Panels laid out in rows; ids are given in order so regeneration is stable."""

    def __init__(self, uid: str, title: str, description: str, tags: list[str]) -> None:
        (self.dash_b, self.ts_b, self.stat_b, self.stl_b, self.prom_b, self.common_b,
         self.common_m, self.dash_m, self.encoder) = _sdk()  # fmt: skip
        self.ds = self.dash_m.DataSourceRef(type_val="prometheus", uid=DATASOURCE_UID)
        self.next_id = 1
        self.d = (
            self.dash_b.Dashboard(title)
            .uid(uid)
            .description(description)
            .tags(tags)
            .editable()
            .refresh("10s")
            .time("now-30m", "now")
            .timezone("browser")
            .tooltip(self.dash_m.DashboardCursorSync.CROSSHAIR)
        )

    def _id(self) -> int:
        i = self.next_id
        self.next_id += 1
        return i

    def row(self, title: str) -> None:
        self.d = self.d.with_row(self.dash_b.Row(title).id(self._id()))

    def _targets(self, queries: list[Q], instant: bool = False) -> list:
        out = []
        for i, q in enumerate(queries):
            t = (
                self.prom_b.Dataquery()
                .expr(q.expr)
                .ref_id(chr(ord("A") + i))
                .datasource(self.ds)
                .legend_format(q.legend or "__auto")
            )
            t = t.instant() if instant else t.range()
            out.append(t)
        return out

    def _panel(self, kind, title: str, description: str, unit: str, w: int, h: int):
        """A panel of ``kind`` (an SDK panel builder module) with what every panel has."""
        return (
            kind.Panel()
            .id(self._id())
            .title(title)
            .description(description)
            .datasource(self.ds)
            .unit(unit)
            .height(h)
            .span(w)
        )

    def _add(self, panel, queries: list[Q]) -> None:
        for t in self._targets(queries):
            panel = panel.with_target(t)
        self.d = self.d.with_panel(panel)

    def _thresholds(self, steps: list[tuple[float | None, str]]):
        return (
            self.dash_b.ThresholdsConfig()
            .mode(self.dash_m.ThresholdsMode.ABSOLUTE)
            .steps([self.dash_m.Threshold(value=v, color=c) for v, c in steps])
        )

    def timeseries(
        self,
        title: str,
        description: str,
        queries: list[Q],
        unit: str,
        *,
        w: int = 12,
        h: int = 8,
        thresholds: list[tuple[float | None, str]] | None = None,
        min_val: float | None = 0,
    ) -> None:
        p = (
            self._panel(self.ts_b, title, description, unit, w, h)
            .line_width(1)
            .fill_opacity(10)
            .show_points(self.common_m.VisibilityMode.NEVER)
            .legend(
                self.common_b.VizLegendOptions()
                .display_mode(self.common_m.LegendDisplayMode.LIST)
                .placement(self.common_m.LegendPlacement.BOTTOM)
                .show_legend(True)
            )
        )
        if min_val is not None:
            p = p.min(min_val)
        if thresholds:
            p = p.thresholds(self._thresholds(thresholds)).thresholds_style(
                self.common_b.GraphThresholdsStyleConfig().mode(
                    self.common_m.GraphThresholdsStyleMode.DASHED
                )
            )
        self._add(p, queries)

    def stat(
        self,
        title: str,
        description: str,
        query: Q,
        unit: str = "none",
        *,
        w: int = 4,
        h: int = 4,
        thresholds: list[tuple[float | None, str]] | None = None,
    ) -> None:
        p = (
            self._panel(self.stat_b, title, description, unit, w, h)
            .graph_mode(self.common_m.BigValueGraphMode.AREA)
            .color_mode(self.common_m.BigValueColorMode.VALUE)
            .reduce_options(self.common_b.ReduceDataOptions().calcs(["lastNotNull"]))
            .thresholds(self._thresholds(thresholds or [(None, "blue")]))
        )
        self._add(p, [query])

    def state_timeline(
        self,
        title: str,
        description: str,
        query: Q,
        states: list[tuple[int, str, str]],
        *,
        w: int = 24,
        h: int = 8,
    ) -> None:
        """One row per series, coloured by ``states``: (value, text, colour)."""
        mapping = self.dash_m.ValueMap(
            options={
                str(v): self.dash_m.ValueMappingResult(text=t, color=c, index=i)
                for i, (v, t, c) in enumerate(states)
            }  # fmt: skip
        )
        p = (
            self._panel(self.stl_b, title, description, "none", w, h)
            .mappings([mapping])
            .show_value(self.common_m.VisibilityMode.NEVER)
            .merge_values(True)
            .fill_opacity(80)
            .line_width(0)
            .thresholds(self._thresholds([(None, "text")]))
            .color_scheme(self.dash_b.FieldColor().mode(self.dash_m.FieldColorModeId.THRESHOLDS))
        )
        self._add(p, [query])

    def agent_variable(self, metric: str) -> None:
        v = (
            self.dash_b.QueryVariable("agent")
            .label("agent")
            .description("Agents to show (regex of agent ids)")
            .datasource(self.ds)
            .query(f"label_values({metric}, agent)")
            .refresh(self.dash_m.VariableRefresh.ON_TIME_RANGE_CHANGED)
            .sort(self.dash_m.VariableSort.NATURAL_ASC)
            .multi(True)
            .include_all(True)
            .all_value(VARIABLES["agent"])
        )
        self.d = self.d.with_variable(v)

    def link(self, title: str, uid: str) -> None:
        self.d = self.d.link(
            self.dash_b.DashboardLink(title)
            .type(self.dash_m.DashboardLinkType.LINK)
            .url(f"/d/{uid}")
            .keep_time(True)
        )

    def json(self) -> dict:
        text = json.dumps(self.d.build(), cls=self.encoder, sort_keys=True)
        return json.loads(text)


def _quantiles(metric: str, by: str = "", window: str = "1m", sel: str = "") -> list[Q]:
    grp = f"le, {by}" if by else "le"
    suffix = f" {{{{{by}}}}}" if by else ""
    return [
        Q(f"histogram_quantile({q}, sum by ({grp}) (rate({metric}_bucket{sel}[{window}])))",
          f"p{int(q * 100)}{suffix}")
        for q in (0.5, 0.95, 0.99)
    ]  # fmt: skip


def _per_group(fn: str, metric: str, by: str, legend: str, window: str, sel: str) -> Q:
    inner = f"{fn}({metric}{sel}[{window}])"
    return Q(f"sum by ({by}) ({inner})" if by else f"sum({inner})", legend)


def _increase(metric: str, by: str, legend: str, window: str = "5m", sel: str = "") -> Q:
    """How much a counter grew over ``window``, summed per ``by`` labels (all if "")."""
    return _per_group("increase", metric, by, legend, window, sel)


def _rate(metric: str, by: str, legend: str, window: str = "1m", sel: str = "") -> Q:
    """A counter's rate per second over ``window``, summed per ``by`` labels (all if "")."""
    return _per_group("rate", metric, by, legend, window, sel)


def _agent_of_key(expr: str, direction: str) -> str:
    """Per-agent traffic from the mapper's per-key byte counters (``key`` is
    ``hivemap/agent/{agent}/{up|down}/...``): the agent id moved into an ``agent`` label."""
    return (
        f'sum by (agent) (label_replace({expr}, "agent", "$1", "key", '
        f'"hivemap/agent/([^/]+)/{direction}/.*"))'
    )


TEAM_UID = "hivemap-team"
SERVER_UID = "hivemap-server"


def team_dashboard() -> dict:
    b = _Builder(
        TEAM_UID, "HiveMap / team",
        "A mission as the server sees it: agents, maps, merges and loops, keyframe "
        "latency, and each agent's tracking and traffic.",
        ["hivemap", "slam"],
    )  # fmt: skip
    b.agent_variable("hivemap_keyframe_latency_seconds_count")
    b.link("Server", SERVER_UID)

    b.row("Team overview")
    b.stat("Agents", "Agents whose keyframes the mapper has registered since it started.",
           Q("count(count by (agent) (hivemap_keyframe_latency_seconds_count))"))  # fmt: skip
    b.stat("Maps", "Server maps holding keyframes now (a merged map is gone from the count).",
           Q("count(hivemap_map_keyframes)"))  # fmt: skip
    b.stat("Merges", "Maps fused into another since the mapper started (CCM-SLAM 4.8).",
           Q("sum(hivemap_map_merges_total)"))  # fmt: skip
    b.stat("Loops closed", "Verified intra-map place matches applied as loop edges.",
           Q('sum(hivemap_matches_applied_total{kind="loop"})'))  # fmt: skip
    b.stat("Keyframes", "Keyframes in all server maps (after redundant-keyframe culling).",
           Q("sum(hivemap_map_keyframes)"))  # fmt: skip
    b.stat("Map points", "Map points in all server maps.", Q("sum(hivemap_map_points)"))
    for code, what, desc, colour in (
        (0, "tracking", "Agents whose last report says they track.", "green"),
        (2, "lost", "Agents that report lost tracking (they still send).", "orange"),
        (3, "disconnected", f"Agents whose reports stopped for over "
         f"{DISCONNECTED_AFTER_S:g} s: out of radio range, or down.", "red"),
    ):  # fmt: skip
        steps = [(None, "green")] if code == 0 else [(None, "green"), (1, colour)]
        b.stat(f"Agents {what}", desc + " Reported in the agents' pose messages, exported "
               "by the mapper.", Q(f"sum(hivemap_agent_state == bool {code})"),
               w=8, h=4, thresholds=steps)  # fmt: skip
    b.timeseries(
        "Keyframes per map",
        "Each server map's size. When two maps merge, the smaller one's line ends and the "
        "larger one jumps.",
        [Q("hivemap_map_keyframes", "{{map}}")], "short",
    )  # fmt: skip
    b.timeseries(
        "Merges and loops (per 5 min)",
        "Place matches the mapper applied: `merge` fused two maps, `loop` closed a loop "
        "inside one, `loop_redundant` was a loop between keyframes already linked.",
        [_increase("hivemap_matches_applied_total", "kind", "{{kind}}")],
        "short",
    )  # fmt: skip

    b.row("Keyframe latency")
    b.timeseries(
        "Keyframe latency, all agents (received -> stored + acked)",
        "Time from the mapper receiving a keyframe batch to the keyframe being "
        "registered, written to Redis and acknowledged. The dashed line is the 200 ms "
        "bar for p95.",
        _quantiles("hivemap_keyframe_latency_seconds"), "s",
        thresholds=[(None, "green"), (LATENCY_WARN_S, "orange"), (LATENCY_BAR_S, "red")],
    )  # fmt: skip
    b.timeseries(
        "Keyframe latency p95 per agent",
        "The same latency, 95th percentile per agent over the last minute.",
        [Q("histogram_quantile(0.95, sum by (le, agent) "
           '(rate(hivemap_keyframe_latency_seconds_bucket{agent=~"$agent"}[1m])))',
           "{{agent}}")], "s",
        thresholds=[(None, "green"), (LATENCY_WARN_S, "orange"), (LATENCY_BAR_S, "red")],
    )  # fmt: skip

    b.row("Per agent: tracking and traffic")
    b.state_timeline(
        "Tracking state per agent",
        "What each agent reports in its pose messages (agents are not scraped: the "
        f"mapper exports their reports). Disconnected: no report for "
        f"{DISCONNECTED_AFTER_S:g} s.",
        Q('hivemap_agent_state{agent=~"$agent"}', "{{agent}}"),
        [(0, "tracking", "green"), (1, "initializing", "blue"), (2, "lost", "orange"),
         (3, "disconnected", "red")],
    )  # fmt: skip
    b.timeseries(
        "Frames per second per agent",
        "Camera frames each agent tracks per second, over its last 2 s.",
        [Q('hivemap_agent_fps{agent=~"$agent"}', "{{agent}}")], "short", w=8,
    )  # fmt: skip
    b.timeseries(
        "Frames dropped and keyframes lost (per minute)",
        "Frames an agent tracked more than a frame period late (a live camera would have "
        "dropped them), and keyframes it dropped unacknowledged because its buffer was "
        "full (the server never gets them).",
        [_increase("hivemap_agent_frames_dropped_total", "agent", "frames {{agent}}", "1m", AGENTS),
         _increase("hivemap_agent_keyframes_lost_total", "agent", "keyframes {{agent}}", "1m",
                   AGENTS)],
        "short", w=8, thresholds=[(None, "green"), (1, "orange")],
    )  # fmt: skip
    b.timeseries(
        "Resends per agent (per minute)",
        "Keyframes and map points each agent sent again (a gap in the acks, a server "
        "asking for a missing predecessor, or no ack in time).",
        [_increase("hivemap_agent_resends_total", "agent", "{{agent}}", "1m", AGENTS)], "short",
        w=8,
    )  # fmt: skip
    b.timeseries(
        "Keyframe ack latency as the agent sees it (publish -> ack)",
        "Median and 95th percentile over each agent's most recent 50 acknowledged "
        "keyframes: the mapper's latency plus the radio link both ways.",
        [Q('hivemap_agent_ack_latency_recent_seconds{quantile="0.95", agent=~"$agent"}',
           "p95 {{agent}}"),
         Q('hivemap_agent_ack_latency_recent_seconds{quantile="0.5", agent=~"$agent"}',
           "p50 {{agent}}")], "s",
        thresholds=[(None, "green"), (LATENCY_WARN_S, "orange"), (LATENCY_BAR_S, "red")],
    )  # fmt: skip
    b.timeseries(
        "Uplink sent by agents vs received by the mapper",
        "Bytes per second each agent says it sent, and what the mapper received from it: "
        "a gap is data lost on the way.",
        [_rate("hivemap_agent_sent_bytes_total", "agent", "sent {{agent}}", sel=AGENTS),
         Q(_agent_of_key('rate(hivemap_bytes_total{service="mapper", direction="in"}[1m])',
                         "up"), "received {{agent}}")], "Bps",
    )  # fmt: skip
    b.timeseries(
        "Keyframes stored per second",
        "Keyframes per second each agent got registered and stored.",
        [_rate("hivemap_keyframe_latency_seconds_count", "agent", "{{agent}}", sel=AGENTS)],
        "ops", w=8,
    )  # fmt: skip
    up = 'rate(hivemap_bytes_total{service="mapper", direction="in"}[1m])'
    down = 'rate(hivemap_bytes_total{service="mapper", direction="out"}[1m])'
    b.timeseries(
        "Uplink per agent (agent -> server)",
        "Bytes per second the mapper receives from each agent: keyframes, map points, "
        "updates and live poses. CCM-SLAM reports about 0.4 MB/s per agent.",
        [Q(_agent_of_key(up, "up"), "{{agent}}")],
        "Bps", w=8,
    )  # fmt: skip
    b.timeseries(
        "Downlink per agent (server -> agent)",
        "Bytes per second the mapper sends each agent: acks and map chunks (feedback).",
        [Q(_agent_of_key(down, "down"), "{{agent}}")], "Bps", w=8,
    )  # fmt: skip
    return b.json()


def server_dashboard() -> dict:
    b = _Builder(
        SERVER_UID, "HiveMap / server",
        "The services behind a mission: health and restarts, overload, place "
        "recognition and optimization, traffic and the API.",
        ["hivemap", "services"],
    )  # fmt: skip
    b.link("Team", TEAM_UID)

    b.row("Service health and restarts")
    b.timeseries(
        "Scrape targets up",
        "1 when Prometheus reached the service's /metrics on its last scrape; 0 when the "
        "process is down or too busy to answer.",
        [Q(f"up{{{JOBS}}}", "{{job}}")], "none", w=8,
        thresholds=[(None, "red"), (1, "green")],
    )  # fmt: skip
    b.timeseries(
        "Service loops running",
        "1 while a service's main loop runs (set by the service itself).",
        [Q("hivemap_service_up", "{{service}}")], "none", w=8,
    )  # fmt: skip
    b.timeseries(
        "Restarts (last hour)",
        "How often each service's process started anew within the last hour (its "
        "process_start_time_seconds changed): a supervisor or the container runtime "
        "restarted it.",
        [Q(f"changes(process_start_time_seconds{{{JOBS}}}[1h])", "{{job}}")], "short", w=8,
        thresholds=[(None, "green"), (1, "orange"), (3, "red")],
    )  # fmt: skip
    b.timeseries(
        "CPU per service",
        "CPU time each service process uses, in cores (1 = one core busy).",
        [Q(f"rate(process_cpu_seconds_total{{{JOBS}}}[1m])", "{{job}}")], "short", w=8,
    )  # fmt: skip
    b.timeseries(
        "Memory per service",
        "Resident memory of each service process.",
        [Q(f"process_resident_memory_bytes{{{JOBS}}}", "{{job}}")], "bytes", w=8,
    )  # fmt: skip
    b.timeseries(
        "Rejected messages and requests",
        "Samples that failed to decode or validate, per service and reason, and API "
        "requests refused (unknown ids, malformed parameters). Never fatal, always counted.",
        [_increase("hivemap_messages_rejected_total", "service, reason", "{{service}}: {{reason}}"),
         _increase("hivemap_api_rejected_total", "reason", "api: {{reason}}")],
        "short", w=8,
    )  # fmt: skip

    b.row("Overload and shedding")
    b.timeseries(
        "Batches waiting per map",
        "Keyframe batches queued for each map's actor. A queue that keeps growing means "
        "the map gets more than one mapper thread can register.",
        [Q("hivemap_map_queue_depth", "{{map}}")], "short", w=8,
        thresholds=[(None, "green"), (10, "orange"), (50, "red")],
    )  # fmt: skip
    b.timeseries(
        "Processing time p95 per message kind",
        "95th percentile of the time each service spends on one received message.",
        [Q("histogram_quantile(0.95, sum by (le, service, kind) "
           "(rate(hivemap_processing_seconds_bucket[5m])))", "{{service}} {{kind}}")],
        "s", w=8,
    )  # fmt: skip
    b.timeseries(
        "Map lock hold time",
        "How long a map's lock is held at a time (registration, fusion, matches, "
        "corrections): long holds delay every agent on that map.",
        _quantiles("hivemap_map_lock_hold_seconds", window="5m"), "s", w=8,
    )  # fmt: skip

    b.row("Place recognition and optimization")
    b.timeseries(
        "Place query time",
        "Bag-of-words conversion, inter- and intra-map queries and consistency check, "
        "per keyframe.",
        _quantiles("hivemap_placerec_query_seconds", window="5m"), "s", w=8,
    )  # fmt: skip
    b.timeseries(
        "Geometric verifications (per 5 min)",
        "Sim(3) RANSAC verifications of place candidates, accepted or rejected, and the "
        "keyframes in the place database.",
        [_increase("hivemap_placerec_verifications_total", "result", "{{result}}"),
         Q("hivemap_placerec_db_keyframes", "keyframes in database")],
        "short", w=8,
    )  # fmt: skip
    b.timeseries(
        "Matches published and applied (per 5 min)",
        "Verified matches placerec published, and those the mapper applied.",
        [_increase("hivemap_placerec_matches_total", "kind", "published {{kind}}"),
         _increase("hivemap_matches_applied_total", "kind", "applied {{kind}}")],
        "short", w=8,
    )  # fmt: skip
    b.timeseries(
        "Optimizations (per 5 min)",
        "Global optimizations (Sim(3) pose graph + BA) requested by the mapper, finished "
        "by the optimizer, superseded by a newer copy of the same map, and corrections "
        "the mapper applied.",
        [_increase("hivemap_optimize_requests_total", "reason", "requested: {{reason}}"),
         _increase("hivemap_optimizations_total", "reason", "finished: {{reason}}"),
         _increase("hivemap_optimizations_superseded_total", "", "superseded"),
         _increase("hivemap_corrections_applied_total", "", "corrections applied")],
        "short", w=8,
    )  # fmt: skip
    b.timeseries(
        "Optimization time",
        "Time for one global optimization of a map copy (pose graph, then time-bounded "
        "BA), median and slowest over 15 min.",
        [Q("histogram_quantile(0.5, sum by (le) (rate(hivemap_processing_seconds_bucket"
           '{service="optimizer", kind="optimize"}[15m])))', "p50"),
         Q("histogram_quantile(1, sum by (le) (rate(hivemap_processing_seconds_bucket"
           '{service="optimizer", kind="optimize"}[15m])))', "max")],
        "s", w=8,
    )  # fmt: skip
    b.timeseries(
        "Culled keyframes (per 5 min)",
        "Redundant keyframes removed from each map (CCM-SLAM 4.6).",
        [_increase("hivemap_keyframes_culled_total", "map", "{{map}}")],
        "short", w=8,
    )  # fmt: skip

    b.row("Traffic and API")
    b.timeseries(
        "Bytes per second by service and direction",
        "Zenoh payload bytes each service sends and receives.",
        [_rate("hivemap_bytes_total", "service, direction", "{{service}} {{direction}}")],
        "Bps", w=8,
    )  # fmt: skip
    b.timeseries(
        "Messages per second by service and direction",
        "Zenoh samples each service sends and receives.",
        [_rate("hivemap_messages_total", "service, direction", "{{service}} {{direction}}")],
        "ops", w=8,
    )  # fmt: skip
    b.timeseries(
        "API requests",
        "HTTP requests per second by route and status, WebSocket connections accepted "
        "per minute.",
        [_rate("hivemap_api_requests_total", "route, status", "{{route}} {{status}}"),
         _increase("hivemap_api_ws_connections_total", "", "websocket connections", window="1m")],
        "reqps", w=8,
    )  # fmt: skip
    b.timeseries(
        "API latency p95 per route",
        "95th percentile of HTTP request handling time.",
        [Q("histogram_quantile(0.95, sum by (le, route) "
           "(rate(hivemap_api_request_seconds_bucket[5m])))", "{{route}}")], "s", w=8,
    )  # fmt: skip
    return b.json()


DASHBOARDS = {"hivemap-team.json": team_dashboard, "hivemap-server.json": server_dashboard}


def render(dashboard: dict) -> str:
    """The checked-in form: sorted keys, two-space indent, a final newline."""
    return json.dumps(dashboard, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def build_all() -> dict[str, str]:
    return {name: render(fn()) for name, fn in DASHBOARDS.items()}


def panels(dashboard: dict) -> list[dict]:
    """Every panel, with those folded inside collapsed rows."""
    out = []
    for p in dashboard.get("panels", []):
        out.append(p)
        out.extend(panels(p))
    return out


def expressions(dashboard: dict) -> list[tuple[str, str]]:
    """(panel title, PromQL) of every query, with the dashboard variables substituted."""
    out = []
    for p in panels(dashboard):
        for t in p.get("targets", []):
            e = t["expr"]
            for name, value in VARIABLES.items():
                e = e.replace(f"${name}", value)
            out.append((p["title"], e))
    return out


def cmd_dashboards(args: argparse.Namespace, settings) -> int:  # noqa: ARG001
    out = Path(args.out)
    built = build_all()
    stale = [n for n, text in built.items()
             if not (out / n).exists() or (out / n).read_text() != text]  # fmt: skip
    extra = sorted(p.name for p in out.glob("*.json") if p.name not in built)
    if args.check:
        for n in stale:
            print(f"{out / n}: differs from what services/dashboards.py builds", file=sys.stderr)
        for n in extra:
            print(f"{out / n}: no dashboard of services/dashboards.py", file=sys.stderr)
        return 1 if stale or extra else 0
    out.mkdir(parents=True, exist_ok=True)
    for n in extra:
        (out / n).unlink()
        print(f"removed {out / n}")
    for n, text in built.items():
        (out / n).write_text(text)
        print(f"{'wrote' if n in stale else 'unchanged'} {out / n}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dashboards", help="regenerate the Grafana dashboards (deploy/grafana)")
    p.add_argument("--out", default=str(DEFAULT_OUT), help="dashboards directory")
    p.add_argument("--check", action="store_true",
                   help="exit 1 when the files differ from what the code builds")  # fmt: skip
    p.set_defaults(func=cmd_dashboards)
