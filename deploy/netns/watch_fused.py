"""Watch a vehicle's fused output and exit once RSU objects have come through the link.

Connects to the OBU's endpoint (scouting off, like every v2i session), subscribes to
``v2x/obu/{vehicle_id}/objects`` and prints one JSON line per fused list that holds at
least one RSU-sourced object, then ``{"event": "done", ...}``. Exit status 0 once
``--min-rsu-lists`` such lists arrived, 1 when ``--timeout-s`` passed first.

Zenoh peers do not forward for each other, so a session connected to the OBU sees what the
OBU publishes, not what the link emulator publishes to the OBU (e.g. its statistics). Behind
a router (``V2I_ZENOH_MODE=client``, ``--connect`` the vehicle side's router) it sees the
whole vehicle side.

    python deploy/netns/watch_fused.py --connect tcp/10.10.2.2:7448 [--vehicle-id ego]
    V2I_ZENOH_MODE=client python deploy/netns/watch_fused.py --connect tcp/10.10.2.1:7447
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time

from schemas.codec import CodecError, decode
from schemas.keys import obu_objects
from schemas.messages import SOURCE_RSU, FusedObjectList
from v2i.runtime.transport import open_session


def _summary(fused: FusedObjectList) -> dict:
    """What one fused list says about the RSU's contribution."""
    rsu_objects = sum(1 for o in fused.objects if o.sources & SOURCE_RSU)
    return {"event": "fused", "seq": fused.seq, "mode": fused.mode, "objects": len(fused.objects),
            "rsu_objects": rsu_objects}


def watch(connect: list[str], vehicle_id: str, min_rsu_lists: int, timeout_s: float) -> bool:
    """True once ``min_rsu_lists`` fused lists with RSU objects were seen before the deadline."""
    inbox: queue.Queue[bytes] = queue.Queue()
    session = open_session(connect=connect)
    subscriber = session.declare_subscriber(obu_objects(vehicle_id), lambda s: inbox.put(s.payload.to_bytes()))
    seen, lists_with_rsu = 0, 0
    deadline = time.monotonic() + timeout_s
    try:
        while lists_with_rsu < min_rsu_lists and (remaining_s := deadline - time.monotonic()) > 0:
            try:
                summary = _decoded_summary(inbox.get(timeout=min(remaining_s, 0.5)))
            except queue.Empty:
                continue
            seen += summary is not None
            if summary is not None and summary["rsu_objects"]:
                lists_with_rsu += 1
                print(json.dumps(summary), flush=True)
    finally:
        subscriber.undeclare()
        session.close()
    print(json.dumps({"event": "done", "fused_lists": seen, "lists_with_rsu_objects": lists_with_rsu}), flush=True)
    return lists_with_rsu >= min_rsu_lists


def _decoded_summary(payload: bytes) -> dict | None:
    """The summary of one fused list, or None (reported) when it does not decode."""
    try:
        return _summary(decode(payload, FusedObjectList))
    except CodecError as exc:
        print(json.dumps({"event": "rejected", "reason": str(exc)}), flush=True)
        return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", action="append", required=True, metavar="EP", help="the OBU's Zenoh endpoint")
    parser.add_argument("--vehicle-id", default="ego", help="vehicle id (default %(default)s)")
    parser.add_argument("--min-rsu-lists", type=int, default=3, help="fused lists with RSU objects to wait for")
    parser.add_argument("--timeout-s", type=float, default=30.0, help="give up after this many seconds")
    args = parser.parse_args()
    return 0 if watch(args.connect, args.vehicle_id, args.min_rsu_lists, args.timeout_s) else 1


if __name__ == "__main__":
    sys.exit(main())
