"""The files and functions one RSU object list passes through in the OBU (issue 29's measure).

    python benchmarks/input_path.py

From ``ObuNode._handle_input`` (one encoded v2i list, policy off, off the intake) until the
``Tracker.update`` that takes its objects. The set-up, untraced: four time exchanges (the
RSU's clock is known), then 20 cycles of own detections at 10 Hz each followed 10 ms later by
the RSU's list of the same capture time, so that the adaptive policy plans the 21st cycle as
intra and waits for its list: that list's ``_handle_input`` fuses the cycle, and one call chain
runs from the intake to the tracker.

Method: ``sys.setprofile`` records every Python call into a file under ``src/`` (dataclass-made
methods and library code are not counted), leaving out the own LiDAR objects' tracker update
(``KalmanFusion._update`` with per-object sources), and stops at the ``Tracker.update`` carrying
the RSU slot's source bit. Printed for the input stage (until the node's ``_publish_if_ready``)
and for the whole path: files (in order of first visit), stops (distinct functions), calls
(every call), calls into another file and how many of those go back into a file already visited,
and the functions entered more than once.
"""

from __future__ import annotations

import os
import sys
from collections import Counter

import numpy as np

from v2i.core.frames import Pose2D
from v2i.core.objects import ObjectArray
from v2i.fusion.wire import states_from_objects
from v2i.runtime.intake import Item
from obu_service.config import ObuConfig
from obu_service.node import ObuNode
from rsu_service.pipeline import answer_time_request
from schemas import keys
from schemas.codec import encode
from schemas.messages import ObjectList, ObjectListHeader
from v2i.services import obu_node

SRC = os.path.realpath(os.path.join(os.path.dirname(__file__), "..", "src")) + os.sep
T0_NS = 1_767_225_600 * 10**9
THETA_NS = 350_000_000  # RSU clock - OBU clock
MS = 1_000_000
RSU = "rsu1"
Call = tuple[str, str, str | None]  # (file, function, caller's file or None)


class StepClock:
    """The node's clock, set by hand."""

    def __init__(self, t_ns: int):
        self.t_ns = t_ns

    def now_ns(self) -> int:
        return self.t_ns


class Sink:
    def put(self, _data: bytes) -> None:
        pass


def objects(xy, vxy) -> ObjectArray:
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    return ObjectArray(ids=np.arange(1, n + 1), cls=np.ones(n, int), xy=xy, z=np.full(n, 0.75),
                       lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=np.zeros(n), vxy=np.atleast_2d(vxy))


def rsu_item(seq: int, capture_ns: int) -> Item:
    """The RSU's list of capture time ``capture_ns`` (OBU clock), received 60 ms later."""
    header = ObjectListHeader(rsu_id=RSU, seq=seq, capture_time_ns=capture_ns + THETA_NS,
                              publish_time_ns=capture_ns + 40 * MS + THETA_NS)
    data = encode(ObjectList(header=header, objects=states_from_objects(objects([[20.0 + 0.5 * seq, 3.0]],
                                                                                [[5.0, 0.0]]))))
    return Item("rsu", keys.rsu_objects(RSU), data, capture_ns + 60 * MS)


def prepared_node() -> tuple[ObuNode, StepClock, Item]:
    """A node with the RSU's clock known and an intra cycle waiting for the returned list."""
    clock = StepClock(T0_NS)
    node = obu_node(ObuConfig(duration_s=5.0, start_at_ns=T0_NS), clock)
    node._pub = {name: Sink() for name in ("objects", "metrics", "pose", "planning")}
    pipeline = node.pipeline
    for k in range(4):
        t1_ns = T0_NS + k * 100 * MS
        t2_ns = t1_ns + 5 * MS + THETA_NS
        reply = answer_time_request(pipeline.make_time_request(t1_ns), RSU, t2_ns, t2_ns)
        clock.t_ns = t1_ns + 10 * MS
        node._handle_input(Item("time", keys.rsu_time(RSU), encode(reply), clock.t_ns))
    for k in range(21):
        capture_ns = T0_NS + (10 + k) * 100 * MS
        pipeline.on_pose(capture_ns, Pose2D(0.0, 0.0, 0.0))
        clock.t_ns = capture_ns + 50 * MS
        node._start_cycle(capture_ns, objects([[10.0, 0.0]], [[0.0, 0.0]]))
        item = rsu_item(k, capture_ns)
        clock.t_ns = item.receive_ns
        if k == 20:
            break
        node._handle_input(item)
        clock.t_ns += 40 * MS
        node._publish_if_ready()
    assert pipeline.pending and pipeline._cycle.mode == "intra", "the last cycle must wait for its list"
    return node, clock, item


def traced(node: ObuNode, item: Item) -> list[Call]:
    calls: list[Call] = []
    skip, done = [], []

    def profile(frame, event, _arg):
        if done or event not in ("call", "return"):
            return
        if skip:  # inside the own objects' tracker update: not the list's path
            if event == "return" and frame is skip[0]:
                skip.clear()
            return
        path = os.path.realpath(frame.f_code.co_filename)
        if event != "call" or not path.startswith(SRC):
            return
        name = frame.f_code.co_qualname
        if name == "KalmanFusion._update" and not isinstance(frame.f_locals.get("sources"), int):
            skip.append(frame)
            return
        caller = os.path.realpath(frame.f_back.f_code.co_filename) if frame.f_back else ""
        calls.append((path[len(SRC):], name, caller[len(SRC):] if caller.startswith(SRC) else None))
        if name.endswith("Tracker.update") and frame.f_locals.get("source_mask", 0) not in (0, 1):
            done.append(True)

    sys.setprofile(profile)
    try:
        node._handle_input(item)
    finally:
        sys.setprofile(None)
    assert done, "the RSU list never reached the tracker"
    return calls


def returns(calls: list[Call]) -> int:
    """Calls from another file into a file the path had already been in (the walk going back)."""
    seen, n = set(), 0
    for path, _, caller in calls:
        n += caller is not None and caller != path and path in seen
        seen.add(path)
    return n


def summary(title: str, calls: list[Call]) -> None:
    files = list(dict.fromkeys(path for path, _, _ in calls))
    stops = list(dict.fromkeys((path, name) for path, name, _ in calls))
    crossings = sum(1 for path, _, caller in calls if caller and caller != path)
    print(f"{title}: {len(files)} files, {len(stops)} stops, {len(calls)} calls, {crossings} into another file, "
          f"{returns(calls)} of them back into a file already visited")
    for path in files:
        print(f"  {path}: " + ", ".join(name for p, name in stops if p == path))
    repeated = {f"{p}:{n}": k for (p, n), k in Counter((p, n) for p, n, _ in calls).items() if k > 1}
    print(f"  entered more than once: {repeated}")


def main() -> None:
    node, _clock, item = prepared_node()
    calls = traced(node, item)
    cut = next(i for i, (_, name, _) in enumerate(calls) if name.endswith("_publish_if_ready"))
    summary("input stage (until the node's _publish_if_ready)", calls[:cut])
    summary("whole path (until the tracker update of the RSU objects)", calls)


if __name__ == "__main__":
    main()
