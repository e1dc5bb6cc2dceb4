"""An RSU's CPMs under the generation rules, segmented to the MTU (pure; RSU ``--cpm-rules``).

``CpmSender.messages(msg, t_ns)`` turns one generation event (the RSU pipeline's object list)
into the CPMs to send: none (too soon after the last one, or nothing to include and a CPM
sent less than T_GenCpmMax ago), one, or up to eight segments. Which objects go is
``rsu_service.cpm_rules``; the bytes are the codec's (``encode``: an ObjectList -> UPER CPM,
``schemas.list_wire.encode_list``), each segment's ``segmentationInfo`` set here.

Segmentation (ETSI TS 103 324 V2.1.1 §6.1.3.1, as open implementations quote it): a CPM
is at most ``MTU_CPM = MTU_AL - HD_CPM - HD_NT`` bytes; when the selected objects do not fit,
the generation event's objects are split over several CPMs, each a complete, independently
interpretable message with the same ``referenceTime`` and ``segmentationInfo`` (``totalMsgNo``,
``thisMsgNo``, both 1..8, ASN.1 ``MessageSegmentationInfo``) in its management container. The
default MTU, 1100 bytes, is the segmentation threshold of the ETSI CPM simulation study
(TR 103 562 V2.1.1 §5.5, as quoted there); ``RsuConfig.cpm_mtu_bytes`` sets it. Objects that
would need a ninth segment are not sent in this event and stay due (not committed).

The OBU takes each segment on its own, as the standard means it (no reassembly buffer, no
timeout; a lost segment loses its own objects only): each segment decodes to an ObjectList of
its objects with the event's times and its own sequence number (a CPM carries none:
``schemas.cpm.sequence`` makes it of ``referenceTime`` and ``thisMsgNo``, so no segment is taken
for a duplicate of another).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from schemas import cpm
from schemas import standard_wire as sw
from schemas.messages import ObjectList

from rsu_service.cpm_rules import CpmInclusion, CpmRulesConfig

DEFAULT_MTU_BYTES = 1100  # TR 103 562 V2.1.1 §5.5: the segmentation threshold of ETSI's CPM simulations
MAX_SEGMENTS = 8  # MessageSegmentationInfo: totalMsgNo, thisMsgNo INTEGER (1..8)
SEGMENT_MARGIN_BYTES = 2  # segmentationInfo: 7 bits


def with_segment_info(data: bytes, this_no: int, total_no: int) -> bytes:
    """The UPER CPM ``data`` with ``segmentationInfo`` {totalMsgNo, thisMsgNo} in its management container."""
    spec = sw.compiled(cpm.ASN1_FILE)
    message = sw.asn1_decode(spec, "CollectivePerceptionMessage", data, "cpm")
    message["payload"]["managementContainer"]["segmentationInfo"] = {"totalMsgNo": total_no, "thisMsgNo": this_no}
    return sw.asn1_encode(spec, "CollectivePerceptionMessage", message, "cpm")


def segment_info(data: bytes) -> tuple[int, int] | None:
    """(thisMsgNo, totalMsgNo) of a UPER CPM; None when it is not segmented."""
    spec = sw.compiled(cpm.ASN1_FILE)
    info = sw.asn1_decode(spec, "CollectivePerceptionMessage", data, "cpm")["payload"]["managementContainer"].get(
        "segmentationInfo")
    return None if info is None else (info["thisMsgNo"], info["totalMsgNo"])


class CpmSender:
    """One RSU's CPM generation: rules (``CpmInclusion``), segmentation, sequence numbers."""

    def __init__(self, encode: Callable[[ObjectList], bytes | None], mtu_bytes: int = DEFAULT_MTU_BYTES,
                 rules: CpmRulesConfig = CpmRulesConfig()):
        self.encode = encode
        self.mtu_bytes = mtu_bytes
        self.inclusion = CpmInclusion(rules)
        self.segmented = 0  # generation events split over several CPMs
        self.overflow = 0  # objects left for a later event: past MAX_SEGMENTS segments

    def messages(self, msg: ObjectList, t_ns: int) -> list[bytes]:
        """The CPMs of one generation event at ``t_ns`` (RSU monotonic ns): ``msg``'s objects that
        the rules include, one CPM or up to MAX_SEGMENTS segments of at most ``mtu_bytes`` each."""
        c = sw.columns_of(msg.objects)
        xy, vxy = np.column_stack([c["x"], c["y"]]), np.column_stack([c["vx"], c["vy"]])
        ids = c["id"].astype(np.int64)
        selection = self.inclusion.select(t_ns, ids, xy, vxy, c["yaw"], c["cls"])
        if not selection.send:
            self.inclusion.commit(t_ns, ids, xy, vxy, c["yaw"], None)
            return []
        out, sent = self._segments(msg, selection.indices)
        self.inclusion.commit(t_ns, ids, xy, vxy, c["yaw"], sent if out else None)
        return out

    def _segments(self, msg: ObjectList, rows: np.ndarray) -> tuple[list[bytes], np.ndarray]:
        """(CPMs, rows sent) of the objects at ``rows``: one CPM if it fits the MTU, else segments."""
        whole = self._encode(msg, rows)
        if whole is None:
            return [], rows[:0]
        if len(whole) <= self.mtu_bytes or len(rows) <= 1:
            return [whole], rows
        empty = len(self._encode(msg, rows[:0]) or b"")
        per_object = (len(whole) - empty) / len(rows)  # mean encoded bytes per object
        per_segment = max(int((self.mtu_bytes - empty - SEGMENT_MARGIN_BYTES) // per_object), 1)
        while True:
            chunks = [rows[i:i + per_segment] for i in range(0, len(rows), per_segment)][:MAX_SEGMENTS]
            parts = [self._encode(msg, chunk) for chunk in chunks]
            parts = [with_segment_info(p, k + 1, len(parts)) for k, p in enumerate(parts)]
            if per_segment == 1 or max(map(len, parts)) <= self.mtu_bytes:
                break
            per_segment -= 1  # an object larger than the mean pushed a segment over: one fewer each
        sent = np.concatenate(chunks)
        self.overflow += len(rows) - len(sent)
        self.segmented += 1
        return parts, sent

    def _encode(self, msg: ObjectList, rows: np.ndarray) -> bytes | None:
        """The codec's CPM of ``msg`` with the objects at ``rows`` only."""
        objects = msg.objects
        subset = type(objects)(objects.codes[rows], objects.fused)  # (trusted: rows of valid codes)
        return self.encode(msg.model_copy(update={"objects": subset}))
