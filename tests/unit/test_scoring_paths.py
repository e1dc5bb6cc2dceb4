"""The scoring's shorter expressions (v2i.scoring.metrics) against the numpy expressions they replace,
bit for bit: ranges from the ego, a box's BEV row, a pair's squared error."""

import numpy as np

from v2i.scoring.metrics import _bev_row, _ranges_m
from v2i.core.objects import ObjectArray


def _hard_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 2) points of every scale, with zeros, signed zeros, subnormals, huge values, NaN and inf."""
    xy = rng.normal(0.0, 1.0, (n, 2)) * 10.0 ** rng.integers(-6, 6, (n, 2))
    specials = np.array([0.0, -0.0, 5e-324, -5e-324, 1e-160, 1e154, 1e200, -1e200, np.nan, np.inf, -np.inf, 80.0])
    pick = rng.random((n, 2)) < 0.1
    xy[pick] = rng.choice(specials, int(pick.sum()))
    return xy


def test_ranges_equal_linalg_norm_bit_for_bit():
    rng = np.random.default_rng(3)
    with np.errstate(over="ignore", invalid="ignore"):
        for n in (0, 1, 2, 7, 1000):
            xy = _hard_points(rng, n)
            assert _ranges_m(xy).tobytes() == np.linalg.norm(xy, axis=1).tobytes()


def test_squared_error_of_two_terms_equals_sum_of_squares():
    rng = np.random.default_rng(4)
    with np.errstate(over="ignore", invalid="ignore"):
        for a, b in zip(_hard_points(rng, 4000), _hard_points(rng, 4000)):
            err = b - a
            ex, ey = b[0] - a[0], b[1] - a[1]
            got, want = ex * ex + ey * ey, float(np.sum(np.square(err)))
            assert np.array([got]).tobytes() == np.array([want]).tobytes()


def test_bev_row_equals_the_concatenation():
    rng = np.random.default_rng(5)
    n = 50
    objs = ObjectArray(ids=np.arange(n), cls=np.zeros(n, np.int64), xy=_hard_points(rng, n), z=np.zeros(n),
                       lwh=np.abs(rng.normal(3.0, 1.0, (n, 3))), yaw=rng.uniform(-4.0, 4.0, n), vxy=np.zeros((n, 2)))
    for i in range(n):
        want = np.concatenate([objs.xy[i], objs.lwh[i, :2], [objs.yaw[i]]])
        assert np.array(_bev_row(objs, i)).tobytes() == want.tobytes()


def _hard_boxes(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 5) boxes [x, y, l, w, yaw]: overlapping, touching, apart, degenerate and NaN."""
    boxes = np.column_stack([rng.normal(0.0, 3.0, (n, 2)), rng.uniform(0.0, 6.0, (n, 2)), rng.uniform(-4.0, 4.0, n)])
    pick = rng.random(n)
    boxes[pick < 0.05, 2] = 0.0
    boxes[(pick >= 0.05) & (pick < 0.08), 0] = np.nan
    boxes[(pick >= 0.08) & (pick < 0.2), :2] *= 20.0
    return boxes


def test_bev_iou_pairs_equal_the_matrix_row_by_row_on_hard_boxes():
    from v2i.fusion.geometry import bev_iou_matrix, bev_iou_pairs

    rng = np.random.default_rng(6)
    for n in (0, 1, 3, 2000):
        a, b = _hard_boxes(rng, n), _hard_boxes(rng, n)
        b[: n // 3] = a[: n // 3] + rng.normal(0.0, 0.3, (n // 3, 5))  # near twins
        b[n // 3: n // 3 + 5] = a[n // 3: n // 3 + 5]  # identical
        want = np.array([bev_iou_matrix(x[None], y[None])[0, 0] for x, y in zip(a, b)])
        got = bev_iou_pairs(a, b)
        assert got.tobytes() == want.tobytes()
        assert n < 2000 or 0 < np.count_nonzero(got) < n


class _ReferenceTargetTally:
    """The previous TargetTally: each pair's IoU, NEES and distance computed when it is added; its id
    switches motmetrics' (a MotTally of the kept outputs and the actors within 80 m, distances its own)."""

    def __init__(self, target_id: int, sources_mask: int | None = None):
        from v2i.scoring.detection_metrics import MotTally

        self.target_id, self.sources_mask = target_id, sources_mask
        self.rows: list[tuple] = []
        self.mot = MotTally()

    def add(self, frame) -> None:
        from v2i.scoring.detection_metrics import nees_values
        from v2i.scoring.metrics import _match_target_cost
        from v2i.fusion.geometry import bev_iou_matrix

        truth, out = frame.truth, frame.out
        near_t = np.linalg.norm(truth.xy, axis=1) <= 80.0
        near_o = np.linalg.norm(out.xy, axis=1) <= 80.0
        if self.sources_mask is not None:
            near_o &= (out.sources & self.sources_mask) != 0
        self.mot.add_frame(truth.ids[near_t], truth.xy[near_t], out.ids[near_o], out.xy[near_o])
        rows = np.flatnonzero(truth.ids == self.target_id)
        if self.sources_mask is None:
            k = _match_target_cost(frame.distances_m, truth.ids, self.target_id, rows)
        else:
            kept = np.flatnonzero(out.sources & self.sources_mask)
            k = _match_target_cost(frame.distances_m[:, kept], truth.ids, self.target_id, rows)
            k = None if k is None else int(kept[k])
        if k is None:
            return
        i = int(rows[0])
        err = out.xy[k] - truth.xy[i]
        box = lambda o, r: np.concatenate([o.xy[r], o.lwh[r, :2], [o.yaw[r]]])  # noqa: E731
        self.rows.append((frame.cycle_ns, frame.t_s, float(bev_iou_matrix(box(truth, i)[None], box(out, k)[None])[0, 0]),
                          float(np.sum(np.square(err))), float(nees_values(err[None], out.cov_xy[k][None])[0]),
                          float(np.linalg.norm(truth.xy[i])), int(out.ids[k])))

    def score(self):
        from v2i.scoring.detection_metrics import nees_summary
        from v2i.scoring.metrics import TargetScore

        order = np.argsort(np.array([r[0] for r in self.rows], dtype=np.int64), kind="stable")
        col = {name: np.array([r[j] for r in self.rows], dtype=float)[order]
               for j, name in ((1, "t_s"), (2, "iou"), (3, "sq_err"), (4, "eps"), (5, "dist"))}
        consistency = nees_summary(col["eps"])
        detected = len(order)
        ids = np.array([r[6] for r in self.rows], dtype=np.int64)[order]
        return TargetScore(
            detected_cycles=detected,
            mean_bev_iou=float(np.mean(col["iou"])) if detected else None,
            rmse_m=float(np.sqrt(np.mean(col["sq_err"]))) if detected else None,
            first_detection_distance_m=float(col["dist"][0]) if detected else None,
            first_detection_time_s=float(col["t_s"][0]) if detected else None,
            nees_mean=consistency["mean"], nees_fraction_inside=consistency["fraction_inside"],
            track_ids=len(np.unique(ids)), id_switches=self.mot.switches_of[self.target_id])


def _frames(rng: np.random.Generator, count: int) -> list:
    """CycleFrames of 1-6 truths (the target id 7 among them most of the time) and noisy outputs, in a
    shuffled cycle order, with random position covariances."""
    from v2i.scoring.metrics import CycleFrame

    frames = []
    for c in rng.permutation(count):
        g = int(rng.integers(1, 7))
        ids = rng.choice(np.arange(1, 12), g, replace=False)
        if rng.random() < 0.8:
            ids[0] = 7
        xy = rng.normal(0.0, 30.0, (g, 2))
        lwh, yaw = rng.uniform(0.5, 5.0, (g, 3)), rng.uniform(-3.0, 3.0, g)
        truth = ObjectArray(ids=ids, cls=np.zeros(g, np.int64), xy=xy, z=np.zeros(g), lwh=lwh, yaw=yaw,
                            vxy=np.zeros((g, 2)))
        seen = rng.random(g) < 0.85
        p = int(seen.sum())
        a = rng.normal(0.0, 0.5, (p, 2, 2))
        out = ObjectArray(ids=rng.integers(100, 110, p), cls=np.zeros(p, np.int64),
                          xy=xy[seen] + rng.normal(0.0, rng.choice([0.2, 1.5]), (p, 2)), z=np.zeros(p),
                          lwh=lwh[seen] + rng.normal(0.0, 0.2, (p, 3)), yaw=yaw[seen] + rng.normal(0.0, 0.1, p),
                          vxy=np.zeros((p, 2)), cov_xy=a @ a.transpose(0, 2, 1) + 0.05 * np.eye(2),
                          sources=rng.integers(1, 8, p))
        frames.append(CycleFrame(int(c) * 100_000_000, 0.1 * int(c), truth, out))
    return frames


def test_target_tally_scores_as_each_pair_scored_alone(monkeypatch):
    """IoU and NEES computed in batches of pending cycles (``PENDING``, or at ``score``) give the scores
    of the previous per-pair computation, bit for bit (fails with the batches' order shuffled)."""
    from v2i.scoring.metrics import TargetTally

    rng = np.random.default_rng(7)
    for pending in (64, 3, 1):
        monkeypatch.setattr(TargetTally, "PENDING", pending)
        frames = _frames(rng, 150)
        for mask in (None, 1, 6):
            got, want = TargetTally(7, mask), _ReferenceTargetTally(7, mask)
            for frame in frames:
                got.add(frame)
                want.add(frame)
            assert repr(got.score()) == repr(want.score())
            assert got.score().detected_cycles > 20
