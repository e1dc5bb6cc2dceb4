"""CPM generation rules (rsu_service.cpm_rules): each rule fires past its threshold and not at it."""

from __future__ import annotations

import numpy as np
import pytest

from rsu_service.cpm_rules import CpmInclusion, CpmRulesConfig
from schemas.classes import ObjectClass

MS = 1_000_000
CAR, PED, CYC, MOTO = int(ObjectClass.CAR), int(ObjectClass.PEDESTRIAN), int(ObjectClass.CYCLIST), int(ObjectClass.MOTORCYCLE)


def event(rules: CpmInclusion, t_ms: float, objs: list[tuple], send_all: bool = True) -> tuple[bool, list[int]]:
    """One generation event over ``objs`` = [(id, x, y, vx, vy, yaw, cls)]: (send, ids selected); the
    selected rows are committed as sent (``send_all``) or the event as not sent."""
    a = np.array(objs, dtype=np.float64).reshape(-1, 7)
    ids, xy, vxy, yaw, cls = a[:, 0].astype(int), a[:, 1:3], a[:, 3:5], a[:, 5], a[:, 6].astype(int)
    t_ns = round(t_ms * MS)
    sel = rules.select(t_ns, ids, xy, vxy, yaw, cls)
    rules.commit(t_ns, ids, xy, vxy, yaw, sel.indices if sel.send and send_all else None)
    return sel.send, ids[sel.indices].tolist()


def car(x=0.0, y=0.0, vx=10.0, vy=0.0, yaw=0.0, i=1, cls=CAR):
    return (i, x, y, vx, vy, yaw, cls)


def test_a_new_object_is_included_and_a_steady_one_is_not():
    rules = CpmInclusion()
    assert event(rules, 0, [car()]) == (True, [1])
    # 200 ms later, 1 m further at the same velocity: nothing to include, and the last CPM was 200 ms ago
    assert event(rules, 200, [car(x=1.0)]) == (False, [])
    assert rules.included_by == {"new": 1}


@pytest.mark.parametrize("dx, included", [(4.0, False), (4.01, True)])
def test_position_rule_fires_past_4_m(dx, included):
    rules = CpmInclusion()
    event(rules, 0, [car(vx=0.0)])
    assert event(rules, 200, [car(x=dx * 0.6, y=dx * 0.8, vx=0.0)])[1] == ([1] if included else [])


@pytest.mark.parametrize("dv, included", [(0.5, False), (0.51, True)])
def test_speed_rule_fires_past_half_a_metre_per_second(dv, included):
    rules = CpmInclusion()
    event(rules, 0, [car(vx=10.0)])
    assert event(rules, 200, [car(vx=10.0 - dv)])[1] == ([1] if included else [])


@pytest.mark.parametrize("deg, included", [(3.99, False), (4.01, True), (-4.01, True)])
def test_heading_rule_fires_past_4_degrees_of_the_ground_velocity(deg, included):
    rules = CpmInclusion()
    event(rules, 0, [car(vx=10.0, yaw=0.0)])
    a = np.deg2rad(deg)
    # the body yaw stays 0: the rule compares the velocity's orientation
    assert event(rules, 200, [car(vx=10.0 * np.cos(a), vy=10.0 * np.sin(a), yaw=0.0)])[1] == ([1] if included else [])


def test_heading_wraps_around_pi():
    rules = CpmInclusion()
    a, b = np.deg2rad(179.0), np.deg2rad(-179.0)  # 2 degrees apart across the wrap
    event(rules, 0, [car(vx=10 * np.cos(a), vy=10 * np.sin(a))])
    assert event(rules, 200, [car(vx=10 * np.cos(b), vy=10 * np.sin(b))])[1] == []


def test_a_standing_object_compares_its_yaw():
    rules = CpmInclusion()
    event(rules, 0, [car(vx=0.0, yaw=0.0)])
    assert event(rules, 200, [car(vx=0.0, yaw=np.deg2rad(3.0))])[1] == []
    assert event(rules, 400, [car(vx=0.0, yaw=np.deg2rad(4.5))])[1] == [1]


@pytest.mark.parametrize("t_ms, included", [(999.0, False), (1000.0, True)])
def test_a_type_b_object_is_refreshed_after_t_gen_cpm_max(t_ms, included):
    rules = CpmInclusion()
    event(rules, 0, [car(vx=0.0), car(vx=0.0, x=50.0, i=2)])
    event(rules, 500, [car(vx=0.0), car(vx=0.0, x=50.0, i=2), car(i=3, x=90.0)])  # a CPM (object 3 is new)
    assert event(rules, t_ms, [car(vx=0.0), car(vx=0.0, x=50.0, i=2), car(i=3, x=90.0)])[1] == ([1, 2] if included else [])


def test_motorcycles_are_type_b():
    rules = CpmInclusion()
    event(rules, 0, [car(vx=0.0, cls=MOTO)])
    assert event(rules, 600, [car(vx=0.0, cls=MOTO)])[1] == []


@pytest.mark.parametrize("t_ms, included", [(499.0, False), (500.0, True)])
def test_one_overdue_vru_brings_every_vru(t_ms, included):
    rules = CpmInclusion()
    event(rules, 0, [car(vx=1.4, i=1, cls=PED)])
    both = [car(vx=1.4, i=1, cls=PED), car(vx=4.0, x=5.0, i=2, cls=CYC), car(x=60.0, i=3)]
    assert event(rules, 300, both)[1] == [2, 3]  # new ones
    # at 500 ms the pedestrian is T_GenCpmMax / 2 without inclusion: both VRUs go (the cyclist sent 200 ms
    # ago too); the car, steady since 300 ms, does not
    got = event(rules, t_ms, both)[1]
    assert got == ([1, 2] if included else [])


def test_vrus_ignore_the_kinematic_rules():
    rules = CpmInclusion()
    event(rules, 0, [car(vx=1.0, cls=PED)])
    assert event(rules, 200, [car(x=5.0, vx=3.0, vy=2.0, cls=PED)])[1] == []


def test_a_cpm_goes_at_least_every_t_gen_cpm_max_even_empty():
    rules = CpmInclusion()
    objs = [car(vx=0.0, cls=PED)]
    assert event(rules, 0, [])[0] is True  # the first event sends (nothing sent before)
    assert event(rules, 200, []) == (False, [])
    assert event(rules, 999, []) == (False, [])
    assert event(rules, 1000, []) == (True, [])
    assert event(rules, 1100, objs) == (True, [1])


def test_events_sooner_than_t_gen_cpm_min_send_nothing():
    rules = CpmInclusion()
    event(rules, 0, [car()])
    assert event(rules, 99, [car(i=2)]) == (False, [])
    assert rules.events["too_soon"] == 1
    assert event(rules, 100, [car(i=2)]) == (True, [2])  # still new: it was never sent


def test_a_track_that_disappears_is_new_when_it_comes_back():
    rules = CpmInclusion()
    event(rules, 0, [car(vx=0.0), car(vx=0.0, x=30.0, i=2)])
    event(rules, 200, [car(vx=0.0)])
    assert event(rules, 400, [car(vx=0.0), car(vx=0.0, x=30.0, i=2)])[1] == [2]


def test_objects_not_sent_stay_due():
    rules = CpmInclusion()
    ids, xy, vxy, yaw, cls = np.array([1, 2]), np.zeros((2, 2)), np.zeros((2, 2)), np.zeros(2), np.array([CAR, CAR])
    sel = rules.select(0, ids, xy, vxy, yaw, cls)
    rules.commit(0, ids, xy, vxy, yaw, sel.indices[:1])  # segmentation left object 2 out
    assert rules.select(200 * MS, ids, xy, vxy, yaw, cls).indices.tolist() == [1]


def test_thresholds_are_configurable():
    rules = CpmInclusion(CpmRulesConfig(min_position_change_m=1.0))
    event(rules, 0, [car(vx=0.0)])
    assert event(rules, 200, [car(x=1.5, vx=0.0)])[1] == [1]
