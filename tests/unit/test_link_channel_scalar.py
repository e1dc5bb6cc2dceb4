"""The channel's per-message path (``Channel.transmit_all`` on a plain channel) in Python floats:
the jitter's g(z) taken from the block's column (``Channel._block_g``) and the distance PDR by
``channel._interp``, against the batch path (numpy over all the messages) and ``np.interp``."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from link_emulator.channel import NONE_NS, NS_PER_MS, Channel, _interp, _jitter_ms
from link_emulator.profile import DirectionProfile

T0_NS = 1_700_000_000 * 10**9
JITTERS = [
    {"distribution": "none"},
    {"distribution": "normal", "mean_ms": 1.0, "std_ms": 4.0},
    {"distribution": "uniform", "low_ms": -2.0, "high_ms": 30.0},
    {"distribution": "exponential", "scale_ms": 6.0},
    {"distribution": "lognormal", "median_ms": 7.0, "sigma": 0.8},
    {"distribution": "pareto", "scale_ms": 3.0, "shape": 1.5},
    {"distribution": "empirical", "samples_ms": [1.0, 2.5, 2.5, 9.0, 40.0]},
]


def _direction(jitter: dict, **fields) -> DirectionProfile:
    return DirectionProfile.model_validate({
        "delay_ms": 15.0, "jitter": jitter, "loss_probability": 0.05, "duplicate_probability": 0.1,
        "spikes": {"probability": 0.1, "extra": {"distribution": "uniform", "low_ms": 0.0, "high_ms": 100.0}},
        "pdr_curve": [[0, 1.0], [100, 1.0], [300, 0.98], [500, 0.67]], **fields})


def _fates(out) -> list[list[int]]:
    return [sorted(int(t) for t in pair if t != NONE_NS) for pair in zip(out.deliver_ns, out.duplicate_ns)]


@pytest.mark.parametrize("jitter", JITTERS, ids=[j["distribution"] for j in JITTERS])
def test_single_messages_equal_one_batch_across_blocks(jitter: dict) -> None:
    """2500 messages (three blocks of variates) one by one, then as one batch: the same fates."""
    direction = _direction(jitter)
    send_ns = T0_NS + 7 * NS_PER_MS * np.arange(2500, dtype=np.int64)
    distance = np.linspace(0.0, 700.0, send_ns.size)
    singles = Channel(direction, np.random.default_rng(3))
    assert singles._plain()
    expected = [singles.transmit_all(int(t), 100, float(d)) for t, d in zip(send_ns, distance)]
    got = _fates(Channel(direction, np.random.default_rng(3)).transmit_batch(send_ns, 100, distance))
    assert got == expected
    assert any(len(times) == 2 for times in expected) and any(not times for times in expected)


def test_a_profile_switch_inside_a_block_uses_the_new_jitter() -> None:
    """g(z) kept for a block belongs to its jitter: after ``set_direction`` the next message uses the new one."""
    first, second = _direction(JITTERS[4]), _direction(JITTERS[2], delay_ms=40.0)
    send_ns = T0_NS + 10 * NS_PER_MS * np.arange(600, dtype=np.int64)
    singles, batched = Channel(first, np.random.default_rng(5)), Channel(first, np.random.default_rng(5))
    expected = [singles.transmit_all(int(t), 100, 50.0) for t in send_ns[:300]]
    got = _fates(batched.transmit_batch(send_ns[:300], 100, 50.0))
    singles.set_direction(second)
    batched.set_direction(second)
    expected += [singles.transmit_all(int(t), 100, 50.0) for t in send_ns[300:]]
    got += _fates(batched.transmit_batch(send_ns[300:], 100, 50.0))
    assert got == expected


@pytest.mark.parametrize("jitter", JITTERS, ids=[j["distribution"] for j in JITTERS])
def test_block_g_equals_the_one_score_expression(jitter: dict) -> None:
    """Each entry of g over a block's column is, bit for bit, ``_jitter_ms`` of that one score."""
    channel = Channel(_direction(jitter), np.random.default_rng(1))
    for _ in range(1500):
        k, z, _ = channel._draws.take_one()
        for column in range(3):
            got = channel._block_g(channel.direction.jitter, column, k)
            assert np.float64(got).tobytes() == np.float64(_jitter_ms(channel.direction.jitter, z[column][k])).tobytes()


@settings(max_examples=200, deadline=None)
@given(points=st.lists(st.tuples(st.floats(0.0, 2000.0), st.floats(0.0, 1.0)), min_size=1, max_size=6),
       seed=st.integers(0, 2**32 - 1))
def test_interp_equals_numpy_bit_for_bit(points: list, seed: int) -> None:
    xp = sorted({x for x, _ in points})
    fp = [p for _, p in points][:len(xp)]
    rng = np.random.default_rng(seed)
    xs = [*rng.uniform(-10.0, 2100.0, 300), *xp, *(np.nextafter(x, np.inf) for x in xp),
          *(np.nextafter(x, -np.inf) for x in xp), np.inf, 0.0]
    for x in xs:
        want = np.interp(x, np.array(xp), np.array(fp))
        assert np.float64(_interp(float(x), xp, fp)).tobytes() == np.float64(want).tobytes(), (x, xp, fp)


def test_take_one_gives_each_row_of_the_blocks_as_floats():
    """take_one's k-th entries of the block's columns are the row ``take(1)`` gives, across blocks."""
    from link_emulator.channel import _Draws

    draws, reference = _Draws(np.random.default_rng(2)), _Draws(np.random.default_rng(2))
    for _ in range(2500):
        k, z, u = draws.take_one()
        normal, uniform = reference.take(1)
        assert [column[k] for column in z] == normal[0].tolist()
        assert [column[k] for column in u] == uniform[0].tolist()
