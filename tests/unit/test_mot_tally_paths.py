"""MotTally's per-frame steps (fewer numpy calls) against the previous code: the same counts, pairs,
last matches and distance sum, bit for bit, after every frame."""

from collections import Counter

import numpy as np

from v2i.scoring.detection_metrics import MotTally, _distance_matrix, _id_list
from v2i.fusion.association import center_distance_cost
from v2i.fusion.lsap import linear_sum_assignment

from test_detection_metrics import generated_tracks


def _legacy_lsa_nan(dist: np.ndarray) -> list[tuple[int, int]]:
    """motmetrics' scipy assignment (``lap.lsa_solve_scipy``): NaN pairs cost a constant too
    large to be chosen, l = 2 r c + 1 with r = min(N, M) and c = max |finite cost| + 1, so
    that scipy returns the same pairs (ties included); pairs on NaN are dropped."""
    valid = np.isfinite(dist)
    if not valid.any():
        return []
    large = 2 * min(dist.shape) * (np.abs(dist[valid]).max() + 1) + 1
    rows, cols = linear_sum_assignment(np.where(valid, dist, large))
    return [(int(i), int(j)) for i, j in zip(rows, cols) if valid[i, j]]


class LegacyMotTally:
    """``mot_metrics`` frame by frame, with motmetrics' MOTAccumulator algorithm (max_switch_time
    inf) and its metrics: per frame (1) a truth keeps the hypothesis it last matched if that
    one is present and within the gate, (2) the rest are assigned by minimum total distance
    (``_lsa_nan``), a truth assigned a hypothesis other than its last is an identity switch,
    (3) unassigned truths are misses, unassigned hypotheses false positives.
    IDF1 needs only frame counts per truth id, per hypothesis id and per (truth, hypothesis)
    pair within the gate: IDTP is the largest total pair count of a one-to-one id matching.
    Memory: those counts and the last match per truth id, none per frame.
    """

    def __init__(self, max_distance_m: float = 2.0):
        self.max_distance_m = max_distance_m
        self._last: dict[int, int] = {}  # truth id -> hypothesis id it last matched (motmetrics' ``m``)
        self._pairs: Counter = Counter()  # (truth id, hyp id) -> frames within the gate
        self.frames = self.matches = self.switches = self.misses = self.false_positives = 0
        self.num_truth = self.num_predictions = 0
        self._distance_sum_m = 0.0

    def add_frame(self, truth_ids, truth_xy, hyp_ids, hyp_xy, cost_m: np.ndarray | None = None) -> None:
        """Truth ids (N,), truth xy (N, 2) m, hypothesis ids (M,), hypothesis xy (M, 2) m; ``cost_m``:
        their centre distances (N, M) m when the caller has them (``center_distance_cost``)."""
        oids, hids = np.ravel(truth_ids).astype(np.int64).tolist(), np.ravel(hyp_ids).astype(np.int64).tolist()
        if cost_m is None or not cost_m.size:
            dist = _distance_matrix(truth_xy, hyp_xy, self.max_distance_m)
        else:  # _distance_matrix from the distances
            dist = np.where(cost_m > self.max_distance_m, np.nan, cost_m)
        self.frames += 1
        self.num_truth, self.num_predictions = self.num_truth + len(oids), self.num_predictions + len(hids)
        finite = np.isfinite(dist)
        rows, cols = np.nonzero(finite)
        self._pairs.update(zip([oids[i] for i in rows.tolist()], [hids[j] for j in cols.tolist()]))
        pairs = self._match(oids, hids, dist, finite) if oids and hids else []
        self.misses += len(oids) - len(pairs)
        self.false_positives += len(hids) - len(pairs)

    def _match(self, oids: list[int], hids: list[int], dist: np.ndarray, finite: np.ndarray) -> list[tuple[int, int]]:
        """Steps (1) and (2): matched (truth index, hyp index) pairs; counts matches and switches.
        ``finite`` (N, M): the pairs that may pair (``np.isfinite(dist)``)."""
        pairs, free_h = [], [True] * len(hids)
        columns: dict[int, list[int]] = {}  # hypothesis id -> its indices in hids, ascending
        for j, h in enumerate(hids):
            columns.setdefault(h, []).append(j)
        for i, o in enumerate(oids):
            h = self._last.get(o)
            if h is None or h not in columns:
                continue
            for j in columns[h]:  # the first free one
                if free_h[j]:
                    if finite[i, j]:
                        pairs.append((i, j))
                        free_h[j] = False
                    break
        self.matches += len(pairs)
        if len(pairs) < len(oids) and len(pairs) < len(hids):  # else no pair is left for step (2)
            pairs += self._assign_rest(oids, hids, dist, pairs, free_h)
        total_m = 0  # summed in pair order, as before
        for d_m in dist[[i for i, _ in pairs], [j for _, j in pairs]].tolist() if pairs else ():
            total_m += d_m
        self._distance_sum_m += float(total_m)
        return pairs

    def _assign_rest(self, oids: list[int], hids: list[int], dist: np.ndarray, pairs: list[tuple[int, int]],
                     free_h: list[bool]) -> list[tuple[int, int]]:
        """Step (2): the free truths and hypotheses assigned (``_lsa_nan`` of the distances without the
        pairs of step (1)); counts matches and switches."""
        rest = dist.copy()
        rest[[i for i, _ in pairs], :] = np.nan
        rest[:, [not free for free in free_h]] = np.nan
        assigned = _legacy_lsa_nan(rest)
        for i, j in assigned:
            o, h = oids[i], hids[j]
            if o in self._last and self._last[o] != h:
                self.switches += 1
            else:
                self.matches += 1
            self._last[o] = h
        return assigned


def _state(tally) -> tuple:
    return (tally.frames, tally.matches, tally.switches, tally.misses, tally.false_positives, tally.num_truth,
            tally.num_predictions, tally._distance_sum_m, dict(tally._last), dict(tally._pairs))


def test_mot_tally_equals_the_previous_code_frame_by_frame():
    rng = np.random.default_rng(5)
    frames_seen = switches = 0
    for _ in range(30):
        frames = generated_tracks(rng, int(rng.integers(1, 60)))
        for with_cost in (False, True):
            new, old = MotTally(), LegacyMotTally()
            for truth_ids, truth_xy, hyp_ids, hyp_xy in frames:
                cost = center_distance_cost(truth_xy, hyp_xy) if with_cost and len(truth_xy) and len(hyp_xy) else None
                new.add_frame(truth_ids, truth_xy, hyp_ids, hyp_xy, cost)
                old.add_frame(truth_ids, truth_xy, hyp_ids, hyp_xy, cost)
                assert _state(new) == _state(old)
                frames_seen += 1
            switches += new.switches
    assert frames_seen > 1000 and switches > 10


def test_id_list_equals_ravel_astype():
    for ids in (np.arange(5), np.arange(6, dtype=np.int32).reshape(2, 3), [3, 1, 2], np.zeros(0), np.array([7.0, 2.0])):
        assert _id_list(ids) == np.ravel(ids).astype(np.int64).tolist()
        assert all(type(v) is int for v in _id_list(ids))
