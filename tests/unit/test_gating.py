"""v2i.fusion.gating's compiled gate against the dense numpy definition: every (track, detection)
pair's distance and Mahalanobis distance, the gate and the class rule, in the same order."""

import numpy as np
import pytest

from v2i.fusion.gating import assign_pairs, associate, gated_pairs, gated_pairs_reference
from v2i.core.objects import ObjectArray
from v2i.fusion.track_table import TrackTable
from v2i.fusion.tracking import TrackerConfig


def random_spd(rng, k, scale):
    a = rng.normal(0, 1, (k, 2, 2)) * scale[:, None, None]
    return a @ a.transpose(0, 2, 1) + 0.01 * np.eye(2)


def scene(rng, n_tracks, n_dets):
    """Tracks (CV) and detections over 60 m, covariances over two decades, five classes with UNKNOWN."""
    table = TrackTable.empty(4, n_tracks)
    table.x[:, :2] = rng.uniform(-30, 30, (n_tracks, 2))
    table.p[:, :2, :2] = random_spd(rng, n_tracks, 10.0 ** rng.uniform(-1, 1, n_tracks))
    table.cls[:] = rng.integers(0, 5, n_tracks)
    xy = table.x[rng.integers(0, n_tracks, n_dets), :2] + rng.normal(0, 3, (n_dets, 2))  # near some tracks
    dets = ObjectArray(ids=np.arange(n_dets), cls=rng.integers(0, 5, n_dets), xy=xy, z=np.zeros(n_dets),
                       lwh=np.ones((n_dets, 3)), yaw=np.zeros(n_dets), vxy=np.zeros((n_dets, 2)),
                       cov_xy=random_spd(rng, n_dets, 10.0 ** rng.uniform(-1, 0.5, n_dets)))
    return table, dets


@pytest.mark.parametrize("gate", ["distance", "mahalanobis", "either"])
@pytest.mark.parametrize("cost", ["distance", "mahalanobis"])
def test_compiled_gate_equals_the_dense_definition(gate, cost):
    config = TrackerConfig(gate=gate, cost=cost)
    rng = np.random.default_rng(10 * len(gate) + len(cost))
    pairs_seen = 0
    for n_tracks, n_dets in [(1, 1), (3, 40), (60, 5), (200, 120)] * 5:
        table, dets = scene(rng, n_tracks, n_dets)
        got = gated_pairs(config, table, dets)
        ti, di, ref_cost = gated_pairs_reference(config, table, dets)
        np.testing.assert_array_equal(got.track, ti)
        np.testing.assert_array_equal(got.det, di)
        np.testing.assert_allclose(got.cost, ref_cost, rtol=1e-12, atol=0)
        pairs_seen += len(ti)
    assert pairs_seen > 500  # the gate passed pairs, and (below) refused some
    assert pairs_seen < 5 * (1 + 3 * 40 + 60 * 5 + 200 * 120)


def test_a_crowded_gate_grows_its_pair_buffer():
    """Every track within every detection's gate: more pairs than the kernel's first buffer (4 (N + M))."""
    table, dets = scene(np.random.default_rng(1), 30, 30)
    table.x[:, :2], table.cls[:] = 0.0, 0
    got = gated_pairs(TrackerConfig(gate="distance", gate_m=1e3), table, dets)
    assert len(got.track) == 900
    np.testing.assert_array_equal(got.track, np.repeat(np.arange(30), 30))
    np.testing.assert_array_equal(got.det, np.tile(np.arange(30), 30))


@pytest.mark.parametrize("gate", ["distance", "mahalanobis", "either"])
@pytest.mark.parametrize("cost", ["distance", "mahalanobis", "iou"])
def test_associate_equals_the_solver_path_on_single_pair_lists_and_the_rest(gate, cost):
    """associate's one-call path (every gated pair a component of its own) gives assign_pairs' matching of
    gated_pairs, array for array and dtype for dtype; lists with shared components take that path itself."""
    config = TrackerConfig(gate=gate, cost=cost)
    rng = np.random.default_rng(7 * len(gate) + len(cost))
    kinds = set()
    for n_tracks, n_dets in [(1, 1), (2, 1), (4, 3), (8, 6), (30, 20), (0, 3), (3, 0)] * 12:
        table, dets = scene(rng, max(n_tracks, 1), n_dets)
        if not n_tracks:
            table = TrackTable.empty(4, 0)
        if rng.random() < 0.5:  # tracks and detections spread apart: mostly single pairs
            table.x[:, :2] *= 4.0
            dets = dets.with_(xy=dets.xy * 4.0)
        got = associate(config, table, dets)
        want = assign_pairs(gated_pairs(config, table, dets), len(table), len(dets))
        for name in ("matches", "unmatched_a", "unmatched_b"):
            g, w = getattr(got, name), getattr(want, name)
            assert g.dtype == w.dtype and g.shape == w.shape and np.array_equal(g, w), name
        pairs = gated_pairs(config, table, dets)
        single = len(np.unique(pairs.track)) == len(pairs.track) and len(np.unique(pairs.det)) == len(pairs.det)
        kinds.add((single, len(pairs.track) > 0))
    assert {(True, True), (False, True)} <= kinds  # both paths ran, on lists with pairs
