"""A recording stopped at any moment reads back: cut short anywhere (a killed recorder), a write
that fails anywhere (a full disk, also while the summary is written), a signal while it closes.
The live version (a real ``v2i record`` process killed mid-write) is in
tests/integration/test_record_crash.py."""

from __future__ import annotations

import errno
import os
import signal

import pytest

from schemas.codec import encode
from schemas.messages import ObjectList, ObjectListHeader
from v2i.telemetry import mcap_writer
from v2i.telemetry.mcap_reader import Recording, RecordingError
from v2i.telemetry.mcap_writer import RunWriter
from v2i.telemetry.recorder import _signals_deferred

T_NS = 1_795_545_547_592_119_513
MESSAGES, PER_CHUNK = 60, 10


def _payload(i: int) -> bytes:
    header = ObjectListHeader(rsu_id="rsu1", seq=i, capture_time_ns=T_NS + i, publish_time_ns=T_NS + i)
    return encode(ObjectList(header=header, objects=[{"id": i, "x": float(i), "y": 1.0, "length": 4.0,
                                                       "width": 2.0, "yaw": 0.0}]))


def _record(path, messages: int = MESSAGES) -> list[bytes]:
    """``messages`` samples, a chunk written every PER_CHUNK (as v2i record's periodic flush), closed."""
    writer = RunWriter(path)
    writer.add_metadata("recording", {"started_ns": str(T_NS)})
    sent = []
    try:
        for i in range(messages):
            sent.append(_payload(i))
            writer.write("rsu", "v2x/rsu/rsu1/objects", sent[-1], T_NS + i * 1000)
            if i % PER_CHUNK == PER_CHUNK - 1:
                writer.flush()
    finally:
        writer.close()
    return sent


def _payloads(recording: Recording) -> list[bytes]:
    return [s.payload for s in recording.samples("rsu")]


def test_a_recording_cut_anywhere_reads_back_its_whole_chunks(tmp_path):
    full = tmp_path / "full.mcap"
    sent = _record(full)
    data = full.read_bytes()
    closed = Recording(full)
    assert closed.closed and closed.problem is None and _payloads(closed) == sent
    cut = tmp_path / "cut.mcap"
    header_end = data.index(b"v2i record") + len(b"v2i record")  # magic + header record
    kept_before = 0
    for end in range(header_end, len(data), 17):  # every 17th byte: ~140 cuts
        cut.write_bytes(data[:end])
        recording = Recording(cut)
        got = _payloads(recording)
        assert not recording.closed and f"{len(got)} messages in its first" in recording.problem
        assert recording.problem.endswith(f" of {end} bytes") and recording.readable_bytes <= end
        assert got == sent[: len(got)] and len(got) % PER_CHUNK == 0  # whole chunks, in order
        assert len(got) >= kept_before
        assert recording.metadata == ({"recording": {"started_ns": str(T_NS)}} if got else recording.metadata)
        kept_before = len(got)
    assert kept_before == MESSAGES  # cut inside the summary: every chunk is still read


def test_a_file_cut_before_its_header_is_a_clear_error(tmp_path):
    full = tmp_path / "full.mcap"
    _record(full, 3)
    cut = tmp_path / "cut.mcap"
    for end in (0, 5, 8, 12):
        cut.write_bytes(full.read_bytes()[:end])
        with pytest.raises(RecordingError, match="cut.mcap"):
            Recording(cut)


def _quota(left: int):
    """``_FileSink.write`` on a disk that takes ``left`` more bytes: a short write up to it, then
    ENOSPC (as Linux does)."""
    room = [left]

    def write(sink, data) -> int:
        take = min(len(data), room[0])
        if take:
            os.write(sink._fd, bytes(data[:take]))
            sink.position += take
            room[0] -= take
        if take < len(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return len(data)

    return write


def test_a_full_disk_anywhere_leaves_a_readable_file(tmp_path, monkeypatch):
    full = tmp_path / "full.mcap"
    sent = _record(full)
    size = full.stat().st_size
    path = tmp_path / "full_disk.mcap"
    for quota in range(60, size, 131):
        monkeypatch.setattr(mcap_writer._FileSink, "write", _quota(quota))
        try:
            _record(path)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
        monkeypatch.undo()
        assert path.stat().st_size <= quota  # cut back to the last whole record
        recording = Recording(path)
        got = _payloads(recording)
        assert not recording.closed and got == sent[: len(got)] and len(got) % PER_CHUNK == 0
    monkeypatch.setattr(mcap_writer._FileSink, "write", _quota(size - 40))  # fails in the footer
    with pytest.raises(OSError):
        _record(path)
    monkeypatch.undo()
    recording = Recording(path)
    assert not recording.closed and _payloads(recording) == sent  # the data section is whole


def test_after_a_failed_write_the_writer_refuses_and_keeps_the_file(tmp_path, monkeypatch):
    path = tmp_path / "r.mcap"
    writer = RunWriter(path)
    writer.write("rsu", "v2x/rsu/rsu1/objects", _payload(0), T_NS)
    writer.flush()
    kept = writer.file_bytes
    monkeypatch.setattr(mcap_writer._FileSink, "write", _quota(5))
    writer.write("rsu", "v2x/rsu/rsu1/objects", _payload(1), T_NS + 1)  # into the chunk in memory
    with pytest.raises(OSError):
        writer.flush()
    monkeypatch.undo()
    assert isinstance(writer.failed, OSError) and path.stat().st_size == kept == writer.file_bytes
    with pytest.raises(OSError):
        writer.write("rsu", "v2x/rsu/rsu1/objects", _payload(2), T_NS + 2)
    writer.close()  # no summary over a broken chunk
    assert _payloads(Recording(path)) == [_payload(0)]


def test_a_signal_while_the_file_closes_is_handled_after_it():
    seen = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: seen.append(signum))
    try:
        with pytest.raises(KeyboardInterrupt):  # SIGINT's default handler, called on the way out
            with _signals_deferred():
                signal.raise_signal(signal.SIGINT)
                signal.raise_signal(signal.SIGTERM)
                seen.append("inside, not interrupted")
        assert seen == ["inside, not interrupted"]  # the first signal only
        with _signals_deferred():
            signal.raise_signal(signal.SIGTERM)
            seen.append("inside again")
        assert seen == ["inside, not interrupted", "inside again", signal.SIGTERM]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handlers put back
    finally:
        signal.signal(signal.SIGTERM, previous)
