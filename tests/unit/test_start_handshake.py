"""The start handshake: a service waits for its start line (``v2i.runtime.process``), an orchestrator
waits until every child is ready and then sends it (``v2i.orchestration.children``), and a child's log
lines are relayed whole and labelled."""

from __future__ import annotations

import io
import json
import os
import re
import sys
import threading
import time
from types import SimpleNamespace

import pytest

from v2i.orchestration.children import Child, DemoError, start_all, wait_ready
from rsu_service.config import RsuConfig
from v2i.runtime.config import ConfigError, load_config
from v2i.runtime.process import parse_start_line, read_start_line, start_line, start_when_told
from v2i.services import rsu_node

# A stand-in service: two stderr lines, ready after argv[1] s, then the start line -> "started", exit argv[2].
FAKE = r"""
import json, sys, time
print("[fake one] loading", file=sys.stderr, flush=True)
print("a line without a name", file=sys.stderr, flush=True)
time.sleep(float(sys.argv[1]))
if sys.argv[2] == "die":
    print("boom: cannot open the thing", file=sys.stderr, flush=True)
    sys.exit(3)
print(json.dumps({"event": "ready", "service": "fake"}), flush=True)
start_ns = json.loads(sys.stdin.readline())["start_at_ns"]
print(json.dumps({"event": "started", "service": "fake", "start_at_ns": start_ns, "ahead_ms": 12.5}), flush=True)
print(f"started at {start_ns}", file=sys.stderr, flush=True)
"""


def fake(name: str, ready_after_s: float, then: str = "run", label: str | None = None) -> Child:
    return Child(name, [sys.executable, "-c", FAKE, str(ready_after_s), then], label=label)


def test_start_line_round_trip_and_refusals():
    assert parse_start_line(start_line(1_767_225_600_123_456_789)) == 1_767_225_600_123_456_789
    for line, why in [("garbage", "not JSON"), ('{"event": "ready"}', "not a start line"),
                      ('{"event": "start"}', "start_at_ns"), ('{"event": "start", "start_at_ns": true}', "start_at_ns"),
                      ('{"event": "start", "start_at_ns": -5}', "start_at_ns"),
                      ('{"event": "start", "start_at_ns": 1.5e18}', "start_at_ns"), ("[1, 2]", "not a start line"),
                      ('{"event": "start", "start_at_ns": 9223372036854775808}', "64-bit")]:  # 2**63: past int64
        with pytest.raises(ValueError, match=why):
            parse_start_line(line)


def test_read_start_line_skips_other_lines_and_ends_on_eof(capsys):
    stop = threading.Event()
    assert read_start_line("obu ego", stop, io.StringIO("garbage\n\n" + start_line(42))) == 42
    assert "[obu ego] ignored a line on stdin (not JSON: 'garbage')" in capsys.readouterr().err
    assert read_start_line("obu ego", stop, io.StringIO("")) is None  # EOF: the service exits cleanly
    assert read_start_line("obu ego", stop, io.StringIO('{"event": "go"}\n')) is None


def test_read_start_line_returns_when_stopped_first():
    read_fd, write_fd = os.pipe()
    stream = os.fdopen(read_fd)
    stop = threading.Event()
    threading.Timer(0.2, stop.set).start()
    t0 = time.monotonic()
    try:
        assert read_start_line("rsu rsu1", stop, stream) is None  # nothing written: SIGTERM before the start
        assert time.monotonic() - t0 < 2.0
    finally:
        os.close(write_fd)


def test_start_when_told_begins_then_announces(capsys):
    begun = []
    told = start_when_told("rsu rsu1", threading.Event(), begun.append, lambda: 1_000_000_000,
                           wait=lambda name, stop: 3_500_000_000)
    assert told and begun == [3_500_000_000]
    started = json.loads(capsys.readouterr().out)
    assert started == {"event": "started", "service": "rsu rsu1", "start_at_ns": 3_500_000_000, "ahead_ms": 2500.0}
    assert not start_when_told("rsu rsu1", threading.Event(), begun.append, lambda: 0, wait=lambda name, stop: None)
    assert begun == [3_500_000_000]  # not begun without a start


def test_one_time_zero_only():
    with pytest.raises(ConfigError, match="exclude each other"):
        load_config(RsuConfig, None, {"await_start": True, "start_at_ns": 1})
    assert load_config(RsuConfig, None, {"await_start": True}).await_start


def test_an_rsu_awaiting_its_start_has_no_clock_yet_and_answers_no_time_query():
    node = rsu_node(RsuConfig(await_start=True, duration_s=2.0, clock_offset_ms=250.0))
    assert node.start_ns is None and node.clock is None
    replies = []
    query = SimpleNamespace(payload=None, key_expr="v2x/rsu/rsu1/time", reply=lambda *a: replies.append(a))
    node._on_time_query(query)
    assert replies == [] and not node.rejected  # unanswered, not counted as a refusal
    node._begin(5_000_000_000)
    assert node.start_ns == node.source.start_ns == 5_000_000_000
    assert node.source.capture_times_ns(1.0)[0] == 5_000_000_000
    assert node.clock.offset_at(5_000_000_000) == round(node.config.clock_offset_ms * 1e6)


def test_wait_ready_then_start_all(capsys):
    children = [fake("one", 0.0, label="fake one"), fake("two", 0.3)]
    try:
        waited_s = wait_ready(children, timeout_s=30.0)
        assert all(c.ready for c in children) and waited_s >= 0.3
        before_ns = time.time_ns()
        start_ns = start_all(children, lead_s=0.5)
        assert before_ns + 0.5e9 <= start_ns <= time.time_ns() + 0.5e9  # now + the lead
        for child in children:
            assert child.proc.wait(10) == 0
            child._stdout.join(5)
            child._stderr.join(5)
            assert child.ahead_ms == 12.5
    finally:
        for child in children:
            child.stop()
    err = capsys.readouterr().err
    assert "[fake one] loading\n" in err and "[fake one] [fake one]" not in err  # named itself: kept as it is
    assert "[two] [fake one] loading\n" in err  # another label: prefixed
    assert "[two] a line without a name\n" in err and f"[two] started at {start_ns}\n" in err


def test_wait_ready_names_a_child_that_died_with_its_last_lines():
    children = [fake("one", 0.0), fake("rsu", 0.1, then="die")]
    try:
        with pytest.raises(DemoError) as error:
            wait_ready(children, timeout_s=30.0)
    finally:
        for child in children:
            child.stop()
    text = str(error.value)
    assert text.startswith("rsu exited with code 3 before it was ready")
    assert "\n    [rsu] boom: cannot open the thing" in text


def test_wait_ready_names_who_is_late_after_the_bound_and_shows_progress(capsys):
    children = [fake("quick", 0.0), fake("slow", 60.0)]
    try:
        with pytest.raises(DemoError) as error:
            wait_ready(children, timeout_s=1.0, progress="v2i demo")
    finally:
        for child in children:
            child.stop()
    text = str(error.value)
    assert text.startswith("not ready after 1 s (--ready-timeout): slow") and "quick" not in text
    assert "[slow] a line without a name" in text
    # not a tty: plain lines; "quick" may be ready before the first one is drawn on a busy machine
    assert re.search(r"^v2i demo: waiting for (quick, )?slow \(\d+\.\d s\)$", capsys.readouterr().err, re.M)


@pytest.mark.parametrize("command", [["demo"], ["chaos", "run", "examples/chaos/outage-10s.yaml"],
                                     ["fuzz", "--target", "rsu"]])
def test_ready_timeout_flag(command, capsys):
    from v2i.cli import _ready_timeout, build_parser, main

    assert main([*command, "--ready-timeout", "0"]) == 2
    assert "--ready-timeout must be a finite number > 0, got 0" in capsys.readouterr().err
    args = build_parser().parse_args([*command, "--ready-timeout", "30"])
    assert _ready_timeout(args) == {"ready_timeout_s": 30.0}
    args = build_parser().parse_args([*command, "--startup", "4"])  # an old script's flag: accepted, not used
    assert _ready_timeout(args) == {}
    assert "--startup is no longer used" in capsys.readouterr().err
