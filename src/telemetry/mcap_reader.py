"""Reading a ``v2i record`` MCAP file back: its sides, samples, metadata and RSU time exchanges."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mcap.reader import make_reader

from schemas.codec import CodecError, decode
from schemas.messages import TimeReply

from .mcap_channels import models_by_type
from .time_shift import Exchange

TIME_REPLY = TimeReply.TYPE


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
    payload: bytes

    @property
    def model(self):
        return models_by_type().get(self.kind)


@dataclass(frozen=True)
class RawChannel:
    topic: str
    side: str
    key: str
    kind: str


class Recording:
    """A ``v2i record`` file: ``channels`` (raw ones, by MCAP channel id), ``metadata`` (name -> dict)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        with open(self.path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None:
                raise ValueError(f"{self.path}: no MCAP summary (a recording that was not closed)")
            self.channels = {cid: RawChannel(c.topic, c.metadata["side"], c.metadata["key"], c.metadata["kind"])
                             for cid, c in summary.channels.items() if "side" in c.metadata}
            self.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            self.message_counts = dict(summary.statistics.channel_message_counts) if summary.statistics else {}

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
        with open(self.path, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages(topics=topics, log_time_order=True):
                c = by_topic[channel.topic]
                yield Sample(c.side, c.key, c.kind, message.log_time, bytes(message.data))

    def exchanges(self) -> dict[str, list[Exchange]]:
        """The recorder's time exchanges by RSU id: t1, t2, t3 from each reply, t4 its log time."""
        topics = [c.topic for c in self.channels.values() if c.kind == TIME_REPLY]
        out: dict[str, list[Exchange]] = defaultdict(list)
        if not topics:
            return out
        with open(self.path, "rb") as f:
            for _, _, message in make_reader(f).iter_messages(topics=topics, log_time_order=True):
                try:
                    reply = decode(bytes(message.data), TimeReply)
                except CodecError:
                    continue
                out[reply.rsu_id].append(Exchange(reply.t1_ns, reply.t2_ns, reply.t3_ns, message.log_time))
        return out
