"""The compiled line-of-sight test (v2i.sim.occlusion._blocked) against the numpy reference (every segment
against every occluder as arrays): the same visible fractions, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from v2i.sim import occlusion
from v2i.sim.occlusion import box_points, visible_fraction


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


def _fractions(compiled: bool, *args, **kwargs) -> np.ndarray:
    saved, occlusion.COMPILED = occlusion.COMPILED, compiled
    try:
        return visible_fraction(*args, **kwargs)
    finally:
        occlusion.COMPILED = saved


def test_compiled_equals_the_numpy_reference_on_random_scenes():
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


@pytest.mark.parametrize("compiled", [True, False])
def test_target_behind_a_wall_is_hidden_either_way(compiled):
    target = ObjectArray(ids=np.array([0]), cls=np.ones(1, dtype=np.int64), xy=np.array([[-30.0, 0.0]]),
                         z=np.zeros(1), lwh=np.array([[4.0, 2.0, 1.5]]), yaw=np.zeros(1), vxy=np.zeros((1, 2)))
    wall = np.array([[-15.0, 0.0, 1.0, 20.0, 0.0]])  # across the -x axis: bearing +-pi from the origin
    assert _fractions(compiled, np.zeros(2), target, wall)[0] == 0.0
    assert _fractions(compiled, np.zeros(2), target, wall + [0, 30.0, 0, 0, 0])[0] == 1.0


def test_sampled_targets_and_degenerate_segments_agree():
    """Only some targets sampled; the origin on an occluder's corner or on a target's sample point (a
    zero-length segment: NaN and infinite slab parameters): the kernel takes the reference's branch."""
    rng = np.random.default_rng(31)
    for it in range(300):
        n, targets, boxes, polys, origin = _scene(rng, 20, False)
        if boxes is not None and it % 3 == 1:  # an axis-aligned occluder's corner
            boxes[0, 4] = 0.0
            origin = boxes[0, :2] + boxes[0, 2:4] / 2.0
        elif n and it % 3 == 2:  # a target's front-left corner
            origin = box_points(targets.xy[:1], targets.lwh[:1, :2], targets.yaw[:1], 5)[0, 1]
        kw = {"samples": 5, "sampled": rng.random(n) < 0.5}
        np.testing.assert_array_equal(_fractions(True, origin, targets, boxes, polys, **kw),
                                      _fractions(False, origin, targets, boxes, polys, **kw))


def test_boxes_apart_from_a_segment_are_skipped_without_changing_a_fraction():
    """The compiled test skips a box whose circumscribed square (+ REACH_MARGIN_M) misses the segment's
    bounding box: on wide scenes (most boxes apart from most segments), long thin boxes (the square far
    larger than the box) and boxes grazing a segment (a corner on the sensor's row or column), the
    fractions of the reference, which tests every pair."""
    rng = np.random.default_rng(41)
    checked = partly = 0
    for it in range(60):
        n = int(rng.integers(20, 120))
        targets = _targets(rng, n, 150.0)
        if it % 2:
            targets.lwh[:, 0], targets.lwh[:, 1] = rng.uniform(5.0, 20.0, n), rng.uniform(0.2, 0.5, n)
        origin = rng.uniform(-20.0, 20.0, 2)
        if it % 3 == 0:  # grazing: corners exactly on the origin's row and column
            corners = box_points(targets.xy, targets.lwh[:, :2], targets.yaw, 5)[:, 1]
            targets.xy[::3, 1] += origin[1] - corners[::3, 1]
            targets.xy[1::3, 0] += origin[0] - corners[1::3, 0]
        m = int(rng.integers(0, 6))
        boxes = np.column_stack([rng.uniform(-150, 150, (m, 2)), rng.uniform(0.5, 30, (m, 2)), rng.uniform(-4, 4, m)])
        for samples in (5, 9):
            want = _fractions(False, origin, targets, boxes, [], samples=samples)
            got = _fractions(True, origin, targets, boxes, [], samples=samples)
            np.testing.assert_array_equal(got, want)
            checked += n
            partly += int(((want > 0) & (want < 1)).sum())
    assert checked > 5000 and partly > 100


def test_a_sampled_mask_of_another_length_is_refused_either_way():
    targets = _targets(np.random.default_rng(2), 4, 20.0)
    for compiled in (True, False):
        with pytest.raises((ValueError, IndexError)):
            _fractions(compiled, np.zeros(2), targets, None, [], sampled=np.ones(5, dtype=bool))
