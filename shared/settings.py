"""Typed settings read from the environment (prefix ``HIVEMAP_``) with fail-fast validation.

Nested groups use ``__``: ``HIVEMAP_ZENOH__CONNECT='["tcp/127.0.0.1:7447"]'``,
``HIVEMAP_INJECT__DROP=0.2``. Build one instance in ``main`` and pass it down;
no module holds a global instance.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

# Where `hivemap up` runs its router and where an agent looks for one unless told:
# the two must agree, or an agent flies a whole mission beside a server that never
# sees it.
DEFAULT_ROUTER = "tcp/127.0.0.1:7447"


def default_of(group: type[BaseModel], name: str) -> Any:
    """The default of a settings field. The services' ``*Params`` dataclasses take the
    defaults of their settings-backed fields from here, and their ``from_settings``
    builds them from a loaded group, so each default is written once, in this module."""
    return group.model_fields[name].get_default(call_default_factory=True)


class ZenohSettings(BaseModel):
    mode: str = "client"
    connect: list[str] = Field(default_factory=lambda: [DEFAULT_ROUTER])
    listen: list[str] = Field(default_factory=list)
    scouting: bool = False
    # -1: keep retrying to reach the router instead of failing at open().
    connect_timeout_ms: int = -1
    # This session's identity on a router with authentication (shared/zenoh_auth.py):
    # user and password, or a credentials file holding both (DATA_DIR/zenoh/USER.json).
    user: str = ""
    password: SecretStr = SecretStr("")
    credentials: str = ""
    # Router mode: the directory of credentials whose users and rules it enforces.
    auth_dir: str = ""
    # A zenoh JSON5 config file read first (TLS listeners and certificates, README).
    config_file: str = ""

    @field_validator("mode")
    @classmethod
    def _mode(cls, v: str) -> str:
        if v not in ("client", "peer", "router"):
            raise ValueError("zenoh mode must be client, peer or router")
        return v


class InjectSettings(BaseModel):
    """Communication controller (CCM-SLAM §5.3): loss and delay on outgoing samples."""

    drop: float = Field(0.0, ge=0.0, le=1.0)
    delay_s: float = Field(0.0, ge=0.0)
    jitter_s: float = Field(0.0, ge=0.0)
    seed: int = 0
    # Only key expressions under this prefix are disturbed ("" = all).
    key_prefix: str = "hivemap/agent/"
    # Only the sending side named here injects (agent, mapper, ...; "" = every service).
    service: str = "agent"


class CommSettings(BaseModel):
    """Agent communication module (CCM-SLAM §4.5)."""

    rate_hz: float = Field(5.0, gt=0)
    max_msg_bytes: int = Field(400_000, gt=1000)
    # The first resend timeout's floor; it follows the measured ack latency above it and
    # doubles per resend of the same item up to backoff_max_s, +-jitter (comm.py).
    resend_timeout_s: float = Field(2.0, gt=0)
    backoff_max_s: float = Field(30.0, gt=0)
    jitter: float = Field(0.2, ge=0, lt=1)
    # Keyframes in flight unacknowledged: starts at window, +1 per ack whose batch the
    # server held (Ack.held_s) within ack_target_s, halved on a later one down to
    # window_min (the agent's share of a loaded server; the target is the bound on the
    # latency of what it accepts; the link's delay is not the server's).
    window: int = Field(8, ge=1)
    window_min: int = Field(2, ge=1)
    window_max: int = Field(32, ge=1)
    ack_target_s: float = Field(0.5, gt=0)
    pose_rate_hz: float = Field(10.0, gt=0)
    # Unacknowledged keyframes the communication module keeps (and resends with backoff
    # until acked), by their estimated wire size, oldest dropped past it. Apart from the
    # VO's local map (CCM-SLAM §4.2 trims that to N + B for its compute): a keyframe is
    # 10-60 kB, so this holds a whole flight's (~5000) while the server is away or shedding.
    buffer_bytes: int = Field(256_000_000, gt=0)
    # A map point moved by local BA is sent again when it moved by more than this share
    # of its distance from its reference keyframe.
    mp_update_rel: float = Field(0.01, ge=0)


class VOSettings(BaseModel):
    """The agent's monocular VO (``services/agent/vo/odometry.py``, which takes this as
    its ``VOParams``): every threshold it uses, by name."""

    n_features: int = Field(1000, gt=0)
    window: int = Field(7, ge=2)  # keyframes in local BA
    local_kfs: int = Field(10, ge=1)  # keyframes whose points are searched while tracking
    foreign_gate_px: float = Field(1.5, gt=0)  # server points must reproject this well
    foreign_max_points: int = Field(1500, ge=0)  # server points kept, oldest forgotten
    search_radius: float = Field(12.0, gt=0)  # px at the nominal frame interval
    search_widen: float = Field(3.0, ge=1)  # the wide search: this times the first
    refine_radius: float = Field(4.0, gt=0)  # px, second search around the refined pose
    refine_keep_ratio: float = Field(0.8, gt=0)  # a re-solve must keep this share of inliers
    min_depth: float = Field(0.05, gt=0)  # points nearer the camera are not searched
    min_inliers: int = Field(40, ge=6)
    # Fewer own inliers than this times min_inliers: the map is thin here, so the
    # server's points join the search and the gate of foreign points stands aside.
    strong_factor: float = Field(2.0, ge=1)
    # Fewer tracked points than this times min_inliers: a keyframe now (leaving the map).
    kf_thin_factor: float = Field(3.0, ge=1)
    kf_min_frames: int = Field(4, ge=0)  # at the nominal frame interval (0.2 s at 20 Hz)
    kf_max_frames: int = Field(12, ge=1)
    kf_inlier_ratio: float = Field(0.7, gt=0, le=1)
    ba: bool = True
    ba_min_points: int = Field(20, ge=0)
    ba_max_iters: int = Field(5, ge=1)
    nominal_dt_s: float = Field(0.05, gt=0)  # the frame interval the frame counts are for
    dt_ratio_min: float = Field(0.5, gt=0)  # frame interval / nominal, clipped to this range
    dt_ratio_max: float = Field(6.0, gt=0)
    # Frame intervals within this factor of each other count as the same rate (jitter);
    # beyond it (a dropped frame: 2x) the motion model scales its step to the interval.
    dt_jitter_max_ratio: float = Field(1.4, gt=1)
    # A pose the motion model cannot explain is not taken from a weakly supported PnP:
    # how far from the prediction it may be (share of the scene depth, plus this many
    # times the frame's own predicted motion), growing with every frame lost.
    jump_depth_share: float = Field(0.15, gt=0)
    jump_motion_factor: float = Field(1.5, ge=0)
    jump_rot_deg: float = Field(12.0, gt=0)
    strong_inliers: int = Field(150, ge=6)  # a PnP this well supported is taken anywhere
    coast_s: float = Field(0.5, ge=0)  # lost: how long the motion model keeps the velocity
    coast_damping: float = Field(0.7, ge=0, le=1)  # ... then it shrinks by this per frame
    # Two-view initialization (ORB-SLAM): reference frame, matching, geometry.
    init_min_features: int = Field(300, ge=8)
    init_max_age_frames: int = Field(40, ge=1)  # then a new reference frame
    init_match_ratio: float = Field(0.8, gt=0, le=1)
    init_match_max_dist: int = Field(60, ge=0, le=256)
    init_min_matches: int = Field(150, ge=8)
    init_min_inliers: int = Field(120, ge=8)
    init_min_parallax_deg: float = Field(1.5, gt=0)
    # Relocalization against the local map's keyframes.
    reloc_kfs: int = Field(6, ge=1)  # keyframes tried per lost frame, nearest first
    reloc_min_matches: int = Field(30, ge=6)
    reloc_match_ratio: float = Field(0.8, gt=0, le=1)
    # Triangulation of a new keyframe against the ones before it.
    tri_kfs: int = Field(2, ge=1)
    tri_min_free: int = Field(10, ge=1)  # unmatched keypoints needed on both sides
    tri_match_ratio: float = Field(0.75, gt=0, le=1)
    tri_match_max_dist: int = Field(50, ge=0, le=256)
    tri_min_matches: int = Field(5, ge=1)
    tri_max_err_px: float = Field(2.0, gt=0)
    tri_min_parallax_deg: float = Field(1.0, gt=0)
    # Point culling (ORB-SLAM): this many keyframes after its creation a point must
    # have been found in this share of the frames that should have seen it.
    cull_min_age_kfs: int = Field(2, ge=0)
    cull_min_found_ratio: float = Field(0.25, ge=0, le=1)


class MapperSettings(BaseModel):
    feedback_rate_hz: float = Field(2.0, gt=0)
    feedback_k: int = Field(5, ge=0)
    # Chunks carry the correction of the agent's VO frame by the map (frame_correction),
    # fitted on this many of its newest keyframes a global optimization settled; 0 sends
    # none. Fewer follow a fast-drifting VO closer, more average the settled frontier's
    # own errors out (a replayed team5 run: 10 -> -25 % reported ATE against the VO, 60
    # -> -10 %). 20 since 2026-11-27 (was 10): replayed on the same recorded map states
    # (bench/replay_feedback.py) of eight runs (seed-1 pair x4, team3, team5, team5 with
    # 1 s delay, team3 with 50 % loss), the sum over their 24 agents was the same (330.1
    # vs 331.0 mm; team5 +1.3 % and +4.3 % with delay, the others lower) and one agent
    # was above its VO instead of three (the seed-1 agent1: 1 of 4 runs instead of 3).
    feedback_correction_kfs: int = Field(20, ge=0)
    refine_poses: bool = True
    # ... against points of settled or other agents' keyframes only: the agent's own
    # unsettled points came from its VO frontier and pull a keyframe wherever that went
    # wrong (services/mapper/registration.py).
    refine_settled_only: bool = True
    scale_correction: bool = True
    kappa: float = Field(0.05, gt=0, le=1)
    fuse: bool = True
    redundancy: bool = True
    redundancy_ratio: float = Field(0.98, gt=0, le=1)
    # At most one map copy to the optimizer per map this often (a burst of matches
    # right after two maps meet becomes one request).
    optimize_min_interval_s: float = Field(3.0, ge=0)
    # With settle_window_kfs 0: an agent this many keyframes past its newest one a global
    # optimization settled gets its map optimized again, spaced as above
    # (services/mapper/collab.py: its frame correction is fitted on settled keyframes
    # only); 0 = only loops and merges.
    settle_after_kfs: int = Field(20, ge=0)
    # Settling without a global optimization: an agent this many keyframes past its newest
    # settled one gets a windowed BA instead ("local": the map's newest unsettled keyframes
    # free, the keyframes sharing most of their points fixed; services/mapper/capture.py
    # capture_window), spaced by its own run time, not the global BA's; 0 = settle through
    # global optimizations (settle_after_kfs). At 457dcb8 (bench/results/*_fb3_457dcb8*):
    # reported-pose ATE summed over the team -24.1 / -11.2 % (seed-1 pair, two runs),
    # -33.5 % (team3), -23.6 % (team5) against the raw VO, every agent at or below its VO.
    settle_window_kfs: int = Field(8, ge=0)
    # A windowed BA holds the window's keyframes to their agents' VO relative motion
    # (services/mapper/capture.py window_odometry): the rotation to 0.3 degrees per
    # keyframe step, the translation to this share of the step. At 0.05 the dark stretch
    # of MH04 took its VO's bad scale (team5 agent4 100 mm against its VO's 44); at 1.0
    # (a weak translation prior) every agent of the seed-1 pair, team3 and team5 came out
    # below its VO (-21.5 / -40.5 / -31.8 %; without the edges -2.3 / -33.5 / -38.0 %).
    window_odometry: bool = True
    window_odometry_trans_share: float = Field(1.0, gt=0)
    # Several mappers (services/mapper/ownership.py): this one's id in map leases ("" =
    # the host name, unique per container; `hivemap up --mappers N` names them), and
    # the lease time: a dead mapper's maps are taken over within about twice it.
    instance: str = ""
    lease_s: float = Field(3.0, gt=0.1)
    # Overload (services/mapper/overload.py): a keyframe batch that waited longer than
    # this in the queue is shed (NACKed: the agent resends it after the retry-after);
    # poses, feedback and background work are shed before, at 15, 40 and 70 % of it.
    # What the mapper accepts is acked within about this plus a group's registration and
    # store (0.1-0.3 s at 48 agents): 0.5 keeps that under the 1 s bar (issue 18).
    shed_after_s: float = Field(0.5, gt=0)
    # Real-time scheduling (SCHED_RR at this priority, 1-99; 0 = normal scheduling) for
    # the mapper, where the process may (root, CAP_SYS_NICE, or an RLIMIT_RTPRIO at
    # least this high): registration is the latency path of every keyframe, and on a
    # saturated host it waited for a core more than it ran. At 24 simulated agents on
    # 2 cores (bench_ramp, fe86aaa) the mapper sat 0.57 s per second in the run queue,
    # niced peers or not, and its p95 was 498 ms; the same step with it at SCHED_RR 10:
    # 0.04 s/s, p95 183 ms. The mapper is one GIL, so it takes at most about one core
    # and the kernel's real-time throttling bounds it beyond that; placerec and the
    # optimizer (background) keep normal scheduling.
    rt_priority: int = Field(10, ge=0, le=99)


class PlacerecSettings(BaseModel):
    """Place recognition (CCM-SLAM §4.7)."""

    vocabulary: str = ""  # "" = the vocabulary shipped with the package
    consistency: int = Field(3, ge=1)  # consecutive consistent keyframes before verifying
    min_inliers: int = Field(20, ge=6)
    min_matches: int = Field(40, ge=6)
    # Same-agent keyframes this close in id are neighbours, not loop candidates.
    loop_min_id_gap: int = Field(30, ge=0)
    # Niceness the process takes on start: recognition is background work, and on a
    # shared host keyframe ingestion (the mapper, real time) must get the CPU first.
    nice: int = Field(5, ge=0, le=19)


class OptimizerSettings(BaseModel):
    ba: bool = True
    ba_max_iterations: int = Field(10, ge=0)
    ba_time_budget_s: float = Field(8.0, gt=0)
    # The same for a windowed BA (reason "local": up to 60 free and 60 fixed keyframes).
    # 2 s was too short on a five-agent map on two busy cores: team5 at 386817f stopped
    # most windows on it, and two in a row left agent3's newest settled keyframes 57 and
    # 113 mm off (its reported ATE 28.5 vs VO 17.3 mm); with 4 s, 14 of 18 converged and
    # every agent's reported pose came out below its VO (bench/results/team5_386817f*).
    local_ba_time_budget_s: float = Field(4.0, gt=0)
    # A newer copy of a map restarts its optimization at most this many times in a
    # row; then the run finishes (and the newest copy runs next), so a stream of loops
    # can't starve the map of corrections.
    max_restarts: int = Field(2, ge=0)
    # The pool (shared/jobs.py): a job its worker has not renewed for this long (the
    # worker renews every quarter of it while alive) is taken over by another worker,
    # at most max_deliveries times in all.
    claim_idle_s: float = Field(20.0, gt=0)
    max_deliveries: int = Field(3, ge=1)
    # As for place recognition: a global BA may take seconds of CPU, ingestion can't.
    nice: int = Field(10, ge=0, le=19)


class Settings(BaseSettings):
    model_config = SettingsConfigDict(
        env_prefix="HIVEMAP_", env_nested_delimiter="__", extra="ignore"
    )

    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    redis_url: str = "redis://127.0.0.1:6379/0"
    inject: InjectSettings = Field(default_factory=InjectSettings)
    comm: CommSettings = Field(default_factory=CommSettings)
    vo: VOSettings = Field(default_factory=VOSettings)
    mapper: MapperSettings = Field(default_factory=MapperSettings)
    placerec: PlacerecSettings = Field(default_factory=PlacerecSettings)
    optimizer: OptimizerSettings = Field(default_factory=OptimizerSettings)
    api_host: str = "127.0.0.1"
    api_port: int = Field(8000, ge=0, le=65535)
    # Bearer token every API endpoint but /health, /ready and /metrics requires ("" = none,
    # allowed only while the API listens on loopback). SecretStr keeps it out of reprs/logs.
    api_token: SecretStr = SecretStr("")
    # Origins a browser may call the API from; empty = no CORS headers at all.
    api_cors_origins: list[str] = Field(default_factory=list)
    # Largest request body (the API only serves GETs) and WebSocket frame it accepts.
    api_max_body_bytes: int = Field(16_384, ge=0)
    metrics_host: str = "127.0.0.1"
    # 0 = no HTTP metrics endpoint (tests read the registry directly).
    metrics_port: int = Field(0, ge=0, le=65535)
    # Ports `hivemap up` gives the services that have no HTTP app of their own.
    mapper_metrics_port: int = Field(9101, ge=1, le=65535)
    placerec_metrics_port: int = Field(9102, ge=1, le=65535)
    optimizer_metrics_port: int = Field(9103, ge=1, le=65535)
    log_level: str = "INFO"
    log_json: bool = True
