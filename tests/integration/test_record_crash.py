"""A real ``v2i record`` process, real Zenoh traffic on tcp/127.0.0.1:<free port>, stopped
mid-write by SIGTERM, SIGINT, SIGKILL or a full disk (RLIMIT_FSIZE: the kernel refuses to grow
the file, as a full disk does): the file reads back, every sample as published and in order.
SIGTERM / SIGINT close it (summary written); SIGKILL and the full disk cannot, and ``v2i replay``
reads it and says it was not closed. Waits are deadlines, never bare sleeps."""

from __future__ import annotations

import queue
import re
import resource
import signal
import subprocess
import sys
import threading
import time

import pytest

from schemas.codec import decode, encode
from schemas.messages import ObjectList, ObjectListHeader
from v2i.runtime.transport import free_tcp_endpoint, open_session
from v2i.telemetry.mcap_reader import Recording, RecordingError

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

T_NS = 1_795_545_547_592_119_513
PUBLISH_PERIOD_S = 0.005
START_DEADLINE_S = 90.0  # a loaded 2-core machine: the recorder's start-up and first chunk
FILE_LIMIT_BYTES = 120_000  # the "disk": a few chunks of this traffic


def _payload(seq: int) -> bytes:
    header = ObjectListHeader(rsu_id="rsu1", seq=seq, capture_time_ns=T_NS + seq, publish_time_ns=T_NS + seq)
    objects = [{"id": k, "x": float(k), "y": float(seq % 50), "length": 4.5, "width": 1.8, "yaw": 0.1} for k in range(8)]
    return encode(ObjectList(header=header, objects=objects))


@pytest.fixture
def traffic():
    """A Zenoh peer listening on a free endpoint, publishing numbered object lists at ~200 Hz."""
    endpoint = free_tcp_endpoint()
    session = open_session(listen=[endpoint])
    stop = threading.Event()

    def publish():
        publisher = session.declare_publisher("v2x/rsu/rsu1/objects")
        seq = 0
        while not stop.wait(PUBLISH_PERIOD_S):
            publisher.put(_payload(seq))
            seq += 1
        publisher.undeclare()

    thread = threading.Thread(target=publish, name="traffic", daemon=True)
    thread.start()
    try:
        yield endpoint
    finally:
        stop.set()
        thread.join(10)
        session.close()


class RecorderProcess:
    """``v2i record`` on ``endpoint`` into ``path``; its stderr lines read into a queue."""

    def __init__(self, endpoint: str, path, preexec_fn=None):
        self.path = path
        self.proc = subprocess.Popen([sys.executable, "-m", "v2i", "record", "--connect", f"rsu={endpoint}",
                                      "--out", str(path), "--time-from", "none"],
                                     stderr=subprocess.PIPE, text=True, preexec_fn=preexec_fn)
        self.lines: queue.Queue = queue.Queue()
        self.stderr: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.put(line)
        self.lines.put(None)

    def wait_line(self, pattern: str, deadline: float) -> re.Match:
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                break
            if line is None:
                break
            self.stderr.append(line)
            if match := re.search(pattern, line):
                return match
        pytest.fail(f"no line matching {pattern!r} from v2i record: {''.join(self.stderr)[-2000:]}")

    def finish(self, timeout_s: float = 60.0) -> int:
        code = self.proc.wait(timeout_s)
        while (line := self.lines.get(timeout=timeout_s)) is not None:
            self.stderr.append(line)
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


def _recorded(path) -> tuple[Recording, list[int]]:
    """The recording and its samples' sequence numbers; each payload checked against what was sent."""
    recording = Recording(path)
    seqs = []
    for sample in recording.samples("rsu"):
        seq = decode(sample.payload, ObjectList).header.seq
        assert sample.payload == _payload(seq)
        seqs.append(seq)
    assert seqs == sorted(set(seqs)), "samples out of order or twice"
    return recording, seqs


def _wait_readable(path, at_least: int, deadline: float) -> int:
    """Wait until the file, read while the recorder writes it, holds ``at_least`` samples."""
    while time.monotonic() < deadline:
        try:
            count = sum(1 for _ in Recording(path).samples("rsu"))
        except (RecordingError, FileNotFoundError):
            count = 0
        if count >= at_least:
            return count
        time.sleep(0.2)  # polling the file with a deadline
    pytest.fail(f"{path} never held {at_least} samples")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_mid_write_closes_the_file(traffic, tmp_path, sig):
    path = tmp_path / "run.mcap"
    recorder = RecorderProcess(traffic, path)
    try:
        deadline = time.monotonic() + START_DEADLINE_S
        recorder.wait_line(r"v2i record: (\d{2,}) messages", deadline)  # recording, not just started
        in_file = _wait_readable(path, 20, deadline)  # a chunk written: the recorder is mid-write
        recorder.proc.send_signal(sig)
        assert recorder.finish() == 0, "".join(recorder.stderr)
    finally:
        recorder.kill()
    wrote = int(re.search(r"wrote (\d+) messages", "".join(recorder.stderr)).group(1))
    recording, seqs = _recorded(path)
    assert recording.closed and recording.problem is None
    assert len(seqs) == wrote >= in_file  # every message the recorder took, none lost at the end


def test_sigkill_mid_write_leaves_what_was_written_readable(traffic, tmp_path):
    path = tmp_path / "run.mcap"
    recorder = RecorderProcess(traffic, path)
    try:
        in_file = _wait_readable(path, 100, time.monotonic() + START_DEADLINE_S)
        recorder.proc.send_signal(signal.SIGKILL)
        assert recorder.finish() == -signal.SIGKILL
    finally:
        recorder.kill()
    recording, seqs = _recorded(path)
    assert not recording.closed and "it has no footer" in recording.problem
    assert len(seqs) >= in_file  # what was in the file before the kill is still there
    replay = subprocess.run([sys.executable, "-m", "v2i", "replay", str(path), "--connect", traffic, "--speed", "50",
                             "--lead", "0.5"], capture_output=True, text=True, timeout=120, check=False)
    assert replay.returncode == 0, replay.stderr
    assert "was not closed" in replay.stderr
    assert re.search(rf"published {len(seqs)}\b", replay.stdout + replay.stderr), replay.stderr


def test_a_full_disk_stops_the_recording_with_a_readable_file(traffic, tmp_path):
    path = tmp_path / "run.mcap"
    limit = (FILE_LIMIT_BYTES, resource.getrlimit(resource.RLIMIT_FSIZE)[1])
    recorder = RecorderProcess(traffic, path, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, limit))
    try:
        recorder.wait_line(r"writing .* failed \(File too large\); stopping", time.monotonic() + START_DEADLINE_S)
        assert recorder.finish() == 1
    finally:
        recorder.kill()
    err = "".join(recorder.stderr)
    assert "NOT CLOSED" in err and "v2i replay reads it" in err
    recording, seqs = _recorded(path)
    assert path.stat().st_size <= FILE_LIMIT_BYTES and not recording.closed
    assert len(seqs) > 0 and recording.readable_bytes == path.stat().st_size  # cut back to whole records
