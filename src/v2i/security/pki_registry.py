"""The RSUs a site PKI directory certifies: which RSU ids its certificates let a sender publish
as, and what an OBU says at start about those it does not register.

An RSU certificate (role ``rsu``, :mod:`.site`) names the key expressions its holder may publish
on; its subject is usually the RSU id, but what counts is the keys: the victim's former key of
``v2i pki attacker`` (subject ``rsu1-revoked``) covers ``v2x/rsu/rsu1/**``. So the id a
certificate certifies is read from its keys, and is kept only when the certificate covers that
RSU's object lists (``v2x/rsu/{id}/objects``). Certificates the directory's revocation list
revokes, or that another CA issued, certify nothing.

Times are not read here: a certificate outside its validity still names its RSU (the RSU itself
warns at start when its own certificate is not valid: ``pki.start_warnings``).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from schemas import keys
from schemas.keys import ID_PATTERN
from v2i.security import certificates as certs
from v2i.security.certificates import Certificate
from v2i.security.pki import CA_NAME, load_trust, read_cert


def certified_rsu_ids(cert: Certificate) -> tuple[str, ...]:
    """The RSU ids an RSU-role ``cert`` lets its holder publish object lists as, in the order
    its keys name them (``v2x/rsu/{id}/**`` or ``v2x/rsu/{id}/objects``; a wildcard id names
    none); () for any other role."""
    if cert.role != "rsu":
        return ()
    ids = []
    for pattern in cert.keys:
        chunks = pattern.split("/")
        if len(chunks) < 3 or chunks[:2] != ["v2x", "rsu"] or not ID_PATTERN.fullmatch(chunks[2]):
            continue
        if chunks[2] not in ids and certs.covers(cert.keys, keys.rsu_objects(chunks[2])):
            ids.append(chunks[2])
    return tuple(ids)


def certified_rsus(directory: str | Path) -> dict[str, Path]:
    """RSU id -> the certificate file of ``directory`` that certifies it (the first by file name),
    for every certificate the directory's CA issued and its revocation list does not revoke;
    sorted by id. PkiError naming the file when one cannot be read."""
    directory = Path(directory)
    trust = load_trust(directory)
    found: dict[str, Path] = {}
    for path in sorted(directory.glob("*.cert")):
        if path.name == f"{CA_NAME}.cert":
            continue
        cert = read_cert(path)
        if cert.issuer != trust.ca.digest or cert.digest in trust.revoked:
            continue
        for rsu_id in certified_rsu_ids(cert):
            found.setdefault(rsu_id, path)
    return dict(sorted(found.items()))


def unregistered_warnings(certified: dict[str, Path], registered: Iterable[str]) -> list[str]:
    """One line per RSU that ``certified`` (``certified_rsus``) names and ``registered`` leaves
    out: its lists get neither the intake priority nor the reserved slot of a registered RSU, and
    its objects are bounded around the vehicle rather than around the RSU."""
    registered = list(registered)
    listed = ", ".join(registered) or "none"
    return [f"{path}: RSU {rsu_id!r} holds a site certificate but is not registered (registered: {listed}): "
            "it gets no intake priority and no reserved slot; register it with --known-rsus (or a site that "
            "lists it)" for rsu_id, path in certified.items() if rsu_id not in registered]
