from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from link_emulator.channel import LinkModel
from link_emulator.profile import load_profile
from v2i.clock.clock_sync import SILENT_BOUND_NS, ClockSync, SyncSample
from v2i.sim.sync_sim import (LTE_DOWNLINK, LTE_UPLINK, BufferedLeg, buffer_episodes, exchanges, forged,
                                  run_sync)
from v2i.sim.clock import ClockStep, DriftingClock, SimClock

T0 = 1_767_225_600 * 10**9
S, MS = 10**9, 10**6


def exchange(t1, theta, up_ns, down_ns, hold_ns=50_000):
    t2 = t1 + up_ns + theta
    t3 = t2 + hold_ns
    t4 = t3 - theta + down_ns
    return SyncSample(t1, t2, t3, t4)


def lte_run(offset_ns, drift_ppm, seed, duration_s=60, steps=()):
    """The scoring set-up: LTE-V2X legs (medians 21 / 22 ms, spikes, 2-3 % loss), 10 Hz."""
    clock = DriftingClock(SimClock(), offset_ns, drift_ppm, T0, steps)
    samples = exchanges(clock, LTE_UPLINK.draw_ns, LTE_DOWNLINK.draw_ns, np.random.default_rng(seed), T0,
                        duration_s * S)
    return clock, samples


def test_single_exchange_formulas():
    s = exchange(T0, theta=350_000_000, up_ns=10_000_000, down_ns=30_000_000)
    assert s.round_trip_ns == 40_000_000
    # error of one sample = (up - down) / 2
    assert s.offset_ns - 350_000_000 == (10_000_000 - 30_000_000) // 2
    assert s.brackets(350_000_000) and not s.brackets(350_000_000 + 11 * MS)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(theta_ms=st.floats(-2000, 2000), seed=st.integers(0, 2**32 - 1))
def test_bound_is_honest_and_naive_is_the_last_sample(theta_ms, seed):
    rng = np.random.default_rng(seed)
    sync = ClockSync(window=16)
    theta = round(theta_ms * 1e6)
    samples = []
    for k in range(16):
        up, down = 5_000_000 + rng.exponential(20e6), 5_000_000 + rng.exponential(20e6)
        samples.append(exchange(T0 + k * 500_000_000, theta, round(up), round(down)))
        assert sync.add(samples[-1])
    est = sync.estimate()
    assert abs(est.offset_ns - theta) <= est.uncertainty_ns + 1  # the bound is honest
    assert est.uncertainty_ns <= np.median([s.round_trip_ns for s in samples]) / 2  # from the low tail
    assert sync.naive().offset_ns == samples[-1].offset_ns


def test_rejects_inconsistent_and_converts_times():
    sync = ClockSync()
    assert sync.to_obu_ns(T0) is None and sync.estimate() is None
    assert not sync.add(SyncSample(T0, T0, T0 + 10, T0 - 1))  # t4 < t1
    assert not sync.add(SyncSample(T0, T0 + 5, T0 + 50, T0 + 20))  # round trip 20 - 45 < 0
    assert sync.estimate() is None and sync.naive() is None
    assert sync.add(exchange(T0, theta=1_000_000_000, up_ns=1_000_000, down_ns=1_000_000))
    assert sync.estimate().samples == 1
    assert sync.to_obu_ns(T0 + 1_000_000_000) == pytest.approx(T0, abs=1)


def test_conversions_use_the_drift():
    sync = ClockSync()
    sync.add(exchange(T0, theta=0, up_ns=MS, down_ns=MS))
    est = sync.estimate_at(T0)
    est = type(est)(est.offset_ns, est.uncertainty_ns, est.samples, 100.0, est.at_ns)  # 100 ppm
    assert est.offset_at_ns(T0 + 10 * S) - est.offset_ns == 1 * MS  # 100 ppm of 10 s = 1 ms
    rsu = est.to_rsu_ns(T0 + 10 * S)
    assert est.to_obu_ns(rsu) == pytest.approx(T0 + 10 * S, abs=1)


@settings(max_examples=15, deadline=None, derandomize=True)
@given(offset_ms=st.floats(-2000, 2000), drift_ppm=st.floats(-100, 100), seed=st.integers(0, 2**16))
def test_any_offset_and_drift_is_recovered(offset_ms, drift_ppm, seed):
    """Stated bound: after 20 s of 10 Hz LTE-V2X exchanges, |error| <= 1 ms at the last
    exchange and 1 s later (extrapolated with the drift), and the error is within the
    reported uncertainty."""
    clock, samples = lte_run(round(offset_ms * MS), drift_ppm, seed, duration_s=20)
    sync = ClockSync()
    for s in samples:
        sync.add(s)
    for t in (samples[-1].t4_ns, samples[-1].t4_ns + S):
        est = sync.estimate_at(t)
        err = est.offset_ns - clock.offset_at(t)
        assert abs(err) <= 1 * MS
        assert abs(err) <= est.uncertainty_ns
    assert sync.steps_detected == 0


@pytest.mark.parametrize("offset_ms, drift_ppm, seed", [(1500, 100, 0), (-2000, -100, 1), (300, 37, 2)])
def test_scoring_target_without_step(offset_ms, drift_ppm, seed):
    clock, samples = lte_run(offset_ms * MS, drift_ppm, seed)
    run = run_sync(clock, samples, T0, 60 * S)
    stats = run.stats_ms(after_ns=5 * S)
    assert stats["p95_ms"] <= 1.0
    assert stats["naive_p95_ms"] >= 10 * stats["p95_ms"]  # the naive latest exchange is much worse
    est = ClockSync()
    for s in samples:
        est.add(s)
    assert est.estimate().drift_ppm == pytest.approx(drift_ppm, abs=25)


@pytest.mark.parametrize("step_ms, seed", [(2000, 0), (-2000, 1), (700, 2), (-700, 3), (500, 0), (-500, 1),
                                           (20, 2), (-20, 4)])
def test_clock_step_is_detected_and_recovered_within_3_s(step_ms, seed):
    """A step beyond what queueing could explain (the readings before and after it allow disjoint
    offsets: > ~40 ms, the least round trip here) and beyond the ~18 ms bound is confirmed; a
    smaller one is not counted as a step, but the offset starts afresh from the readings that
    disagree with the old ones all the same: recovered and honest as fast."""
    step_ns = T0 + 15 * S
    clock, samples = lte_run(-700 * MS, 60.0, seed, duration_s=30, steps=(ClockStep(step_ns, step_ms * MS),))
    run = run_sync(clock, samples, T0, 30 * S)
    assert run.steps_detected == (abs(step_ms) > 100)
    assert run.reconvergence_ns(15 * S, tol_ns=1 * MS) < 3 * S
    assert run.stats_ms(after_ns=5 * S, until_ns=15 * S)["p95_ms"] <= 1.0
    # honest except right after the step: from the first reply stamped after it on when that reply
    # reveals it (a suspected step widens the bound), within 0.5 s for a step of the order of the
    # bound itself (the first replies after it agree with both clocks)
    first_after_ns = min(s.t4_ns for s in samples if s.t1_ns >= step_ns) - T0
    bad = run.unbounded()
    assert np.all(bad >= 15 * S) and np.all(bad < first_after_ns + (0 if abs(step_ms) > 100 else S // 2))
    settled_s = 16 if abs(step_ms) > 100 else 17  # a confirmed step within a second, a new segment within two
    assert abs(run.error_ns[run.t_ns >= settled_s * S]).max() < 5 * MS


def test_spikes_do_not_move_the_estimate():
    """Replies queued 300 ms move a plain NTP client by ~145 ms; the filter moves no more than
    if those exchanges had been lost."""
    rng = np.random.default_rng(7)
    theta = 123_456_789
    calm = [exchange(T0 + k * S // 10, theta, round(10 * MS + rng.exponential(MS)), round(10 * MS + rng.exponential(MS)))
            for k in range(200)]
    spikes = [exchange(T0 + k * S // 10, theta, round(10 * MS + rng.exponential(MS)), 300 * MS) for k in range(200, 205)]
    spiky, lossy = ClockSync(), ClockSync()
    for s in calm:
        spiky.add(s)
        lossy.add(s)
    for s in spikes:
        spiky.add(s)
    assert abs(spiky.naive().offset_ns - theta) > 100 * MS
    t = T0 + 21 * S
    assert abs(spiky.estimate_at(t).offset_ns - lossy.estimate_at(t).offset_ns) < 10_000
    assert abs(spiky.estimate_at(t).offset_ns - theta) < 200_000
    assert spiky.steps_detected == 0


def test_unconfirmed_outliers_are_given_back_not_a_step():
    sync = ClockSync()
    theta = 0
    for k in range(100):
        sync.add(exchange(T0 + k * S // 10, theta, 10 * MS, 10 * MS))
    # two readings far below the envelope (a +50 ms step would do that) then ordinary ones again
    for k in range(100, 102):
        sync.add(exchange(T0 + k * S // 10, theta + 50 * MS, 10 * MS, 10 * MS))
    assert abs(sync.estimate().offset_ns - theta) < 1000  # held aside: no effect
    for k in range(102, 120):
        sync.add(exchange(T0 + k * S // 10, theta, 10 * MS, 10 * MS))
    assert sync.steps_detected == 0
    assert sync.outliers_rejected == 2
    # a real step: three in a row
    for k in range(120, 123):
        sync.add(exchange(T0 + k * S // 10, theta + 50 * MS, 10 * MS, 10 * MS))
    assert sync.steps_detected == 1
    assert abs(sync.estimate().offset_ns - (theta + 50 * MS)) < 1000


def test_memory_and_time_window_are_bounded():
    sync = ClockSync(window=100, horizon_ns=5 * S)
    for k in range(1000):
        sync.add(exchange(T0 + k * S // 20, 0, MS, MS))
    assert len(sync.window()) == 100
    sync = ClockSync(horizon_ns=5 * S)
    for k in range(200):
        sync.add(exchange(T0 + k * S // 10, 0, MS, MS))
    kept = sync.window()
    assert kept[-1].t4_ns - kept[0].t4_ns <= 5 * S
    assert kept[-1].t4_ns - kept[0].t4_ns > 5 * S - S // 10


# --- issue 10, item 9: multi-second delays, late and out-of-order exchanges -----------------------

def buffered_run(seed, duration_s=120, offset_ns=350 * MS, drift_ppm=60.0):
    """LTE-V2X legs that buffer in episodes of 2-30 s (gaps ~ Exp(30 s)), delivered late and in order."""
    rng = np.random.default_rng(seed)
    up = BufferedLeg(LTE_UPLINK, buffer_episodes(rng, T0, duration_s * S, 30.0, (2.0, 30.0)))
    down = BufferedLeg(LTE_DOWNLINK, buffer_episodes(rng, T0, duration_s * S, 30.0, (2.0, 30.0)))
    clock = DriftingClock(SimClock(), offset_ns, drift_ppm, T0)
    return clock, exchanges(clock, up.draw_ns, down.draw_ns, rng, T0, duration_s * S)


@pytest.mark.parametrize("seed", range(6))
def test_buffered_legs_an_estimate_forms_and_its_bound_holds(seed):
    clock, samples = buffered_run(seed)
    late = [s for s in samples if s.t4_ns - s.t1_ns > 2 * S]
    assert late and max(s.t4_ns - s.t1_ns for s in samples) <= 61 * S  # 2-30 s per leg
    run = run_sync(clock, samples, T0, 120 * S)
    assert run.t_ns[0] <= samples[0].t4_ns - T0 + 20 * MS  # an estimate from the first reply on
    assert len(run.unbounded()) == 0
    assert run.steps_detected == 0
    assert np.median(np.abs(run.error_ns[run.t_ns >= 5 * S])) < 1 * MS


def long_buffered_run(seed, duration_s):
    """Legs that buffer in episodes of 15-50 s (gaps ~ Exp(20 s)), each direction on its own; by seed,
    the uplink or the downlink starts inside an episode (a run that begins buffered), -85 ppm."""
    rng = np.random.default_rng(seed)

    def legs_episodes(starts_in):
        episodes = buffer_episodes(rng, T0, duration_s * S, 20.0, (15.0, 50.0))
        if not starts_in:
            return episodes
        first = (T0, T0 + round(rng.uniform(15.0, 50.0) * S))
        return [first] + [(a, b) for a, b in episodes if a > first[1]]

    up = BufferedLeg(LTE_UPLINK, legs_episodes(seed % 3 == 0))
    down = BufferedLeg(LTE_DOWNLINK, legs_episodes(seed % 3 == 1))
    clock = DriftingClock(SimClock(), 350 * MS, -85.0, T0)
    return clock, exchanges(clock, up.draw_ns, down.draw_ns, rng, T0, duration_s * S)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("duration_s", [30, 90])
def test_seconds_of_buffering_never_make_a_step_and_the_estimate_recovers(seed, duration_s):
    """Replies buffered for seconds, then a burst, then prompt ones: queueing explains every change of
    the readings, so no step is confirmed, the bound holds throughout, and once prompt exchanges are
    back the estimate is as good as ever (it used to hold a seconds-wrong offset to the end, or
    confirm a step that never happened)."""
    clock, samples = long_buffered_run(seed, duration_s)
    run = run_sync(clock, samples, T0, duration_s * S)
    assert run.steps_detected == 0
    assert len(run.unbounded()) == 0
    recent = [s for s in samples if T0 + (duration_s - 20) * S <= s.t4_ns <= T0 + duration_s * S]
    prompt_up = sum(s.t2_ns - clock.offset_at(s.t1_ns) - s.t1_ns < 200 * MS for s in recent)  # true one-way delays
    prompt_down = sum(s.t4_ns - (s.t3_ns - clock.offset_at(s.t4_ns)) < 200 * MS for s in recent)
    if min(prompt_up, prompt_down) >= 40:  # each leg prompt again for a while before the end
        assert abs(run.error_ns[-1]) < 5 * MS


def test_buffered_profile_through_the_link_emulator_channels():
    """The rural-5g-buffered profile (synthetic stand-in for the issue's trace) delivers 2-30 s late
    and in order, and the estimate formed over it states an honest bound."""
    for seed in range(2):
        link = LinkModel(load_profile("rural-5g-buffered"), seed)
        clock = DriftingClock(SimClock(), 350 * MS, 60.0, T0)
        def leg(channel):
            def draw(send_ns, rng):
                arrival = channel.transmit(send_ns, 200)
                return None if arrival is None else arrival - send_ns
            return draw
        samples = exchanges(clock, leg(link.uplink), leg(link.downlink), np.random.default_rng(seed), T0, 120 * S)
        round_trips = np.array([s.t4_ns - s.t1_ns for s in samples])
        assert round_trips.max() > 2 * S and np.median(round_trips) < 100 * MS
        run = run_sync(clock, samples, T0, 120 * S)
        assert len(run.unbounded()) == 0
        assert run.steps_detected == 0
        assert np.median(np.abs(run.error_ns[run.t_ns >= 5 * S])) < 1 * MS


def test_arrival_order_does_not_matter():
    """Exchanges that complete tens of seconds late arrive out of send order: the window is kept by
    receive time, so any arrival order of the same exchanges gives the same estimate."""
    clock, samples = lte_run(350 * MS, 60.0, 5, duration_s=20)
    rng = np.random.default_rng(5)
    late = [SyncSample(s.t1_ns, s.t2_ns, s.t3_ns, s.t4_ns + round(rng.uniform(2, 25) * S)) if k % 7 == 0 else s
            for k, s in enumerate(samples)]  # every 7th reply buffered 2-25 s on its way down
    by_t4 = sorted(late, key=lambda s: s.t4_ns)
    shuffled = [by_t4[i] for i in rng.permutation(len(by_t4))]
    a, b = ClockSync(), ClockSync()
    for s in by_t4:
        a.add(s)
    for s in shuffled:
        b.add(s)
    assert a.window() == b.window()
    t = by_t4[-1].t4_ns
    assert a.estimate_at(t) == b.estimate_at(t)
    assert abs(a.estimate_at(t).offset_ns - clock.offset_at(t)) <= a.estimate_at(t).uncertainty_ns


def test_uncertainty_grows_with_the_drift_sd_while_no_exchange_arrives():
    clock, samples = lte_run(350 * MS, 80.0, 6, duration_s=30)
    sync = ClockSync()
    for s in samples:
        sync.add(s)
    assert sync.converged
    t_last = samples[-1].t4_ns
    u = [sync.estimate_at(t_last + k * 10 * S).uncertainty_ns for k in range(7)]
    growth = np.diff(u)
    assert np.all(growth > 0) and np.ptp(growth) <= 2  # linear in the time since the last exchange
    sd_ns_per_s = sync.estimate().drift_sd_ppm * 1e3
    assert growth[0] == pytest.approx(3.0 * sd_ns_per_s * 10, abs=2)  # k sd per second, k = 3
    for k in range(7):
        est = sync.estimate_at(t_last + k * 10 * S)
        assert abs(est.offset_ns - clock.offset_at(t_last + k * 10 * S)) <= est.uncertainty_ns


def test_a_clock_not_heard_promptly_is_not_bounded():
    """A step while no prompt exchange arrives (the uplink buffers: the RSU gets no query) cannot be
    seen: past silence_ns after the last prompt exchange the bound is SILENT_BOUND_NS, and a prompt
    one brings it back; buffered replies (round trip > silence_ns) do not."""
    step_ns = T0 + 15 * S
    clock, samples = lte_run(350 * MS, 60.0, 2, duration_s=30, steps=(ClockStep(step_ns, 500 * MS),))
    silent = [s for s in samples if s.t1_ns < T0 + 12 * S]  # nothing sent after 12 s arrives before 25 s...
    late = [SyncSample(s.t1_ns, s.t2_ns, s.t3_ns, T0 + 25 * S) for s in samples if T0 + 12 * S <= s.t1_ns < T0 + 20 * S]
    sync, quiet = ClockSync(), ClockSync()
    for s in silent:
        sync.note_request(s.t1_ns)
        sync.add(s)
        quiet.add(s)
    for t1_ns in range(T0 + 12 * S, T0 + 25 * S, S // 10):  # queries every 100 ms (no answer yet)
        sync.note_request(t1_ns)
    t_last = silent[-1].t4_ns
    assert sync.estimate_at(t_last + S).uncertainty_ns < 30 * MS
    est = sync.estimate_at(T0 + 20 * S)  # 500 ms wrong since 15 s: not bounded by the old fit
    assert abs(est.offset_ns - clock.offset_at(T0 + 20 * S)) > 400 * MS
    assert est.uncertainty_ns == SILENT_BOUND_NS
    assert quiet.estimate_at(T0 + 20 * S).uncertainty_ns < 50 * MS  # (no queries noted: the rule is off)
    for s in late:  # ... then the buffered ones, all at once: still nothing prompt
        sync.add(s)
    assert sync.estimate_at(T0 + 25 * S).uncertainty_ns >= SILENT_BOUND_NS
    prompt = [s for s in samples if s.t1_ns >= T0 + 25 * S]
    for s in prompt:
        sync.note_request(s.t1_ns)
        sync.add(s)
    est = sync.estimate_at(prompt[-1].t4_ns)
    assert est.uncertainty_ns < 30 * MS and abs(est.offset_ns - clock.offset_at(prompt[-1].t4_ns)) < 5 * MS


def test_a_reply_stamped_before_a_step_and_delivered_after_it_is_no_step_back():
    step_ns = T0 + 15 * S
    clock, samples = lte_run(0, 20.0, 7, duration_s=30, steps=(ClockStep(step_ns, 500 * MS),))
    pre = [s for s in samples if s.t1_ns < step_ns - 300 * MS]
    delayed = [SyncSample(s.t1_ns, s.t2_ns, s.t3_ns, step_ns + 8 * S + k * MS) for k, s in enumerate(pre[-5:])]
    feed = sorted([s for s in samples if s not in pre[-5:]] + delayed, key=lambda s: s.t4_ns)
    sync = ClockSync()
    for s in feed:
        sync.add(s)
    assert sync.steps_detected == 1
    assert sum(s in sync.window() for s in delayed) == 5  # kept, in the segment they were stamped in
    t = feed[-1].t4_ns
    assert abs(sync.estimate_at(t).offset_ns - clock.offset_at(t)) < 1 * MS


def test_the_window_s_columns_follow_its_samples_through_steps_late_replies_and_cuts():
    """The (t1, t2, t3, t4) and segment columns a fit reads stay those of the window's samples
    through out-of-order inserts, window and horizon cuts, a confirmed step and late pre-step replies."""
    step_ns = T0 + 15 * S
    clock, samples = lte_run(0, 20.0, 7, duration_s=40, steps=(ClockStep(step_ns, 500 * MS),))
    pre = [s for s in samples if s.t1_ns < step_ns - 300 * MS]
    delayed = [SyncSample(s.t1_ns, s.t2_ns, s.t3_ns, step_ns + 8 * S + k * MS) for k, s in enumerate(pre[-5:])]
    feed = sorted([s for s in samples if s not in pre[-5:]] + delayed, key=lambda s: s.t4_ns)
    rng = np.random.default_rng(2)
    for i in range(0, len(feed) - 3, 4):  # some replies overtaken by the next ones
        if rng.random() < 0.5:
            feed[i], feed[i + 2] = feed[i + 2], feed[i]
    sync = ClockSync(window=250, horizon_ns=30 * S)
    for k, s in enumerate(feed):
        sync.add(s)
        if k % 17 == 0 or k == len(feed) - 1:
            assert list(sync._times) == [t for w in sync.window() for t in (w.t1_ns, w.t2_ns, w.t3_ns, w.t4_ns)]
            assert list(sync._segments) == [seg for _, seg, _ in sync._samples]
    assert sync.steps_detected == 1 and len(sync.window()) == 250
    assert set(sync._segments) == {0, 1}


# --- forged replies and outliers against a converged fit ------------------------------------------

def forged_mix(seed, shift_ns, every, start_s, rtt_ns, duration_s=40):
    """Genuine LTE-V2X exchanges where, from start_s on, every ``every``-th reply is forged; and the
    same exchanges with those replies lost instead (what the filter should behave like)."""
    clock, samples = lte_run(350 * MS, 60.0, seed, duration_s=duration_s)
    hit = [s.t1_ns >= T0 + start_s * S and k % every == 0 for k, s in enumerate(samples)]
    mixed = sorted([forged(s.t1_ns, clock.offset_at(s.t1_ns), shift_ns, rtt_ns) if h else s
                    for h, s in zip(hit, samples)], key=lambda s: s.t4_ns)
    return clock, mixed, [s for h, s in zip(hit, samples) if not h], sum(hit)


# (a shift smaller than a realistic round trip, e.g. 8 ms at 35 ms, agrees with the genuine replies
# as well as a small clock step would: see the module doc of clock_sync)
@pytest.mark.parametrize("shift_ms, every, rtt_ms", [(245, 2, 10), (-245, 2, 10), (245, 5, 35), (-245, 3, 35),
                                                     (2500, 2, 10), (-2500, 5, 35), (8, 2, 10), (-8, 5, 10)])
def test_forged_replies_against_a_converged_fit_are_rejected_not_averaged(shift_ms, every, rtt_ms):
    clock, mixed, lossy, n_forged = forged_mix(1, shift_ms * MS, every, 10, rtt_ms * MS)
    sync = ClockSync()
    run = run_sync(clock, mixed, T0, 40 * S, sync=sync)
    ref = run_sync(clock, lossy, T0, 40 * S)
    assert np.array_equal(run.t_ns, ref.t_ns)
    assert np.abs(run.error_ns - ref.error_ns).max() <= 1_000  # as if those replies had been lost
    assert run.steps_detected == 0
    assert sync.outliers_rejected == n_forged
    assert len(run.unbounded()) == 0


def test_forged_replies_before_convergence_cannot_hide_behind_the_bound():
    """Half the replies forged from the first one on: no majority, so the bound covers both
    stories (honest once a genuine reply is in), and the fit never counts as converged."""
    clock, mixed, _, _ = forged_mix(2, 245 * MS, 2, 0, 10 * MS, duration_s=20)
    sync = ClockSync()
    run = run_sync(clock, mixed, T0, 20 * S, sync=sync)
    first_genuine_ns = min(s.t4_ns for s in mixed if s.round_trip_ns > 20 * MS) - T0
    assert len(run.unbounded(after_ns=first_genuine_ns)) == 0
    assert run.uncertainty_ns[-1] > 245 * MS
    assert not sync.converged


def test_a_real_step_is_still_detected_among_forged_replies():
    step_ns = T0 + 25 * S
    clock, samples = lte_run(350 * MS, 60.0, 3, duration_s=40, steps=(ClockStep(step_ns, -700 * MS),))
    hit = [T0 + 10 * S <= s.t1_ns and k % 3 == 0 for k, s in enumerate(samples)]
    mixed = sorted([forged(s.t1_ns, clock.offset_at(s.t1_ns), 245 * MS, 10 * MS) if h else s
                    for h, s in zip(hit, samples)], key=lambda s: s.t4_ns)
    run = run_sync(clock, mixed, T0, 40 * S)
    ref = run_sync(clock, [s for h, s in zip(hit, samples) if not h], T0, 40 * S)
    before = run.t_ns < 25 * S
    assert np.abs(run.error_ns[before] - ref.error_ns[before]).max() <= 1_000  # forgeries: no effect
    assert run.steps_detected == 1
    assert run.reconvergence_ns(25 * S, tol_ns=1 * MS) < 3 * S


@settings(max_examples=12, deadline=None, derandomize=True)
@given(offset_ms=st.floats(-2000, 2000), drift_ppm=st.floats(-100, 100),
       step_ms=st.sampled_from([-2000, -700, 300, 2000]), step_at_s=st.floats(12, 20), seed=st.integers(0, 2**16))
def test_the_bound_holds_over_offsets_drifts_and_steps(offset_ms, drift_ppm, step_ms, step_at_s, seed):
    """|estimate - truth| <= uncertainty at every scored time except between a step and the first
    reply stamped after it (nothing can be known then)."""
    step_ns = T0 + round(step_at_s * S)
    clock, samples = lte_run(round(offset_ms * MS), drift_ppm, seed, duration_s=30,
                             steps=(ClockStep(step_ns, step_ms * MS),))
    run = run_sync(clock, samples, T0, 30 * S)
    first_after_ns = min(s.t4_ns for s in samples if s.t1_ns >= step_ns) - T0
    bad = run.unbounded()
    assert np.all((bad >= step_ns - T0) & (bad < first_after_ns))
    assert run.steps_detected == 1


def test_a_converged_filter_refits_every_refit_every_exchanges_not_each_one(monkeypatch):
    """Until armed every exchange refits, then one refit per refit_every (5) exchanges; between
    refits the extrapolated estimate stays inside its bound."""
    clock, samples = lte_run(300 * MS, 40.0, 5, duration_s=30)
    fits = Counter()
    compute = ClockSync._compute_fit

    def counting(self):
        fits[id(self)] += 1
        return compute(self)

    monkeypatch.setattr(ClockSync, "_compute_fit", counting)
    throttled, every = ClockSync(), ClockSync(refit_every=1)
    armed = 0
    for s in samples:
        for sync in (throttled, every):
            sync.add(s)
            est = sync.estimate_at(s.t4_ns)
            assert abs(est.offset_ns - clock.offset_at(s.t4_ns)) <= est.uncertainty_ns
        armed += throttled.converged
    assert fits[id(every)] == len(samples)
    unarmed = len(samples) - armed
    assert unarmed < 0.3 * len(samples) and fits[id(throttled)] <= unarmed + armed / 5 + 2


def test_an_estimate_asked_again_is_the_one_computed_afresh():
    """estimate_at keeps its last answer for (fit, t, exchanges, segment) while no step is suspected:
    through a step among forged replies (hypotheses open and close) every answer, repeated or not,
    equals the one computed without the kept answer, at the same and at other instants."""
    step_ns = T0 + 25 * S
    clock, samples = lte_run(350 * MS, 60.0, 3, duration_s=40, steps=(ClockStep(step_ns, -700 * MS),))
    mixed = sorted([forged(s.t1_ns, clock.offset_at(s.t1_ns), 245 * MS, 10 * MS) if T0 + 10 * S <= s.t1_ns and k % 3 == 0
                    else s for k, s in enumerate(samples)], key=lambda s: s.t4_ns)
    sync, kept, suspected = ClockSync(), 0, 0
    for sample in mixed:
        sync.add(sample)
        suspected += bool(sync._hypotheses)
        for t_ns in (sample.t4_ns, sample.t4_ns, sample.t4_ns + 50 * MS, sample.t4_ns, float(sample.t4_ns)):
            got = sync.estimate_at(t_ns)
            kept += got is not None and sync.estimate_at(t_ns) is got
            sync._last_estimate = None
            want = sync.estimate_at(t_ns)
            assert got == want and type(got.at_ns) is type(t_ns)
    assert sync.steps_detected == 1 and suspected > 0 and kept > 0


@pytest.mark.parametrize("delay_ms", [100, 30_000])
def test_request_legs_delayed_by_a_relay_never_make_a_step(delay_ms):
    """Issue 32: someone holds back every third query for 100 ms or 30 s before the RSU sees it (its
    reply then leaves late too): longer round trips, which queueing explains; no step, the bound holds."""
    clock, samples = lte_run(350 * MS, 60.0, 4, duration_s=40)
    delayed = sorted((SyncSample(s.t1_ns, s.t2_ns + delay_ms * MS, s.t3_ns + delay_ms * MS, s.t4_ns + delay_ms * MS)
                      if k % 3 == 0 else s for k, s in enumerate(samples)), key=lambda s: s.t4_ns)
    run = run_sync(clock, delayed, T0, 40 * S)
    assert run.steps_detected == 0
    assert len(run.unbounded()) == 0
    assert run.stats_ms(after_ns=5 * S)["p95_ms"] < 2.0
