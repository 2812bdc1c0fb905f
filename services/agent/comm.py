"""The agent's communication module (CCM-SLAM §4.5), free of any transport.

New keyframes and map points are sent once with all their data, later changes only
as pose/position updates. Messages leave at most at ``rate_hz`` and are cut at
``max_msg_bytes``; what does not fit waits for the next message. Sending is
optimistic: an item counts as delivered unless an ack shows a gap (a later id
acked while an earlier one was not), or no ack came within its resend timeout
(which also covers a lost last message and a server that restarted). Both put the
full item back in the queue.

An overloaded server must not be buried under resends (a fixed 2 s timeout made 32
agents send 3-7x their data when acks took longer than that). So, as TCP does:
- the resend timeout follows the measured ack latency (``srtt + 4 rttvar``, never
  below ``resend_timeout_s``; only first sends are timed, Karn's rule), and doubles
  with each timeout in silence of the same item up to ``backoff_max_s``, with
  +-``jitter`` so agents that lost the server together do not come back in step;
- at most ``window`` keyframes are in flight unacknowledged. The window grows by one
  per ack that came back within ``ack_target_s`` and halves (at most once per round
  trip) on one that did not: a slow server slows its agents' sending, and the backlog
  waits in the agents' buffers (CCM-SLAM §4.5) instead of in the server's queue,
  which keeps the latency of what the server accepts bounded. A timeout in silence
  halves it too. Keyframes the server holds (waiting for a predecessor) or asks for
  again are outside the window, so a hole can always be filled, and while the server
  says nothing for a timeout one keyframe probes past a full window. It never goes
  below ``window_min``.

A long link is no slow server either. The window is the server's back-pressure, so a
late ack counts only for the time the server held the batch (``Ack.held_s``, from its
arrival to the ack; an ack without it counts whole). Before, every ack on a link with
0.5-1.5 s delay came later than ``ack_target_s``, the window sat at ``window_min`` (103
cuts in one flight) and two keyframes per round trip were fewer than the VO made: the
seed-1 pair's agent1 had 40-60 keyframes queued by the end of its flight, the map and
its settled keyframes that far behind it, and the frame correction carried that far
put its reported pose 30-47 mm off over its last 20 s (VO 5-8 mm).

Loss is no congestion (issue 18 item 6). Backoff and the window cut answer a server
that is slow or gone, i.e. a timeout in silence. A timeout of an item whose batch got
no answer while a batch sent after it did (``_answered``) is a loss on the way: the
item goes again at the same timeout, and neither the backoff (its own, or the one
carried to first sends) nor the window changes. An overloaded server does not look like
this: it NACKs what it sheds, and a slow one answers in order, so nothing later is
answered first. Before, on a 50 % lossy link every such timeout doubled the timeouts
and halved the window to 2, whose two keyframes, both lost, then stalled the agent for
timeout after timeout while the server answered its update batches at once (team3:
the window at its minimum in 19-54 % of once-a-second samples, 34-50 window cuts per
agent; ack p95 8-14 s, one agent with 57 keyframes unacked after its flush). So that
a lone batch at the tail (nothing sent after it) is told from silence too, an empty
batch follows it once it is unanswered for twice the ack latency (TCP's tail loss
probe, at most two in a row).

An overloaded mapper sheds batches that waited too long in its queue and says so: a
NACK (an ``Ack`` of that batch with ``retry_after_s``). Everything the batch carried goes
back to the queue at once (oldest first, so a run the server shed together goes out
again together) and no keyframe leaves before the retry-after (+-``jitter``) is over;
the window halves as on a late ack. Without the NACK the agent learned of a shed batch
only from its resend timeout, seconds and doubling, while the server shed everything
it sent after it meanwhile (it registers an agent's keyframes in order). A NACK of what
went out after a hold doubles the next hold (up to ``shed_backoff_max_s``) until the
server takes keyframes again: a server far over its capacity gets fewer batches it can
only shed (each a resend; in tests/test_overload_scale.py's simulation 0.85 -> 0.58
resends per keyframe, and 2.9 -> 1.7 with a third of the capacity). The cap is short:
a hold that outlasts the queue leaves the server idle while agents wait (at the end of
a flight, few agents are left to keep it busy).

Every keyframe stays here, and is resent with backoff, until the server acknowledges
it: the backlog of an overloaded or absent server waits in this buffer (CCM-SLAM §4.5),
not in the VO's local map, which is trimmed for the VO's compute (§4.2) and may let go
of a keyframe this buffer still holds. The buffer is bounded by the keyframes' estimated
wire size (``buffer_bytes``, a whole flight's by default); only past that is the oldest
unacknowledged keyframe dropped (counted as lost).

Updates are small and superseded by newer ones, but a keyframe's last update (when it
leaves the VO's local BA window) has no successor: lost on a lossy link, the server
would keep that keyframe's stale pose, and every keyframe chained after it the same
error (20 % loss doubled the joint ATE). So updates are tracked per message too: the
server's ack names the batch it answers (``Ack.seq``); an update whose message was
followed by an ack of a later one, or not answered within the resend timeout, goes out
again unless a newer one for the same item is already queued. An update of a keyframe
not acknowledged yet is also folded into the buffered keyframe, so a resend of it
carries the newest pose. (The server applies pose data newer than what it has only,
so reordered messages cannot bring an old pose back.)

Loss is inferred from the batch an ack answers (``Ack.seq``): what went out in an
earlier batch and is neither acknowledged nor held by the server was lost, since the
server takes an agent's batches in the order they arrive. On a link that reorders
(delay with jitter) a batch overtaken by a later one is not lost, only late: as TCP's
RACK does, only a batch sent more than a reordering window before the answered one
counts as lost (``reorder_s``: four times the ack latency's mean deviation, estimated
from 0, so ~0 on a steady link), else every overtaken batch was sent twice.

The same class serves the real VO agent and the feature-level simulated agent.
"""

from __future__ import annotations

import bisect
import math
import random
import secrets
from dataclasses import dataclass, field

import numpy as np

from shared.messages import Ack, KeyframeBatch, KeyframeUpdate, MapPoints, NewKeyframe

_KF_OVERHEAD = 900  # msgpack keys, 3 poses and scalars of one keyframe
# Sizes in the full wire form: the compact one agents send is smaller, so the cap
# holds for either.
_KP_BYTES = 8 + 1 + 32 + 8  # keypoint, octave, descriptor, map point id
_MP_BYTES = 8 + 8 + 24 + 32
_UPD_KF_BYTES = 500


def estimate_kf_bytes(kf: NewKeyframe) -> int:
    return _KF_OVERHEAD + _KP_BYTES * len(kf.keypoints)


@dataclass
class _Sent:
    t: float  # when it was sent (or last heard of as held)
    seq: int
    timeout: float = 0.0  # resend unless acked or held within this long of ``t``


class _BySeq:
    """Items on their way, ``id -> (seq of the message that carried them, data)``, found
    by id and by message: an answer or a timeout of one message takes its items without
    a scan of everything in flight."""

    def __init__(self) -> None:
        self.items: dict[int, tuple[int, object]] = {}
        self.seqs: dict[int, set[int]] = {}

    def __contains__(self, i: int) -> bool:
        return i in self.items

    def put(self, i: int, seq: int, data: object = None) -> None:
        self.pop(i)  # a newer send of the same item: the older message no longer has it
        self.items[i] = (seq, data)
        self.seqs.setdefault(seq, set()).add(i)

    def pop(self, i: int) -> tuple[int, object] | None:
        e = self.items.pop(i, None)
        if e is not None:
            ids = self.seqs[e[0]]
            ids.discard(i)
            if not ids:
                del self.seqs[e[0]]
        return e

    def of(self, seq: int) -> list[int]:
        """The ids message ``seq`` carries, in id order."""
        return sorted(self.seqs.get(seq, ()))

    def take(self, seq: int) -> list[tuple[int, object]]:
        """Removes and returns message ``seq``'s items, ``(id, data)`` in id order."""
        return [(i, self.items.pop(i)[1]) for i in sorted(self.seqs.pop(seq, ()))]

    def clear(self) -> None:
        self.items.clear()
        self.seqs.clear()


@dataclass
class CommStats:
    messages: int = 0
    bytes: int = 0
    kf_sent: int = 0
    kf_resent: int = 0
    mp_sent: int = 0
    mp_resent: int = 0
    kf_dropped_unacked: int = 0
    window_cuts: int = 0  # times the window halved on a late ack
    batches_shed: int = 0  # batches the server NACKed (overload)
    probes: int = 0  # empty batches sent to learn whether the server answers
    ack_latencies: list[float] = field(default_factory=list)
    ack_sent_at: list[float] = field(default_factory=list)  # first send of each, monotonic
    ack_attempts: list[int] = field(default_factory=list)  # sends each acked keyframe took
    # Diagnostics (issue 18 item 6): a sample of the sending state about once a second,
    # ("s", t, window, in flight, queued kfs, unacked kfs, held, urgent, rto, backoff,
    # queued mps, kf updates, mp updates), and events ("to", t, kf, attempts, its
    # timeout) per keyframe timeout, ("cut", t, window) per window cut.
    trace: list = field(default_factory=list)


class CommModule:
    def __init__(
        self,
        agent: str,
        rate_hz: float = 5.0,
        max_msg_bytes: int = 400_000,
        resend_timeout_s: float = 2.0,
        backoff_max_s: float = 30.0,
        jitter: float = 0.2,
        window: int = 8,
        window_max: int = 32,
        ack_target_s: float = 0.5,
        window_min: int = 2,
        buffer_bytes: int = 256_000_000,
        session: int | None = None,
        shed_backoff_max_s: float = 4.0,
    ) -> None:
        self.agent = agent
        # This flight's session: a new one per process, so the server tells this flight's
        # keyframe ids from an earlier flight's under the same agent id
        # (services/mapper/sessions.py); the same in every message, resends included.
        self.session = secrets.randbits(63) if session is None else session
        self.min_interval = 1.0 / rate_hz
        self.max_msg_bytes = max_msg_bytes
        self.resend_timeout_s = resend_timeout_s
        self.backoff_max_s = max(backoff_max_s, resend_timeout_s)
        self.jitter = jitter
        self._rng = random.Random(agent)  # seeded: a run replays the same resend times
        self.srtt: float | None = None
        self.rttvar = 0.0
        # No resend can be due before this (a lower bound: entries only leave, or are
        # pushed later by a "held"): check_timeouts skips its walks until then.
        self._earliest_due = math.inf
        self.mdev = 0.0  # the ack latency's mean deviation, from 0 (for reorder_s)
        self.window = float(window)
        self.window_max = window_max
        self.window_min = min(window_min, window)
        self.ack_target_s = ack_target_s
        self._last_cut = -1e18
        self._backoff = 1.0  # carried from the last timeout to first sends (Karn)
        self._last_ack_t = -1e18
        self._last_probe = -1e18
        self._last_sample = -1e18
        self._hold_until = -1e18  # no keyframe goes out before (a NACK's retry-after)
        self._shed_streak = 0  # holds in a row that ended in a NACK again
        self.shed_backoff_max_s = shed_backoff_max_s
        self.attempts: dict[int, int] = {}  # keyframe id -> sends so far (unacked ones)
        # Timeouts in silence (no later batch answered) so far, per unacked keyframe /
        # map point: the exponent of its resend timeout's backoff.
        self._silent: dict[int, int] = {}
        self._mp_silent: dict[int, int] = {}
        self._answered = -1  # the newest batch the server answered (not a NACK)
        self._probes = 0  # empty probe batches sent since the last answer or data batch
        self.held: set[int] = set()  # sent keyframes the server said it holds
        self.urgent: set[int] = set()  # asked for again by the server: not windowed
        self.seq = 0
        self.last_send = -1e18
        # Full data of every keyframe / map point not yet acknowledged.
        self.kfs: dict[int, NewKeyframe] = {}
        self.buffer_bytes = buffer_bytes
        self.buffered_bytes = 0  # estimated wire size of ``kfs``
        self.mps: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}  # id -> ref, p_ref, desc
        self.queued_kfs: list[int] = []  # sorted ids waiting to go out
        self.queued_mps: set[int] = set()
        self.sent_kfs: dict[int, _Sent] = {}
        self.sent_mps: dict[int, _Sent] = {}
        self._mps_by_seq = _BySeq()  # the same points by message (sent_mps keeps the timing)
        self.first_sent_at: dict[int, float] = {}
        self.kf_updates: dict[int, KeyframeUpdate] = {}
        self.mp_updates: dict[int, tuple[int, np.ndarray]] = {}
        self._after_ack: dict[int, tuple[int, np.ndarray]] = {}  # updates of points in flight
        self.acked_kfs: set[int] = set()
        self.forgotten: set[int] = set()  # dropped unacknowledged (may still arrive)
        self._last_seq_by_kf: dict[int, int] = {}
        # Updates sent and not known to have arrived (id -> seq of their message, data),
        # and the messages that carried them: seq -> when sent, timeout.
        self._upd_kf_sent = _BySeq()  # data: the KeyframeUpdate
        self._upd_mp_sent = _BySeq()  # data: (ref kf, p_ref)
        self._upd_msgs: dict[int, _Sent] = {}
        self._seq_t: dict[int, float] = {}  # when each batch went out
        self.resent_reasons: dict[tuple[str, str], int] = {}
        self.stats = CommStats()

    @classmethod
    def from_settings(cls, agent: str, c) -> CommModule:
        """From ``shared.settings.CommSettings``."""
        return cls(agent, c.rate_hz, c.max_msg_bytes, c.resend_timeout_s, c.backoff_max_s,
                   c.jitter, c.window, c.window_max, c.ack_target_s, c.window_min,
                   c.buffer_bytes)  # fmt: skip

    # --- resend timing and window --------------------------------------------------------
    @property
    def rto(self) -> float:
        """The first resend timeout: the ack latency and its spread, at least the
        configured floor."""
        if self.srtt is None:
            return self.resend_timeout_s
        return min(max(self.resend_timeout_s, self.srtt + 4 * self.rttvar), self.backoff_max_s)

    def _timeout(self, attempts: int) -> float:
        """Timeout after the ``attempts``-th send (1 = first): doubling, capped, jittered.
        A first send also keeps the backoff of the last timeout until a first send is
        acked in time (Karn): else, with acks slower than the floor, every keyframe would
        time out before its ack and the latency would never be measured."""
        mult = max(2.0 ** max(attempts - 1, 0), self._backoff)
        base = min(self.rto * mult, self.backoff_max_s)
        return base * (1.0 + self.jitter * (2.0 * self._rng.random() - 1.0))

    def _on_latency(self, lat: float, now: float, held_s: float | None = None) -> None:
        """One first send's ack latency ``lat``; ``held_s``: how much of it the server
        held the batch (None: a server that does not say, then all of it is the
        server's). The resend timeout follows the whole latency, the window only the
        server's part."""
        self._backoff = 1.0
        if self.srtt is None:
            self.srtt, self.rttvar = lat, lat / 2
        else:
            self.mdev = 0.75 * self.mdev + 0.25 * abs(lat - self.srtt)
            self.rttvar = 0.75 * self.rttvar + 0.25 * abs(lat - self.srtt)
            self.srtt = 0.875 * self.srtt + 0.125 * lat
        if (lat if held_s is None else held_s) <= self.ack_target_s:
            self.window = min(self.window + 1.0, float(self.window_max))
        else:
            self._cut_window(now)

    def _cut_window(self, now: float) -> None:
        # One cut per round trip: the acks of one late burst are one congestion signal.
        if now - self._last_cut >= (self.srtt or self.resend_timeout_s):
            self._last_cut = now
            self.window = max(float(self.window_min), self.window / 2)
            self.stats.window_cuts += 1
            self._trace(("cut", round(now, 3), self.window))

    def _trace(self, e: tuple) -> None:
        if len(self.stats.trace) < 20_000:  # bounded: an agent may fly for hours
            self.stats.trace.append(e)

    def _sample(self, now: float) -> None:
        if now - self._last_sample < 1.0:
            return
        self._last_sample = now
        self._trace(("s", round(now, 3), round(self.window, 2), self.in_flight,
                                 len(self.queued_kfs), len(self.kfs), len(self.held),
                                 len(self.urgent), round(self.rto, 3), self._backoff,
                                 len(self.queued_mps), len(self.kf_updates),
                                 len(self.mp_updates)))  # fmt: skip

    @property
    def reorder_s(self) -> float:
        """How much earlier than an answered batch another must have gone out to count
        as lost rather than overtaken (RACK's reordering window)."""
        return min(4 * self.mdev, self.rto)

    def _lost_before(self, seq: int, answered: int) -> bool:
        """Batch ``seq`` is lost: batch ``answered``, sent later, was answered first."""
        if seq >= answered:
            return False
        t, ta = self._seq_t.get(seq), self._seq_t.get(answered)
        return t is None or ta is None or t < ta - self.reorder_s

    @property
    def in_flight(self) -> int:
        return sum(1 for i in self.sent_kfs if i not in self.held and i not in self.urgent)

    # --- input from the local map -------------------------------------------------
    def add_keyframe(self, kf: NewKeyframe) -> list[int]:
        """Buffer a new keyframe until acknowledged. Returns the ids of the oldest
        unacknowledged ones dropped to keep the buffer within ``buffer_bytes``
        (normally none)."""
        old = self.kfs.get(kf.id)
        if old is not None:
            self.buffered_bytes -= estimate_kf_bytes(old)
        else:
            bisect.insort(self.queued_kfs, kf.id)
        self.kfs[kf.id] = kf
        self.buffered_bytes += estimate_kf_bytes(kf)
        dropped = []
        while self.buffered_bytes > self.buffer_bytes and len(self.kfs) > 1:
            oldest = min(self.kfs)
            dropped.append(oldest)
            self.forget_keyframe(oldest)
        return dropped

    def _unbuffer(self, kf_id: int) -> NewKeyframe | None:
        kf = self.kfs.pop(kf_id, None)
        if kf is not None:
            self.buffered_bytes -= estimate_kf_bytes(kf)
        return kf

    def add_map_points(self, mps: MapPoints) -> None:
        for j, i in enumerate(mps.ids.tolist()):
            self.mps[i] = (int(mps.ref_kf[j]), mps.p_ref[j].copy(), mps.descriptors[j].copy())
            self.queued_mps.add(i)

    def update_keyframe(self, upd: KeyframeUpdate) -> None:
        kf = self.kfs.get(upd.id)
        if kf is not None:
            # Not acknowledged: fold the change into the buffered keyframe (a resend
            # carries it); if it never went out, that is all (else the server may have
            # it, its ack lost or late, and a resend would be only acknowledged).
            kf.pred_id, kf.T_pred_kf = upd.pred_id, upd.T_pred_kf
            kf.parent_id, kf.T_par_kf = upd.parent_id, upd.T_par_kf
            if upd.mp_ids is not None:
                kf.mp_ids = upd.mp_ids
            if upd.id not in self.first_sent_at:
                self.kf_updates.pop(upd.id, None)
                self._upd_kf_sent.pop(upd.id)  # older than the fold
                return
        prev = self.kf_updates.get(upd.id)
        if prev is not None and upd.mp_ids is None and prev.mp_ids is not None:
            upd.mp_ids = prev.mp_ids  # new poses, the associations still to send
        self.kf_updates[upd.id] = upd

    def update_map_point(self, mp_id: int, ref_kf: int, p_ref: np.ndarray) -> None:
        if mp_id in self.mps:
            # Unacknowledged: a resend of the full point carries the new position. If
            # it is on its way, the update follows its ack: the server may still hold
            # the point back (its keyframe not registered yet) and would drop an
            # update for a point it does not have.
            _, _, desc = self.mps[mp_id]
            self.mps[mp_id] = (ref_kf, np.asarray(p_ref, float), desc)
            if mp_id in self.sent_mps:
                self._after_ack[mp_id] = (ref_kf, np.asarray(p_ref, float))
            return
        self.mp_updates[mp_id] = (ref_kf, np.asarray(p_ref, float))

    def forget_keyframe(self, kf_id: int) -> None:
        """Drop an unacknowledged keyframe (the buffer is full): it is lost."""
        if self._unbuffer(kf_id) is not None:
            self.stats.kf_dropped_unacked += 1
            self.forgotten.add(kf_id)
        self.sent_kfs.pop(kf_id, None)
        self.attempts.pop(kf_id, None)
        self._silent.pop(kf_id, None)
        self.held.discard(kf_id)
        self.urgent.discard(kf_id)
        i = bisect.bisect_left(self.queued_kfs, kf_id)
        if i < len(self.queued_kfs) and self.queued_kfs[i] == kf_id:
            self.queued_kfs.pop(i)
        self.kf_updates.pop(kf_id, None)
        self._upd_kf_sent.pop(kf_id)

    def forget_map_point(self, mp_id: int) -> None:
        self._mp_silent.pop(mp_id, None)
        self.mps.pop(mp_id, None)
        self._after_ack.pop(mp_id, None)
        self.queued_mps.discard(mp_id)
        self._unsend_mp(mp_id)

    @property
    def unacked_kf_ids(self) -> set[int]:
        return set(self.kfs)

    @property
    def has_updates(self) -> bool:
        """Updates wait to go out (they are never acknowledged: CCM-SLAM sends them
        optimistically, and a newer one supersedes a lost one)."""
        return bool(self.kf_updates or self.mp_updates or self._upd_msgs)

    @property
    def pending(self) -> bool:
        return bool(self.kfs or self.mps)

    # --- acks -------------------------------------------------------------------------
    def on_ack(self, ack: Ack, now: float) -> list[float]:
        """Drop acknowledged data; requeue what the ack proves lost. Returns the
        publish-to-ack latency of each keyframe acknowledged for the first time."""
        lat: list[float] = []
        self._last_ack_t = now
        if ack.retry_after_s is not None and ack.seq >= 0:
            self._on_shed(ack.seq, ack.retry_after_s, now)
            return lat
        acked = ack.kf_ids.tolist()
        if acked:
            self._shed_streak = 0  # the server takes keyframes again
        newest_seq = max((self._last_seq_by_kf.get(i, -1) for i in acked), default=-1)
        for i in acked:
            if self._unbuffer(i) is not None:
                t0 = self.first_sent_at.pop(i, None)
                if t0 is not None:
                    lat.append(now - t0)
                    self.stats.ack_sent_at.append(t0)
                    self.stats.ack_attempts.append(self.attempts.get(i, 0))
                    sent = self.sent_kfs.get(i)
                    # Karn: a resent item's latency mixes up its sends; a held one's
                    # includes waiting for another keyframe.
                    if self.attempts.get(i) == 1 and i not in self.held and sent is not None:
                        self._on_latency(now - sent.t, now, ack.held_s)
            self.sent_kfs.pop(i, None)
            self._last_seq_by_kf.pop(i, None)
            self.attempts.pop(i, None)
            self._silent.pop(i, None)
            self.held.discard(i)
            self.urgent.discard(i)
            self.acked_kfs.add(i)
        for i in ack.mp_ids.tolist():
            self.mps.pop(i, None)
            upd = self._after_ack.pop(i, None)
            if upd is not None:
                self.mp_updates[i] = upd
            self._unsend_mp(i)
            self.queued_mps.discard(i)
            self._mp_silent.pop(i, None)
        held = set() if ack.held_kf_ids is None else set(ack.held_kf_ids.tolist())
        if held:
            # Received and waiting on the server: not lost, so no timeout resend.
            for i in held:
                if i in self.sent_kfs:
                    self.sent_kfs[i].t = now
                    self.held.add(i)
        # The batch this ack answers: its own seq, or (a server that does not say) the
        # newest batch one of the acknowledged keyframes went out in. Only a batch whose
        # keyframes the server took (acknowledged or held) proves an earlier one lost:
        # an overloaded mapper sheds keyframe batches unanswered yet still answers
        # update-only ones, and what it shed must wait for its backed-off timeout.
        took = bool(acked) or bool(held)
        answered = (ack.seq if ack.seq >= 0 else newest_seq) if took else -1
        if ack.missing_kf_ids is not None:
            for i in ack.missing_kf_ids.tolist():
                s = self.sent_kfs.get(i)
                # Not when it went out again after the answered batch (on its way).
                again = s is not None and ack.seq >= 0 and not self._lost_before(s.seq, ack.seq)
                if i in self.kfs and i not in self.queued_kfs and not again:
                    self._requeue_kf(i, "nack")
                    self.urgent.add(i)
        if answered >= 0:
            # Gap evidence: anything sent in an earlier batch than the answered one,
            # yet neither acked nor held, was lost (batches are processed in order).
            for i, s in list(self.sent_kfs.items()):
                if i not in held and self._lost_before(s.seq, answered):
                    self._requeue_kf(i, "gap")
            for i, s in list(self.sent_mps.items()):
                # A point whose keyframe is not acknowledged waits with it on the
                # server (or goes again with it): no evidence of its own loss.
                if self._lost_before(s.seq, answered) and not self._waits_for_kf(i):
                    self._requeue_mp(i, "gap")
            # Seqs go out in increasing order, so the dict's oldest entries come first:
            # prune from the front instead of scanning every entry on each ack.
            while self._seq_t and (q := next(iter(self._seq_t))) < answered - 10_000:
                del self._seq_t[q]
        if ack.seq > self._answered:
            self._answered = ack.seq
        self._probes = 0
        self._on_update_ack(ack.seq)
        self.stats.ack_latencies.extend(lat)
        return lat

    def _on_shed(self, seq: int, retry_after_s: float, now: float) -> None:
        """The server shed batch ``seq`` (overload): all it carried goes back to the
        queue now, and no keyframe goes out for ``retry_after_s``."""
        self.stats.batches_shed += 1
        for i in [i for i, s in self.sent_kfs.items() if s.seq == seq]:
            self._requeue_kf(i, "shed")  # with its points of the same batch
        for i in self._mps_by_seq.of(seq):
            if self.sent_mps.get(i) is not None and self.sent_mps[i].seq == seq:
                self._requeue_mp(i, "shed")
        if self._upd_msgs.pop(seq, None) is not None:
            self._requeue_updates(seq, "shed")
        if now >= self._hold_until:  # else a NACK of the same shed run
            self._shed_streak += 1
        mult = 2.0 ** min(self._shed_streak - 1, 16)
        wait = max(min(retry_after_s * mult, self.shed_backoff_max_s), retry_after_s)
        wait *= 1.0 + self.jitter * (2.0 * self._rng.random() - 1.0)
        self._hold_until = max(self._hold_until, now + wait)
        self._cut_window(now)

    def _on_update_ack(self, seq: int) -> None:
        """The server answered batch ``seq``: its updates arrived, and those of earlier
        unanswered batches sent before the reordering window were lost (the server takes
        an agent's batches in the order they arrive); later ones may still come."""
        if seq < 0:  # a server that does not say: as before, updates are optimistic
            self._upd_msgs.clear()
            self._upd_kf_sent.clear()
            self._upd_mp_sent.clear()
            return
        for s in [s for s in self._upd_msgs if s == seq or self._lost_before(s, seq)]:
            self._upd_msgs.pop(s)
            if s < seq:
                self._requeue_updates(s, "gap")
            else:
                self._upd_kf_sent.take(s)
                self._upd_mp_sent.take(s)

    def _requeue_updates(self, seq: int, reason: str) -> None:
        n = 0
        for i, upd in self._upd_kf_sent.take(seq):
            if i not in self.kf_updates:  # else a newer one waits already
                self.kf_updates[i] = upd
                n += 1
        for i, upd in self._upd_mp_sent.take(seq):
            if i not in self.mp_updates and i not in self.mps:
                self.mp_updates[i] = upd
                n += 1
        if n:
            key = ("upd", reason)
            self.resent_reasons[key] = self.resent_reasons.get(key, 0) + n

    def _sent(self, now: float, seq: int, timeout: float) -> _Sent:
        self._earliest_due = min(self._earliest_due, now + timeout)
        return _Sent(now, seq, timeout)

    def check_timeouts(self, now: float) -> int:
        n = 0
        self._sample(now)
        # Called on every wake of the agent loop (20-70 times a second): walking every
        # point in flight each time was a few per cent of a simulated agent's CPU.
        if now <= self._earliest_due:
            return 0
        for i, s in list(self.sent_kfs.items()):
            if now - s.t > s.timeout:
                lost = self._lost_before(s.seq, self._answered)
                self._trace(("to", round(now, 3), i, self.attempts.get(i, 1),
                             round(s.timeout, 3), lost))  # fmt: skip
                if lost:
                    # The server answered a later batch: this one was lost on the way
                    # (a lossy link), not left unanswered by a server that is slow or
                    # gone. Resent at the same timeout, and no congestion signal.
                    self._requeue_kf(i, "lost")
                    n += 1
                    continue
                k = self._silent[i] = self._silent.get(i, 0) + 1
                self._backoff = min(max(self._backoff, 2.0**k),
                                    self.backoff_max_s / self.resend_timeout_s)  # fmt: skip
                # A loaded server sheds what waited too long and acknowledges nothing
                # of it: no late ack to measure, so the timeout is the signal.
                self._cut_window(now)
                self._requeue_kf(i, "timeout")
                n += 1
        for i, s in list(self.sent_mps.items()):
            if now - s.t > s.timeout and not self._waits_for_kf(i):
                if self._lost_before(s.seq, self._answered):
                    self._requeue_mp(i, "lost")
                else:
                    self._mp_silent[i] = self._mp_silent.get(i, 0) + 1
                    self._requeue_mp(i, "timeout")
                n += 1
        for seq, s in list(self._upd_msgs.items()):
            if now - s.t > s.timeout:
                del self._upd_msgs[seq]
                self._requeue_updates(seq, "timeout")
        self._earliest_due = min(
            (s.t + s.timeout for d in (self.sent_kfs, self.sent_mps, self._upd_msgs)
             for s in d.values()),
            default=math.inf,
        )  # fmt: skip
        return n

    def _waits_for_kf(self, mp_id: int) -> bool:
        mp = self.mps.get(mp_id)
        return mp is not None and mp[0] in self.kfs

    def _requeue_kf(self, i: int, reason: str) -> None:
        sent = self.sent_kfs.pop(i, None)
        self.held.discard(i)
        if sent is not None:
            # Its points on their way in the same message were lost with it.
            for j in self._mps_by_seq.of(sent.seq):
                if self.mps.get(j, (-1,))[0] == i:
                    self._requeue_mp(j, reason)
        if i in self.kfs:
            j = bisect.bisect_left(self.queued_kfs, i)
            if j >= len(self.queued_kfs) or self.queued_kfs[j] != i:
                self.queued_kfs.insert(j, i)
                self.resent_reasons[("kf", reason)] = self.resent_reasons.get(("kf", reason), 0) + 1

    def _unsend_mp(self, i: int) -> None:
        self.sent_mps.pop(i, None)
        self._mps_by_seq.pop(i)

    def _requeue_mp(self, i: int, reason: str) -> None:
        self._unsend_mp(i)
        if i in self.mps and i not in self.queued_mps:
            self.queued_mps.add(i)
            self.resent_reasons[("mp", reason)] = self.resent_reasons.get(("mp", reason), 0) + 1

    # --- output -------------------------------------------------------------------------
    def due(self, now: float) -> bool:
        has = self.queued_kfs or self.queued_mps or self.kf_updates or self.mp_updates
        return bool(has) and now - self.last_send >= self.min_interval

    def next_message(self, now: float, now_ns: int, kf_ref: int) -> KeyframeBatch | None:
        """The next batch if one is due, within the size cap."""
        if not self.due(now):
            return self._tail_probe(now, now_ns, kf_ref)
        budget = self.max_msg_bytes
        seq = self.seq
        new_kfs: list[NewKeyframe] = []
        room = int(self.window) - self.in_flight
        if self._last_probe < 0:
            self._last_probe = now  # silence is counted from the first message on
        held_back = now < self._hold_until  # a NACK's retry-after: no keyframe at all
        if held_back:
            room = 0
        elif room <= 0 and now - max(self._last_ack_t, self._last_probe) >= self.rto:
            # A full window and a silent server: one new keyframe per timeout goes out
            # anyway, so a server that came back (a restarted mapper) is noticed at its
            # first ack -- which requeues everything older at once (gap) -- and not only
            # when the backed-off timeouts of the window's keyframes run out.
            room = 1
            self._last_probe = now
        j = 0
        while j < len(self.queued_kfs):
            kid = self.queued_kfs[j]
            kf = self.kfs.get(kid)
            if kf is None:
                self.queued_kfs.pop(j)
                continue
            urgent = kid in self.urgent and not held_back
            if room <= 0 and not urgent:
                j += 1  # a later one may be urgent
                continue
            size = estimate_kf_bytes(kf)
            if new_kfs and size > budget:
                break
            budget -= size
            new_kfs.append(kf)
            self.queued_kfs.pop(j)
            room -= not urgent
        for kf in new_kfs:
            resend = kf.id in self.first_sent_at
            self.stats.kf_resent += resend
            self.stats.kf_sent += 1
            self.first_sent_at.setdefault(kf.id, now)
            self.attempts[kf.id] = self.attempts.get(kf.id, 0) + 1
            self.sent_kfs[kf.id] = self._sent(
                now, seq, self._timeout(1 + self._silent.get(kf.id, 0))
            )
            self._last_seq_by_kf[kf.id] = seq
        # Map points in id order, as many as fit, once the server has (or gets in this
        # message) the keyframe they hang on: before that they would only wait there,
        # or time out here.
        out_kfs = {kf.id for kf in new_kfs}
        ready = sorted(i for i in self.queued_mps
                       if (r := self.mps[i][0]) in out_kfs or r in self.sent_kfs
                       or r in self.acked_kfs or r not in self.kfs)  # fmt: skip
        mp_ids = ready[: max(0, budget // _MP_BYTES)]
        for i in mp_ids:
            self.queued_mps.discard(i)
            self.sent_mps[i] = self._sent(now, seq, self._timeout(1 + self._mp_silent.get(i, 0)))
            self._mps_by_seq.put(i, seq)
        budget -= len(mp_ids) * _MP_BYTES
        new_mps = self._pack_mps(mp_ids)
        self.stats.mp_sent += len(mp_ids)
        kf_upd = []
        for i in sorted(self.kf_updates)[: max(0, budget // _UPD_KF_BYTES)]:
            upd = self.kf_updates.pop(i)
            kf_upd.append(upd)
            self._upd_kf_sent.put(i, seq, upd)
        budget -= len(kf_upd) * _UPD_KF_BYTES
        upd_ids = sorted(self.mp_updates)[: max(0, budget // 48)]
        mp_upd = MapPoints(
            np.array(upd_ids, np.int64),
            np.array([self.mp_updates[i][0] for i in upd_ids], np.int64),
            np.array([self.mp_updates[i][1] for i in upd_ids], np.float64).reshape(-1, 3),
            None,
        )
        for i in upd_ids:
            self._upd_mp_sent.put(i, seq, self.mp_updates.pop(i))
        if not (new_kfs or mp_ids or kf_upd or upd_ids):
            # All of it waits for the window (or its keyframe).
            return self._tail_probe(now, now_ns, kf_ref)
        self._probes = 0
        if kf_upd or upd_ids:
            self._upd_msgs[seq] = self._sent(now, seq, self._timeout(1))
        return self._emit(now, now_ns, kf_ref, new_kfs, kf_upd, new_mps, mp_upd)

    def _tail_probe(self, now: float, now_ns: int, kf_ref: int) -> KeyframeBatch | None:
        """An empty batch when the newest one, with keyframes or points on their way,
        is unanswered for twice the ack latency and nothing else goes out (TCP's tail
        loss probe): its answer shows the server answers, so what went before it
        unanswered was lost on the way, and its timeout is no congestion signal (see
        ``check_timeouts``). At most two in a row, and only while acks come within
        ``ack_target_s`` (a server that answers late has a queue a probe would add to:
        48 agents' probes cost the simulated one of tests/test_overload_scale.py without
        shedding ~10 s of drain)."""
        newest = self.seq - 1
        if newest < 0 or self._answered >= newest or self._probes >= 2 or self.srtt is None:
            return None
        if self.srtt > self.ack_target_s:
            return None  # a slow server: late acks, not loss (no load on its queue)
        if not (self.sent_kfs or self.sent_mps):  # (any answer shows lost updates)
            return None
        pto = min(max(2 * self.srtt, 2 * self.min_interval), self.rto / 2)
        if now - max(self.last_send, self._seq_t.get(newest, now)) < pto:
            return None
        self._probes += 1
        self.stats.probes += 1
        return self._emit(now, now_ns, kf_ref, [], [], MapPoints.empty(), MapPoints.empty())

    def _emit(self, now: float, now_ns: int, kf_ref: int, new_kfs: list, kf_upd: list,
              new_mps: MapPoints, mp_upd: MapPoints) -> KeyframeBatch:  # fmt: skip
        """The batch numbered ``self.seq``, sent now (its send time kept for loss and
        reordering judgements)."""
        seq = self.seq
        self._seq_t[seq] = now
        self.seq += 1
        self.last_send = now
        return KeyframeBatch(self.agent, seq, now_ns, kf_ref, new_kfs, kf_upd, new_mps, mp_upd,
                             self.session)  # fmt: skip

    def record_sent(self, nbytes: int) -> None:
        self.stats.messages += 1
        self.stats.bytes += nbytes

    def _pack_mps(self, ids: list[int]) -> MapPoints:
        if not ids:
            return MapPoints.empty()
        return MapPoints(
            np.array(ids, np.int64),
            np.array([self.mps[i][0] for i in ids], np.int64),
            np.stack([self.mps[i][1] for i in ids]).astype(np.float64),
            np.stack([self.mps[i][2] for i in ids]).astype(np.uint8),
        )
