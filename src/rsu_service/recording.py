"""Frames of a recording: a video file (``cv2.VideoCapture``) or a folder of images.

Every frame is hostile until checked: a file that is not an image, is too large (in bytes,
or in pixels by its header, before anything is decoded: a small PNG can claim 10^10
pixels), or has another size than the calibration is refused and counted by reason
(``refused``), never raised, so one bad frame does not stop the RSU.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from v2i.core.files import FileRefused, FileTooLarge, check_regular, read_bounded

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
MAX_IMAGE_BYTES = 64 << 20  # a larger file (or not a regular file) is refused unread
MAX_IMAGE_PIXELS = 1 << 25  # 33 Mpx (8K is 33.2 Mpx): a larger header is refused undecoded
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
DEFAULT_FOLDER_FPS = 10.0


class RecordingError(ValueError):
    """A recording that cannot be opened at all (missing, not a video, empty folder)."""


class ImageFrames:
    """Frames (H, W, 3) uint8 BGR in order; ``expect_wh`` (W, H) refuses other sizes."""

    def __init__(self, path: str | Path, expect_wh: tuple[int, int] | None = None, folder_fps: float = DEFAULT_FOLDER_FPS):
        self.path = Path(path)
        self.expect_wh = expect_wh
        self.refused: Counter[str] = Counter()
        self.read = 0
        self.skipped = 0  # frames passed over unread (``skip``)
        self.ended = False  # no frame left
        self._files: list[Path] | None = None
        self._video = None
        if self.path.is_dir():
            self._files = sorted(p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self._files:
                raise RecordingError(f"{self.path}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
            self.fps, self.count = folder_fps, len(self._files)
        elif self.path.exists():
            self._check_video()
            self._video = cv2.VideoCapture(str(self.path))
            if not self._video.isOpened():
                raise RecordingError(f"{self.path}: OpenCV cannot open this file as a video")
            fps = self._video.get(cv2.CAP_PROP_FPS)
            self.fps = fps if np.isfinite(fps) and 0.1 <= fps <= 1000 else DEFAULT_FOLDER_FPS
            count = int(self._video.get(cv2.CAP_PROP_FRAME_COUNT))
            self.count = count if count > 0 else None  # unknown for some containers: read to the end
        else:
            raise RecordingError(f"{self.path}: no such video file or image folder")

    def _check_video(self) -> None:
        """The video is a regular file (OpenCV streams it: any size); RecordingError naming it otherwise."""
        try:
            check_regular(self.path, None, "video")
        except FileRefused as exc:
            raise RecordingError(str(exc)) from None

    @property
    def position(self) -> int:
        """Index of the frame ``next`` or ``skip`` takes: frames read, refused and skipped so far."""
        return self.read + self.skipped + sum(self.refused.values())

    def skip(self) -> None:
        """Pass over the next frame unread (a video frame grabbed, not decoded); ``ended`` at the end."""
        if self._video is not None:
            self.ended = not self._video.grab()
        else:
            self.ended = self.position >= len(self._files)
        self.skipped += not self.ended

    def next(self) -> np.ndarray | None:
        """The next frame, or None when it is refused or the recording has ended (``ended``)."""
        image = self._next_video() if self._video is not None else self._next_file()
        if image is None:
            return None
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if image.ndim != 3 or image.shape[2] not in (3, 4) or image.dtype != np.uint8:
            return self._refuse("not_8bit_colour")
        if image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        if self.expect_wh is not None and (image.shape[1], image.shape[0]) != tuple(self.expect_wh):
            return self._refuse("wrong_size")
        self.read += 1
        return image

    def _next_video(self) -> np.ndarray | None:
        ok, image = self._video.read()
        self.ended = not ok
        return image if ok else None

    def _next_file(self) -> np.ndarray | None:
        index = self.position
        if index >= len(self._files):
            self.ended = True
            return None
        path = self._files[index]
        try:
            data = np.frombuffer(read_bounded(path, MAX_IMAGE_BYTES, "image"), dtype=np.uint8)
            wh = image_size(data[:65536].tobytes())
            if wh is None:
                return self._refuse("unreadable")
            if wh[0] * wh[1] > MAX_IMAGE_PIXELS:
                return self._refuse("too_large")
            if not complete(data[-12:].tobytes()):
                return self._refuse("truncated")
            image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        except FileTooLarge:
            return self._refuse("too_large")
        except (OSError, cv2.error):  # FileRefused too: a FIFO, a device, a directory named *.png
            image = None
        return image if image is not None else self._refuse("unreadable")

    def _refuse(self, reason: str) -> None:
        self.refused[reason] += 1
        return None

    def close(self) -> None:
        if self._video is not None:
            self._video.release()


def complete(tail: bytes) -> bool:
    """Whether a PNG or JPEG file ends as one must (IEND chunk, EOI marker): a truncated file is
    refused before the decoder, which would print its complaints or return half an image."""
    return tail.endswith(b"IEND\xaeB`\x82") or tail.endswith(b"\xff\xd9")


def image_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header (the first bytes of the file); None if neither."""
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and len(head) >= 24:
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if head[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 <= len(head):  # JPEG: walk the segments to the first start-of-frame
        if head[i] != 0xFF:
            return None
        marker, length = head[i + 1], int.from_bytes(head[i + 2:i + 4], "big")
        if marker in _JPEG_SOF:
            return int.from_bytes(head[i + 7:i + 9], "big"), int.from_bytes(head[i + 5:i + 7], "big")
        i += 2 + length
    return None
