"""Late fusion by non-maximum suppression over the pooled boxes of all sources.

Boxes from the vehicle and from RSUs (same frame and time) are pooled and ranked by
confidence; a box is kept unless it overlaps (BEV IoU >= threshold) a higher-ranked kept
box. The survivors keep their own source bit; a suppressed box ORs its source into the
box that suppressed it, so ``sources`` tells who saw each object.
"""

from __future__ import annotations

import numpy as np

from v2i.fusion.geometry import bev_boxes, bev_iou_matrix
from v2i.core.objects import ObjectArray


def nms_fuse(own: ObjectArray, rsu: ObjectArray, iou_threshold: float = 0.1) -> ObjectArray:
    """Greedy NMS of own + RSU objects by descending confidence (ties: own first)."""
    pool = ObjectArray.concat([own, rsu])
    if not len(pool):
        return pool
    order = np.lexsort((np.arange(len(pool)), -pool.confidence))
    iou = bev_iou_matrix(bev_boxes(pool), bev_boxes(pool))
    keep: list[int] = []
    sources = pool.sources.copy()
    for i in order:
        winners = [k for k in keep if iou[i, k] >= iou_threshold]
        if winners:
            sources[winners[0]] |= pool.sources[i]
        else:
            keep.append(int(i))
    return pool.with_(sources=sources).take(np.sort(keep))
