"""Reading a ``v2i record`` MCAP file back: its sides, samples, metadata and RSU time exchanges.

A recording is untrusted input: it must be a regular file (``v2i.core.files``: not a FIFO or a
device; any size, as it is streamed), it is read once through at open (CRCs checked, records and
chunks at most ``MAX_CHUNK_BYTES`` compressed or not, every message decoded from its chunk), and
anything wrong with it is a ``RecordingError`` (a ``ValueError``) naming the file, never a traceback.

A recording that was not closed (the recorder killed by SIGKILL, its disk full, its summary cut
short) has no usable summary: it is read from the start up to its last whole record
(``v2i.telemetry.mcap_prefix``), ``closed`` is False and ``problem`` says what was found. Its samples
are then gathered and sorted by log time at each pass (no index to merge them by).

Signed samples (``v2i.telemetry.mcap_channels``: channel metadata ``signed``) keep their envelope in
``Sample.payload``; ``Sample.content`` is the message inside, and the time exchanges are read
from it (unchecked: a recording is evidence, not a trust decision).
"""

from __future__ import annotations

import io
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from mcap.reader import SeekingReader
from mcap.records import Channel, Header, Message, Metadata

from schemas.codec import CodecError, decode
from schemas.messages import TimeReply
from v2i.core.files import FileRefused, open_regular
from v2i.security.envelope import unwrap

from v2i.telemetry.mcap_channels import models_by_type
from v2i.telemetry.mcap_prefix import MAGIC, PrefixReader
from v2i.telemetry.time_shift import Exchange

TIME_REPLY = TimeReply.TYPE
MAX_CHUNK_BYTES = 64 << 20  # v2i record writes chunks of ~1 MB


class RecordingError(ValueError):
    """The file is not a readable ``v2i record`` recording."""


def key_matches(pattern: str, key: str) -> bool:
    """True when Zenoh key ``key`` (no wildcards) matches ``pattern``, whose chunks may be ``*``
    (exactly one chunk) or ``**`` (any number of chunks, none included)."""
    return _match(tuple(pattern.split("/")), tuple(key.split("/")))


def _match(pattern: tuple[str, ...], key: tuple[str, ...]) -> bool:
    if not pattern:
        return not key
    if pattern[0] == "**":
        return any(_match(pattern[1:], key[i:]) for i in range(len(key) + 1))
    return bool(key) and pattern[0] in ("*", key[0]) and _match(pattern[1:], key[1:])


@dataclass(frozen=True)
class Sample:
    side: str
    key: str
    kind: str
    log_time_ns: int
    payload: bytes  # as recorded (a signed envelope included)
    signed: bool = False

    @property
    def model(self):
        return models_by_type().get(self.kind)

    @property
    def content(self) -> bytes:
        """The message bytes: a signed sample's payload without its envelope, else ``payload``."""
        return unwrap(self.payload) if self.signed else self.payload


@dataclass(frozen=True)
class RawChannel:
    topic: str
    side: str
    key: str
    kind: str
    signed: bool = False


class Recording:
    """A ``v2i record`` file: ``channels`` (raw ones, by MCAP channel id), ``metadata`` (name -> dict);
    ``closed`` (False: read up to its last whole record, ``problem`` says why)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.closed, self.problem = True, None
        with self._reader() as reader:
            summary = self._summary(reader)
            if summary is not None:
                big = [c.uncompressed_size for c in summary.chunk_indexes if c.uncompressed_size > MAX_CHUNK_BYTES]
                if big:
                    raise RecordingError(f"{self.path}: a chunk of {big[0]} bytes (at most {MAX_CHUNK_BYTES})")
                self._set_channels(summary.channels)
                self.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
                self.message_counts = dict(summary.statistics.channel_message_counts) if summary.statistics else {}
                for _ in reader.iter_messages():  # every chunk decompressed and checked once, here
                    pass
                self.readable_bytes = self.path.stat().st_size
        if summary is None:
            self._read_prefix()

    def _summary(self, reader: SeekingReader):
        """The file's summary, or None (``closed`` False, ``problem`` set) when it has none that reads."""
        summary = None
        with self._open() as f:
            f.seek(max(f.seek(0, io.SEEK_END) - len(MAGIC), 0))
            ends_with_magic = f.read() == MAGIC
        if not ends_with_magic:
            self.problem = "it has no footer"
        else:
            try:
                summary = reader.get_summary()
            except Exception as exc:  # noqa: BLE001 - a damaged footer or summary: read the records instead
                self.problem = f"its footer or summary cannot be read ({type(exc).__name__}: {exc})"
            else:
                self.problem = None if summary is not None else "it has no summary"
        self.closed = summary is not None
        return summary

    def _read_prefix(self) -> None:
        """Channels, metadata and counts of a file without summary, read from its records."""
        channels: dict[int, Channel] = {}
        self.metadata, self.message_counts = {}, defaultdict(int)
        with self._prefix() as prefix:
            records = prefix.records()
            first = next(records, None)
            if first is None and prefix.ended_by:
                raise RecordingError(f"{self.path}: holds no whole record ({self.problem}; {prefix.ended_by}): "
                                     "the recorder stopped as it started")
            if not isinstance(first, Header):
                raise RecordingError(f"{self.path}: not a readable v2i recording (no MCAP header)")
            for record in records:
                if isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Metadata):
                    self.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Message):
                    self.message_counts[record.channel_id] += 1
        self._set_channels(channels)
        self.readable_bytes = prefix.end_bytes
        raw = sum(n for cid, n in self.message_counts.items() if cid in self.channels)  # derived ones not
        self.problem = (f"{self.problem}; {prefix.ended_by}: read {raw} messages in its first {self.readable_bytes} "
                        f"of {prefix.size_bytes} bytes")

    def _set_channels(self, channels: dict[int, Channel]) -> None:
        self.channels = {cid: RawChannel(str(c.topic), str(c.metadata["side"]), str(c.metadata["key"]),
                                         str(c.metadata["kind"]), c.metadata.get("signed") == "true")
                         for cid, c in channels.items() if "side" in c.metadata}

    @contextmanager
    def _reader(self) -> Iterator[SeekingReader]:
        """A reader of the file whose every failure is a ``RecordingError`` naming it."""
        with self._named_errors(), self._open() as f:
            yield SeekingReader(f, validate_crcs=True, record_size_limit=MAX_CHUNK_BYTES)

    @contextmanager
    def _prefix(self) -> Iterator[PrefixReader]:
        """A prefix reader of the file (``v2i.telemetry.mcap_prefix``); failures as in ``_reader``."""
        with self._named_errors(), self._open() as f:
            yield PrefixReader(f, MAX_CHUNK_BYTES)

    def _open(self):
        """The file, opened for reading: a regular file (a recording is streamed: any size); a
        RecordingError naming it otherwise."""
        try:
            return open_regular(self.path, "recording")
        except FileRefused as exc:
            raise RecordingError(str(exc)) from None

    @contextmanager
    def _named_errors(self) -> Iterator[None]:
        try:
            yield
        except (RecordingError, OSError):
            raise
        except Exception as exc:  # noqa: BLE001 - mcap, zstd, lz4, struct, unicode, key errors of a bad file
            raise RecordingError(f"{self.path}: not a readable v2i recording ({type(exc).__name__}: {exc})") from exc

    def _messages(self, topics: list[str]) -> Iterator[tuple[str, Message]]:
        """(topic, message) of ``topics`` in log-time order."""
        if self.closed:
            with self._reader() as reader:
                for _, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                    yield channel.topic, message
            return
        topic_of = {cid: c.topic for cid, c in self.channels.items() if c.topic in topics}
        with self._prefix() as prefix:
            found = [m for m in prefix.records() if isinstance(m, Message) and m.channel_id in topic_of]
        found.sort(key=lambda m: m.log_time)  # stable: file order among equal times
        for message in found:
            yield topic_of[message.channel_id], message

    @property
    def sides(self) -> list[str]:
        return sorted({c.side for c in self.channels.values()})

    def samples(self, side: str, pattern: str = "**", skip_kinds: tuple[str, ...] = (TIME_REPLY,)) -> Iterator[Sample]:
        """Raw samples of ``side`` whose key matches ``pattern``, in log-time order (the recorder's
        own time replies left out by default)."""
        topics = [c.topic for c in self.channels.values()
                  if c.side == side and c.kind not in skip_kinds and key_matches(pattern, c.key)]
        if not topics:
            return
        by_topic = {c.topic: c for c in self.channels.values()}
        for topic, message in self._messages(topics):
            c = by_topic[topic]
            yield Sample(c.side, c.key, c.kind, message.log_time, bytes(message.data), c.signed)

    def exchanges(self) -> dict[str, list[Exchange]]:
        """The recorder's time exchanges by RSU id: t1, t2, t3 from each reply, t4 its log time."""
        topics = [c.topic for c in self.channels.values() if c.kind == TIME_REPLY]
        out: dict[str, list[Exchange]] = defaultdict(list)
        if not topics:
            return out
        for _, message in self._messages(topics):
            try:
                reply = decode(unwrap(bytes(message.data)), TimeReply)
            except CodecError:
                continue
            out[reply.rsu_id].append(Exchange(reply.t1_ns, reply.t2_ns, reply.t3_ns, message.log_time))
        return out
