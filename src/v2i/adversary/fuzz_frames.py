"""``v2i fuzz --target frames``: hostile image files in the RSU's recording (``--source video``).

A folder holds ``WARMUP_FRAMES`` genuine frames, then ``count`` hostile files, each between two genuine frames of the
red-light-runner RSU camera (rendered clean); the RSU service reads it at ``min(rate, 20)``
frames per second through the shipped detector and calibration. Kinds: random bytes, a
truncated PNG, an empty file, a PNG header claiming 2^30 pixels, an image of another size, a
16-bit image, and a file past the byte limit (sparse). Normal output: one object list per
file (a refused frame yields an empty detection set, the tracker coasts), late when
published more than 250 ms after its capture. The RSU publishes only what is current: on a busy
machine it lets some capture times pass (``skipped``; their files go unread). A list's capture
time names its file (``rsu_service.source.RecordedCamera``), so the report says which hostile
files the RSU read (``hostile_read``): each of them must be refused, and nothing else. The
report has ``v2i fuzz``'s keys.
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from v2i.core.jit import load_kernels
from v2i.offline.kernels import RUN_KERNEL_MODULES
from schemas import keys
from schemas.codec import CodecError, decode
from schemas.messages import ObjectList, RsuMetrics
from v2i.runtime.transport import free_tcp_endpoint, open_session

from v2i.orchestration.children import READY_TIMEOUT_S, Child, start_all, wait_ready
from v2i.adversary.fuzz import RSU_ID, _r, rss_mb
from v2i.adversary.fuzz_targets import RSU_LATE_NS

MAX_FRAME_RATE_HZ = 20.0  # the detector's pace on this machine, with margin
WARMUP_FRAMES = 10  # genuine frames first: RSS is measured from the 10th list on (ONNX Runtime's arena is warm)
GENUINE_TIMES_S = (5.0, 5.5, 6.0, 6.5, 7.0, 7.5, 8.0, 8.5)


def _png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def hostile_frames(genuine: bytes, size_wh: tuple[int, int]) -> dict[str, tuple[str, object]]:
    """kind -> (file suffix, bytes or a byte count of a sparse file)."""
    w, h = size_wh
    bomb = b"\x89PNG\r\n\x1a\n\0\0\0\x0dIHDR" + (1 << 15).to_bytes(4, "big") * 2 + bytes([8, 2, 0, 0, 0, 0, 0, 0, 0])
    return {
        "random_bytes": (".jpg", np.random.default_rng(0).integers(0, 256, 20_000, dtype=np.uint8).tobytes()),
        "truncated": (".png", genuine[: len(genuine) // 3]),
        "empty": (".jpg", b""),
        "pixel_bomb": (".png", bomb),
        "wrong_size": (".png", _png(np.zeros((h // 2, w // 2, 3), np.uint8))),
        "deep": (".png", _png(np.full((h, w), 1000, np.uint16))),
        "huge_file": (".jpg", (64 << 20) + 1),
    }


class FramesFuzz:
    name = "frames"

    def __init__(self, count: int, seed: int = 0, rate_hz: float = 10.0, ready_timeout_s: float = READY_TIMEOUT_S,
                 kinds=None, progress=sys.stderr):
        """``ready_timeout_s``: the RSU must say it is ready within this (``--ready-timeout``);
        ``progress``: where the progress lines go (None: nowhere)."""
        if count < 1 or not rate_hz > 0 or not ready_timeout_s > 0:
            raise ValueError("--count must be >= 1, --rate and --ready-timeout > 0")
        self.count, self.ready_timeout_s, self.progress = count, ready_timeout_s, progress
        self.rate_hz = min(rate_hz, MAX_FRAME_RATE_HZ)
        self.rng = np.random.default_rng(seed)
        self.kinds = list(kinds or ())
        self.lock = threading.Lock()
        self.lists: list[tuple[int, bool]] = []  # (capture time, late) of each list
        self.plan: list[str | None] = []  # the hostile kind of each file, in order (None: a genuine frame)
        self.metrics: RsuMetrics | None = None
        self.ready_s: float | None = None  # the RSU ready this long after it was started

    def _write(self, folder: Path) -> Counter[str]:
        from v2i.sim.camera import rsu_camera
        from v2i.sim.render import SceneRenderer
        from v2i.sim.scenario import load_scenario
        from v2i.sim.world import World

        world = World(load_scenario("red-light-runner"))
        camera = rsu_camera(world.scenario.rsu)
        renderer = SceneRenderer(world, 0)
        genuine = [_png(renderer.render(camera, t).image) for t in GENUINE_TIMES_S]
        pool = hostile_frames(genuine[0], (camera.width, camera.height))
        unknown = sorted(set(self.kinds) - set(pool))
        if unknown:
            raise ValueError(f"unknown frame kind(s) {', '.join(unknown)}; kinds: {', '.join(pool)}")
        kinds = self.kinds or list(pool)
        sent: Counter[str] = Counter()
        self.plan = [None] * WARMUP_FRAMES
        for i in range(WARMUP_FRAMES):
            (folder / f"0{i:06d}.png").write_bytes(genuine[i % len(genuine)])
        for i in range(self.count):
            kind = kinds[int(self.rng.integers(len(kinds)))]
            self.plan += [None, kind]
            suffix, data = pool[kind]
            (folder / f"1{2 * i:07d}.png").write_bytes(genuine[i % len(genuine)])
            path = folder / f"1{2 * i + 1:07d}{suffix}"
            if isinstance(data, int):
                with open(path, "wb") as f:
                    os.truncate(f.fileno(), data)  # sparse: no disk used
            else:
                path.write_bytes(data)
            sent[kind] += 1
        return sent

    def run(self) -> dict:
        # compiled once per machine (v2i.core.jit: tens of seconds) here, not in the child
        load_kernels(RUN_KERNEL_MODULES)
        with tempfile.TemporaryDirectory(prefix="v2i-fuzz-frames-") as tmp:
            sent = self._write(Path(tmp))
            files = WARMUP_FRAMES + 2 * self.count
            ep = free_tcp_endpoint()
            run_s = files / self.rate_hz
            child = Child("rsu", [sys.executable, "-m", "v2i", "rsu", "--listen", ep, "--source", "video",
                                  "--video", tmp, "--rate-hz", str(self.rate_hz), "--await-start",
                                  "--duration", str(run_s + 30.0)])
            session = None
            try:
                self.ready_s = wait_ready([child], self.ready_timeout_s,
                                          "v2i fuzz frames" if self.progress is not None else None)
                session = open_session(connect=[ep])
                subs = [session.declare_subscriber(keys.rsu_objects(RSU_ID), self._on_list),
                        session.declare_subscriber(keys.rsu_metrics(RSU_ID), self._on_metrics)]
                start_ns = start_all([child])  # subscribed before time zero
                crash = self._watch(child, WARMUP_FRAMES, start_ns, run_s)
                before = rss_mb(child.proc.pid)
                crash = crash or self._watch(child, files, start_ns, run_s)
                report = self._report(sent, start_ns, before, rss_mb(child.proc.pid), crash, run_s)
                for sub in subs:
                    sub.undeclare()
                return report
            finally:
                if session is not None:
                    session.close()
                child.stop()

    def _watch(self, child: Child, files: int, start_ns: int, run_s: float) -> str | None:
        """Until the time of ``files`` frames has come, each one published or skipped, and every list
        the RSU published arrived (or twice the time they need passed); a crash's text."""
        deadline = time.monotonic() + (start_ns - time.time_ns()) * 1e-9 + 2.0 * run_s + 10.0
        last_note = time.monotonic()
        while time.monotonic() < deadline:
            if child.proc.poll() is not None:
                return f"rsu exited with code {child.proc.returncode}"
            with self.lock:
                m = self.metrics
                done = m is not None and m.published + m.skipped >= files and len(self.lists) >= m.published
            if done:
                return None
            if self.progress is not None and time.monotonic() - last_note > 5.0:
                last_note = time.monotonic()
                print(f"v2i fuzz frames: {len(self.lists)}/{files} frames published", file=self.progress, flush=True)
            time.sleep(0.05)
        return None

    def _on_list(self, sample) -> None:
        try:
            header = decode(sample.payload.to_bytes(), ObjectList).header
        except CodecError:
            return
        with self.lock:
            self.lists.append((header.capture_time_ns, header.publish_time_ns - header.capture_time_ns > RSU_LATE_NS))

    def _on_metrics(self, sample) -> None:
        try:
            metrics = decode(sample.payload.to_bytes(), RsuMetrics)
        except CodecError:
            return
        with self.lock:
            self.metrics = metrics

    def _report(self, sent: Counter, start_ns: int, before, after, crash: str | None, run_s: float) -> dict:
        """The report; a list's file is the one of its capture time (``start + k / rate``: the RSU's
        clock is the true one here)."""
        with self.lock:
            lists, metrics = list(self.lists), self.metrics
        files, skipped = len(self.plan), metrics.skipped if metrics else 0
        refused = {k: v for k, v in (metrics.rejected if metrics else {}).items() if k.startswith("frame_")}
        kinds = [self.plan[k] if 0 <= (k := round((capture_ns - start_ns) * self.rate_hz * 1e-9)) < files else None
                 for capture_ns, _ in lists]
        read = Counter(kind for kind in kinds if kind is not None)
        return {
            "target": self.name, "sent": sum(sent.values()), "sent_by_kind": dict(sorted(sent.items())),
            "rate_hz": self.rate_hz, "fuzz_s": round(run_s, 2),
            "rejected": dict(sorted(refused.items())), "rejected_total": sum(refused.values()),
            # hostile files the RSU read (the others' capture times passed unpublished): each must be refused
            "hostile_read": sum(read.values()), "hostile_read_by_kind": dict(sorted(read.items())),
            "hostile_late": sum(late for kind, (_, late) in zip(kinds, lists) if kind is not None),
            "crashes": 0 if crash is None else 1, "crash": crash,
            # skipped: capture times the RSU let pass (it publishes only what is current), their files unread
            "outputs": {"expected": files, "received": len(lists), "late": sum(late for _, late in lists),
                        "skipped": skipped, "missing": max(files - len(lists) - skipped, 0)},
            "rss_mb": {"before": _r(before), "after": _r(after),
                       "growth": None if before is None or after is None else _r(after - before)},
            "startup": {"ready_s": _r(self.ready_s)},
        }
