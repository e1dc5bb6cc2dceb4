"""The ghost recogniser of ``v2i attack`` (v2i.adversary.attack_ghosts) on hand-made fused outputs."""

from __future__ import annotations

import numpy as np

from v2i.adversary.attack_ghosts import GhostWatch
from v2i.adversary.attack_messages import ghost_xy
from v2i.core.frames import Pose2D, map_to_base_points
from schemas.classes import ObjectClass
from schemas.limits import SOURCE_RSU, SOURCE_VEHICLE
from schemas.messages import FusedObject, FusedObjectList

T_NS = 1_800_000_000 * 10**9
EGO = Pose2D(5.25, -12.35, np.pi / 2)


def output(*objects: tuple[np.ndarray, ObjectClass, int], t_ns: int = T_NS) -> FusedObjectList:
    """A fused list at ``t_ns`` of objects given as (map xy, class, sources), in base_link."""
    rows = []
    for i, (xy, cls, sources) in enumerate(objects):
        bx, by = map_to_base_points(np.asarray(xy, float)[None], EGO)[0]
        rows.append(FusedObject(id=i, cls=cls, x=bx, y=by, length=0.6, width=0.6, sources=sources))
    return FusedObjectList(vehicle_id="ego", seq=1, cycle_time_ns=t_ns, publish_time_ns=t_ns + 10**7,
                           ego_x=EGO.x, ego_y=EGO.y, ego_yaw=EGO.yaw, objects=rows)


def test_a_ghost_where_it_was_put_counts_once():
    watch, spot = GhostWatch(), ghost_xy(EGO)
    watch.place(T_NS - 200_000_000, spot)
    assert watch.ghosts_in(output((spot + [0.5, 0.5], ObjectClass.PEDESTRIAN, SOURCE_RSU))) == 1
    assert watch.ghosts_in(output((spot, ObjectClass.PEDESTRIAN, SOURCE_RSU | SOURCE_VEHICLE),
                                  (spot + [20.0, 0.0], ObjectClass.PEDESTRIAN, SOURCE_RSU))) == 1


def test_not_ghosts_wrong_class_vehicle_only_far_or_too_old():
    watch, spot = GhostWatch(), ghost_xy(EGO)
    watch.place(T_NS - 200_000_000, spot)
    assert watch.ghosts_in(output((spot, ObjectClass.CAR, SOURCE_RSU))) == 0
    assert watch.ghosts_in(output((spot, ObjectClass.PEDESTRIAN, SOURCE_VEHICLE))) == 0
    assert watch.ghosts_in(output((spot + [2.5, 0.0], ObjectClass.PEDESTRIAN, SOURCE_RSU))) == 0
    assert watch.ghosts_in(output((spot, ObjectClass.PEDESTRIAN, SOURCE_RSU), t_ns=T_NS + 5 * 10**9)) == 0
    assert GhostWatch().ghosts_in(output((spot, ObjectClass.PEDESTRIAN, SOURCE_RSU))) == 0  # nothing placed


def test_a_genuine_rsu_object_at_the_spot_is_not_a_ghost():
    watch, spot = GhostWatch(), ghost_xy(EGO)
    watch.place(T_NS - 200_000_000, spot)
    # a genuine pedestrian captured 0.5 s ago 1 m short of the spot, walking 2 m/s towards it
    watch.genuine(T_NS - 500_000_000, (spot - [1.0, 0.0])[None], np.array([[2.0, 0.0]]))
    assert watch.ghosts_in(output((spot, ObjectClass.PEDESTRIAN, SOURCE_RSU))) == 0
    # the same pedestrian captured 2 s ago is forgotten: the ghost counts
    watch2 = GhostWatch()
    watch2.place(T_NS - 200_000_000, spot)
    watch2.genuine(T_NS - 2 * 10**9, (spot - [1.0, 0.0])[None], np.zeros((1, 2)))
    assert watch2.ghosts_in(output((spot, ObjectClass.PEDESTRIAN, SOURCE_RSU))) == 1


def test_decoys_are_judged_apart_from_sent_ghosts():
    watch, spot = GhostWatch(), ghost_xy(EGO)
    watch.place(T_NS - 200_000_000, spot, decoy=True)
    fused = output((spot, ObjectClass.PEDESTRIAN, SOURCE_RSU))
    assert watch.ghosts_in(fused) == 0 and watch.ghosts_in(fused, decoy=True) == 1
