"""Two OBUs (``v2i obu --v2v``) through the V2V emulator (``v2i link --v2v``) as OS processes on
explicit loopback TCP endpoints: each learns the other's clock through the emulator and the
ego fuses what car-3's LiDAR sees (connected-intersection, no RSU running: every cooperative
object in the ego's output came over V2V). The OBUs start on their start line once all three
processes are ready and the watcher is subscribed (``v2i.orchestration.children``); each OBU ends by
itself (``--duration``), the emulator on SIGTERM after them; all exit 0 and are reaped."""

from __future__ import annotations

import json
import queue
import sys
import time

import pytest

from v2i.orchestration.children import Child, start_all, wait_ready
from schemas import keys
from schemas.codec import decode
from schemas.messages import SOURCE_RSU, FusedObjectList, ObuMetrics
from v2i.runtime.transport import free_tcp_endpoint, open_session

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

DURATION_S = 8.0  # scenario seconds: car-3's LiDAR sees the runner from t = 4.5 s, the ego's not before 10 s
SCENARIO = "connected-intersection"


END_WAIT_S = 30.0  # an OBU ends at time zero + duration + 1 s; more on a busy machine


def _argv_obu(vid: str, ep: str) -> list[str]:
    return [sys.executable, "-m", "v2i", "obu", "--vehicle-id", vid, "--listen", ep, "--scenario", SCENARIO,
            "--seed", "0", "--await-start", "--duration", str(DURATION_S), "--v2v"]


@pytest.fixture(scope="module")
def run() -> dict:
    eps = {"ego": free_tcp_endpoint(), "car-3": free_tcp_endpoint()}
    heard: queue.Queue = queue.Queue()
    children, watcher, subs = {}, None, []
    try:
        for vid, ep in eps.items():
            children[vid] = Child(vid, _argv_obu(vid, ep), label=f"obu {vid}")
        link = ["--vehicle", f"ego={eps['ego']}", "--vehicle", f"car-3={eps['car-3']}"]
        children["link"] = Child("link", [sys.executable, "-m", "v2i", "link", "--v2v", "--link-id", "v2v-test",
                                          *link, "--profile", "lte-v2x", "--seed", "1"], label="link v2v-test")
        wait_ready(children.values())
        watcher = open_session(connect=list(eps.values()))
        for vid in eps:
            for kind, key in (("objects", keys.obu_objects(vid)), ("peers", keys.obu_peers(vid)),
                              ("metrics", keys.obu_metrics(vid))):
                subs.append(watcher.declare_subscriber(
                    key, lambda s, k=kind, v=vid: heard.put((k, v, s.payload.to_bytes()))))
        start_ns = start_all(children.values())
        end = time.monotonic() + (start_ns - time.time_ns()) * 1e-9 + DURATION_S + END_WAIT_S
        codes = {}
        for name in eps:  # each OBU ends by itself (--duration)
            try:
                codes[name] = children[name].proc.wait(max(end - time.monotonic(), 0.1))
            except Exception:  # noqa: BLE001 - a hung child is stopped below and fails the test
                codes[name] = None
        children["link"].stop()  # SIGTERM: a clean stop
        codes["link"] = children["link"].proc.returncode
    finally:
        for sub in subs:
            sub.undeclare()
        if watcher is not None:
            watcher.close()
        for child in children.values():
            child.stop()
    out: dict = {"codes": codes, "children": children, "objects": {v: [] for v in eps}, "peers": {},
                 "metrics": {}}
    while not heard.empty():
        kind, vid, data = heard.get()
        if kind == "objects":
            out["objects"][vid].append(decode(data, FusedObjectList))
        elif kind == "peers":
            out["peers"][vid] = json.loads(data)
        else:
            out["metrics"][vid] = decode(data, ObuMetrics)
    return out


def test_every_process_ended_cleanly_and_is_reaped(run):
    assert run["codes"] == {"ego": 0, "car-3": 0, "link": 0}
    for child in run["children"].values():
        assert child.proc.poll() is not None


def test_each_obu_syncs_to_the_other_through_the_emulator(run):
    for me, peer in (("ego", "car-3"), ("car-3", "ego")):
        summary = run["peers"][me][peer]
        assert summary["lists_accepted"] > 0.5 * DURATION_S * 10, (me, summary)
        assert summary["sync_samples"] > 10, (me, summary)
        # one host clock: the truth is 0, and the estimate stays within its own bound
        assert abs(summary["clock_offset_ms"]) <= summary["clock_uncertainty_ms"] + 0.5, (me, summary)
        rejected = {k: n for k, n in run["metrics"][me].rejected.items() if k.startswith("v2v_")}
        assert not {"v2v_self", "v2v_key_mismatch", "v2v_bad_frame"} & set(rejected), rejected


def test_the_ego_fuses_what_only_car_3_sees(run):
    outs = run["objects"]["ego"]
    assert len(outs) > 0.9 * DURATION_S * 10
    cooperative = [o for o in outs if any(obj.sources & SOURCE_RSU for obj in o.objects)]
    assert len(cooperative) > 0.5 * len(outs)  # no RSU runs: V2V is the only cooperative source
    late = [o for o in outs if o.cycle_time_ns >= outs[0].cycle_time_ns + 6_000_000_000]
    assert late and all(any(obj.sources == SOURCE_RSU for obj in o.objects) for o in late)
