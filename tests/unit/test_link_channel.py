"""Pure tests of the link profiles and channel models (no Zenoh, no clock)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from link_emulator.channel import NONE_NS, NS_PER_MS, Channel, LinkModel
from link_emulator.profile import (
    DirectionProfile,
    LinkProfile,
    ProfileError,
    bundled_profiles,
    load_profile,
)
from link_emulator.trace import mean_run_length
from link_emulator.validate import Settings, declared
from v2i.runtime.config import ConfigError

N_SAMPLES = 20_000
T0_NS = 1_700_000_000 * 10**9
PERIOD_NS = 100 * NS_PER_MS  # 10 Hz, the object-list rate


def _delays_ms(channel: Channel, n: int = N_SAMPLES, period_ns: int = PERIOD_NS) -> list[float | None]:
    """n delivery delays in ms (None when lost), one message of 200 B every ``period_ns``."""
    out: list[float | None] = []
    for k in range(n):
        send_ns = T0_NS + k * period_ns
        due_ns = channel.transmit(send_ns, 200)
        out.append(None if due_ns is None else (due_ns - send_ns) / NS_PER_MS)
    return out


def _direction(**fields) -> DirectionProfile:
    return DirectionProfile.model_validate(fields)


def test_bundled_profiles_are_listed_and_load() -> None:
    names = bundled_profiles()
    assert {"ideal", "dsrc", "lte-v2x"} <= set(names)
    for name in names:
        assert load_profile(name).name == name


def test_same_seed_same_draws_different_seed_different_draws() -> None:
    profile = load_profile("lte-v2x")
    a, b, c = LinkModel(profile, 7), LinkModel(profile, 7), LinkModel(profile, 8)
    draws_a = [a.downlink.transmit(T0_NS, 100) for _ in range(500)]
    assert draws_a == [b.downlink.transmit(T0_NS, 100) for _ in range(500)]
    assert draws_a != [c.downlink.transmit(T0_NS, 100) for _ in range(500)]


@pytest.mark.parametrize("name", bundled_profiles())
@pytest.mark.parametrize("direction", ["uplink", "downlink"])
def test_loss_ratio_and_median_delay_match_declaration(name: str, direction: str) -> None:
    profile = load_profile(name)
    spec = getattr(profile, direction)
    if spec.outage is not None and spec.outage.mode == "hold" and spec.outage.random_down_fraction() > 0.01:
        # the declaration describes a message sent while the link is up; long hold outages
        # (rural-5g-buffered: 2-30 s) only delay the others: compare the channel without them
        profile = profile.model_copy(update={direction: spec.model_copy(update={"outage": None})})
    channel = getattr(LinkModel(profile, seed=1), direction)
    send_ns = T0_NS + PERIOD_NS * np.arange(N_SAMPLES)
    out = channel.transmit_batch(send_ns, 200)  # equal to N single transmits, see the test below
    delivered = (out.deliver_ns[~out.lost] - send_ns[~out.lost]) / NS_PER_MS
    loss_ratio = 1.0 - delivered.size / N_SAMPLES
    summary, _ = declared(getattr(profile, direction), Settings(samples=N_SAMPLES, size_bytes=200))
    # Binomial standard error sqrt(p (1 - p) / n) <= 0.0036 for n = 20000; bursts and
    # outages (iaad-field: ~1 s every minute) widen it; allow ~0.012.
    assert loss_ratio == pytest.approx(summary.loss_ratio, abs=0.012)
    assert np.median(delivered) == pytest.approx(summary.p50_ms, rel=0.03, abs=0.05)
    assert delivered.mean() == pytest.approx(summary.mean_ms, rel=0.03, abs=0.05)
    assert delivered.min() >= 0.0


def test_delay_is_clipped_at_zero_and_declared_values_account_for_it() -> None:
    # Base 1 ms with N(0, 5^2) jitter: ~42 % of raw draws are negative and must be clipped.
    direction = _direction(delay_ms=1.0, jitter={"distribution": "normal", "std_ms": 5.0})
    delays = np.array(_delays_ms(Channel(direction, np.random.default_rng(3))))
    assert delays.min() == 0.0
    summary = direction.declared_delay_ms()
    assert np.median(delays) == pytest.approx(summary.median_ms, abs=0.15)
    assert delays.mean() == pytest.approx(summary.mean_ms, rel=0.03)


def test_uniform_jitter_with_negative_low_is_clipped() -> None:
    direction = _direction(delay_ms=2.0, jitter={"distribution": "uniform", "low_ms": -4.0, "high_ms": 4.0})
    delays = np.array(_delays_ms(Channel(direction, np.random.default_rng(5))))
    assert delays.min() == 0.0
    assert delays.mean() == pytest.approx(direction.declared_delay_ms().mean_ms, rel=0.03)


def test_send_time_is_preserved_in_delivery_time() -> None:
    channel = Channel(_direction(delay_ms=50.0), np.random.default_rng(0))
    assert channel.transmit(T0_NS, 10) == T0_NS + 50 * NS_PER_MS
    with pytest.raises(ValueError, match="size_bytes"):
        channel.transmit(T0_NS, -1)


def test_uplink_and_downlink_are_independent() -> None:
    profile = load_profile("lte-v2x")
    alone = LinkModel(profile, 11)
    downlink_alone = [alone.downlink.transmit(T0_NS, 100) for _ in range(1000)]
    mixed = LinkModel(profile, 11)
    downlink_mixed = []
    uplink_mixed = []
    for _ in range(1000):
        uplink_mixed.append(mixed.uplink.transmit(T0_NS, 100))
        downlink_mixed.append(mixed.downlink.transmit(T0_NS, 100))
    # Uplink traffic does not shift the downlink's random stream...
    assert downlink_mixed == downlink_alone
    # ...and the two directions are uncorrelated.
    pairs = np.array([(u, d) for u, d in zip(uplink_mixed, downlink_mixed) if u is not None and d is not None])
    assert abs(np.corrcoef(pairs[:, 0], pairs[:, 1])[0, 1]) < 0.1


def test_loss_one_drops_everything_loss_zero_nothing() -> None:
    lossy = Channel(_direction(delay_ms=1.0, loss_probability=1.0), np.random.default_rng(0))
    clean = Channel(_direction(delay_ms=1.0), np.random.default_rng(0))
    assert all(lossy.transmit(T0_NS, 1) is None for _ in range(100))
    assert all(clean.transmit(T0_NS, 1) is not None for _ in range(100))


def _write_profile(tmp_path, text: str):
    path = tmp_path / "custom.yaml"
    path.write_text(text)
    return path


def test_profile_from_file(tmp_path) -> None:
    path = _write_profile(
        tmp_path,
        "name: fixed\nuplink: {delay_ms: 50}\ndownlink: {delay_ms: 40, loss_probability: 0.5}\n",
    )
    profile = load_profile(path)
    assert isinstance(profile, LinkProfile)
    assert profile.uplink.declared_delay_ms() == (50.0, 50.0)
    assert profile.downlink.loss_probability == 0.5


@pytest.mark.parametrize(
    ("downlink", "field"),
    [
        ("{delay_ms: -1}", "downlink.delay_ms"),
        ("{delay_ms: 1, loss_probability: 1.5}", "downlink.loss_probability"),
        ("{delay_ms: 1, jitter: {distribution: normal, std_ms: -2}}", "downlink.jitter.normal.std_ms"),
        ("{delay_ms: 1, jitter: {distribution: uniform, low_ms: 3, high_ms: 1}}", "downlink.jitter.uniform.high_ms"),
        ("{delay_ms: 1, jitter: {distribution: lognormal, median_ms: 0, sigma: 1}}", "downlink.jitter.lognormal.median_ms"),
        ("{delay_ms: 1, jitter: {distribution: cauchy}}", "downlink.jitter"),
        ("{delay_ms: 1, bandwidth: 3}", "downlink.bandwidth"),
    ],
)
def test_profile_errors_name_the_field(tmp_path, downlink: str, field: str) -> None:
    path = _write_profile(tmp_path, f"name: bad\nuplink: {{delay_ms: 1}}\ndownlink: {downlink}\n")
    with pytest.raises(ProfileError, match=field.replace(".", r"\.")) as info:
        load_profile(path)
    assert isinstance(info.value, ConfigError)
    assert str(path) in str(info.value)


def test_unknown_profile_lists_bundled_names() -> None:
    with pytest.raises(ProfileError) as info:
        load_profile("no-such-profile")
    message = str(info.value)
    assert "no-such-profile" in message
    for name in bundled_profiles():
        assert name in message


def test_profile_yaml_must_be_a_mapping(tmp_path) -> None:
    with pytest.raises(ProfileError, match="mapping"):
        load_profile(_write_profile(tmp_path, "- just\n- a list\n"))


# ---- channel features ----------------------------------------------------------------------


def _send_times(n: int, period_ns: int = PERIOD_NS) -> np.ndarray:
    return T0_NS + period_ns * np.arange(n, dtype=np.int64)


def _batch_delays_ms(direction: DirectionProfile, n: int, seed: int = 0, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """Delays (ms, NaN when lost) and loss flags of n messages of 200 B at 10 Hz."""
    send_ns = kwargs.pop("send_ns", _send_times(n))
    out = Channel(direction, np.random.default_rng(seed)).transmit_batch(send_ns, kwargs.pop("size", 200), **kwargs)
    delays = np.where(out.lost, np.nan, (out.deliver_ns - send_ns) / NS_PER_MS)
    return delays, out.lost


def _lag1(x: np.ndarray) -> float:
    return float(np.corrcoef(x[:-1], x[1:])[0, 1])


@pytest.mark.parametrize("jitter", [
    {"distribution": "normal", "std_ms": 5.0},
    {"distribution": "lognormal", "median_ms": 10.0, "sigma": 0.6},
    {"distribution": "pareto", "scale_ms": 10.0, "shape": 4.0},
])
def test_correlation_raises_lag1_autocorrelation_and_keeps_the_marginal(jitter: dict) -> None:
    independent = _direction(delay_ms=50.0, jitter=jitter)
    correlated = _direction(delay_ms=50.0, jitter=jitter, correlation=0.8)
    plain, _ = _batch_delays_ms(independent, 50_000)
    corr, _ = _batch_delays_ms(correlated, 50_000)
    assert abs(_lag1(plain)) < 0.03
    assert _lag1(corr) > 0.6  # 0.8 on the normal score; a monotone transform keeps most of it
    # Gaussian copula: the marginal distribution is the declared one whatever rho
    for q in (0.1, 0.5, 0.9):
        declared_q = independent.jitter.quantile_ms(50.0, q)
        assert np.quantile(corr, q) == pytest.approx(declared_q, rel=0.03)


def test_fifo_never_reorders_and_reordering_happens_without_it() -> None:
    jitter = {"distribution": "uniform", "low_ms": 0.0, "high_ms": 300.0}
    send_ns = _send_times(5000, 10 * NS_PER_MS)  # 10 ms apart, up to 300 ms jitter
    fifo = Channel(_direction(delay_ms=5.0, jitter=jitter, fifo=True, duplicate_probability=0.2), np.random.default_rng(1))
    free = Channel(_direction(delay_ms=5.0, jitter=jitter), np.random.default_rng(1))
    fifo_ns = [t for s in send_ns for t in fifo.transmit_all(int(s), 100)]
    free_ns = [free.transmit(int(s), 100) for s in send_ns]
    assert np.all(np.diff(fifo_ns) >= 0)
    assert np.any(np.diff(free_ns) < 0)
    assert min(np.array(fifo_ns[:10]) - send_ns[0]) >= 5 * NS_PER_MS


@settings(max_examples=30, deadline=None)
@given(
    gaps_ms=st.lists(st.integers(0, 200), min_size=2, max_size=60),
    high_ms=st.floats(0.0, 500.0),
    dup=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_fifo_order_holds_for_any_send_pattern(gaps_ms: list[int], high_ms: float, dup: float, seed: int) -> None:
    direction = _direction(delay_ms=1.0, jitter={"distribution": "uniform", "low_ms": 0.0, "high_ms": high_ms},
                           fifo=True, duplicate_probability=dup, bandwidth_kbps=500.0)
    send_ns = T0_NS + np.cumsum(np.array(gaps_ms, dtype=np.int64) * NS_PER_MS)
    out = Channel(direction, np.random.default_rng(seed)).transmit_batch(send_ns, 300)
    seq = np.column_stack((out.deliver_ns, out.duplicate_ns)).reshape(-1)
    seq = seq[seq != NONE_NS]
    assert np.all(np.diff(seq) >= 0)
    assert np.all(out.deliver_ns[~out.lost] >= send_ns[~out.lost])


@pytest.mark.parametrize(("loss", "burst"), [(0.1, 5.0), (0.02, 3.0), (0.3, 2.0)])
def test_gilbert_elliott_mean_burst_length_and_rate_match(loss: float, burst: float) -> None:
    _, lost = _batch_delays_ms(_direction(delay_ms=1.0, loss_probability=loss, mean_burst_len=burst), 200_000)
    assert lost.mean() == pytest.approx(loss, rel=0.08)
    assert mean_run_length(lost) == pytest.approx(burst, rel=0.08)


def test_bernoulli_loss_has_geometric_bursts_and_short_requested_bursts_act_as_bernoulli() -> None:
    _, lost = _batch_delays_ms(_direction(delay_ms=1.0, loss_probability=0.3), 200_000)
    assert mean_run_length(lost) == pytest.approx(1 / 0.7, rel=0.03)
    _, lost_short = _batch_delays_ms(_direction(delay_ms=1.0, loss_probability=0.3, mean_burst_len=1.0), 200_000)
    assert mean_run_length(lost_short) == pytest.approx(1 / 0.7, rel=0.03)


def test_pdr_curve_against_distance_is_interpolated() -> None:
    direction = _direction(delay_ms=1.0, pdr_curve=[[0, 1.0], [100, 0.9], [300, 0.5]])
    for distance_m, pdr in ((0.0, 1.0), (50.0, 0.95), (100.0, 0.9), (200.0, 0.7), (300.0, 0.5), (900.0, 0.5)):
        _, lost = _batch_delays_ms(direction, 40_000, distance_m=distance_m)
        assert 1.0 - lost.mean() == pytest.approx(pdr, abs=0.012), distance_m
    _, unknown = _batch_delays_ms(direction, 5000, distance_m=None)
    _, nan = _batch_delays_ms(direction, 5000, distance_m=np.full(5000, np.nan))
    assert not unknown.any() and not nan.any()


def test_pdr_multiplies_the_distance_independent_loss() -> None:
    direction = _direction(delay_ms=1.0, loss_probability=0.2, pdr_curve=[[0, 0.5], [10, 0.5]])
    _, lost = _batch_delays_ms(direction, 100_000, distance_m=5.0)
    assert 1.0 - lost.mean() == pytest.approx(0.8 * 0.5, abs=0.01)


def test_range_limit_loses_everything_beyond_it() -> None:
    direction = _direction(delay_ms=1.0, range_m=80.0)  # seed 000: the virtual RSU transmits within 80 m
    distances = np.linspace(0.0, 160.0, 4001)
    _, lost = _batch_delays_ms(direction, distances.size, distance_m=distances)
    assert not lost[distances <= 80.0].any()
    assert lost[distances > 80.0].all()
    model = LinkModel(LinkProfile(name="r", uplink=direction, downlink=direction), 0)
    assert model.downlink.transmit(T0_NS, 100, distance_m=79.9) is not None
    assert model.downlink.transmit(T0_NS, 100, distance_m=80.1) is None


def test_serialization_and_queueing_make_big_messages_later() -> None:
    direction = _direction(delay_ms=10.0, bandwidth_kbps=100.0)  # 1000 B = 8000 bit = 80 ms
    small = Channel(direction, np.random.default_rng(0))
    big = Channel(direction, np.random.default_rng(0))
    assert small.transmit(T0_NS, 100) == T0_NS + 18 * NS_PER_MS  # 10 + 8 ms
    assert big.transmit(T0_NS, 1000) == T0_NS + 90 * NS_PER_MS  # 10 + 80 ms
    # back to back: the second waits for the first (Lindley), the third too
    queue = Channel(direction, np.random.default_rng(0))
    due = [queue.transmit(T0_NS + k * NS_PER_MS, 1000) for k in range(3)]
    assert [(d - T0_NS) // NS_PER_MS for d in due] == [90, 170, 250]
    # after an idle gap the queue is empty again
    assert queue.transmit(T0_NS + 10**9, 1000) == T0_NS + 10**9 + 90 * NS_PER_MS


def test_queue_limit_drops_what_would_wait_too_long() -> None:
    direction = _direction(delay_ms=0.0, bandwidth_kbps=100.0, queue_limit_ms=100.0)
    channel = Channel(direction, np.random.default_rng(0))
    fates = [channel.transmit(T0_NS, 1000) for _ in range(4)]  # each takes 80 ms
    # waits: 0, 80, 160 (> 100: dropped), 160 (the dropped one never occupied the queue)
    assert [None if f is None else (f - T0_NS) // NS_PER_MS for f in fates] == [80, 160, None, None]


def test_duplication_gives_two_deliveries_and_transmit_returns_the_first() -> None:
    direction = _direction(delay_ms=5.0, jitter={"distribution": "uniform", "low_ms": 0.0, "high_ms": 20.0},
                           duplicate_probability=0.3)
    channel = Channel(direction, np.random.default_rng(2))
    counts = [len(channel.transmit_all(int(t), 100)) for t in _send_times(10_000)]
    assert np.mean(np.array(counts) == 2) == pytest.approx(0.3, abs=0.02)
    assert set(counts) == {1, 2}
    twin = Channel(direction, np.random.default_rng(2))
    again = Channel(direction, np.random.default_rng(2))
    for t in _send_times(200):
        times = twin.transmit_all(int(t), 100)
        assert times == sorted(times) and again.transmit(int(t), 100) == times[0]
    never = Channel(_direction(delay_ms=5.0), np.random.default_rng(2))
    assert all(len(never.transmit_all(int(t), 100)) == 1 for t in _send_times(1000))


def test_scheduled_outage_drop_and_hold() -> None:
    outage = {"windows_s": [[1.0, 2.0]]}
    dropped = Channel(_direction(delay_ms=3.0, outage=outage), np.random.default_rng(0))
    held = Channel(_direction(delay_ms=3.0, outage={**outage, "mode": "hold"}), np.random.default_rng(0))
    send_ns = _send_times(40)  # 0 .. 3.9 s after the first message
    fates = [dropped.transmit(int(t), 10) for t in send_ns]
    inside = (send_ns - T0_NS >= 10**9) & (send_ns - T0_NS < 2 * 10**9)
    assert all((f is None) == i for f, i in zip(fates, inside))
    holds = np.array([held.transmit(int(t), 10) for t in send_ns])
    assert np.all(holds[inside] == T0_NS + 2 * 10**9 + 3 * NS_PER_MS)
    assert np.all(holds[~inside] == send_ns[~inside] + 3 * NS_PER_MS)


def test_random_outage_process_down_fraction() -> None:
    direction = _direction(delay_ms=1.0, outage={"mean_interval_s": 9.0, "duration_s": [0.5, 1.5]})
    _, lost = _batch_delays_ms(direction, 200_000)  # 20000 s, ~2000 outages
    assert lost.mean() == pytest.approx(1.0 / 10.0, rel=0.08)
    assert mean_run_length(lost) == pytest.approx(10.0, rel=0.1)  # ~1 s of 10 Hz messages


def test_impairment_windows_apply_only_inside_and_to_their_direction() -> None:
    model = LinkModel(load_profile("ideal"), 0)
    start, end = T0_NS + 10**9, T0_NS + 2 * 10**9
    model.add_impairment(start, end, direction="downlink", outage=True)
    model.add_impairment(end, end + 10**9, extra_delay_ms=40.0)
    model.add_impairment(end + 10**9, end + 2 * 10**9, direction="uplink", loss_probability=1.0)
    model.add_impairment(end + 2 * 10**9, end + 3 * 10**9, bandwidth_kbps=8.0)  # 100 B = 100 ms
    assert model.downlink.transmit(start - 1, 100) == start - 1
    assert model.downlink.transmit(start, 100) is None and model.downlink.transmit(end - 1, 100) is None
    assert model.uplink.transmit(start, 100) == start  # outage was downlink only
    assert model.downlink.transmit(end, 100) == end + 40 * NS_PER_MS
    assert model.uplink.transmit(end, 100) == end + 40 * NS_PER_MS
    t = end + 10**9
    assert model.uplink.transmit(t, 100) is None and model.downlink.transmit(t, 100) == t
    t = end + 2 * 10**9
    assert model.downlink.transmit(t, 100) == t + 100 * NS_PER_MS
    model.clear_impairments()
    assert model.downlink.transmit(start + 1, 100) == start + 1


def test_impairment_loss_probability_is_bernoulli_and_overlaps_combine() -> None:
    model = LinkModel(load_profile("ideal"), 3)
    model.add_impairment(T0_NS, T0_NS + 10**13, loss_probability=0.25)
    model.add_impairment(T0_NS, T0_NS + 10**13, loss_probability=0.5, extra_delay_ms=1.0)
    model.add_impairment(T0_NS, T0_NS + 10**13, extra_delay_ms=2.0)
    out = model.downlink.transmit_batch(_send_times(40_000), 100)
    assert out.lost.mean() == pytest.approx(0.5, abs=0.015)  # the highest probability wins
    assert np.all(out.deliver_ns[~out.lost] - _send_times(40_000)[~out.lost] == 3 * NS_PER_MS)  # extras add


@pytest.mark.parametrize("kwargs", [
    {"start_ns": 5, "end_ns": 5}, {"direction": "sideways"}, {"loss_probability": 1.5},
    {"bandwidth_kbps": 0.0}, {"extra_delay_ms": -1.0},
])
def test_bad_impairments_are_rejected(kwargs: dict) -> None:
    args = {"start_ns": 0, "end_ns": 10, **kwargs}
    with pytest.raises(ValueError):
        LinkModel(load_profile("ideal"), 0).add_impairment(**args)


def test_switch_profile_takes_effect_from_the_next_message() -> None:
    model = LinkModel(load_profile("ideal"), 0)
    assert model.downlink.transmit(T0_NS, 100) == T0_NS
    model.switch_profile(fixed := LinkProfile(name="slow", uplink=_direction(delay_ms=70.0),
                                              downlink=_direction(delay_ms=50.0)))
    assert model.profile is fixed
    assert model.downlink.transmit(T0_NS, 100) == T0_NS + 50 * NS_PER_MS
    assert model.uplink.transmit(T0_NS, 100) == T0_NS + 70 * NS_PER_MS


FULL = {
    "delay_ms": 5.0, "jitter": {"distribution": "lognormal", "median_ms": 10.0, "sigma": 0.8}, "correlation": 0.6,
    "spikes": {"probability": 0.1, "extra": {"distribution": "uniform", "low_ms": 0.0, "high_ms": 50.0}},
    "loss_probability": 0.1, "mean_burst_len": 3.0, "pdr_curve": [[0, 1.0], [100, 0.8]], "range_m": 150.0,
    "outage": {"mode": "hold", "windows_s": [[1.0, 2.0]], "mean_interval_s": 5.0, "duration_s": [0.2, 0.5]},
    "bandwidth_kbps": 200.0, "queue_limit_ms": 100.0, "fifo": True, "duplicate_probability": 0.2,
}


@settings(max_examples=25, deadline=None)
@given(
    gaps_ms=st.lists(st.integers(0, 120), min_size=1, max_size=80),
    sizes=st.lists(st.integers(0, 4000), min_size=80, max_size=80),
    fifo=st.booleans(),
    queue=st.booleans(),
    mode=st.sampled_from(["drop", "hold"]),
    seed=st.integers(0, 2**32 - 1),
    chunk=st.integers(1, 30),
)
def test_batch_equals_single_messages_for_every_feature(gaps_ms, sizes, fifo, queue, mode, seed, chunk) -> None:
    fields = {**FULL, "fifo": fifo, "outage": {**FULL["outage"], "mode": mode}}
    if not queue:  # without a send queue the jitter reorders often: fifo has work to do
        fields = {k: v for k, v in fields.items() if k not in ("bandwidth_kbps", "queue_limit_ms")}
    direction = _direction(**fields)
    n = len(gaps_ms)
    send_ns = T0_NS + np.cumsum(np.array(gaps_ms, dtype=np.int64) * NS_PER_MS)
    size = np.array(sizes[:n])
    distance = np.where(np.arange(n) % 5 == 0, np.nan, np.linspace(0.0, 200.0, n))
    singles = Channel(direction, np.random.default_rng(seed))
    expected = [singles.transmit_all(int(t), int(b), None if np.isnan(d) else float(d))
                for t, b, d in zip(send_ns, size, distance)]
    chunked = Channel(direction, np.random.default_rng(seed))
    got: list[list[int]] = []
    for i in range(0, n, chunk):
        out = chunked.transmit_batch(send_ns[i:i + chunk], size[i:i + chunk], distance[i:i + chunk])
        got += [sorted(int(t) for t in pair if t != NONE_NS) for pair in zip(out.deliver_ns, out.duplicate_ns)]
    assert got == expected


@pytest.mark.parametrize("fifo", [True, False])
@pytest.mark.parametrize("chunk", [1, 7, 500])
def test_batch_equals_single_messages_when_fifo_and_correlation_bind(fifo: bool, chunk: int) -> None:
    fields = {k: v for k, v in FULL.items() if k not in ("bandwidth_kbps", "queue_limit_ms")}
    direction = _direction(**{**fields, "fifo": fifo})
    send_ns = _send_times(500, 5 * NS_PER_MS)  # 5 ms apart, tens of ms of jitter: reordering is common
    singles = Channel(direction, np.random.default_rng(8))
    expected = [singles.transmit_all(int(t), 100, 50.0) for t in send_ns]
    batched = Channel(direction, np.random.default_rng(8))
    got: list[list[int]] = []
    for i in range(0, send_ns.size, chunk):
        out = batched.transmit_batch(send_ns[i:i + chunk], 100, 50.0)
        got += [sorted(int(t) for t in pair if t != NONE_NS) for pair in zip(out.deliver_ns, out.duplicate_ns)]
    assert got == expected
    firsts = [times[0] for times in expected if times]
    assert (np.all(np.diff(firsts) >= 0)) == fifo


@pytest.mark.parametrize("name", bundled_profiles())
def test_single_transmits_equal_the_batch_for_shipped_profiles(name: str) -> None:
    profile = load_profile(name)
    send_ns = _send_times(3000, 37 * NS_PER_MS)
    single = LinkModel(profile, 5)
    expected = [single.downlink.transmit(int(t), 1500) for t in send_ns]
    out = LinkModel(profile, 5).downlink.transmit_batch(send_ns, 1500)
    first = [None if lost else int(min(d, c) if c != NONE_NS else d)
             for lost, d, c in zip(out.lost, out.deliver_ns, out.duplicate_ns)]
    assert first == expected


def test_every_feature_is_deterministic_for_a_seed() -> None:
    direction = _direction(**FULL)
    send_ns = _send_times(20_000, 20 * NS_PER_MS)
    runs = [Channel(direction, np.random.default_rng(seed)).transmit_batch(send_ns, 800, 60.0) for seed in (4, 4, 5)]
    assert np.array_equal(runs[0].deliver_ns, runs[1].deliver_ns)
    assert np.array_equal(runs[0].duplicate_ns, runs[1].duplicate_ns)
    assert not np.array_equal(runs[0].deliver_ns, runs[2].deliver_ns)


def test_random_stream_of_a_message_does_not_depend_on_earlier_fates() -> None:
    # the same seed with and without loss: the delivered messages keep their delays
    lossless = _direction(delay_ms=5.0, jitter={"distribution": "exponential", "scale_ms": 4.0})
    lossy = _direction(delay_ms=5.0, jitter={"distribution": "exponential", "scale_ms": 4.0}, loss_probability=0.5)
    a, _ = _batch_delays_ms(lossless, 2000, seed=9)
    b, lost = _batch_delays_ms(lossy, 2000, seed=9)
    assert lost.any() and np.array_equal(a[~lost], b[~lost])


@pytest.mark.parametrize("fifo", [True, False])
@pytest.mark.parametrize("dup", [0.0, 0.3])
def test_plain_channel_single_transmits_equal_the_batch(fifo: bool, dup: float) -> None:
    """transmit_all's scalar path (no impairment, outage, trace or rate cap: ``_plain``) gives what
    one batch of every message gives: loss chain, distance PDR (unknown, in range, beyond range_m),
    correlated jitter, spikes, duplicates and fifo."""
    fields = {k: v for k, v in FULL.items() if k not in ("bandwidth_kbps", "queue_limit_ms", "outage")}
    direction = _direction(**{**fields, "fifo": fifo, "duplicate_probability": dup})
    send_ns = _send_times(2000, 5 * NS_PER_MS)
    distance = np.where(np.arange(send_ns.size) % 7 == 0, np.nan, np.linspace(0.0, 200.0, send_ns.size))
    singles = Channel(direction, np.random.default_rng(11))
    assert singles._plain()
    expected = [singles.transmit_all(int(t), 100, None if np.isnan(d) else float(d)) for t, d in zip(send_ns, distance)]
    out = Channel(direction, np.random.default_rng(11)).transmit_batch(send_ns, 100, distance)
    got = [sorted(int(t) for t in pair if t != NONE_NS) for pair in zip(out.deliver_ns, out.duplicate_ns)]
    assert got == expected
    assert 0 < sum(not times for times in expected) < send_ns.size  # some lost, not all
    assert any(len(times) == 2 for times in expected) == (dup > 0)


@pytest.mark.parametrize("name", bundled_profiles())
def test_one_distance_pdr_equals_the_profiles_curve(name: str) -> None:
    """Channel._pdr_one (transmit_all's scalar path) equals DirectionProfile.pdr_at, bit for bit,
    from 0 m to past range_m, at the curve's own knots and between them."""
    for channel in (LinkModel(load_profile(name), 0).uplink, LinkModel(load_profile(name), 0).downlink):
        d = channel.direction
        knots = [x for x, _ in d.pdr_curve or []] + ([d.range_m] if d.range_m is not None else [])
        for distance_m in [*np.linspace(0.0, 1500.0, 301), *knots, *(np.nextafter(k, np.inf) for k in knots)]:
            want = float(d.pdr_at(distance_m))
            got = channel._pdr_one(float(distance_m))
            assert np.float64(got).tobytes() == np.float64(want).tobytes(), (name, distance_m)
