"""The OBU node's V2V I/O (``--v2v``): the Zenoh shell around ``peers.PeerIntake``.

Published by this vehicle (``me``): its shared list on ``v2x/v2v/{me}/objects`` after every
output (``peers.shared_list``), a time request on ``v2x/v2v/{me}/time`` with every time-sync
tick, and its answer to a peer's request on ``v2x/v2v/{me}/time_reply/{peer}`` (t2 = the
request's receive stamp, t3 = read just before the put). Heard: ``v2x/v2v/*/objects``,
``v2x/v2v/*/time`` and ``v2x/v2v/*/time_reply/{me}``; the callbacks put them into the node's
bounded intake like every other input (kinds ``v2v_objects``, ``v2v_time``, ``v2v_reply``) and
the node's loop hands them to ``handle``. What this vehicle sends to peers is published for
remote subscribers only (``Locality.REMOTE``), so it never hears its own messages back from its
own session; a sample on its own ``v2x/v2v/{me}/...`` keys came from elsewhere (a replay, a
forger) and is refused as ``v2v_self`` (``PeerIntake``).
Between vehicles the V2V emulator (``link_emulator.v2v_relay``) is the only path.
"""

from __future__ import annotations

import json
from collections.abc import Callable

import zenoh

from schemas import keys
from schemas.codec import CodecError, decode, encode
from v2i.runtime.intake import Item
from schemas.messages import FusedObjectList, TimeReply, TimeRequest
from v2i.core.clock import Clock

from obu_service.peers import PeerIntake, shared_list

KINDS = ("v2v_objects", "v2v_time", "v2v_reply")


class V2vShell:
    """V2V publishers and subscribers of one OBU node; ``put(kind, sample)`` is the node's intake."""

    def __init__(self, me: str, peers: PeerIntake, clock: Clock, max_bytes: int):
        self.me, self.peers, self.clock, self.max_bytes = me, peers, clock, max_bytes
        self._session = None
        self._pub: dict = {}

    def declare(self, session, put: Callable[[str, object], None]) -> list:
        """Publishers and subscribers on ``session``; the entities to undeclare."""
        self._session = session
        remote = zenoh.Locality.REMOTE
        self._pub = {"objects": session.declare_publisher(keys.v2v_objects(self.me), allowed_destination=remote),
                     "time": session.declare_publisher(keys.v2v_time(self.me), allowed_destination=remote),
                     "peers": session.declare_publisher(keys.obu_peers(self.me))}

        def heard(kind: str):
            return lambda sample: put(kind, sample)

        subs = [session.declare_subscriber(keys.V2V_OBJECTS_ALL, heard("v2v_objects")),
                session.declare_subscriber(keys.V2V_TIME_ALL, heard("v2v_time")),
                session.declare_subscriber(f"v2x/v2v/*/time_reply/{self.me}", heard("v2v_reply"))]
        return [*self._pub.values(), *subs]

    def handle(self, item: Item) -> None:
        """One V2V input from the intake; an undecodable one is counted as ``v2v_<codec reason>``."""
        try:
            self._handle(item)
        except CodecError as exc:
            self.peers.rejected[exc.reason] += 1

    def _handle(self, item: Item) -> None:
        try:
            sender = keys.v2v_sender(item.source)
        except ValueError:  # a key whose id chunk is no vehicle id (Zenoh allows more characters)
            self.peers.rejected["bad_sender_key"] += 1
            return
        if item.kind == "v2v_objects":
            self.peers.on_list(decode(item.payload, FusedObjectList, self.max_bytes), sender, item.receive_ns)
        elif item.kind == "v2v_time":
            request = decode(item.payload, TimeRequest, self.max_bytes)
            reply = self.peers.answer(request, sender, item.receive_ns, self.clock.now_ns())
            if reply is not None:
                self._session.put(keys.v2v_time_reply(self.me, sender), encode(reply),
                                  allowed_destination=zenoh.Locality.REMOTE)
        else:
            self.peers.on_time_reply(decode(item.payload, TimeReply, self.max_bytes), sender, item.receive_ns)

    def share(self, out: FusedObjectList) -> None:
        """After an output: what this vehicle's own sensors perceive, to its peers; and, for
        monitors, the peers as this OBU sees them (JSON on ``v2x/obu/{me}/peers``)."""
        self._pub["objects"].put(encode(shared_list(out)))
        self._pub["peers"].put(json.dumps(self.peers.summary(out.publish_time_ns)).encode(),
                               encoding=zenoh.Encoding.APPLICATION_JSON)

    def sync(self, now_ns: int) -> None:
        """A time-sync tick: one request to every peer."""
        self._pub["time"].put(encode(self.peers.make_time_request(now_ns)))
