"""Pure tests of the link profiles and channel models (no Zenoh, no clock)."""

from __future__ import annotations

import numpy as np
import pytest

from link_emulator.channel import NS_PER_MS, Channel, LinkModel
from link_emulator.profile import (
    DirectionProfile,
    LinkProfile,
    ProfileError,
    bundled_profiles,
    load_profile,
)
from schemas.config import ConfigError

N_SAMPLES = 20_000
T0_NS = 1_700_000_000 * 10**9


def _delays_ms(channel: Channel, n: int = N_SAMPLES) -> list[float | None]:
    """n delivery delays in ms (None when lost), sent at a fixed epoch time."""
    out: list[float | None] = []
    for _ in range(n):
        due_ns = channel.transmit(T0_NS, 200)
        out.append(None if due_ns is None else (due_ns - T0_NS) / NS_PER_MS)
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
    declared = getattr(profile, direction)
    delays = _delays_ms(getattr(LinkModel(profile, seed=1), direction))
    delivered = np.array([d for d in delays if d is not None])
    loss_ratio = 1.0 - delivered.size / N_SAMPLES
    # Binomial standard error sqrt(p (1 - p) / n) <= 0.0036 for n = 20000; allow ~5 sigma.
    assert loss_ratio == pytest.approx(declared.loss_probability, abs=0.006)
    summary = declared.declared_delay_ms()
    assert np.median(delivered) == pytest.approx(summary.median_ms, rel=0.03, abs=0.05)
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
