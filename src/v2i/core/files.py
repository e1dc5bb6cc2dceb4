"""Bounded file reads: every file v2i reads is a regular file under a stated size limit.

A path handed to v2i (``--config``, ``--site``, a PKI folder, a model, a recording) may name
anything: ``/dev/zero`` (reading it never ends), a FIFO (opening it blocks until a writer comes),
a directory, a 100 GB file. Each reader states its limit next to itself and reads through
:func:`read_bounded` / :func:`read_text`, or, where the file is streamed (a recording, a video)
or a library opens the path itself (Lanelet2, OpenCV), checks it with :func:`open_regular` /
:func:`check_regular`. What is not a regular file under the limit is refused with a one-line
:class:`FileRefused` (an ``OSError``): ``cannot read <what> <path>: <what was found>; a <what>
must be a regular file of at most <limit>``, before any byte of it is read.

How (no time-of-check/time-of-use gap): ``stat`` first, so that a device or FIFO is never even
opened; then ``open(O_NONBLOCK)`` (a FIFO swapped in meanwhile cannot block the open) and
``fstat`` of the opened descriptor, the one that is read: it must be a regular file of at most
``limit_bytes``; then at most ``limit_bytes + 1`` bytes are read, so a file growing while read is
refused as well. Symbolic links are followed: what they point at is checked.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

KiB = 1 << 10
MiB = 1 << 20

# stat's file types, as an error names them
_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"))


class FileRefused(OSError):
    """A file v2i will not read; ``str()`` is one line: what it is for, the path, why."""


class FileMissing(FileRefused, FileNotFoundError):
    """A file that is not there (also a ``FileNotFoundError``)."""


class FileTooLarge(FileRefused):
    """A regular file over its limit (when checked, or grown while read)."""


def size_text(n_bytes: int) -> str:
    """``n_bytes`` as a limit is written: ``1 MiB``, ``64 KiB``, else ``N bytes``."""
    for unit, name in ((MiB, "MiB"), (KiB, "KiB")):
        if n_bytes >= unit and n_bytes % unit == 0:
            return f"{n_bytes // unit} {name}"
    return f"{n_bytes} bytes"


def _rule(what: str, limit_bytes: int | None) -> str:
    limit = "" if limit_bytes is None else f" of at most {size_text(limit_bytes)}"
    return f"a {what} must be a regular file{limit}"


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def _refused(path: str | Path, what: str, finding: str, limit_bytes: int | None,
             kind: type[FileRefused] = FileRefused) -> FileRefused:
    return kind(f"cannot read {what} {path}: {finding}; {_rule(what, limit_bytes)}")


def _os_error(path: str | Path, what: str, exc: OSError) -> FileRefused:
    """``exc`` of stat or open as a FileRefused naming the file (FileMissing when it is not there)."""
    if isinstance(exc, FileNotFoundError):
        return FileMissing(f"cannot read {what} {path}: no such file")
    return FileRefused(f"cannot read {what} {path}: {(exc.strerror or str(exc)).lower()}")


def _check(st: os.stat_result, path: str | Path, what: str, limit_bytes: int | None) -> None:
    if not stat.S_ISREG(st.st_mode):
        raise _refused(path, what, _kind(st.st_mode), limit_bytes)
    if limit_bytes is not None and st.st_size > limit_bytes:
        raise _refused(path, what, f"{st.st_size} bytes", limit_bytes, FileTooLarge)


def check_regular(path: str | Path, limit_bytes: int | None, what: str) -> int:
    """The size (bytes) of the regular file ``path`` of at most ``limit_bytes`` (None: any size);
    FileRefused otherwise. For a file a library opens by path itself (it may change between this
    check and that open: prefer :func:`read_bounded` where the library takes bytes)."""
    with open_regular(path, what, limit_bytes) as f:
        return os.fstat(f.fileno()).st_size


def open_regular(path: str | Path, what: str, limit_bytes: int | None = None) -> BinaryIO:
    """``path`` opened for binary reading, checked (on the opened descriptor) to be a regular file
    of at most ``limit_bytes`` (None: any size, e.g. a recording streamed record by record);
    FileRefused naming ``what`` and the path otherwise. The caller closes it (``with``)."""
    try:
        _check(os.stat(path), path, what, limit_bytes)  # a device or FIFO is not even opened
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except FileRefused:
        raise
    except OSError as exc:
        raise _os_error(path, what, exc) from None
    try:
        _check(os.fstat(fd), path, what, limit_bytes)  # what is read is what was checked
    except BaseException:
        os.close(fd)
        raise
    return os.fdopen(fd, "rb")


def read_open(f: BinaryIO, limit_bytes: int, what: str, path: str | Path) -> bytes:
    """The rest of the open regular file ``f``, at most ``limit_bytes``; FileRefused when it holds
    more (it grew after it was checked)."""
    expected = os.fstat(f.fileno()).st_size
    data = f.read(min(expected, limit_bytes) + 1)  # the file as fstat saw it, and one byte to see if it grew
    if len(data) > expected:
        data += f.read(limit_bytes + 1 - len(data))
    if len(data) > limit_bytes:
        raise _refused(path, what, f"over {size_text(limit_bytes)} (it grew while read)", limit_bytes, FileTooLarge)
    return data


def read_bounded(path: str | Path, limit_bytes: int, what: str) -> bytes:
    """The bytes of the regular file ``path`` of at most ``limit_bytes``; FileRefused naming
    ``what`` ("config", "site", "certificate"), the path and the limit otherwise."""
    with open_regular(path, what, limit_bytes) as f:
        return read_open(f, limit_bytes, what, path)


def read_text(path: str | Path, limit_bytes: int, what: str) -> str:
    """:func:`read_bounded` decoded as UTF-8; FileRefused naming the first bad byte otherwise."""
    data = read_bounded(path, limit_bytes, what)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FileRefused(f"cannot read {what} {path}: not UTF-8 text (byte {exc.start})") from None
