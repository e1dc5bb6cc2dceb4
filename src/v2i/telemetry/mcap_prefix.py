"""Reading an MCAP file that was not closed (``v2i record`` killed, or its disk full): its records
from the start up to the last whole one.

``v2i.telemetry.mcap_writer`` leaves such a file a valid MCAP *prefix*: the magic, the header, whole
records, and at most one record cut short at the end (the process was killed while writing it).
The mcap library reads a file without a summary only with its linear reader, which cannot tell
a record cut short from a damaged one; this scan can, from the file's size: a record that runs
past the end of the file ends the scan (``PrefixReader.ended_by``), one that lies within the file
but does not parse is damage (raised: the caller names the file). Records are at most
``max_record_bytes``, compressed and not; chunks are zstd or uncompressed, their CRCs checked.
"""

from __future__ import annotations

import io
import struct
from collections.abc import Iterator
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Header, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk, read_magic

MAGIC = b"\x89MCAP0\r\n"  # at the start and at the end of a closed file
MAGIC_BYTES = len(MAGIC)
HEAD_BYTES = 9  # opcode (1) and length (8) of every record
_PLAIN = {Opcode.HEADER: Header, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata}
CUT_SHORT = "its last record was cut short"
AT_SUMMARY = "it ends in its summary"  # DataEnd written: killed while the summary was written


class PrefixReader:
    """The records of an MCAP prefix in file order; after ``records()`` is exhausted, ``end_bytes``
    is where the last whole record ends and ``ended_by`` why the scan stopped."""

    def __init__(self, stream: BinaryIO, max_record_bytes: int):
        self._stream, self._max_bytes = stream, max_record_bytes
        self.size_bytes = stream.seek(0, io.SEEK_END)
        self.end_bytes = 0
        self.ended_by = ""

    def records(self) -> Iterator[McapRecord]:
        """Header, Schema, Channel, Metadata and Message records (the chunks' opened); ValueError
        (or an mcap / zstd error) for a whole record that does not parse."""
        self._stream.seek(0)
        read_magic(ReadDataStream(self._stream))
        self.end_bytes = MAGIC_BYTES
        while True:
            head = self._stream.read(HEAD_BYTES)
            if len(head) < HEAD_BYTES:
                self.ended_by = CUT_SHORT if head else "it ends after a whole record"
                return
            opcode, length = struct.unpack("<BQ", head)
            if self.end_bytes + HEAD_BYTES + length > self.size_bytes:
                self.ended_by = CUT_SHORT
                return
            if opcode in (Opcode.DATA_END, Opcode.FOOTER):
                self.ended_by = AT_SUMMARY
                return
            if length > self._max_bytes:
                raise ValueError(f"a record of {length} bytes at byte {self.end_bytes} (at most {self._max_bytes})")
            body = self._stream.read(length)
            self.end_bytes += HEAD_BYTES + length
            yield from self._parsed(opcode, body)

    def _parsed(self, opcode: int, body: bytes) -> Iterator[McapRecord]:
        stream = ReadDataStream(io.BytesIO(body))
        if opcode == Opcode.MESSAGE:
            yield Message.read(stream, len(body))
        elif opcode == Opcode.CHUNK:
            yield from self._chunk(Chunk.read(stream))
        elif opcode in _PLAIN:
            yield _PLAIN[opcode].read(stream)
        # indexes, attachments, statistics and unknown records: nothing a recording needs

    def _chunk(self, chunk: Chunk) -> list[McapRecord]:
        if chunk.compression not in ("", "zstd"):
            raise ValueError(f"a chunk compressed with {chunk.compression!r} (v2i record writes zstd)")
        if chunk.uncompressed_size > self._max_bytes:
            raise ValueError(f"a chunk of {chunk.uncompressed_size} bytes (at most {self._max_bytes})")
        return breakup_chunk(chunk, validate_crc=True)
