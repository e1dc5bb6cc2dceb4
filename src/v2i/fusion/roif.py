"""ROIF: image-level fusion of an on-board (OBU) and a roadside (RSU) camera (Maqsud's ROIF thesis, Ch. 4-5).

Per frame, with the detections of both cameras (boxes in their own images):

1. ORB keypoints and descriptors, detected only inside the detection boxes of each image
   (a mask; the thesis's Sec. 5.3: features outside the boxes gave false matches, Fig. 6.3):
   ``v2i.fusion.roif_features.ViewFeatures``, computed by each camera's own node (the RSU sends
   its features, never its image); ``roif_fuse`` takes the two views' features.
2. Brute-force Hamming matching (``cv2.BFMatcher(cv2.NORM_HAMMING)``), OBU -> RSU. A match
   is kept when (a) its normalised Hamming distance d = bits / 256 is below
   ``max_distance`` (the thesis keeps "d < 0.5", i.e. < 128 of 256 bits, which is about
   what two unrelated descriptors score: it filters almost nothing, so the default here is
   0.25 = 64 bits), (b) it passes Lowe's ratio test d1 < ``ratio`` d2 against the second
   best, and (c) it is mutual (the RSU descriptor's best OBU match is the same: cross check).
3. Frame homography H (OBU image -> RSU image) by ``cv2.findHomography(..., cv2.RANSAC)`` over
   all matches (the thesis' one H per frame); fewer than ``min_inliers`` RANSAC inliers (or
   too few features / matches before it): no frame homography (``status`` says why).
4. OBU boxes into the RSU view. ``mapping="frame"`` (the thesis): every box through the
   frame's H; none without one. ``mapping="object"`` (default): each box through its own
   transform, fitted by RANSAC to the matches whose OBU keypoint lies in the box and whose
   RSU keypoint lies in the RSU box most of them land in (its corresponding box, the thesis's
   Fig. 6.4), where at least ``min_object_inliers`` agree; a box without one goes through the
   frame's H if ``object_fallback``, else is not mapped. Why: a street of 3-D vehicles at
   different depths is no plane, and one homography maps well only the depth its inliers
   came from (RANSAC's dominant object); one object's visible faces are nearly one plane.
   ``object_model="similarity"`` (default) restricts a box's own homography to scale,
   rotation and translation (4 degrees of freedom, ``cv2.estimateAffinePartial2D``): with the
   8-30 matches one small box yields, a full 8-degree homography extrapolated to the box's
   corners is unstable. Mapping a box: its 4 corners in homogeneous coordinates,
   [u', v', w']^T = H [u, v, 1]^T, (u'/w', v'/w'); the mapped box is the axis-aligned box of
   the 4 mapped corners, clipped to the RSU image (a corner with w' <= 0, behind the
   view, or a box left with no area drops it).
5. IoU of every (RSU, mapped OBU) pair, eq. 5.1-5.5; pairs with IoU >= ``iou_gate`` (0.1)
   may fuse; a one-to-one assignment minimises sum(1 - IoU) (Hungarian: ``v2i.fusion.lsap``).
6. Each assigned pair fuses by confidence-weighted corner averaging, eq. 5.6-5.11; the
   fused confidence is the larger of the two, the class that of the more confident box.
   Unassigned boxes of either side pass through unchanged (OBU boxes mapped), so the
   fused list is in the RSU view; with no OBU box mapped it is the RSU list.

Pure: arrays in, arrays out; no clock, no I/O. Boxes are (N, 4) [x1, y1, x2, y2] px.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from v2i.fusion.association import assign
from v2i.fusion.roif_features import ViewFeatures, view_features

SOURCE_RSU = 1  # bit of a fused box: the RSU camera saw it
SOURCE_OBU = 2  # bit: the OBU camera saw it (mapped into the RSU view)
DESCRIPTOR_BITS = 256  # ORB descriptors are 32 bytes

MAPPED_NONE, MAPPED_FRAME, MAPPED_OWN = 0, 1, 2  # how an OBU box was mapped
# why a frame has no homography
OK, FEW_FEATURES, FEW_MATCHES, FEW_INLIERS = "ok", "few_features", "few_matches", "few_inliers"


@dataclass(frozen=True)
class RoifConfig:
    """ROIF parameters (units in the names); the module docstring says how each is used."""

    orb_features: int = 2000  # ORB keypoints per image at most
    orb_fast_threshold: int = 5  # FAST corner threshold (grey levels); low: vehicle faces are smooth
    orb_patch_px: int = 31  # ORB patchSize = edgeThreshold (px): descriptor footprint
    orb_levels: int = 12  # ORB pyramid levels, scale 1.2 apart: views up to 1.2^(levels - 1) apart in scale match
    max_distance: float = 0.25  # normalised Hamming distance bits / 256 a match must stay below
    ratio: float = 0.8  # Lowe ratio test: best < ratio * second best
    cross_check: bool = True  # keep mutual best matches only
    ransac_reproj_px: float = 4.0  # RANSAC inlier threshold (px, RSU image)
    min_inliers: int = 12  # fewer RANSAC inliers: no frame homography
    mapping: Literal["object", "frame"] = "object"  # each box through its own transform, or all through the frame's
    min_object_inliers: int = 8  # RANSAC inliers a box's own transform needs
    object_model: Literal["similarity", "homography"] = "similarity"  # a box's own transform
    object_fallback: bool = False  # a box without its own transform goes through the frame's H
    iou_gate: float = 0.1  # eq. 5.1-5.5 IoU a (RSU, mapped OBU) pair needs to fuse


@dataclass(frozen=True)
class HomographyFit:
    """H (3, 3) OBU px -> RSU px or None; counts; mean inlier re-projection error (px) or None.

    ``obu_px``, ``rsu_px`` (K, 2): the matched points (after the distance, ratio and cross
    checks); ``inlier`` (K,) bool: RANSAC's inliers among them.
    """

    H: np.ndarray | None
    status: str
    keypoints_obu: int
    keypoints_rsu: int
    matches: int
    inliers: int
    reprojection_px: float | None
    obu_px: np.ndarray
    rsu_px: np.ndarray
    inlier: np.ndarray


@dataclass(frozen=True)
class FusedBoxes:
    """Boxes in the RSU view: xyxy (F, 4) px, scores (F,), cls (F,) int64, sources (F,) bitmask
    (SOURCE_RSU | SOURCE_OBU), rsu_index (F,) / obu_index (F,): the input rows each came from (-1: none)."""

    xyxy: np.ndarray
    scores: np.ndarray
    cls: np.ndarray
    sources: np.ndarray
    rsu_index: np.ndarray
    obu_index: np.ndarray


@dataclass(frozen=True)
class BoxMapping:
    """How each of M OBU boxes reaches the RSU view: ``transform`` (M, 3, 3) (NaN: not mapped),
    ``how`` (M,) MAPPED_NONE / MAPPED_FRAME / MAPPED_OWN, ``inlier_error_px`` (M,) mean
    re-projection error of the RANSAC inliers of its transform (NaN: none), ``rsu_box`` (M,) the
    corresponding RSU box its own transform came from (-1: none)."""

    transform: np.ndarray
    how: np.ndarray
    inlier_error_px: np.ndarray
    rsu_box: np.ndarray

    @classmethod
    def none(cls, m: int) -> BoxMapping:
        return cls(np.full((m, 3, 3), np.nan), np.full(m, MAPPED_NONE, np.int64), np.full(m, np.nan),
                   np.full(m, -1, np.int64))


@dataclass(frozen=True)
class RoifResult:
    """One fused frame: the boxes, every OBU box mapped into the RSU view (M, 4) (NaN rows:
    not mapped or dropped), how each was mapped, and the frame's homography fit."""

    fused: FusedBoxes
    mapped_obu_xyxy: np.ndarray
    mapping: BoxMapping
    fit: HomographyFit

    @property
    def homography(self) -> np.ndarray | None:
        """The frame's homography (3, 3) OBU px -> RSU px, or None."""
        return self.fit.H

    @property
    def mapped(self) -> bool:
        """Whether any OBU box reached the RSU view this frame."""
        return bool(np.any(self.mapping.how != MAPPED_NONE))


def match_descriptors(desc_obu: np.ndarray, desc_rsu: np.ndarray, config: RoifConfig) -> np.ndarray:
    """Matches (K, 2) rows (OBU index, RSU index) passing the distance, ratio and cross checks."""
    if len(desc_obu) < 2 or len(desc_rsu) < 2:
        return np.zeros((0, 2), dtype=int)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
    pairs = [p for p in matcher.knnMatch(desc_obu, desc_rsu, k=2) if len(p) == 2]
    best = np.array([[p[0].queryIdx, p[0].trainIdx] for p in pairs], dtype=int).reshape(-1, 2)
    d1 = np.array([p[0].distance for p in pairs], dtype=float)
    d2 = np.array([p[1].distance for p in pairs], dtype=float)
    keep = (d1 / DESCRIPTOR_BITS < config.max_distance) & (d1 < config.ratio * d2)
    best = best[keep]
    if config.cross_check and len(best):
        back = {m.queryIdx: m.trainIdx for m in matcher.match(desc_rsu, desc_obu)}  # RSU -> OBU best
        best = best[np.array([back.get(r) == o for o, r in best], dtype=bool)]
    return best


def fit_homography(obu: ViewFeatures, rsu: ViewFeatures, config: RoifConfig = RoifConfig()) -> HomographyFit:
    """Steps 2-3 on the features of both views (step 1, ``v2i.fusion.roif_features.view_features``):
    matching, RANSAC homography OBU -> RSU."""
    kp_o, desc_o, kp_r, desc_r = obu.keypoints, obu.descriptors, rsu.keypoints, rsu.descriptors

    def failed(status: str, obu_px=None, rsu_px=None, inlier=None, inliers: int = 0) -> HomographyFit:
        obu_px, rsu_px = (np.zeros((0, 2)) if v is None else v for v in (obu_px, rsu_px))
        inlier = np.zeros(len(obu_px), bool) if inlier is None else inlier
        return HomographyFit(None, status, len(kp_o), len(kp_r), len(obu_px), inliers, None, obu_px, rsu_px, inlier)

    if min(len(kp_o), len(kp_r)) < config.min_inliers:
        return failed(FEW_FEATURES)
    pairs = match_descriptors(desc_o, desc_r, config)
    obu_px, rsu_px = kp_o[pairs[:, 0]], kp_r[pairs[:, 1]]
    if len(pairs) < max(config.min_inliers, 4):
        return failed(FEW_MATCHES, obu_px, rsu_px)
    H, mask = cv2.findHomography(obu_px, rsu_px, cv2.RANSAC, config.ransac_reproj_px)
    inlier = np.zeros(len(pairs), bool) if mask is None else mask.ravel().astype(bool)
    if H is None or inlier.sum() < config.min_inliers:
        return failed(FEW_INLIERS, obu_px, rsu_px, inlier, int(inlier.sum()))
    return HomographyFit(H, OK, len(kp_o), len(kp_r), len(pairs), int(inlier.sum()),
                         inlier_error_px(H, obu_px[inlier], rsu_px[inlier]), obu_px, rsu_px, inlier)


def fit_homography_images(image_obu: np.ndarray, boxes_obu: np.ndarray, image_rsu: np.ndarray, boxes_rsu: np.ndarray,
                          config: RoifConfig = RoifConfig()) -> HomographyFit:
    """Steps 1-3 from the two images (H, W, 3) BGR and their boxes (N, 4) px."""
    return fit_homography(_features(image_obu, boxes_obu, config), _features(image_rsu, boxes_rsu, config), config)


def _features(image: np.ndarray, xyxy: np.ndarray, config: RoifConfig) -> ViewFeatures:
    """Features of an image with boxes only (scores 0, class 0: the fit does not read them)."""
    n = len(np.asarray(xyxy, float).reshape(-1, 4))
    return view_features(image, (xyxy, np.zeros(n), np.zeros(n, np.int64)), config)


def inlier_error_px(H: np.ndarray, obu_px: np.ndarray, rsu_px: np.ndarray) -> float:
    """Mean re-projection error |pi(H p_obu) - p_rsu| (px) of point pairs (K, 2) + (K, 2)."""
    return float(np.linalg.norm(map_points(H, obu_px) - rsu_px, axis=1).mean())


def map_points(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Points (N, 2) px through H (3, 3): (u'/w', v'/w') with [u', v', w'] = H [u, v, 1]."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    return cv2.perspectiveTransform(uv.reshape(-1, 1, 2), H).reshape(-1, 2) if len(uv) else uv


def map_boxes(H: np.ndarray, xyxy: np.ndarray, image_wh: tuple[int, int]) -> np.ndarray:
    """Boxes (N, 4) px through H into an image of size (W, H): axis-aligned box of the 4 mapped
    corners, clipped to the image; NaN rows where a corner maps behind (w' <= 0) or no area is left."""
    xyxy = np.asarray(xyxy, dtype=float).reshape(-1, 4)
    corners = xyxy[:, [[0, 1], [2, 1], [2, 3], [0, 3]]]  # (N, 4, 2): tl, tr, br, bl
    homog = np.concatenate([corners, np.ones(corners.shape[:2] + (1,))], axis=2) @ np.asarray(H, float).T
    w = homog[..., 2]
    ok = np.all(w > 1e-9, axis=1)
    uv = homog[..., :2] / np.where(ok[:, None], w, 1.0)[..., None]
    out = np.column_stack([uv[..., 0].min(1), uv[..., 1].min(1), uv[..., 0].max(1), uv[..., 1].max(1)])
    out = np.clip(out, 0.0, np.array([image_wh[0], image_wh[1], image_wh[0], image_wh[1]], dtype=float))
    ok &= (out[:, 2] > out[:, 0]) & (out[:, 3] > out[:, 1])
    out[~ok] = np.nan
    return out


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU (N, M) of axis-aligned boxes a (N, 4) and b (M, 4), eq. 5.1-5.5:

    x_min,i = max(x_min,a, x_min,b), y_min,i = max(...), x_max,i = min(x_max,a, x_max,b),
    y_max,i = min(...); intersection = 0 when x_min,i >= x_max,i or y_min,i >= y_max,i;
    union = area a + area b - intersection; IoU = intersection / union (0 for an empty union).
    NaN boxes overlap nothing.
    """
    a, b = np.asarray(a, float).reshape(-1, 4), np.asarray(b, float).reshape(-1, 4)
    x1 = np.maximum(a[:, None, 0], b[None, :, 0])  # eq. 5.1
    y1 = np.maximum(a[:, None, 1], b[None, :, 1])  # eq. 5.2
    x2 = np.minimum(a[:, None, 2], b[None, :, 2])  # eq. 5.3
    y2 = np.minimum(a[:, None, 3], b[None, :, 3])  # eq. 5.4
    inter = np.clip(x2 - x1, 0.0, None) * np.clip(y2 - y1, 0.0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter  # eq. 5.5
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0.0, inter / union, 0.0)
    return np.nan_to_num(iou, nan=0.0)


def fuse_pair(xyxy_rsu: np.ndarray, score_rsu: np.ndarray, xyxy_obu: np.ndarray, score_obu: np.ndarray) -> np.ndarray:
    """Confidence-weighted corners (K, 4) of K box pairs (K, 4) + (K, 4), scores (K,), eq. 5.6-5.11:

    x_tl = (x_tl,red w_red + x_tl,green w_green) / (w_red + w_green)   (5.6; y_tl 5.7,
    x_br 5.8, y_br 5.9), red = RSU, green = mapped OBU, w = the detection's confidence;
    width = x_br - x_tl (5.10), height = y_br - y_tl (5.11).
    """
    w_red = np.asarray(score_rsu, float).reshape(-1, 1)
    w_green = np.asarray(score_obu, float).reshape(-1, 1)
    none = (w_red + w_green) <= 0.0  # two zero confidences: plain average
    w_red, w_green = np.where(none, 1.0, w_red), np.where(none, 1.0, w_green)
    total_weight = w_red + w_green
    return (np.asarray(xyxy_rsu, float) * w_red + np.asarray(xyxy_obu, float) * w_green) / total_weight


def fuse_boxes(rsu: tuple[np.ndarray, np.ndarray, np.ndarray], mapped_obu: tuple[np.ndarray, np.ndarray, np.ndarray],
               iou_gate: float = 0.1) -> FusedBoxes:
    """Steps 5-6 on boxes already in the RSU view: (xyxy (N, 4) px, scores (N,), cls (N,)) each;
    NaN OBU rows (not mapped) take part in nothing."""
    xr, sr, cr = _columns(rsu)
    xo, so, co = _columns(mapped_obu)
    pairs = assign(1.0 - iou_matrix(xr, xo), gate=1.0 - iou_gate)  # IoU >= gate <=> 1 - IoU <= 1 - gate
    i_r, i_o, lone_r = pairs.matches[:, 0], pairs.matches[:, 1], pairs.unmatched_a
    lone_o = pairs.unmatched_b[np.isfinite(xo[pairs.unmatched_b]).all(axis=1)]
    obu_wins = so[i_o] > sr[i_r]
    n_pair, n_r, n_o = len(i_r), len(lone_r), len(lone_o)
    return FusedBoxes(
        xyxy=np.vstack([fuse_pair(xr[i_r], sr[i_r], xo[i_o], so[i_o]), xr[lone_r], xo[lone_o]]).reshape(-1, 4),
        scores=np.concatenate([np.maximum(sr[i_r], so[i_o]), sr[lone_r], so[lone_o]]),
        cls=np.concatenate([np.where(obu_wins, co[i_o], cr[i_r]), cr[lone_r], co[lone_o]]).astype(np.int64),
        sources=np.repeat(np.array([SOURCE_RSU | SOURCE_OBU, SOURCE_RSU, SOURCE_OBU], np.int64), [n_pair, n_r, n_o]),
        rsu_index=np.concatenate([i_r, lone_r, np.full(n_o, -1)]).astype(np.int64),
        obu_index=np.concatenate([i_o, np.full(n_r, -1), lone_o]).astype(np.int64),
    )


def _columns(boxes: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xyxy, scores, cls) as (N, 4) float, (N,) float, (N,) int64."""
    xyxy, scores, cls = boxes
    return (np.asarray(xyxy, float).reshape(-1, 4), np.asarray(scores, float).reshape(-1),
            np.asarray(cls, np.int64).reshape(-1))


def _inside(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(K,) bool: points (K, 2) px inside the box [x1, y1, x2, y2] (edges included)."""
    return (points[:, 0] >= box[0]) & (points[:, 0] <= box[2]) & (points[:, 1] >= box[1]) & (points[:, 1] <= box[3])


def _object_transform(obu_px: np.ndarray, rsu_px: np.ndarray, config: RoifConfig) -> tuple[np.ndarray | None, float]:
    """A box's own transform (3, 3) from its matches (K, 2) + (K, 2) and its inliers' mean error
    (px); (None, NaN) below ``min_object_inliers`` inliers."""
    if len(obu_px) < max(config.min_object_inliers, 4):
        return None, float("nan")
    if config.object_model == "similarity":
        a, mask = cv2.estimateAffinePartial2D(obu_px, rsu_px, method=cv2.RANSAC,
                                              ransacReprojThreshold=config.ransac_reproj_px)
        h = None if a is None else np.vstack([a, [0.0, 0.0, 1.0]])
    else:
        h, mask = cv2.findHomography(obu_px, rsu_px, cv2.RANSAC, config.ransac_reproj_px)
    if h is None or mask is None or mask.sum() < config.min_object_inliers:
        return None, float("nan")
    inlier = mask.ravel().astype(bool)
    return h, inlier_error_px(h, obu_px[inlier], rsu_px[inlier])


def box_mapping(fit: HomographyFit, boxes_obu: np.ndarray, boxes_rsu: np.ndarray, config: RoifConfig) -> BoxMapping:
    """Step 4: how each OBU box (M, 4) reaches the RSU view (module docstring); RSU boxes (N, 4)."""
    boxes, rsu_boxes = np.asarray(boxes_obu, float).reshape(-1, 4), np.asarray(boxes_rsu, float).reshape(-1, 4)
    out = BoxMapping.none(len(boxes))
    if fit.H is not None and (config.mapping == "frame" or config.object_fallback):
        out.transform[:], out.how[:], out.inlier_error_px[:] = fit.H, MAPPED_FRAME, fit.reprojection_px
    if config.mapping == "frame" or not len(rsu_boxes) or not len(fit.obu_px):
        return out
    in_rsu = np.stack([_inside(fit.rsu_px, b) for b in rsu_boxes])  # (N, K)
    for j, box in enumerate(boxes):
        sel = _inside(fit.obu_px, box)
        i = int(np.argmax((in_rsu & sel).sum(axis=1)))  # the RSU box most of its matches land in
        h, err = _object_transform(fit.obu_px[sel & in_rsu[i]], fit.rsu_px[sel & in_rsu[i]], config)
        if h is not None:
            out.transform[j], out.how[j], out.inlier_error_px[j], out.rsu_box[j] = h, MAPPED_OWN, err, i
    return out


def roif_fuse(obu: ViewFeatures, rsu: ViewFeatures, config: RoifConfig = RoifConfig()) -> RoifResult:
    """One frame of ROIF, steps 2-6, on the two views' features (boxes, scores, classes, ORB
    keypoints and descriptors inside the boxes): the OBU's computed on board, the RSU's as it
    sent them. Fused boxes are in the RSU view (``rsu.image_wh``)."""
    xo, so, co = obu.detections
    fit = fit_homography(obu, rsu, config)
    mapping = box_mapping(fit, xo, rsu.boxes, config)
    mapped = np.full((len(xo), 4), np.nan)
    for j in np.flatnonzero(mapping.how != MAPPED_NONE):
        mapped[j] = map_boxes(mapping.transform[j], xo[j:j + 1], rsu.image_wh)[0]
    return RoifResult(fuse_boxes(rsu.detections, (mapped, so, co), config.iou_gate), mapped, mapping, fit)


def roif_fuse_images(image_obu: np.ndarray, obu: tuple[np.ndarray, np.ndarray, np.ndarray],
                     image_rsu: np.ndarray, rsu: tuple[np.ndarray, np.ndarray, np.ndarray],
                     config: RoifConfig = RoifConfig()) -> RoifResult:
    """One frame of ROIF, steps 1-6, from both images (H, W, 3) BGR and their detections
    (xyxy (N, 4) px, scores (N,), cls (N,)): both views' features computed here."""
    return roif_fuse(view_features(image_obu, obu, config), view_features(image_rsu, rsu, config), config)
