"""Wire messages of image-level fusion (ROIF, Maqsud's thesis): RSU features down, OBU boxes out.

- ``RsuImageFeatures`` (RSU -> vehicles, ``v2x/rsu/{rsu_id}/image_features``): one camera
  frame's detection boxes and the ORB keypoints + descriptors inside them, so that the OBU can
  fuse its own camera's boxes into the RSU's view without the RSU's image.
- ``ImageFusedBoxes`` (OBU output, ``v2x/obu/{vehicle_id}/image_objects``): one OBU camera
  frame's fused boxes (RSU view, or the ego view when no RSU frame paired), the tracks, and what
  a monitor needs to score it (the OBU's boxes and how each was mapped, the RSU's boxes).

Arrays travel as columns of little-endian bytes (``<f4`` coordinates and scores, ``u1``
classes, ``<u2`` indices, descriptors 32 bytes a keypoint), never as per-point objects: a
1000-keypoint frame is ~42 kB and decodes with ``np.frombuffer``. The models hold the bytes, so
``decode(encode(m)) == m`` exactly; ``view()`` / ``arrays()`` give numpy arrays. Every column is
checked on construction (length, finite, in the image, indices in range) with an error that
names it; the codec turns that into an ``InvalidMessage``.
"""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import Field, Strict, model_validator

from schemas.classes import ObjectClass
from schemas.messages import SCHEMA_VERSION, Count, Message, NodeId, SchemaVersion, Seq, TimeNs

MAX_BOXES = 256  # boxes per frame
MAX_KEYPOINTS = 4096  # keypoints per frame (an RSU caps its ORB well below: --image-features-max, 1000)
DESCRIPTOR_BYTES = 32
MAX_IMAGE_PX = 8192  # image width / height
F4, U1, U2, I2, U4 = (np.dtype(t) for t in ("<f4", "u1", "<u2", "<i2", "<u4"))
N_CLASSES = len(ObjectClass)

ImagePx = Annotated[int, Field(ge=1, le=MAX_IMAGE_PX)]
BoxCount = Annotated[int, Field(ge=0, le=MAX_BOXES)]
Column = Annotated[bytes, Strict(), Field(max_length=MAX_KEYPOINTS * DESCRIPTOR_BYTES)]


def column(buf: bytes, dtype: np.dtype, n: int, width: int, name: str) -> np.ndarray:
    """(n, width) array of a byte column (ValueError naming it when its length is not n * width items)."""
    expected = n * width * dtype.itemsize
    if len(buf) != expected:
        raise ValueError(f"{name}: {len(buf)} bytes, expected {expected} ({n} x {width} x {dtype.str})")
    return np.frombuffer(buf, dtype=dtype).reshape(n, width)


def to_bytes(values, dtype: np.dtype) -> bytes:
    """Little-endian bytes of an array in ``dtype``."""
    return np.ascontiguousarray(np.asarray(values), dtype=dtype).tobytes()


def _first_bad(ok: np.ndarray) -> int | None:
    ok = np.asarray(ok, bool)
    bad = np.flatnonzero(~ok.reshape(len(ok), -1).all(axis=1)) if ok.size else ()
    return int(bad[0]) if len(bad) else None


class BoxColumns(Message):
    """N image boxes: ``xyxy`` (N, 4) ``<f4`` [x1, y1, x2, y2] px, ``score`` (N,) ``<f4`` in [0, 1],
    ``cls`` (N,) ``u1`` ObjectClass codes. Boxes are finite and non-empty (x2 > x1, y2 > y1)."""

    TYPE: ClassVar[str] = "box_columns"
    n: BoxCount = 0
    xyxy: Column = b""
    score: Column = b""
    cls: Column = b""

    @model_validator(mode="after")
    def _valid(self) -> BoxColumns:
        xyxy, score, cls = self.arrays()
        for name, ok in (("xyxy: not finite", np.isfinite(xyxy)),
                         ("xyxy: empty box (x2 <= x1 or y2 <= y1)", (xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1])),
                         ("score: not a finite number in [0, 1]", np.isfinite(score) & (score >= 0) & (score <= 1)),
                         (f"cls: not an object class code 0..{N_CLASSES - 1}", cls < N_CLASSES)):
            i = _first_bad(ok)
            if i is not None:
                raise ValueError(f"box {i} {name}")
        return self

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xyxy (N, 4) float64, score (N,) float64, cls (N,) int64)."""
        return (column(self.xyxy, F4, self.n, 4, "xyxy").astype(float),
                column(self.score, F4, self.n, 1, "score").ravel().astype(float),
                column(self.cls, U1, self.n, 1, "cls").ravel().astype(np.int64))

    def outside(self, width: int, height: int) -> int | None:
        """The first box not inside [0, width] x [0, height], or None."""
        xyxy = self.arrays()[0]
        return _first_bad((xyxy[:, :2] >= 0) & (xyxy[:, 2:] <= [width, height]))

    @classmethod
    def of(cls, xyxy, score, classes) -> BoxColumns:
        xyxy = np.asarray(xyxy, float).reshape(-1, 4)
        return cls(n=len(xyxy), xyxy=to_bytes(xyxy, F4), score=to_bytes(np.clip(score, 0.0, 1.0), F4),
                   cls=to_bytes(classes, U1))


class RsuImageFeatures(Message):
    """RSU -> vehicles on ``v2x/rsu/{rsu_id}/image_features``: one camera frame for ROIF.

    ``t_ns``: the frame's capture time (RSU clock). ``boxes``: the detections (inside the image).
    ``n_keypoints`` = K ORB keypoints found inside the boxes: ``keypoints`` (K, 2) ``<f4`` [u, v] px
    inside the image, ``descriptors`` (K, 32) bytes, ``keypoint_box`` (K,) ``<u2`` the box each
    keypoint lies in (< boxes.n).
    """

    TYPE: ClassVar[str] = "rsu_image_features"
    schema_version: SchemaVersion = SCHEMA_VERSION
    rsu_id: NodeId
    seq: Seq
    t_ns: TimeNs
    image_width: ImagePx
    image_height: ImagePx
    boxes: BoxColumns = BoxColumns()
    n_keypoints: Annotated[int, Field(ge=0, le=MAX_KEYPOINTS)] = 0
    keypoints: Column = b""
    descriptors: Column = b""
    keypoint_box: Column = b""

    @model_validator(mode="after")
    def _valid(self) -> RsuImageFeatures:
        box = self.boxes.outside(self.image_width, self.image_height)
        if box is not None:
            raise ValueError(f"boxes: box {box} is not inside the {self.image_width} x {self.image_height} image")
        k = self.n_keypoints
        kp = column(self.keypoints, F4, k, 2, "keypoints")
        column(self.descriptors, U1, k, DESCRIPTOR_BYTES, "descriptors")
        index = column(self.keypoint_box, U2, k, 1, "keypoint_box").ravel()
        i = _first_bad(np.isfinite(kp) & (kp >= 0) & (kp <= [self.image_width, self.image_height]))
        if i is not None:
            raise ValueError(f"keypoints: keypoint {i} {kp[i].tolist()} is not a finite point inside the image")
        i = _first_bad(index < self.boxes.n)
        if i is not None:
            raise ValueError(f"keypoint_box: keypoint {i} names box {int(index[i])}, the frame has {self.boxes.n}")
        return self

    @classmethod
    def from_view(cls, rsu_id: str, seq: int, t_ns: int, view) -> RsuImageFeatures:
        """The message of a ``ViewFeatures`` (keypoints in no box are not sent)."""
        keep = (view.box_index >= 0) & (view.box_index < len(view.boxes))
        return cls(rsu_id=rsu_id, seq=seq, t_ns=t_ns, image_width=view.image_wh[0], image_height=view.image_wh[1],
                   boxes=BoxColumns.of(*view.detections), n_keypoints=int(keep.sum()),
                   keypoints=to_bytes(view.keypoints[keep], F4), descriptors=to_bytes(view.descriptors[keep], U1),
                   keypoint_box=to_bytes(view.box_index[keep], U2))


class ImageFusedBoxes(Message):
    """OBU output on ``v2x/obu/{vehicle_id}/image_objects``: one ego camera frame after ROIF.

    ``t_ns``: the ego frame's capture time (OBU clock). ``view``: the image the ``fused`` boxes
    are in (``image_width`` x ``image_height``): ``rsu`` when an RSU frame paired (``rsu_*``: its
    id, seq, capture time on the RSU clock and on the OBU's), ``ego`` when none did (the OBU's
    own boxes). ``fused_sources`` (F,) ``u1`` bit 1 RSU / bit 2 OBU, ``fused_rsu_index`` /
    ``fused_obu_index`` (F,) ``<i2`` the ``rsu`` / ``obu`` rows each came from (-1: none).
    ``tracks`` (RSU view) with ``track_ids`` (T,) ``<u4``. ``obu``: the OBU's boxes in its own
    image, ``obu_mapping`` (M,) ``u1`` 0 not mapped / 1 frame homography / 2 own transform,
    ``obu_mapped`` (M, 4) ``<f4`` in the RSU view (NaN rows: not mapped), ``obu_transform``
    (M, 9) ``<f4`` (row-major 3 x 3, NaN: none), ``obu_inlier_error_px`` (M,) ``<f4``. ``rsu``: the
    paired RSU frame's boxes. ``status``: the frame homography's (``v2i.fusion.roif``).
    """

    TYPE: ClassVar[str] = "image_fused_boxes"
    schema_version: SchemaVersion = SCHEMA_VERSION
    vehicle_id: NodeId
    seq: Seq
    t_ns: TimeNs
    publish_time_ns: TimeNs
    view: Literal["rsu", "ego"]
    image_width: ImagePx
    image_height: ImagePx
    rsu_id: NodeId | None = None
    rsu_seq: Seq | None = None
    rsu_t_ns: TimeNs | None = None
    rsu_t_obu_ns: TimeNs | None = None
    status: Annotated[str, Field(max_length=32)] = ""
    keypoints_obu: Count = 0
    keypoints_rsu: Count = 0
    matches: Count = 0
    inliers: Count = 0
    frame_inlier_error_px: Annotated[float | None, Field(ge=0, allow_inf_nan=False)] = None
    fused: BoxColumns = BoxColumns()
    fused_sources: Column = b""
    fused_rsu_index: Column = b""
    fused_obu_index: Column = b""
    tracks: BoxColumns = BoxColumns()
    track_ids: Column = b""
    obu: BoxColumns = BoxColumns()
    obu_mapping: Column = b""
    obu_mapped: Column = b""
    obu_transform: Column = b""
    obu_inlier_error_px: Column = b""
    rsu: BoxColumns = BoxColumns()

    @model_validator(mode="after")
    def _valid(self) -> ImageFusedBoxes:
        if self.publish_time_ns < self.t_ns:
            raise ValueError("publish_time_ns is before t_ns (same OBU clock)")
        if (self.view == "rsu") != (self.rsu_id is not None and self.rsu_seq is not None and self.rsu_t_ns is not None):
            raise ValueError("rsu_id, rsu_seq and rsu_t_ns are given exactly when view is 'rsu'")
        f, m = self.fused.n, self.obu.n
        column(self.fused_sources, U1, f, 1, "fused_sources")
        for name, n_rows in (("fused_rsu_index", self.rsu.n), ("fused_obu_index", m)):
            index = column(getattr(self, name), I2, f, 1, name).ravel()
            i = _first_bad((index >= -1) & (index < n_rows))
            if i is not None:
                raise ValueError(f"{name}: row {i} names {int(index[i])}, out of -1..{n_rows - 1}")
        column(self.track_ids, U4, self.tracks.n, 1, "track_ids")
        mapping = column(self.obu_mapping, U1, m, 1, "obu_mapping").ravel()
        if _first_bad(mapping <= 2) is not None:
            raise ValueError("obu_mapping: codes are 0, 1, 2")
        column(self.obu_mapped, F4, m, 4, "obu_mapped")
        column(self.obu_transform, F4, m, 9, "obu_transform")
        column(self.obu_inlier_error_px, F4, m, 1, "obu_inlier_error_px")
        return self
