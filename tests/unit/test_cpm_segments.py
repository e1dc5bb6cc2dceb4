"""CpmSender (rsu_service.cpm_segments): CPMs under the generation rules, segmented to the MTU with
segmentationInfo, each segment a complete CPM the OBU reads on its own."""

from __future__ import annotations

import numpy as np
import pytest

from rsu_service.cpm_segments import MAX_SEGMENTS, CpmSender, segment_info
from schemas import list_wire
from schemas import standard_wire as sw
from schemas.classes import ObjectClass
from schemas.messages import ObjectList, ObjectListHeader

T0 = 1_767_225_600_000_000_000
MS = 1_000_000


def _list(n: int, seq: int = 7, x0: float = 0.0) -> ObjectList:
    """n moving cars 5 m apart (ids 100..), captured at T0."""
    cols = sw.empty_columns(n)
    cols.update(id=np.arange(100, 100 + n, dtype=float), cls=np.full(n, float(ObjectClass.CAR)),
                x=x0 + 5.0 * np.arange(n), y=np.full(n, 3.0), vx=np.full(n, 8.0), length=np.full(n, 4.5),
                width=np.full(n, 1.8), height=np.full(n, 1.5), cov_xx=np.full(n, 0.5), cov_yy=np.full(n, 0.5),
                cov_vxx=np.full(n, 0.04), cov_vyy=np.full(n, 0.04), confidence=np.full(n, 0.9))
    header = ObjectListHeader(rsu_id="rsu1", seq=seq, capture_time_ns=T0, publish_time_ns=T0 + 90 * MS)
    return sw.object_list(header, cols)


def _sender(mtu: int = 1100) -> CpmSender:
    return CpmSender(lambda m: list_wire.encode_list(m, "cpm"), mtu)


def test_a_list_that_fits_goes_as_one_unsegmented_cpm():
    data = _sender().messages(_list(5), 0)
    assert len(data) == 1 and segment_info(data[0]) is None
    got = list_wire.decode_list(data[0], "cpm", "rsu1")
    assert got.objects.ids.tolist() == list(range(100, 105))


def test_a_list_over_the_mtu_is_split_into_complete_segments():
    sender = _sender(600)
    whole = list_wire.encode_list(_list(40), "cpm")
    data = sender.messages(_list(40), 0)
    assert len(whole) > 600 and len(data) > 1
    assert all(len(d) <= 600 for d in data)
    assert [segment_info(d) for d in data] == [(k + 1, len(data)) for k in range(len(data))]
    lists = [list_wire.decode_list(d, "cpm", "rsu1") for d in data]  # each segment read on its own
    assert len({(m.header.capture_time_ns, m.header.publish_time_ns) for m in lists}) == 1  # one event's times
    ids = np.concatenate([m.objects.ids for m in lists])
    assert sorted(ids.tolist()) == list(range(100, 140))
    assert sender.segmented == 1 and sender.overflow == 0
    assert sender.messages(_list(1), 300 * MS) == []  # nothing due: no CPM
    later = sender.messages(_list(1), 1300 * MS)  # T_GenCpmMax: object 100 refreshed
    assert list_wire.decode_list(later[0], "cpm", "rsu1").objects.ids.tolist() == [100]


def test_objects_past_eight_segments_stay_due_for_the_next_event():
    sender = _sender(200)
    first = sender.messages(_list(60), 0)
    assert len(first) == MAX_SEGMENTS and sender.overflow > 0
    sent = {int(i) for d in first for i in list_wire.decode_list(d, "cpm", "rsu1").objects.ids}
    # 200 ms later the cars moved 1.6 m: only those never sent are due (rule: new)
    moved = _list(60, x0=1.6)
    later = {int(i) for d in sender.messages(moved, 200 * MS) for i in list_wire.decode_list(d, "cpm", "rsu1").objects.ids}
    assert later == set(range(100, 160)) - sent


@pytest.mark.parametrize("t_ms, count", [(50, 0), (200, 0), (1000, 1)])
def test_steady_objects_are_refreshed_by_the_rules(t_ms, count):
    sender = _sender()
    sender.messages(_list(3), 0)
    data = sender.messages(_list(3), t_ms * MS)  # same positions and velocities
    assert len(data) == count
    if count:
        assert len(list_wire.decode_list(data[0], "cpm", "rsu1").objects) == 3  # T_GenCpmMax refresh
