"""v2i.telemetry.live_line: the demo's compact line (format, tty redraw with log lines above it, plain
lines elsewhere) and the monitor's dashboard drawing every key of a snapshot."""

from __future__ import annotations

import io
import json
import re
import sys
import threading
import time

from rich.console import Console

from schemas.messages import ObuMetrics, RsuLinkStatus
from v2i.telemetry.live_line import CLEAR, LiveLine, format_line
from v2i.telemetry.snapshot import TelemetryBoard
from v2i.monitor_view import dashboard

T0 = 1_767_225_600 * 10**9


def metrics(cycles: int, misses: int, mode: str = "intra", vid: str = "ego") -> ObuMetrics:
    return ObuMetrics(vehicle_id=vid, t_ns=T0, cycles=cycles, output_deadline_misses=misses, covered_cycles=cycles,
                      rsu_deadline_misses=1, mode=mode, mode_counts={mode: cycles},
                      rsus=(RsuLinkStatus(rsu_id="rsu1", messages_accepted=7, clock_offset_ns=2_000_000,
                                          clock_uncertainty_ns=100_000),))


def test_format_line_states():
    board = TelemetryBoard()
    assert "begins in 2.0 s" in format_line("v2i demo", board.totals(), -2.0, 30.0)
    assert "waiting for the OBU's metrics" in format_line("v2i demo", board.totals(), 1.0, 30.0)
    board.on_obu_metrics(metrics(20, 1), 10**9)
    line = format_line("v2i chaos run", board.totals(), 12.34, 30.0, (1, 3))
    assert line.startswith("v2i chaos run  12.3/30 s")
    assert "misses: output 1/20 5.0% (10 s -), RSU 5.0% (10 s -)" in line  # one message: no window yet
    assert "mode intra" in line and "RSU lists 7" in line and "chaos 1/3" in line
    board.on_obu_metrics(metrics(20, 0, "inter", vid="car2"), 10**9)
    assert "mode inter 1, intra 1" in format_line("v2i demo", board.totals(), 1.0, 30.0)


class FakeTty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_tty_line_is_redrawn_and_log_lines_go_above_it(monkeypatch):
    stream = FakeTty()
    monkeypatch.setattr(sys, "stderr", stream)
    live = LiveLine("v2i demo", time.time_ns(), 30.0)
    live.start()
    live.feed(metrics(10, 0))
    live.draw()
    print("[demo] chaos: outage sent", file=sys.stderr)  # the demo's own log while the line shows
    live.stop()
    assert sys.stderr is stream  # restored
    text = stream.getvalue()
    assert CLEAR + "[demo] chaos: outage sent\nv2i demo" in text  # the line erased, the log, the line again
    assert "output 0/10" in text and text.endswith(CLEAR)
    # the log line never shares a row with the status line
    for row in text.split("\n"):
        assert not ("chaos: outage" in row and "misses:" in row.split(CLEAR)[-1])


def test_plain_lines_when_not_a_tty():
    stream = io.StringIO()
    live = LiveLine("v2i demo", time.time_ns(), 30.0, stream=stream)
    live.feed(metrics(5, 0))
    live.draw()
    live.draw()  # within PLAIN_EVERY_S: nothing more
    assert stream.getvalue().count("\n") == 1 and "\r" not in stream.getvalue()
    assert "output 0/5" in stream.getvalue()


def test_dashboard_draws_a_snapshot():
    board = TelemetryBoard()
    board.on_obu_metrics(metrics(10, 1).model_copy(update={"latency_ms": {}}), 10**9)
    stats = {"latency_ms": {"relay_hold": {"count": 4, "p50": 0.25, "p95": 0.5, "p99": 0.75}}, "link_id": "link1", "time_ns": T0, "profile": "lte-v2x",
             "downlink": {"received": 10, "delivered": 9, "dropped": 1, "delay_ms": {"mean": 30.0, "max": 60.0}},
             "control": {"recent": [{"seq": 1, "result": "outage on both for 3 s"}]}, "refused": {"rate": 2}}
    board.on_sample("v2x/link/link1/stats", json.dumps(stats).encode(), 10**9)
    snap = board.snapshot(2 * 10**9)
    out = io.StringIO()
    Console(file=out, width=200).print(dashboard(snap, [{"endpoint": "tcp/x:1", "connected": True, "messages": 2}]))
    text = out.getvalue()
    for expected in ("vehicle ego", "output misses 10.0%", "+2.000 ± 0.100 ms", "link1", "lte-v2x",
                     "outage on both (3 s left)", "rejected by reason", "rate", "relay_hold", "0.75"):
        assert expected in text, expected


def test_tty_lines_of_several_threads_are_written_whole(monkeypatch):
    """Each thread writes its lines in pieces (as print does: the text, then the newline) at the same
    time as the others: every row on the terminal is one thread's line, whole."""
    stream = FakeTty()
    monkeypatch.setattr(sys, "stderr", stream)
    live = LiveLine("v2i demo", time.time_ns(), 30.0)
    live.start()
    barrier = threading.Barrier(4)

    def writer(tag: str) -> None:
        for k in range(50):
            sys.stderr.write(f"[{tag}] line {k}")
            barrier.wait()  # every thread has half a line written
            sys.stderr.write(" and its end")
            sys.stderr.write("\n")

    threads = [threading.Thread(target=writer, args=(tag,)) for tag in "abcd"]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    sys.stderr.write("[demo] unfinished")  # no newline yet when the line stops: still written, on its own
    live.stop()
    rows = [row.split(CLEAR)[-1] for row in stream.getvalue().split("\n")]
    lines = [row for row in rows if row.startswith("[")]
    assert len(lines) == 4 * 50 + 1
    assert all(re.fullmatch(r"\[[abcd]\] line \d+ and its end", row) for row in lines[:-1]), lines[:5]
    assert lines[-1] == "[demo] unfinished"
