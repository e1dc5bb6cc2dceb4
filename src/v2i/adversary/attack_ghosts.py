"""Recognising injected ghosts in an OBU's fused output (pure; times are arguments).

The attacker knows where it put each ghost (map frame, when) and, from the RSU's broadcast,
where the genuine RSU objects are. A fused object (``FusedObjectList``, ``base_link``) counts as
a ghost when all of these hold:

1. its class is pedestrian (the ghost's) and its sources include ``SOURCE_RSU`` (vehicle-only
   objects come from the ego's own sensors, which no V2X message reaches);
2. moved to ``map`` with the output's own ego pose (p_m = R(ego_yaw) p_b + t_ego), it lies within
   ``radius_m`` of a ghost placed in the last ``ghost_life_ns`` before the output's cycle time
   (or up to ``lead_ns`` after it: a list may be fused at a cycle slightly earlier than its send);
3. it lies farther than ``genuine_clear_m`` from every object of the genuine RSU lists captured
   in the last ``genuine_life_ns``, each predicted to the cycle time at its velocity
   (p(t) = p + v (t - t_capture)): a real pedestrian near the ghost's spot is not a ghost.

The same rule run before any ghost is sent, on positions where the attacker *would* have put
them (:meth:`GhostWatch.place` with ``decoy=True``), measures its own false-positive rate on the
genuine traffic: the tool reports both.

Clocks: placement, genuine capture and cycle times must be in one clock (the attacker converts
the RSU's capture times with its offset estimate; the OBU and the attacker share a machine clock
in the demo and the netns test).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from v2i.core.frames import Pose2D, base_to_map_points
from schemas.classes import ObjectClass
from schemas.limits import SOURCE_RSU
from schemas.messages import FusedObjectList

S_NS = 1_000_000_000


class GhostWatch:
    """Ghost placements and genuine RSU objects of the recent past; judges fused outputs."""

    def __init__(self, radius_m: float = 2.0, genuine_clear_m: float = 3.0, ghost_life_ns: int = 3 * S_NS,
                 genuine_life_ns: int = S_NS, lead_ns: int = S_NS // 2):
        self.radius_m, self.genuine_clear_m = radius_m, genuine_clear_m
        self.ghost_life_ns, self.genuine_life_ns, self.lead_ns = ghost_life_ns, genuine_life_ns, lead_ns
        self._ghosts: deque[tuple[int, float, float, bool]] = deque()  # (t_ns, x, y, decoy)
        self._genuine: deque[tuple[int, np.ndarray, np.ndarray]] = deque()  # (t_ns, xy (N, 2), vxy (N, 2))

    def place(self, t_ns: int, xy: np.ndarray, decoy: bool = False) -> None:
        """A ghost put at map ``xy`` (2,) at ``t_ns``; ``decoy``: not sent (false-positive baseline)."""
        self._ghosts.append((t_ns, float(xy[0]), float(xy[1]), decoy))
        self._forget(self._ghosts, t_ns - 2 * self.ghost_life_ns)

    def genuine(self, t_ns: int, xy: np.ndarray, vxy: np.ndarray) -> None:
        """A genuine RSU list's objects captured at ``t_ns``: map positions and velocities (N, 2)."""
        self._genuine.append((t_ns, np.asarray(xy, float).reshape(-1, 2), np.asarray(vxy, float).reshape(-1, 2)))
        self._forget(self._genuine, t_ns - 2 * self.genuine_life_ns)

    @staticmethod
    def _forget(items: deque, before_ns: int) -> None:
        while items and items[0][0] < before_ns:
            items.popleft()

    def _ghost_points(self, t_ns: int, decoy: bool) -> np.ndarray:
        """Ghost positions (M, 2) placed in [t - ghost_life, t + lead]."""
        lo, hi = t_ns - self.ghost_life_ns, t_ns + self.lead_ns
        pts = [(x, y) for t, x, y, d in self._ghosts if lo <= t <= hi and d == decoy]
        return np.array(pts, float).reshape(-1, 2)

    def _genuine_points(self, t_ns: int) -> np.ndarray:
        """Genuine objects (K, 2) captured in [t - genuine_life, t + lead], predicted to ``t_ns``."""
        lo, hi = t_ns - self.genuine_life_ns, t_ns + self.lead_ns
        pts = [xy + vxy * ((t_ns - t) * 1e-9) for t, xy, vxy in self._genuine if lo <= t <= hi]
        return np.concatenate(pts) if pts else np.empty((0, 2))

    def ghosts_in(self, out: FusedObjectList, decoy: bool = False) -> int:
        """How many objects of ``out`` are ghosts (``decoy``: judged against the decoy placements)."""
        objs = out.objects
        if not len(objs):
            return 0
        rsu = (objs.column("cls") == int(ObjectClass.PEDESTRIAN)) & (objs.column("sources").astype(int) & SOURCE_RSU > 0)
        if not rsu.any():
            return 0
        ghosts = self._ghost_points(out.cycle_time_ns, decoy)
        if not len(ghosts):
            return 0
        ego = Pose2D(out.ego_x, out.ego_y, out.ego_yaw)
        xy = base_to_map_points(np.column_stack([objs.column("x"), objs.column("y")])[rsu], ego)  # (N, 2) map
        near_ghost = _min_distance(xy, ghosts) <= self.radius_m
        genuine = self._genuine_points(out.cycle_time_ns)
        clear = _min_distance(xy, genuine) > self.genuine_clear_m
        return int(np.count_nonzero(near_ghost & clear))


def _min_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of ``a`` (N, 2) its distance to the nearest of ``b`` (M, 2); inf if M = 0."""
    if not len(b):
        return np.full(len(a), np.inf)
    return np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=-1)).min(axis=1)
