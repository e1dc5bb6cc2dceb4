"""OBU pipeline (pure): clock sync, RSU buffering, fusion modes, delay compensation, deadlines.

Driven by calls, never by a clock or Zenoh: the live node and the offline runner feed
the same object. All times are OBU-clock nanoseconds unless named ``*_rsu_ns``.

A cycle: ``on_detections`` (own LiDAR objects of capture time t_c) plans the cycle's mode
and its fusion deadline ``fuse_by_ns``; the driver calls ``fuse`` as soon as ``ready``
says so (at once, or when the awaited RSU frame arrives, or at ``fuse_by_ns``):

  fuse_by = min(t_c + D, last publish + output interval bound) - compute margin

so the output is on time whatever the link does (IAAD's E2E and output-interval bounds).

Whatever passes admission can never crash fusion, and fusion always publishes: the RSU
input is admitted or refused from its header before any object is decoded
(``obu_service.admission``: slots in the ``RsuTable``, object and path counts, predictions,
duplicates, future and stale stamps, the site radius); a cycle fuses at most
``max_rsu_objects_per_cycle`` RSU objects (known RSUs and newer frames first); the output is
fitted to the wire (``v2i.fusion.wire.fit_to_wire``: clip, drop, truncate, each counted in
``output_dropped``), never raising. Every refusal is counted by reason in ``rejected``.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from v2i.core.frames import Pose2D, map_to_base
from v2i.core.identity_memo import IdentityMemo
from v2i.fusion.merger import iou_merge
from v2i.core.objects import ObjectArray, read_only
from v2i.fusion.pose_history import PoseHistory
from v2i.fusion.tracking import slot_source
from v2i.fusion.wire import objects_from_states, wire_columns
from schemas.list_wire import UNCOUNTED_SENSORS
from schemas.messages import (MAX_OBJECTS, SOURCE_VEHICLE, FusedObjectList, ObjectList, ObjectListHeader, ObuMetrics,
                              PredictionList, RsuLinkStatus, TimeReply, TimeRequest)

from obu_service.admission import Admission, AdmittedList, AdmittedPaths, Limits
from v2i.clock.clock_sync import OffsetEstimate
from obu_service.fusion_mode import FUSION_MODES, MODES, Feasible, ModePolicy, mode_reason
from obu_service.methods import COMPENSATIONS, FUSION_METHODS, OWN_ONLY_METHODS, RsuFrame, check_fusion, make_fusion
from obu_service.mode_inputs import ModeInputs, Received
from obu_service.peers import MAX_PEERS, PeerIntake
from obu_service.planning import objects_at, retimed
from obu_service.rsu_table import MAX_RSUS, RSU_ID_BASE, RsuState, RsuTable
from v2i.clock.time_requests import TimeRequests

__all__ = ["COMPENSATIONS", "FUSION_METHODS", "FUSION_MODES", "RSU_ID_BASE", "ObuPipeline", "ObuPipelineConfig"]

# an RSU list's objects (map) as received: the same for every vehicle that hears it (read-only, shared)
_rsu_objects = IdentityMemo(lambda columns: read_only(objects_from_states(columns)))


@dataclass(frozen=True)
class ObuPipelineConfig:
    vehicle_id: str = "ego"
    fusion: str = "kf"
    compensation: str = "predict"
    fusion_mode: str = "adaptive"
    iou_threshold: float = 0.1  # Saravanan et al.'s merger: an RSU object this overlapping an own one is a duplicate
    inter_max_age_s: float = 0.6  # IAAD, Liu et al.: inter-frame fusion tolerates RSU data this old
    planning_max_age_s: float = 5.0  # IAAD, Liu et al.: the RSU's paths are usable this long after t0
    # the largest stated clock uncertainty (OffsetEstimate.uncertainty_ns) an RSU's data is fused through
    # (obu_service.mode_inputs). A clock error e places an object moving at v off by v e, so
    #   e_max = position error allowed / fastest speed expected = 1.5 m / 30 m/s = 50 ms
    # (1.5 m: about the RSU's own position error at range, 0.8-1.4 m measured by the eval; 30 m/s: the
    # fastest actors of the bundled scenarios, highway-merge's 27-30.5 m/s; 50 ms moves 30.5 m/s 1.53 m).
    max_clock_uncertainty_ms: float = 50.0  # intra, inter: frames fed to the tracker
    # planning hands the RSU's 5 s paths to the planner, which keeps a time gap to them (2 s, the
    # headway rule and the scenarios' traffic), not a box in the tracker: a timing error of a
    # quarter of that gap, 2 s / 4 = 500 ms (15 m at 30.5 m/s of a 61 m gap; 7 m at 13.9 m/s
    # urban), a tenth of the 5 s horizon, still leaves the planner three quarters of its margin
    planning_max_clock_uncertainty_ms: float = 500.0
    deadline_ms: float = 100.0  # end-to-end: own LiDAR capture -> publish
    output_interval_ms: float = 150.0  # bound on the time between two consecutive outputs
    compute_margin_ms: float = 10.0  # fusion compute + publish must fit between fuse_by and the deadline
    intra_min_probability: float = 0.9  # adaptive waits for the intra frame only if it arrives this surely
    hysteresis_cycles: int = 3
    coverage_timeout_s: float = 10.0  # an RSU heard this recently is "in coverage" for the miss ratio
    frames_kept: int = 8
    # admission (see the module docstring)
    known_rsus: Mapping[str, tuple[float, float]] = field(default_factory=dict)  # id -> map position (m)
    accept_unknown_rsus: bool = True
    max_unknown_rsus: int = 16
    rsu_expiry_s: float = 30.0  # an RSU not heard this long is forgotten
    site_radius_m: float = 2000.0
    max_objects_per_list: int = 256
    max_rsu_objects_per_cycle: int = 1024
    max_prediction_s: float = 1.0  # header prediction_ns above this is refused
    max_path_points: int = 8192  # predicted positions in one prediction list (objects x points)
    future_tolerance_ms: float = 20.0  # beyond the clock uncertainty
    ego_size_m: tuple[float, float] = (4.7, 1.85)  # length, width of this vehicle: RSU objects on it are itself
    self_margin_m: float = 1.0  # beyond the footprint (the RSU's error near its pole is ~0.8 m, Saravanan et al.)

    def limits(self) -> Limits:
        """What admission allows (obu_service.admission), in ns."""
        return Limits(self.max_objects_per_list, self.max_path_points, round(self.max_prediction_s * 1e9),
                      round(self.future_tolerance_ms * 1e6), round(self.inter_max_age_s * 1e9),
                      round(self.planning_max_age_s * 1e9), self.site_radius_m,
                      (self.ego_size_m[0] / 2 + self.self_margin_m, self.ego_size_m[1] / 2 + self.self_margin_m))

    def __post_init__(self) -> None:
        check_fusion(self.fusion, self.compensation)
        ModePolicy(self.fusion_mode, self.hysteresis_cycles)  # validates the mode
        if not 0 <= self.max_clock_uncertainty_ms <= self.planning_max_clock_uncertainty_ms:
            raise ValueError(f"need 0 <= max_clock_uncertainty_ms ({self.max_clock_uncertainty_ms}) <= "
                             f"planning_max_clock_uncertainty_ms ({self.planning_max_clock_uncertainty_ms})")
        slots = len(self.known_rsus) + (self.max_unknown_rsus if self.accept_unknown_rsus else 0)
        if slots > MAX_RSUS:
            raise ValueError(f"known_rsus ({len(self.known_rsus)}) + max_unknown_rsus ({self.max_unknown_rsus}) "
                             f"exceed {MAX_RSUS} RSU slots (one fusion source bit each)")


@dataclass
class _Cycle:
    """The cycle being fused: own objects, the planned mode and its deadline."""

    capture_ns: int
    own: ObjectArray
    mode: str
    fuse_by_ns: int
    intra_slots: dict[str, int]  # RSU id -> expected capture (OBU ns) of the frame intra waits for
    # what on_detections and ready asked ModeInputs at capture_ns, each with the inputs' version then
    # (ObuPipeline._inputs_version): fuse asks again only if an input came in since
    asked: dict[str, tuple[int, object]] = field(default_factory=dict)


class ObuPipeline:
    def __init__(self, config: ObuPipelineConfig = ObuPipelineConfig(), lanes=None):
        """``lanes``: the scenario's ``LanePredictor``, needed by the ``lane`` compensation."""
        self.config = config
        self.poses = PoseHistory(horizon_s=10.0)
        self.rejected: Counter[str] = Counter()
        self.output_dropped: Counter[str] = Counter()  # output objects clipped or dropped to fit the wire
        self.modes: Counter[str] = Counter({m: 0 for m in MODES})
        self.mode_reasons: Counter[str] = Counter()  # outputs by mode_reason (obu_service.fusion_mode)
        self.cycles = 0
        self.deadline_misses = 0
        self.rsu_deadline_misses = 0
        self.covered_cycles = 0
        self.crowded_out_cycles = 0  # cycles that fell back while the intake refused genuine input (live node)
        self.last_mode = "vehicle-only"
        self._last_reason = ""
        self.last_planning: PredictionList | None = None  # planner-facing output of the last cycle
        # ids of the RSUs whose data the last cycle's output used: frames fed to the fusion method in
        # intra / inter (the tracker's fresh frames for kf, the newest for the stateless methods), the
        # paths merged in planning; () when none
        self.last_rsu_inputs: tuple[str, ...] = ()
        self._policy = ModePolicy(config.fusion_mode, config.hysteresis_cycles)
        self._fusion = make_fusion(config.fusion, config.compensation, config.iou_threshold, lanes)
        self._rsus = RsuTable(config.known_rsus, config.max_unknown_rsus, round(config.rsu_expiry_s * 1e9),
                              config.accept_unknown_rsus)
        self._requests = TimeRequests(config.vehicle_id)
        self._admission = Admission(config.limits(), self._rsus, self.rejected)
        self._inputs = ModeInputs(config, self._rsus)
        self._cycle: _Cycle | None = None
        self._inputs_version = 0  # counts the inputs that can change what ModeInputs answers (see _sync)
        self._last_publish_ns: int | None = None
        self._out_seq = 0
        self.peers: PeerIntake | None = None  # V2V peers (``enable_v2v``)

    def enable_v2v(self, max_peers: int = MAX_PEERS) -> PeerIntake:
        """Take in V2V peers' shared lists (``obu_service.peers``), in slots after the RSUs'."""
        first_slot = len(self.config.known_rsus) + self._rsus.max_unknown
        self.peers = PeerIntake(self.config, self.rejected, self.poses, first_slot, max_peers)
        return self.peers

    # --- clock synchronisation -------------------------------------------------------
    def make_time_request(self, t1_ns: int) -> TimeRequest:
        """A request to send now (t1 = OBU send time); replies are matched by seq. Every RSU's clock
        filter notes it: one asked and not answered promptly is not trusted (ClockSync.silence_ns)."""
        for state in self._rsus:
            state.sync.note_request(t1_ns)
        return self._requests.make(t1_ns)

    def on_time_reply(self, reply: TimeReply, t4_ns: int, verified: bool = False) -> None:
        """A reply is held briefly (``TimeRequests``: the first verified reply to a request counts; of
        unverified ones, a conflicting second reply voids both). ``verified``: its signature checked."""
        refused = self._requests.match(reply, t4_ns, verified)
        if refused is not None:
            self.rejected[refused] += 1
        self._sync(t4_ns)

    def _sync(self, now_ns: int) -> None:
        """Feed the replies whose hold has passed to their RSU's clock filter. Every input that can change
        what ModeInputs answers (a time reply, the admission of an RSU list or paths, a cycle's start with
        its expiry) passes here first: ``on_time_reply``, ``admit_list``, ``admit_paths``, ``on_detections``."""
        self._inputs_version += 1
        for rsu_id, sample in self._requests.ripe(now_ns):
            state = self._rsus.admit(rsu_id, sample.t4_ns)
            if isinstance(state, str):
                self.rejected[state] += 1
            elif not state.sync.add(sample):
                self.rejected["time_reply_inconsistent"] += 1
            elif state.sync.steps_detected > state.steps_seen:
                state.steps_seen = state.sync.steps_detected
                self._restamp(state)
                if self._last_reason == "clock_uncertainty":  # the step explains the fallback, not the link
                    self._policy.climb_at_once()

    def _restamp(self, state: RsuState) -> None:
        """The RSU clock stepped (``ClockSync.last_step``): what it stamped before the step is placed by
        the old clock's estimate from now on, what it stamped since by the new one (``RsuState.clock_of``);
        only lists and paths whose stamps could be either's are dropped (``stale_after_clock_step``)."""
        kept = deque()
        for raw in state.frames:
            if raw.clock is None:  # (one stamped before an earlier step keeps the clock that places it)
                clock, which = self._clock_of(state, raw.capture_rsu_ns, raw.receive_ns)
                if which == "ambiguous":
                    self.rejected["stale_after_clock_step"] += 1
                    continue
                raw.clock = clock if which == "old" else None
            kept.append(raw)
        state.frames = kept
        if state.predictions is not None and state.predictions_clock is None:
            clock, which = self._clock_of(state, state.predictions.header.capture_time_ns, state.predictions_receive_ns)
            if which == "ambiguous":
                self.rejected["stale_after_clock_step"] += 1
                state.predictions = None
            elif which == "old":
                state.predictions_clock = clock

    def _clock_of(self, state: RsuState, stamp_rsu_ns: int, receive_ns: int) -> tuple[OffsetEstimate | None, str]:
        """``RsuState.clock_of`` with this OBU's slack: the clock uncertainty and the future tolerance."""
        est = state.sync.estimate_at(receive_ns)
        slack_ns = (0 if est is None else est.uncertainty_ns) + round(self.config.future_tolerance_ms * 1e6)
        return state.clock_of(stamp_rsu_ns, receive_ns, slack_ns)

    def clock_offset(self, rsu_id: str, t_ns: int | None = None) -> OffsetEstimate | None:
        """Offset estimate (theta = rsu - obu) of one RSU, at OBU time ``t_ns`` if given."""
        state = self._rsus.get(rsu_id)
        if state is None:
            return None
        return state.sync.estimate() if t_ns is None else state.sync.estimate_at(t_ns)

    def naive_clock_offset(self, rsu_id: str) -> OffsetEstimate | None:
        """The latest single exchange's offset, as an unfiltered NTP client would use it."""
        state = self._rsus.get(rsu_id)
        return None if state is None else state.sync.naive()

    # --- admission (obu_service.admission) --------------------------------------------
    def admit_list(self, header: ObjectListHeader, n_objects: int, receive_ns: int) -> RsuState | None:
        """The state of the RSU if an object list with this header may be decoded and fused, else None
        (counted). ``take_list`` takes the decoded list of an admitted header (``obu_service.inbox``)."""
        self._sync(receive_ns)
        return self._admission.lists(header, n_objects, receive_ns)

    def admit_paths(self, header: ObjectListHeader, n_objects: int, n_points: int, receive_ns: int) -> RsuState | None:
        """The state of the RSU if a prediction list with this header and ``n_points`` predicted positions
        may be decoded and kept, else None (counted); ``take_paths`` takes it."""
        self._sync(receive_ns)
        return self._admission.paths(header, n_objects, n_points, receive_ns)

    # --- inputs ----------------------------------------------------------------------
    def on_pose(self, t_ns: int, pose: Pose2D) -> None:
        self.poses.add(t_ns, pose)

    def on_rsu_message(self, msg: ObjectList, receive_ns: int) -> int | None:
        """One decoded RSU object list received at ``receive_ns`` (OBU clock): admitted, then taken
        (``take_list``). Returns its publish time in OBU time (None: refused, or no clock estimate yet)."""
        state = self.admit_list(msg.header, len(msg.objects), receive_ns)
        return None if state is None else self.take_list(AdmittedList(msg, state, receive_ns))

    def take_list(self, admitted: AdmittedList) -> int | None:
        """Keep an admitted RSU object list (its objects on the site, not the ego, in the RSU's slot).
        Returns its publish time in OBU time through the RSU's clock estimate (None: no estimate yet)."""
        msg, state, receive_ns = admitted.message, admitted.state, admitted.receive_ns
        header = msg.header
        state.lists_seen.add((header.seq, header.capture_time_ns))
        ego_now = self.poses.at(receive_ns, uncertainty=False)
        est, which = self._clock_of(state, header.capture_time_ns, receive_ns)
        if which == "ambiguous":  # stamped around a clock step by either clock: it cannot be placed
            self.rejected["stale_after_clock_step"] += 1
            return None
        objects = self._admission.on_site(state, _rsu_objects(msg.objects), ego_now)
        capture_ns = receive_ns if est is None else est.to_obu_ns(header.capture_time_ns)
        objects = self._admission.not_ego(objects, self.poses.at(capture_ns, uncertainty=False))
        objects = objects.with_(ids=self._rsu_ids(state, objects.ids),
                                sources=np.full(len(objects), slot_source(state.index), np.int64))
        state.frames.append(Received(header.capture_time_ns, header.valid_time_ns, header.seq, objects, receive_ns,
                                     clock=est if which == "old" else None))
        state.accepted += 1
        state.last_receive_ns = receive_ns
        publish_obu_ns = None if est is None else est.to_obu_ns(header.publish_time_ns)
        counted = header.sensor not in UNCOUNTED_SENSORS
        if est is not None:
            state.monitor.on_message(header.seq, est.to_obu_ns(header.capture_time_ns), publish_obu_ns, receive_ns,
                                     counted)
        elif counted:  # no delay without a clock estimate, but the numbering counts (messages_sent)
            state.monitor.note_sequence(header.seq)
        while len(state.frames) > self.config.frames_kept:
            state.frames.popleft()
        return publish_obu_ns

    def on_predictions(self, msg: PredictionList, receive_ns: int) -> None:
        """One decoded RSU prediction list (planning fusion): admitted, then taken (``take_paths``)."""
        n_points = sum(len(p.x) for p in msg.paths)
        state = self.admit_paths(msg.header, max(len(msg.objects), len(msg.paths)), n_points, receive_ns)
        if state is not None:
            self.take_paths(AdmittedPaths(msg, state, receive_ns))

    def take_paths(self, admitted: AdmittedPaths) -> None:
        """Keep an admitted prediction list's long-horizon paths: the newest t0 is kept."""
        msg, state, receive_ns = admitted.message, admitted.state, admitted.receive_ns
        header = msg.header
        state.predictions_seen.add((header.seq, header.capture_time_ns))
        clock, which = self._clock_of(state, header.capture_time_ns, receive_ns)
        if which == "ambiguous":
            self.rejected["stale_after_clock_step"] += 1
            return
        if state.predictions is None or self._newer_paths(state, header.valid_time_ns, clock, which):
            state.predictions, state.predictions_receive_ns = msg, receive_ns
            state.predictions_clock = clock if which == "old" else None
            state.last_receive_ns = receive_ns

    @staticmethod
    def _newer_paths(state: RsuState, valid_rsu_ns: int, clock: OffsetEstimate | None, which: str) -> bool:
        """Whether paths valid at RSU time ``valid_rsu_ns``, read by the ``which`` clock (``clock`` places
        them), are newer than the kept ones: in RSU time while both are the current clock's, else in OBU time."""
        kept_rsu_ns, kept_clock = state.predictions.header.valid_time_ns, state.predictions_clock
        if clock is None or which == "current" and kept_clock is None:
            return valid_rsu_ns > kept_rsu_ns
        current = clock if which == "current" else state.sync.estimate()
        return clock.to_obu_ns(valid_rsu_ns) > (kept_clock or current).to_obu_ns(kept_rsu_ns)

    def on_detections(self, dets: ObjectArray, capture_ns: int) -> int:
        """Own LiDAR objects (base_link at capture_ns) start a cycle; returns its fuse_by_ns."""
        if self._cycle is not None:
            self.rejected["cycle_overrun"] += 1  # the previous cycle was never fused
        self._sync(capture_ns)
        self._rsus.expire(capture_ns)
        own = dets.with_(sources=np.full(len(dets), SOURCE_VEHICLE))
        fuse_by_ns = capture_ns + round((self.config.deadline_ms - self.config.compute_margin_ms) * 1e6)
        if self._last_publish_ns is not None:
            interval_ns = round((self.config.output_interval_ms - self.config.compute_margin_ms) * 1e6)
            fuse_by_ns = min(fuse_by_ns, max(self._last_publish_ns + interval_ns, capture_ns))
        slots = self._inputs.intra_slots(capture_ns, fuse_by_ns)
        inter, planning = self._inputs.inter(capture_ns), self._inputs.planning(capture_ns)
        mode = self._policy.select(Feasible(intra=bool(slots), inter=bool(inter[0]), planning=bool(planning)))
        self._cycle = _Cycle(capture_ns, own, mode, fuse_by_ns, slots if mode == "intra" else {})
        self._cycle.asked.update(inter=(self._inputs_version, inter), planning=(self._inputs_version, planning))
        return fuse_by_ns

    @property
    def pending(self) -> bool:
        """A cycle has started and is not fused yet."""
        return self._cycle is not None

    def ready(self, now_ns: int) -> bool:
        """Whether to fuse the pending cycle now: nothing to wait for, or its deadline is here."""
        cycle = self._cycle
        if cycle is None:
            return False
        if cycle.mode != "intra" or not cycle.intra_slots or now_ns >= cycle.fuse_by_ns:
            return True
        intra = self._inputs.intra(cycle.capture_ns, cycle.intra_slots)
        cycle.asked["intra"] = (self._inputs_version, intra)
        return bool(intra[0])

    def reject(self, reason: str, count: int = 1) -> None:
        """Count inputs the shell refused (a codec error's reason, an intake refusal)."""
        self.rejected[reason] += count

    # --- the cycle -------------------------------------------------------------------
    def fuse(self, now_ns: int) -> FusedObjectList:
        """Fuse the pending cycle with the RSU data its mode can use; publish time = now_ns."""
        cycle = self._cycle
        if cycle is None:
            raise RuntimeError("fuse() without a pending cycle (call on_detections first)")
        self._cycle = None
        t_c = cycle.capture_ns
        ego = self.poses.at(t_c) or Pose2D(0.0, 0.0, 0.0)
        intra = self._asked(cycle, "intra", lambda: self._inputs.intra(t_c, cycle.intra_slots))
        inter = self._asked(cycle, "inter", lambda: self._inputs.inter(t_c))
        planning = self._asked(cycle, "planning", lambda: self._inputs.planning(t_c))
        feasible = Feasible(bool(intra[0]), bool(inter[0]), bool(planning))
        mode = self._policy.resolve(cycle.mode, feasible)
        if self.config.fusion in OWN_ONLY_METHODS:
            mode = "vehicle-only"
        reason = self._reason(cycle, mode, feasible)
        own = cycle.own.with_(ids=np.arange(1, len(cycle.own) + 1))
        newest, fresh = (self._within_budget(frames) for frames in {"intra": intra, "inter": inter}.get(mode, ([], [])))
        if self.peers is not None and self.config.fusion not in OWN_ONLY_METHODS:  # V2V: every cycle, inter-frame
            peer_newest, peer_fresh = self.peers.frames(t_c)
            newest, fresh = newest + peer_newest, fresh + peer_fresh
            self.peers.consume(peer_fresh, t_c)
        fused = self._fusion.fuse(t_c, ego, own, newest, fresh)
        used = {f.rsu_index for f in self._fusion.used(newest, fresh)}
        for state in self._rsus:
            ages = [(t_c - f.valid_ns) * 1e-6 for f in newest if f.rsu_index == state.index]
            state.monitor.on_fusion(t_c, ages[0] if ages else None)
        self._inputs.consume(fresh, t_c)
        self.last_planning = None
        if mode == "planning":
            fused = self._with_planning(fused, planning, t_c, ego, now_ns)
            used = {self._rsus.get(pred.header.rsu_id).index for pred, _ in planning}
        self.last_rsu_inputs = tuple(s.rsu_id for s in self._rsus if s.index in used)  # (peers' slots are not RSUs)
        self._account(t_c, mode, now_ns)
        self.mode_reasons[reason] += 1
        self._last_reason = reason
        self._out_seq += 1
        objects, dropped = wire_columns(fused, MAX_OBJECTS, fused=True)  # fit_to_wire, then its wire columns
        self.output_dropped.update(dropped)
        return FusedObjectList(
            vehicle_id=self.config.vehicle_id, seq=self._out_seq, cycle_time_ns=t_c, publish_time_ns=now_ns,
            fusion=self.config.fusion, mode=mode, mode_reason=reason, ego_x=ego.x, ego_y=ego.y, ego_yaw=ego.yaw,
            objects=objects,
        )

    def _asked(self, cycle: _Cycle, what: str, ask):
        """ModeInputs' answer about the cycle (``ask()``), as on_detections or ready had it if no input came in
        since (the same state and time: the same answer, and the same side effects: its placements kept,
        ``last_age_ms`` the same value)."""
        version, answer = cycle.asked.get(what, (None, None))
        return answer if version == self._inputs_version else ask()

    def _reason(self, cycle: _Cycle, mode: str, feasible: Feasible) -> str:
        """Why the cycle ran ``mode`` (``obu_service.fusion_mode.mode_reason``)."""
        if self.config.fusion in OWN_ONLY_METHODS:
            return "best"
        fusion_mode, t_c = self.config.fusion_mode, cycle.capture_ns
        reason = mode_reason(fusion_mode, mode, feasible, set())  # the usual case: no RSU state looked at
        if reason in ("best", "hysteresis"):
            return reason
        return mode_reason(fusion_mode, mode, feasible, self._inputs.withheld(t_c),
                           intra_late=fusion_mode == "intra" and bool(cycle.intra_slots),
                           not_synced=any(s.sync.estimate() is None and (s.frames or s.predictions) for s in self._rsus))

    def _within_budget(self, frames: list[RsuFrame]) -> list[RsuFrame]:
        """The frames a cycle may fuse: at most max_rsu_objects_per_cycle objects in all, known
        RSUs first, then newer frames (the rest counted as ``rsu_objects_over_budget``)."""
        if sum(len(frame.objects) for frame in frames) <= self.config.max_rsu_objects_per_cycle:
            return frames  # all within the budget (the usual case): every frame kept, as the loop below keeps them
        known = {s.index for s in self._rsus if s.known}
        kept, total = [], 0
        for frame in sorted(frames, key=lambda f: (f.rsu_index not in known, -f.valid_ns)):
            if total + len(frame.objects) > self.config.max_rsu_objects_per_cycle:
                self.rejected["rsu_objects_over_budget"] += len(frame.objects)
                continue
            total += len(frame.objects)
            kept.append(frame)
        return sorted(kept, key=lambda f: f.valid_ns) if len(kept) < len(frames) else frames

    def _account(self, t_c: int, mode: str, now_ns: int) -> None:
        """Mode share, output deadline (E2E and interval) and RSU deadline counters."""
        self.cycles += 1
        self.last_mode = mode
        self.modes[mode] += 1
        late = now_ns > t_c + round(self.config.deadline_ms * 1e6)
        gap = self._last_publish_ns is not None and now_ns - self._last_publish_ns > self.config.output_interval_ms * 1e6
        self.deadline_misses += int(late or gap)
        self._last_publish_ns = now_ns
        timeout_ns = self.config.coverage_timeout_s * 1e9
        if any(s.last_receive_ns is not None and t_c - s.last_receive_ns <= timeout_ns for s in self._rsus):
            self.covered_cycles += 1
            self.rsu_deadline_misses += int(mode == "vehicle-only")

    def _with_planning(self, fused: ObjectArray, inputs, t_c: int, ego: Pose2D, now_ns: int) -> ObjectArray:
        """Own result plus the RSU's predicted objects at the cycle time; the newest paths
        (re-timed to the OBU clock) become the planner-facing output."""
        rsu = []
        for pred, t0_ns in inputs:
            state = self._rsus.get(pred.header.rsu_id)
            objs = self._admission.on_site(state, objects_at(pred, (t_c - t0_ns) * 1e-9), ego)
            rsu.append(map_to_base(objs.with_(ids=self._rsu_ids(state, objs.ids),
                                              sources=np.full(len(objs), slot_source(state.index), np.int64)),
                                   ego))
        pred, t0_ns = max(inputs, key=lambda item: item[1])
        self.last_planning = retimed(pred, t0_ns, now_ns)
        return iou_merge(fused, ObjectArray.concat(rsu), self.config.iou_threshold)

    @staticmethod
    def _rsu_ids(state: RsuState, ids: np.ndarray) -> np.ndarray:
        return RSU_ID_BASE * (state.index + 1) + np.mod(ids, RSU_ID_BASE)

    # --- reporting -------------------------------------------------------------------
    def metrics(self, now_ns: int, latency_ms: dict | None = None) -> ObuMetrics:
        """The counters at ``now_ns``; ``latency_ms``: the node's per-stage latency (v2i.telemetry.latency)."""
        return ObuMetrics(
            vehicle_id=self.config.vehicle_id, t_ns=now_ns, cycles=self.cycles,
            output_deadline_misses=self.deadline_misses, rsu_deadline_misses=self.rsu_deadline_misses,
            covered_cycles=self.covered_cycles, crowded_out_cycles=self.crowded_out_cycles, mode=self.last_mode,
            mode_counts=dict(self.modes),
            mode_reasons=dict(self.mode_reasons), rsu_inputs=self.last_rsu_inputs,
            rsus=tuple(self._rsu_status(s, now_ns) for s in self._rsus), rejected=dict(self.rejected),
            output_dropped=dict(self.output_dropped), latency_ms=latency_ms or {},
        )

    @staticmethod
    def _rsu_status(state: RsuState, now_ns: int) -> RsuLinkStatus:
        est, naive = state.sync.estimate_at(now_ns), state.sync.naive()
        link = state.monitor.summary(now_ns)
        return RsuLinkStatus(
            rsu_id=state.rsu_id, clock_offset_ns=None if est is None else est.offset_ns,
            clock_uncertainty_ns=None if est is None else est.uncertainty_ns,
            clock_drift_ppm=None if est is None else est.drift_ppm,
            clock_offset_naive_ns=None if naive is None else naive.offset_ns,
            sync_samples=0 if est is None else est.samples, sync_outliers=state.sync.outliers_rejected,
            clock_steps=state.sync.steps_detected,
            messages_accepted=state.accepted, messages_sent=state.monitor.sent_total(),
            last_data_age_ms=state.last_age_ms, delay_p50_ms=link["delay_p50_ms"], delay_p95_ms=link["delay_p95_ms"],
            jitter_ms=link["jitter_ms"], loss_ratio=link["loss_ratio"],
        )
