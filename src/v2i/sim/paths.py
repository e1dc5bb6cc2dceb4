"""Paths and speed profiles as scenario authors write them, turned into what ``v2i.sim.world`` drives.

- ``rounded_path``: a polyline whose corners are replaced by circular arcs of radius r, so a
  turn needs no hand-densified points. At a corner turning by phi the arc is tangent to both
  segments at distance d = r tan(phi / 2) from the corner; its centre lies r from the first
  tangent point along the inward normal. Arcs are sampled every ``ARC_STEP_DEG`` at most.
- ``speed_keys_from_distance``: a speed profile by distance along the path, [[s_m, mps], ...],
  with constant acceleration between keys, converted exactly into the time keys
  [[t_s, mps], ...] that ``v2i.sim.world`` integrates: between keys k and k+1
  (v_k + v_{k+1}) / 2 is the mean speed, so t_{k+1} = t_k + 2 (s_{k+1} - s_k) / (v_k + v_{k+1}).
"""

from __future__ import annotations

import math

import numpy as np

Point2 = tuple[float, float]
ARC_STEP_DEG = 5.0
_STRAIGHT_RAD = 1e-9  # a corner turning less than this is left as it is
_SAME_POINT_M = 1e-6


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.hypot(v[0], v[1])


def _corner_arc(before: np.ndarray, corner: np.ndarray, after: np.ndarray, radius_m: float) -> tuple[float, np.ndarray]:
    """Tangent distance d (m) and the arc's points (K, 2) replacing ``corner`` (empty if straight)."""
    u_in, u_out = _unit(corner - before), _unit(after - corner)
    phi = math.acos(float(np.clip(u_in @ u_out, -1.0, 1.0)))  # turn angle, 0 (straight) .. pi (reversal)
    if phi < _STRAIGHT_RAD:
        return 0.0, np.zeros((0, 2))
    if phi > math.pi - 1e-6:
        raise ValueError(f"path reverses at {tuple(corner.tolist())}: a corner cannot be rounded there")
    d = radius_m * math.tan(phi / 2.0)
    left = u_in[0] * u_out[1] - u_in[1] * u_out[0] > 0.0  # cross(u_in, u_out) > 0: a left turn
    normal = np.array([-u_in[1], u_in[0]]) if left else np.array([u_in[1], -u_in[0]])
    start = corner - d * u_in
    centre = start + radius_m * normal
    a0 = math.atan2(start[1] - centre[1], start[0] - centre[0])
    steps = max(1, math.ceil(math.degrees(phi) / ARC_STEP_DEG))
    angles = a0 + (1.0 if left else -1.0) * phi * np.arange(steps + 1) / steps
    return d, centre + radius_m * np.column_stack([np.cos(angles), np.sin(angles)])


def rounded_path(path: list[Point2], radius_m: float) -> list[Point2]:
    """``path`` with every corner replaced by an arc of ``radius_m`` (m); ValueError when an arc
    does not fit: the tangent distances of two corners exceed the segment between them."""
    pts = np.asarray(path, dtype=float)
    if len(pts) < 3:
        return list(path)
    arcs = [_corner_arc(pts[i - 1], pts[i], pts[i + 1], radius_m) for i in range(1, len(pts) - 1)]
    reach = [0.0] + [d for d, _ in arcs] + [0.0]  # tangent distance used at each vertex
    for i in range(len(pts) - 1):
        length = float(np.hypot(*(pts[i + 1] - pts[i])))
        if reach[i] + reach[i + 1] > length + 1e-9:
            raise ValueError(f"corner_radius_m {radius_m} does not fit between {tuple(pts[i].tolist())} and "
                             f"{tuple(pts[i + 1].tolist())}: the arcs need {reach[i] + reach[i + 1]:.2f} m of the "
                             f"{length:.2f} m segment")
    out = [pts[0]]
    for _, arc in arcs:
        out.extend(arc if len(arc) else [])
    out.append(pts[-1])
    kept = [out[0]]
    for p in out[1:]:
        if np.hypot(*(p - kept[-1])) > _SAME_POINT_M:
            kept.append(p)
    # straight corners (no arc) are dropped by the loop above; a straight line needs no vertex there
    return [(float(x), float(y)) for x, y in kept]


def speed_keys_from_distance(keys: list[Point2]) -> list[Point2]:
    """[[s_m, mps], ...] with s strictly increasing -> [[t_s, mps], ...] (module docstring).
    Before the first key the body moves at its speed (it must be > 0 if s_0 > 0)."""
    s = [float(k[0]) for k in keys]
    v = [float(k[1]) for k in keys]
    if any(b <= a for a, b in zip(s, s[1:])):
        raise ValueError(f"speed_at_m distances must strictly increase, got {s}")
    out: list[Point2] = [(0.0, v[0])]
    t_s = 0.0
    if s[0] > 0.0:
        if v[0] <= 0.0:
            raise ValueError(f"speed 0 at s = {s[0]} m: the body could never reach its first key from s = 0")
        t_s = s[0] / v[0]
        out.append((t_s, v[0]))
    for k in range(len(s) - 1):
        if v[k] + v[k + 1] <= 0.0:
            raise ValueError(f"speed 0 at both s = {s[k]} m and s = {s[k + 1]} m: the body never gets between them")
        t_s += 2.0 * (s[k + 1] - s[k]) / (v[k] + v[k + 1])
        out.append((t_s, v[k + 1]))
    return out
