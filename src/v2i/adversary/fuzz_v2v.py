"""``v2i fuzz --target obu-v2v``: the OBU's V2V inputs under attack (``obu_service.peers``).

The ``obu`` target's topology (an RSU with a 250 ms clock offset, the OBU connected to it
directly) with the OBU running ``--v2v``; the attacker's session reaches the OBU as a peer
vehicle would. Every hostile kind of ``v2i.adversary.hostile`` is made around each V2V message
(a peer's shared list, ``FusedObjectList``; a peer's time request; a peer's time reply) and
put on the V2V keys of made-up peers (``v2x/v2v/x<k>/objects``, ``.../time``,
``.../time_reply/ego``). Special kinds: a flood of one peer's valid lists; valid lists from
ever new peer ids (the peer table is bounded); a key that names another vehicle than the list
(``v2v_key_mismatch``); the OBU's own id (``v2v_self``: a replay of its own list or a forger);
lists whose objects are not the sender's own perception; time replies answering no request.
Normal output and the refusal counters as for ``obu`` (its metrics' ``rejected``, where the
V2V refusals are ``v2v_<reason>``).
"""

from __future__ import annotations

import itertools
import sys
import time

import numpy as np

from v2i.core.objects import ObjectArray
from v2i.fusion.wire import states_from_objects
from schemas import keys
from schemas.codec import encode
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, FusedObjectList, TimeReply
from v2i.runtime.transport import free_tcp_endpoint
from obu_service.fusion_mode import MODE_REASONS, MODES

from v2i.adversary.fuzz import VEHICLE_ID
from v2i.adversary.fuzz_targets import CLOCK_OFFSET_MS, ObuFuzz
from v2i.adversary.hostile import MS, HostileInputs

V2V_TYPES = ("fused_object_list", "time_request", "time_reply")


class V2vHostile(HostileInputs):
    """``HostileInputs`` that also know a peer's shared list (``fused_object_list``)."""

    def valid(self, type_name: str, t_ns: int, n_objects: int = 8, **header) -> bytes:
        if type_name != "fused_object_list":
            return super().valid(type_name, t_ns, n_objects, **header)
        return encode(self.shared(t_ns, n_objects, **header))

    def shared(self, t_ns: int, n: int = 8, sources: int = SOURCE_VEHICLE, spread_m: float = 60.0,
               **fields) -> FusedObjectList:
        """A peer's shared list: n objects in its base_link, its pose near the site, stamped ~100 ms ago."""
        xy = self.rng.uniform(-spread_m, spread_m, (n, 2))
        objs = ObjectArray(ids=np.arange(n), cls=self.rng.integers(0, 4, n), xy=xy, z=np.zeros(n),
                           lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=self.rng.uniform(-3, 3, n),
                           vxy=self.rng.uniform(-20, 20, (n, 2)), cov_xy=np.tile(np.eye(2), (n, 1, 1)),
                           sources=np.full(n, sources, np.int64))
        cycle_ns = t_ns - 100 * MS
        values = dict(vehicle_id="x0", seq=int(self.rng.integers(1 << 40)), cycle_time_ns=cycle_ns,
                      publish_time_ns=cycle_ns + 50 * MS, ego_x=float(self.rng.uniform(-50, 50)),
                      ego_y=float(self.rng.uniform(-50, 50)), ego_yaw=float(self.rng.uniform(-3, 3)),
                      mode=str(self.rng.choice(MODES)), mode_reason=str(self.rng.choice(MODE_REASONS)))
        return FusedObjectList(**{**values, **fields}, objects=states_from_objects(objs, fused=True))

    def extreme_values(self, type_name: str, t_ns: int) -> bytes:
        if type_name != "fused_object_list":
            return super().extreme_values(type_name, t_ns)
        return encode(self.shared(t_ns, int(self.rng.choice([1, 256])), spread_m=1e6, ego_x=1e6, ego_y=-1e6,
                                  mode_reason="r" * 32))  # (the longest a mode_reason may be)


class ObuV2vFuzz(ObuFuzz):
    name = "obu-v2v"
    input_types = V2V_TYPES

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.hostile = V2vHostile(self.rng, "x0", "x0", "link1")

    def argv(self, duration_s: float) -> dict[str, list[str]]:
        self.eps = {"rsu": free_tcp_endpoint(), "obu": free_tcp_endpoint()}
        base, common = [sys.executable, "-m", "v2i"], self.common(duration_s)
        return {"rsu": [*base, "rsu", "--listen", self.eps["rsu"], *common, "--clock-offset-ms", str(CLOCK_OFFSET_MS)],
                self.name: [*base, "obu", "--listen", self.eps["obu"], "--connect", self.eps["rsu"], *common, "--v2v"]}

    def deliver(self, typ: str, payload: bytes, key: str | None = None) -> None:
        self.fuzzing = True
        if key is None:
            peer = f"x{int(self.rng.integers(8))}"
            key = (keys.v2v_objects(peer) if typ == "fused_object_list" else keys.v2v_time(peer)
                   if typ == "time_request" else keys.v2v_time_reply(peer, VEHICLE_ID))
        self.attacker.put(key, payload)

    def special_actions(self) -> list:
        fake = itertools.count()
        h = self.hostile

        def shared(peer: str, **fields) -> bytes:
            return encode(h.shared(time.time_ns(), vehicle_id=peer, **fields))

        def fake_peer() -> None:
            peer = f"fake{next(fake) % 200}"
            self.deliver("fused_object_list", shared(peer), keys.v2v_objects(peer))

        def stray_reply() -> None:
            reply = TimeReply(rsu_id="x1", seq=int(h.rng.integers(1 << 30)), t1_ns=time.time_ns() - 20 * MS,
                              t2_ns=time.time_ns(), t3_ns=time.time_ns())
            self.deliver("time_reply", encode(reply), keys.v2v_time_reply("x1", VEHICLE_ID))

        flood = shared("flood")
        return [("v2v_flood", lambda: self.deliver("fused_object_list", flood, keys.v2v_objects("flood"))),
                ("v2v_fake_peer", fake_peer),
                ("v2v_key_mismatch", lambda: self.deliver("fused_object_list", shared("x2"), keys.v2v_objects("x3"))),
                ("v2v_self", lambda: self.deliver("fused_object_list", shared(VEHICLE_ID), keys.v2v_objects(VEHICLE_ID))),
                ("v2v_not_own", lambda: self.deliver("fused_object_list", shared("x4", sources=SOURCE_RSU),
                                                     keys.v2v_objects("x4"))),
                ("v2v_stray_reply", stray_reply)]
