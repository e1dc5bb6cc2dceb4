"""--save-wire's file writer: names in send order per RSU and wire, bytes as given, a refused folder
at start, a failed write counted and logged once (never raised), a bound on the count."""

import os
import stat

import pytest

from v2i.runtime import wire_files
from v2i.runtime.wire_files import WireFiles, check_wire_folder


def test_files_sort_in_send_order_and_hold_the_bytes(tmp_path):
    files = WireFiles(tmp_path / "out", "rsu1", "cpm")
    payloads = [bytes([k]) * (k + 1) for k in range(12)]
    paths = [files.save(p) for p in payloads]
    assert [p.name for p in paths] == [f"{k:06d}.cpm.uper" for k in range(12)]
    assert all(p.parent == tmp_path / "out" / "rsu1" for p in paths)
    assert [p.read_bytes() for p in sorted(paths)] == payloads
    assert sorted(os.listdir(tmp_path / "out" / "rsu1")) == [p.name for p in paths]  # no temporary left
    assert files.saved == 12 and files.failed == 0
    assert "12 lists saved" in files.summary()


@pytest.mark.parametrize("wire, suffix", [("v2i", "v2i.msgpack"), ("sdsm", "sdsm.uper")])
def test_each_wire_names_its_files(tmp_path, wire, suffix):
    assert WireFiles(tmp_path, "rsu-nw", wire).save(b"x").name == f"000000.{suffix}"


def test_a_second_writer_continues_after_the_saved_files(tmp_path):
    first = WireFiles(tmp_path, "rsu1", "v2i")
    for _ in range(3):
        first.save(b"a")
    again = WireFiles(tmp_path, "rsu1", "cpm")  # a restarted RSU: nothing overwritten
    assert again.save(b"b").name == "000003.cpm.uper"
    assert (tmp_path / "rsu1" / "000000.v2i.msgpack").read_bytes() == b"a"


def test_unknown_wire_and_unwritable_folder_are_refused_at_start(tmp_path):
    with pytest.raises(ValueError, match="unknown wire"):
        WireFiles(tmp_path, "rsu1", "json")
    a_file = tmp_path / "file"
    a_file.write_text("")
    with pytest.raises(ValueError, match="--save-wire .*cannot write"):
        check_wire_folder(a_file / "sub")
    if os.geteuid() != 0:  # root writes through mode bits
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(stat.S_IRUSR | stat.S_IXUSR)
        try:
            with pytest.raises(ValueError, match="cannot write"):
                WireFiles(locked, "rsu1", "cpm")
        finally:
            locked.chmod(stat.S_IRWXU)


def test_a_failed_write_is_counted_and_logged_once(tmp_path, monkeypatch):
    lines = []
    files = WireFiles(tmp_path, "rsu1", "cpm", log=lambda name, text: lines.append((name, text)))

    def full_disk(self, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(type(tmp_path), "write_bytes", full_disk)
    assert [files.save(b"x") for _ in range(5)] == [None] * 5
    monkeypatch.undo()
    assert files.failed == 5 and len(lines) == 1 and "No space left" in lines[0][1]
    assert files.save(b"y").name == "000005.cpm.uper"  # the gap marks the lost lists; saving resumes
    assert os.listdir(tmp_path / "rsu1") == ["000005.cpm.uper"]
    assert "5 failed writes" in files.summary()


def test_saving_stops_at_the_bound(tmp_path, monkeypatch):
    lines = []
    monkeypatch.setattr(wire_files, "MAX_FILES", 2)
    files = WireFiles(tmp_path, "rsu1", "sdsm", log=lambda name, text: lines.append(text))
    assert [files.save(b"z") is not None for _ in range(4)] == [True, True, False, False]
    assert files.over_limit == 2 and len(lines) == 1


class _Publisher:
    """A Zenoh publisher stand-in: its key and what was put on it."""

    def __init__(self, key: str):
        self.key_expr, self.puts = key, []

    def put(self, data: bytes) -> None:
        self.puts.append(bytes(data))


def test_rsu_node_saves_each_list_it_sends_unsigned(tmp_path):
    """``v2i rsu --save-wire``: each list put is saved, the signed one as its payload, and decodes."""
    import threading
    import time

    from rsu_service.config import RsuConfig
    from schemas.keys import rsu_cpm
    from schemas.list_wire import decode_list
    from v2i.security.envelope import Signer, unwrap
    from v2i.security.site import memory_site
    from v2i.services import rsu_node

    node = rsu_node(RsuConfig(await_start=True, duration_s=2.0, wire="cpm", save_wire=str(tmp_path / "w")))
    start_ns = time.time_ns() - 2_000_000_000  # frames 0-2 s in are due already: no wait
    node._begin(start_ns)
    node._loop_signer = Signer(memory_site(start_ns, ["rsu1"])[1]["rsu1"])
    lists = _Publisher(rsu_cpm("rsu1"))
    node._predictions, node._metrics, node._features = (_Publisher(k) for k in ("p", "m", "f"))
    for capture_ns in list(node.source.capture_times_ns(2.0))[:5]:
        assert node._publish(lists, node.source.capture(int(capture_ns)), threading.Event())
    saved = sorted((tmp_path / "w" / "rsu1").iterdir())
    assert [p.name for p in saved] == [f"{k:06d}.cpm.uper" for k in range(5)]
    assert [p.read_bytes() for p in saved] == [unwrap(data) for data in lists.puts]
    assert all(p.read_bytes() != data for p, data in zip(saved, lists.puts))  # the signature is not saved
    assert sum(len(decode_list(p.read_bytes(), "cpm", "rsu1").objects) for p in saved) > 0


def test_rsu_node_refuses_an_unwritable_folder_at_start(tmp_path):
    from rsu_service.config import RsuConfig
    from v2i.services import rsu_node

    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="--save-wire"):
        rsu_node(RsuConfig(await_start=True, duration_s=2.0, save_wire=str(tmp_path / "file" / "w")))
