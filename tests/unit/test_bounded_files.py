"""v2i.core.files: only regular files under a limit are read, and nothing blocks or runs away."""

from __future__ import annotations

import os
import socket
import time

import pytest

from v2i.core.files import (FileMissing, FileRefused, FileTooLarge, KiB, MiB, check_regular, open_regular,
                            read_bounded, read_open, read_text, size_text)


def _refusal(path, limit_bytes=1 * MiB) -> str:
    with pytest.raises(FileRefused) as caught:
        read_bounded(path, limit_bytes, "config")
    message = str(caught.value)
    assert "\n" not in message and message.startswith(f"cannot read config {path}: ")
    return message


def test_reads_a_regular_file_up_to_its_limit_inclusive(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_bytes(b"x" * 100)
    assert read_bounded(path, 100, "config") == b"x" * 100
    assert read_text(path, 100, "config") == "x" * 100
    assert check_regular(path, 100, "config") == 100
    assert "100 bytes; a config must be a regular file of at most 99 bytes" in _refusal(path, 99)


def test_a_symlink_to_a_regular_file_is_followed(tmp_path):
    (tmp_path / "real.yaml").write_text("a: 1\n")
    (tmp_path / "link.yaml").symlink_to(tmp_path / "real.yaml")
    assert read_text(tmp_path / "link.yaml", KiB, "config") == "a: 1\n"


def test_dev_zero_behind_a_symlink_is_refused_before_reading(tmp_path, alarm):
    (tmp_path / "zero.yaml").symlink_to("/dev/zero")
    assert "a character device; a config must be a regular file of at most 1 MiB" in _refusal(tmp_path / "zero.yaml")


def test_a_fifo_is_refused_without_blocking(tmp_path, alarm):
    os.mkfifo(tmp_path / "fifo.yaml")
    started = time.monotonic()
    assert "a FIFO;" in _refusal(tmp_path / "fifo.yaml")
    assert time.monotonic() - started < 1.0


def test_a_fifo_swapped_in_after_the_stat_does_not_block(tmp_path, alarm, monkeypatch):
    """The descriptor is opened non-blocking and checked itself: a regular file at stat time
    replaced by a FIFO before the open is still refused, at once."""
    path = tmp_path / "c.yaml"
    path.write_text("a: 1\n")
    real_stat = os.stat

    def stat_then_swap(p, *args, **kwargs):
        result = real_stat(p, *args, **kwargs)
        os.unlink(p)
        os.mkfifo(p)
        return result

    monkeypatch.setattr(os, "stat", stat_then_swap)
    assert "a FIFO;" in _refusal(path)


def test_an_oversized_sparse_file_is_refused_unread(tmp_path):
    path = tmp_path / "big.yaml"
    with open(path, "wb") as f:
        f.truncate(100 * MiB)
    assert f"{100 * MiB} bytes; a config must be a regular file of at most 1 MiB" in _refusal(path)
    with pytest.raises(FileTooLarge):
        read_bounded(path, MiB, "config")


def test_a_directory_a_socket_and_a_missing_file_are_refused(tmp_path):
    assert "a directory;" in _refusal(tmp_path)
    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(tmp_path / "sock"))
        assert "a socket;" in _refusal(tmp_path / "sock")
    with pytest.raises(FileMissing, match="no such file") as caught:
        read_bounded(tmp_path / "none.yaml", KiB, "config")
    assert isinstance(caught.value, FileNotFoundError)


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_an_unreadable_file_is_refused_with_the_reason(tmp_path):
    path = tmp_path / "secret.yaml"
    path.write_text("a: 1\n")
    path.chmod(0)
    assert f"config {path}: permission denied" in _refusal(path)


def test_a_file_that_grows_while_read_is_refused(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_bytes(b"x" * 10)
    with open_regular(path, "config", 100) as f:
        with open(path, "ab") as grow:
            grow.write(b"y" * 200)
        with pytest.raises(FileTooLarge, match="it grew while read"):
            read_open(f, 100, "config", path)


def test_a_file_that_grows_within_its_limit_is_read_whole(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_bytes(b"x" * 10)
    with open_regular(path, "config", 100) as f:
        with open(path, "ab") as grow:
            grow.write(b"y" * 20)
        assert read_open(f, 100, "config", path) == b"x" * 10 + b"y" * 20


def test_text_that_is_not_utf8_is_refused(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_bytes(b"ab\xff")
    with pytest.raises(FileRefused, match=r"not UTF-8 text \(byte 2\)"):
        read_text(path, KiB, "config")


def test_a_stream_needs_no_limit_but_a_regular_file(tmp_path):
    path = tmp_path / "r.mcap"
    path.write_bytes(b"m" * 5000)
    with open_regular(path, "recording") as f:
        assert f.read(3) == b"mmm"
    os.mkfifo(tmp_path / "fifo.mcap")
    with pytest.raises(FileRefused, match="fifo.mcap: a FIFO; a recording must be a regular file$"):
        open_regular(tmp_path / "fifo.mcap", "recording")


def test_limits_are_written_in_their_unit():
    assert (size_text(MiB), size_text(64 * KiB), size_text(1000), size_text(3 * MiB + 1)) == \
        ("1 MiB", "64 KiB", "1000 bytes", f"{3 * MiB + 1} bytes")
