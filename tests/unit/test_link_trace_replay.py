"""Trace replay: the trace's own send times, its delays at its rows, its order and its gaps (pure)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import ks_2samp

from link_emulator.channel import NONE_NS, NS_PER_MS, Channel, LinkModel
from link_emulator.processes import TraceClock
from link_emulator.profile import DirectionProfile, load_profile
from link_emulator.trace import DelayTrace, load_trace, overtaken_ratio, parse_cicv5g
from link_emulator.validate import quantile_ms

TRACE = "cicv5g/urban_n78_v20_run01.txt.gz"
T0_NS = 1_700_000_000 * 10**9
HEADER = "pub_time(ms) sub_time(ms) delay(ms)"
# (pub, delay) ms: irregular send times, a rise to a 100 ms spike that drains; arrivals stay
# monotonic (10, 140, 155, 162, 222, 280, 315), as in every measured trace
ROWS = [(0, 10), (40, 100), (95, 60), (150, 12), (210, 12), (260, 20), (300, 15)]


def _trace(rows: list[tuple[float, float]]) -> DelayTrace:
    return parse_cicv5g("\n".join([HEADER] + [f"{p} {p + d} {d}" for p, d in rows]), "test")


def _replay(clock: TraceClock, x_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Delays (ms) and lost flags of messages sent ``x_ms`` after the trace's first row."""
    delay_ns, lost = clock.delay_ns(np.rint(np.asarray(x_ms) * NS_PER_MS).astype(np.int64))
    return delay_ns / NS_PER_MS, lost


def test_the_replay_rule_by_hand() -> None:
    trace = _trace(ROWS)
    assert trace.period_ms == 52.5 and trace.lost_after.tolist() == [0, 0, 0, 0, 0, 0, 0]
    clock = TraceClock(trace, phase_ns=0)
    # rise 10 -> 100 between p = 0 and 40: the nearer row's delay, stepping up at c = 20
    # fall 100 -> 60 between p = 40 and 95 (c = 67.5): a 40 ms drain centred on c, every
    # message of it arriving at h = 67.5 + (100 + 60) / 2 = 147.5
    x_ms = np.array([10.0, 30.0, 47.5, 50.0, 60.0, 70.0, 87.5, 90.0])
    delay_ms, lost = _replay(clock, x_ms)
    assert delay_ms.tolist() == [10.0, 100.0, 100.0, 97.5, 87.5, 77.5, 60.0, 60.0]
    assert not lost.any()


def test_a_message_sent_at_a_row_gets_its_delay_and_gaps_are_lost() -> None:
    rows = [(0, 10), (55, 12), (110, 30), (168, 11), (335, 14), (390, 14), (500, 13), (553, 10)]
    trace = _trace(rows)  # after 168: a 167 ms gap (2 lost); after 390: 110 ms (1 lost)
    assert trace.period_ms == 55.0 and trace.lost_after.tolist() == [0, 0, 0, 2, 0, 1, 0, 0]
    assert trace.loop_ms == 553.0 + 55.0
    # the lost messages take one period each at the gap's end: [225, 335) and [445, 500)
    assert trace.loss_ratio == pytest.approx(3 * 55.0 / 608.0)
    clock = TraceClock(trace, phase_ns=0)
    delay_ms, lost = _replay(clock, np.array([p for p, _ in rows]))
    assert delay_ms.tolist() == [d for _, d in rows] and not lost.any()
    _, lost = _replay(clock, np.array([224.0, 225.0, 334.0, 444.0, 445.0, 499.0, 500.0]))
    assert lost.tolist() == [False, True, True, False, True, True, False]
    # one loop later (and with a phase) the same
    shifted = TraceClock(trace, phase_ns=round(100.0 * NS_PER_MS))
    delay_ms, _ = _replay(shifted, np.array([p for p, _ in rows]) + 608.0 - 100.0)
    assert delay_ms.tolist() == [d for _, d in rows]


def test_replay_never_reorders_nor_leaves_the_neighbouring_rows_delays() -> None:
    trace = _trace(ROWS)
    clock = TraceClock(trace, phase_ns=0)
    x_ms = np.arange(0.0, 3 * trace.loop_ms, 0.25)  # three loops, a message every 0.25 ms
    delay_ms, lost = _replay(clock, x_ms)
    arrival_ms = x_ms + delay_ms
    assert np.all(np.diff(arrival_ms[~lost]) >= 0.0)
    pub = np.array([p for p, _ in ROWS], dtype=float)
    d = np.array([d for _, d in ROWS], dtype=float)
    row = np.searchsorted(pub, x_ms % trace.loop_ms, side="right") - 1
    low, high = np.minimum(d[row], np.roll(d, -1)[row]), np.maximum(d[row], np.roll(d, -1)[row])
    assert np.all((delay_ms >= low) & (delay_ms <= high))  # no inflation beyond the trace


def test_a_trace_that_reorders_is_replayed_with_its_own_delays() -> None:
    trace = _trace([(0, 100), (10, 10), (60, 12), (115, 11)])  # row 1 overtakes row 0
    assert trace.overtaken_ratio == pytest.approx(0.25)
    delay_ms, _ = _replay(TraceClock(trace, phase_ns=0), np.array([0.0, 10.0, 60.0, 115.0]))
    assert delay_ms.tolist() == [100.0, 10.0, 12.0, 11.0]


def test_loop_seam_keeps_order_after_a_late_last_row() -> None:
    trace = _trace([(0, 10), (55, 12), (110, 11), (165, 200)])  # the last row arrives at 365
    assert trace.loop_ms == 365.0 - 10.0  # >= a_{n-1} - a_0, not 165 + 55
    clock = TraceClock(trace, phase_ns=0)
    x_ms = np.arange(0.0, 4 * trace.loop_ms, 0.5)
    delay_ms, lost = _replay(clock, x_ms)
    assert np.all(np.diff((x_ms + delay_ms)[~lost]) >= 0.0)


@pytest.mark.parametrize("rate_hz", [5.0, 10.0, 1000.0])
def test_shipped_replay_keeps_order_and_the_trace_distribution(rate_hz: float) -> None:
    trace = load_trace(TRACE)
    channel = LinkModel(load_profile("5g-uu-trace"), seed=3).downlink
    n = int(min(40_000, 10 * trace.loop_ms / 1000.0 * rate_hz))  # 10 loops, or 40 s at 1000 msg/s
    send_ns = T0_NS + np.rint(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    out = channel.transmit_batch(send_ns, 1000)
    assert overtaken_ratio(out.deliver_ns[~out.lost]) == 0.0
    delays_ms = (out.deliver_ns[~out.lost] - send_ns[~out.lost]) / NS_PER_MS
    assert delays_ms.max() <= trace.delay_ms.max()
    if rate_hz < 1000.0:  # whole loops: the trace's distribution and its loss
        assert ks_2samp(delays_ms, trace.delay_ms).statistic < 0.01
        assert quantile_ms(delays_ms, 0.5) == quantile_ms(trace.delay_ms, 0.5)
        assert abs(quantile_ms(delays_ms, 0.99) - quantile_ms(trace.delay_ms, 0.99)) <= 1.0
        assert delays_ms.mean() == pytest.approx(trace.delay_ms.mean(), abs=0.1)
        assert out.lost.mean() == pytest.approx(trace.loss_ratio, rel=0.1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_backlogged_send_queue_does_not_reorder_a_draining_replay(tmp_path, seed: int) -> None:
    # a saw-tooth trace that drains at 1 ms/ms most of the time (arrivals flat, then a rise)
    delays = [400 - 50 * (k % 8) for k in range(80)]
    path = tmp_path / "saw.txt"
    path.write_text("\n".join([HEADER] + [f"{50 * k} {50 * k + d} {d}" for k, d in enumerate(delays)]))
    direction = DirectionProfile.model_validate({"delay_ms": 0.0, "replay": {"trace": str(path)},
                                                 "bandwidth_kbps": 1000.0})  # 12 ms per 1500 B
    # a burst of 30 (a 360 ms backlog), then one every 30 ms: departures 12 ms apart while
    # the send times are 30 ms apart; looked up at the send time, the drain would reorder them
    send_ns = T0_NS + np.concatenate((np.zeros(30), 30.0 * np.arange(1, 60))).astype(np.int64) * NS_PER_MS
    out = Channel(direction, np.random.default_rng(seed)).transmit_batch(send_ns, 1500)
    assert not out.lost.any() and np.all(np.diff(out.deliver_ns) >= 0)


@settings(max_examples=25, deadline=None)
@given(
    gaps_ms=st.lists(st.integers(0, 120), min_size=2, max_size=60),
    bandwidth_kbps=st.sampled_from([None, 200.0, 2000.0]),
    hold=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
)
def test_replay_keeps_order_through_a_send_queue_and_an_outage_hold(gaps_ms, bandwidth_kbps, hold, seed) -> None:
    fields = {"delay_ms": 2.0, "replay": {"trace": TRACE}, "bandwidth_kbps": bandwidth_kbps,
              "duplicate_probability": 0.1}
    if hold:
        fields["outage"] = {"mode": "hold", "windows_s": [[0.1, 0.4]]}
    direction = DirectionProfile.model_validate(fields)
    send_ns = T0_NS + np.cumsum(np.array(gaps_ms, dtype=np.int64) * NS_PER_MS)
    out = Channel(direction, np.random.default_rng(seed)).transmit_batch(send_ns, 1500)
    delivered = out.deliver_ns[~out.lost]
    assert np.all(np.diff(delivered) >= 0)
    copies = out.duplicate_ns != NONE_NS
    assert np.all(out.duplicate_ns[copies] >= out.deliver_ns[copies])
    single = Channel(direction, np.random.default_rng(seed))  # the live relay's path: one message per call
    expected = [single.transmit_all(int(t), 1500) for t in send_ns]
    assert expected == [sorted(int(t) for t in pair if t != NONE_NS) for pair in zip(out.deliver_ns, out.duplicate_ns)]
