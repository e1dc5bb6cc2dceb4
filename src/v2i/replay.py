"""``v2i replay``: a ``v2i record`` file republished on its keys, for re-running an OBU on recorded RSU traffic.

Design: what a replayed OBU must see to behave as the recorded one did.

- **One time translation for everything.** The recording starts at ``L0`` (the recorded run's
  scenario start, MCAP metadata ``run.start_ns``, else the first replayed sample's log time).
  The replay maps it to ``T0`` (the new OBU's ``--start-at-ns``; standalone: now + ``--lead``)
  and moves every clock by ``shift = T0 - L0``, rounded to a whole millisecond
  (``v2i.telemetry.time_shift``): a sample logged at ``l`` is published at ``T0 + (l - L0) / speed``,
  and each stamp it carries (``capture_time_ns``, ``publish_time_ns``, ... in the RSU's clock)
  moves by ``shift`` (decoded and encoded with ``schemas.codec``; a CPM / SDSM through
  ``schemas.list_wire``, exact because the shift is whole ms). The fresh OBU simulates its own
  LiDAR from the scenario at ``T0``, so its own detections, the RSU lists' capture times and
  their ages on arrival are those of the recording, up to the replay's real-time jitter
  (measured and reported as ``lateness_ms``). The alternative, an OBU at the recorded start with
  a clock offset, keeps the bytes but needs a clock option in the OBU and a shifted scorer; the
  shift needs neither and keeps the RSU's offset and drift against the OBU exactly.
- **The RSU clock.** The recorder's own time exchanges with each RSU (``v2i record
  --time-from``) give theta(h) = rsu - host over the run (``RsuClockTrack``). The replay
  declares ``v2x/rsu/<id>/time`` for each recorded RSU and answers a request at replay time t
  with t2 = t3 = t + theta(L0 + (t - T0) * speed), so the OBU's clock filter finds the recorded
  offset and drift (a running median over 9 exchanges: a step keeps its edge). Replies come back over
  loopback, not through the recorded link: the replayed OBU's clock estimate is at least as good
  as the live one (its error bound, half the delay asymmetry, was set by the link live).
- **What is replayed.** Samples of one side (``--side``; default ``vehicle`` when recorded, i.e.
  as they arrived at the OBU, after the link) whose key matches ``--keys`` (default
  ``v2x/rsu/**``), the recorder's own time replies excepted. A sample that does not decode is
  published unchanged (counted ``unshifted``): a hostile input stays hostile.
- **Signed recordings** (RSUs run with ``--pki``: ``v2i.security.envelope``). A signature covers the
  stamps, so a shifted message cannot keep it, and the replay holds no RSU key to sign anew: a
  signed sample is republished *unsigned*, its payload taken out of the envelope and shifted
  (counted ``envelopes_removed``); the recorder's exchanges are read from inside theirs, and
  the replay's own time replies are unsigned too. The OBU fed must therefore run without
  ``--pki`` (or ``--security off``); ``--score`` starts it so. (An envelope that does not decode
  is published as recorded, like any sample that does not decode.)
- **What it says.** A readable summary on stderr (published, lateness, RSU clocks; ``--json`` for
  the numbers). A recording that was not closed (``v2i.telemetry.mcap_reader``: its recorder killed,
  its disk full) is replayed as far as it was written, with a line saying so.
- **Scoring a ``v2i record`` file** (``--score``): it carries no run metadata, so the scenario and
  its start come from ``--scenario`` and ``--start-at-ns`` (``v2i.offline.recorded_run``).
- ``--speed`` other than 1 scales the spacing; a sample's stamps then move by (its publish time -
  its log time), so each keeps its recorded age at publication. An OBU runs in real time only at 1.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

from v2i.core.files import check_regular
from v2i.telemetry.replayer import LATE_NS, Replayer

DEFAULT_LEAD_S = 2.0



def configure_parser(p: argparse.ArgumentParser) -> None:
    p.description = ("Republish a v2i record MCAP file on its original keys with the recorded spacing (scaled by "
                     "--speed), every stamp moved to now, and answer the recorded RSUs' time queries from their "
                     "recorded clocks; or, with --score, start a fresh OBU with the recorded run's spec and score "
                     "it on the replayed RSU traffic (the v2i demo report). Signed messages (RSUs with --pki) are "
                     "republished UNSIGNED: a signature covers the stamps, so a time-shifted message cannot keep "
                     "it; feed an OBU without --pki (or with --security off); --score does. Design: v2i/replay.py.")
    p.add_argument("recording", metavar="FILE", help="MCAP file written by v2i record or v2i demo --record")
    p.add_argument("--connect", action="append", metavar="EP", help="endpoint of the OBU to feed (repeatable; "
                   "not with --score)")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed (default %(default)s; an OBU needs 1)")
    p.add_argument("--keys", default="v2x/rsu/**", help="key expression of the samples to replay (default %(default)s)")
    p.add_argument("--side", help="recorded side to replay (default: vehicle, i.e. after the link, when recorded)")
    p.add_argument("--lead", type=float, default=DEFAULT_LEAD_S,
                   help="seconds between start-up and the recording's start (default %(default)s)")
    p.add_argument("--score", action="store_true", help="start a fresh OBU (the recording's scenario, seed and "
                   "options: its run metadata, written by v2i demo --record, or the flags below) and score it like "
                   "v2i demo")
    p.add_argument("--ready-timeout", type=float, metavar="S", help="with --score: seconds the OBU may take to say "
                   "it is ready (default 120); the replay starts when it is")
    p.add_argument("--startup", type=float, help=argparse.SUPPRESS)  # before --ready-timeout: ignored, noted
    p.add_argument("--json", metavar="PATH", help="write the JSON to PATH ('-' for stdout): with --score the report, "
                   "else the replay's counts (default: readable lines only)")
    run = p.add_argument_group("the recorded run, for --score", "a v2i demo --record file carries it (values given "
                               "here win); a v2i record file does not: give at least --scenario and --start-at-ns, "
                               "as the recorded services were started")
    run.add_argument("--scenario", help="the scenario the recorded services ran")
    run.add_argument("--start-at-ns", type=int, metavar="NS", help="their scenario time zero (their --start-at-ns)")
    run.add_argument("--seed", type=int, help="their --seed (the fresh OBU's own LiDAR; default 0)")
    run.add_argument("--duration", type=float, metavar="S", help="seconds to score (default: the recorded run's; "
                     "for a v2i record file the recorded RSU traffic after the start)")
    run.add_argument("--rsu-clock-offset-ms", type=float, metavar="MS", help="the RSU clock's true offset, for the "
                     "clock-error score (default 0)")
    run.add_argument("--rsu-clock-drift-ppm", type=float, metavar="PPM", help="its true drift (default 0)")


_RUN_FLAGS = {"scenario": "scenario", "start_at_ns": "start_ns", "seed": "seed", "duration": "duration_s",
              "rsu_clock_offset_ms": "rsu_clock_offset_ms", "rsu_clock_drift_ppm": "rsu_clock_drift_ppm"}


def given_run(args: argparse.Namespace) -> dict:
    """The run's values given on the command line (``v2i.offline.recorded_run.run_of``; None: not given)."""
    if args.duration is not None and not 0 < args.duration < float("inf"):
        raise ValueError(f"--duration must be > 0, got {args.duration:g}")
    if args.start_at_ns is not None and args.start_at_ns <= 0:
        raise ValueError(f"--start-at-ns must be > 0 (Unix ns), got {args.start_at_ns}")
    return {field: getattr(args, dest) for dest, field in _RUN_FLAGS.items()}


def replay_summary(stats: dict) -> str:
    """``Replayer.stats`` (a --score report's ``replay``) as two or three readable lines."""
    late = stats["lateness_ms"]
    timing = (f"; late by p50 {late['p50']:.1f} ms, p99 {late['p99']:.1f} ms, max {late['max']:.1f} ms, "
              f"{stats.get('late', 0)} later than {LATE_NS / 1e6:g} ms") if late.get("max") is not None else ""
    clocks = ", ".join(f"{rsu} from {c['exchanges_used']} recorded exchanges"
                       + (f" ({c['exchanges_dropped']} left out)" if c["exchanges_dropped"] else "")
                       for rsu, c in stats["rsu_clocks"].items()) or "none recorded"
    lines = [f"v2i replay: published {stats.get('published', 0)} samples of side {stats['side']} ({stats['keys']}) at "
             f"speed {stats['speed']:g}, every stamp moved by {stats['shift_ns'] / 1e9:.3f} s{timing}",
             f"  RSU clocks: {clocks}; {stats.get('time_replies', 0)} time queries answered"
             + (f", {stats['time_query_refused']} refused" if stats.get("time_query_refused") else "")]
    notes = [f"{stats['envelopes_removed']} signed samples republished unsigned" if stats.get("envelopes_removed") else "",
             f"{stats['unshifted']} that do not decode republished as recorded" if stats.get("unshifted") else "",
             f"the recorded run signed ({stats['recorded_security']}), the fresh OBU does not"
             if stats.get("recorded_security") else ""]
    if any(notes):
        lines.append("  " + "; ".join(n for n in notes if n))
    return "\n".join(lines)


def say_if_not_closed(recording) -> None:
    """One stderr line when the recording was not closed (``Recording.closed``)."""
    if not recording.closed:
        print(f"v2i replay: {recording.path} was not closed (its recorder was killed, or its disk filled): "
              f"{recording.problem}; replaying what it holds", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    from v2i.runtime.process import stop_on_signals
    from v2i.telemetry.mcap_reader import Recording

    check_regular(args.recording, None, "recording")  # streamed record by record: any size
    if args.json not in (None, "-"):
        from v2i.console import check_writable

        check_writable(Path(args.json), "--json")
    if args.score:
        return run_scored(args)
    if not args.connect:
        raise ValueError("v2i replay needs --connect EP (the OBU's endpoint), or --score")
    given = [f"--{dest.replace('_', '-')}" for dest in _RUN_FLAGS if getattr(args, dest) is not None]
    if given:
        raise ValueError(f"{', '.join(given)}: only with --score (the run a fresh OBU is started for)")
    recording = Recording(args.recording)
    say_if_not_closed(recording)
    replayer = Replayer(recording, args.side, args.keys, args.speed)
    code = play_standalone(replayer, args.connect, args.lead, stop_on_signals())
    _write_json(replayer.stats(), args.json)
    return code


def _write_json(stats: dict, path: str | None) -> None:
    if path == "-":
        print(json.dumps(stats, indent=2))
    elif path:
        Path(path).write_text(json.dumps(stats, indent=2) + "\n")


def play_standalone(replayer: Replayer, connect: list[str], lead_s: float, stop: threading.Event) -> int:
    """Replay into the OBU at ``connect`` starting ``lead_s`` from now; a summary on stderr."""
    from v2i.runtime.transport import open_session

    session = open_session(connect=connect)
    try:
        queryables = replayer.declare_clocks(session)
        t0_ns = replayer.align(time.time_ns() + round(lead_s * 1e9))
        print(f"v2i replay: {replayer.recording.path} side {replayer.side} from {t0_ns} ns "
              f"(stamps moved by {(t0_ns - replayer.l0_ns) / 1e9:.3f} s)", file=sys.stderr)
        replayer.play(session, stop)
        for q in queryables:
            q.undeclare()
    finally:
        session.close()
    print(replay_summary(replayer.stats()), file=sys.stderr)
    return 0


def run_scored(args: argparse.Namespace) -> int:
    """``--score``: a fresh OBU on the replayed traffic, reported like ``v2i demo``."""
    from v2i.console import emit, live
    from v2i.orchestration.replay_demo import ReplayDemo

    if args.connect:
        raise ValueError("--score starts its own OBU: leave out --connect")
    if args.speed != 1.0:
        raise ValueError("--score runs the OBU in real time: --speed must be 1")
    if args.startup is not None:
        print("v2i replay: --startup is no longer used: the replay starts when the OBU is ready (bound: "
              "--ready-timeout)", file=sys.stderr)
    if args.ready_timeout is not None and not args.ready_timeout > 0:
        raise ValueError(f"--ready-timeout must be > 0, got {args.ready_timeout:g}")
    timeout = {} if args.ready_timeout is None else {"ready_timeout_s": args.ready_timeout}
    demo = ReplayDemo(args.recording, keys_pattern=args.keys, progress="v2i replay", given=given_run(args), **timeout)
    say_if_not_closed(demo.recording)
    report = live(demo.run, "v2i replay")
    if isinstance(report, int):
        return report
    emit(report, args.json)
    print(replay_summary(report["replay"]), file=sys.stderr)
    return 0
