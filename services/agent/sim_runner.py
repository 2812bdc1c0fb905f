"""The simulated agent (:class:`SimAgent`) as a producer of the agent loop: the
load-test agent, against a real server over Zenoh.

Frames are paced by the trajectory's timestamps divided by ``speed`` (0 = as fast as
possible); between frames the loop waits for acks instead of sleeping. At the end it
keeps resending until everything is acknowledged or ``flush_timeout_s`` passes.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator

from shared.messages import MapChunk
from shared.settings import Settings

from .comm import CommModule
from .loop import AgentLoop, AgentStats, Frame, Step
from .sim_agent import SimAgent


class SimProducer:
    """Keyframes and map points straight from the simulation (no images)."""

    uses_map = False  # it takes nothing from the server's map

    def __init__(self, sim: SimAgent) -> None:
        self.sim = sim

    def bind(self, comm: CommModule, stats: AgentStats) -> None:
        self.comm, self.stats = comm, stats

    def frames(self) -> Iterator[Frame]:
        stamps = self.sim.traj.stamps_ns
        while not self.sim.done:
            yield Frame(int(stamps[self.sim.state.frame]))

    def step(self, frame: Frame) -> Step:
        stamp, T_l_c, kf = self.sim.step()
        s = Step(stamp, T_l_c)
        if kf is not None:
            self.comm.add_keyframe(kf.kf)
            self.comm.add_map_points(kf.new_mps)
            s.keyframes = 1
            self.stats.map_points += len(kf.new_mps)
        if self.sim.last_kf is not None:
            s.kf_ref, s.T_l_ref = self.sim.last_kf[0], self.sim.last_kf[1]
        return s

    def poll(self) -> None:
        pass

    def finish(self) -> None:
        pass

    def on_chunk(self, chunk: MapChunk) -> None:
        pass

    def close(self) -> None:
        pass


class SimAgentRunner(AgentLoop):
    """The agent loop with a simulated agent; it connects before it flies."""

    def __init__(
        self,
        settings: Settings,
        agent_id: str,
        sim: SimAgent,
        speed: float = 1.0,
        flush_timeout_s: float = 30.0,
        stop: threading.Event | None = None,
    ) -> None:
        self.sim = sim
        super().__init__(settings, agent_id, SimProducer(sim), speed=speed,
                         wait_for_server=True, flush_timeout_s=flush_timeout_s,
                         stop=stop)  # fmt: skip

    @property
    def estimates(self):
        return self.vo_poses

    def run(self, bus=None) -> AgentStats:
        try:
            return super().run(bus)
        finally:
            if bus is None and self.bus is not None:
                self.bus.close()
                self._session.close()
