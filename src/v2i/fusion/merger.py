"""Saravanan et al.'s asynchronous late-fusion merger (Section II-F).

When an RSU object overlaps an on-board object (BEV IoU >= threshold) the RSU
instance is removed; objects that do not overlap are concatenated unfiltered.
"""

from __future__ import annotations

import numpy as np

from v2i.fusion.geometry import bev_boxes, bev_iou_matrix
from v2i.core.objects import ObjectArray


def iou_merge(vehicle: ObjectArray, rsu: ObjectArray, iou_threshold: float = 0.1) -> ObjectArray:
    """Own objects plus the RSU objects that overlap none of them (same frame and time)."""
    if not len(rsu):
        return vehicle
    iou = bev_iou_matrix(bev_boxes(rsu), bev_boxes(vehicle))  # (N_rsu, N_vehicle)
    duplicate = (iou >= iou_threshold).any(axis=1) if len(vehicle) else np.zeros(len(rsu), bool)
    return ObjectArray.concat([vehicle, rsu.take(~duplicate)])
