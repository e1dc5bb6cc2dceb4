"""Multi-object tracker over the batched Kalman filters of ``fusion.kalman`` (map frame).

Cycle (seed 001, two updates per cycle): ``predict(t)``, ``update(lidar, t, SOURCE_VEHICLE)``,
``update(rsu, t, SOURCE_RSU)`` for each RSU list, ``prune(t)``, ``tracks(t)``; ``step(dets, t)``
does one predict / update / prune / tracks. Times are seconds on any fixed origin; the
filter never goes back in time (``fusion.oosm.OosmTracker`` re-filters late measurements).

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
minimum-cost one-to-one assignment (scipy ``linear_sum_assignment``) with cost
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
   twice. CI (``fusion.covariance_intersection``): the Kalman update with P / w and
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
import shapely

from . import kalman
from .association import Assignment, assign_sparse
from .covariance_intersection import ci_update, ci_weights
from .frames import wrap_angle
from .geometry import box_polygons
from .objects import ObjectArray

SOURCE_BITS = 63  # source bitmasks are int64: bit 0 own vehicle, bits 1..62 one per RSU / peer slot
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


@dataclass
class TrackTable:
    """Columns of N tracks: filter state x (N, n), P (N, n, n); ids, cls (N,); z (N,) m,
    lwh (N, 3) m, yaw (N,) rad, confidence (N,) of the last detection; hits (N,);
    born_s, updated_s (N,) s; seen_s (N, SOURCE_BITS) s, last update per source bit (-inf never);
    shape_var (N,) m^2, shape_s (N,) s: position variance and time of the detection the box shape came from;
    confirmed (N,) bool (see the life cycle); birth_x (N, n), birth_p (N, n, n): the state the track was
    born with; velocity_prior (N,) bool: born without a measured velocity (two-point initialisation)."""

    x: np.ndarray
    p: np.ndarray
    ids: np.ndarray
    cls: np.ndarray
    z: np.ndarray
    lwh: np.ndarray
    yaw: np.ndarray
    confidence: np.ndarray
    hits: np.ndarray
    born_s: np.ndarray
    updated_s: np.ndarray
    seen_s: np.ndarray
    shape_var: np.ndarray
    shape_s: np.ndarray
    confirmed: np.ndarray
    birth_x: np.ndarray
    birth_p: np.ndarray
    velocity_prior: np.ndarray

    @classmethod
    def empty(cls, dim_x: int) -> TrackTable:
        z1, no = np.zeros(0), np.zeros(0, bool)
        x, p = np.zeros((0, dim_x)), np.zeros((0, dim_x, dim_x))
        return cls(x, p, np.zeros(0, np.int64), np.zeros(0, np.int64), z1, np.zeros((0, 3)), z1, z1,
                   np.zeros(0, np.int64), z1, z1, np.zeros((0, SOURCE_BITS)), z1, z1, no, x.copy(), p.copy(), no.copy())

    def __len__(self) -> int:
        return len(self.x)

    def take(self, index) -> TrackTable:
        return TrackTable(*(column[index] for column in self.columns()))

    def copy(self) -> TrackTable:
        return TrackTable(*(column.copy() for column in self.columns()))

    def append(self, other: TrackTable) -> TrackTable:
        return TrackTable(*(np.concatenate([a, b]) for a, b in zip(self.columns(), other.columns())))

    def columns(self):
        """The column arrays in field order (the instance dict holds exactly the fields, in order)."""
        return vars(self).values()


@dataclass(frozen=True)
class TrackerSnapshot:
    """The whole filter state of a Tracker (deep copies): time, next id, track table, and the
    source bits that have delivered estimates (SOURCE_BITS,) bool."""

    t_s: float | None
    next_id: int
    table: TrackTable
    estimate_bits: np.ndarray


def compatible_classes(track_cls: np.ndarray, det_cls: np.ndarray) -> np.ndarray:
    """True where classes are equal or either is UNKNOWN (0); paired arrays or broadcast (N, 1), (1, M)."""
    return (track_cls == det_cls) | (track_cls == 0) | (det_cls == 0)


@dataclass(frozen=True)
class GatedPairs:
    """K (track, detection) pairs inside the gate and class-compatible, with their cost (K,)."""

    track: np.ndarray
    det: np.ndarray
    cost: np.ndarray


def _trace2(c: np.ndarray) -> np.ndarray:
    """Trace of 2 x 2 covariances (K, 2, 2): an upper bound of their largest eigenvalue."""
    return c[:, 0, 0] + c[:, 1, 1]


def _candidates(config: TrackerConfig, table: TrackTable, dets: ObjectArray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs that may pass the gate: tracks near the detections' bounding box, then a bound on each pair.

    Distance gate: |y| <= gate_m. Mahalanobis gate: d2 = y^T S^-1 y >= |y|^2 / lambda_max(S) and
    lambda_max(S) <= tr(S) = tr(H P H^T) + tr(R), so a pair with |y|^2 > chi2 (tr P_xy + tr R) fails.
    Either gate: a pair that passes one of the two bounds, within gate_max_m.
    """
    if not len(table) or not len(dets):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    reach_m = config.gate_m
    if config.gate != "distance":
        lam_p, lam_r = _trace2(table.p[:, :2, :2]), _trace2(dets.cov_xy)
        reach_m = np.sqrt(config.gate_chi2 * (lam_p.max() + lam_r.max()))
        if config.gate == "either":
            reach_m = min(max(reach_m, config.gate_m), config.gate_max_m)
    (x_lo, y_lo), (x_hi, y_hi) = dets.xy.min(axis=0) - reach_m, dets.xy.max(axis=0) + reach_m
    tx, ty = table.x[:, 0], table.x[:, 1]
    rows = np.flatnonzero((tx >= x_lo) & (tx <= x_hi) & (ty >= y_lo) & (ty <= y_hi))
    dx = np.subtract.outer(table.x[rows, 0], dets.xy[:, 0])
    dy = np.subtract.outer(table.x[rows, 1], dets.xy[:, 1])
    r2 = dx * dx + dy * dy
    near_distance = r2 <= config.gate_m**2 if config.gate != "mahalanobis" else False
    near_mahalanobis = r2 <= config.gate_chi2 * np.add.outer(lam_p[rows], lam_r) if config.gate != "distance" else False
    if config.gate == "either":
        near_mahalanobis &= r2 <= config.gate_max_m**2
    ti, di = np.nonzero(near_distance | near_mahalanobis)
    ti = rows[ti]
    keep = compatible_classes(table.cls[ti], dets.cls[di])
    return ti[keep], di[keep]


def gated_pairs(config: TrackerConfig, table: TrackTable, dets: ObjectArray) -> GatedPairs:
    """Class-compatible pairs inside the configured gate with the configured cost (see module doc)."""
    ti, di = _candidates(config, table, dets)
    y = dets.xy[di] - table.x[ti, :2]
    dist = np.hypot(y[:, 0], y[:, 1])
    if config.gate != "distance" or config.cost == "mahalanobis":
        d2 = kalman.mahalanobis_sq_pairs(table.x[ti], table.p[ti], dets.xy[di], dets.cov_xy[di])
    if config.gate == "distance":
        inside = dist <= config.gate_m
    elif config.gate == "mahalanobis":
        inside = d2 <= config.gate_chi2
    else:
        inside = (dist <= config.gate_m) | ((d2 <= config.gate_chi2) & (dist <= config.gate_max_m))
    ti, di = ti[inside], di[inside]
    if config.cost == "distance":
        cost = dist[inside]
    elif config.cost == "mahalanobis":
        cost = d2[inside]
    else:  # 1 - BEV IoU of the predicted box (last detected size and yaw) and the detected box
        a = np.column_stack([table.x[ti, :2], table.lwh[ti, :2], table.yaw[ti]])
        cost = 1.0 - paired_bev_iou(a, np.column_stack([dets.xy[di], dets.lwh[di, :2], dets.yaw[di]]))
    return GatedPairs(ti, di, cost)


def paired_bev_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU (K,) of paired BEV boxes a[k], b[k] (K, 5) [x, y, l, w, yaw]: |A n B| / (|A| + |B| - |A n B|).

    Polygons from ``fusion.geometry``; one intersection per pair instead of a whole matrix.
    """
    if not len(a):
        return np.zeros(0)
    inter = shapely.area(shapely.intersection(box_polygons(a), box_polygons(b)))
    union = a[:, 2] * a[:, 3] + b[:, 2] * b[:, 3] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def assign_pairs(pairs: GatedPairs, n_tracks: int, n_dets: int) -> Assignment:
    """Minimum-cost one-to-one matching among the gated pairs (``association.assign_sparse``:
    per connected component of the gated graph, scipy linear_sum_assignment for those of more than one pair)."""
    return assign_sparse(pairs.track, pairs.det, pairs.cost, n_tracks, n_dets)


def associate(config: TrackerConfig, table: TrackTable, dets: ObjectArray) -> Assignment:
    """Gate, cost and assign the detections to the tracks (indices into table and dets)."""
    return assign_pairs(gated_pairs(config, table, dets), len(table), len(dets))


def association_cost(config: TrackerConfig, table: TrackTable, dets: ObjectArray) -> np.ndarray:
    """Dense cost (N tracks, M detections) of the gated pairs; inf elsewhere."""
    pairs = gated_pairs(config, table, dets)
    cost = np.full((len(table), len(dets)), np.inf)
    cost[pairs.track, pairs.det] = pairs.cost
    return cost


def assign_gated(cost: np.ndarray) -> Assignment:
    """Minimum-cost one-to-one matching among the finite entries of a dense cost (N, M)."""
    ti, di = np.nonzero(np.isfinite(cost))
    return assign_pairs(GatedPairs(ti, di, cost[ti, di]), *cost.shape)


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
    """Multi-object tracker; see the module docstring for the cycle, gating and life cycle."""

    def __init__(self, config: TrackerConfig = TrackerConfig()):
        self.config = config
        self.model = config.motion_model()
        self._prior = config.prior()
        self._next_id = 1
        self._t_s: float | None = None
        self._table = TrackTable.empty(self.model.dim_x)
        self._estimate_bits = np.zeros(SOURCE_BITS, bool)  # bits that have delivered estimates

    def __len__(self) -> int:
        return len(self._table)

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
        if self._t_s is not None and t_s > self._t_s and len(self._table):
            self._table.x, self._table.p = kalman.predict(self._table.x, self._table.p, self.model, t_s - self._t_s)
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
        bits = source_mask_bits(np.asarray(dets.sources) | int(source_mask))
        if estimates:
            self._estimate_bits |= source_mask_bits(np.array([int(source_mask)]))[0] | bits.any(axis=0)
        result = associate(self.config, self._table, dets)
        ti, di = result.matches[:, 0], result.matches[:, 1]
        alone = self._seen_only_by(ti, bits[di], t_s) if estimates else np.zeros(len(ti), bool)
        # one initialisation, from the detection alone, for the tracks an estimate replaces and the new tracks
        start = np.concatenate([di[alone], result.unmatched_b])
        inputs = filter_inputs(dets, start)
        x0, p0 = self.model.initial(inputs, self._prior)
        k = int(alone.sum())
        self._table.x[ti[alone]], self._table.p[ti[alone]] = x0[:k], p0[:k]
        ti, di = ti[~alone], di[~alone]
        if estimates and self.config.estimate_fusion != "kf":
            shared = self._shared_with_estimates(ti, bits[di], t_s)
            shared |= self.config.estimate_fusion == "ci-all"  # every track another source shares
            self._intersect(ti[shared], di[shared], dets)
            ti, di = ti[~shared], di[~shared]
        pair = self._second_positions(ti, di, dets, t_s)
        if pair.any():
            self._two_point(ti[pair], di[pair], dets, t_s)
            ti, di = ti[~pair], di[~pair]
        self._correct(ti, di, dets, velocity=not estimates)
        self._record(result.matches[:, 0], result.matches[:, 1], dets, bits, t_s, estimates)
        measured = inputs.velocity_measured(self._prior.speed_std_mps)[k:]
        self._spawn(dets, result.unmatched_b, bits, t_s, x0[k:], p0[k:], estimates, ~measured)

    def prune(self, t_s: float) -> None:
        """Delete stale tracks (last update older than max_coast_s) and missed tentative tracks."""
        tab = self._table
        since_s = t_s - tab.updated_s
        tentative = tab.hits < self.config.confirm_hits
        doomed = (since_s > self.config.max_coast_s) | (tentative & (since_s > self.config.tentative_max_coast_s))
        if doomed.any():
            self._table = tab.take(~doomed)

    def tracks(self, t_s: float) -> ObjectArray:
        """Confirmed and coasting tracks at t_s (map frame), predicted on a copy: the filter is not changed
        (a t_s before the filter time extrapolates backwards with the motion model).

        ids, cls, z, lwh, yaw, confidence from the last detection; xy, vxy, axy, yaw_rate,
        cov_xy (position block of P) and cov_vxy (velocity covariance) from the filter; age_s
        since birth; sources (see module doc).
        """
        tab = self._table
        keep = tab.confirmed & (t_s - tab.updated_s <= self.config.max_coast_s)
        tab = tab.take(keep)
        x, p = tab.x, tab.p
        if self._t_s is not None and t_s != self._t_s and len(tab):
            x, p = kalman.predict(x, p, self.model, t_s - self._t_s)
        recent = (t_s - tab.seen_s) <= self.config.max_coast_s
        return ObjectArray(
            ids=tab.ids, cls=tab.cls, xy=x[:, :2].copy(), z=tab.z, lwh=tab.lwh, yaw=tab.yaw,
            vxy=np.array(self.model.velocity(x)), axy=self.model.acceleration(x), yaw_rate=self.model.yaw_rate(x),
            cov_xy=p[:, :2, :2].copy(), cov_vxy=self.model.velocity_cov(x, p), confidence=tab.confidence,
            age_s=t_s - tab.born_s,
            sources=(recent * _BIT_VALUES[None, :]).sum(axis=1).astype(np.int64),
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
        return TrackerSnapshot(self._t_s, self._next_id, self._table.copy(), self._estimate_bits.copy())

    def restore(self, snapshot: TrackerSnapshot) -> None:
        """Return to a snapshot (copied again, so it can be restored more than once)."""
        self._t_s, self._next_id, self._table = snapshot.t_s, snapshot.next_id, snapshot.table.copy()
        self._estimate_bits = snapshot.estimate_bits.copy()

    def _check_time(self, t_s: float) -> None:
        if self._t_s is not None and t_s < self._t_s:
            raise ValueError(f"t_s={t_s} precedes the filter time {self._t_s}; use fusion.oosm.OosmTracker")

    def _seen_only_by(self, ti: np.ndarray, bits: np.ndarray, t_s: float) -> np.ndarray:
        """(K,) True where tracks ti were updated within max_coast_s by no source outside bits (K, SOURCE_BITS)."""
        recent = (t_s - self._table.seen_s[ti]) <= self.config.max_coast_s
        return ~(recent & ~bits).any(axis=1)

    def _shared_with_estimates(self, ti: np.ndarray, bits: np.ndarray, t_s: float) -> np.ndarray:
        """(K,) True where tracks ti were updated within max_coast_s by a source outside bits
        (K, SOURCE_BITS) that has delivered estimates (rule 2 of the module docstring)."""
        recent = (t_s - self._table.seen_s[ti]) <= self.config.max_coast_s
        return (recent & ~bits & self._estimate_bits[None, :]).any(axis=1)

    def _intersect(self, ti: np.ndarray, di: np.ndarray, dets: ObjectArray) -> None:
        """Covariance intersection of tracks ti with estimates di: the position, or the position and
        velocity where the estimate measured one (CV / CA with velocity_updates), one w per track."""
        tab = self._table
        if not len(ti):
            return
        with_v = np.zeros(len(ti), bool)
        if self.config.velocity_updates and self.config.motion in ("cv", "ca"):
            with_v = dets.velocity_known()[di]
        for rows, z, r in ((~with_v, dets.xy[di], dets.cov_xy[di]), (with_v, *_position_velocity(dets, di))):
            t = ti[rows]
            if len(t):
                w = ci_weights(tab.p[t], r[rows])
                tab.x[t], tab.p[t] = ci_update(tab.x[t], tab.p[t], z[rows], r[rows], w)

    def _second_positions(self, ti: np.ndarray, di: np.ndarray, dets: ObjectArray, t_s: float) -> np.ndarray:
        """(K,) True where the pair (track ti, detection di) is a two-point initialisation: the track
        has one hit, was born without a measured velocity at an earlier time, and the detection
        measures no velocity either (a measured one is fused by ``_correct``)."""
        tab = self._table
        first = tab.hits[ti] == 1
        if not first.any() or not self.config.two_point_init or self.config.motion not in ("cv", "ca"):
            return np.zeros(len(ti), bool)
        return first & tab.velocity_prior[ti] & (tab.born_s[ti] < t_s) & ~dets.velocity_known()[di]

    def _two_point(self, ti: np.ndarray, di: np.ndarray, dets: ObjectArray, t_s: float) -> None:
        """Tracks ti take their state from their birth and the second positions di (``kalman.two_point``)."""
        tab = self._table
        for born_s in np.unique(tab.born_s[ti]):
            t, d = ti[tab.born_s[ti] == born_s], di[tab.born_s[ti] == born_s]
            tab.x[t], tab.p[t] = kalman.two_point(self.model, tab.birth_x[t], tab.birth_p[t], dets.xy[d],
                                                  dets.cov_xy[d], t_s - born_s)

    def _correct(self, ti: np.ndarray, di: np.ndarray, dets: ObjectArray, velocity: bool = True) -> None:
        """Kalman update of tracks ti with detections di: position, then the measured velocity
        unless ``velocity`` is off. It is off for another tracker's estimates fused into a track
        other sources update too: an estimate's velocity is its filter's, built from the same
        measurements list after list, so fusing it every list as if independent would count them
        again and again (measured: NEES 4-5 on LiDAR+RSU tracks on highway-merge)."""
        tab = self._table
        if not len(ti):
            return
        tab.x[ti], tab.p[ti], _ = kalman.update(tab.x[ti], tab.p[ti], dets.xy[di], dets.cov_xy[di])
        if velocity and self.config.velocity_updates and self.config.motion in ("cv", "ca"):
            # sources that estimate velocity (tracking RSUs, CenterPoint) update it too:
            # H = [0 I_2 0], R = the detection's velocity covariance
            known = dets.velocity_known()[di]
            vt, v = ti[known], di[known]
            if len(vt):
                tab.x[vt], tab.p[vt], _ = kalman.update(tab.x[vt], tab.p[vt], dets.vxy[v], dets.cov_vxy[v], first=2)

    def _record(self, ti: np.ndarray, di: np.ndarray, dets: ObjectArray, bits: np.ndarray, t_s: float,
                estimates: bool) -> None:
        """Bookkeeping of matched tracks ti: class, shape, confidence, hits, confirmation and update times."""
        tab = self._table
        tab.cls[ti] = np.where(tab.cls[ti] == 0, dets.cls[di], tab.cls[ti])  # UNKNOWN adopts a class
        self._take_shape(ti, dets, di, t_s)
        tab.confidence[ti] = dets.confidence[di]
        tab.hits[ti] += 1
        tab.confirmed[ti] |= (tab.hits[ti] >= self.config.confirm_hits) | estimates
        tab.updated_s[ti] = t_s
        seen = tab.seen_s[ti]
        seen[bits[di]] = t_s
        tab.seen_s[ti] = seen

    def _take_shape(self, ti: np.ndarray, dets: ObjectArray, di: np.ndarray, t_s: float) -> None:
        """Box size, height and heading come from the most precise recent detection: a
        detection replaces the track's shape when its position variance is no larger, or
        when the shape is older than ``shape_hold_s`` (a coarse RSU box never overwrites the
        fresh LiDAR box of the same cycle)."""
        tab = self._table
        var = _trace2(dets.cov_xy[di])
        take = (var <= tab.shape_var[ti] * 1.01) | (t_s - tab.shape_s[ti] > self.config.shape_hold_s)
        t, d = ti[take], di[take]
        tab.z[t], tab.lwh[t], tab.yaw[t] = dets.z[d], dets.lwh[d], wrap_angle(dets.yaw[d])
        tab.shape_var[t], tab.shape_s[t] = var[take], t_s

    def _spawn(self, dets: ObjectArray, index: np.ndarray, bits: np.ndarray, t_s: float, x: np.ndarray,
               p: np.ndarray, estimates: bool, velocity_prior: np.ndarray) -> None:
        """New tracks from the detections dets[index], initial state x (n, dim), P (n, dim, dim): tentative,
        or confirmed when they are another tracker's estimates; velocity_prior (n,) as in TrackTable."""
        n = len(index)
        if not n:
            return
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        born = np.full(n, t_s)
        new = TrackTable(x, p, ids, dets.cls[index].astype(np.int64), dets.z[index].astype(float),
                         dets.lwh[index].astype(float), wrap_angle(dets.yaw[index]),
                         dets.confidence[index].astype(float),
                         np.ones(n, np.int64), born, born.copy(), np.where(bits[index], t_s, -np.inf),
                         _trace2(dets.cov_xy[index]), born.copy(),
                         np.full(n, estimates or self.config.confirm_hits <= 1), x, p, velocity_prior)
        self._table = self._table.append(new)


def _position_velocity(dets: ObjectArray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """z (K, 4) = [x, y, vx, vy] and R (K, 4, 4) = blockdiag(cov_xy, cov_vxy) of dets[index]."""
    r = np.zeros((len(index), 4, 4))
    r[:, :2, :2], r[:, 2:, 2:] = dets.cov_xy[index], dets.cov_vxy[index]
    return np.column_stack([dets.xy[index], dets.vxy[index]]), r


def filter_inputs(dets: ObjectArray, index: np.ndarray) -> kalman.Measured:
    """Filter inputs of the detections dets[index]."""
    return kalman.Measured(dets.xy[index], dets.cov_xy[index], dets.vxy[index], dets.axy[index], dets.yaw[index],
                           dets.yaw_rate[index], dets.cov_vxy[index])
