"""ModeInputs reuses an RSU's placement only while it is the same; the RSU period's median."""

from __future__ import annotations

import numpy as np

from v2i.core.objects import ObjectArray
from v2i.clock.clock_sync import OffsetEstimate, SyncSample
from obu_service.mode_inputs import ModeInputs, Received, rsu_period_ns
from obu_service.pipeline import ObuPipelineConfig
from obu_service.rsu_table import RsuTable

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
S = 1_000_000_000
OFFSET_NS = 3 * MS  # rsu clock - obu clock


def _objects(n: int) -> ObjectArray:
    return ObjectArray(ids=np.arange(n), cls=np.ones(n, int), xy=np.zeros((n, 2)), z=np.zeros(n),
                       lwh=np.ones((n, 3)), yaw=np.zeros(n), vxy=np.zeros((n, 2)))


def _synced_state(table: RsuTable, t_ns: int):
    state = table.admit("rsu-a", t_ns)
    for k in range(6):  # symmetric 1 ms legs: theta = OFFSET_NS
        t1 = t_ns + k * 100 * MS
        state.sync.add(SyncSample(t1, t1 + MS + OFFSET_NS, t1 + MS + OFFSET_NS, t1 + 2 * MS))
    return state


def _receive(state, capture_obu_ns: int, seq: int) -> Received:
    raw = Received(capture_obu_ns + OFFSET_NS, capture_obu_ns + OFFSET_NS, seq, _objects(3), capture_obu_ns + 30 * MS)
    state.frames.append(raw)
    return raw


def _same(a, b) -> bool:
    return len(a) == len(b) and all(ra is rb and fa == fb for (ra, fa), (rb, fb) in zip(a, b))


def _three_placed():
    """(inputs, the synced RSU's state, t_ns, its three frames placed at t_ns)."""
    table = RsuTable()
    inputs = ModeInputs(ObuPipelineConfig(), table)
    state = _synced_state(table, T0)
    t_ns = T0 + 1000 * MS
    for seq in range(3):
        _receive(state, T0 + 700 * MS + seq * 100 * MS, seq)
    return inputs, state, t_ns, inputs.placed(state, t_ns)


def test_placement_is_reused_only_while_estimate_and_frames_are_unchanged():
    inputs, state, t_ns, first = _three_placed()
    assert len(first) == 3 and inputs.placed(state, t_ns) == first
    assert inputs.placed(state, t_ns) is not first  # callers get their own list

    _receive(state, T0 + 1000 * MS, 3)  # a new frame: placed again
    again = inputs.placed(state, t_ns)
    assert len(again) == 4 and _same(again, inputs._place(state, state.sync.estimate_at(t_ns)))

    state.frames.popleft()  # one dropped: placed again
    assert _same(inputs.placed(state, t_ns), inputs._place(state, state.sync.estimate_at(t_ns)))

    # a later cycle (another estimate) and a new exchange that moves the offset: placed again
    later = T0 + 1100 * MS
    t1 = T0 + 900 * MS
    state.sync.add(SyncSample(t1, t1 + MS + OFFSET_NS + 2 * MS, t1 + MS + OFFSET_NS + 2 * MS, t1 + 2 * MS))
    assert _same(inputs.placed(state, later), inputs._place(state, state.sync.estimate_at(later)))

    state.frames.clear()
    assert inputs.placed(state, later) == []


def test_rsu_period_is_the_median_capture_interval():
    table = RsuTable()
    state = table.admit("rsu-a", T0)
    assert rsu_period_ns(state) == 200 * MS  # the default until two captures
    rng = np.random.default_rng(0)
    captures = T0 + np.cumsum(rng.integers(80 * MS, 130 * MS, 8))
    for seq, c in enumerate(captures):
        _receive(state, int(c), seq)
    _receive(state, int(captures[-1]), 99)  # a repeated capture counts once
    expected = int(np.median(np.diff(np.unique(captures))))
    assert rsu_period_ns(state) == expected


def test_placed_times_are_the_estimate_s_own_conversion():
    """_place converts RSU stamps with est.to_obu_ns's arithmetic (inlined): the same integers for a
    drifting, offset estimate, frames by valid time, each linked to the one before; a frame valid
    later than its arrival beyond the tolerance is left out."""
    table = RsuTable()
    inputs = ModeInputs(ObuPipelineConfig(), table)
    state = table.admit("rsu-a", T0)
    rng = np.random.default_rng(5)
    for seq in rng.permutation(40):
        capture = T0 + int(seq) * 97 * MS + int(rng.integers(0, MS))
        state.frames.append(Received(capture + 1234567, capture + 1234567 + 80 * MS + 13, int(seq), _objects(2),
                                     capture + int(rng.integers(-40, 400)) * MS))
    for est in (OffsetEstimate(1234567, 2 * MS, 9, 37.3, T0 + 2 * S, 0), OffsetEstimate(-7654321, 0, 9, -412.9, T0, 1),
                OffsetEstimate(1234567, 5 * MS, 9, 0.0, T0 + 5 * S, 0)):
        placed = inputs._place(state, est)
        tolerance_ns = est.uncertainty_ns + ObuPipelineConfig().future_tolerance_ms * 1e6
        want = [raw for raw in sorted(state.frames, key=lambda f: f.valid_rsu_ns)
                if est.to_obu_ns(raw.valid_rsu_ns) - raw.receive_ns <= tolerance_ns]
        assert 0 < len(placed) == len(want) < 40 and [raw for raw, _ in placed] == want
        for k, (raw, frame) in enumerate(placed):
            assert frame.valid_ns == est.to_obu_ns(raw.valid_rsu_ns) and type(frame.valid_ns) is int
            assert frame.capture_ns == est.to_obu_ns(raw.capture_rsu_ns) and frame.seq == raw.seq
            assert frame.previous is (placed[k - 1][1] if k else None) and frame.objects is raw.objects


def test_placement_is_not_reused_when_a_frame_is_another_object_of_the_same_count():
    inputs, state, t_ns, first = _three_placed()
    old = state.frames[1]
    state.frames[1] = Received(old.capture_rsu_ns, old.valid_rsu_ns, old.seq, old.objects, old.receive_ns)  # equal, not it
    again = inputs.placed(state, t_ns)
    assert again[1][0] is state.frames[1] and first[1][0] is old and _same(again, inputs._place(state, state.sync.estimate_at(t_ns)))
