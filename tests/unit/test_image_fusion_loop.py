"""The image-level OBU's loop (``ImageFusionNode._loop``) on a simulated clock: when it is behind
(every event overdue, as on a loaded machine where a capture takes longer than a period) it still
handles the inputs queued in its intake, a bounded number before each event."""

from __future__ import annotations

import itertools
import threading

from obu_service.config import ObuConfig
from obu_service.image_fusion_node import INPUTS_PER_LATE_EVENT
from schemas import keys
from v2i.services import obu_node
from v2i.sim.clock import SimClock

SCENARIO, RSU_ID = "roif-intersection", "rsu-roif"
CAPTURE_COST_NS = 150_000_000  # 1.5 camera periods: every later event is overdue


def _runs_of_inputs(log: list[str]) -> list[int]:
    return [len(list(group)) for kind, group in itertools.groupby(log) if kind == "input"]


def test_a_loop_behind_its_events_still_handles_queued_inputs_a_bounded_number_at_a_time():
    clock = SimClock(1_700_000_000_000_000_000)
    node = obu_node(ObuConfig(scenario=SCENARIO, fusion="roif", roif_threads=1, start_at_ns=clock.t_ns,
                              duration_s=2.0, sync_rate_hz=20.0), clock=clock)
    log, stop = [], threading.Event()

    def capture(_due_ns: int) -> None:
        log.append("capture")
        clock.t_ns += CAPTURE_COST_NS
        if log.count("capture") == 6:
            stop.set()

    node._do_capture, node._do_sync = capture, lambda _due_ns: log.append("sync")
    node._handle_input, node._publish_ready = lambda item: log.append("input"), lambda: None
    key = keys.rsu_image_features(RSU_ID)
    for _ in range(20):
        node._intake.put("features", key, 3, clock.t_ns, lambda: b"abc")
    node._schedule()
    node._loop(stop)
    assert log.count("input") == 20, log
    runs = _runs_of_inputs(log)
    assert max(runs) == INPUTS_PER_LATE_EVENT and len(runs) >= 3, log  # 8, 8, 4 between overdue events
    assert log.count("capture") == 6 and len(node._intake) == 0
