"""The scoring of one output computes the truth-to-output centre distances once (``CycleFrame.distances_m``)
and every tally takes its rows and columns: the same bits as each tally's own ``center_distance_cost``."""

import numpy as np

from v2i.scoring.detection_metrics import CenterDistanceAp, MotTally, _distance_matrix, _lsa_nan
from v2i.scoring.metrics import MAX_RANGE_M, RANGE_BINS_M, CycleFrame, DetectionTally, TargetTally, _match_target_xy
from v2i.fusion.association import center_distance_cost
from v2i.core.objects import ObjectArray

from test_detection_metrics import generated_tracks


def _objects(rng: np.random.Generator, xy: np.ndarray, ids: np.ndarray) -> ObjectArray:
    n = len(xy)
    return ObjectArray(ids=ids.astype(np.int64), cls=np.ones(n, dtype=np.int64), xy=xy, z=np.zeros(n),
                       lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=rng.uniform(-3.0, 3.0, n), vxy=np.zeros((n, 2)),
                       confidence=np.round(rng.random(n), 1), cov_xy=np.tile(np.eye(2) * 0.2, (n, 1, 1)),
                       sources=rng.integers(1, 8, n))


def _frames(seed: int, count: int) -> list[CycleFrame]:
    """Frames of 0-12 actors over +-100 m (across the range bins and MAX_RANGE_M), each output near an
    actor or anywhere, on a coarse grid: tied distances, shared nearest actors, duplicated ids."""
    rng = np.random.default_rng(seed)
    frames = []
    for f in range(count):
        truth_xy = np.round(rng.uniform(-100.0, 100.0, (rng.integers(0, 13), 2)))
        near = truth_xy[rng.integers(0, len(truth_xy), rng.integers(0, 10))] if len(truth_xy) else np.zeros((0, 2))
        out_xy = np.vstack([np.round(near + rng.normal(0.0, rng.choice([0.5, 2.0]), near.shape), 1),
                            rng.uniform(-100.0, 100.0, (rng.integers(0, 3), 2))])
        truth = _objects(rng, truth_xy, rng.permutation(len(truth_xy)) + 1)
        out = _objects(rng, out_xy, rng.integers(100, 106, len(out_xy)))
        frames.append(CycleFrame(f, 0.1 * f, truth, out))
    return frames


def test_any_rows_and_columns_of_the_frame_distances_are_their_own_costs():
    rng = np.random.default_rng(1)
    for frame in _frames(1, 300):
        truth, out = frame.truth.xy, frame.out.xy
        t, o = rng.random(len(truth)) < 0.7, rng.random(len(out)) < 0.7
        whole = frame.distances_m
        assert whole.tobytes() == center_distance_cost(truth, out).tobytes()
        assert whole[t][:, o].tobytes() == center_distance_cost(truth[t], out[o]).tobytes()
        assert np.ascontiguousarray(whole[t][:, o].T).tobytes() == center_distance_cost(out[o], truth[t]).tobytes()


def test_tallies_given_the_frame_distances_equal_their_own_costs():
    """CenterDistanceAp and MotTally fed the frame's distances score as when they compute them; the
    tallies of a run (DetectionTally, TargetTally with and without a sources mask) as those."""
    ap_own, ap_given = CenterDistanceAp(range_bins_m=RANGE_BINS_M), CenterDistanceAp(range_bins_m=RANGE_BINS_M)
    mot_own, mot_given = MotTally(), MotTally()
    detection = DetectionTally()
    targets = [TargetTally(target_id, mask) for target_id in (1, 2, 3) for mask in (None, 1, 6)]
    for frame in _frames(2, 400):
        truth, out = frame.truth, frame.out
        t = np.linalg.norm(truth.xy, axis=1) <= MAX_RANGE_M
        o = np.linalg.norm(out.xy, axis=1) <= MAX_RANGE_M
        ap_own.add_frame(truth.xy[t], out.xy[o], out.confidence[o])
        mot_own.add_frame(truth.ids[t], truth.xy[t], out.ids[o], out.xy[o])
        cost = center_distance_cost(truth.xy[t], out.xy[o]) if t.any() and o.any() else np.zeros((t.sum(), o.sum()))
        ap_given.add_frame(truth.xy[t], out.xy[o], out.confidence[o], cost)
        mot_given.add_frame(truth.ids[t], truth.xy[t], out.ids[o], out.xy[o], cost)
        detection.add(frame)
        for tally in targets:
            tally.add(frame)
    assert ap_given.result() == ap_own.result() and detection.ap.result() == ap_own.result()
    assert mot_given.result() == mot_own.result() and detection.mot.result() == mot_own.result()
    assert mot_own.result()["id_switches"] > 0
    for tally in targets:  # the output each cycle matched, against _match_target_xy on the kept outputs alone
        cycles, ids, xy = [], [], []
        for frame in _frames(2, 400):
            out = frame.out
            kept = np.arange(len(out)) if tally.sources_mask is None else np.flatnonzero(out.sources & tally.sources_mask)
            k = _match_target_xy(frame.truth.xy, frame.truth.ids, out.xy[kept], tally.target_id)
            if k is not None:
                cycles.append(frame.cycle_ns), ids.append(int(out.ids[kept[k]])), xy.extend(out.xy[kept[k]].tolist())
        assert len(cycles) > 10
        assert (list(tally._cycle_ns), list(tally._ids), list(tally._out_xy)) == (cycles, ids, xy)


class _MotTallyBefore(MotTally):
    """MotTally's frame step as it was before the distances were shared (the reference)."""

    def add_frame(self, truth_ids, truth_xy, hyp_ids, hyp_xy, cost_m=None) -> None:
        oids, hids = [int(i) for i in np.ravel(truth_ids)], [int(h) for h in np.ravel(hyp_ids)]
        dist = _distance_matrix(truth_xy, hyp_xy, self.max_distance_m)
        self.frames += 1
        self.num_truth, self.num_predictions = self.num_truth + len(oids), self.num_predictions + len(hids)
        rows, cols = np.nonzero(np.isfinite(dist))
        self._pairs.update(zip([oids[i] for i in rows.tolist()], [hids[j] for j in cols.tolist()]))
        pairs = self._match_before(oids, hids, dist) if oids and hids else []
        self.misses += len(oids) - len(pairs)
        self.false_positives += len(hids) - len(pairs)

    def _match_before(self, oids, hids, dist):
        pairs, free_h = [], [True] * len(hids)
        columns: dict[int, list[int]] = {}
        for j, h in enumerate(hids):
            columns.setdefault(h, []).append(j)
        finite = np.isfinite(dist)
        for i, o in enumerate(oids):
            h = self._last.get(o)
            if h is None or h not in columns:
                continue
            for j in columns[h]:
                if free_h[j]:
                    if finite[i, j]:
                        pairs.append((i, j))
                        free_h[j] = False
                    break
        self.matches += len(pairs)
        rest = dist.copy()
        rest[[i for i, _ in pairs], :] = np.nan
        rest[:, [not free for free in free_h]] = np.nan
        for i, j in _lsa_nan(rest):
            o, h = oids[i], hids[j]
            if o in self._last and self._last[o] != h:
                self.switches += 1
            else:
                self.matches += 1
            self._last[o] = h
            pairs.append((i, j))
        total_m = 0
        for d_m in dist[[i for i, _ in pairs], [j for _, j in pairs]].tolist() if pairs else ():
            total_m += d_m
        self._distance_sum_m += float(total_m)
        return pairs


def test_mot_tally_equals_its_step_before_the_shared_distances_bit_for_bit():
    """Step (2) skipped when no truth or no hypothesis is left, the distances read as Python floats:
    the same counts and the same MOTP bits as before, on generated tracks and on the frames above."""
    rng = np.random.default_rng(12)
    cases = [generated_tracks(rng, int(rng.integers(1, 80))) for _ in range(40)]
    cases.append([(f.truth.ids, f.truth.xy, f.out.ids, f.out.xy) for f in _frames(3, 300)])
    switches = 0
    for frames in cases:
        new, before = MotTally(), _MotTallyBefore()
        for frame in frames:
            new.add_frame(*frame)
            before.add_frame(*frame)
        assert new.result() == before.result()
        switches += new.result()["id_switches"]
    assert switches > 10
