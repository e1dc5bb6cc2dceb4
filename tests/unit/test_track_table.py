"""The tracker's preallocated track store against plain TrackTable arithmetic, compact source columns,
and the covariance-intersection fast paths against the row-by-row ones."""

import numpy as np
import pytest

from v2i.fusion.covariance_intersection import ci_update, ci_update_into, ci_weights
from v2i.core.objects import ObjectArray
from v2i.fusion.track_table import SOURCE_BITS, TrackStore, TrackTable
from v2i.fusion.tracking import Tracker, TrackerConfig, slot_source


def random_rows(rng: np.random.Generator, n: int, seen_bits: np.ndarray, first_id: int) -> TrackTable:
    table = TrackTable.empty(4, n, seen_bits)
    for column in table.columns():
        column[...] = rng.normal(size=column.shape) if column.dtype == float else rng.integers(0, 5, column.shape)
    table.ids[:] = np.arange(first_id, first_id + n)
    return table


def assert_tables_equal(a: TrackTable, b: TrackTable) -> None:
    assert len(a) == len(b)
    np.testing.assert_array_equal(a.seen_bits, b.seen_bits)
    for x, y in zip(a.columns(), b.columns()):
        np.testing.assert_array_equal(x, y)


def test_store_appends_keeps_and_loads_like_concatenation_and_masking():
    rng = np.random.default_rng(3)
    bits = np.array([0, 4], np.int64)
    store, reference, next_id = TrackStore(4), TrackTable.empty(4, 0, bits), 1
    store.source_columns(np.array([1 | 16]))  # bits 0 and 4 in use: two seen columns, in that order
    for step in range(60):  # past several capacity doublings (64, 128, ...)
        new = random_rows(rng, int(rng.integers(0, 9)), bits, next_id)
        next_id += len(new)
        store.append(new)
        reference = reference.append(new)
        if step % 3 == 2:
            keep = rng.random(len(reference)) < 0.8
            store.keep(keep)
            reference = reference.take(keep)
        assert_tables_equal(store.view, reference)
    snap = store.snapshot()
    store.view.x[:] += 1.0  # the view writes the store; the snapshot is a copy
    assert not np.array_equal(store.view.x, snap.x)
    store.load(snap)
    assert_tables_equal(store.view, reference)


def test_store_adds_a_column_for_a_source_bit_seen_for_the_first_time():
    store = TrackStore(4)
    cols, union = store.source_columns(np.array([1, 1], np.int64))
    assert union == 1
    assert cols.tolist() == [[True], [True]] and store.view.seen_bits.tolist() == [0]
    store.append(TrackTable.empty(4, 2, store.view.seen_bits))
    store.view.seen_s[:, 0] = [1.0, 2.0]
    cols, union = store.source_columns(np.array([1 | slot_source(3), slot_source(3)], np.int64))
    assert union == 1 | slot_source(3)
    assert store.view.seen_bits.tolist() == [0, 4]
    assert cols.tolist() == [[True, True], [False, True]]
    np.testing.assert_array_equal(store.view.seen_s, [[1.0, -np.inf], [2.0, -np.inf]])


def dets(xy, sources=0):
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    return ObjectArray(ids=np.full(n, -1), cls=np.ones(n, int), xy=xy, z=np.zeros(n), lwh=np.ones((n, 3)),
                       yaw=np.zeros(n), vxy=np.zeros((n, 2)), cov_xy=np.tile(np.eye(2) * 0.25, (n, 1, 1)),
                       sources=np.full(n, sources, np.int64))


def test_tracker_keeps_seen_columns_only_for_the_sources_in_use():
    tracker = Tracker(TrackerConfig())
    for k in range(4):
        t = 0.1 * k
        tracker.predict(t)
        tracker.update(dets([[0.0, 0.0], [30.0, 0.0]]), t, 1)
        tracker.update(dets([[30.0, 0.0]]), t, slot_source(7), estimates=True)
        tracker.prune(t)
    assert tracker._table.seen_bits.tolist() == [0, 8] and tracker._table.seen_s.shape == (2, 2)
    assert sorted(tracker.tracks(0.3).sources.tolist()) == [1, 1 | slot_source(7)]
    assert tracker.snapshot().table.seen_bits.tolist() == [0, 8]
    full = TrackTable.empty(4, 1)  # a table built without seen_bits has one column per bit
    assert full.seen_s.shape == (1, SOURCE_BITS)


def spd(rng: np.random.Generator, k: int, n: int) -> np.ndarray:
    a = rng.normal(size=(k, n, n))
    return a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(n)


def test_ci_weights_of_good_rows_do_not_depend_on_broken_rows_in_the_batch():
    rng = np.random.default_rng(5)
    p, r = spd(rng, 6, 4), spd(rng, 6, 2)
    clean = ci_weights(p, r)
    broken_p, broken_r = p.copy(), r.copy()
    broken_p[1, 0, 0] = np.inf  # not finite
    broken_r[3] = [[1.0, 2.0], [2.0, 1.0]]  # no Cholesky factor
    w = ci_weights(broken_p, broken_r)
    good = [0, 2, 4, 5]
    np.testing.assert_array_equal(w[good], clean[good])
    assert w[1] == 1.0 and w[3] == 1.0


def test_ci_update_into_writes_what_ci_update_returns():
    rng = np.random.default_rng(6)
    p, r = spd(rng, 5, 4), spd(rng, 5, 4)
    x, z = rng.normal(size=(5, 4)), rng.normal(size=(5, 4))
    for w in (ci_weights(p, r), np.array([0.3, 1.0, 0.5, 1.0, 1e-6]), np.ones(5)):
        x_ref, p_ref = ci_update(x, p, z, r, w)
        x_in, p_in = x.copy(), p.copy()
        ci_update_into(x_in, p_in, z, r, w)
        np.testing.assert_array_equal(x_in, x_ref)
        np.testing.assert_array_equal(p_in, p_ref)
        # into rows of a larger table (the tracker's store): the same rows, the others untouched
        rows = np.array([7, 2, 5, 0, 3])
        table_x, table_p = rng.normal(size=(9, 4)), spd(rng, 9, 4)
        table_x[rows], table_p[rows] = x, p
        before_x, before_p = table_x.copy(), table_p.copy()
        ci_update_into(table_x, table_p, z, r, w, rows=rows)
        np.testing.assert_array_equal(table_x[rows], x_ref)
        np.testing.assert_array_equal(table_p[rows], p_ref)
        others = np.setdiff1d(np.arange(9), rows)
        np.testing.assert_array_equal(table_x[others], before_x[others])
        np.testing.assert_array_equal(table_p[others], before_p[others])


@pytest.mark.parametrize("rows", [0, 1, 9])
def test_source_masks_equal_the_sum_of_the_marked_bit_values(rows):
    """The product form equals the old sum of bool x bit value (int64), high bits (62) included."""
    rng = np.random.default_rng(rows)
    bits = np.array([0, 5, 1, 62, 30], np.int64)
    table = TrackTable.empty(4, rows, bits)
    recent = rng.random((rows, len(bits))) < 0.5
    got = table.source_masks(recent)
    want = (recent * (np.int64(1) << bits)).sum(axis=1).astype(np.int64)
    assert got.dtype == np.int64 and got.shape == (rows,) and np.array_equal(got, want)
    assert np.array_equal(table.source_masks(np.ones((rows, len(bits)), bool)),
                          np.full(rows, int(sum(1 << int(b) for b in bits)), np.int64))
