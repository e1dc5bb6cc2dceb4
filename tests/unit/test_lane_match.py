"""The lane predictor's compiled segment match (v2i.fusion.lane_match) against its numpy expression."""

from __future__ import annotations

import numpy as np
import pytest

from v2i.fusion.lane_match import chain_frame_points, match_reference, match_segments
from v2i.fusion.lane_prediction import HEADING_BASE_M, LanePredictor, chain_points
from v2i.core.objects import ObjectArray
from schemas.classes import ObjectClass
from v2i.sim.maps import MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG, bundled_maps, map_path


def _match_numpy(pred: LanePredictor, objs: ObjectArray):
    return match_reference(pred.config, pred._seg, pred._map_classes, objs)


def _objects(pred: LanePredictor, rng: np.random.Generator, n: int) -> ObjectArray:
    """n objects on, beside, at the ends of and off the predictor's lanes; every class, moving or not."""
    seg = pred._seg
    on = rng.integers(0, len(seg.lane), n)
    u = rng.choice([rng.uniform(-0.3, 1.3), 0.0, 1.0, -1e-7, 1.0 + 1e-7], n)[:, None]  # exactly at the ends too
    aside = rng.choice([0.0, rng.normal(0.0, 2.0)], n, p=[0.2, 0.8])[:, None]
    xy = seg.a[on] + u * seg.length[on, None] * seg.t[on] + aside * seg.t[on][:, ::-1] * [-1, 1]
    far = rng.random(n) < 0.15
    xy[far] = rng.uniform(-300.0, 300.0, (int(far.sum()), 2))
    speed = rng.choice([0.0, 0.2, 1.0, 8.0], n)
    angle = seg.psi[on] + rng.normal(0.0, 0.6, n) + rng.choice([0.0, np.pi, np.pi / 4], n, p=[0.8, 0.1, 0.1])
    return ObjectArray(
        ids=np.arange(n, dtype=np.int64), cls=rng.choice([int(c) for c in ObjectClass], n).astype(np.int64), xy=xy,
        z=np.zeros(n), lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=seg.psi[on] + rng.normal(0.0, 0.6, n),
        vxy=speed[:, None] * np.column_stack([np.cos(angle), np.sin(angle)]),
    )


@pytest.mark.parametrize("name", sorted(bundled_maps()))
def test_compiled_match_equals_the_numpy_expression(name):
    """Lanes, s0 and d0 of the compiled loop equal the numpy expression's as bytes on every bundled map
    (objects on lanes, beside them, exactly at segment ends, off the map; none, one or many)."""
    pred = LanePredictor.from_osm(map_path(name), MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG)
    rng = np.random.default_rng(11)
    matched = 0
    for n in (0, 1, 2, 3, 7, 40, 300):
        objs = _objects(pred, rng, n)
        got, want = pred.match(objs), _match_numpy(pred, objs)
        for g, w in zip(got, want):
            assert g.dtype == w.dtype and g.shape == w.shape and g.tobytes() == w.tobytes()
        matched += int(np.count_nonzero(got[0] >= 0))
    assert matched > 40


def test_compiled_match_takes_numpy_argmin_rule():
    """Equal costs: the first segment; a zero half width (0 / 0 cost, NaN): numpy's argmin takes it and
    the object is unmatched; no candidate at all: unmatched."""
    seg = np.zeros((3, 12))
    seg[:, 2] = 100.0  # reach_sq
    seg[:, 5] = 1.0  # tangent x
    seg[:, 7] = 10.0  # length
    seg[:, 8:10] = 2.0  # half widths
    seg[:, 11] = [0.0, 10.0, 20.0]  # s0
    index = np.array([[4, 1, 0], [5, 0, 0], [6, 0, 1]], dtype=np.int64)
    rules = np.array([0.5, np.pi / 4, 0.2])
    lane, s0, d0 = np.empty(1, dtype=np.int64), np.empty(1), np.empty(1)
    xy, heading, road = np.array([[3.0, 0.5]]), np.zeros(1), np.ones(1, dtype=bool)
    match_segments(xy, heading, road, seg, index, rules, lane, s0, d0)
    assert (lane[0], s0[0], d0[0]) == (4, 3.0, 0.5)  # three equal costs: the first
    seg[1, 8:10] = 0.0
    match_segments(np.array([[3.0, 0.0]]), heading, road, seg, index, rules, lane, s0, d0)
    assert (lane[0], s0[0], d0[0]) == (-1, 0.0, 0.0)  # segment 1 costs NaN
    match_segments(np.array([[300.0, 0.0]]), heading, road, seg, index, rules, lane, s0, d0)
    assert lane[0] == -1
    match_segments(xy, heading, np.zeros(1, dtype=bool), seg, index, rules, lane, s0, d0)
    assert lane[0] == -1  # not a road class


def test_compiled_match_refuses_inputs_of_other_lengths():
    seg, index, rules = np.zeros((2, 12)), np.zeros((2, 3), dtype=np.int64), np.zeros(3)
    lane, s0, d0 = np.empty(2, dtype=np.int64), np.empty(2), np.empty(2)
    with pytest.raises(ValueError):  # one heading for two objects
        match_segments(np.zeros((2, 2)), np.zeros(1), np.ones(2, dtype=bool), seg, index, rules, lane, s0, d0)
    with pytest.raises(ValueError):  # a segment index table of another length
        match_segments(np.zeros((2, 2)), np.zeros(2), np.ones(2, dtype=bool), seg, index[:1], rules, lane, s0, d0)


@pytest.mark.parametrize("name", sorted(bundled_maps()))
def test_compiled_chain_points_equal_numpy_lookups(name):
    """chain_frame's compiled lookup equals chain_points (numpy's searchsorted, clip and gathers) of
    s, s + b and s - b as bytes: arc lengths at the vertices exactly (ties of side="right"), between
    them, past either end of a chain, and NaN."""
    chains = LanePredictor.from_osm(map_path(name), MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG)._chains
    rng = np.random.default_rng(3)
    for p, t in ((1, 1), (4, 3), (30, 51)):
        chain = rng.integers(0, len(chains.first), p)
        at_vertex = chains.cum[rng.integers(chains.first[chain][:, None], chains.last[chain][:, None] + 1, (p, t))]
        s = np.where(rng.random((p, t)) < 0.3, at_vertex, rng.uniform(-1500.0, 2000.0, (p, t)))
        s[rng.random((p, t)) < 0.05] = np.nan
        points = np.empty((p, 3 * t, 2))
        chain_frame_points(chains.key, chains.first, chains.last, chains.vertex, chains.cum, chains.tangent,
                           chains.span, chain, s, HEADING_BASE_M, points)
        want = chain_points(chains, chain, np.concatenate([s, s + HEADING_BASE_M, s - HEADING_BASE_M], axis=1))
        assert points.tobytes() == want.tobytes()
    with pytest.raises(ValueError):  # a chain outside the table
        chain_frame_points(chains.key, chains.first, chains.last, chains.vertex, chains.cum, chains.tangent,
                           chains.span, np.array([len(chains.first)]), np.zeros((1, 1)), HEADING_BASE_M, np.empty((1, 3, 2)))
