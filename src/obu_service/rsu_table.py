"""The RSUs an OBU hears (pure): known and unknown ids, expiry, and per-RSU duplicate windows.

Memory and trust are bounded by rules, not by the order in which ids are heard:

- known ids (the site's registry, with their map positions) always get a slot;
- unknown ids get at most ``max_unknown`` slots (none when ``accept_unknown`` is off); when
  they are full a new one takes the slot of the least recently heard unknown RSU that is not
  *established* (clock synchronised and with data accepted), or is refused;
- an RSU not heard for ``expiry_ns`` is forgotten (its slot and index are free again).

So a flood of fake ids can neither lock a registered RSU out nor hold the table for good.
Every slot is a tracker source bit (``v2i.fusion.tracking.slot_source``): an OBU's tables (its RSUs',
its V2V peers') share ``MAX_RSUS`` slots.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

from schemas.messages import PredictionList

from v2i.clock.clock_sync import ClockSync, OffsetEstimate
from v2i.fusion.tracking import SOURCE_BITS
from obu_service.link_monitor import LinkMonitor

MAX_RSUS = SOURCE_BITS - 1  # slots of RSUs and peers together: one tracker source bit each (62; metrics list <= 64)
RECENT_KEYS = 512  # (seq, capture) keys remembered per RSU and stream for duplicate detection
# clock_of: a list's capture-to-arrival latency is plausible up to this quantile of the link's measured ones
# (not the maximum: lists received while a step was suspected were measured through the old clock)
LATENCY_QUANTILE = 0.95
RSU_ID_BASE = 1_000_000  # output ids of a slot's objects: RSU_ID_BASE * (slot index + 1) + track id mod base


class RecentKeys:
    """The last ``capacity`` keys seen, for O(1) duplicate checks with bounded memory."""

    def __init__(self, capacity: int = RECENT_KEYS):
        self._keys: OrderedDict[tuple, None] = OrderedDict()
        self._capacity = capacity

    def __contains__(self, key: tuple) -> bool:
        return key in self._keys

    def add(self, key: tuple) -> None:
        self._keys[key] = None
        while len(self._keys) > self._capacity:
            self._keys.popitem(last=False)


@dataclass
class RsuState:
    """What the OBU keeps of one RSU. Times are OBU-clock ns."""

    rsu_id: str
    index: int  # small integer naming this RSU in fused output ids and frames
    known: bool
    heard_ns: int  # last message of any kind (expiry)
    sync: ClockSync = field(default_factory=ClockSync)
    monitor: LinkMonitor = field(default_factory=LinkMonitor)
    frames: deque = field(default_factory=deque)  # received lists, oldest first
    predictions: PredictionList | None = None
    lists_seen: RecentKeys = field(default_factory=RecentKeys)
    predictions_seen: RecentKeys = field(default_factory=RecentKeys)
    accepted: int = 0
    last_receive_ns: int | None = None  # last list or paths accepted (coverage)
    last_age_ms: float | None = None
    steps_seen: int = 0  # RSU clock steps already acted on
    placement: object = None  # obu_service.mode_inputs.Placement: its frames as last placed in OBU time
    predictions_clock: OffsetEstimate | None = None  # places ``predictions`` when stamped before a step (clock_of)
    predictions_receive_ns: int | None = None  # when ``predictions`` arrived

    @property
    def established(self) -> bool:
        """Clock synchronised and data accepted: a working RSU, not just a name heard."""
        return self.accepted > 0 and self.sync.estimate() is not None

    def clock_of(self, stamp_rsu_ns: int, receive_ns: int, slack_ns: int) -> tuple[OffsetEstimate | None, str]:
        """(the estimate that places an RSU time stamp of a message received at ``receive_ns``, which
        clock read it: "current", "old" or "ambiguous"): the RSU's current estimate, or, around its
        last confirmed clock step (``ClockSync.last_step``: between OBU times after_ns and
        before_ns), the old clock's (``previous``, extrapolated with its drift) for a stamp read
        before the step.

        A stamp read by the old clock lies, placed by it, before the step (t_old <= before_ns); one
        read by the new clock, placed by it, after (t_new >= after_ns); either is no later than its
        arrival (t <= receive_ns + slack_ns). When exactly one reading holds it names the clock.
        When both do (a stamp within |step| of the step), the latency each implies (receive - t)
        decides if only one is within what the link delivers (``LATENCY_QUANTILE`` of the RSU's
        measured capture-to-arrival latency, plus slack): after a step of -700 ms, a list
        captured just after it would otherwise have taken 700 ms more than the link takes. Else
        the stamp is ambiguous (None), unless the two placements differ by at most ``slack_ns``
        (the current estimate then). Before sync: (None, "current")."""
        est = self.sync.estimate_at(receive_ns)
        step = self.sync.last_step
        if est is None or step is None:
            return est, "current"
        t_old, t_new = step.previous.to_obu_ns(stamp_rsu_ns), est.to_obu_ns(stamp_rsu_ns)
        latest_ns = receive_ns + slack_ns
        old_ok = t_old <= min(step.before_ns, latest_ns)
        new_ok = step.after_ns <= t_new <= latest_ns
        if old_ok and new_ok and abs(t_old - t_new) > slack_ns:
            old_ok, new_ok = self._within_link_latency(receive_ns - t_old, slack_ns), \
                self._within_link_latency(receive_ns - t_new, slack_ns)
        if old_ok == new_ok:  # (a step smaller than the slack: either places it within the slack)
            return (est, "current") if abs(t_old - t_new) <= slack_ns else (None, "ambiguous")
        return (step.previous, "old") if old_ok else (est, "current")

    def _within_link_latency(self, latency_ns: int, slack_ns: int) -> bool:
        """Whether the link delivers lists this late: latency <= its LATENCY_QUANTILE + slack (no: unmeasured)."""
        bound_ms = self.monitor.latency_quantile_ms(LATENCY_QUANTILE)
        return bound_ms is not None and latency_ns <= bound_ms * 1e6 + slack_ns


class RsuTable:
    """RSU states by id; see the module docstring for who gets a slot and for how long."""

    def __init__(self, known: Mapping[str, tuple[float, float]] | None = None, max_unknown: int = 16,
                 expiry_ns: int = 30_000_000_000, accept_unknown: bool = True, first_index: int = 0):
        """``first_index``: the smallest slot index handed out (a second table, such as the V2V
        peers', takes slots after the RSUs' so that no two sources share a tracker bit)."""
        self.known = dict(known or {})
        self.first_index = first_index
        self.max_unknown = max_unknown if accept_unknown else 0
        self.expiry_ns = expiry_ns
        self._states: dict[str, RsuState] = {}

    def __iter__(self) -> Iterator[RsuState]:
        return iter(list(self._states.values()))

    def __len__(self) -> int:
        return len(self._states)

    def get(self, rsu_id: str) -> RsuState | None:
        return self._states.get(rsu_id)

    def position(self, rsu_id: str) -> tuple[float, float] | None:
        """Map position (m) of a known RSU; None for an unknown one."""
        return self.known.get(rsu_id)

    def admit(self, rsu_id: str, now_ns: int) -> RsuState | str:
        """The state of ``rsu_id`` (created if there is room), marked heard at ``now_ns``;
        or the rejection reason: ``unknown_rsu`` (unknown ids refused) or ``too_many_rsus``."""
        state = self._states.get(rsu_id)
        if state is None:
            state = self._create(rsu_id, now_ns)
            if isinstance(state, str):
                return state
        state.heard_ns = max(state.heard_ns, now_ns)
        return state

    def expire(self, now_ns: int) -> list[str]:
        """Forget the RSUs not heard for ``expiry_ns``; their ids."""
        gone = [s.rsu_id for s in self._states.values() if now_ns - s.heard_ns > self.expiry_ns]
        for rsu_id in gone:
            del self._states[rsu_id]
        return gone

    def _create(self, rsu_id: str, now_ns: int) -> RsuState | str:
        known = rsu_id in self.known
        if not known:
            if self.max_unknown == 0:
                return "unknown_rsu"
            unknown = [s for s in self._states.values() if not s.known]
            if len(unknown) >= self.max_unknown:
                spare = [s for s in unknown if not s.established]
                if not spare:
                    return "too_many_rsus"
                del self._states[min(spare, key=lambda s: s.heard_ns).rsu_id]
        used = {s.index for s in self._states.values()}
        index = next(i for i in range(self.first_index, self.first_index + len(used) + 1) if i not in used)
        self._states[rsu_id] = RsuState(rsu_id, index, known, now_ns)
        return self._states[rsu_id]
