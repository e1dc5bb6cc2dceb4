"""A whole site's signing material in one call: the CA, one certificate per RSU, vehicle and operator.

Subjects are the ids the services already carry: an RSU's certificate subject is its ``rsu_id``
(publishing on ``v2x/rsu/{rsu_id}/**``), a vehicle's its ``vehicle_id`` (``v2x/obu/{vehicle_id}/**``),
an operator's its name (``v2x/link/*/control``): :func:`certificates.default_keys`.

- :func:`write_site` fills a PKI directory (``v2i pki site``, the live demo): the CA if absent, then
  every subject that has no certificate yet; existing ones are kept, so it is idempotent and a
  harness may add subjects or revoke some before the services load the directory.
- :func:`memory_site` gives the same material without keeping files (the offline evaluator, tests).

Times are arguments; nothing here reads a clock.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable
from pathlib import Path

from v2i.security.pki import CA_NAME, Identity, Pki, Trust, load_signer, load_trust

DEFAULT_DAYS = 30.0


def _roles(rsu_ids: Iterable[str], vehicle_ids: Iterable[str], operators: Iterable[str]) -> dict[str, str]:
    """subject -> role, in order; ValueError when one id is asked for under two roles."""
    roles: dict[str, str] = {}
    for role, subjects in (("rsu", rsu_ids), ("vehicle", vehicle_ids), ("operator", operators)):
        for subject in subjects:
            if roles.setdefault(subject, role) != role:
                raise ValueError(f"subject {subject!r} asked for as both {roles[subject]} and {role}")
    return roles


def write_site(directory: str | Path, now_ns: int, rsu_ids: Iterable[str] = (), vehicle_ids: Iterable[str] = (),
               operators: Iterable[str] = ("operator",), days: float = DEFAULT_DAYS) -> Path:
    """The site PKI in ``directory``: the CA (``Pki.init``'s ten years) if absent, then a key and
    certificate valid ``days`` from ``now_ns`` for every subject that has none. Returns the directory;
    PkiError on bad files."""
    directory = Path(directory)
    roles = _roles(rsu_ids, vehicle_ids, operators)
    if (directory / f"{CA_NAME}.cert").exists():
        pki = Pki.load(directory)
    else:
        pki = Pki.init(directory, now_ns)
    for subject, role in roles.items():
        if not (directory / f"{subject}.cert").exists():
            pki.issue(subject, role, now_ns, days=days)
    return directory


def memory_site(now_ns: int, rsu_ids: Iterable[str] = (), vehicle_ids: Iterable[str] = (),
                operators: Iterable[str] = ("operator",)) -> tuple[Trust, dict[str, Identity]]:
    """The trust and every subject's signing identity of a fresh site, no files kept."""
    roles = _roles(rsu_ids, vehicle_ids, operators)
    with tempfile.TemporaryDirectory(prefix="v2i-pki-") as tmp:
        write_site(tmp, now_ns, *(list(ids) for ids in _split(roles)))
        return load_trust(tmp), {subject: load_signer(tmp, subject) for subject in roles}


def _split(roles: dict[str, str]) -> tuple[list[str], list[str], list[str]]:
    return tuple([s for s, r in roles.items() if r == role] for role in ("rsu", "vehicle", "operator"))
