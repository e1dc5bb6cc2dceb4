"""RSU perception sources: recordings (hostile frames refused and counted) and the perception score."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from v2i.perception.scoring import PerceptionTally, match
from rsu_service.recording import MAX_IMAGE_PIXELS, ImageFrames, RecordingError, image_size
from rsu_service.source import RecordedCamera

W, H = 64, 48


def _image(value: int) -> np.ndarray:
    return np.full((H, W, 3), value, dtype=np.uint8)


def _png_header(width: int, height: int) -> bytes:
    """A PNG signature and IHDR claiming width x height, then nothing (a 'decompression bomb' header)."""
    ihdr = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 2, 0, 0, 0])
    return b"\x89PNG\r\n\x1a\n" + (13).to_bytes(4, "big") + b"IHDR" + ihdr + b"\0\0\0\0"


def test_image_size_reads_png_and_jpeg_headers():
    for ext in (".png", ".jpg"):
        ok, data = cv2.imencode(ext, np.zeros((37, 91, 3), np.uint8))
        assert image_size(data.tobytes()) == (91, 37)
    assert image_size(_png_header(100_000, 100_000)) == (100_000, 100_000)
    assert image_size(b"GIF89a....") is None
    assert image_size(b"\xff\xd8\xff\xe0\x00") is None  # a JPEG cut before its frame header


def test_folder_frames_in_order_hostile_ones_refused_and_counted(tmp_path):
    cv2.imwrite(str(tmp_path / "00.png"), _image(10))
    (tmp_path / "01.jpg").write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    (tmp_path / "02.png").write_bytes(_png_header(1 << 14, 1 << 14))  # 268 Mpx claimed
    cv2.imwrite(str(tmp_path / "03.png"), np.zeros((H + 1, W, 3), np.uint8))  # another size
    cv2.imwrite(str(tmp_path / "04.png"), np.zeros((H, W), np.uint16))  # 16-bit grey
    ok, data = cv2.imencode(".jpg", _image(200))
    (tmp_path / "05.jpg").write_bytes(data.tobytes()[: len(data) // 2])  # truncated: decodes partly or not
    cv2.imwrite(str(tmp_path / "06.png"), np.full((H, W), 30, np.uint8))  # 8-bit grey: accepted as BGR
    cv2.imwrite(str(tmp_path / "07.png"), np.dstack([_image(40), np.full((H, W), 255, np.uint8)]))  # BGRA
    (tmp_path / "notes.txt").write_text("not a frame")
    frames = ImageFrames(tmp_path, expect_wh=(W, H))
    assert frames.count == 8
    got = [frames.next() for _ in range(8)]
    assert frames.next() is None and frames.ended
    good = [g for g in got if g is not None]
    assert [int(g[0, 0, 0]) for g in (got[0], got[6], got[7])] == [10, 30, 40]
    assert all(g.shape == (H, W, 3) and g.dtype == np.uint8 for g in good)
    assert frames.refused["unreadable"] >= 1
    assert frames.refused["truncated"] == 1  # refused before the decoder sees it
    assert frames.refused["too_large"] == 1 and frames.refused["wrong_size"] == 1
    assert frames.refused["not_8bit_colour"] == 1
    assert frames.read + sum(frames.refused.values()) == 8
    assert MAX_IMAGE_PIXELS < (1 << 28)


def test_video_file_frames_and_rate(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 12.0, (W, H))
    for k in range(5):
        writer.write(_image(40 * k))
    writer.release()
    frames = ImageFrames(path, expect_wh=(W, H))
    assert frames.fps == pytest.approx(12.0)
    values = [int(frames.next()[10, 10, 1]) for _ in range(5)]
    assert values == pytest.approx([0, 40, 80, 120, 160], abs=6)
    assert frames.next() is None and frames.ended


class _SeenPerception:
    """An ImagePerception stand-in: no detections, notes each frame's first pixel (which frame it was)."""

    def __init__(self):
        self.seen: list[int] = []

    def perceive(self, image):
        self.seen.append(int(image[0, 0, 1]))
        return ObjectArray.empty(), 1.0


@pytest.mark.parametrize("kind", ["folder", "video"])
def test_a_recording_frame_keeps_its_capture_time_after_skipped_ones(tmp_path, kind):
    """Capture times the RSU let pass (a stall: it publishes only what is current) skip their frames
    unread: frame k is published with capture time k, and the recording ends on time."""
    if kind == "folder":
        for k in range(6):
            cv2.imwrite(str(tmp_path / f"{k:02d}.png"), _image(40 * k))
        path = tmp_path
    else:
        path = tmp_path / "clip.avi"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
        for k in range(6):
            writer.write(_image(40 * k))
        writer.release()
    frames, perception = ImageFrames(path, expect_wh=(W, H)), _SeenPerception()
    camera = RecordedCamera(frames, perception, start_ns=0, rate_hz=10.0)
    camera.start_at(5_000_000_000)
    times = camera.capture_times_ns(60.0)
    assert len(times) == 6  # one per frame
    for k in (0, 3, 5):  # the times of frames 1, 2 and 4 passed unpublished
        assert camera.capture(int(times[k])).capture_true_ns == times[k]
    assert perception.seen == pytest.approx([0, 120, 200], abs=6) and frames.skipped == 3
    assert camera.capture(int(times[5]) + 100_000_000) is None and frames.ended  # a 7th time: the recording has ended


def test_unusable_recordings_are_clear_errors(tmp_path):
    with pytest.raises(RecordingError, match="no such video"):
        ImageFrames(tmp_path / "missing.mp4")
    with pytest.raises(RecordingError, match="no images"):
        ImageFrames(tmp_path)
    (tmp_path / "x.mp4").write_bytes(b"garbage" * 10)
    with pytest.raises(RecordingError, match="cannot open"):
        ImageFrames(tmp_path / "x.mp4")


def test_match_is_one_to_one_within_the_gate():
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [50.0, 50.0]])
    dets = np.array([[0.5, 0.0], [0.2, 0.1], [10.0, 4.0], [80.0, 80.0]])
    ti, di = match(truth, dets, gate_m=5.0)
    assert sorted(zip(ti.tolist(), di.tolist())) == [(0, 1), (1, 2)]


def test_tally_recall_precision_and_error_by_range_bin():
    tally = PerceptionTally()
    camera = np.array([0.0, 0.0])
    truth = np.array([[20.0, 0.0], [60.0, 0.0], [90.0, 0.0]])  # one per recall bin: 0-50, 50-80, 80-120
    tally.add(truth, np.array([[20.0, 1.0], [62.0, 0.0], [0.0, 30.0]]), camera, detector_ms=12.0)
    tally.add(truth[:1], np.zeros((0, 2)), camera, detector_ms=20.0)
    s = tally.scores()
    assert s["frames"] == 2
    assert s["recall"] == 0.5 and s["precision"] == pytest.approx(2 / 3, abs=1e-4)  # rounded to 4 places
    assert s["recall_by_range"] == {"0-50m": 0.5, "50-80m": 1.0, "80-120m": 0.0}
    assert s["mean_error_m"] == {"0-50m": 1.0, "50-120m": 2.0}
    assert s["detector_ms"]["p50"] == pytest.approx(16.0)
    empty = PerceptionTally().scores()
    assert empty["recall"] is None and empty["detector_ms"] is None
