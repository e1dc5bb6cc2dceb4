"""``v2i record``: every ``v2x/**`` sample heard at one or more endpoints, into an MCAP file (the command:
its options and its run; the recorder and its design: ``v2i.telemetry.recorder``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from v2i.telemetry.recorder import Recorder


def parse_endpoint(text: str, index: int) -> tuple[str, str]:
    """``[LABEL=]ENDPOINT`` -> (label, endpoint); label default ``ep<index>``."""
    label, sep, endpoint = text.partition("=")
    if not sep:
        return f"ep{index}", text
    from schemas.keys import check_id

    return check_id(label), endpoint


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.description = ("Record every v2x/** sample heard at the given endpoints into an MCAP file: one channel per "
                     "key expression and side, the wire bytes with receive (log) and publish times, schemas, plus "
                     "Foxglove channels (foxglove.SceneUpdate cubes for object lists, JSON for metrics). Also runs "
                     "time exchanges with the RSUs (--time-from) so that v2i replay can rebuild their clocks. Signed "
                     "messages (RSUs with --pki) are kept with their envelopes and signatures, as on the wire; the "
                     "Foxglove channels and v2i replay read the payload inside (unchecked). Ctrl-C / SIGTERM close the "
                     "file with its summary; a recorder killed by SIGKILL loses at most its last "
                     "second and a full disk stops it (exit 1): either file still reads back (v2i replay says it "
                     "was not closed).")
    p.add_argument("--connect", action="append", required=True, metavar="[LABEL=]EP",
                   help="endpoint to record, as a Zenoh client (repeatable), e.g. rsu=tcp/127.0.0.1:7447 "
                        "vehicle=tcp/127.0.0.1:7448; the label names the side in topics (default ep0, ep1, ...)")
    p.add_argument("--out", required=True, metavar="FILE", help="the MCAP file to write (replaced)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: Ctrl-C / SIGTERM)")
    p.add_argument("--time-from", metavar="LABEL", help="side whose RSUs get the recorder's time exchanges "
                   "(default: the first endpoint's; 'none': no exchanges)")
    p.add_argument("--sync-rate-hz", type=float, default=10.0, help="time exchanges per second (default %(default)s)")


def run(args: argparse.Namespace) -> int:
    from v2i.runtime.process import stop_on_signals

    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be > 0, got {args.duration:g}")
    if not args.sync_rate_hz > 0:
        raise ValueError(f"--sync-rate-hz must be > 0, got {args.sync_rate_hz:g}")
    out = Path(args.out)
    if out.is_dir() or not out.parent.is_dir():
        raise ValueError(f"--out {out}: not a file in an existing folder")
    endpoints = [parse_endpoint(text, i) for i, text in enumerate(args.connect)]
    time_from = "" if args.time_from is None else (None if args.time_from == "none" else args.time_from)
    stop = stop_on_signals()  # before the file is opened: a signal from here on ends with the file closed
    recorder = Recorder(endpoints, out, time_from, args.sync_rate_hz)
    recorder.run(stop, args.duration)
    return 0 if recorder.failure is None else 1
