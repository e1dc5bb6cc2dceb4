"""``RunWriter``: recorded samples into an MCAP file (``mcap`` library), raw plus derived channels.

One raw channel per (side, key expression, kind, signed or not), topic ``/<side>/<key>`` (a
second kind on the same key gets ``/<side>/<key>~<kind label>``, e.g. ``~signed-object_list``),
with the channel metadata ``side``, ``key``, ``kind`` and ``signed`` (``true`` / ``false``) that
``v2i replay`` reads; a signed sample is written as received, envelope included, and its derived
message is made from the payload inside; the kinds, encodings and derived channels are described in
``v2i.telemetry.mcap_channels``. A message's ``log_time`` is its receive time and ``publish_time``
the sender's publish stamp where the message has one (else the receive time), both ns.

Bounded: a payload over ``derive_max_bytes``, or one that does not decode, is still written raw,
but no derived message is made; both are counted in ``skipped`` by reason. The file is chunked
(zstd) and ``close()`` writes the summary and index, so a recording stopped by Ctrl-C / SIGTERM
is a valid MCAP. Not thread-safe: one thread writes (``v2i.telemetry.recorder`` has a queue in front).

Crash-safe: whatever stops it, the file is a complete MCAP or a valid MCAP *prefix* (whole
records, no summary), which ``v2i.telemetry.mcap_reader`` reads back (``Recording.closed`` False).
The mcap ``Writer`` writes through ``_FileSink``: unbuffered (``os.write`` until every byte is
out, so a process killed by SIGKILL leaves in the file all that was written, and ``tell()`` is
the count of bytes really written), its end after each whole call remembered (``commit``). A
write that fails (a full disk, an I/O error) cuts the file back to that end (``rollback``), and
the writer refuses every later call (its ``Writer`` may hold half a chunk): ``failed`` says why.
``flush()`` ends the chunk in progress and writes it, so a kill loses at most what came since the
last flush (``v2i.telemetry.recorder`` flushes every ``FLUSH_S``); a chunk of ``CHUNK_BYTES`` is written
without waiting.
"""

from __future__ import annotations

import json
import os
from collections import Counter
from pathlib import Path

from mcap.writer import CompressionType, Writer

from schemas.codec import CodecError, decode
from schemas.messages import Message
from v2i.security.envelope import unwrap

from v2i.telemetry import mcap_channels as mc

DERIVE_MAX_BYTES = 256 * 1024  # larger payloads are recorded raw only
CHUNK_BYTES = 1 << 20
LIBRARY = "v2i record"


def publish_stamp(msg: Message | None) -> int | None:
    """The sender's publish stamp of a decoded message (ns, its clock), where it has one."""
    if msg is None:
        return None
    header = getattr(msg, "header", None)
    for holder in (header, msg):
        stamp = getattr(holder, "publish_time_ns", None) if holder is not None else None
        if isinstance(stamp, int):
            return stamp
    stamp = getattr(msg, "t_ns", None)
    return stamp if isinstance(stamp, int) else None


class _FileSink:
    """The file under the mcap ``Writer``: every write whole and unbuffered, its length known;
    ``commit()`` marks the end of whole records, ``rollback()`` cuts the file back to it."""

    def __init__(self, path: str | Path):
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self.position = 0  # bytes written
        self.committed = 0  # bytes that end with a whole record

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            written = os.write(self._fd, view)
            view = view[written:]
            self.position += written
        return len(data)

    def tell(self) -> int:
        return self.position

    def flush(self) -> None:
        """Nothing is buffered here."""

    def commit(self) -> None:
        self.committed = self.position

    def rollback(self) -> None:
        """Cut off what was written since the last commit (a record cut short, its space freed)."""
        os.ftruncate(self._fd, self.committed)
        os.lseek(self._fd, self.committed, os.SEEK_SET)
        self.position = self.committed

    def close(self) -> None:
        os.close(self._fd)


class RunWriter:
    """Writes samples to ``path`` until ``close()``; after a failed write, ``failed`` holds the
    error and every call raises it again (the file keeps what was written before)."""

    def __init__(self, path: str | Path, derive_max_bytes: int = DERIVE_MAX_BYTES):
        self._sink = _FileSink(path)
        self._writer = Writer(self._sink, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self.failed: OSError | None = None
        self.derive_max_bytes = derive_max_bytes
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[tuple, int] = {}
        self._topics: set[str] = set()
        self._topic_of: dict[tuple, str] = {}
        self._sequence = Counter()
        self.messages = 0  # raw messages written
        self.bytes = 0  # raw payload bytes written
        self.derived = 0
        self.skipped: Counter = Counter()  # derived messages not made, by reason
        self.closed = False
        try:
            self._guarded(self._writer.start, profile="", library=LIBRARY)
        except OSError:
            self._sink.close()
            raise

    # ------------------------------------------------------------------ public
    def write(self, side: str, key: str, payload: bytes, log_time_ns: int) -> mc.Kind:
        """Record one received sample (raw, and its derived message when it can be made);
        OSError when the file cannot take it (then ``failed``)."""
        kind = mc.classify(key, payload)
        msg = self._decoded(kind, payload)
        publish_ns = publish_stamp(msg) or log_time_ns
        self._guarded(self._write, side, key, kind, payload, msg, log_time_ns, publish_ns)
        return kind

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """An MCAP metadata record (e.g. the run's spec as ``run``); values must be strings."""
        self._guarded(self._writer.add_metadata, name, {k: str(v) for k, v in data.items()})

    def flush(self) -> None:
        """Write the chunk in progress now (a process killed later keeps it)."""
        self._guarded(self._writer.flush)

    def close(self) -> None:
        """Write the summary and index and close the file (idempotent). OSError when the summary
        could not be written: the file then ends with the last whole chunk, without a summary."""
        if self.closed:
            return
        self.closed = True
        try:
            if self.failed is None:
                self._guarded(self._writer.finish)
        finally:
            self._sink.close()

    @property
    def file_bytes(self) -> int:
        """Bytes in the file that end with a whole record."""
        return self._sink.committed

    # ------------------------------------------------------------------ internals
    def _guarded(self, call, *args, **kwargs) -> None:
        """``call`` on the mcap writer, the file cut back to its last whole record if it fails."""
        if self.failed is not None:
            raise self.failed
        try:
            call(*args, **kwargs)
        except OSError as exc:
            self.failed = exc
            self._sink.rollback()
            raise
        self._sink.commit()

    def _write(self, side: str, key: str, kind: mc.Kind, payload: bytes, msg: Message | None, log_time_ns: int,
               publish_ns: int) -> None:
        topic = self._raw_topic(side, key, kind)
        self._add(self._raw_channel(side, key, kind, topic), payload, log_time_ns, publish_ns)
        self.messages += 1
        self.bytes += len(payload)
        if msg is not None:
            self._write_derived(topic, msg, log_time_ns, publish_ns)

    def _decoded(self, kind: mc.Kind, payload: bytes) -> Message | None:
        if kind.model is None:
            return None
        if len(payload) > self.derive_max_bytes:
            self.skipped["oversized"] += 1
            return None
        try:
            return decode(unwrap(payload) if kind.signed else payload, kind.model)
        except CodecError as exc:
            self.skipped[f"undecodable_{exc.reason}"] += 1
            return None

    def _write_derived(self, raw_topic: str, msg: Message, log_time_ns: int, publish_ns: int) -> None:
        try:
            schema_name, body = mc.derived_message(msg, log_time_ns)
            data = json.dumps(body, separators=(",", ":")).encode()
        except (ValueError, TypeError) as exc:  # e.g. a value JSON cannot hold
            self.skipped[f"derive_{type(exc).__name__}"] += 1
            return
        topic = mc.derived_topic(raw_topic, msg)
        key = ("derived", topic)
        if key not in self._channels:
            schema_id = self._schema(schema_name, "jsonschema", lambda: mc.derived_schema(schema_name, type(msg)))
            self._channels[key] = self._writer.register_channel(topic, "json", schema_id, {"derived_from": raw_topic})
        self._add(self._channels[key], data, log_time_ns, publish_ns)
        self.derived += 1

    def _raw_topic(self, side: str, key: str, kind: mc.Kind) -> str:
        channel = (side, key, kind.label)
        if channel in self._channels:
            return self._topic_of[channel]
        topic = f"/{side}/{key}"
        if topic in self._topics:
            topic = f"{topic}~{kind.label}"
        return topic

    def _raw_channel(self, side: str, key: str, kind: mc.Kind, topic: str) -> int:
        channel = (side, key, kind.label)
        if channel not in self._channels:
            schema = mc.schema_of(kind)
            schema_id = 0 if schema is None else self._schema(schema[0], schema[1], lambda: schema[2])
            metadata = {"side": side, "key": key, "kind": kind.name, "signed": "true" if kind.signed else "false"}
            self._channels[channel] = self._writer.register_channel(topic, kind.message_encoding, schema_id, metadata)
            self._topics.add(topic)
            self._topic_of[channel] = topic
        return self._channels[channel]

    def _schema(self, name: str, encoding: str, data) -> int:
        if (name, encoding) not in self._schemas:
            self._schemas[(name, encoding)] = self._writer.register_schema(name, encoding, data())
        return self._schemas[(name, encoding)]

    def _add(self, channel_id: int, data: bytes, log_time_ns: int, publish_ns: int) -> None:
        self._sequence[channel_id] += 1
        self._writer.add_message(channel_id, log_time=log_time_ns, data=data, publish_time=publish_ns,
                                 sequence=self._sequence[channel_id])
