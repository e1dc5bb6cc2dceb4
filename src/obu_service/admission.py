"""Admission of RSU input to the OBU (pure): what may be decoded, kept and fused. Times are OBU ns.

From the header alone, before any object is decoded (``lists``, ``paths``):
- at most ``max_objects_per_list`` objects, ``prediction_ns`` at most ``max_prediction_ns``,
  a prediction list at most ``max_path_points`` predicted positions;
- the RSU gets a slot in the ``RsuTable`` (known ids first, unknown ones bounded and expiring);
- not a duplicate of a (seq, capture) seen recently from that RSU;
- once the RSU's clock is known: valid no later than its arrival plus the clock uncertainty
  and ``future_tolerance_ns`` (else ``future_timestamp``), and no older than the oldest data a
  mode can use (``list_max_age_ns``, inter-frame fusion; ``paths_max_age_ns``, planning) plus the
  uncertainty (else ``stale``; a stale list still tells the link monitor its delay), placed by
  the clock that stamped it around a confirmed clock step (``RsuState.clock_of``). A replay
  is a duplicate or stale. Paths are kept only once the clock is known (they cannot be placed
  before, and the next ones come within a period).
Then ``on_site`` drops the objects farther than ``site_radius_m`` from their RSU (from the
ego, for an RSU of unknown position), and ``not_ego`` the RSU's detection of this very
vehicle (an RSU sees every vehicle it serves: an object centred within the ego's footprint
grown by a margin, at the list's capture time, is the ego itself, never an obstacle).
Every refusal is counted by reason in ``rejected``.

What passes the header checks is an ``AdmittedList`` / ``AdmittedPaths``: the decoded message with
the state of the RSU that admitted it, which the pipeline takes as is (admitted once per message).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from v2i.core.frames import Pose2D, outside_box_rows
from v2i.core.objects import ObjectArray
from schemas.list_wire import UNCOUNTED_SENSORS
from schemas.messages import ObjectList, ObjectListHeader, PredictionList

from obu_service.rsu_table import RsuState, RsuTable


@dataclass(frozen=True)
class Limits:
    max_objects_per_list: int
    max_path_points: int
    max_prediction_ns: int
    future_tolerance_ns: int
    list_max_age_ns: int
    paths_max_age_ns: int
    site_radius_m: float
    ego_half_lw_m: tuple[float, float] = (0.0, 0.0)  # ego half length, half width + margin (m); 0: no filter


@dataclass(frozen=True)
class AdmittedList:
    """An RSU object list whose header was admitted at ``receive_ns`` (OBU ns), to be taken at once."""

    message: ObjectList
    state: RsuState
    receive_ns: int


@dataclass(frozen=True)
class AdmittedPaths:
    """An RSU prediction list whose header was admitted at ``receive_ns`` (OBU ns), to be taken at once."""

    message: PredictionList
    state: RsuState
    receive_ns: int


class Admission:
    """``link_stats``: a stale list still tells its source's link monitor its delay (off for sources whose
    link statistics nothing reads: the V2V peers)."""

    def __init__(self, limits: Limits, rsus: RsuTable, rejected: Counter, link_stats: bool = True):
        self.limits, self._rsus, self.rejected, self.link_stats = limits, rsus, rejected, link_stats

    def lists(self, header: ObjectListHeader, n_objects: int, receive_ns: int) -> RsuState | None:
        """The RSU's state if an object list with this header is admitted, else None (counted)."""
        return self._screen(header, n_objects, receive_ns, paths=False)

    def paths(self, header: ObjectListHeader, n_objects: int, n_points: int, receive_ns: int) -> RsuState | None:
        """The RSU's state if a prediction list with this header and ``n_points`` predicted
        positions is admitted, else None (counted)."""
        if n_points > self.limits.max_path_points:
            self.rejected["too_many_path_points"] += 1
            return None
        state = self._screen(header, n_objects, receive_ns, paths=True)
        if state is not None and state.sync.estimate_at(receive_ns) is None:
            self.rejected["paths_before_clock_sync"] += 1
            return None
        return state

    def on_site(self, state: RsuState, objects: ObjectArray, ego: Pose2D | None) -> ObjectArray:
        """The objects within site_radius_m of their RSU (of the ego for an RSU of unknown position)."""
        centre = self._rsus.position(state.rsu_id) or (None if ego is None else (ego.x, ego.y))
        if centre is None or not len(objects):
            return objects
        inside = np.hypot(objects.xy[:, 0] - centre[0], objects.xy[:, 1] - centre[1]) <= self.limits.site_radius_m
        if inside.all():
            return objects
        self.rejected["object_outside_site"] += int((~inside).sum())
        return objects.take(inside)

    def not_ego(self, objects: ObjectArray, ego: Pose2D | None) -> ObjectArray:
        """The objects (map) whose centre is outside the ego's footprint at pose ``ego``
        (|x| <= half length, |y| <= half width in base_link: ``ego_self_detection``)."""
        half_l, half_w = self.limits.ego_half_lw_m
        if ego is None or half_l <= 0.0 or not len(objects):
            return objects
        kept = outside_box_rows(objects.xy, ego, half_l, half_w)  # (the rows outside, ascending)
        if len(kept) == len(objects):
            return objects  # no copy
        self.rejected["ego_self_detection"] += len(objects) - len(kept)
        return objects.take(kept)

    def _screen(self, header: ObjectListHeader, n_objects: int, receive_ns: int, paths: bool) -> RsuState | None:
        lim = self.limits
        reason = ("prediction_too_long" if header.prediction_ns > lim.max_prediction_ns else
                  "too_many_objects" if n_objects > lim.max_objects_per_list else None)
        state = self._rsus.admit(header.rsu_id, receive_ns) if reason is None else reason
        if isinstance(state, str):
            self.rejected[state] += 1
            return None
        seen = state.predictions_seen if paths else state.lists_seen
        duplicate = (header.seq, header.capture_time_ns) in seen
        reason = "duplicate" if duplicate else self._timing(state, header, receive_ns, paths)
        if reason is not None:
            self.rejected[reason] += 1
            return None
        return state

    def _timing(self, state: RsuState, header: ObjectListHeader, receive_ns: int, paths: bool) -> str | None:
        """``future_timestamp``, ``stale`` or None, once the RSU's clock is known."""
        est = state.sync.estimate_at(receive_ns)
        if est is None:
            return None
        tolerance_ns = est.uncertainty_ns + self.limits.future_tolerance_ns
        # around a confirmed clock step a list stamped before it is placed by the old clock (RsuState.clock_of;
        # an ambiguous one is judged by the current clock here and dropped when taken)
        place = state.clock_of(header.capture_time_ns, receive_ns, tolerance_ns)[0] or est
        valid_ns = place.to_obu_ns(header.valid_time_ns)
        if valid_ns - receive_ns > tolerance_ns:
            return "future_timestamp"
        max_age_ns = self.limits.paths_max_age_ns if paths else self.limits.list_max_age_ns
        if receive_ns - valid_ns <= max_age_ns + est.uncertainty_ns:
            return None
        if not paths and self.link_stats:
            state.monitor.on_message(header.seq, place.to_obu_ns(header.capture_time_ns),
                                     place.to_obu_ns(header.publish_time_ns), receive_ns,
                                     header.sensor not in UNCOUNTED_SENSORS)
        return "stale"
