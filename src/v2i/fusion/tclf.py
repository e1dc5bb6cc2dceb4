"""DAIR-V2X time-compensated late fusion (TCLF) baseline.

The infrastructure's velocity is estimated from its two latest frames (no RSU tracker
trusted): objects of frame k are matched to frame k-1 by centre distance and
v = (p_k - p_{k-1}) / (t_k - t_{k-1}); each object is then extrapolated linearly by the
latency, p(t) = p_k + v (t - t_k). Vehicle and compensated RSU objects are matched by
centre distance (Hungarian) and matched pairs are merged by a confidence-weighted mean
of their positions; unmatched objects of either side are kept.
"""

from __future__ import annotations

import numpy as np

from v2i.fusion.association import assign, center_distance_cost
from v2i.core.objects import ObjectArray


def two_frame_velocity(prev: ObjectArray, curr: ObjectArray, dt_s: float, gate_m: float = 5.0) -> np.ndarray:
    """(N_curr, 2) velocity of each current object from its match in the previous frame
    (zero where it has none or dt is not positive)."""
    vxy = np.zeros((len(curr), 2))
    if dt_s <= 0 or not len(prev) or not len(curr):
        return vxy
    result = assign(center_distance_cost(curr.xy, prev.xy, curr.cls, prev.cls), gate_m)
    i, j = result.matches[:, 0], result.matches[:, 1]
    vxy[i] = (curr.xy[i] - prev.xy[j]) / dt_s
    return vxy


def tclf_compensate(prev: ObjectArray | None, curr: ObjectArray, frame_dt_s: float, latency_s: float) -> ObjectArray:
    """RSU objects of the newest frame extrapolated by ``latency_s`` with two-frame velocity."""
    vxy = two_frame_velocity(prev, curr, frame_dt_s) if prev is not None else np.zeros((len(curr), 2))
    return curr.with_(xy=curr.xy + vxy * latency_s, vxy=vxy)


def tclf_fuse(own: ObjectArray, rsu: ObjectArray, gate_m: float = 3.0) -> ObjectArray:
    """Own + compensated RSU objects; matched pairs merged by confidence-weighted position."""
    if not len(rsu) or not len(own):
        return ObjectArray.concat([own, rsu])
    result = assign(center_distance_cost(own.xy, rsu.xy, own.cls, rsu.cls), gate_m)
    i, j = result.matches[:, 0], result.matches[:, 1]
    w_own, w_rsu = own.confidence[i, None], rsu.confidence[j, None]
    xy = own.xy.copy()
    xy[i] = (w_own * own.xy[i] + w_rsu * rsu.xy[j]) / np.maximum(w_own + w_rsu, 1e-9)
    sources = own.sources.copy()
    sources[i] |= rsu.sources[j]
    return ObjectArray.concat([own.with_(xy=xy, sources=sources), rsu.take(result.unmatched_b)])
