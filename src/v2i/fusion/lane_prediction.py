"""Map-aware prediction: objects move along Lanelet2 lane centrelines in Frenet coordinates.

Per object matched to a lanelet (s arc length along the lane sequence, d signed lateral offset,
left positive; c(s) centreline point, t(s) / n(s) unit tangent / left normal, psi(s) heading):
    s(t) = s0 + v_s t                                  constant speed along the lane (default), or
    s(t) = s0 + v_s t + a_s t^2 / 2, frozen once v_s + a_s t = 0   (``use_acceleration``: no reversing)
    d(t) = d0 exp(-t / tau_d)                          (tau_d = inf, the default, keeps the offset)
    xy(t) = xy0 + F(s(t), d(t)) - F(s0, d0),  F(s, d) = c(s) + d n(s)    (exact at t = 0)
    yaw(t) = psi(s(t)) + (yaw0 - psi(s0)) exp(-t / tau_psi)   (the heading offset to the lane relaxes)
    v(t) = v_s(t) t(s(t)) + d'(t) n(s(t)),   v_s = v0 . t(s0),  a_s = a0 . t(s0)
psi(s) is the heading of the central chord c(s + 0.5 m) - c(s - 0.5 m), smooth across the vertices
of sampled arcs.
The lateral velocity v0 . n(s0) is dropped: lane changes are not predicted.

Matching: an object of a road class (``map_classes``) is matched to the centreline segment with
the lowest cost (dist / half_width)^2 + (dpsi / heading_scale)^2 among those it lies on (within
the lanelet's half width + margin, not before its first / after its last vertex) whose heading
agrees with its own (velocity direction when moving, else yaw) within ``heading_tolerance_rad``.
Unmatched objects (pedestrians, unknown class, off the road, wrong way) get constant velocity,
exactly ``v2i.fusion.motion.predict_cv``.

Successors (choice documented): the path is a lane sequence from the matched lanelet through the
routing graph's successors (no lane changes), ``lookahead_m`` beyond it; past the end of the map
it continues straight. Where a lanelet has several successors each gets a prior
p_k = exp(-(dpsi_k / turn_sigma)^2) / sum_j exp(-(dpsi_j / turn_sigma)^2), dpsi_k its total heading
change: the straightest is the most likely (turn_sigma = 1 rad: 0.92 straight vs 0.08 for a
90 deg turn). ``predict_objects`` and ``predict_trajectories`` follow the most probable sequence;
``predict_hypotheses`` returns up to ``max_hypotheses`` sequences with their probabilities. An
object shows its branch once it is on a connector (it then matches the connector whose heading
agrees), so a turning vehicle is predicted straight until it turns in, and along its arc after.

Cost: centrelines are cached at construction as flat numpy polylines with cumulative arc length,
one per lane sequence, stacked with disjoint arc-length keys, so that a call is one segment match
(a compiled loop: ``v2i.fusion.lane_match``) and one ``searchsorted`` for all objects and steps; lanelet2 is only used
to load the map and build the routing graph.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from schemas.classes import ObjectClass

from v2i.core.files import MiB, check_regular
from v2i.core.frames import wrap_angle
from v2i.fusion.lane_match import chain_frame_points, match_segments
from v2i.fusion.motion import predict_cv
from v2i.core.objects import ObjectArray

# A Lanelet2 OSM map: a bundled intersection is 110 kB, a city district some MB.
MAP_LIMIT_BYTES = 64 * MiB
EXTEND_M = 1000.0  # straight extension before / after every lane sequence
HEADING_BASE_M = 0.5  # half base of the central chord giving the lane heading
ROAD_CLASSES = (ObjectClass.CAR, ObjectClass.VAN, ObjectClass.TRUCK, ObjectClass.BUS, ObjectClass.CYCLIST,
                ObjectClass.MOTORCYCLE)


@dataclass(frozen=True)
class LanePredictionConfig:
    heading_tolerance_rad: float = np.pi / 4  # match only lanes within this of the object's heading
    lateral_margin_m: float = 0.5  # ... and within the lane's half width plus this
    heading_scale_rad: float = 0.2  # match cost (dist / half_width)^2 + (dpsi / scale)^2
    min_speed_for_heading_mps: float = 1.0  # slower: match on yaw, not on the velocity direction
    lateral_decay_s: float = np.inf  # tau_d: d(t) = d0 exp(-t / tau_d); inf keeps the offset
    heading_decay_s: float = 1.0  # tau_psi: the yaw offset to the lane relaxes
    use_acceleration: bool = False  # constant acceleration along the lane (else constant speed)
    turn_sigma_rad: float = 1.0  # branch prior p_k ∝ exp(-(dpsi_k / sigma)^2)
    lookahead_m: float = 300.0  # lane sequences reach this far past the matched lanelet
    max_hypotheses: int = 3  # lane sequences kept per lanelet, most probable first
    map_classes: tuple[int, ...] = field(default_factory=lambda: tuple(int(c) for c in ROAD_CLASSES))


@dataclass(frozen=True)
class LaneGeometry:
    """Lanes as plain arrays: centreline (K_i, 2) m in driving direction, half widths (K_i - 1, 2)
    [left, right] m per segment, successor lane indices, names."""

    names: tuple[str, ...]
    centres: tuple[np.ndarray, ...]
    half_widths: tuple[np.ndarray, ...]
    successors: tuple[tuple[int, ...], ...]


def polyline_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit tangents (K-1, 2), segment lengths (K-1,) and cumulative arc length (K,) of (K, 2)."""
    seg = np.diff(points, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    return seg / length[:, None], length, np.concatenate([[0.0], np.cumsum(length)])


def point_polyline_distance(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance (M,) m from points (M, 2) to a polyline (K, 2)."""
    t, length, _ = polyline_frame(poly)
    rel = p[:, None, :] - poly[None, :-1]
    u = np.clip(np.einsum("msk,sk->ms", rel, t), 0.0, length)
    return np.min(np.linalg.norm(rel - u[..., None] * t, axis=2), axis=1)


def lane_geometry_from_lanelet_map(lmap, participant: str = "Vehicle") -> LaneGeometry:
    """Centrelines, half widths and routing-graph successors (no lane changes) of every lanelet."""
    import lanelet2

    rules = lanelet2.traffic_rules.create(lanelet2.traffic_rules.Locations.Germany,
                                          getattr(lanelet2.traffic_rules.Participants, participant))
    graph = lanelet2.routing.RoutingGraph(lmap, rules)
    lanelets = sorted(lmap.laneletLayer, key=lambda ll: ll.id)
    index = {ll.id: i for i, ll in enumerate(lanelets)}

    def xy(line) -> np.ndarray:
        return np.array([[p.x, p.y] for p in line], dtype=float)

    centres, half_widths = [], []
    for ll in lanelets:
        c = xy(ll.centerline)
        c = c[np.concatenate([[True], np.hypot(*np.diff(c, axis=0).T) > 1e-6])]  # no zero-length segments
        mid = 0.5 * (c[1:] + c[:-1])
        half_widths.append(np.column_stack([point_polyline_distance(mid, xy(ll.leftBound)),
                                            point_polyline_distance(mid, xy(ll.rightBound))]))
        centres.append(c)
    return LaneGeometry(
        names=tuple(ll.attributes["name"] if "name" in ll.attributes else str(ll.id) for ll in lanelets),
        centres=tuple(centres), half_widths=tuple(half_widths),
        successors=tuple(tuple(index[f.id] for f in graph.following(ll, False)) for ll in lanelets),
    )


def branch_priors(geometry: LaneGeometry, sigma_rad: float) -> list[np.ndarray]:
    """Per lane, prior probability of each successor: p_k ∝ exp(-(dpsi_k / sigma)^2)."""
    turn = []
    for c in geometry.centres:
        t, _, _ = polyline_frame(c)
        turn.append(abs(wrap_angle(np.arctan2(t[-1, 1], t[-1, 0]) - np.arctan2(t[0, 1], t[0, 0]))))
    priors = []
    for succ in geometry.successors:
        w = np.exp(-(np.array([turn[k] for k in succ]) / sigma_rad) ** 2)
        priors.append(w / w.sum() if len(succ) else w)
    return priors


def lane_sequences(geometry: LaneGeometry, priors: list[np.ndarray], start: int, lookahead_m: float,
                   lengths_m: np.ndarray | None = None) -> list[tuple[tuple[int, ...], float]]:
    """Every successor sequence from lane ``start`` reaching ``lookahead_m`` past its end (or a
    dead end), with its probability (product of branch priors), most probable first."""
    lengths = [polyline_frame(c)[2][-1] for c in geometry.centres] if lengths_m is None else lengths_m
    done, stack = [], [((start,), 1.0, lookahead_m)]
    while stack:
        seq, prob, left_m = stack.pop()
        succ = [k for k in geometry.successors[seq[-1]] if k not in seq]
        if left_m <= 0.0 or not succ:
            done.append((seq, prob))
            continue
        p_succ = priors[seq[-1]]
        for k, p in zip(geometry.successors[seq[-1]], p_succ):
            if k in succ:
                stack.append((seq + (k,), prob * float(p), left_m - lengths[k]))
    return sorted(done, key=lambda item: -item[1])


@dataclass(frozen=True)
class _Segments:
    """All lane centreline segments (S), for matching."""

    a: np.ndarray  # (S, 2) start point m
    t: np.ndarray  # (S, 2) unit tangent
    length: np.ndarray  # (S,) m
    psi: np.ndarray  # (S,) heading rad
    lane: np.ndarray  # (S,) lane index
    s0: np.ndarray  # (S,) arc length of the segment start along its lane, m
    half_w: np.ndarray  # (S, 2) [left, right] m
    first: np.ndarray  # (S,) bool: first segment of its lane
    last: np.ndarray  # (S,) bool
    mid: np.ndarray  # (S, 2) midpoint a + t length / 2, m
    reach_sq: np.ndarray  # (S,) m^2: (length / 2 + the wider half width + REACH_SLACK_M)^2 (``LanePredictor.match``)


REACH_SLACK_M = 1.0  # beyond rounding: a segment's candidate disc is a bound, not a test


def segment_tables(seg: _Segments) -> tuple[np.ndarray, np.ndarray]:
    """The segments as ``lane_match.match_segments`` reads them: floats (S, 12) and lane, first, last (S, 3)."""
    floats = np.column_stack([seg.mid, seg.reach_sq, seg.a, seg.t, seg.length, seg.half_w, seg.psi, seg.s0])
    return np.ascontiguousarray(floats, dtype=np.float64), np.column_stack([seg.lane, seg.first, seg.last]).astype(np.int64)


def _segments(geometry: LaneGeometry) -> _Segments:
    parts = []
    for i, (c, hw) in enumerate(zip(geometry.centres, geometry.half_widths)):
        t, length, cum = polyline_frame(c)
        n = len(length)
        parts.append((c[:-1], t, length, np.full(n, i), cum[:-1], hw, np.arange(n) == 0, np.arange(n) == n - 1))
    a, t, length, lane, s0, hw, first, last = (np.concatenate(col) for col in zip(*parts))
    return _Segments(a, t, length, np.arctan2(t[:, 1], t[:, 0]), lane, s0, hw, first, last,
                     a + 0.5 * length[:, None] * t, (0.5 * length + hw.max(axis=1) + REACH_SLACK_M) ** 2)


@dataclass(frozen=True)
class _Chains:
    """Lane sequences (C) as one flat polyline table (M vertices) with disjoint arc-length keys."""

    vertex: np.ndarray  # (M, 2) m
    tangent: np.ndarray  # (M, 2) unit tangent of the segment starting at the vertex
    cum: np.ndarray  # (M,) arc length along the sequence, 0 at the start of its first lane
    key: np.ndarray  # (M,) cum + chain * span: sorted over the whole table
    first: np.ndarray  # (C,) index of the first vertex
    last: np.ndarray  # (C,) index of the last vertex
    span: float
    of_lane: np.ndarray  # (L, H) chain indices per start lane, most probable first, -1 padded
    prob: np.ndarray  # (L, H) their probabilities, 0 padded


def _chain_polyline(geometry: LaneGeometry, seq: tuple[int, ...]) -> np.ndarray:
    """Centreline (K, 2) of a lane sequence, extended straight by EXTEND_M at both ends."""
    pts = np.vstack([geometry.centres[seq[0]]] + [geometry.centres[k][1:] for k in seq[1:]])
    t0, _, _ = polyline_frame(pts[:2])
    t1, _, _ = polyline_frame(pts[-2:])
    return np.vstack([pts[0] - EXTEND_M * t0[0], pts, pts[-1] + EXTEND_M * t1[0]])


def _chains(geometry: LaneGeometry, cfg: LanePredictionConfig) -> _Chains:
    priors = branch_priors(geometry, cfg.turn_sigma_rad)
    lengths = np.array([polyline_frame(c)[2][-1] for c in geometry.centres])
    per_lane = [lane_sequences(geometry, priors, i, cfg.lookahead_m, lengths)[: cfg.max_hypotheses]
                for i in range(len(geometry.centres))]
    polylines = [_chain_polyline(geometry, seq) for seqs in per_lane for seq, _ in seqs]
    frames = [polyline_frame(p) for p in polylines]
    span = 2.0 * max(cum[-1] for _, _, cum in frames) + 1.0
    counts = np.array([len(p) for p in polylines])
    last = np.cumsum(counts) - 1
    cum = np.concatenate([c - EXTEND_M for _, _, c in frames])
    chain_of_vertex = np.repeat(np.arange(len(polylines)), counts)
    h = max(len(s) for s in per_lane)
    of_lane, prob = np.full((len(per_lane), h), -1), np.zeros((len(per_lane), h))
    k = 0
    for i, seqs in enumerate(per_lane):
        for j, (_, p) in enumerate(seqs):
            of_lane[i, j], prob[i, j] = k, p
            k += 1
    return _Chains(
        vertex=np.vstack(polylines), tangent=np.vstack([np.vstack([t, t[-1:]]) for t, _, _ in frames]),
        cum=cum, key=cum + chain_of_vertex * span, first=last - counts + 1, last=last, span=span,
        of_lane=of_lane, prob=prob,
    )


def chain_points(chains: _Chains, chain: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Centreline points c(s) (P, T, 2) m at arc lengths s (P, T) m on chains (P,)."""
    j = np.searchsorted(chains.key, s + (chain * chains.span)[:, None], side="right") - 1
    j = np.clip(j, chains.first[chain][:, None], chains.last[chain][:, None] - 1)
    return chains.vertex[j] + (s - chains.cum[j])[..., None] * chains.tangent[j]


def chain_frame(chains: _Chains, chain: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centreline points (P, T, 2) m and headings (P, T) rad at arc lengths s (P, T) on chains (P,).

    Heading of the central chord psi(s) = atan2(c(s + b) - c(s - b)), b = HEADING_BASE_M: exact on
    straights and circles, and smooth across a sampled arc's vertices (a segment's own heading
    would jump by the sampling step there).
    """
    t = s.shape[1]  # the three sets of points in one compiled lookup: chain_points of [s, s + b, s - b]
    points = np.empty((len(chain), 3 * t, 2))
    chain_frame_points(chains.key, chains.first, chains.last, chains.vertex, chains.cum, chains.tangent, chains.span,
                       chain, s, HEADING_BASE_M, points)
    ahead, behind = points[:, t:2 * t], points[:, 2 * t:]
    return points[:, :t], np.arctan2(ahead[..., 1] - behind[..., 1], ahead[..., 0] - behind[..., 0])


def propagate_along(s0, v0, a0, t, use_acceleration: bool) -> tuple[np.ndarray, np.ndarray]:
    """Arc length s (N, T) m and speed (N, T) m/s at times t (N, T) s from s0, v0, a0 (N,).

    CV: s = s0 + v0 t. CA: s = s0 + v0 t' + a0 t'^2 / 2, v = v0 + a0 t', t' = min(t, -v0 / a0)
    when braking (a0 < 0): the object stops instead of reversing.
    """
    s0, v0, a0 = (np.asarray(x, dtype=float)[:, None] for x in (s0, v0, a0))
    if not use_acceleration:
        return s0 + v0 * t, np.broadcast_to(v0, t.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_stop = np.where(a0 < 0.0, np.maximum(-v0 / a0, 0.0), np.inf)
    te = np.minimum(t, t_stop)
    return s0 + v0 * te + 0.5 * a0 * te**2, v0 + a0 * te


@lru_cache(maxsize=8)
def _step_times(horizon_s: float, step_s: float) -> np.ndarray:
    """(T,) s: step_s, 2 step_s, ..., T step_s with T = round(horizon_s / step_s) (read-only, kept)."""
    times = step_s * np.arange(1, round(horizon_s / step_s) + 1)
    times.flags.writeable = False
    return times


def _kinematics(objs: ObjectArray, rows: np.ndarray) -> SimpleNamespace:
    """The columns ``LanePredictor._frenet`` reads (xy, vxy, axy, yaw) of some objects' rows."""
    return SimpleNamespace(**{name: getattr(objs, name).take(rows, axis=0) for name in ("xy", "vxy", "axy", "yaw")})


class LanePredictor:
    """Lane-following predictor over one map (see the module docstring for the model)."""

    def __init__(self, geometry: LaneGeometry, config: LanePredictionConfig | None = None):
        self.geometry = geometry
        self.config = config or LanePredictionConfig()
        self._seg = _segments(geometry)
        self._chains = _chains(geometry, self.config)
        self._map_classes = np.asarray(self.config.map_classes, dtype=np.int64)
        self._map_class_set = frozenset(self._map_classes.tolist())  # match's np.isin, for few objects
        self._seg_table, self._seg_index = segment_tables(self._seg)
        self._match_rules = np.array([self.config.lateral_margin_m, self.config.heading_tolerance_rad,
                                      self.config.heading_scale_rad])

    @classmethod
    def from_lanelet_map(cls, lmap, config: LanePredictionConfig | None = None) -> LanePredictor:
        return cls(lane_geometry_from_lanelet_map(lmap), config)

    @classmethod
    def from_osm(cls, path: str | Path, origin_lat_deg: float, origin_lon_deg: float,
                 config: LanePredictionConfig | None = None) -> LanePredictor:
        """Load a Lanelet2 OSM map projected local-cartesian about the origin (x east, y north, m);
        a regular file of at most ``MAP_LIMIT_BYTES`` (FileRefused otherwise; Lanelet2 opens the path
        itself, after this check)."""
        import lanelet2
        from lanelet2.projection import LocalCartesianProjector

        check_regular(path, MAP_LIMIT_BYTES, "Lanelet2 map")
        proj = LocalCartesianProjector(lanelet2.io.Origin(origin_lat_deg, origin_lon_deg))
        return cls.from_lanelet_map(lanelet2.io.load(str(path), proj), config)

    def match(self, objs: ObjectArray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Lane index (N,) (-1: unmatched), arc length s0 (N,) m and lateral offset d0 (N,) m.

        The lowest cost over every (object, segment) pair, first segment on a tie. Only pairs whose
        object lies within sqrt(``reach_sq``) of the segment's midpoint can pass the lateral test
        (distance to the segment <= half width + margin, and |p - mid| <= that distance + length / 2):
        the others cost inf without being computed. The pairs in one compiled loop
        (``v2i.fusion.lane_match``: the numpy expression's operations, bit for bit); the headings here.
        """
        cfg = self.config
        n = len(objs)
        lane, s0, d0 = np.empty(n, dtype=np.int64), np.empty(n), np.empty(n)
        if n == 0:
            return lane, s0, d0
        vxy = objs.vxy
        moving = np.hypot(vxy[:, 0], vxy[:, 1]) > cfg.min_speed_for_heading_mps
        heading = np.where(moving, np.arctan2(vxy[:, 1], vxy[:, 0]), objs.yaw)
        road = np.array([c in self._map_class_set for c in objs.cls.tolist()], dtype=bool)  # np.isin
        match_segments(objs.xy, heading, road, self._seg_table, self._seg_index, self._match_rules, lane, s0, d0)
        return lane, s0, d0

    def _frenet(self, objs: ObjectArray, chain: np.ndarray, s0, d0, t: np.ndarray,
                motion: bool = True) -> dict[str, np.ndarray]:
        """Predicted xy (P, T, 2), yaw (P, T), and with ``motion`` vxy (P, T, 2) and lane heading
        change dpsi (P, T), for objects (already restricted to P rows: any holder of their xy, vxy, axy and yaw
        columns) on ``chain`` (P,) at times t (P, T) s."""
        cfg = self.config
        n = len(s0)
        _, psi0 = chain_frame(self._chains, chain, s0[:, None])
        t0 = np.stack([np.cos(psi0[:, 0]), np.sin(psi0[:, 0])], axis=1)
        v_s = np.sum(objs.vxy * t0, axis=1)  # v_s = v . t(s0)
        a_s = np.sum(objs.axy * t0, axis=1) if cfg.use_acceleration else np.zeros(n)
        tt = np.concatenate([np.zeros((n, 1)), t], axis=1)  # column 0: t = 0
        s, v = propagate_along(s0, v_s, a_s, tt, cfg.use_acceleration)
        if cfg.lateral_decay_s == np.inf:  # exp(-t / inf) = exp(-0) = 1 and d0 * 1 = d0: the column, broadcast
            d = d0[:, None]
        else:
            d = d0[:, None] * np.exp(-tt / cfg.lateral_decay_s)  # d(t) = d0 exp(-t / tau_d)
        c, psi = chain_frame(self._chains, chain, s)
        cos_psi, sin_psi = np.cos(psi), np.sin(psi)
        normal = np.stack([-sin_psi, cos_psi], axis=-1)
        f = c + d[..., None] * normal  # F(s, d) = c(s) + d n(s)
        offset = wrap_angle(objs.yaw - psi[:, 0])[:, None] * np.exp(-tt / cfg.heading_decay_s)
        out = {
            "xy": objs.xy[:, None, :] + (f - f[:, :1])[:, 1:],
            "yaw": wrap_angle(psi + offset)[:, 1:],  # yaw = psi(s) + (yaw0 - psi(s0)) exp(-t / tau_psi)
        }
        if motion:
            tan = np.stack([cos_psi, sin_psi], axis=-1)
            out["vxy"] = (v[..., None] * tan + (-d / cfg.lateral_decay_s)[..., None] * normal)[:, 1:]
            out["dpsi"] = wrap_angle(psi - psi[:, :1])[:, 1:]
        return out

    def predict_objects(self, objs: ObjectArray, dt_s) -> ObjectArray:
        """Objects dt_s (scalar or (N,) s) later along their lanes; a drop-in for ``predict_cv``.

        Unmatched rows are exactly ``predict_cv``. Matched rows get new xy, yaw, vxy and axy
        (rotated with the lane; zero once a braking object has stopped); covariances unchanged.
        """
        out = predict_cv(objs, dt_s)
        lane, s0, d0 = self.match(objs)
        idx = np.flatnonzero(lane >= 0)
        if len(idx) == 0:
            return out
        dt = np.broadcast_to(np.asarray(dt_s, dtype=float), (len(objs),))[idx, None]
        sub = objs.take(idx)
        p = self._frenet(sub, self._chains.of_lane[lane[idx], 0], s0[idx], d0[idx], dt)
        c, s = np.cos(p["dpsi"][:, 0]), np.sin(p["dpsi"][:, 0])
        axy = np.stack([c * sub.axy[:, 0] - s * sub.axy[:, 1], s * sub.axy[:, 0] + c * sub.axy[:, 1]], axis=1)
        if self.config.use_acceleration:
            axy = np.where((np.hypot(*p["vxy"][:, 0].T) > 0.0)[:, None], axy, 0.0)
        xy, yaw, vxy, axy_out = out.xy.copy(), out.yaw.copy(), out.vxy.copy(), out.axy.copy()
        xy[idx], yaw[idx], vxy[idx], axy_out[idx] = p["xy"][:, 0], p["yaw"][:, 0], p["vxy"][:, 0], axy
        return out.with_(xy=xy, yaw=yaw, vxy=vxy, axy=axy_out)

    def _trajectories(self, objs: ObjectArray, horizon_s: float, step_s: float,
                      n_hyp: int, probabilities: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, H, T, 3) trajectories and (N, H) probabilities (None without ``probabilities``) for the
        first H <= n_hyp hypotheses."""
        times = _step_times(horizon_s, step_s)
        n, h = len(objs), min(n_hyp, self._chains.of_lane.shape[1])
        cv_xy = objs.xy[:, None, :] + objs.vxy[:, None, :] * times[None, :, None]  # x = x0 + v t
        traj = np.concatenate([cv_xy, np.repeat(objs.yaw[:, None, None], len(times), axis=1)], axis=2)
        traj = np.repeat(traj[:, None], h, axis=1)
        lane, s0, d0 = self.match(objs)
        chains = np.where((lane >= 0)[:, None], self._chains.of_lane[np.maximum(lane, 0), :h], -1)  # (N, H)
        obj, hyp = np.nonzero(chains >= 0)
        if len(obj):
            rows = objs if h == 1 and len(obj) == n else _kinematics(objs, obj)  # (h = 1: obj = rows matched)
            p = self._frenet(rows, chains[obj, hyp], s0[obj], d0[obj],
                             np.broadcast_to(times, (len(obj), len(times))), motion=False)
            traj[obj, hyp] = np.concatenate([p["xy"], p["yaw"][..., None]], axis=2)
            if h > 1:  # a matched object's missing hypotheses repeat its first (with one, the first is itself)
                missing = (lane >= 0)[:, None] & (chains < 0)
                traj[missing] = np.repeat(traj[:, :1], h, axis=1)[missing]
        if not probabilities:
            return traj, None
        prob = np.zeros((n, h))
        prob[:, 0] = 1.0
        if len(obj):
            prob[obj, hyp] = self._chains.prob[lane[obj], hyp]
            prob /= prob.sum(axis=1, keepdims=True)  # renormalise over the H kept
        return traj, prob

    def predict_hypotheses(self, objs: ObjectArray, horizon_s: float = 5.0,
                           step_s: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
        """Up to H = ``max_hypotheses`` lane-sequence hypotheses per object: trajectories
        (N, H, T, 3) [x m, y m, yaw rad] at t = step_s, 2 step_s, ..., horizon_s, and probabilities
        (N, H), rows summing to 1, most probable first. Missing hypotheses repeat the first with
        probability 0; unmatched objects have one, constant velocity, with probability 1."""
        return self._trajectories(objs, horizon_s, step_s, self.config.max_hypotheses)

    def predict_trajectories(self, objs: ObjectArray, horizon_s: float = 5.0, step_s: float = 0.1) -> np.ndarray:
        """Most probable trajectory per object (N, T, 3) [x m, y m, yaw rad] at t = step_s .. horizon_s
        (T = round(horizon_s / step_s)); unmatched objects: constant velocity, constant yaw."""
        return self._trajectories(objs, horizon_s, step_s, 1, probabilities=False)[0][:, 0]
