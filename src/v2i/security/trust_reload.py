"""A running verifier's revocation list kept in step with its PKI directory: a revocation without a restart.

``v2i pki revoke DIR SUBJECT`` rewrites ``DIR/revoked.crl`` (atomically: a new file renamed over
the old). A service that verifies (the OBU, the link emulator's control) loads its trust through a
:class:`TrustReload` and calls :meth:`TrustReload.poll` from its loop, not per message: at most once
per ``interval_s`` it stats the list, and only when the file changed (inode, size or mtime) does it
read the list again (:func:`pki.read_crl`: parsed, signed by the CA in force). The caller hands an
accepted :attr:`Reload.trust` (the trust in force with the new list) to its verifier
(``Verifier.set_trust``), whose cached certificates are judged against the new list from the next
message on. Only the list is re-read: the CA and the pre-distributed certificates stay those of
start-up, so a bad file elsewhere in the directory cannot hold a revocation back.

A new list is refused, the list in force kept, and the refusal returned once per change of the
file (the caller logs it) when:

- it cannot be read, does not parse or is not signed by the CA (``PkiError``);
- it leaves out a certificate the list in force revokes (an older list put back would un-revoke what
  was revoked since; ``v2i pki revoke`` only adds, so only a restart takes an un-revocation);
- it was removed while the list in force revokes something (the same downgrade, by deletion).

Times are arguments (``now_ns``, any clock of the caller's, only compared with itself).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from v2i.security.certificates import RevocationList
from v2i.security.pki import CRL_FILE, PkiError, Trust, load_trust, read_crl

NS_PER_S = 1_000_000_000
INTERVAL_S = 1.0

Stamp = tuple[int, int, int] | None  # (inode, size, mtime_ns) of the list, None when it is absent


@dataclass(frozen=True)
class Reload:
    """One change of the revocation list: taken (``accepted``, ``revoked`` certificates listed now)
    or refused (``reason``; the list in force, listing ``revoked``, stays)."""

    path: Path
    accepted: bool
    revoked: int
    reason: str = ""
    trust: Trust | None = field(default=None, repr=False)  # the trust with the new list, when accepted

    def describe(self) -> str:
        """One log line."""
        if self.accepted:
            return f"reloaded {self.path}: {self.revoked} certificate(s) revoked"
        return f"refused the new {self.path} ({self.reason}); kept the previous list ({self.revoked} revoked)"


def _stamp(path: Path) -> Stamp:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


def downgrade(current: Trust, crl: RevocationList | None) -> str | None:
    """Why ``crl`` (None: no list) may not replace ``current``'s list, or None when it may: a list
    only grows (``v2i pki revoke`` adds), so one that leaves out a revoked certificate is a downgrade."""
    if not current.revoked:
        return None
    if crl is None:
        return "the revocation list was removed"
    dropped = len(current.revoked - crl.revoked)
    if dropped:
        return (f"it leaves out {dropped} certificate(s) the list in force revokes (an older list put back?); "
                "a restart takes an un-revocation")
    return None


class TrustReload:
    """The trust of ``directory`` (loaded here: PkiError on a bad file) and its later revocation
    lists; one owner thread."""

    def __init__(self, directory: str | Path, interval_s: float = INTERVAL_S) -> None:
        self.directory = Path(directory)
        self.path = self.directory / CRL_FILE
        self._interval_ns = round(interval_s * NS_PER_S)
        self._next_ns: int | None = None
        self._stamp = _stamp(self.path)  # before the load: a list written during it is seen at the first poll
        self.trust = load_trust(self.directory)

    def poll(self, now_ns: int) -> Reload | None:
        """At most once per interval: the outcome when the list changed since the last look, else None."""
        if self._next_ns is not None and now_ns < self._next_ns:
            return None
        self._next_ns = now_ns + self._interval_ns
        stamp = _stamp(self.path)
        if stamp == self._stamp:
            return None
        self._stamp = stamp
        return self._reload()

    def _reload(self) -> Reload:
        current = self.trust
        try:
            crl = read_crl(self.directory, current.ca, current.ca_key)
        except PkiError as exc:
            reason = " ".join(str(exc).removeprefix(f"{self.path}: ").split())
            return Reload(self.path, False, len(current.revoked), reason)
        reason = downgrade(current, crl)
        if reason is not None:
            return Reload(self.path, False, len(current.revoked), reason)
        self.trust = dataclasses.replace(current, revoked=crl.revoked if crl else frozenset())
        return Reload(self.path, True, len(self.trust.revoked), trust=self.trust)
