"""Ground-truth world: every body's state at any time, from a ``Scenario``.

Kinematics of one body (all bodies evaluated at once on padded arrays):
    v(t)  piecewise linear through the keys (t_k, v_k), constant outside them
    s(t)  = F(t) - F(0),  F an antiderivative of v, closed form per piece:
            F(t) = F_k + v_k (t - t_k) + a_k (t - t_k)^2 / 2,  a_k = (v_{k+1} - v_k) / (t_{k+1} - t_k)
    p(t)  = point at arc length s(t) on the polyline, clamped to [0, L] (stops at the end)
    heading = tangent u of the current segment; velocity = v u; acceleration = (dv/dt) u.
The centripetal term v^2 kappa is ignored: a polyline has zero curvature on its segments
and turns at its vertices (``corner_radius_m`` rounds the corners into finely sampled arcs).
A body spawned at ``spawn_s`` follows its trajectory on the clock t - spawn_s.

Whose world: the scenario seen from one vehicle (``ego``, default the first): the other
vehicles are actors like any other, so its sensors see them and its scores count them. The
site view (``ego=None``, what an RSU sees) has every vehicle as an actor and no ego.
Ids: actors 1..N in YAML order, then the vehicles N+1..N+V, the same in every view.
"""

from __future__ import annotations

from bisect import bisect_right

import numpy as np

from v2i.core.frames import Pose2D
from v2i.core.identity_memo import IdentityMemo
from v2i.core.jit import IN_F1, IN_F2, IN_F3, IN_I1, kernel
from v2i.core.objects import ObjectArray, read_only

from v2i.sim.scenario import Building, Scenario, Trajectory


def _pad(rows: list[np.ndarray], fill_last: bool, fill: float = np.inf) -> np.ndarray:
    """Ragged list of (K_i, ...) arrays -> (N, K_max, ...); pad with ``fill`` or the last row."""
    k_max = max(len(r) for r in rows)
    out = np.full((len(rows), k_max) + rows[0].shape[1:], fill, dtype=float)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
        if fill_last:
            out[i, len(r):] = r[-1]
    return out


class _SpeedProfiles:
    """Piecewise-linear speed v(t) and its integral s(t) for N bodies, vectorised."""

    def __init__(self, trajectories: list[Trajectory]):
        keys = [np.asarray(tr.time_keys(), dtype=float) for tr in trajectories]
        slopes, integrals = [], []
        for k in keys:
            dt, dv = np.diff(k[:, 0]), np.diff(k[:, 1])
            a = np.append(dv / dt, 0.0)  # slope to the next key; 0 after the last one
            # F_{k+1} = F_k + v_k dt + a_k dt^2 / 2, F_0 = 0
            integrals.append(np.concatenate([[0.0], np.cumsum(k[:-1, 1] * dt + 0.5 * a[:-1] * dt**2)]))
            slopes.append(a)
        self._t = _pad([k[:, 0] for k in keys], fill_last=False)  # inf: never reached
        self._v = _pad([k[:, 1] for k in keys], fill_last=True)
        self._a = _pad(slopes, fill_last=False, fill=0.0)
        self._f = _pad(integrals, fill_last=True)
        self._rows = np.arange(len(keys))
        self._tavf = np.stack([self._t, self._a, self._v, self._f], axis=-1)  # (N, K, 4): one gather per call
        self._f0 = self._antiderivative(0.0)[0]

    def _antiderivative(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F(t), v(t), dv/dt, each (N,); t a time (s) for every body, or (N,) one per body."""
        t_col = t[:, None] if np.ndim(t) else t
        k = np.maximum((self._t <= t_col).sum(axis=1) - 1, 0)
        t_k, a_k, v_k, f_k = self._tavf[self._rows, k].T  # each (N,)
        before = t < self._t[:, 0]
        if not before.any():  # the common case: np.where below would pick the second branch everywhere
            dt = t - t_k
            return f_k + v_k * dt + 0.5 * a_k * dt**2, v_k + a_k * dt, a_k
        dt = np.where(before, 0.0, t - t_k)
        a = np.where(before, 0.0, a_k)
        v = v_k + a * dt
        f = np.where(before, self._v[:, 0] * (t - self._t[:, 0]), f_k + v_k * dt + 0.5 * a * dt**2)
        return f, v, a

    def at(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arc length s (N,) m, speed (N,) m/s, dv/dt (N,) m/s^2 at time t (s; or (N,), one per body)."""
        f, v, a = self._antiderivative(t)
        return f - self._f0, v, a


class _Paths:
    """Polylines for N bodies: point and unit tangent at an arc length, vectorised."""

    def __init__(self, trajectories: list[Trajectory]):
        pts = [np.asarray(tr.points(), dtype=float) for tr in trajectories]
        tangents, cum = [], []
        for tr, p in zip(trajectories, pts):
            seg = np.diff(p, axis=0)
            length = np.hypot(seg[:, 0], seg[:, 1])
            if len(p) == 1:
                yaw = np.deg2rad(tr.yaw_deg or 0.0)
                tangents.append(np.array([[np.cos(yaw), np.sin(yaw)]]))
            else:
                tangents.append(seg / length[:, None])
            cum.append(np.concatenate([[0.0], np.cumsum(length)]))
        self._p = _pad(pts, fill_last=True)
        self._u = _pad(tangents, fill_last=True)
        self._cum = _pad(cum, fill_last=False)  # inf: never reached
        self.length = np.array([c[-1] for c in cum])  # (N,) m
        self._last_seg = np.array([max(len(p) - 2, 0) for p in pts])
        self._rows = np.arange(len(pts))
        k_seg = self._u.shape[1]  # segment j <= _last_seg < k_seg: point, tangent and arc length at its start
        self._puc = np.concatenate([self._p[:, :k_seg], self._u, self._cum[:, :k_seg, None]], axis=-1)  # (N, k_seg, 5)

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Point (N, 2) m and unit tangent (N, 2) at arc lengths s (N,), clamped to [0, L]."""
        s = np.clip(s, 0.0, self.length)
        j = np.minimum(np.maximum((self._cum <= s[:, None]).sum(axis=1) - 1, 0), self._last_seg)
        puc = self._puc[self._rows, j]  # (N, 5): point, tangent, arc length at segment j's start
        u = puc[:, 2:4]
        return puc[:, 0:2] + (s - puc[:, 4])[:, None] * u, u


class Trajectories:
    """Kinematic state of N bodies at time t (map frame)."""

    def __init__(self, trajectories: list[Trajectory]):
        self._speed = _SpeedProfiles(trajectories)
        self._paths = _Paths(trajectories)
        sp, pa = self._speed, self._paths
        u = pa._puc[..., 2:4]  # each segment's heading, as at_numpy computes it (arctan2 elementwise)
        self._kernel_args = (sp._t, sp._tavf, sp._f0, pa._cum, pa._puc, pa._last_seg, pa.length,
                             np.arctan2(u[..., 1], u[..., 0]))

    def body(self, i: int) -> _Body:
        """Body ``i`` alone, evaluated in plain floats (``_Body``)."""
        return _Body(self, i)

    def at(self, t_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """xy (N, 2) m, yaw (N,) rad, vxy (N, 2) m/s, axy (N, 2) m/s^2 at time t_s (s; or (N,), one per body):
        ``at_numpy`` compiled (``_states``), the same bits."""
        t = np.asarray(t_s, dtype=float).reshape(-1) if np.ndim(t_s) else np.array([float(t_s)])
        if len(t) != 1 and len(t) != len(self._paths.length):  # the kernel reads t[i] for every body i
            raise ValueError(f"{len(t)} times for {len(self._paths.length)} bodies: one time, or one per body")
        return _states(t, *self._kernel_args)

    def at_numpy(self, t_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``at`` by numpy over every body at once (the reference of ``_states``)."""
        s, v, a = self._speed.at(np.asarray(t_s, dtype=float) if np.ndim(t_s) else float(t_s))
        xy, u = self._paths.at(s)
        moving = (s >= 0.0) & (s < self._paths.length)  # stopped at either end of the path
        yaw = np.arctan2(u[:, 1], u[:, 0])
        return xy, yaw, np.where(moving, v, 0.0)[:, None] * u, np.where(moving, a, 0.0)[:, None] * u


@kernel(IN_F1, IN_F2, IN_F3, IN_F1, IN_F2, IN_F3, IN_I1, IN_F1, IN_F2)
def _states(t: np.ndarray, key_t: np.ndarray, tavf: np.ndarray, f0: np.ndarray, cum: np.ndarray, puc: np.ndarray,
            last_seg: np.ndarray, length: np.ndarray,
            seg_yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``Trajectories.at_numpy`` body by body with its float64 operations in its order (``_Body.at`` is the
    same in Python floats): t (1,) s for every body or (N,) one per body; speed keys key_t (N, K) and
    [t, a, v, F] per key tavf (N, K, 4), F(0) f0 (N,); path arc lengths cum (N, Kp), per segment point,
    tangent and start arc length puc (N, Ks, 5), last segment (N,), length (N,) m, heading seg_yaw (N, Ks)."""
    n = len(f0)
    xy, yaw, vxy, axy = np.empty((n, 2)), np.empty(n), np.empty((n, 2)), np.empty((n, 2))
    for i in range(n):
        ti = t[0] if len(t) == 1 else t[i]
        k = -1  # the key: #(keys <= t) - 1, at least 0
        for j in range(key_t.shape[1]):
            k += key_t[i, j] <= ti
        k = max(k, 0)
        if ti < key_t[i, 0]:  # before the first key: v = v_0 + 0 0, F = v_0 (t - t_0), dv/dt = 0
            a = 0.0
            v = tavf[i, k, 2] + a * 0.0
            f = tavf[i, 0, 2] * (ti - key_t[i, 0])
        else:  # F = F_k + v_k dt + a_k dt^2 / 2, v = v_k + a_k dt
            dt, a = ti - tavf[i, k, 0], tavf[i, k, 1]
            v = tavf[i, k, 2] + a * dt
            f = tavf[i, k, 3] + tavf[i, k, 2] * dt + 0.5 * a * (dt * dt)
        s = f - f0[i]
        sc = s if s > 0.0 else 0.0  # np.clip(s, 0, L): max (0.0 for -0.0), then min
        sc = sc if sc < length[i] else length[i]
        j = -1  # the segment: #(cum <= s) - 1 in [0, last_seg]
        for m in range(cum.shape[1]):
            j += cum[i, m] <= sc
        j = min(max(j, 0), last_seg[i])
        ux, uy, along = puc[i, j, 2], puc[i, j, 3], sc - puc[i, j, 4]
        xy[i, 0], xy[i, 1], yaw[i] = puc[i, j, 0] + along * ux, puc[i, j, 1] + along * uy, seg_yaw[i, j]
        moving = s >= 0.0 and s < length[i]  # stopped at either end of the path
        speed, accel = (v, a) if moving else (0.0, 0.0)
        vxy[i, 0], vxy[i, 1], axy[i, 0], axy[i, 1] = speed * ux, speed * uy, accel * ux, accel * uy
    return xy, yaw, vxy, axy


class _Body:
    """``Trajectories.at`` of one body at one time, in Python floats: the same float64 operations
    in the same order as the vectorised path (key and segment found by bisection instead of a
    count of the keys <= t), so the same bits, at a tenth of the cost of ~20 numpy calls (the
    ego's pose is asked for ~10k times per run)."""

    def __init__(self, traj: Trajectories, i: int):
        sp, pa = traj._speed, traj._paths
        keys = int(np.isfinite(sp._t[i]).sum())  # the body's own keys; the padding is never reached
        self._t, self._tavf = sp._t[i, :keys].tolist(), sp._tavf[i, :keys].tolist()  # [t, a, v, F] per key
        self._f0 = float(sp._f0[i])
        segs = int(pa._last_seg[i]) + 1
        self._cum, self._length = pa._cum[i, :segs + 1].tolist(), float(pa.length[i])
        self._last_seg = int(pa._last_seg[i])
        self._puc = pa._puc[i].tolist()  # per segment: point x, y, tangent x, y, arc length at its start
        u = pa._puc[i:i + 1, :, 2:4]
        self._yaw = [float(np.arctan2(u[:, j, 1], u[:, j, 0])[0]) for j in range(u.shape[1])]  # as at() computes it

    def at(self, t_s: float) -> tuple[float, float, float, float, float]:
        """x, y (m), yaw (rad), vx, vy (m/s) at t_s (s): ``Trajectories.at`` row i."""
        t = float(t_s)
        s, v = self._s_v(t)
        # _Paths.at: s clipped to [0, L] (np.clip: max then min), segment j = #(cum <= s) - 1 in [0, last]
        sc = min(self._length, max(0.0, s))  # np.clip(s, 0, L): max(0.0, -0.0) is 0.0 as there
        j = min(max(bisect_right(self._cum, sc) - 1, 0), self._last_seg)
        px, py, ux, uy, c = self._puc[j]
        moving = 0.0 <= s < self._length
        speed = v if moving else 0.0
        return px + (sc - c) * ux, py + (sc - c) * uy, self._yaw[j], speed * ux, speed * uy

    def _s_v(self, t: float) -> tuple[float, float]:
        """Arc length s = F(t) - F(0) (m) and speed v(t) (m/s): ``_SpeedProfiles.at`` row i."""
        if t < self._t[0]:  # before the first key: v = v_0, F = v_0 (t - t_0)
            _, _, v0, _ = self._tavf[0]
            return v0 * (t - self._t[0]) - self._f0, v0 + 0.0 * 0.0
        t_k, a_k, v_k, f_k = self._tavf[max(bisect_right(self._t, t) - 1, 0)]
        dt = t - t_k
        return f_k + v_k * dt + 0.5 * a_k * (dt * dt) - self._f0, v_k + a_k * dt


class _Bodies:
    """Every body of a scenario (its actors, then its vehicles) at its own clock t - spawn_s, all at
    once: ``Trajectories.at`` (row by row the same bits for any set of rows: each row's keys, segment and
    arithmetic are its own). The scenario's views (each vehicle's, the site's) ask for the same instants
    (the LiDARs' and cameras' shared capture times), so the last ``RECENT`` instants are kept."""

    RECENT = 8

    def __init__(self, scenario: Scenario):
        bodies = list(scenario.actors) + list(scenario.vehicles)
        self._trajectories = Trajectories([b.trajectory for b in bodies])
        spawn_s = np.array([b.spawn_s for b in bodies], dtype=float)  # (B,) s
        self._spawn_s = spawn_s if spawn_s.any() else 0.0  # none late: one scalar time (t - 0 = t, the same rows)
        self._recent: dict[float, tuple[np.ndarray, ...]] = {}

    def at(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """xy (B, 2) m, yaw (B,) rad, vxy (B, 2) m/s, axy (B, 2) m/s^2 at scenario time t_s (s): read them only."""
        state = self._recent.get(t_s)
        if state is None:
            state = self._trajectories.at(t_s - self._spawn_s)  # shared by the views: they take rows (copies)
            if len(self._recent) >= self.RECENT:
                del self._recent[next(iter(self._recent))]  # the oldest
            self._recent[t_s] = state
        return state


_bodies_of = IdentityMemo(_Bodies)  # the _Bodies of a scenario, one per scenario object (shared by its views)


def _building_arrays(buildings: list[Building]) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Boxes (M, 5) [x, y, l, w, yaw rad] and polygons, each (K, 2), of the static occluders."""
    boxes = [[b.box.x, b.box.y, b.box.l, b.box.w, np.deg2rad(b.box.yaw_deg)] for b in buildings if b.box is not None]
    polygons = tuple(np.asarray(b.polygon, dtype=float) for b in buildings if b.polygon is not None)
    return np.asarray(boxes, dtype=float).reshape(-1, 5), polygons


class World:
    """Ground truth of a scenario from one vehicle (module docstring). Ids are stable across views."""

    def __init__(self, scenario: Scenario, ego: str | None = None, *, site: bool = False):
        """``ego``: the vehicle whose view this is (None: the first); ``site=True``: the RSU's
        view, every vehicle an actor and no ego."""
        self.scenario = scenario
        ego_spec = None if site else scenario.vehicle(ego)
        bodies = list(scenario.actors) + list(scenario.vehicles)
        all_ids = np.arange(1, len(bodies) + 1, dtype=np.int64)
        keep = [b is not ego_spec for b in bodies]
        actors = [b for b, k in zip(bodies, keep) if k]
        self.ego_name: str | None = None if ego_spec is None else ego_spec.name
        self.ids = all_ids[keep]
        self.cls = np.array([int(a.cls) for a in actors], dtype=np.int64)
        self.lwh = np.array([a.size for a in actors], dtype=float)  # (N, 3) m
        self.actor_names: dict[int, str] = {int(i): a.name for i, a in zip(self.ids, actors)}
        self.vehicle_ids: dict[str, int] = {v.name: int(i) for v, i in zip(scenario.vehicles, all_ids[len(scenario.actors):])}
        self.target_id: int = next(i for i, n in self.actor_names.items() if n == scenario.target)
        self.building_boxes, self.building_polygons = _building_arrays(scenario.buildings)
        self._spawn_s = np.array([a.spawn_s for a in actors])
        self._despawn_s = np.array([np.inf if a.despawn_s is None else a.despawn_s for a in actors])
        self._timed = bool((self._spawn_s > 0).any() or np.isfinite(self._despawn_s).any())
        self._bodies, self._rows = _bodies_of(scenario), np.flatnonzero(keep)  # the actors' rows among the bodies
        self._static_present: dict[bytes, ObjectArray] = {}  # present mask -> those actors' static columns
        self._ego = None if ego_spec is None else Trajectories([ego_spec.trajectory])
        self._ego_body = None if ego_spec is None else self._ego.body(0)
        self.ego_size = None if ego_spec is None else np.array(ego_spec.size, dtype=float)  # (3,) l, w, h (m)
        self._static = self._static_truth()

    @property
    def duration_s(self) -> float:
        return self.scenario.duration_s

    def present(self, t_s: float) -> np.ndarray:
        """(N,) bool: the actors that exist at t_s (spawn_s <= t_s < despawn_s)."""
        return (self._spawn_s <= t_s) & (t_s < self._despawn_s)

    def actors_at(self, t_s: float) -> ObjectArray:
        """Ground truth at time t_s (s), map frame, of every actor present then (the other
        vehicles included, this view's ego excluded); each actor on its own clock t_s - spawn_s."""
        xy, yaw, vxy, axy = self._bodies.at(t_s)
        static, rows = self._static, self._rows
        if self._timed:
            present = self.present(t_s)
            static, rows = self._static_of(present), rows[present]
        return static.with_(xy=xy[rows], yaw=yaw[rows], vxy=vxy[rows], axy=axy[rows])

    def _static_of(self, present: np.ndarray) -> ObjectArray:
        """``_static_truth`` of the actors present (N,) bool, kept per mask (it changes at spawns)."""
        key = present.tobytes()
        static = self._static_present.get(key)
        if static is None:
            static = self._static_present[key] = read_only(self._static.take(present))
        return static

    def _static_truth(self) -> ObjectArray:
        """Every actor's time-independent columns (ids, class, size, z = h / 2, zero covariance,
        confidence 1, no sources), built once and read-only: ``actors_at`` adds the kinematics."""
        n = len(self.ids)
        out = ObjectArray(
            ids=self.ids.copy(), cls=self.cls.copy(), xy=np.zeros((n, 2)), z=self.lwh[:, 2] / 2.0,
            lwh=self.lwh.copy(), yaw=np.zeros(n), vxy=np.zeros((n, 2)), cov_xy=np.zeros((n, 2, 2)),
            confidence=np.ones(n), sources=np.zeros(n, dtype=np.int64),
        )
        return read_only(out)  # shared by every state (actors_at replaces the kinematics): never written

    def positions_of(self, ids: np.ndarray, t_s: float) -> np.ndarray:
        """(K, 2) map positions (m) at t_s of the bodies ``ids`` (K,): actors present then, or 0 for the ego."""
        ids = np.asarray(ids, dtype=np.int64)
        xy = np.zeros((len(ids), 2))
        actor = ids != 0
        truth = self.actors_at(t_s)
        xy[actor] = truth.xy[np.searchsorted(truth.ids, ids[actor])]
        if not actor.all():
            ego = self.ego_at(t_s)
            xy[~actor] = (ego.x, ego.y)
        return xy

    def ego_at(self, t_s: float) -> Pose2D:
        """True ego pose (box centre = base_link origin) and velocity in map at t_s (s)."""
        if self._ego is None:
            raise ValueError("the site view (World(..., site=True)) has no ego")
        x, y, yaw, vx, vy = self._ego_body.at(t_s)  # = self._ego.at(t_s) row 0, bit for bit
        return Pose2D(x=x, y=y, yaw=yaw, vx=vx, vy=vy)

    def ego_xy_at(self, t_s: float) -> tuple[float, float]:
        """x, y (m) of ``ego_at(t_s)``, without building the Pose2D (for callers that need the position alone)."""
        if self._ego is None:
            raise ValueError("the site view (World(..., site=True)) has no ego")
        x, y, _, _, _ = self._ego_body.at(t_s)
        return x, y
