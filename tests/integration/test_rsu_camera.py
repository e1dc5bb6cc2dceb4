"""The RSU service on its own recording (``--source video``): the shipped detector and the
scenario's calibration turn rendered frames into object lists on Zenoh; hostile frames in
the folder are refused, counted in its metrics, and do not stop it."""

from __future__ import annotations

import queue
import threading
import time

import cv2
import numpy as np
import pytest

from rsu_service.config import RsuConfig
from rsu_service.node import RsuNode
from schemas import keys
from schemas.codec import decode
from schemas.messages import ObjectList, RsuMetrics
from schemas.transport import free_tcp_endpoint, open_session
from sim.camera import rsu_camera
from sim.render import SceneRenderer
from sim.scenario import load_scenario
from sim.world import World

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]


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
    rsu = RsuNode(RsuConfig(listen=[ep], source="video", video=str(tmp_path), rate_hz=5.0,
                            start_at_ns=time.time_ns() + 2_000_000_000, duration_s=6.0))
    lists, metrics = queue.Queue(), queue.Queue()
    probe = open_session(connect=[ep])
    subs = [probe.declare_subscriber(keys.rsu_objects("rsu1"), lambda s: lists.put(decode(s.payload.to_bytes(), ObjectList))),
            probe.declare_subscriber(keys.rsu_metrics("rsu1"), lambda s: metrics.put(decode(s.payload.to_bytes(), RsuMetrics)))]
    stop = threading.Event()
    thread = threading.Thread(target=rsu.run, args=(stop,))
    thread.start()
    try:
        got, last, deadline = [], None, time.monotonic() + 30.0
        while time.monotonic() < deadline and (last is None or last.published < 11):
            try:
                last = metrics.get(timeout=0.1)
            except queue.Empty:
                continue
        while not lists.empty():
            got.append(lists.get())
    finally:
        stop.set()
        thread.join(15.0)
        for s in subs:
            s.undeclare()
        probe.close()
    assert not thread.is_alive()
    assert last is not None and last.published == 11, "one list per frame, refused ones included"
    assert {k: v for k, v in last.rejected.items() if k.startswith("frame_")} == {
        "frame_unreadable": 1, "frame_wrong_size": 1, "frame_too_large": 1}
    assert got and got[-1].header.sensor == "camera/video"
    near = [o for m in got for o in m.objects if np.hypot(o.x + 3.5, o.y - 8.5) < 80]
    assert near, "the detector's adversary became a confirmed track in map"
    assert all(abs(o.y + 1.75) < 3.0 for o in near), "on the eastbound lane, where the adversary drives"
