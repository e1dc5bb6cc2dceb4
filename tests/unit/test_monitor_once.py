"""``v2i monitor --once`` before any RSU is heard: the snapshot is valid and says so, and --once
waits (briefly) for each vehicle's first RSU list when an RSU is known to be there."""

from __future__ import annotations

import io
import json

from rich.console import Console

from schemas.messages import ObuMetrics, RsuLinkStatus, RsuMetrics
from v2i.telemetry.snapshot import TelemetryBoard
from v2i.monitor import LINK_GRACE_S, RSU_GRACE_S, still_waiting
from v2i.monitor_view import dashboard

S = 1_000_000_000
T0 = 1_767_225_600 * S


def _obu(cycles: int, rsus: list[RsuLinkStatus]) -> ObuMetrics:
    return ObuMetrics(vehicle_id="ego", t_ns=T0 + cycles * S // 10, cycles=cycles, mode="vehicle_only",
                      mode_counts={"vehicle_only": cycles}, rsus=rsus)


def _draw(snapshot: dict) -> str:
    out = io.StringIO()
    Console(file=out, width=200).print(dashboard(snapshot, []))
    return out.getvalue()


def test_a_snapshot_before_any_rsu_is_heard_is_valid_and_says_so():
    board = TelemetryBoard()
    board.on_obu_metrics(_obu(1, []), S)
    snap = json.loads(json.dumps(board.snapshot(S)))  # JSON-ready
    ego = snap["vehicles"]["ego"]
    assert ego["rsu_heard"] is False and ego["rsus"] == {} and ego["rsu_lists_received"] == 0
    assert snap["totals"]["vehicles_hearing_no_rsu"] == 1
    assert "(no RSU heard yet)" in _draw(snap)
    board.on_obu_metrics(_obu(2, [RsuLinkStatus(rsu_id="rsu1", messages_accepted=1)]), 2 * S)
    snap = board.snapshot(2 * S)
    assert snap["vehicles"]["ego"]["rsu_heard"] is True and snap["totals"]["vehicles_hearing_no_rsu"] == 0
    assert snap["vehicles"]["ego"]["rsus"]["rsu1"]["messages_accepted"] == 1
    assert "(no RSU heard yet)" not in _draw(snap)


def test_once_waits_for_a_vehicle_to_hear_an_rsu_only_when_one_is_there():
    board = TelemetryBoard()
    board.on_obu_metrics(_obu(1, []), S)
    board.on_sample("v2x/link/link1/stats", json.dumps({"link_id": "link1"}).encode(), S)
    assert not still_waiting(board, 0.0)  # no RSU metrics: a vehicle-only site, nothing to wait for
    board.on_rsu_metrics(RsuMetrics(rsu_id="rsu1", t_ns=T0, published=3), S)
    assert still_waiting(board, 0.0) and still_waiting(board, RSU_GRACE_S - 0.01)  # its first lists are coming
    assert not still_waiting(board, RSU_GRACE_S)  # bounded: then the snapshot says rsu_heard false
    board.on_obu_metrics(_obu(2, [RsuLinkStatus(rsu_id="rsu1", messages_accepted=1)]), 2 * S)
    assert not still_waiting(board, 0.0)


def test_once_waits_briefly_for_a_links_stats():
    board = TelemetryBoard()
    board.on_obu_metrics(_obu(1, [RsuLinkStatus(rsu_id="rsu1", messages_accepted=1)]), S)
    assert still_waiting(board, LINK_GRACE_S - 0.01) and not still_waiting(board, LINK_GRACE_S)
