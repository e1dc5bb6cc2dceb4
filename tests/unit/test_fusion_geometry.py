import numpy as np
import pytest
import shapely

from v2i.fusion.geometry import (
    bev_iou,
    bev_iou_matrix,
    bev_iou_pairs,
    box_corners,
    box_polygons,
)
from v2i.fusion.merger import iou_merge
from v2i.core.objects import ObjectArray


def boxes_objs(boxes):
    b = np.asarray(boxes, float).reshape(-1, 5)
    n = len(b)
    return ObjectArray(ids=np.arange(n), cls=np.ones(n, int), xy=b[:, :2], z=np.zeros(n),
                       lwh=np.column_stack([b[:, 2:4], np.full(n, 1.5)]), yaw=b[:, 4], vxy=np.zeros((n, 2)))


@pytest.mark.parametrize(
    "a, b, expected",
    [
        ([0, 0, 4, 2, 0], [0, 0, 4, 2, 0], 1.0),
        ([0, 0, 4, 2, 0], [10, 0, 4, 2, 0], 0.0),
        ([0, 0, 2, 2, 0], [1, 0, 2, 2, 0], 1 / 3),  # overlap 2 of union 6
        ([0, 0, 2, 2, 0], [0, 0, 2, 2, np.pi / 2], 1.0),  # a square turned 90 degrees is itself
        ([0, 0, 4, 2, 0], [0, 0, 4, 2, np.pi / 2], 4 / 12),  # cross: 2x2 overlap, union 8 + 8 - 4
    ],
)
def test_bev_iou_known_values(a, b, expected):
    assert bev_iou(a, b) == pytest.approx(expected, abs=1e-9)


def test_bev_iou_matrix_equals_pairwise_shapely():
    rng = np.random.default_rng(3)
    a = np.column_stack([rng.uniform(-5, 5, (20, 2)), rng.uniform(1, 5, (20, 2)), rng.uniform(-np.pi, np.pi, 20)])
    b = np.column_stack([rng.uniform(-5, 5, (15, 2)), rng.uniform(1, 5, (15, 2)), rng.uniform(-np.pi, np.pi, 15)])
    iou = bev_iou_matrix(a, b)
    pa, pb = box_polygons(a), box_polygons(b)
    for i in range(len(a)):
        for j in range(len(b)):
            inter = pa[i].intersection(pb[j]).area
            assert iou[i, j] == pytest.approx(inter / (pa[i].area + pb[j].area - inter), abs=1e-9)


def test_bev_iou_pairs_equal_the_matrix_bit_for_bit():
    """bev_iou_pairs(a, b)[k] is bev_iou_matrix(a[k][None], b[k][None])[0, 0] as float64 bits, pair by pair and
    in one call: overlapping,
    nested, equal and far boxes, and pairs at the skip test's boundary (centre distance = the half
    diagonals' sum, to the last bit on either side)."""
    rng = np.random.default_rng(11)
    a = np.column_stack([rng.uniform(-6, 6, (3000, 2)), rng.uniform(0.1, 8, (3000, 2)), rng.uniform(-4, 4, 3000)])
    b = np.column_stack([rng.uniform(-6, 6, (3000, 2)), rng.uniform(0.1, 8, (3000, 2)), rng.uniform(-4, 4, 3000)])
    b[:300] = a[:300]  # equal boxes
    b[300:600, :2] = a[300:600, :2]  # the same centre, other sizes and yaws
    reach = 0.5 * (np.hypot(a[:, 2], a[:, 3]) + np.hypot(b[:, 2], b[:, 3]))
    b[600:900, 0] = a[600:900, 0] + reach[600:900]  # on the boundary along x
    b[600:900, 1] = a[600:900, 1]
    b[900:1000, 0] = np.nextafter(b[600:700, 0], -np.inf)
    b[900:1000, 1] = a[600:700, 1]
    b[900:1000, 2:] = b[600:700, 2:]
    a[900:1000] = a[600:700]
    overlapping = 0
    for x, y in zip(a, b):
        want = bev_iou_matrix(x[None], y[None])[0, 0]
        got = bev_iou_pairs(x[None], y[None])[0]
        assert got.tobytes() == want.tobytes(), (x, y, got, want)
        overlapping += got > 0
    assert 1000 < overlapping < 3000  # both branches taken
    want = np.array([bev_iou_matrix(x[None], y[None])[0, 0] for x, y in zip(a, b)])
    assert bev_iou_pairs(a, b).tobytes() == want.tobytes()


def test_box_corners_rotate_about_centre():
    corners = box_corners([[1.0, 2.0, 4.0, 2.0, np.pi / 2]])[0]
    assert shapely.Polygon(corners).area == pytest.approx(8.0)
    np.testing.assert_allclose(corners.mean(axis=0), [1.0, 2.0])
    np.testing.assert_allclose(np.ptp(corners, axis=0), [2.0, 4.0], atol=1e-12)  # long side now along y


def test_iou_merge_drops_rsu_duplicates_keeps_the_rest():
    own = boxes_objs([[0, 0, 4, 2, 0]])
    rsu = boxes_objs([[0.3, 0.1, 4, 2, 0.05], [30, 0, 4, 2, 0]])
    merged = iou_merge(own, rsu, iou_threshold=0.1)
    assert len(merged) == 2
    np.testing.assert_allclose(merged.xy, [[0, 0], [30, 0]])


def test_the_compiled_iou_equals_shapely_on_hard_pairs():
    """iou_rows (Sutherland-Hodgman clipping) against shapely's intersection: random overlapping
    pairs, equal boxes, nested ones, the same centre turned 90 degrees, edges that touch or are
    collinear, slivers, and degenerate boxes of zero width."""
    from v2i.fusion.geometry import iou_rows

    rng = np.random.default_rng(17)
    n = 4000
    a = np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.uniform(0.2, 6, (n, 2)), rng.uniform(-4, 4, n)])
    b = np.column_stack([a[:, :2] + rng.normal(0, 1.5, (n, 2)), rng.uniform(0.2, 6, (n, 2)), rng.uniform(-4, 4, n)])
    b[:200] = a[:200]  # equal
    b[200:400, :2], b[200:400, 2:4] = a[200:400, :2], 0.5 * a[200:400, 2:4]  # nested, other yaws
    b[400:600], b[400:600, 4] = a[400:600], a[400:600, 4] + np.pi / 2  # the same box turned 90 degrees
    b[600:800], b[600:800, 4] = a[600:800], a[600:800, 4]  # then shifted by its own length: edges touch
    b[600:800, 0] += a[600:800, 2] * np.cos(a[600:800, 4])
    b[600:800, 1] += a[600:800, 2] * np.sin(a[600:800, 4])
    b[800:1000], b[800:1000, 0] = a[800:1000], a[800:1000, 0] + 1e-9  # slivers of each other
    a[1000:1100, 3] = 0.0  # zero width
    pa, pb = box_polygons(a), box_polygons(b)
    inter = shapely.area(shapely.intersection(pa, pb))
    union = shapely.area(pa) + shapely.area(pb) - inter
    want = np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
    got = iou_rows(a, b)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert np.all(got[:200] == pytest.approx(1.0)) and np.all(got[600:800] < 1e-9) and np.all(got[1000:1100] < 1e-12)
