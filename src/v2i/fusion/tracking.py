"""Multi-object tracker over the batched Kalman filters of ``v2i.fusion.kalman`` (map frame).

Cycle (Bidare's KF poster: two updates per cycle): ``predict(t)``, ``update(lidar, t, SOURCE_VEHICLE)``,
``update(rsu, t, SOURCE_RSU)`` for each RSU list, ``prune(t)``, ``tracks(t)``; ``step(dets, t)``
does one predict / update / prune / tracks. Times are seconds on any fixed origin; the
filter never goes back in time (``v2i.fusion.oosm.OosmTracker`` re-filters late measurements).

Motion (``TrackerConfig.motion``): ``cv`` [x, y, vx, vy], ``ca`` [x, y, vx, vy, ax, ay],
``ctrv`` [x, y, v, psi, omega] (EKF); process noise sigmas ``accel_std_mps2`` (CV, CTRV v-dot),
``jerk_std_mps3`` (CA), ``yaw_accel_std_radps2`` (CTRV omega-dot). New tracks start at the
detection (position covariance from the detection, velocity / acceleration / yaw / yaw rate
from the detection with the ``init_*`` prior standard deviations; CV / CA take the
detection's velocity covariance where it is tighter than the speed prior). Two-point
initialisation (CV / CA, ``two_point_init``): a track born without a measured velocity
whose second hit is again a position only takes its velocity from the two positions,
v = (z2 - z1) / dt with P_vv = (R1 + R2) / dt^2 (+ process noise; ``kalman.two_point``),
instead of a Kalman update against the 0 m/s prior, which shrinks the velocity of a fast
target toward 0 (at 80 m from a 5 Hz camera, R ~ 1.8 m^2: about half of it) and lets
the young track fall behind it.

Association per ``update``: a pair (track, detection) is allowed when the classes are
compatible (equal, or either is UNKNOWN = 0) and the pair passes the gate:
``gate="distance"``: centre distance <= ``gate_m``; ``gate="mahalanobis"``:
d2 = y^T S^-1 y <= ``gate_chi2`` (9.21: 99 % for 2 dof); ``gate="either"``: one of the two
within ``gate_max_m`` (a young track whose velocity is still uncertain reaches as far as its
covariance says, but not across a junction on an unknown velocity's 100 m/s prior; an
established one at least ``gate_m`` however small its covariance). Among allowed pairs a
minimum-cost one-to-one assignment (``v2i.fusion.lsap``, scipy's algorithm compiled) with cost
``distance`` (m), ``mahalanobis`` (d2) or ``iou`` (1 - BEV IoU of the predicted box and the
detected box). Matched tracks get a Kalman update of the position and, for CV / CA with
``velocity_updates``, of the velocity where the detection measured one (``cov_vxy`` below
``UNKNOWN_VELOCITY_VAR``, R = cov_vxy); unmatched detections spawn tracks.

Life cycle (``tracks`` returns confirmed and coasting tracks):
- tentative: spawned by an unmatched detection with one hit; every update adds a hit
  (own LiDAR and an RSU in the same cycle give two).
- confirmed: hits >= ``confirm_hits``, or matched with or spawned by another tracker's
  estimate (``update(..., estimates=True)``: an RSU object is the RSU's confirmed track),
  and updated at the current time.
- a track with fewer than ``confirm_hits`` hits (tentative, or confirmed by a single
  estimate) is deleted by ``prune`` when its last update is older than
  ``tentative_max_coast_s`` (0: at its first miss): an RSU object heard once lingers no
  longer than a tentative track lives.
- coasting: confirmed but not updated at the current time; predicted only.
- deleted: by ``prune`` once its last update is older than ``max_coast_s``.

Sources: each update carries a bitmask (``source_mask`` OR the detection's ``sources``)
of ``SOURCE_BITS`` (63) bits, so an int64; the OBU gives bit 0 to its own vehicle and bit
1 + i to RSU slot i (``slot_source``; ``schemas.messages`` documents the bits and how the
wire folds them into one byte). A track's ``sources`` is the OR of the bits that updated it
within the last ``max_coast_s``. Ids are unique within a Tracker instance, starting at 1.
The tracks live in preallocated rows (``track_table.TrackStore``) with one last-update column per
source bit in use, not 63; association (gating, cost, assignment) is ``v2i.fusion.gating``.

Fusing another tracker's estimates (``update(..., estimates=True)``, e.g. an RSU's tracks).
A matched pair (track, estimate with bits b) is fused by exactly one rule, in this order:
1. alone: no source outside b updated the track within ``max_coast_s``: the track takes the
   estimate as its state (x, P from the estimate as for a new track): the newest estimate
   already holds everything that source said before.
2. covariance intersection: a source outside b that has delivered estimates (any earlier
   ``estimates=True`` update of this tracker) updated the track within ``max_coast_s``.
   The track then holds another filter's estimates, whose errors are correlated with this
   one's in an unknown way (common process noise, the same source's earlier estimates
   reaching it through the other's), so a Kalman update would count shared information
   twice. CI (``v2i.fusion.covariance_intersection``): the Kalman update with P / w and
   R / (1 - w), i.e. P+^-1 = w P^-1 + (1 - w) H^T R^-1 H,
   x+ = P+ (w P^-1 x + (1 - w) H^T R^-1 z), w minimising det P+; H observes the position,
   and also the velocity where the estimate measured one (CV / CA with ``velocity_updates``;
   R = blockdiag(cov_xy, cov_vxy)). ``estimate_fusion="kf"`` turns this rule off (rule 3);
   ``"ci-all"`` applies it to every track rule 1 leaves (rule 3 never applies).
3. otherwise (only raw-measurement sources, such as the own LiDAR, share the track): a
   Kalman update of the position only (see ``_correct``).
Raw measurements (``estimates=False``) always get the Kalman update (position, and the
velocity where measured).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from v2i.fusion import kalman
from v2i.fusion.covariance_intersection import ci_fuse_objects
from v2i.core.frames import wrap_angle
from v2i.fusion.gating import (  # noqa: F401  (re-exported: association is part of the tracker's interface)
    GatedPairs,
    assign_gated,
    assign_pairs,
    associate,
    association_cost,
    compatible_classes,
    gated_pairs,
    paired_bev_iou,
)
from v2i.core.objects import ObjectArray
from v2i.fusion.track_table import SOURCE_BITS, TrackStore, TrackTable, estimate_rules, record_matches

_BIT_VALUES = 1 << np.arange(SOURCE_BITS)


@dataclass(frozen=True)
class TrackerConfig:
    """Tracker parameters (units in the names); the module docstring says how each is used."""

    gate_m: float = 5.0  # centre-distance gate for association (gate="distance")
    accel_std_mps2: float = 3.0  # sigma_a: CV white-noise acceleration, CTRV v-dot noise
    init_speed_std_mps: float = 10.0  # prior std of an unknown velocity / speed
    confirm_hits: int = 2
    max_coast_s: float = 0.6
    motion: Literal["cv", "ca", "ctrv"] = "cv"
    gate: Literal["distance", "mahalanobis", "either"] = "distance"
    gate_chi2: float = kalman.CHI2_2DOF_99  # d2 gate for gate="mahalanobis" or "either"
    gate_max_m: float = 15.0  # gate="either": no pair farther apart, whatever its d2 (35 m/s x 0.4 s)
    cost: Literal["distance", "mahalanobis", "iou"] = "distance"
    jerk_std_mps3: float = 5.0  # sigma_j: CA white-noise jerk
    yaw_accel_std_radps2: float = 1.0  # sigma_alpha: CTRV omega-dot noise
    init_accel_std_mps2: float = 3.0  # CA prior std of the acceleration
    init_yaw_std_rad: float = 0.5  # CTRV prior std of the heading
    init_yaw_rate_std_radps: float = 0.5  # CTRV prior std of the turn rate
    tentative_max_coast_s: float = 0.3  # a tentative track survives misses this long (>= slowest source period)
    velocity_updates: bool = True  # cv / ca: measured velocities (cov_vxy below unknown) update the state too
    shape_hold_s: float = 0.3  # a box shape from a precise source is kept this long against coarser ones
    two_point_init: bool = True  # cv / ca: a track born without a velocity takes it from its first two positions
    estimate_fusion: Literal["ci", "kf", "ci-all"] = "ci"  # estimates into a track others share (module doc)

    def __post_init__(self) -> None:
        for name, allowed in (("gate", ("distance", "mahalanobis", "either")), ("cost", ("distance", "mahalanobis", "iou")),
                              ("estimate_fusion", ("ci", "kf", "ci-all"))):
            if getattr(self, name) not in allowed:
                raise ValueError(f"TrackerConfig.{name} must be one of {allowed}, got {getattr(self, name)!r}")
        kalman.make_model(self.motion, 1.0, 1.0, 1.0)  # validates the name

    def motion_model(self) -> kalman.MotionModel:
        return kalman.make_model(self.motion, self.accel_std_mps2, self.jerk_std_mps3, self.yaw_accel_std_radps2)

    def prior(self) -> kalman.StatePrior:
        return kalman.StatePrior(self.init_speed_std_mps, self.init_accel_std_mps2, self.init_yaw_std_rad,
                                 self.init_yaw_rate_std_radps)


@dataclass(frozen=True)
class TrackerSnapshot:
    """The whole filter state of a Tracker (deep copies): time, next id, track table, and the
    bitmask of the sources that have delivered estimates."""

    t_s: float | None
    next_id: int
    table: TrackTable
    estimate_mask: int


def slot_source(slot: int) -> int:
    """Source bit of cooperative slot ``slot`` (an RSU or peer vehicle): 1 << (1 + slot), slot in [0, 62)."""
    if not 0 <= slot < SOURCE_BITS - 1:
        raise ValueError(f"source slot must be in [0, {SOURCE_BITS - 1}), got {slot}")
    return 1 << (1 + slot)


def source_mask_bits(masks: np.ndarray) -> np.ndarray:
    """(K, SOURCE_BITS) booleans of K int64 bitmasks; negative masks (bit 63) are refused."""
    masks = np.asarray(masks, dtype=np.int64)
    if np.any(masks < 0):
        raise ValueError(f"source bitmasks must be in [0, 2^{SOURCE_BITS}), got {masks.min()}")
    return (masks[:, None] & _BIT_VALUES[None, :]) != 0


class Tracker:
    """Multi-object tracker; see the module docstring for the cycle, gating and life cycle.

    The tracks live in a ``track_table.TrackStore`` (preallocated rows, updated in place);
    ``_table`` is the TrackTable of the live rows (views into the store)."""

    def __init__(self, config: TrackerConfig = TrackerConfig()):
        self.config = config
        self.model = config.motion_model()
        self._prior = config.prior()
        self._next_id = 1
        self._t_s: float | None = None
        self._store = TrackStore(self.model.dim_x)
        self._estimate_mask = 0  # bitmask of the sources that have delivered estimates

    @property
    def _table(self) -> TrackTable:
        return self._store.view

    def __len__(self) -> int:
        return self._store.n

    @property
    def time_s(self) -> float | None:
        """Time of the filter state (None before the first call)."""
        return self._t_s

    def step(self, dets: ObjectArray, t_s: float) -> ObjectArray:
        """Predict to t_s, update with detections (map frame), prune, return confirmed and coasting tracks."""
        self.predict(t_s)
        self.update(dets, t_s)
        self.prune(t_s)
        return self.tracks(t_s)

    def predict(self, t_s: float) -> None:
        """Predict every track to t_s (x' = f(x), P' = F P F^T + Q); t_s must not precede the filter time."""
        self._check_time(t_s)
        if self._t_s is not None and t_s > self._t_s and self._store.n:
            tab = self._table
            tab.x[...], tab.p[...] = kalman.predict(tab.x, tab.p, self.model, t_s - self._t_s)
        self._t_s = t_s

    def update(self, dets: ObjectArray, t_s: float, source_mask: int = 0, estimates: bool = False) -> None:
        """Associate detections (map frame) with the tracks predicted to t_s, update the matched
        tracks, spawn tracks from the unmatched detections. Several updates per cycle are allowed.

        ``estimates``: the detections are another tracker's estimates (an RSU's tracks), fused by
        the rules of the module docstring (alone: replace; shared with another estimate source:
        covariance intersection; else a Kalman position update). Tracks matched with or spawned
        by an estimate are confirmed (another tracker confirmed it).
        """
        self.predict(t_s)
        source_mask = int(source_mask)
        if source_mask < 0:
            raise ValueError(f"source bitmasks must be in [0, 2^{SOURCE_BITS}), got {source_mask}")
        # (M, B): the seen_s columns each detection's bits (its sources | source_mask) set, and their OR
        cols, union = self._store.source_columns(dets.sources, source_mask)
        if estimates:
            self._estimate_mask |= source_mask | union
        tab = self._table
        result = associate(self.config, tab, dets)
        ti, di = result.matches[:, 0], result.matches[:, 1]
        k = n_ci = 0
        if estimates and len(ti):  # pairs by rule (module docstring): k alone, n_ci to intersect, the rest
            order, k, n_ci = estimate_rules(tab.seen_s, ti, cols, di, self._store.col_values,
                                            self._intersecting_mask(), t_s, self.config.max_coast_s)
            ti, di = ti.take(order), di.take(order)
        # one initialisation, from the detection alone, for the tracks an estimate replaces and the new tracks
        spawned = result.unmatched_b
        if k or len(spawned):  # most updates start none
            x0, p0, measured = self._initial(dets, np.concatenate([di[:k], spawned]) if k else spawned)
            if k:
                replaced = ti[:k]
                tab.x[replaced], tab.p[replaced] = x0[:k], p0[:k]
                ti, di = ti[k:], di[k:]
        if len(ti):
            self._fuse(ti, di, n_ci, dets, t_s, estimates)
        self._record(result.matches[:, 0], result.matches[:, 1], dets, cols, t_s, estimates)
        if len(spawned):
            self._spawn(dets, spawned, cols, t_s, x0[k:], p0[k:], estimates, ~measured[k:])

    def _initial(self, dets: ObjectArray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x (K, n), P (K, n, n) of tracks started from the detections dets[index] alone (``MotionModel.initial``)
        and (K,) True where their velocity was measured."""
        inputs = filter_inputs(dets, index)
        x0, p0 = self.model.initial(inputs, self._prior)
        return x0, p0, inputs.velocity_measured(self._prior.speed_std_mps)

    def _intersecting_mask(self) -> int:
        """Bits of the sources whose recent update of a track makes an estimate intersect it (rule 2; int64):
        the sources that delivered estimates (``ci``), every source (``ci-all``), none (``kf``: rule 3 instead)."""
        fusion = self.config.estimate_fusion
        return self._estimate_mask if fusion == "ci" else (-1 if fusion == "ci-all" else 0)

    def _fuse(self, ti: np.ndarray, di: np.ndarray, n_ci: int, dets: ObjectArray, t_s: float, estimates: bool) -> None:
        """Matched pairs (ti, di) that no estimate replaced: covariance intersection of the first n_ci (estimates
        into a track another estimate source shares), then two-point initialisation, else a Kalman update."""
        if n_ci:
            self._intersect(ti[:n_ci], di[:n_ci], dets)
            ti, di = ti[n_ci:], di[n_ci:]
            if not len(ti):
                return
        known = dets.velocity_known()
        pair = self._second_positions(ti, di, known, t_s)
        if pair is not None:
            self._two_point(ti[pair], di[pair], dets, t_s)
            ti, di = ti[~pair], di[~pair]
        self._correct(ti, di, dets, known, velocity=not estimates)

    def prune(self, t_s: float) -> None:
        """Delete stale tracks (last update older than max_coast_s) and missed tentative tracks."""
        tab = self._table
        since_s = t_s - tab.updated_s
        tentative = tab.hits < self.config.confirm_hits
        doomed = (since_s > self.config.max_coast_s) | (tentative & (since_s > self.config.tentative_max_coast_s))
        if doomed.any():
            self._store.keep(~doomed)

    def tracks(self, t_s: float) -> ObjectArray:
        """Confirmed and coasting tracks at t_s (map frame), predicted on a copy: the filter is not changed
        (a t_s before the filter time extrapolates backwards with the motion model).

        ids, cls, z, lwh, yaw, confidence from the last detection; xy, vxy, axy, yaw_rate,
        cov_xy (position block of P) and cov_vxy (velocity covariance) from the filter; age_s
        since birth; sources (see module doc).
        """
        tab = self._table
        rows = np.flatnonzero(tab.confirmed & (t_s - tab.updated_s <= self.config.max_coast_s))
        x, p = tab.x.take(rows, axis=0), tab.p.take(rows, axis=0)  # only the columns the output needs, gathered
        if self._t_s is not None and t_s != self._t_s and len(rows):
            x, p = kalman.predict(x, p, self.model, t_s - self._t_s)
        recent = (t_s - tab.seen_s.take(rows, axis=0)) <= self.config.max_coast_s
        return ObjectArray(
            ids=tab.ids.take(rows), cls=tab.cls.take(rows), xy=x[:, :2].copy(), z=tab.z.take(rows),
            lwh=tab.lwh.take(rows, axis=0), yaw=tab.yaw.take(rows), vxy=np.array(self.model.velocity(x)),
            axy=self.model.acceleration(x), yaw_rate=self.model.yaw_rate(x), cov_xy=p[:, :2, :2].copy(),
            cov_vxy=self.model.velocity_cov(x, p), confidence=tab.confidence.take(rows),
            age_s=t_s - tab.born_s.take(rows), sources=tab.source_masks(recent),
        )

    def lifecycle(self, t_s: float) -> dict[int, str]:
        """State of every live track at t_s by id: ``tentative``, ``confirmed`` or ``coasting``."""
        tab = self._table
        confirmed = tab.confirmed
        coasting = confirmed & (tab.updated_s < t_s)
        names = np.where(coasting, "coasting", np.where(confirmed, "confirmed", "tentative"))
        return {int(i): str(n) for i, n in zip(tab.ids, names)}

    def snapshot(self) -> TrackerSnapshot:
        """Deep copy of the whole filter state."""
        return TrackerSnapshot(self._t_s, self._next_id, self._store.snapshot(), self._estimate_mask)

    def restore(self, snapshot: TrackerSnapshot) -> None:
        """Return to a snapshot (copied again, so it can be restored more than once)."""
        self._t_s, self._next_id = snapshot.t_s, snapshot.next_id
        self._store.load(snapshot.table)
        self._estimate_mask = snapshot.estimate_mask

    def _check_time(self, t_s: float) -> None:
        if self._t_s is not None and t_s < self._t_s:
            raise ValueError(f"t_s={t_s} precedes the filter time {self._t_s}; use v2i.fusion.oosm.OosmTracker")

    def _intersect(self, ti: np.ndarray, di: np.ndarray, dets: ObjectArray) -> None:
        """Covariance intersection of tracks ti with estimates di: the position, or the position and
        velocity where the estimate measured one (CV / CA with velocity_updates), one w per track
        (``covariance_intersection.ci_fuse_objects``)."""
        tab = self._table
        velocity = self.config.velocity_updates and self.config.motion in ("cv", "ca")
        ci_fuse_objects(tab.x, tab.p, ti, dets.xy, dets.cov_xy, dets.vxy, dets.cov_vxy, di, velocity)

    def _second_positions(self, ti: np.ndarray, di: np.ndarray, known: np.ndarray, t_s: float) -> np.ndarray | None:
        """(K,) True where the pair (track ti, detection di) is a two-point initialisation: the track
        has one hit, was born without a measured velocity at an earlier time, and the detection
        measures no velocity either (known (M,) False; a measured one is fused by ``_correct``).
        None where no pair is one."""
        if not self.config.two_point_init or self.config.motion not in ("cv", "ca"):
            return None
        tab = self._table
        first = tab.hits.take(ti) == 1
        if not first.any():
            return None
        pair = first & tab.velocity_prior.take(ti) & (tab.born_s.take(ti) < t_s) & ~known.take(di)
        return pair if pair.any() else None

    def _two_point(self, ti: np.ndarray, di: np.ndarray, dets: ObjectArray, t_s: float) -> None:
        """Tracks ti take their state from their birth and the second positions di (``kalman.two_point``)."""
        tab = self._table
        for born_s in np.unique(tab.born_s[ti]):
            t, d = ti[tab.born_s[ti] == born_s], di[tab.born_s[ti] == born_s]
            tab.x[t], tab.p[t] = kalman.two_point(self.model, tab.birth_x[t], tab.birth_p[t], dets.xy[d],
                                                  dets.cov_xy[d], t_s - born_s)

    def _correct(self, ti: np.ndarray, di: np.ndarray, dets: ObjectArray, known: np.ndarray,
                 velocity: bool = True) -> None:
        """Kalman update of tracks ti with detections di: position, then the measured velocity
        (known (M,)) unless ``velocity`` is off. It is off for another tracker's estimates fused into a
        track other sources update too: an estimate's velocity is its filter's, built from the same
        measurements list after list, so fusing it every list as if independent would count them
        again and again (measured: NEES 4-5 on LiDAR+RSU tracks on highway-merge)."""
        tab = self._table
        if not len(ti):
            return
        kalman.update_rows(tab.x, tab.p, ti, dets.xy, dets.cov_xy, di, 0)
        if velocity and self.config.velocity_updates and self.config.motion in ("cv", "ca"):
            # sources that estimate velocity (tracking RSUs, CenterPoint) update it too:
            # H = [0 I_2 0], R = the detection's velocity covariance
            v = known.take(di)
            n_v = int(np.count_nonzero(v))
            if n_v == len(v):
                kalman.update_rows(tab.x, tab.p, ti, dets.vxy, dets.cov_vxy, di, 2)
            elif n_v:
                kalman.update_rows(tab.x, tab.p, ti[v], dets.vxy, dets.cov_vxy, di[v], 2)

    def _record(self, ti: np.ndarray, di: np.ndarray, dets: ObjectArray, cols: np.ndarray, t_s: float,
                estimates: bool) -> None:
        """Bookkeeping of matched tracks ti (``track_table.record_matches``): class, shape, confidence,
        hits, confirmation and update times; cols (M, B) the seen_s columns of each detection's sources.
        Box size, height and heading come from the most precise recent detection: a coarse RSU box never
        overwrites the fresh LiDAR box of the same cycle."""
        if not len(ti):
            return
        tab = self._table
        record_matches(tab.cls, tab.z, tab.lwh, tab.yaw, tab.shape_var, tab.shape_s, tab.confidence, tab.hits,
                       tab.confirmed, tab.updated_s, tab.seen_s, ti, di, dets.cls, dets.z, dets.lwh, dets.yaw,
                       dets.cov_xy, dets.confidence, cols, t_s, estimates, self.config.confirm_hits,
                       self.config.shape_hold_s)

    def _spawn(self, dets: ObjectArray, index: np.ndarray, cols: np.ndarray, t_s: float, x: np.ndarray,
               p: np.ndarray, estimates: bool, velocity_prior: np.ndarray) -> None:
        """New tracks from the detections dets[index], initial state x (n, dim), P (n, dim, dim): tentative,
        or confirmed when they are another tracker's estimates; velocity_prior (n,) as in TrackTable;
        cols (M, B) the seen_s columns of each detection's sources. The box shape's variance is the trace
        of the position covariance, its heading wrapped to [-pi, pi) (as ``record_matches``)."""
        n = len(index)
        if not n:
            return
        rows, new = self._store.extend(n)  # the store's columns, and the slice of the n new rows in them
        rows.ids[new] = np.arange(self._next_id, self._next_id + n)
        self._next_id += n
        rows.x[new], rows.p[new], rows.birth_x[new], rows.birth_p[new] = x, p, x, p
        rows.cls[new], rows.z[new] = dets.cls.take(index), dets.z.take(index)
        rows.lwh[new] = dets.lwh.take(index, axis=0)
        rows.yaw[new], rows.confidence[new] = wrap_angle(dets.yaw.take(index)), dets.confidence.take(index)
        rows.hits[new], rows.born_s[new], rows.updated_s[new], rows.shape_s[new] = 1, t_s, t_s, t_s
        rows.seen_s[new] = np.where(cols.take(index, axis=0), t_s, -np.inf)
        c = dets.cov_xy.take(index, axis=0)
        rows.shape_var[new] = c[:, 0, 0] + c[:, 1, 1]
        rows.confirmed[new], rows.velocity_prior[new] = estimates or self.config.confirm_hits <= 1, velocity_prior


def filter_inputs(dets: ObjectArray, index: np.ndarray) -> kalman.Measured:
    """Filter inputs of the detections dets[index] (an index array, or a boolean mask)."""
    index = np.asarray(index)
    if index.dtype == bool:
        index = np.flatnonzero(index)
    return kalman.Measured(dets.xy.take(index, axis=0), dets.cov_xy.take(index, axis=0), dets.vxy.take(index, axis=0),
                           dets.axy.take(index, axis=0), dets.yaw[index], dets.yaw_rate[index],
                           dets.cov_vxy.take(index, axis=0))
