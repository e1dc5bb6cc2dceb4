import numpy as np
import pytest

from obu_service.link_monitor import LinkMonitor, gap_loss, mean_abs_diff

T0 = 1_767_225_600 * 10**9
MS = 10**6
PERIOD = 100 * MS  # RSU frames at 10 Hz


def feed(mon, seqs, delay_ms=20.0, processing_ms=100.0, start_ns=T0):
    """Frame seq captured at start + seq * PERIOD, published processing_ms later, received delay_ms after."""
    for seq in seqs:
        capture = start_ns + seq * PERIOD
        publish = capture + round(processing_ms * MS)
        mon.on_message(seq, capture, publish, publish + round(delay_ms * MS))


def test_loss_from_gaps():
    mon = LinkMonitor()
    feed(mon, [s for s in range(50) if s not in (10, 11, 30)])
    assert mon.loss() == (3, 50)
    assert mon.loss_ratio() == pytest.approx(3 / 50)


def test_reordering_fills_the_gap_and_duplicates_are_ignored():
    mon = LinkMonitor()
    feed(mon, [0, 1, 2, 4, 5, 3, 6, 6, 7, 2])
    assert mon.loss() == (0, 8)
    assert mon.reordered_total == 1 and mon.duplicates_total == 2
    assert mon.summary()["messages"] == 8


def test_numbers_that_are_no_counter_count_for_latency_not_for_loss():
    """A CPM's seq is 8 x its referenceTime (ms): 800 apart at 10 Hz. As counters those gaps would
    be 99.9 % loss; uncounted, the loss is unknown and the arrival probability is the latency's."""
    mon = LinkMonitor(max_records=8)
    for i in range(20):
        capture = T0 + i * PERIOD
        mon.on_message(8 * (capture // MS), capture, capture + 100 * MS, capture + 120 * MS, counted=False)
    assert mon.loss() == (0, 0) and mon.loss_ratio() is None and mon.restarts_total == 0
    assert mon.arrival_probability(150.0) == 1.0 and mon.arrival_probability(110.0) == 0.0
    assert len(mon.latencies_ms()) == 8  # bounded memory holds for them too
    assert not mon.on_message(8 * ((T0 + 19 * PERIOD) // MS), None, None, T0 + 19 * PERIOD + 130 * MS, counted=False)
    assert mon.duplicates_total == 1
    feed(mon, [0, 1, 3], start_ns=T0 + 20 * PERIOD)  # a counting wire beside them: its gaps only
    assert mon.loss() == (1, 4)


def test_rsu_restart_starts_a_new_sequence_epoch():
    mon = LinkMonitor()
    feed(mon, range(1000, 1020))
    # the RSU restarts: numbering from 0 again, 2 frames lost after the restart
    feed(mon, [0, 1, 4, 5], start_ns=T0 + 102_500 * MS)
    assert mon.restarts_total == 1 and mon.reordered_total == 0
    assert mon.loss() == (2, 26)  # 20 of 20 before, 4 of 6 after: not 1000 lost
    # a small backward jump is reordering, not a restart
    mon2 = LinkMonitor()
    feed(mon2, [10, 11, 12, 9])
    assert mon2.restarts_total == 0 and mon2.reordered_total == 1


def test_gap_loss_helper():
    seqs, epochs = np.array([5, 7, 8, 0, 2]), np.array([0, 0, 0, 1, 1])
    assert gap_loss(seqs, epochs) == (2, 7)
    assert gap_loss([5, 5, 7, 3], [0, 0, 0, 2]) == (1, 4)  # lists too; a repeated (epoch, seq) counts once


def test_quantiles_and_arrival_probability():
    rng = np.random.default_rng(3)
    mon = LinkMonitor(window_ns=60 * 10**9)
    delays = 15.0 + rng.lognormal(np.log(7.0), 0.8, 500)
    seqs = [s for s in range(500)]
    lost = set(rng.choice(500, 25, replace=False).tolist()) - {0, 499}
    for seq in seqs:
        if seq in lost:
            continue
        capture = T0 + seq * PERIOD
        mon.on_message(seq, capture, capture + 100 * MS, capture + 100 * MS + round(delays[seq] * MS))
    kept = np.array([delays[s] for s in seqs if s not in lost])
    assert mon.delay_quantile_ms(0.5) == pytest.approx(np.quantile(kept, 0.5), abs=1e-3)
    assert mon.delay_quantile_ms(0.95) == pytest.approx(np.quantile(kept, 0.95), abs=1e-3)
    assert mon.latency_quantile_ms(0.99) == pytest.approx(100 + np.quantile(kept, 0.99), abs=1e-3)
    loss = len(lost) / 500
    assert mon.loss_ratio() == pytest.approx(loss)
    # P(latency <= 130 ms) = (1 - loss) * P(delay <= 30 ms | arrived)
    expected = (1 - loss) * np.mean(kept <= 30.0)
    assert mon.arrival_probability(130.0) == pytest.approx(expected)
    assert mon.arrival_probability(90.0) == 0.0  # nothing arrives before the RSU has processed it
    assert mon.arrival_probability(10_000.0) == pytest.approx(1 - loss)
    s = mon.summary(T0 + 500 * PERIOD)
    assert s["delay_p50_ms"] < s["delay_p95_ms"] < s["delay_p99_ms"]
    assert s["latency_p50_ms"] == pytest.approx(100 + s["delay_p50_ms"], abs=1e-6)


def test_jitter_is_mean_abs_difference_of_consecutive_delays():
    mon = LinkMonitor()
    for seq, d in enumerate([20.0, 22.0, 19.0, 19.0, 25.0]):
        capture = T0 + seq * PERIOD
        mon.on_message(seq, capture, capture, capture + round(d * MS))
    assert mon.jitter_ms() == pytest.approx((2 + 3 + 0 + 6) / 4)
    assert mean_abs_diff(np.array([1.0])) is None
    steady = LinkMonitor()
    feed(steady, range(20), delay_ms=20.0)
    assert steady.jitter_ms() == pytest.approx(0.0)


def test_window_expiry_and_bounded_memory():
    mon = LinkMonitor(window_ns=10 * 10**9, max_records=50)
    feed(mon, range(40), delay_ms=80.0)  # 4 s of a slow link
    feed(mon, range(40, 200), delay_ms=20.0)  # then 16 s of a fast one
    s = mon.summary()
    assert s["messages"] <= 50
    assert s["delay_p99_ms"] == pytest.approx(20.0)  # the slow period has left the window
    # nothing heard for 15 s: the window is empty, nothing is claimed
    last_receive = T0 + 199 * PERIOD + 120 * MS
    s = mon.summary(last_receive + 15 * 10**9)
    assert s["messages"] == 0 and s["delay_p50_ms"] is None and s["loss_ratio"] is None
    assert s["since_last_ms"] == pytest.approx(15_000.0)
    assert mon.arrival_probability(1_000.0) == 0.0


def test_fusion_age_and_unknown_clock():
    mon = LinkMonitor(window_ns=10 * 10**9)
    for k, age in enumerate([120.0, 150.0, None, 180.0]):
        mon.on_fusion(T0 + k * PERIOD, age)
    s = mon.summary(T0 + 4 * PERIOD)
    assert s["fusion_age_mean_ms"] == pytest.approx(150.0) and s["fusion_age_max_ms"] == 180.0
    # before clock sync the RSU stamps cannot be placed: counted for loss, not for delay
    mon.on_message(0, None, None, T0)
    mon.on_message(2, None, None, T0 + 2 * PERIOD)
    assert mon.loss() == (1, 3) and mon.delay_quantile_ms(0.5) is None
    assert mon.summary(T0 + 20 * 10**9)["fusion_age_mean_ms"] is None


def test_sent_counts_every_numbered_list_since_first_heard_across_restarts_and_window():
    mon = LinkMonitor(window_ns=500 * MS)
    assert mon.sent_total() is None
    feed(mon, [5, 6, 8, 7, 11])  # 5..11 numbered, 9 and 10 never arrived, 7 late
    assert mon.sent_total() == 7
    feed(mon, [4], start_ns=T0)  # a late one below the first: the span grows
    assert mon.sent_total() == 8
    feed(mon, range(200, 230))  # past the window: the total is not windowed
    assert mon.sent_total() == 226  # 4..229, whatever arrived
    feed(mon, [0, 1, 3], start_ns=T0 + 900_000 * MS)  # the RSU restarts: a new span on top
    assert mon.restarts_total == 1 and mon.sent_total() == 226 + 4  # 0..3 after it


def test_numbers_heard_before_the_clock_is_known_count_as_sent_not_as_arrivals():
    mon = LinkMonitor()
    for seq in (3, 4, 6):
        mon.note_sequence(seq)
    feed(mon, [7, 8])
    assert mon.sent_total() == 6 and mon.loss() == (0, 2)  # 3..8 numbered; loss only over what was timed
