"""ROIF per frame (Maqsud's ROIF thesis Ch. 5): the one pure object both drivers step.

``v2i eval --fusion roif`` (``v2i.offline.image_fusion``) and the live OBU
(``obu_service.image_fusion``) feed it the same way: per OBU camera frame, the OBU's
``ViewFeatures``, the RSU's paired ``ViewFeatures`` (or None: no RSU frame pairs with this one)
and the frame time; it fuses them (``v2i.fusion.roif.roif_fuse``) and steps the box tracker
(``v2i.fusion.box_tracker``) on the fused boxes, which are in the RSU view.

A frame without an RSU partner has no RSU view to fuse into: its output is the OBU's own boxes
in its own (ego) view, ``view == VIEW_EGO``, and the tracker (RSU view) is stepped with no
detections, so its confirmed tracks coast. Pure: no clock, no I/O; times are arguments.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2i.fusion.box_tracker import BoxTracker, BoxTrackerConfig, BoxTracks
from v2i.fusion.roif import SOURCE_OBU, FusedBoxes, RoifConfig, RoifResult, roif_fuse
from v2i.fusion.roif_features import ViewFeatures

VIEW_RSU, VIEW_EGO = "rsu", "ego"  # the image a frame's output boxes are in


@dataclass(frozen=True)
class RoifFrame:
    """One stepped frame: the inputs, ROIF's result (None without an RSU partner), the confirmed
    tracks (RSU view) and the output boxes (``fused``) in ``view``."""

    t_s: float
    obu: ViewFeatures
    rsu: ViewFeatures | None
    result: RoifResult | None
    tracks: BoxTracks

    @property
    def view(self) -> str:
        return VIEW_EGO if self.result is None else VIEW_RSU

    @property
    def image_wh(self) -> tuple[int, int]:
        """Size (W, H) px of the image the output boxes are in."""
        return self.obu.image_wh if self.rsu is None else self.rsu.image_wh

    @property
    def fused(self) -> FusedBoxes:
        """The output boxes: ROIF's fused list, or the OBU's own boxes (ego view) without a partner."""
        if self.result is not None:
            return self.result.fused
        n = len(self.obu.boxes)
        return FusedBoxes(self.obu.boxes, self.obu.scores, self.obu.cls, np.full(n, SOURCE_OBU, np.int64),
                          np.full(n, -1, np.int64), np.arange(n, dtype=np.int64))


class RoifFramePipeline:
    """ROIF + box tracker; ``step`` once per OBU frame, frame times increasing."""

    def __init__(self, roif: RoifConfig | None = None, tracker: BoxTrackerConfig | None = None):
        self.roif = roif or RoifConfig()
        self.tracker = BoxTracker(tracker or BoxTrackerConfig())
        self.frames = 0
        self.unpaired = 0  # frames stepped without an RSU partner

    def step(self, obu: ViewFeatures, rsu: ViewFeatures | None, t_s: float) -> RoifFrame:
        """Fuse (when ``rsu`` is given) and track one frame at ``t_s`` (s, any epoch, increasing)."""
        self.frames += 1
        if rsu is None:
            self.unpaired += 1
            tracks = self.tracker.step(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64), t_s)
            return RoifFrame(t_s, obu, None, None, tracks)
        result = roif_fuse(obu, rsu, self.roif)
        fused = result.fused
        tracks = self.tracker.step(fused.xyxy, fused.scores, fused.cls, t_s)
        return RoifFrame(t_s, obu, rsu, result, tracks)
