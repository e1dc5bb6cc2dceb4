"""The RSU service on its own recording (``--source video``): the shipped detector and the
scenario's calibration turn rendered frames into object lists on Zenoh; hostile frames in
the folder are refused, counted in its metrics, and do not stop it."""

from __future__ import annotations

import queue

import cv2
import numpy as np
import pytest

from v2i.orchestration.children import READY_TIMEOUT_S, START_LEAD_S
from rsu_service.config import RsuConfig
from schemas import keys
from schemas.codec import decode
from schemas.messages import ObjectList, RsuMetrics
from v2i.runtime.transport import free_tcp_endpoint
from v2i.services import rsu_node
from v2i.sim.camera import rsu_camera
from v2i.sim.render import SceneRenderer
from v2i.sim.scenario import load_scenario
from v2i.sim.world import World

from test_obu_node import probe_session, running, wait_for  # tests/integration is on sys.path (rootdir-less import)

RATE_HZ = 5.0  # frames per second read from the folder
FILES = 11  # 8 clean frames and 3 hostile files
MARGIN_S = 20.0  # for a loaded machine, beyond the files' 2.2 s at the rate
RUN_S = 60.0  # the RSU's run from time zero: longer than the wait; the block's end stops it
pytestmark = [pytest.mark.integration, pytest.mark.timeout(READY_TIMEOUT_S + 60)]


def _recording(folder, times_s) -> None:
    """Clean RSU frames of red-light-runner at times_s, with three hostile files among them."""
    world = World(load_scenario("red-light-runner"))
    renderer, camera = SceneRenderer(world, 0), rsu_camera(world.scenario.rsu)
    for k, t in enumerate(times_s):
        cv2.imwrite(str(folder / f"{2 * k:03d}.png"), renderer.render(camera, t).image)
    (folder / "001.jpg").write_bytes(b"\xff\xd8\xff" + bytes(range(256)) * 8)  # broken JPEG
    cv2.imwrite(str(folder / "003.png"), np.zeros((100, 100, 3), np.uint8))  # not the calibrated size
    (folder / "005.png").write_bytes(b"\x89PNG\r\n\x1a\n\0\0\0\x0dIHDR" + (50_000).to_bytes(4, "big") * 2 + bytes(9))


def test_rsu_runs_the_detector_on_a_recording_and_refuses_bad_frames(tmp_path):
    _recording(tmp_path, times_s=np.arange(6.0, 7.6, 0.2))  # the adversary 60-40 m from the camera
    ep = free_tcp_endpoint()
    rsu = rsu_node(RsuConfig(listen=[ep], source="video", video=str(tmp_path), rate_hz=RATE_HZ, await_start=True,
                             duration_s=RUN_S))
    lists, metrics = queue.Queue(), queue.Queue()
    with running(rsu, start=False) as gate, probe_session(ep) as (probe, entities):
        entities += [
            probe.declare_subscriber(keys.rsu_objects("rsu1"), lambda s: lists.put(decode(s.payload.to_bytes(), ObjectList))),
            probe.declare_subscriber(keys.rsu_metrics("rsu1"), lambda s: metrics.put(decode(s.payload.to_bytes(), RsuMetrics)))]
        # the RSU's liveliness token answers over the same link, after the subscriptions: the RSU knows them now
        assert any(r.ok is not None for r in probe.liveliness().get(keys.rsu_alive("rsu1"), timeout=10.0))
        gate.start()
        # every file's time has come: each one published, or (a stall) skipped
        last = wait_for(metrics, lambda m: m.published + m.skipped >= FILES, START_LEAD_S + FILES / RATE_HZ + MARGIN_S)
    got = []
    while not lists.empty():
        got.append(lists.get())
    assert last.published == FILES, f"one list per frame, refused ones included ({last.skipped} skipped)"
    assert {k: v for k, v in last.rejected.items() if k.startswith("frame_")} == {
        "frame_unreadable": 1, "frame_wrong_size": 1, "frame_too_large": 1}
    assert got and got[-1].header.sensor == "camera/video"
    near = [o for m in got for o in m.objects if np.hypot(o.x + 3.5, o.y - 8.5) < 80]
    assert near, "the detector's adversary became a confirmed track in map"
    assert all(abs(o.y + 1.75) < 3.0 for o in near), "on the eastbound lane, where the adversary drives"
