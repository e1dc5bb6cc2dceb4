"""The fusion-mode policy: each mode is chosen when it should be, with hysteresis upwards."""

from __future__ import annotations

import pytest

from obu_service.fusion_mode import FUSION_MODES, MODES, Feasible, ModePolicy

ALL = Feasible(intra=True, inter=True, planning=True)
NONE = Feasible()


def test_adaptive_picks_the_most_accurate_feasible_mode() -> None:
    policy = ModePolicy("adaptive", hysteresis_cycles=1)
    assert policy.select(ALL) == "intra"
    assert policy.select(Feasible(inter=True, planning=True)) == "inter"
    assert policy.select(Feasible(planning=True)) == "planning"
    assert policy.select(NONE) == "vehicle-only"


def test_intra_and_inter_alternate_freely_within_tracking() -> None:
    policy = ModePolicy("adaptive", hysteresis_cycles=5)
    for _ in range(5):
        policy.select(Feasible(inter=True))
    seen = [policy.select(Feasible(intra=k % 2 == 0, inter=True)) for k in range(6)]
    assert seen == ["intra", "inter"] * 3


def test_going_down_is_immediate_and_coming_back_needs_a_stable_streak() -> None:
    policy = ModePolicy("adaptive", hysteresis_cycles=3)
    for _ in range(3):
        assert policy.select(Feasible(inter=True, planning=True)) == "inter"
    assert policy.select(Feasible(planning=True)) == "planning"  # tracking lost: down at once
    # tracking is feasible again, but only the third feasible cycle in a row brings it back
    assert policy.select(Feasible(inter=True, planning=True)) == "planning"
    assert policy.select(Feasible(inter=True, planning=True)) == "planning"
    assert policy.select(Feasible(inter=True, planning=True)) == "inter"


def test_a_flapping_link_does_not_flap_the_mode() -> None:
    policy = ModePolicy("adaptive", hysteresis_cycles=3)
    policy.select(Feasible(planning=True))
    modes = [policy.select(Feasible(inter=k % 2 == 0, planning=True)) for k in range(20)]
    assert set(modes) == {"planning"}


def test_a_level_that_becomes_infeasible_is_left_even_during_hysteresis() -> None:
    policy = ModePolicy("adaptive", hysteresis_cycles=10)
    assert policy.select(Feasible(planning=True)) == "planning"
    # planning itself is gone: the policy must move, to tracking if that is what is left
    assert policy.select(Feasible(inter=True)) == "inter"
    assert policy.select(NONE) == "vehicle-only"


def test_fixed_modes_are_always_planned() -> None:
    for mode in MODES:
        assert ModePolicy(mode).select(NONE) == mode


def test_resolve_falls_back_within_the_cycle_only_when_adaptive() -> None:
    adaptive, intra = ModePolicy("adaptive"), ModePolicy("intra")
    frame_late = Feasible(intra=False, inter=True, planning=True)
    assert adaptive.resolve("intra", frame_late) == "inter"
    assert adaptive.resolve("intra", Feasible(planning=True)) == "planning"
    assert adaptive.resolve("inter", NONE) == "vehicle-only"
    assert adaptive.resolve("planning", ALL) == "planning"  # never up within a cycle
    assert intra.resolve("intra", frame_late) == "vehicle-only"  # a fixed mode that missed: no RSU data
    assert intra.resolve("intra", ALL) == "intra"


def test_bad_arguments_are_rejected() -> None:
    assert FUSION_MODES[0] == "adaptive"
    with pytest.raises(ValueError, match="fusion mode"):
        ModePolicy("sometimes")
    with pytest.raises(ValueError, match="hysteresis"):
        ModePolicy("adaptive", hysteresis_cycles=0)
