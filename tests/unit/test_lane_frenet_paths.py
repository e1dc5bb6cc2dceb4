"""LanePredictor after its leaner Frenet step (the rows' four columns instead of every column, the tangent only
for motion, an infinite lateral decay's exp(-t / inf) = 1 skipped) against its previous body, bit for bit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from v2i.fusion import lane_prediction as lp
from v2i.core.frames import wrap_angle
from v2i.fusion.lane_prediction import LanePredictor, chain_frame, propagate_along
from v2i.core.objects import ObjectArray
from v2i.sim.maps import MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG, map_path


def _frenet_ref(self, objs, chain, s0, d0, t, motion=True):
    """LanePredictor._frenet before (commit 2ba02fe)."""
    cfg = self.config
    _, psi0 = chain_frame(self._chains, chain, s0[:, None])
    t0 = np.stack([np.cos(psi0[:, 0]), np.sin(psi0[:, 0])], axis=1)
    v_s = np.sum(objs.vxy * t0, axis=1)
    a_s = np.sum(objs.axy * t0, axis=1) if cfg.use_acceleration else np.zeros(len(objs))
    tt = np.concatenate([np.zeros((len(objs), 1)), t], axis=1)
    s, v = propagate_along(s0, v_s, a_s, tt, cfg.use_acceleration)
    d = d0[:, None] * np.exp(-tt / cfg.lateral_decay_s)
    c, psi = chain_frame(self._chains, chain, s)
    tan = np.stack([np.cos(psi), np.sin(psi)], axis=-1)
    normal = np.stack([-tan[..., 1], tan[..., 0]], axis=-1)
    f = c + d[..., None] * normal
    offset = wrap_angle(objs.yaw - psi[:, 0])[:, None] * np.exp(-tt / cfg.heading_decay_s)
    out = {"xy": objs.xy[:, None, :] + (f - f[:, :1])[:, 1:], "yaw": wrap_angle(psi + offset)[:, 1:]}
    if motion:
        out["vxy"] = (v[..., None] * tan + (-d / cfg.lateral_decay_s)[..., None] * normal)[:, 1:]
        out["dpsi"] = wrap_angle(psi - psi[:, :1])[:, 1:]
    return out


def _trajectories_ref(self, objs, horizon_s, step_s, n_hyp, probabilities=True):
    """LanePredictor._trajectories before (commit 2ba02fe): every column of the matched rows taken."""
    times = lp._step_times(horizon_s, step_s)
    n, h = len(objs), min(n_hyp, self._chains.of_lane.shape[1])
    cv_xy = objs.xy[:, None, :] + objs.vxy[:, None, :] * times[None, :, None]
    traj = np.concatenate([cv_xy, np.repeat(objs.yaw[:, None, None], len(times), axis=1)], axis=2)
    traj = np.repeat(traj[:, None], h, axis=1)
    lane, s0, d0 = self.match(objs)
    chains = np.where((lane >= 0)[:, None], self._chains.of_lane[np.maximum(lane, 0), :h], -1)
    obj, hyp = np.nonzero(chains >= 0)
    if len(obj):
        p = self._frenet(objs.take(obj), chains[obj, hyp], s0[obj], d0[obj],
                         np.broadcast_to(times, (len(obj), len(times))), motion=False)
        traj[obj, hyp] = np.concatenate([p["xy"], p["yaw"][..., None]], axis=2)
        if h > 1:
            missing = (lane >= 0)[:, None] & (chains < 0)
            traj[missing] = np.repeat(traj[:, :1], h, axis=1)[missing]
    if not probabilities:
        return traj, None
    prob = np.zeros((n, h))
    prob[:, 0] = 1.0
    if len(obj):
        prob[obj, hyp] = self._chains.prob[lane[obj], hyp]
        prob /= prob.sum(axis=1, keepdims=True)
    return traj, prob


class _Previous(LanePredictor):
    """The previous body: every column taken (ObjectArray.take), the previous _frenet."""

    _frenet = _frenet_ref
    _trajectories = _trajectories_ref


def _previous(pred: LanePredictor) -> _Previous:
    old = _Previous.__new__(_Previous)
    old.__dict__.update(pred.__dict__)
    return old


def _objects(rng, n, xy_range):
    cls = rng.choice([1, 1, 1, 2, 3, 5, 6], n)  # mostly cars, some pedestrians (unmatched)
    return ObjectArray(ids=np.arange(n), cls=cls, xy=rng.uniform(*xy_range, (n, 2)), z=np.zeros(n),
                       lwh=np.ones((n, 3)), yaw=rng.uniform(-np.pi, np.pi, n), vxy=rng.normal(0, 8, (n, 2)),
                       axy=rng.normal(0, 2, (n, 2)))


@pytest.mark.parametrize("name", ["dense-intersection", "connected-intersection", "highway-merge"])
@pytest.mark.parametrize("config", [{}, {"lateral_decay_s": 2.0}, {"use_acceleration": True}])
def test_predictions_equal_the_previous_body(name, config):
    pred = LanePredictor.from_osm(map_path(name), MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG)
    pred = LanePredictor(pred.geometry, dataclasses.replace(pred.config, **config))
    old = _previous(pred)
    rng = np.random.default_rng(len(name))
    lo, hi = pred._chains.vertex.min(axis=0), pred._chains.vertex.max(axis=0)
    matched = 0
    for n in (0, 1, 3, 8, 20):
        for _ in range(6):
            objs = _objects(rng, n, (float(min(lo)), float(max(hi))))
            on_lane = pred._chains.vertex[rng.integers(0, len(pred._chains.vertex), n)]  # some on a centreline
            objs = objs.with_(xy=np.where(rng.random((n, 1)) < 0.7, on_lane + rng.normal(0, 0.5, (n, 2)), objs.xy))
            matched += int((pred.match(objs)[0] >= 0).sum())
            assert pred.predict_trajectories(objs).tobytes() == old.predict_trajectories(objs).tobytes()
            for got, want in zip(pred.predict_hypotheses(objs), old.predict_hypotheses(objs)):
                assert got.tobytes() == want.tobytes()
            dt = rng.uniform(0, 0.5, n) if n % 2 else 0.23
            got, want = pred.predict_objects(objs, dt), old.predict_objects(objs, dt)
            for column in ("xy", "yaw", "vxy", "axy"):
                assert getattr(got, column).tobytes() == getattr(want, column).tobytes(), column
    assert matched > 20  # (rows on a lane: the Frenet step ran)
