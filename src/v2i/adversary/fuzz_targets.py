"""The three fuzz targets of ``v2i fuzz`` (``v2i.adversary.fuzz``): where each service's inputs
are, what its normal output is and where it counts what it refused.

- ``obu``: an RSU (clock offset 250 ms) and the OBU connected to it directly. The attacker's
  session reaches both: it publishes on the RSU keys of other ids (v2i lists, and CPM / SDSM
  lists on ``.../cpm`` / ``.../sdsm``: ``v2i.adversary.fuzz_standard``; and, as one special kind
  among the others, valid lists on the genuine RSU's own key: without signatures (``--security none``),
  those are indistinguishable from the RSU's), replays the genuine RSU's lists, and, once the OBU has synchronised and fuses RSU data, answers
  half of its time queries at once with a forged clock (245 ms further ahead, a
  precise-looking round trip). Normal output: a fused list per 10 Hz cycle, late after the
  100 ms deadline. Also reported: the OBU's clock error against its stated uncertainty
  while the forger is active, and the genuine RSU's lists published and accepted by the OBU in
  the window. Kind ``trickle``: raw TCP sockets to the OBU's listen endpoint instead of messages
  (``v2i.adversary.fuzz``); its RSU lists keep coming over the OBU's own connection to the RSU.
- ``rsu``: the RSU alone. The attacker sends hostile time queries (or trickles to its listen
  endpoint); a probe asks the time genuinely at 10 Hz. Normal output: the object lists at the camera rate, late when the RSU
  stamped publish more than 250 ms after capture; and the probes' answers.
- ``obu-inputs`` / ``rsu-inputs`` (``v2i.adversary.fuzz_inputs``): ``v2i world`` feeding the
  service with ``--source zenoh``, the attacker on its sensor input keys.
- ``link``: the demo's topology (RSU, emulator with profile ``ideal``, OBU), the emulator
  also connected to the attacker's two sessions; the attacker sends hostile lists on the RSU
  side and hostile poses, controls and time queries on the vehicle side. Normal output: the
  OBU's fused list per cycle (the RSU's lists relayed through the emulator under attack).
"""

from __future__ import annotations

import itertools
import json
import sys
import threading
import time
from collections import Counter

import zenoh

from schemas import keys
from schemas.codec import CodecError, decode, encode
from schemas.messages import FusedObjectList, ObjectList, ObuMetrics, RsuMetrics, TimeReply, TimeRequest
from v2i.runtime.transport import free_tcp_endpoint
from v2i.sim.maps import MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG
from v2i.sim.scenario import load_scenario

from v2i.adversary.fuzz import LINK_ID, MS, RSU_ID, VEHICLE_ID, FuzzRun
from v2i.adversary.fuzz_standard import StandardHostile

STANDARD_WIRES = "v2i,cpm,sdsm"  # the OBU takes every encoding: hostile CPM / SDSM reach it too

CLOCK_OFFSET_MS = 250.0  # the RSU's injected clock offset: the truth the OBU's estimate is scored against
FORGED_SHIFT_NS = 245_000_000  # forged time replies claim the RSU clock is this much further ahead
RSU_LATE_NS = 250 * MS  # an RSU list is late when published this long after its capture
REPLAY_AGE_NS = 5_000 * MS


def _ignore(_reply) -> None:
    """Reply handler of a hostile query: what the target answers to it is not what is measured."""


class ObuFuzz(FuzzRun):
    name = "obu"
    input_types = ("object_list", "prediction_list")
    trickle_target = "obu"

    def argv(self, duration_s: float) -> dict[str, list[str]]:
        self.eps = {"rsu": free_tcp_endpoint(), "obu": free_tcp_endpoint()}
        base, common = [sys.executable, "-m", "v2i"], self.common(duration_s)
        return {"rsu": [*base, "rsu", "--listen", self.eps["rsu"], *common, "--clock-offset-ms", str(CLOCK_OFFSET_MS)],
                "obu": [*base, "obu", "--listen", self.eps["obu"], "--connect", self.eps["rsu"], *common,
                        "--wires", STANDARD_WIRES]}

    def open(self) -> None:
        self.metrics: dict | None = None
        self.clock_rows: list[tuple[int, int, int]] = []  # (t, offset, uncertainty) ns while fuzzing
        self.genuine: list[tuple[int, bytes]] = []
        self.forged = 0
        self.fuzzing = False  # hostile messages sent: the forger answers time queries from then on
        self.watching = False  # the fuzzing window began: the clock rows are kept from then on
        self.rsu_published: int | None = None  # lists the RSU says it published, latest
        self.lists_at_start: tuple[int, int] | None = None  # (published, accepted by the OBU) at fuzz start
        s = self.attacker = self.session(connect=[self.eps["obu"], self.eps["rsu"]])
        self.declare(s.declare_subscriber(keys.obu_objects(VEHICLE_ID), self._on_fused))
        self.declare(s.declare_subscriber(keys.obu_metrics(VEHICLE_ID), self._on_metrics))
        self.declare(s.declare_subscriber(keys.rsu_objects(RSU_ID), self._on_genuine))
        self.declare(s.declare_subscriber(keys.rsu_metrics(RSU_ID), self._on_rsu_metrics))
        for rsu_id in (RSU_ID, "forger"):
            self.declare(s.declare_queryable(keys.rsu_time(rsu_id), lambda q, rsu_id=rsu_id: self._forge_reply(q, rsu_id)))

    def deliver(self, typ: str, payload: bytes, key: str | None = None) -> None:
        self.fuzzing = True
        if key is None:
            topic = keys.rsu_objects if typ == "object_list" else keys.rsu_predictions
            key = topic(f"x{int(self.rng.integers(8))}")
        self.attacker.put(key, payload)

    def special_actions(self) -> list:
        fake = itertools.count()

        def valid(**header) -> bytes:
            return self.hostile.valid("object_list", time.time_ns(), **header)

        def fake_id() -> None:
            rsu_id = f"fake{next(fake) % 200}"
            self.deliver("object_list", valid(rsu_id=rsu_id), keys.rsu_objects(rsu_id))

        flood = valid(rsu_id="flood")
        return [("flood", lambda: self.deliver("object_list", flood, keys.rsu_objects("flood"))),
                ("fake_id", fake_id), ("replay", self._replay),
                ("spoofed_id", lambda: self.deliver("object_list", valid(), keys.rsu_objects(RSU_ID))),
                *self._standard_actions()]

    def _standard_actions(self) -> list:
        """Hostile CPM / SDSM lists (``v2i.adversary.fuzz_standard``) on the RSU keys of other ids."""
        # the OBU's scenario site: every bundled scenario's map has this origin (v2i.sim.scenario_site)
        hostile = StandardHostile(self.rng, origin=(MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG))
        now, actions = time.time_ns(), []
        for wire, topic in (("cpm", keys.rsu_cpm), ("sdsm", keys.rsu_sdsm)):
            pool = itertools.cycle([hostile.make(wire, now)[1] for _ in range(64)])
            actions.append((wire, lambda topic=topic, pool=pool: self.deliver(
                "object_list", next(pool), topic(f"x{int(self.rng.integers(8))}"))))
        return actions

    def _replay(self) -> None:
        """A captured genuine list again: the newest (a duplicate) or one >= 5 s old (stale)."""
        with self.lock:
            captured = list(self.genuine)
        if captured:
            old = [p for t, p in captured if time.time_ns() - t > REPLAY_AGE_NS]
            payload = old[-1] if old and self.rng.random() < 0.5 else captured[-1][1]
            self.deliver("object_list", payload, keys.rsu_objects(RSU_ID))

    def _on_fused(self, sample) -> None:
        try:
            out = decode(sample.payload.to_bytes(), FusedObjectList)
        except CodecError:
            return
        self.output(out.cycle_time_ns, out.publish_time_ns - out.cycle_time_ns > self.deadline_ns, out.mode)

    def _on_metrics(self, sample) -> None:
        try:
            metrics = decode(sample.payload.to_bytes(), ObuMetrics)
        except CodecError:
            return
        with self.lock:
            self.metrics = metrics.model_dump()
            if self.watching:
                self.clock_rows += [(metrics.t_ns, r.clock_offset_ns, r.clock_uncertainty_ns or 0)
                                    for r in metrics.rsus if r.rsu_id == RSU_ID and r.clock_offset_ns is not None]

    def _on_genuine(self, sample) -> None:
        with self.lock:
            self.genuine = [*self.genuine[-63:], (time.time_ns(), sample.payload.to_bytes())]

    def _on_rsu_metrics(self, sample) -> None:
        try:
            published = decode(sample.payload.to_bytes(), RsuMetrics).published
        except CodecError:
            return
        with self.lock:
            self.rsu_published = published

    def _lists(self) -> tuple[int, int]:
        """(lists the RSU published, lists the OBU accepted from it) so far."""
        with self.lock:
            rsus = (self.metrics or {}).get("rsus", [])
            accepted = next((r["messages_accepted"] for r in rsus if r["rsu_id"] == RSU_ID), 0)
            return self.rsu_published or 0, accepted

    def at_fuzz_start(self) -> None:
        self.lists_at_start = self._lists()
        self.watching = True

    def _genuine_lists(self) -> dict:
        """The genuine RSU's lists published and accepted by the OBU since the fuzzing began."""
        (published0, accepted0), (published1, accepted1) = self.lists_at_start or (0, 0), self._lists()
        return {"published": published1 - published0, "accepted_by_obu": accepted1 - accepted0}

    def warmed_up(self) -> bool:
        """The OBU has an RSU clock estimate and has accepted RSU lists."""
        with self.lock:
            rsus = (self.metrics or {}).get("rsus", [])
        return any(r["rsu_id"] == RSU_ID and r["clock_offset_ns"] is not None and r["messages_accepted"] for r in rsus)

    def _forge_reply(self, query, rsu_id: str) -> None:
        """While fuzzing, answer half the OBU's time queries at once as ``rsu_id``, claiming a
        clock 245 ms further ahead."""
        try:
            request = decode(query.payload.to_bytes(), TimeRequest)
        except (CodecError, AttributeError):
            return
        if not self.fuzzing or request.seq % 2:
            return
        t2 = request.t1_ns + round(CLOCK_OFFSET_MS * MS) + FORGED_SHIFT_NS + 500_000
        query.reply(keys.rsu_time(rsu_id), encode(TimeReply(rsu_id=rsu_id, seq=request.seq, t1_ns=request.t1_ns,
                                                             t2_ns=t2, t3_ns=t2 + 50_000)))
        with self.lock:
            self.forged += 1

    def refused(self) -> Counter[str]:
        with self.lock:
            return Counter((self.metrics or {}).get("rejected", {}))

    def expected_outputs(self, seconds: float) -> int:
        return int(seconds * 10.0)

    def extra(self) -> dict:
        with self.lock:
            rows, metrics, forged = list(self.clock_rows), self.metrics or {}, self.forged
        truth = CLOCK_OFFSET_MS * MS
        errors = [abs(offset - truth) for _, offset, _ in rows]
        beyond = [abs(offset - truth) - unc for _, offset, unc in rows]
        return {
            "forged_time_replies": forged,
            "obu_output_deadline_misses": metrics.get("output_deadline_misses"),
            "obu_cycles": metrics.get("cycles"),
            "clock": {"samples": len(rows), "max_error_ms": _ms(max(errors, default=None)),
                      "max_error_beyond_uncertainty_ms": _ms(max(beyond, default=None))},
            "genuine_lists": self._genuine_lists(),
        }


def _ms(v: float | None) -> float | None:
    return None if v is None else round(v / MS, 3)


class RsuFuzz(FuzzRun):
    name = "rsu"
    input_types = ("time_request",)
    trickle_target = "rsu"

    def argv(self, duration_s: float) -> dict[str, list[str]]:
        self.eps = {"rsu": free_tcp_endpoint()}
        return {"rsu": [sys.executable, "-m", "v2i", "rsu", "--listen", self.eps["rsu"], *self.common(duration_s)]}

    def open(self) -> None:
        self.metrics: dict | None = None
        self.probes = Counter()
        s = self.attacker = self.session(connect=[self.eps["rsu"]])
        self.declare(s.declare_subscriber(keys.rsu_objects(RSU_ID), self._on_list))
        self.declare(s.declare_subscriber(keys.rsu_metrics(RSU_ID), self._on_metrics))
        threading.Thread(target=self._probe, daemon=True).start()

    def deliver(self, typ: str, payload: bytes) -> None:
        self.attacker.get(keys.rsu_time(RSU_ID), _ignore, payload=payload, timeout=0.5)

    def special_actions(self) -> list:
        def query_flood() -> None:
            self.deliver("time_request", self.hostile.valid("time_request", time.time_ns()))

        def no_payload() -> None:
            self.attacker.get(keys.rsu_time(RSU_ID), _ignore, timeout=0.5)

        return [("query_flood", query_flood), ("no_payload", no_payload)]

    def _probe(self) -> None:
        """A genuine time query every 100 ms: is the RSU still answering?"""
        for seq in itertools.count():
            if self.stop.wait(0.1):
                return
            request = TimeRequest(obu_id="probe", seq=seq, t1_ns=time.time_ns())
            try:
                self.attacker.get(keys.rsu_time(RSU_ID), self._on_probe_reply, payload=encode(request), timeout=1.0)
            except zenoh.ZError:  # the run ended and closed the session meanwhile
                return
            with self.lock:
                self.probes["sent"] += 1

    def _on_probe_reply(self, reply) -> None:
        if reply.ok is not None:
            with self.lock:
                self.probes["answered"] += 1

    def _on_list(self, sample) -> None:
        try:
            header = decode(sample.payload.to_bytes(), ObjectList).header
        except CodecError:
            return
        self.output(time.time_ns(), header.publish_time_ns - header.capture_time_ns > RSU_LATE_NS)

    def _on_metrics(self, sample) -> None:
        try:
            metrics = decode(sample.payload.to_bytes(), RsuMetrics)
        except CodecError:
            return
        with self.lock:
            self.metrics = metrics.model_dump()

    def refused(self) -> Counter[str]:
        with self.lock:
            return Counter((self.metrics or {}).get("rejected", {}))

    def expected_outputs(self, seconds: float) -> int:
        return int(seconds * load_scenario("red-light-runner").rsu.rate_hz)

    def extra(self) -> dict:
        with self.lock:
            return {"probes": dict(self.probes), "rsu_skipped_frames": (self.metrics or {}).get("skipped")}


class LinkFuzz(ObuFuzz):
    """The demo's topology (RSU, link emulator with profile ``ideal``, OBU), the emulator also
    connected to the attacker's RSU-side and vehicle-side sessions."""

    name = "link"
    input_types = ("object_list", "ego_pose", "link_control", "time_request")

    def argv(self, duration_s: float) -> dict[str, list[str]]:
        names = ("rsu", "obu", "attacker_rsu_side", "attacker_vehicle_side")
        self.eps = {name: free_tcp_endpoint() for name in names}
        base, common = [sys.executable, "-m", "v2i"], self.common(duration_s)
        return {"rsu": [*base, "rsu", "--listen", self.eps["rsu"], *common, "--clock-offset-ms", str(CLOCK_OFFSET_MS)],
                "obu": [*base, "obu", "--listen", self.eps["obu"], *common, "--wires", STANDARD_WIRES],
                # unauthenticated control: the hostile controls reach the decoder, not only the signature check
                # (that one is fuzzed by tests/unit/test_link_control_auth.py's hostile bytes)
                "link": [*base, "link", "--link-id", LINK_ID, "--profile", "ideal", "--insecure-control",
                         "--rsu-connect", self.eps["rsu"], "--rsu-connect", self.eps["attacker_rsu_side"],
                         "--vehicle-connect", self.eps["obu"], "--vehicle-connect", self.eps["attacker_vehicle_side"]]}

    def open(self) -> None:
        self.metrics, self.clock_rows, self.forged, self.fuzzing, self.watching = None, [], 0, False, False
        self.stats: dict = {}
        self.rsu_published: int | None = None  # lists the RSU says it published, latest
        self.lists_at_start: tuple[int, int] | None = None  # (published, accepted by the OBU) at fuzz start
        self.rsu_side = self.session(listen=[self.eps["attacker_rsu_side"]])
        self.vehicle_side = self.session(listen=[self.eps["attacker_vehicle_side"]])
        monitor = self.session(connect=[self.eps["obu"], self.eps["rsu"]])
        self.declare(monitor.declare_subscriber(keys.obu_objects(VEHICLE_ID), self._on_fused))
        self.declare(monitor.declare_subscriber(keys.obu_metrics(VEHICLE_ID), self._on_metrics))
        self.declare(monitor.declare_subscriber(keys.rsu_metrics(RSU_ID), self._on_rsu_metrics))
        self.declare(self.vehicle_side.declare_subscriber(keys.link_stats(LINK_ID), self._on_stats))

    def deliver(self, typ: str, payload: bytes, key: str | None = None) -> None:
        self.fuzzing = True
        if typ == "object_list":
            self.rsu_side.put(key or keys.rsu_objects(f"x{int(self.rng.integers(8))}"), payload)
        elif typ == "ego_pose":
            self.vehicle_side.put(keys.obu_pose(f"v{int(self.rng.integers(4))}"), payload)
        elif typ == "link_control":
            self.vehicle_side.put(keys.link_control(LINK_ID), payload)
        else:
            self.vehicle_side.get(keys.rsu_time(RSU_ID), _ignore, payload=payload, timeout=0.5)

    def special_actions(self) -> list:
        flood = self.hostile.valid("object_list", time.time_ns(), rsu_id="flood")
        fake = itertools.count()

        def fake_id() -> None:
            rsu_id = f"fake{next(fake) % 200}"
            self.deliver("object_list", self.hostile.valid("object_list", time.time_ns(), rsu_id=rsu_id),
                         keys.rsu_objects(rsu_id))

        return [("flood", lambda: self.deliver("object_list", flood, keys.rsu_objects("flood"))), ("fake_id", fake_id)]

    def _on_stats(self, sample) -> None:
        try:
            stats = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with self.lock:
            self.stats = stats

    def refused(self) -> Counter[str]:
        with self.lock:
            stats = self.stats
        counts = Counter(stats.get("refused", {}))
        counts.update({f"control_{k}": v for k, v in stats.get("control", {}).get("rejected", {}).items()})
        counts.update({f"pose_{k}": v for k, v in stats.get("pose", {}).get("refused", {}).items()})
        return +counts

    def extra(self) -> dict:
        with self.lock:
            stats, metrics = self.stats, self.metrics or {}
        return {"relay": {k: stats.get(k) for k in ("downlink", "uplink", "lateness_ms", "in_flight", "open_queries")},
                "obu_output_deadline_misses": metrics.get("output_deadline_misses"), "obu_cycles": metrics.get("cycles"),
                "genuine_lists": self._genuine_lists()}


from v2i.adversary.fuzz_inputs import ObuInputsFuzz, RsuInputsFuzz  # noqa: E402 (they build on FuzzRun, not on this module)

TARGETS = {"obu": ObuFuzz, "rsu": RsuFuzz, "link": LinkFuzz, "obu-inputs": ObuInputsFuzz, "rsu-inputs": RsuInputsFuzz}
