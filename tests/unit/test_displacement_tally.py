"""IAAD's displacement error (``DisplacementTally``) follows each matched actor by id over its path."""

from types import SimpleNamespace

import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from v2i.fusion.wire import states_from_objects
from v2i.scoring.metrics import DisplacementTally
from schemas.messages import ObjectListHeader, PredictedPath, PredictionList

T0 = 1_767_225_600 * 10**9


def cars(xy, ids) -> ObjectArray:
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    return ObjectArray(ids=np.asarray(ids), cls=np.ones(n, int), xy=xy, z=np.zeros(n), lwh=np.tile([4.5, 1.8, 1.5], (n, 1)),
                       yaw=np.zeros(n), vxy=np.zeros((n, 2)))


class ComingAndGoing:
    """Actor 7 drives east at 10 m/s from x = -40 m; actor 3, listed before it, leaves after 0.45 s
    (so actor 7's row number changes), actor 9 appears after 1 s (listed first)."""

    scenario = SimpleNamespace(duration_s=10.0)

    def actors_at(self, t_s: float) -> ObjectArray:
        rows = [([50.0, 50.0], 3)] if t_s < 0.45 else []
        rows = ([([0.0, 80.0], 9)] if t_s >= 1.0 else []) + rows + [([-40.0 + 10.0 * t_s, 0.0], 7)]
        return cars([xy for xy, _ in rows], [i for _, i in rows])


def paths_along(offset_m: float) -> PredictionList:
    """The RSU's paths at t0 = 0: actor 7's, 2 s at 10 Hz, ``offset_m`` north of its true track."""
    k = np.arange(1, 21) * 0.1
    path = PredictedPath(id=1, x=(-40.0 + 10.0 * k).tolist(), y=[offset_m] * 20, yaw=[0.0] * 20)
    header = ObjectListHeader(rsu_id="rsu1", seq=1, capture_time_ns=T0, publish_time_ns=T0 + 50_000_000)
    objects = cars([[-40.0, offset_m]], [1]).with_(vxy=np.array([[10.0, 0.0]]))
    return PredictionList(header=header, objects=states_from_objects(objects), paths=(path,))


@pytest.mark.parametrize("offset_m", [0.0, 0.5])
def test_displacement_follows_the_actor_by_id_while_others_come_and_go(offset_m):
    tally = DisplacementTally(ComingAndGoing(), T0)
    tally.add(paths_along(offset_m))
    assert tally.value() == pytest.approx(offset_m, abs=1e-6)  # every point of the path, against actor 7
