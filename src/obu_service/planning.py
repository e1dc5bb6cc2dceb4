"""Planning fusion inputs (IAAD, Liu et al.): the RSU's long-horizon paths, sampled and re-timed. Pure."""

from __future__ import annotations

import numpy as np

from v2i.core.objects import ObjectArray
from v2i.fusion.wire import objects_from_states
from schemas.messages import ObjectListHeader, PredictionList


def path_array(pred: PredictionList) -> np.ndarray:
    """(N, K + 1, 3) [x, y, yaw] at t0 + k step, k = 0..K (k = 0: the object itself)."""
    objs = objects_from_states(pred.objects)
    k = max((len(p.x) for p in pred.paths), default=0)
    out = np.empty((len(objs), k + 1, 3))
    out[:, 0, :2], out[:, 0, 2] = objs.xy, objs.yaw
    for i, p in enumerate(pred.paths):
        out[i, 1:] = np.column_stack([p.x, p.y, p.yaw]) if len(p.x) == k else out[i, 0]  # short paths: hold
    return out


def objects_at(pred: PredictionList, dt_s: float) -> ObjectArray:
    """The predicted objects (map) at t0 + dt_s, linearly interpolated along their paths.

    Velocity is the path's finite difference there; ``dt_s`` is clipped to [0, horizon].
    """
    objs = objects_from_states(pred.objects)
    if not len(objs):
        return objs
    paths = path_array(pred)  # (N, K + 1, 3)
    step_s = pred.step_ns * 1e-9
    u = float(np.clip(dt_s / step_s, 0.0, paths.shape[1] - 1))
    i0 = min(int(u), max(paths.shape[1] - 2, 0))
    i1 = min(i0 + 1, paths.shape[1] - 1)
    a = u - i0
    xy = (1 - a) * paths[:, i0, :2] + a * paths[:, i1, :2]  # p(t) = (1 - a) p_k + a p_k+1
    vxy = (paths[:, i1, :2] - paths[:, i0, :2]) / step_s if i1 > i0 else objs.vxy
    yaw = np.where(a < 0.5, paths[:, i0, 2], paths[:, i1, 2])
    return objs.with_(xy=xy, vxy=vxy, yaw=yaw, axy=np.zeros_like(xy), age_s=objs.age_s + max(dt_s, 0.0))


def retimed(pred: PredictionList, t0_obu_ns: int, publish_obu_ns: int) -> PredictionList:
    """The same paths with header times in the OBU clock (the planner-facing output)."""
    header = ObjectListHeader(rsu_id=pred.header.rsu_id, seq=pred.header.seq, capture_time_ns=t0_obu_ns,
                              publish_time_ns=max(publish_obu_ns, t0_obu_ns), sensor=pred.header.sensor,
                              frame_id=pred.header.frame_id)
    return pred.model_copy(update={"header": header})
