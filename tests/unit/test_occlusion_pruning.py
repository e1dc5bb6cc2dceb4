"""Occlusion pruning by bearing and range: the same visible fractions as testing every pair."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.objects import ObjectArray
from sim import occlusion
from sim.occlusion import cone_pairs, segments_hit_boxes, visible_fraction


def _targets(rng, n: int, span_m: float) -> ObjectArray:
    return ObjectArray(
        ids=np.arange(n), cls=np.ones(n, dtype=np.int64), xy=rng.uniform(-span_m, span_m, (n, 2)), z=np.zeros(n),
        lwh=np.column_stack([rng.uniform(0.3, 8, n), rng.uniform(0.3, 3, n), np.ones(n)]),
        yaw=rng.uniform(-np.pi, np.pi, n), vxy=np.zeros((n, 2)),
    )


def _star(rng, centre, k: int = 7) -> np.ndarray:
    ang, rad = np.sort(rng.uniform(0, 2 * np.pi, k)), rng.uniform(1.0, 6.0, k)
    return centre + np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])


def _scene(rng, max_targets: int, origin_on_target: bool):
    """A random scene: (n, n targets, up to 5 boxes (or None), up to 2 star polygons, the sensor origin:
    the first target's centre where origin_on_target and there is one, else anywhere)."""
    n, span_m = int(rng.integers(0, max_targets)), float(rng.choice([5.0, 20.0, 60.0]))
    targets = _targets(rng, n, span_m)
    m = int(rng.integers(0, 6))
    boxes = np.column_stack([rng.uniform(-span_m, span_m, (m, 2)), rng.uniform(0.5, 10, (m, 2)),
                             rng.uniform(-4, 4, m)]) if m else None
    polys = [_star(rng, rng.uniform(-span_m, span_m, 2)) for _ in range(int(rng.integers(0, 3)))]
    origin = targets.xy[0].copy() if origin_on_target and n else rng.uniform(-span_m, span_m, 2)
    return n, targets, boxes, polys, origin


def _fractions(prune: bool, *args, **kwargs) -> np.ndarray:
    saved, occlusion.PRUNE = occlusion.PRUNE, prune
    try:
        return visible_fraction(*args, **kwargs)
    finally:
        occlusion.PRUNE = saved


def test_pruned_equals_every_pair_on_random_scenes():
    rng = np.random.default_rng(11)
    checked = partly = 0
    for it in range(400):
        # origins: anywhere, inside a target's box (its own centre), on the row of every target (bearing +-pi)
        n, targets, boxes, polys, origin = _scene(rng, 50, it % 3 == 0)
        if it % 5 == 0 and n:
            targets.xy[:, 1] = origin[1]
        for samples in (1, 5, 9):
            for targets_occlude in (True, False):
                kw = {"samples": samples, "targets_occlude": targets_occlude}
                want = _fractions(False, origin, targets, boxes, polys, **kw)
                got = _fractions(True, origin, targets, boxes, polys, **kw)
                np.testing.assert_array_equal(got, want)
                checked += n
                partly += int(((want > 0) & (want < 1)).sum())
    assert checked > 10_000 and partly > 500  # scenes where occlusion happens, not only all-or-nothing


def test_cone_pairs_keep_every_hit_and_drop_most_misses():
    rng = np.random.default_rng(5)
    origin = np.array([1.0, -2.0])
    pts = rng.uniform(-80, 80, (2000, 2))
    boxes = np.column_stack([rng.uniform(-80, 80, (60, 2)), rng.uniform(0.5, 6, (60, 2)), rng.uniform(-4, 4, 60)])
    boxes[0, :2] = origin + [0.5, 0.2]  # a box around the origin: every segment is a candidate
    boxes[1, :2] = [-40.0, -2.0]  # straight behind along -x: its bearing span wraps past +-pi
    hits = segments_hit_boxes(np.broadcast_to(origin, pts.shape), pts, boxes)
    q, k = cone_pairs(origin, pts, boxes[:, :2], np.hypot(boxes[:, 2], boxes[:, 3]) / 2.0)
    kept = np.zeros_like(hits)
    kept[q, k] = True
    assert hits[:, 1].any() and not (hits & ~kept).any()
    assert kept[:, 0].all()
    assert kept.sum() < 0.2 * kept.size  # far fewer exact tests than Q x B


def test_cone_pairs_with_no_points_or_circles():
    q, k = cone_pairs(np.zeros(2), np.zeros((0, 2)), np.ones((3, 2)), np.ones(3))
    assert len(q) == len(k) == 0
    q, k = cone_pairs(np.zeros(2), np.ones((4, 2)), np.zeros((0, 2)), np.zeros(0))
    assert len(q) == len(k) == 0


@pytest.mark.parametrize("prune", [True, False])
def test_target_behind_a_wall_is_hidden_either_way(prune):
    target = ObjectArray(ids=np.array([0]), cls=np.ones(1, dtype=np.int64), xy=np.array([[-30.0, 0.0]]),
                         z=np.zeros(1), lwh=np.array([[4.0, 2.0, 1.5]]), yaw=np.zeros(1), vxy=np.zeros((1, 2)))
    wall = np.array([[-15.0, 0.0, 1.0, 20.0, 0.0]])  # across the -x axis: bearing +-pi from the origin
    assert _fractions(prune, np.zeros(2), target, wall)[0] == 0.0
    assert _fractions(prune, np.zeros(2), target, wall + [0, 30.0, 0, 0, 0])[0] == 1.0


def test_every_pair_path_equals_the_pruned_path_on_random_scenes():
    """visible_fraction's small-input path (every (point, occluder) pair through the pruned path's
    own exact tests, up to SMALL_PAIRS pairs) gives the pruned path's fractions on random scenes."""
    rng = np.random.default_rng(23)
    saved = occlusion.SMALL_PAIRS
    try:
        for it in range(300):
            n, targets, boxes, polys, origin = _scene(rng, 30, it % 3 == 0)
            for targets_occlude in (True, False):
                kw = {"samples": 9, "targets_occlude": targets_occlude}
                occlusion.SMALL_PAIRS = 0
                pruned = visible_fraction(origin, targets, boxes, polys, **kw)
                occlusion.SMALL_PAIRS = 10**9
                every = visible_fraction(origin, targets, boxes, polys, **kw)
                np.testing.assert_array_equal(every, pruned)
    finally:
        occlusion.SMALL_PAIRS = saved
