"""Every object list an RSU sends, saved as sent, one file per message (``--save-wire DIR``).

Layout: ``DIR/<rsu_id>/<index>.<wire>.<ext>``

- ``index``: six digits, 000000 for the first list this RSU sent, then one more per list: the names
  sort in send order. A folder that already holds saved lists (a restarted RSU, a second run) is
  continued after its highest index, never overwritten. A write that fails still uses its index
  (a gap in the names is a list that could not be saved).
- ``wire`` and ``ext``: ``v2i.msgpack`` (the v2i codec, ``schemas.codec``), ``cpm.uper`` (ETSI CPM,
  UPER) or ``sdsm.uper`` (SAE J3224 SDSM, UPER): the RSU's ``--wire``.
- The bytes are exactly the list's encoding as published, before any security envelope (``--pki``
  signs what goes on the wire, not what is saved). An SDSM has no message for an empty list: none is
  sent, none is saved.

Bounded and safe: at most ``MAX_FILES`` lists per RSU (then saving stops, counted, logged once); each
file is written under a hidden temporary name and renamed, so a reader never sees half a message; a
failed write (full disk, folder removed) is counted and logged once, never raised: the RSU goes on.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path

from v2i.runtime.process import log as process_log

FILE_SUFFIX = {"v2i": "v2i.msgpack", "cpm": "cpm.uper", "sdsm": "sdsm.uper"}  # by --wire
INDEX_DIGITS = 6
MAX_FILES = 10**INDEX_DIGITS  # lists saved per RSU at most (~28 h at 10 Hz); the names keep sorting
_SAVED = re.compile(rf"^(\d{{{INDEX_DIGITS}}})\.")


def check_wire_folder(folder: str | Path, flag: str = "--save-wire") -> Path:
    """The folder, created (with its parents) if absent and shown writable by a probe file;
    ValueError naming ``flag`` otherwise."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ValueError(f"{flag} {folder}: cannot write there ({exc.strerror or exc})") from None
    return folder


class WireFiles:
    """One RSU's saved lists: ``save(data)`` per list sent, in send order."""

    def __init__(self, folder: str | Path, rsu_id: str, wire: str, name: str = "rsu",
                 log: Callable[[str, str], None] = process_log):
        """``folder``: the ``--save-wire`` folder (this RSU's files go in ``folder/rsu_id``);
        ``wire``: v2i, cpm or sdsm; ``name``: the log lines' service name. ValueError at once when
        the folder cannot be created or written."""
        if wire not in FILE_SUFFIX:
            raise ValueError(f"--save-wire: unknown wire {wire!r}; one of {', '.join(FILE_SUFFIX)}")
        self.folder = check_wire_folder(Path(folder) / rsu_id)
        self.suffix = FILE_SUFFIX[wire]
        self.name, self._log = name, log
        self.next_index = self._first_free_index()
        self.saved = 0
        self.failed = 0  # writes that raised (full disk, ...): counted, the first one logged
        self.over_limit = 0  # lists past MAX_FILES: not saved

    def _first_free_index(self) -> int:
        """One past the highest index already saved in the folder (0 in an empty one)."""
        indices = [int(m.group(1)) for entry in os.scandir(self.folder) if (m := _SAVED.match(entry.name))]
        return max(indices, default=-1) + 1

    def path(self, index: int) -> Path:
        return self.folder / f"{index:0{INDEX_DIGITS}d}.{self.suffix}"

    def save(self, data: bytes) -> Path | None:
        """Write one list's bytes as the next file; its path, or None when it was not saved
        (counted; the first failure of each kind is logged). Never raises."""
        if self.next_index >= MAX_FILES:
            if not self.over_limit:
                self._log(self.name, f"--save-wire: {MAX_FILES} lists saved in {self.folder}; "
                                     "later ones are not saved (counted)")
            self.over_limit += 1
            return None
        path = self.path(self.next_index)
        self.next_index += 1
        tmp = path.with_name(f".{path.name}.tmp")
        try:
            tmp.write_bytes(data)
            os.replace(tmp, path)
        except OSError as exc:
            if not self.failed:
                self._log(self.name, f"--save-wire: writing {path} failed ({exc.strerror or exc}); "
                                     "later failures are counted, not logged")
            self.failed += 1
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
            return None
        self.saved += 1
        return path

    def summary(self) -> str:
        """One line: what was saved where, and what was not."""
        lost = [f"{n} {what}" for n, what in ((self.failed, "failed writes"), (self.over_limit, "over the limit")) if n]
        return f"--save-wire: {self.saved} lists saved in {self.folder}" + (f" ({', '.join(lost)})" if lost else "")
