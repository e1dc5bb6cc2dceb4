"""The OBU's inbox (pure): one RSU message from its bytes into the pipeline, in one direction.

    envelope -> header -> admission -> body -> pipeline

1. envelope: ``InboundSecurity.open`` checks and removes the signed envelope (a drop is counted as
   ``security_<reason>``; a time reply is never judged fresh or stale);
2. header: the message opened up to its header and counts (``schemas.codec.open_body``,
   ``header_of``, ``object_count``, ``path_point_count``); a CPM or SDSM is decoded whole
   (``schemas.list_wire``: its objects are not apart from its header);
3. admission: ``ObuPipeline.admit_list`` / ``admit_paths`` (``obu_service.admission``), once;
4. body: the objects of an admitted message only (``schemas.codec.from_body``);
5. the pipeline takes the ``AdmittedList`` / ``AdmittedPaths`` as it is (``take_list``,
   ``take_paths``); a time reply goes to ``on_time_reply``.

A codec error at any step is counted by its reason (``CodecError.reason``, in the pipeline's
``rejected``) and ``details`` keeps the first message of each reason. Times are arguments
(``receive_ns``, OBU clock); no Zenoh, no clock. The live node (``obu_service.node``) and the offline
runner (``v2i.offline.runner``) drive the same ``Inbox``: the node with its stage latencies (``verify``,
``decode``, ``ingest``, ``rsu_to_obu``: ``ticks`` and ``latency``), the runner with a ``Memo`` that reads
the bytes of a broadcast once for all its receivers (``v2i.offline.decode_memo.DecodeMemo``).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

from schemas import list_wire
from schemas.list_wire import STANDARD_WIRES  # object lists in a standard encoding
from schemas.codec import (MAX_MESSAGE_BYTES, CodecError, decode, from_body, header_of, object_count, open_body,
                           path_point_count)
from schemas.columns import ObjectColumns
from schemas.keys import rsu_id_or_none
from schemas.messages import Message, ObjectList, ObjectListHeader, PredictionList, TimeReply
from schemas.object_wire import unpack_objects

from obu_service.admission import AdmittedList, AdmittedPaths
from obu_service.inbound_security import InboundSecurity

T = TypeVar("T")
KINDS = ("rsu", "predictions", "time", *STANDARD_WIRES)  # what the inbox takes: every RSU message, all signed


class Outcome(enum.Enum):
    """What became of one message."""

    DROPPED = "dropped"  # its envelope failed (counted as security_<reason>)
    UNREADABLE = "unreadable"  # a codec error (counted by its reason)
    READ = "read"  # read and offered to the pipeline (which admitted it or counted why not)


class Memo(Protocol):
    """How the inbox reads a broadcast once: ``decoded(data, key, read)`` is ``read()``, or its result (or
    its CodecError) for this very ``data`` object and ``key``; ``unpack`` decodes an objects section."""

    def decoded(self, data: bytes, key: Any, read: Callable[[], T]) -> T: ...

    def unpack(self, section: Any, fused: bool) -> ObjectColumns: ...


class StageRecorder(Protocol):
    """Where stage durations go (``v2i.telemetry.latency.StageLatency``)."""

    def observe_ns(self, stage: str, start_ns: int, end_ns: int) -> None: ...


@dataclass
class Opened:
    """An RSU list read up to its header: the header and counts; ``message`` decodes the objects on demand,
    once (a CodecError once too: raised again). A standard encoding's list comes decoded whole."""

    header: ObjectListHeader
    n_objects: int
    n_points: int  # predicted positions (a prediction list)
    body: dict[str, Any] | None  # the opened body (schemas.codec.open_body), None once decoded
    model: type[Message]
    decoded: Message | CodecError | None = None

    def message(self, unpack: Callable[[Any, bool], ObjectColumns] = unpack_objects) -> Message:
        if self.decoded is None:
            try:
                self.decoded = from_body(self.body, self.model, unpack)
            except CodecError as exc:
                self.decoded = exc
            self.body = None
        if isinstance(self.decoded, CodecError):
            raise self.decoded
        return self.decoded


def opened(payload: bytes, kind: str, key_expr: str, max_bytes: int,
           origin: tuple[float, float] | None = None) -> Opened:
    """``payload`` (no envelope) of a ``kind`` list heard on ``key_expr``, read up to its header and
    counts; a standard encoding is decoded whole (its RSU named by the key), placed in the ``map``
    of the site whose WGS84 ``origin`` (lat, lon degrees) is given. CodecError if unreadable."""
    if kind in STANDARD_WIRES:
        msg = list_wire.decode_list(payload, kind, rsu_id_or_none(key_expr), max_bytes, origin)
        return Opened(msg.header, len(msg.objects), 0, None, ObjectList, msg)
    model = PredictionList if kind == "predictions" else ObjectList
    body = open_body(payload, model, max_bytes)
    header, n_objects = header_of(body), object_count(body)
    return Opened(header, n_objects, path_point_count(body) if model is PredictionList else 0, body, model)


class Inbox:
    """One OBU's RSU input (see the module docstring). ``pipeline``: an ``ObuPipeline``; ``security``:
    its ``InboundSecurity``; ``max_bytes``: the largest payload read; ``memo``: reads a broadcast once
    (None: every message read anew, as a live OBU's, each with one receiver); ``details``: reason ->
    the first codec error message (the node's log); ``origin``: the site's WGS84 origin (lat, lon
    degrees), where a standard message (CPM, SDSM) is placed."""

    def __init__(self, pipeline, security: InboundSecurity, max_bytes: int = MAX_MESSAGE_BYTES,
                 memo: Memo | None = None, latency: StageRecorder | None = None,
                 ticks: Callable[[], int] = int, details: dict[str, str] | None = None,
                 origin: tuple[float, float] | None = None):
        """``latency``: where the stage durations go, timed by ``ticks`` (a monotonic ns counter; the
        default ``int`` reads 0: no timing)."""
        self.pipeline, self.security, self.max_bytes, self.memo = pipeline, security, max_bytes, memo
        self.latency, self.ticks = latency, ticks
        self.details = {} if details is None else details
        self.origin = origin

    def take(self, kind: str, key_expr: str, data: bytes, receive_ns: int) -> Outcome:
        """One message of ``kind`` (``KINDS``) heard on ``key_expr`` at ``receive_ns``, as received.
        Stage ``verify``: the envelope."""
        t0_ns = self.ticks()
        payload = self.security.open(data, key_expr, receive_ns, time_reply=kind == "time")
        if self.latency is not None:
            self.latency.observe_ns("verify", t0_ns, self.ticks())
        if payload is None:
            return Outcome.DROPPED
        try:
            if kind == "time":
                self.pipeline.on_time_reply(decode(payload, TimeReply, self.max_bytes), receive_ns, self.security.verified)
            else:
                self._list(kind, key_expr, data, payload, receive_ns)
        except CodecError as exc:
            self.pipeline.reject(exc.reason)
            self.details.setdefault(exc.reason, f"{kind} on {key_expr}: {exc}")
            return Outcome.UNREADABLE
        return Outcome.READ

    def _list(self, kind: str, key_expr: str, data: bytes, payload: bytes, receive_ns: int) -> None:
        """An object or prediction list: header, admission (once), objects, into the pipeline. Stages of an
        object list: ``decode`` (header, admission, objects), ``ingest`` (the pipeline takes it) and
        ``rsu_to_obu`` (RSU publish stamp -> receive, in OBU time through the clock estimate)."""
        t0_ns, memo = self.ticks(), self.memo
        head = (opened(payload, kind, key_expr, self.max_bytes, self.origin) if memo is None else
                memo.decoded(data, (kind, key_expr), lambda: opened(payload, kind, key_expr, self.max_bytes, self.origin)))
        unpack = unpack_objects if memo is None else memo.unpack
        if kind == "predictions":
            state = self.pipeline.admit_paths(head.header, head.n_objects, head.n_points, receive_ns)
            if state is not None:
                self.pipeline.take_paths(AdmittedPaths(head.message(unpack), state, receive_ns))
            return
        state = self.pipeline.admit_list(head.header, head.n_objects, receive_ns)
        if state is None:
            return
        admitted = AdmittedList(head.message(unpack), state, receive_ns)
        t1_ns = self.ticks()
        publish_obu_ns = self.pipeline.take_list(admitted)
        if self.latency is not None:
            self.latency.observe_ns("decode", t0_ns, t1_ns)
            self.latency.observe_ns("ingest", t1_ns, self.ticks())
            if publish_obu_ns is not None:
                self.latency.observe_ns("rsu_to_obu", publish_obu_ns, receive_ns)
