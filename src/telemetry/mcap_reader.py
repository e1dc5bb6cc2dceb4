"""Reading a ``v2i record`` MCAP file back: its sides, samples, metadata and RSU time exchanges.

A recording is untrusted input: the file is read once through at open (CRCs checked, records and
chunks at most ``MAX_CHUNK_BYTES`` compressed or not, every message decoded from its chunk), and
anything wrong with it is a ``RecordingError`` (a ``ValueError``) naming the file, never a traceback.

Signed samples (``telemetry.mcap_channels``: channel metadata ``signed``) keep their envelope in
``Sample.payload``; ``Sample.content`` is the message inside, and the time exchanges are read
from it (unchecked: a recording is evidence, not a trust decision).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from mcap.reader import SeekingReader

from schemas.codec import CodecError, decode
from schemas.messages import TimeReply
from security.envelope import unwrap

from .mcap_channels import models_by_type
from .time_shift import Exchange

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
    """A ``v2i record`` file: ``channels`` (raw ones, by MCAP channel id), ``metadata`` (name -> dict)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        with self._reader() as reader:
            summary = reader.get_summary()
            if summary is None:
                raise RecordingError(f"{self.path}: no MCAP summary (a recording that was not closed)")
            big = [c.uncompressed_size for c in summary.chunk_indexes if c.uncompressed_size > MAX_CHUNK_BYTES]
            if big:
                raise RecordingError(f"{self.path}: a chunk of {big[0]} bytes (at most {MAX_CHUNK_BYTES})")
            self.channels = {cid: RawChannel(str(c.topic), str(c.metadata["side"]), str(c.metadata["key"]),
                                             str(c.metadata["kind"]), c.metadata.get("signed") == "true")
                             for cid, c in summary.channels.items() if "side" in c.metadata}
            self.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            self.message_counts = dict(summary.statistics.channel_message_counts) if summary.statistics else {}
            for _ in reader.iter_messages():  # every chunk decompressed and checked once, here
                pass

    @contextmanager
    def _reader(self) -> Iterator[SeekingReader]:
        """A reader of the file whose every failure is a ``RecordingError`` naming it."""
        try:
            with open(self.path, "rb") as f:
                yield SeekingReader(f, validate_crcs=True, record_size_limit=MAX_CHUNK_BYTES)
        except (RecordingError, OSError):
            raise
        except Exception as exc:  # noqa: BLE001 - mcap, zstd, lz4, struct, unicode, key errors of a bad file
            raise RecordingError(f"{self.path}: not a readable v2i recording ({type(exc).__name__}: {exc})") from exc

    def _messages(self, topics: list[str]):
        """(channel, message) of ``topics`` in log-time order."""
        with self._reader() as reader:
            for _, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                yield channel, message

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
        for channel, message in self._messages(topics):
            c = by_topic[channel.topic]
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
