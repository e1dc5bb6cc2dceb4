"""Scoring of fused outputs against ground truth (pure; shared by ``eval`` and ``demo``).

Each output is scored as it arrives (``RunRecord`` in ``spec`` drives the tallies here):
the run keeps counts and compact per-cycle numbers, never the outputs. The functions
``score_target``, ``detection_scores`` and ``displacement_error_m`` score a list of
outputs through the same tallies.
"""

from __future__ import annotations

from array import array
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from v2i.fusion.association import assign, center_distance_cost
from v2i.core.frames import map_to_base
from v2i.fusion.geometry import bev_iou_pairs
from v2i.core.objects import ObjectArray
from v2i.fusion.wire import objects_from_states
from schemas.messages import FusedObjectList, PredictionList

from obu_service.fusion_mode import MODES
from obu_service.planning import path_array

from v2i.scoring.detection_metrics import CenterDistanceAp, MotTally, nees_summary, nees_values

MAX_RANGE_M = 80.0  # detection metrics cover actors within this distance of the ego
MATCH_GATE_M = 4.0  # an output object within 4 m of a true actor (nuScenes' widest threshold) is its detection
RANGE_BINS_M = ((0.0, 40.0), (40.0, MAX_RANGE_M), (0.0, np.inf))  # detection AP bins (OTVIC)
RECENT_HANDOFFS = 256  # RSU lists remembered to score each handed-over list once


@dataclass(frozen=True)
class TargetScore:
    """How one actor appears in a stream of outputs: mean BEV IoU, RMSE and the NEES of the
    stated position covariance (``detection_metrics.nees``: mean, and the share inside the
    95 % chi-square interval) over the cycles where it is detected, and the ego-target
    distance at its first detection."""

    detected_cycles: int
    mean_bev_iou: float | None
    rmse_m: float | None
    first_detection_distance_m: float | None
    first_detection_time_s: float | None
    nees_mean: float | None = None
    nees_fraction_inside: float | None = None
    track_ids: int = 0  # distinct output ids the target was detected under
    id_switches: int = 0  # its identity switches as motmetrics counts them (MotTally: 2 m gate, within 80 m)

    def as_dict(self) -> dict:
        return {
            "mean_bev_iou": _round(self.mean_bev_iou), "rmse_m": _round(self.rmse_m),
            "first_detection_distance_m": _round(self.first_detection_distance_m),
            "first_detection_time_s": _round(self.first_detection_time_s), "detected_cycles": self.detected_cycles,
            "nees_mean": _round(self.nees_mean), "nees_fraction_inside": _round(self.nees_fraction_inside),
            "track_ids": self.track_ids, "id_switches": self.id_switches,
        }


def _round(v: float | None, nd: int = 4) -> float | None:
    return None if v is None else round(float(v), nd)


def match_target(truth: ObjectArray, output: ObjectArray, target_id: int) -> int | None:
    """Index of the output object assigned to the target, by a global centre-distance
    assignment of all true actors to all output objects (so a neighbour cannot be
    mistaken for the target); None when the target is not detected."""
    return _match_target_xy(truth.xy, truth.ids, output.xy, target_id)


def _match_target_xy(truth_xy: np.ndarray, truth_ids: np.ndarray, out_xy: np.ndarray, target_id: int) -> int | None:
    """``match_target`` on arrays: truth centres (G, 2) and ids (G,), output centres (P, 2)."""
    if not len(out_xy) or not len(truth_xy):
        return None
    return _match_target_cost(center_distance_cost(truth_xy, out_xy), truth_ids, target_id)


def _match_target_cost(cost_m: np.ndarray, truth_ids: np.ndarray, target_id: int,
                       rows: np.ndarray | None = None) -> int | None:
    """``match_target`` on the centre distances (G, P) m of truths (ids (G,)) to outputs; ``rows``:
    the truth rows of ``target_id`` (found when None).

    Shortcut, exact for the minimum-cost matching of ``assign``: a target with no output inside
    the gate is not detected; when its only output inside the gate has no other truth inside
    the gate, the two form a component of their own and every optimum matches them. (A NaN or
    inf cost is never <= the gate, so the comparison alone keeps the finite costs inside it.)
    """
    if not cost_m.shape[0] or not cost_m.shape[1]:
        return None
    rows = np.flatnonzero(truth_ids == target_id) if rows is None else rows
    if not len(rows):
        return None  # no truth row of the target: no match of the full assignment is its
    if len(rows) == 1:  # the target's row of the (G, P) cost, and the one column it may need
        near = np.flatnonzero(cost_m[rows[0]] <= MATCH_GATE_M)
        if not len(near):
            return None
        if len(near) == 1 and np.count_nonzero(cost_m[:, near[0]] <= MATCH_GATE_M) == 1:
            return int(near[0])
    result = assign(cost_m, MATCH_GATE_M)  # (G, P) m
    rows = result.matches[truth_ids[result.matches[:, 0]] == target_id]
    return int(rows[0, 1]) if len(rows) else None


def _bev_row(objs: ObjectArray, i: int) -> list[float]:
    """``bev_boxes`` row of object ``i`` alone, as floats: [x, y, length, width, yaw]."""
    return [*objs.xy[i].tolist(), *objs.lwh[i, :2].tolist(), objs.yaw.item(i)]


def _ranges_m(xy: np.ndarray) -> np.ndarray:
    """(N,) distances (m) of points (N, 2) from the origin: ``np.linalg.norm(xy, axis=1)`` bit for bit,
    sqrt(x^2 + y^2) (its reduce of the two squares is this one addition), in fewer numpy calls."""
    sq = xy * xy
    return np.sqrt(sq[:, 0] + sq[:, 1])


@dataclass(frozen=True)
class CycleFrame:
    """One output and the truth at its cycle time, both in the true base_link of that cycle
    (ObjectArrays, m); ``t_s`` = cycle time - run start (s)."""

    cycle_ns: int
    t_s: float
    truth: ObjectArray
    out: ObjectArray
    # (truth row, output row) -> TargetTally's numbers of that pair (``pair_values``): a function of this
    # frame's arrays alone, kept so that the run's two tallies (all sources, vehicle only) read a pair once
    _pair_values: dict = field(default_factory=dict, compare=False, repr=False)
    _truth_rows: dict = field(default_factory=dict, compare=False, repr=False)  # actor id -> its truth rows

    @cached_property
    def distances_m(self) -> np.ndarray:
        """(G, P) centre distances (m) of every truth row to every output row, computed once per
        frame: each element is ``center_distance_cost``'s of that pair alone (elementwise, so any
        subset of rows and columns, either way round, is the cost of those subsets bit for bit)."""
        return center_distance_cost(self.truth.xy, self.out.xy)

    def truth_rows(self, actor_id: int) -> np.ndarray:
        """The truth rows (R,) of ``actor_id`` (one when present), found once per frame and id."""
        rows = self._truth_rows.get(actor_id)
        if rows is None:
            rows = self._truth_rows[actor_id] = np.flatnonzero(self.truth.ids == actor_id)
        return rows

    def pair_values(self, i: int, k: int) -> tuple[float, list[float], tuple[float, float], list[float]]:
        """Truth row i scored against output row k (base_link), as floats: the squared error |e|^2
        (e = out xy - truth xy), the two BEV boxes [x, y, l, w, yaw] (truth's, then the output's: 10), e
        and the output's position covariance (4, row-major). ``TargetTally`` derives the IoU and NEES."""
        values = self._pair_values.get((i, k))
        if values is None:
            truth, out = self.truth, self.out
            (tx, ty), (ox, oy) = truth.xy[i].tolist(), out.xy[k].tolist()
            ex, ey = ox - tx, oy - ty
            # |e|^2 = ex^2 + ey^2: np.sum(np.square(e)) of the two, one addition of the same squares
            values = self._pair_values[i, k] = (ex * ex + ey * ey, _bev_row(truth, i) + _bev_row(out, k), (ex, ey),
                                                out.cov_xy[k].ravel().tolist())
        return values

    @classmethod
    def of(cls, world, msg: FusedObjectList, start_ns: int,
           truth: tuple[float, ObjectArray] | None = None) -> CycleFrame:
        """``truth``: (t_s, the truth in the true base_link at t_s) already derived in this step
        (the LiDAR's frame, ``v2i.sim.sensors.Lidar.last_truth``); taken when t_s is this cycle's."""
        t_s = (msg.cycle_time_ns - start_ns) * 1e-9
        if truth is not None and truth[0] == t_s:
            return cls(msg.cycle_time_ns, t_s, truth[1], objects_from_states(msg.objects))
        return cls(msg.cycle_time_ns, t_s, map_to_base(world.actors_at(t_s), world.ego_at(t_s)),
                   objects_from_states(msg.objects))


class TargetTally:
    """``world.target_id`` in a stream of outputs. Per cycle where it is detected: cycle time,
    BEV IoU, squared error, NEES eps, the truth's position (for the ego distance at the first
    detection) and the output id (64 bytes), and for the run report the output's position in
    base_link and its source class (17 bytes); scored in cycle order.

    A detected cycle's IoU and NEES wait with the pair's boxes, error and covariance (144 bytes) until
    ``PENDING`` cycles have gathered (or a score is asked for), then are computed for all of them at
    once (``v2i.fusion.geometry.bev_iou_pairs``, ``nees_values``: row by row the numbers of one pair alone)."""

    PENDING = 64

    def __init__(self, target_id: int, sources_mask: int | None = None, mot: MotTally | None = None):
        """``mot``: the run's ``MotTally`` over the same outputs (``DetectionTally.mot``), whose identity
        switches of the target are its ``id_switches``; None: a tally of its own, fed by ``add``
        (over the outputs ``sources_mask`` keeps)."""
        self.target_id, self.sources_mask = target_id, sources_mask
        self.mot, self._own_mot = (MotTally(), True) if mot is None else (mot, False)
        self._cycle_ns, self._cols = array("q"), {k: array("d") for k in ("t_s", "iou", "sq_err", "eps")}
        self._ids = array("q")
        self._truth_xy = array("d")  # x, y interleaved (base_link, m)
        self._out_xy, self._sources = array("d"), array("B")  # x, y interleaved (base_link, m); source class
        self._boxes, self._err, self._cov = array("d"), array("d"), array("d")  # pending: 10, 2 and 4 per cycle

    def add(self, frame: CycleFrame) -> None:
        truth, out = frame.truth, frame.out
        rows = frame.truth_rows(self.target_id)
        if self.sources_mask is None:
            kept = None
            k = _match_target_cost(frame.distances_m, truth.ids, self.target_id, rows)
        else:  # the kept outputs' columns of the cost
            kept = np.flatnonzero(out.sources & self.sources_mask)
            k = _match_target_cost(frame.distances_m[:, kept], truth.ids, self.target_id, rows)
            k = None if k is None else int(kept[k])  # the index in the whole output
        if self._own_mot:
            mot_frame(self.mot, frame, kept)
        if k is None:
            return
        i = rows.item(0)
        sq_err, boxes, err, cov = frame.pair_values(i, k)
        self._cycle_ns.append(frame.cycle_ns)
        self._ids.append(out.ids.item(k))
        self._truth_xy.extend(truth.xy[i].tolist())
        self._out_xy.extend(out.xy[k].tolist())
        mask = out.sources.item(k)  # bit 0 the own vehicle, bits 1..62 the RSU / peer slots
        self._sources.append((mask & 1) | (2 if mask >> 1 else 0))
        self._cols["t_s"].append(frame.t_s)
        self._cols["sq_err"].append(sq_err)
        self._boxes.extend(boxes)
        self._err.extend(err)
        self._cov.extend(cov)
        if len(self._err) >= 2 * self.PENDING:
            self._score_pending()

    def _score_pending(self) -> None:
        """The IoU and NEES eps of the pending cycles, in their order."""
        if not self._err:
            return
        boxes = np.array(self._boxes, dtype=float).reshape(-1, 2, 5)  # (K, 2, 5): truth, output
        self._cols["iou"].extend(bev_iou_pairs(boxes[:, 0], boxes[:, 1]).tolist())
        errors, covariances = np.array(self._err, dtype=float).reshape(-1, 2), np.array(self._cov, dtype=float)
        self._cols["eps"].extend(nees_values(errors, covariances.reshape(-1, 2, 2)).tolist())
        for pending in (self._boxes, self._err, self._cov):
            del pending[:]

    def score(self) -> TargetScore:
        """Mean IoU, RMSE = sqrt(mean |e|^2), NEES over the detected cycles; the first one's distance and time."""
        self._score_pending()
        order = np.argsort(np.array(self._cycle_ns, dtype=np.int64), kind="stable")
        col = {k: np.array(v, dtype=float)[order] for k, v in self._cols.items()}
        consistency = nees_summary(col["eps"])
        detected = len(order)
        ids = np.array(self._ids, dtype=np.int64)[order]
        # the ego distance |truth xy| of the first detection (np.linalg.norm of that (2,) row, as ever)
        first_xy = np.array(self._truth_xy, dtype=float).reshape(-1, 2)[order[0]] if detected else None
        return TargetScore(
            detected_cycles=detected,
            mean_bev_iou=float(np.mean(col["iou"])) if detected else None,
            rmse_m=float(np.sqrt(np.mean(col["sq_err"]))) if detected else None,
            first_detection_distance_m=float(np.linalg.norm(first_xy)) if detected else None,
            first_detection_time_s=float(col["t_s"][0]) if detected else None,
            nees_mean=consistency["mean"], nees_fraction_inside=consistency["fraction_inside"],
            track_ids=len(np.unique(ids)), id_switches=int(self.mot.switches_of[self.target_id]),
        )

    def series(self) -> TargetSeries:
        """The detected cycles in cycle order (``TargetSeries``)."""
        order = np.argsort(np.array(self._cycle_ns, dtype=np.int64), kind="stable")
        t_s = np.array(self._cols["t_s"], dtype=float)[order]
        error_m = np.sqrt(np.array(self._cols["sq_err"], dtype=float))[order]
        xy = np.array(self._out_xy, dtype=float).reshape(-1, 2)[order]
        return TargetSeries(t_s, error_m, xy, np.array(self._sources, dtype=np.int64)[order])


@dataclass(frozen=True)
class TargetSeries:
    """Per detected cycle: t_s (K,) run seconds, error_m (K,) |output - truth|, out_xy (K, 2) the
    output's position in that cycle's true base_link (m), sources (K,) its source class: bit 0 the
    own vehicle's sensors, bit 1 any cooperative source (RSU or peer); 1 vehicle-only, 2 cooperative
    only, 3 fused."""

    t_s: np.ndarray
    error_m: np.ndarray
    out_xy: np.ndarray
    sources: np.ndarray


def score_target(world, outputs: Iterable[FusedObjectList], start_ns: int,
                 sources_mask: int | None = None) -> TargetScore:
    """Score ``world.target_id`` in the outputs; with ``sources_mask`` only objects whose
    sources intersect it count (SOURCE_VEHICLE gives the vehicle-only view)."""
    tally = TargetTally(world.target_id, sources_mask)
    for msg in outputs:
        tally.add(CycleFrame.of(world, msg, start_ns))
    return tally.score()


class CycleLog:
    """Per output, in arrival order: cycle time, publish time (ns) and fusion mode (17 bytes)."""

    def __init__(self):
        self.cycle_ns, self.publish_ns, self._mode = array("q"), array("q"), array("b")
        self._names: list[str] = []  # mode code -> name, in order of first appearance

    def add(self, msg: FusedObjectList) -> None:
        if msg.mode not in self._names:
            self._names.append(msg.mode)
        self.cycle_ns.append(msg.cycle_time_ns)
        self.publish_ns.append(msg.publish_time_ns)
        self._mode.append(self._names.index(msg.mode))

    def __len__(self) -> int:
        return len(self.cycle_ns)

    def modes(self) -> list[str]:
        return [self._names[c] for c in self._mode]


def deadline_miss_ratio(cycle_times_ns: Sequence[int], output_cycle_ns: Sequence[int], output_publish_ns: Sequence[int],
                        deadline_ms: float) -> float:
    """Share of expected cycles with no output published by cycle time + deadline; outputs as
    parallel (M,) arrays of their cycle and publish times (ns)."""
    if not len(cycle_times_ns):
        return 0.0
    limit_ns = int(deadline_ms * 1e6)
    cycle_ns, publish_ns = np.array(output_cycle_ns, dtype=np.int64), np.array(output_publish_ns, dtype=np.int64)
    on_time = cycle_ns[publish_ns <= cycle_ns + limit_ns]
    return int(np.count_nonzero(~np.isin(np.array(cycle_times_ns, dtype=np.int64), on_time))) / len(cycle_times_ns)


def mode_share(modes: Sequence[str]) -> dict[str, float]:
    """Share of cycles per fusion mode, keyed ``intra``, ``inter``, ``planning``, ``vehicle_only``."""
    return {m.replace("-", "_"): round(sum(x == m for x in modes) / max(len(modes), 1), 4) for m in MODES}


CLOCK_WARMUP_S = 5.0  # clock errors are scored after the estimator's first 5 s
STEP_SETTLE_S = 3.0  # the 3 s after an injected RSU clock step are scored apart (the step window)
STEP_RECOVERED_MS = 1.0  # the recovery band is never narrower than 1 ms ...
PRE_STEP_S = 3.0  # ... and otherwise set by the largest error in the 3 s before the step
RECOVERY_MARGIN = 1.25  # band = 1.25 x max(that level, 1 ms)
FUSED, PLANNED = 0, 1  # kinds of the clock errors of the cycles that used RSU data


def _error_stats(err_ms: np.ndarray) -> dict:
    """p50 / p95 / max (None without samples) and the sample count."""
    if not len(err_ms):
        return {"p50": None, "p95": None, "max": None, "samples": 0}
    p50, p95 = np.percentile(err_ms, [50, 95])
    return {"p50": round(float(p50), 4), "p95": round(float(p95), 4), "max": round(float(err_ms.max()), 4),
            "samples": int(len(err_ms))}


def _truth_ns(truth, t_ns: np.ndarray, rsu: np.ndarray) -> np.ndarray:
    """(K,) true offsets (ns) at t_ns (K,) of the RSUs rsu (K,) (indexes into ``truth``, a sequence of
    DriftingClocks; a single clock stands for every RSU's)."""
    clocks = truth if isinstance(truth, (list, tuple)) else None
    if clocks is None:
        return np.array([truth.offset_at(int(t)) for t in t_ns], dtype=float)
    return np.array([clocks[int(r)].offset_at(int(t)) for t, r in zip(t_ns, rsu)], dtype=float)


def clock_errors(samples, truth, start_ns: int, step_ns: int | None, fused=(), steps: dict | None = None,
                 rsu_ids: Sequence[str] = ()) -> dict:
    """The clock figures of a run.

    ``samples``: (t_ns, theta_ns, naive theta_ns, drift ppm[, RSU index]) rows ((K, 4) or (K, 5)
    array-like, float64), each RSU's estimate at t scored against its true clock (``truth``: one
    DriftingClock per RSU index, or one for all: offset_at(t), drift_ppm).
    - ``clock_offset_error_ms`` (and ``_naive_ms``, the single exchange): |estimate - truth| (ms) over
      the steady state, t >= start + CLOCK_WARMUP_S and outside the step window [step, step + STEP_SETTLE_S);
    - ``clock_offset_error_step_window_ms``: the same over the step window (no samples without a step);
    - ``clock_drift_error_ppm``: median |drift - true drift| over the steady state;
    - ``clock_step_recovery_s`` (with a step): ``_recovery_s`` of each RSU, the slowest (None if one
      never recovered);
    - ``clock_error_when_fused_max_ms`` / ``..._planning_max_ms``: max |estimate - truth| over ``fused``,
      (t_ns, theta_ns, RSU index, kind FUSED or PLANNED) rows: each RSU whose data a cycle fused (intra,
      inter) or whose paths it placed (planning), its estimate at the cycle time; None when no cycle did;
    - ``clock_steps_detected``: the steps the OBU's estimators confirmed, summed over ``steps`` (RSU id ->
      count; None: not known, e.g. a live OBU's metrics without them);
    - ``clock_rsus``: per RSU id (``rsu_ids``, by index) its steps and steady-state offset error.
    """
    rows = np.asarray(samples, dtype=float)
    rows = rows.reshape(-1, rows.shape[1] if rows.ndim == 2 and rows.shape[1] == 5 else 4)
    rsu = rows[:, 4].astype(np.int64) if rows.shape[1] == 5 else np.zeros(len(rows), dtype=np.int64)
    true_ns = _truth_ns(truth, rows[:, 0], rsu)
    err_ms, naive_ms = np.abs(rows[:, 1] - true_ns) * 1e-6, np.abs(rows[:, 2] - true_ns) * 1e-6
    window = np.zeros(len(rows), dtype=bool)
    if step_ns is not None:
        window = (rows[:, 0] >= step_ns) & (rows[:, 0] < step_ns + STEP_SETTLE_S * 1e9)
    scored = (rows[:, 0] >= start_ns + CLOCK_WARMUP_S * 1e9) & ~window
    drift_err = np.abs(rows[scored, 3] - _drift_ppm(truth, rsu[scored]))
    report = {
        "clock_offset_error_ms": _error_stats(err_ms[scored]),
        "clock_offset_error_naive_ms": _error_stats(naive_ms[scored]),
        "clock_offset_error_step_window_ms": _error_stats(err_ms[window]),
        "clock_drift_error_ppm": round(float(np.median(drift_err)), 3) if len(drift_err) else None,
        **_fused_errors(fused, truth),
        "clock_steps_detected": None if steps is None else int(sum(steps.values())),
        "clock_rsus": {rid: {"steps_detected": None if steps is None else steps.get(rid, 0),
                             "offset_error_ms": _error_stats(err_ms[scored & (rsu == k)])}
                       for k, rid in enumerate(rsu_ids)},
    }
    if step_ns is not None:
        report["clock_step_recovery_s"] = _slowest_recovery_s(rows[:, 0], err_ms, rsu, step_ns)
    return report


def _drift_ppm(truth, rsu: np.ndarray) -> np.ndarray | float:
    """The true drift (ppm) of each sample's RSU (one clock: its drift)."""
    if isinstance(truth, (list, tuple)):
        return np.array([truth[int(r)].drift_ppm for r in rsu], dtype=float)
    return truth.drift_ppm


def _fused_errors(fused, truth) -> dict:
    """max |theta - truth| (ms) over the FUSED rows and over the PLANNED rows of ``fused`` ((F, 4):
    t_ns, theta_ns, RSU index, kind); None for a kind without rows."""
    rows = np.asarray(fused, dtype=float).reshape(-1, 4)
    err_ms = np.abs(rows[:, 1] - _truth_ns(truth, rows[:, 0], rows[:, 2].astype(np.int64))) * 1e-6
    out = {}
    for key, kind in (("clock_error_when_fused_max_ms", FUSED), ("clock_error_when_planning_max_ms", PLANNED)):
        errors = err_ms[rows[:, 3] == kind]
        out[key] = round(float(errors.max()), 4) if len(errors) else None
    return out


def _slowest_recovery_s(t_ns: np.ndarray, err_ms: np.ndarray, rsu: np.ndarray, step_ns: int) -> float | None:
    """``_recovery_s`` of each RSU with samples after the step: the largest; None if one never
    recovered (or no RSU has samples after the step)."""
    times = []
    for k in np.unique(rsu):
        mine = rsu == k
        if not np.any(t_ns[mine] >= step_ns):
            continue
        times.append(_recovery_s(t_ns[mine], err_ms[mine], step_ns))
    return None if not times or None in times else max(times)


def recovery_band_ms(t_ns: np.ndarray, err_ms: np.ndarray, step_ns: int) -> float:
    """The error a step must come back within: RECOVERY_MARGIN x max(L, STEP_RECOVERED_MS), with
    L = the largest |error| (ms) in the PRE_STEP_S before the step (0 without samples there).
    On an asymmetric link the filter's honest error is the asymmetry bias, (up - down) / 2 (15 ms
    for 40 / 10 ms): the band is then ~19 ms, where an absolute 1 ms would never be reached."""
    before = (t_ns >= step_ns - PRE_STEP_S * 1e9) & (t_ns < step_ns)
    level_ms = float(err_ms[before].max()) if np.any(before) else 0.0
    return RECOVERY_MARGIN * max(level_ms, STEP_RECOVERED_MS)


def _recovery_s(t_ns: np.ndarray, err_ms: np.ndarray, step_ns: int) -> float | None:
    """Seconds from the step until the error stays within ``recovery_band_ms`` for good (samples in
    time order); 0 if it never left it; None if the run ends outside it or has no sample after the step."""
    after = t_ns >= step_ns
    if not after.any():
        return None
    bad = np.flatnonzero(after & (err_ms > recovery_band_ms(t_ns, err_ms, step_ns)))
    if not len(bad):
        return 0.0
    if bad[-1] == len(t_ns) - 1:
        return None
    return round((t_ns[bad[-1] + 1] - step_ns) * 1e-9, 3)


class DisplacementTally:
    """IAAD, Liu et al. eq. 1 over the RSU paths handed to the planner, each RSU list once: mean
    |predicted - true location| over their points, for objects matched to a true actor at t0
    (centre-distance assignment, gate MATCH_GATE_M); points after the scenario's end are not
    scored. Keeps a sum, a count and the last RECENT_HANDOFFS (rsu id, seq) keys (a list is
    handed over in consecutive cycles until a newer one arrives)."""

    def __init__(self, world, start_ns: int):
        self.world, self.start_ns = world, start_ns
        self._recent: OrderedDict = OrderedDict()
        self._sum_m, self._points = 0.0, 0

    def add(self, pred: PredictionList) -> None:
        key = (pred.header.rsu_id, pred.header.seq)
        if key in self._recent:
            return
        self._recent[key] = None
        if len(self._recent) > RECENT_HANDOFFS:
            self._recent.popitem(last=False)
        errors = self._errors_m(pred)
        self._sum_m += float(np.sum(errors))
        self._points += len(errors)

    def _errors_m(self, pred: PredictionList) -> np.ndarray:
        """(K,) distances (m) between the matched objects' path points and the true positions."""
        t0_s = (pred.header.valid_time_ns - self.start_ns) * 1e-9
        objs, truth = objects_from_states(pred.objects), self.world.actors_at(t0_s)
        if not len(objs) or not len(truth):
            return np.zeros(0)
        matches = assign(center_distance_cost(objs.xy, truth.xy), MATCH_GATE_M).matches  # (M, 2) object, actor
        if not len(matches):
            return np.zeros(0)
        paths = path_array(pred)[matches[:, 0]]  # (M, K + 1, 3)
        ids = truth.ids[matches[:, 1]]  # (M,) the matched actors, followed by id (actors come and go)
        errors = []
        for j in range(1, paths.shape[1]):
            t_s = t0_s + j * pred.step_ns * 1e-9
            if t_s > self.world.scenario.duration_s:
                break
            later = self.world.actors_at(t_s)
            kept, rows = np.nonzero(ids[:, None] == later.ids[None, :])  # (matched, row at t_s) of those still there
            errors.append(np.linalg.norm(paths[kept, j, :2] - later.xy[rows], axis=1))
        return np.concatenate(errors) if errors else np.zeros(0)

    def value(self) -> float | None:
        """The mean error (m, 4 decimals); None when no path was handed over."""
        return round(self._sum_m / self._points, 4) if self._points else None


def displacement_error_m(world, handed: Iterable[PredictionList], start_ns: int) -> float | None:
    """``DisplacementTally`` of the paths handed to the planner, in order."""
    tally = DisplacementTally(world, start_ns)
    for pred in handed:
        tally.add(pred)
    return tally.value()


class DetectionTally:
    """Centre-distance mAP (0-40 m, 40-80 m, overall = 0-80 m) and MOTA / IDF1 of all actors
    within MAX_RANGE_M of the ego, output by output."""

    def __init__(self):
        self.ap, self.mot = CenterDistanceAp(range_bins_m=RANGE_BINS_M), MotTally()

    def add(self, frame: CycleFrame) -> None:
        truth, out = frame.truth, frame.out
        t = _ranges_m(truth.xy) <= MAX_RANGE_M
        o = _ranges_m(out.xy) <= MAX_RANGE_M
        cost_m = frame.distances_m[t][:, o]  # (G_t, P_o): the frame's distances of the actors and outputs in range
        truth_xy, out_xy = truth.xy[t], out.xy[o]
        self.ap.add_frame(truth_xy, out_xy, out.confidence[o], cost_m)
        self.mot.add_frame(truth.ids[t], truth_xy, out.ids[o], out_xy, cost_m)

    def scores(self) -> dict:
        mot = self.mot.result()
        return {"detection": self.ap.result(), "tracking": {k: mot[k] for k in ("mota", "idf1", "id_switches")}}


def mot_frame(mot: MotTally, frame: CycleFrame, kept: np.ndarray | None = None) -> None:
    """One frame into ``mot`` as ``DetectionTally.add`` feeds its own: the actors and outputs within
    MAX_RANGE_M of the ego; ``kept``: the output rows that count (all when None)."""
    truth, out = frame.truth, frame.out
    t = np.flatnonzero(_ranges_m(truth.xy) <= MAX_RANGE_M)
    cols = np.arange(len(out)) if kept is None else np.asarray(kept, dtype=np.int64)
    o = cols[_ranges_m(out.xy[cols]) <= MAX_RANGE_M]
    mot.add_frame(truth.ids[t], truth.xy[t], out.ids[o], out.xy[o], frame.distances_m[np.ix_(t, o)])


def detection_scores(world, outputs: Iterable[FusedObjectList], start_ns: int) -> dict:
    """``DetectionTally`` of the outputs, in order."""
    tally = DetectionTally()
    for msg in outputs:
        tally.add(CycleFrame.of(world, msg, start_ns))
    return tally.scores()
